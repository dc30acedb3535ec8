"""Run every benchmark suite and write its figures into one folder (``make bench``).

Each ``benchmarks/bm_*.py`` module that defines ``run_suite(out, preset, log) -> dict``
(with a ``markdown`` entry) is a suite. Each suite is a unit (``validation.units``),
``OUT/units/<suite>/``: it runs into a temporary folder that moves into place when the suite
has finished, so that a kill loses only the suite in progress and the same command again
runs only the unfinished suites. A unit records the preset, the code's commit, the CPU
model and core count, the Mitsuba variant and the library versions: one made otherwise
exits 2 naming what differs, so figures of other code or another machine are never mixed
in (``--overwrite`` runs this call's suites again). When every suite has run, their files
are copied to OUT's top level, then ``machine.json`` and ``README.md`` are written, each
atomically, so a reader never sees a half-written report::

    python -m benchmarks.run_all --out bench-out [--quick] [--only raster]
                                 [--overwrite] [--results results]

``--results DIR`` also writes the rasterizer's figures as ``DIR/raster_vs_mitsuba.json``,
the schema ``make results`` renders into RESULTS.md (``scripts/results.py``).
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import os
import pkgutil
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.io.atomic import atomic_path, write_json, write_text
from mi_shadowgs.io.provenance import (
    Provenance,
    device_name,
    git_commit,
    uncommitted_digest,
)
from validation import claim_out
from validation.units import UNITS, open_unit, run_unit, settings_of, staged_folder

STUDY = "benchmarks.run_all"
SUITE_FILES = "files"  # a suite unit's sub-folder holding the files the suite wrote


def discover_suites() -> dict[str, object]:
    """name (module name without ``bm_``) -> module, for every bm_* module with run_suite."""
    import benchmarks

    suites = {}
    for info in sorted(pkgutil.iter_modules(benchmarks.__path__), key=lambda i: i.name):
        if info.name.startswith("bm_"):
            module = importlib.import_module(f"benchmarks.{info.name}")
            if hasattr(module, "run_suite"):
                suites[info.name[3:]] = module
    return suites


def machine_info() -> dict:
    """What a reader needs to compare figures: CPU, cores, load, library versions, date."""
    import drjit
    import mitsuba

    model = platform.processor() or "unknown"
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                model = line.split(":", 1)[1].strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return {
        "date_utc": _now(),
        "cpu_model": model,
        "cpu_count": os.cpu_count(),
        "loadavg_start": list(os.getloadavg()),
        "python": platform.python_version(),
        "mitsuba": mitsuba.__version__,
        "drjit": drjit.__version__,
        "variant": mitsuba.variant(),
        "command": " ".join([Path(sys.executable).name, "-m", "benchmarks.run_all",
                             *sys.argv[1:]]),
    }


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def suite_settings(info: dict, preset: str) -> dict:
    """What a suite's figures depend on besides the suite: the preset, the code (its commit
    and any uncommitted changes), the machine (its GPU too: the CUDA suite runs where one
    exists) and the libraries."""
    from mi_shadowgs import backend

    gpu = device_name("cuda_ad_rgb") if backend.variant_available("cuda_ad_rgb") else None
    return settings_of(preset=preset, commit=git_commit(), changes=uncommitted_digest(),
                       gpu=gpu,
                       **{k: info[k] for k in ("cpu_model", "cpu_count", "variant", "python",
                                               "mitsuba", "drjit")})


def suite_provenance(name: str, settings: dict) -> Provenance:
    return Provenance(settings={**settings, "suite": name})


def run_suite_unit(out: Path, name: str, module, settings: dict, overwrite: bool) -> dict:
    """Suite ``name``'s unit: {"markdown", "wall_s", "date_utc"}, the suite run (into the
    unit's ``SUITE_FILES``) unless it finished earlier with the same settings."""
    def work(unit) -> dict:
        t0 = time.perf_counter()
        date = _now()
        with staged_folder(unit, SUITE_FILES) as tmp:
            summary = module.run_suite(tmp, preset=settings["preset"],
                                       log=lambda msg: print(msg, flush=True))
        return {"markdown": summary.get("markdown", f"## {name}\n(no summary)"),
                "wall_s": time.perf_counter() - t0, "date_utc": date}

    return run_unit(out, name, STUDY, suite_provenance(name, settings), work,
                    overwrite=overwrite)


def publish(out: Path, suites: list[str]) -> None:
    """Copy the files of ``suites``' units to ``out``'s top level, where the suites wrote
    them before they were units, each atomically. A file that another suite's unit holds and
    these do not is removed there: an earlier call's, which this call's report does not
    cover."""
    def files(name: str) -> dict[str, Path]:
        root = out / UNITS / name / SUITE_FILES
        return {p.relative_to(root).as_posix(): p for p in sorted(root.rglob("*"))
                if p.is_file()}

    ours = {rel: path for name in suites for rel, path in files(name).items()}
    for rel, path in ours.items():
        with atomic_path(out / rel) as tmp:
            shutil.copyfile(path, tmp)
    others = [p.name for p in (out / UNITS).iterdir() if p.is_dir() and p.name not in suites] \
        if (out / UNITS).is_dir() else []
    for rel in {rel for name in others for rel in files(name)} - set(ours):
        (out / rel).unlink(missing_ok=True)


def _suite_times(suites: dict) -> str:
    return ", ".join(f"{name} {s['wall_s'] / 60:.1f} min on {s['date_utc']}"
                     for name, s in suites.items())


def write_raster_result(out: Path, results: Path, info: dict) -> None:
    """The rasterizer suite's figures (``OUT/raster.json``) as a result file."""
    import json

    from scripts.results import raster_result, write_result

    summary = json.loads((out / "raster.json").read_text(encoding="utf-8"))
    path = results / "raster_vs_mitsuba.json"
    write_result(path, raster_result(summary, info, info["command"]))
    print(f"benchmarks: wrote {path}")


def main(argv=None) -> int:
    suites = discover_suites()
    ap = argparse.ArgumentParser(description="Run the mi_shadowgs benchmarks.")
    ap.add_argument("--out", required=True, help="output folder: new or an earlier "
                    "benchmark run's (its finished suites are reused)")
    ap.add_argument("--quick", action="store_true",
                    help="reduced sweep (the cpu-small presets) for a fast check")
    ap.add_argument("--only", action="append", choices=sorted(suites),
                    help="run only this suite (repeatable)")
    ap.add_argument("--overwrite", action="store_true",
                    help="run this call's suites again, also those that finished (with other "
                         "code, on another machine or preset: those exit 2 otherwise)")
    ap.add_argument("--results", default=None, metavar="DIR",
                    help="also write the rasterizer's figures as DIR/raster_vs_mitsuba.json "
                         "(the committed result files: make results renders them)")
    args = ap.parse_args(argv)
    out = claim_out(args.out, STUDY, ("machine.json",))
    preset = "cpu-small" if args.quick else "paper"
    chosen = args.only or sorted(suites)
    info = machine_info()
    info["preset"] = preset
    settings = suite_settings(info, preset)
    print(f"benchmarks: {', '.join(chosen)} ({preset}) on {info['cpu_model']}, "
          f"{info['cpu_count']} cores, load {info['loadavg_start']}", flush=True)
    if not args.overwrite:  # a unit made otherwise exits 2 before any suite runs, not after
        for name in chosen:
            open_unit(out, name, STUDY, suite_provenance(name, settings))
    t0 = time.perf_counter()
    results = {name: run_suite_unit(out, name, suites[name], settings, args.overwrite)
               for name in chosen}
    sections = [r["markdown"] for r in results.values()]
    publish(out, chosen)
    info["loadavg_end"] = list(os.getloadavg())
    # the suites' own seconds: a call that resumes runs only the unfinished ones
    info["wall_s"] = sum(r["wall_s"] for r in results.values())
    info["suites"] = {name: {"wall_s": r["wall_s"], "date_utc": r["date_utc"]}
                      for name, r in results.items()}
    info["commit"] = settings["commit"]
    write_json(out / "machine.json", info)
    header = [
        "# Benchmarks (latest run)", "",
        f"- Command: `{info['command']}`",
        f"- Date: {info['date_utc']}; total {info['wall_s'] / 60:.1f} min "
        f"(the suites: {_suite_times(info['suites'])})",
        f"- Machine: {info['cpu_model']}, {info['cpu_count']} cores; load average "
        f"{info['loadavg_start'][0]:.2f} at start, {info['loadavg_end'][0]:.2f} at end "
        "(above ~0.5 means other processes shared the cores)",
        f"- Mitsuba {info['mitsuba']}, Dr.Jit {info['drjit']}, {info['variant']}, "
        f"Python {info['python']}; code {info['commit']}", "",
    ]
    write_text(out / "README.md", "\n".join(header + sections) + "\n")
    if args.results and (out / "raster.json").is_file():
        write_raster_result(out, Path(args.results), info)
    print("\n".join(sections))
    print(f"benchmarks: wrote {args.out} in {(time.perf_counter() - t0) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
