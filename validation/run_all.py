"""Run every registered validation and gather their reports in one folder (``make validate``).

A validation is a function ``fn(out_dir: Path, quick: bool, opts: dict) -> dict`` that
writes its files into ``out_dir`` and returns a summary with a ``markdown`` entry. To add
one, import it here and give it a name in ``VALIDATIONS``::

    python -m validation.run_all --out validation-out [--quick] [--only visibility]
                                 [--scene NAME ...] [--lights PAIR ...] [--threads N]
                                 [--overwrite] [--address ADDR]

The pipeline table (every scene under both light pairs, ``validation.pipeline``) takes hours,
so each validation writes into ``OUT/<name>/`` in place and the table resumes per scene and
pair: the same command again after a kill redoes only the unfinished runs. ``--scene`` and
``--lights`` choose a subset of the table (the tables gather every finished row under
``OUT/pipeline``). ``report_pages`` then checks each table run's ``report.html`` in headless
Chromium (``validation.report_page``). ``README.md`` and ``run.json`` are written last.

The studies after the table keep their work in units (``validation.units``): a unit made
from other inputs or settings makes its study exit 2, reported as failed, and
``--overwrite`` makes those studies' units again. The table's finished rows always stand as
recorded (each row names its commit): remove ``OUT/pipeline/<row>`` to run one again.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.io.atomic import write_json, write_text
from validation import fail


def _overwrite(opts: dict | None) -> bool:
    """Whether the studies make their units again (``--overwrite``)."""
    return bool(opts and opts.get("overwrite"))


def _table_models(out_dir: Path) -> tuple[list[Path], list[Path]]:
    """The stage-1 models the pipeline validation (run before) trained, and their datasets."""
    models = sorted((out_dir.parent / "pipeline").glob("*/run/geometry/model.ply"))
    return models, [m.parents[2] / "data" for m in models]


def _visibility(out_dir: Path, quick: bool, opts: dict | None = None) -> dict:
    """Table 2 on ground-truth surfels, with the paper's maps, plus rows for the table's
    stage-1 models when there are any."""
    from . import visibility

    models, datas = _table_models(out_dir)
    return visibility.run(out_dir, quick=quick, model=models, data=datas,
                          overwrite=_overwrite(opts))


def _visibility_runs(out_dir: Path, quick: bool, opts: dict | None = None) -> dict:
    """The table's stage-1 models with the maps and receivers their runs use (the preset
    the rows were made at), each split by factor."""
    from . import pipeline, visibility

    models, datas = _table_models(out_dir)
    if not models:
        return {"markdown": "## visibility_runs\n\nNo stage-1 models: run the pipeline first."}
    row = models[0].parents[2] / "row.json"
    preset = pipeline.row_preset(json.loads(row.read_text())) if row.is_file() else \
        pipeline.dataset_preset(datas[0] / "dataset.json")
    return visibility.run(out_dir, quick=quick, model=models, data=datas, factors=True,
                          models_only=True, preset=preset, overwrite=_overwrite(opts))


def _pipeline(out_dir: Path, quick: bool, opts: dict | None = None) -> dict:
    from . import pipeline

    opts = opts or {}
    return pipeline.run(out_dir, quick=quick, scenes=opts.get("scenes"),
                        lights=opts.get("lights"),
                        command=opts.get("command", "python -m validation.pipeline"),
                        address=opts.get("address"), threads=opts.get("threads"))


def _metric_floor(out_dir: Path, quick: bool, opts: dict | None = None) -> dict:
    """The pipeline's datasets, each scene box-filtered against its point-sampled truth:
    what the table's albedo and shadow figures can tell apart at the datasets' size; and
    the method itself on each scene's exact geometry (the table's cpu-small settings)."""
    from . import metric_floor

    datas = sorted(p.parent for p in (out_dir.parent / "pipeline").glob("*/data/dataset.json"))
    return metric_floor.run(out_dir, datas, progress=False,
                            command=[opts.get("command", "")] if opts else None,
                            exact="cpu-small", overwrite=_overwrite(opts))


def _lowpass_drift(out_dir: Path, quick: bool, opts: dict | None = None) -> dict:
    from . import lowpass_drift

    return lowpass_drift.run(out_dir, quick=quick, overwrite=_overwrite(opts))


def _report_pages(out_dir: Path, quick: bool, opts: dict | None = None) -> dict:
    """Every table run's report in headless Chromium: images load, the page fits 1400 px."""
    from . import report_page

    reports = sorted((out_dir.parent / "pipeline").glob("*/run/report.html"))
    return report_page.run(out_dir, reports)


# name -> fn(out_dir, quick, opts) -> {"markdown": ...}; each writes under out_dir/<name>/.
VALIDATIONS: dict[str, Callable[[Path, bool, dict], dict]] = {
    "pipeline": _pipeline,  # stages 1-5 per scene and light pair: Tables 1 and 3
    "visibility": _visibility,  # after the pipeline: its stage-1 models get Table 2 rows
    "visibility_runs": _visibility_runs,  # the same models with their runs' maps, split
    "metric_floor": _metric_floor,  # after the pipeline: its datasets' exact scenes scored
    "lowpass_drift": _lowpass_drift,  # does stage 1 keep a correct surface in place?
    "report_pages": _report_pages,  # after the pipeline: its reports in headless Chromium
}
RUN_JSON = "run.json"


def _check_out(out: Path) -> None:
    """OUT is new, empty, or an earlier run_all output (its run.json or one of its
    validation folders): never someone else's folder."""
    if not out.exists():
        return
    if not out.is_dir():
        fail(f"--out {out}: exists and is not a folder")
    entries = {p.name for p in out.iterdir()}
    ours = set(VALIDATIONS) | {RUN_JSON, "README.md"}
    if entries and not entries & ours:
        fail(f"--out {out}: holds files that validation.run_all did not write "
             f"(e.g. {sorted(entries)[0]}); choose a new folder")


def write_pipeline_result(table: Path, results: Path, command: str, date: str) -> None:
    """The pipeline table's rows (``table/pipeline.json``) as one result file per preset."""
    import platform

    from scripts.results import pipeline_result, write_result

    rows = json.loads((table / "pipeline.json").read_text(encoding="utf-8"))
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
    by_preset: dict[str, list[dict]] = {}
    for row in rows:
        by_preset.setdefault(row.get("preset", "cpu-small"), []).append(row)
    for preset, preset_rows in sorted(by_preset.items()):
        path = results / f"pipeline_{preset.replace('-', '_')}.json"
        write_result(path, pipeline_result(preset_rows, command, machine, date[:10]))
        print(f"validation: wrote {path}", flush=True)


def main(argv=None) -> int:
    from . import pipeline

    ap = argparse.ArgumentParser(description="Run the mi_shadowgs validations.")
    ap.add_argument("--out", required=True, help="output folder (resumed when it is ours)")
    ap.add_argument("--quick", action="store_true", help="small smoke runs")
    ap.add_argument("--only", action="append", choices=sorted(VALIDATIONS),
                    help="run only this validation (repeatable)")
    ap.add_argument("--scene", action="append", choices=sorted(pipeline.SCENES),
                    help="pipeline table: only this scene (repeatable)")
    ap.add_argument("--lights", action="append", choices=sorted(pipeline.LIGHT_PAIRS),
                    help="pipeline table: only this light pair (repeatable)")
    ap.add_argument("--threads", type=int, default=None,
                    help="Dr.Jit threads (with --address: each table row's CPUs, default 1)")
    ap.add_argument("--address", default=None,
                    help="run the pipeline table's rows as Ray tasks on this cluster, or "
                         "'local' (validation.pipeline --address)")
    ap.add_argument("--overwrite", action="store_true",
                    help="make the studies' units again where they were made from other "
                         "inputs or settings (the table's finished rows stand)")
    ap.add_argument("--results", default=None, metavar="DIR",
                    help="also write the pipeline table as DIR/pipeline_<preset>.json (the "
                         "committed result files: make results renders them)")
    args = ap.parse_args(argv)
    if args.threads:
        import drjit as dr

        dr.set_thread_count(args.threads)
    chosen = args.only or list(VALIDATIONS)
    out = Path(args.out)
    _check_out(out)
    command = " ".join(["python", "-m", "validation.run_all", *(argv or sys.argv[1:])])
    opts = {"scenes": args.scene, "lights": args.lights, "command": command,
            "overwrite": args.overwrite, "address": args.address, "threads": args.threads}
    t0 = time.perf_counter()
    load0 = os.getloadavg()
    sections, failed = [], []
    out.mkdir(parents=True, exist_ok=True)
    for name in chosen:
        print(f"validation: {name}", flush=True)
        t = time.perf_counter()
        try:
            summary = VALIDATIONS[name](out / name, args.quick, opts)
            sections.append(summary.get("markdown", f"## {name}\n(no summary)"))
        except (Exception, SystemExit) as exc:  # one broken stage must not hide the others
            # A study that refuses its folder (exit 2, e.g. a unit made with other settings)
            # has said why on stderr; the others still run.
            why = f"exit {exc.code} (its message is above)" if isinstance(exc, SystemExit) \
                else f"{type(exc).__name__}: {exc}"
            failed.append(name)
            sections.append(f"## {name}\nFAILED: {why}")
            print(f"validation {name} FAILED: {why}", file=sys.stderr, flush=True)
        print(f"validation: {name} took {time.perf_counter() - t:.0f} s", flush=True)
    info = {"date_utc": datetime.datetime.now(datetime.timezone.utc)
            .strftime("%Y-%m-%d %H:%M UTC"), "cpu_count": os.cpu_count(),
            "loadavg_start": list(load0), "loadavg_end": list(os.getloadavg()),
            "wall_s": time.perf_counter() - t0, "quick": args.quick,
            "command": command, "failed": failed}
    write_json(out / RUN_JSON, info)
    if args.results and (out / "pipeline" / "pipeline.json").is_file():
        write_pipeline_result(out / "pipeline", Path(args.results), command, info["date_utc"])
    header = ["# Validation (latest run)", "", f"- Command: `{info['command']}`",
              f"- Date: {info['date_utc']}; {info['wall_s'] / 60:.1f} min; "
              f"{info['cpu_count']} cores, load {load0[0]:.2f} at start", ""]
    write_text(out / "README.md", "\n".join(header + sections) + "\n")
    print("\n\n".join(sections))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
