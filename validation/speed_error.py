"""Speed against error for the whole method: albedo PSNR, shadow IoU and
relight PSNR against training wall time, over a small sweep around ``cpu-small``::

    python -m validation.speed_error --out OUT [--base TABLE] [--scene default --scene bunny]
                                     [--point res64 ...] [--threads 1] [--figures docs/figures]
                                     [--wait] [--plots-only] [--attach RUN ...]

Each point changes one setting of ``cpu-small`` (``POINTS``): the dataset's resolution (64,
192; 128 is cpu-small), stage 1's steps (its whole schedule scaled) or stage 4's steps. The
cpu-small point itself is read from a finished ``validation.pipeline`` run (``--base``:
``TABLE/<scene>-tuned/{data,run,row.json}``; without it, it is made under ``OUT/base``). Points
at 128 px train on that run's dataset (read only), and the stage-4 points start from a copy
of its stage 1 and 2 (same dataset, same settings: the provenance check accepts them), so
they cost one stage-4 fit; their stage 1 and 2 times are the base run's, said in the CSV.

Wall time is the method's training time: stage 1 + stage 2 + stages 3-4 (the fit), from the
runs' own stage timers; scoring the test views (stage 5) is not counted. Every point lives in
``OUT/<scene>/<point>/`` and is skipped once its ``point.json`` exists; a killed sweep resumes
(the stages continue from their checkpoints). ``OUT/speed_error.csv`` (with each point's
single-metric Pareto fronts, and whether it is on the joint front of time and all three
metrics) and one PNG per scene (``speed_error_<scene>.png``) are rewritten from every
finished point after each one;
``--attach RUN`` puts the plots into a run's ``speed_error/``, where its report shows them
with the sweep they came from (``speed_error/source.json``); it never writes over a file there
that the run's manifest does not list.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs import presets as run_presets
from validation import claim_out, fail

from . import pipeline as vpipe

SCENES = ("default", "bunny")
CPU_SMALL = "cpu-small"  # the base point's label
PRESET = CPU_SMALL  # the preset every point starts from (tests use test-tiny)
# point -> what it changes from cpu-small (one setting each): "resolution" of the dataset,
# "stage1" factor on stage 1's schedule, "stage4" iterations of the stage-4 fit.
POINTS = {
    "res64": {"resolution": 64},
    "s4_300": {"stage4": 300},
    "s1x0.5": {"stage1": 0.5},
    "s4_1200": {"stage4": 1200},
    "res192": {"resolution": 192},
    "s1x1.5": {"stage1": 1.5},  # not in the default sweep: ~1.5x cpu-small's cost
}
# Cheapest first, so that a sweep cut short still has points on both sides of cpu-small.
DEFAULT_POINTS = ("res64", "s4_300", "s1x0.5", "s4_1200", "res192")
METRICS = (("albedo_psnr", "albedo PSNR (dB)"), ("shadow_iou", "shadow IoU"),
           ("relight_psnr", "relight PSNR (dB)"))
STAGE_KEYS = vpipe.STAGE_KEYS
CSV_COLUMNS = ("scene", "point", "changed", "resolution", "stage1_iterations",
               "stage4_iterations", "wall_s", "stage1_s", "stage2_s", "stage4_s",
               "albedo_psnr", "shadow_iou", "relight_psnr", "light_cosine", "pareto",
               "pareto_joint", "source", "load")


# -- settings ---------------------------------------------------------------------------------
def scaled_geometry(factor: float):
    """cpu-small's stage-1 config with its step count and whole schedule (SH degree steps,
    regulariser starts, densification window and interval, opacity resets, previews and
    checkpoints) scaled by ``factor``, so a shorter run does the same things in fewer steps."""

    c = run_presets.geometry_config(PRESET)

    def s(n: int) -> int:
        return max(1, int(round(n * factor)))

    d = c.densify
    densify = dataclasses.replace(d, start=s(d.start), stop=s(d.stop), interval=s(d.interval),
                                  opacity_reset_interval=s(d.opacity_reset_interval)
                                  if d.opacity_reset_interval else 0)
    return dataclasses.replace(
        c, iterations=s(c.iterations), sh_degree_interval=s(c.sh_degree_interval),
        normal_from=s(c.normal_from), dist_from=s(c.dist_from), densify=densify,
        lr_position_max_steps=s(c.lr_position_max_steps) if c.lr_position_max_steps else None,
        preview_every=s(c.preview_every), checkpoint_every=s(c.checkpoint_every))


def register_stage1_preset(factor: float) -> str:
    """A preset named after the point: cpu-small's tree with stage 1 scaled."""
    from mi_shadowgs import presets

    name = f"{PRESET}-s1x{factor:g}"
    presets.GENERATE.setdefault(name, presets.GENERATE[PRESET])
    presets.PRESETS[name] = dataclasses.replace(presets.PRESETS[PRESET], preset=name,
                                                geometry=scaled_geometry(factor))
    return name


# -- the base (cpu-small) point ------------------------------------------------------------------
def base_folder(base: Path, scene: str) -> Path:
    return base / f"{scene}-tuned"


def ensure_base(base: Path, scene: str, make: bool) -> dict | None:
    """The cpu-small row of ``scene`` (``row.json``); made with ``validation.pipeline`` when
    ``make`` (the sweep's own base), else None until that run has finished."""
    row = base_folder(base, scene) / "row.json"
    if row.is_file():
        return json.loads(row.read_text())
    if not make:
        return None
    avail = vpipe.available_scenes()
    if scene not in avail:
        raise FileNotFoundError(f"scene {scene!r} needs its mesh under "
                                f"{vpipe.SHARED_DATA / 'meshes'}")
    # the sweep reads only the full model's figures: Table 3's ablations would cost two more
    # stage-4 fits (not in the time axis, but in the sweep's wall time)
    return vpipe.run_scene(scene, avail[scene], base, "tuned", ablations=False)


def _base_metrics(row: dict) -> dict:
    full = row["variants"]["full"]
    return {k: full.get(k) for k in ("albedo_psnr", "shadow_iou", "relight_psnr",
                                     "light_cosine")}


# -- one point -------------------------------------------------------------------------------------
def ready(point: str, base: Path, scene: str, base_row: dict | None) -> bool:
    """Whether a point can start: the resolution points make their own dataset, the other
    stage-1 points need the base run's dataset, the stage-4 points its stages 1 and 2."""
    spec = POINTS[point]
    if "resolution" in spec:
        return True
    if "stage4" in spec:
        return base_row is not None
    return (base_folder(base, scene) / "data" / "dataset.json").is_file()


def run_point(scene: str, point: str, out: Path, base: Path, base_row: dict | None) -> dict:
    """Run one sweep point into ``out/<scene>/<point>/`` and write its ``point.json``."""
    from mi_shadowgs.io.atomic import write_json
    from mi_shadowgs.pipeline import run_pipeline
    from mi_shadowgs.presets import build, get_config

    spec = POINTS[point]
    folder = out / scene / point
    run = folder / "run"
    folder.mkdir(parents=True, exist_ok=True)
    config = get_config(PRESET)
    reused = {}
    if "resolution" in spec:
        data = vpipe.make_dataset(scene, vpipe.available_scenes().get(scene), folder, "tuned",
                                  "sky", spec["resolution"], PRESET)
    else:
        data = base_folder(base, scene) / "data"  # read only
    if "stage1" in spec:
        config = get_config(register_stage1_preset(spec["stage1"]))
    if "stage4" in spec:
        config = build(config.preset, {"material": {"iterations": spec["stage4"]}})
        src = base_folder(base, scene) / "run"
        for part in ("geometry", "segmentation"):  # same dataset and settings: reused as is
            if not (run / part).exists():
                shutil.copytree(src / part, run / part)
        reused = {k: v for k, v in vpipe.stage_seconds(base_row.get("stage_s", {}), src).items()
                  if k in ("stage1_s", "stage2_s")}
    t0, c0 = time.perf_counter(), time.process_time()
    summary = run_pipeline(data, run, config, progress=True)
    secs = vpipe.stage_seconds({s["name"]: s.get("seconds") for s in summary.get("stages", [])})
    secs.update(reused)
    metrics = json.loads((run / "material" / "full" / "metrics.json").read_text())
    row = {"scene": scene, "point": point, "changed": spec, "dataset": str(data),
           "run": str(run), **secs, "run_s": time.perf_counter() - t0,
           # CPU seconds of the process (stages run here and scoring): less load-dependent
           # than wall time on a shared machine, but not comparable with the base's wall
           "run_cpu_s": time.process_time() - c0,
           "metrics": {k: metrics.get(k) for k in ("albedo_psnr", "shadow_iou",
                                                   "relight_psnr", "light_cosine")},
           "source": ("stages 1-2 reused from " + str(base_folder(base, scene) / "run"))
           if reused else "run", "load": os.getloadavg()[0]}
    write_json(folder / "point.json", row)
    return row


# -- the table and the plots ---------------------------------------------------------------------
def _iterations(spec: dict) -> tuple[int, int]:
    from mi_shadowgs.presets import material_config as get_config

    s1 = run_presets.geometry_config(PRESET).iterations
    s4 = get_config(PRESET).iterations
    return (int(round(s1 * spec.get("stage1", 1.0))), int(spec.get("stage4", s4)))


def gather(out: Path, base: Path, scenes: list[str]) -> list[dict]:
    """One row per finished point (and per scene's base), wall time summed over stages."""
    rows = []
    for scene in scenes:
        found = []
        base_row = ensure_base(base, scene, make=False)
        if base_row is not None:
            found.append({"point": CPU_SMALL, "changed": {}, **vpipe.stage_seconds(
                base_row.get("stage_s", {}), base_folder(base, scene) / "run"),
                "metrics": _base_metrics(base_row),
                "source": f"reused: {base_folder(base, scene) / 'row.json'}",
                "load": base_row.get("load_end")})
        for p in sorted((out / scene).glob("*/point.json")):
            found.append(json.loads(p.read_text()))
        for r in found:
            spec = r["changed"]
            s1, s4 = _iterations(spec)
            stages = [r.get(k) for k in STAGE_KEYS]
            wall = float(sum(stages)) if all(v is not None for v in stages) else float("nan")
            rows.append({"scene": scene, "point": r["point"],
                         "changed": ", ".join(f"{k}={v}" for k, v in spec.items()) or "none",
                         "resolution": spec.get("resolution", 128), "stage1_iterations": s1,
                         "stage4_iterations": s4, "wall_s": wall,
                         **{k: r.get(k) for k in STAGE_KEYS}, **r["metrics"],
                         "source": r["source"], "load": r.get("load")})
    for scene in scenes:
        mine = [r for r in rows if r["scene"] == scene]
        fronts = {m: pareto(mine, m) for m, _ in METRICS}
        joint = pareto(mine, tuple(m for m, _ in METRICS))
        for r in mine:
            r["pareto"] = "/".join(m for m, _ in METRICS if r["point"] in fronts[m]) or "-"
            r["pareto_joint"] = r["point"] in joint
    return rows


def pareto(rows: list[dict], metric: str | tuple[str, ...]) -> set[str]:
    """Points that no other point dominates: as fast or faster (wall time) and as good or
    better on ``metric`` (higher; a tuple: on every one of them), better on one."""
    metrics = (metric,) if isinstance(metric, str) else tuple(metric)
    ok = [r for r in rows if np.isfinite(r["wall_s"]) and
          all(r.get(m) is not None for m in metrics)]

    def key(r):
        return (-r["wall_s"], *(r[m] for m in metrics))

    front = set()
    for r in ok:
        kr = key(r)
        if not any(all(a >= b for a, b in zip(key(o), kr, strict=True)) and key(o) != kr
                   for o in ok):
            front.add(r["point"])
    return front


def write_csv(path: Path, rows: list[dict]) -> None:
    from mi_shadowgs.io.atomic import write_text

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    write_text(path, buf.getvalue())


def plot_scene(path: Path, scene: str, rows: list[dict]) -> None:
    """Three panels (albedo PSNR, shadow IoU, relight PSNR against wall time): every point
    labelled, the Pareto front as a step line, cpu-small as a star."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from mi_shadowgs.io.atomic import write_bytes

    fig = Figure(figsize=(12.6, 3.7), dpi=100, layout="constrained")
    axes = fig.subplots(1, len(METRICS))
    for ax, (key, label) in zip(axes, METRICS, strict=True):
        ok = [r for r in rows if np.isfinite(r["wall_s"]) and r.get(key) is not None]
        front = sorted((r for r in ok if r["point"] in pareto(ok, key)),
                       key=lambda r: r["wall_s"])
        if front:
            ax.step([r["wall_s"] / 60 for r in front], [r[key] for r in front], where="post",
                    color="C1", lw=1.2, marker="o", ms=12, mfc="none",
                    label="Pareto front")
        for r in ok:
            base = r["point"] == CPU_SMALL
            ax.plot(r["wall_s"] / 60, r[key], marker="*" if base else "o",
                    ms=14 if base else 6, color="C3" if base else "C0", ls="none",
                    label="cpu-small" if base else None)
            ax.annotate(r["point"], (r["wall_s"] / 60, r[key]), fontsize=7.5,
                        xytext=(4, 4), textcoords="offset points")
        ax.set_xlabel("training wall time (min; stages 1-4)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if ok:
            ax.legend(fontsize=7.5, loc="lower right")
    joint = sorted(r["point"] for r in rows if r.get("pareto_joint"))  # marked by gather
    fig.suptitle(f"Speed against error: {scene} (one setting changed from cpu-small); on the "
                 f"joint front of time and all three metrics: {', '.join(joint) or 'none'}")
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
    write_bytes(path, buf.getvalue())


def markdown(rows: list[dict], command: str) -> str:
    lines = ["| scene | point | changed | wall min | albedo PSNR | shadow IoU | relight PSNR "
             "| Pareto on (one metric) | on the joint front | source |",
             "|---|---|---|---|---|---|---|---|---|---|"]

    def f(v, fmt):
        return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else \
            format(v, fmt)

    for r in rows:
        lines.append(f"| {r['scene']} | {r['point']} | {r['changed']} | "
                     f"{f(r['wall_s'] / 60, '.1f')} | {f(r.get('albedo_psnr'), '.2f')} | "
                     f"{f(r.get('shadow_iou'), '.3f')} | {f(r.get('relight_psnr'), '.2f')} | "
                     f"{r['pareto']} | {'yes' if r.get('pareto_joint') else 'no'} | "
                     f"{r['source']} |")
    return f"`{command}`\n\n" + "\n".join(lines) + "\n"


def write_outputs(out: Path, base: Path, scenes: list[str], figures: Path | None,
                  command: str) -> list[dict]:
    """The CSV, the table and the plots of every scene with finished points (not only
    ``scenes``: a call for one scene keeps the other's rows)."""
    from mi_shadowgs.io.atomic import write_text

    scenes = [s for s in SCENES if s in scenes or (out / s).is_dir()]
    rows = gather(out, base, scenes)
    write_csv(out / "speed_error.csv", rows)
    write_text(out / "speed_error.md", markdown(rows, command))
    for scene in scenes:
        mine = [r for r in rows if r["scene"] == scene]
        if mine:
            plot_scene(out / f"speed_error_{scene}.png", scene, mine)
            if figures is not None:
                figures.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(out / f"speed_error_{scene}.png",
                                figures / f"speed_error_{scene}.png")
    return rows


def sweep(out: Path, base: Path | None, scenes: list[str], points: list[str],
          figures: Path | None, command: str, wait: bool) -> list[dict]:
    """Every point of every scene not yet finished, the first ready one in ``points`` order
    each time (so a base run that finishes meanwhile lets its cheap points go first); with
    ``wait``, points whose base run is not finished yet are retried every minute."""
    own_base = base is None
    base = out / "base" if own_base else base
    order = [(s, p) for p in points for s in scenes]
    while True:
        pending, ran = [], False
        for scene, point in order:
            if (out / scene / point / "point.json").is_file():
                continue
            base_row = ensure_base(base, scene, make=own_base)
            if not ready(point, base, scene, base_row):
                pending.append(f"{scene}/{point}")
                continue
            print(f"speed_error: {scene} {point}", flush=True)
            run_point(scene, point, out, base, base_row)
            write_outputs(out, base, scenes, figures, command)
            ran = True
            break
        if ran:
            continue
        if not pending:
            break
        if not wait:
            print("speed_error: base runs not finished, not run: " + ", ".join(pending),
                  flush=True)
            break
        time.sleep(60)
    return write_outputs(out, base, scenes, figures, command)


def attach(run: Path, plots: list[Path], command: str = "") -> Path:
    """Copy ``plots`` into ``RUN/speed_error/`` of a ``mi-shadowgs run`` folder, list them in
    its manifest (so ``--overwrite`` removes them and they are not foreign files), say where
    they came from (``SPEED_ERROR_SOURCE``: the sweep's folder and ``command``; the report
    shows it, since the plots measure the sweep's scenes, not this run), and rewrite its
    report with them. A file of the same name that the run's manifest does not list (one
    put there by hand) is not written over. Returns the report's path."""
    from mi_shadowgs.io.atomic import write_json
    from mi_shadowgs.io.provenance import MANIFEST_NAME, read_manifest
    from mi_shadowgs.io.report import write_report
    from mi_shadowgs.summary import SPEED_ERROR_SOURCE, refresh_speed_error

    run = Path(run)
    manifest = read_manifest(run)
    if manifest is None or manifest.get("command") != "run" or \
            "report.html" not in manifest["files"]:
        fail(f"--attach {run}: not a run folder of `mi-shadowgs run` (no "
             f"{MANIFEST_NAME} listing report.html)")
    if not plots:
        fail(f"--attach {run}: the sweep has no plots yet (no speed_error_<scene>.png)")
    plot_names = [f"speed_error/{p.name}" for p in plots]
    names = plot_names + [SPEED_ERROR_SOURCE]
    for name in names:
        if (run / name).exists() and name not in manifest["files"]:
            fail(f"--attach {run}: {run / name} exists and the run did not write it (its "
                 f"{MANIFEST_NAME} does not list it); move it away first")
    manifest["files"] += [n for n in names if n not in manifest["files"]]
    write_json(run / MANIFEST_NAME, manifest)  # listed before written, as Output does
    (run / "speed_error").mkdir(exist_ok=True)
    for p, name in zip(plots, plot_names, strict=True):
        shutil.copyfile(p, run / name)
    sweep_folder = Path(plots[0]).resolve().parent
    write_json(run / SPEED_ERROR_SOURCE, {
        "sweep": str(sweep_folder), "command": command,
        "date": time.strftime("%Y-%m-%d %H:%M", time.localtime()),
        "plots": [p.name for p in plots]})
    refresh_speed_error(run)
    return write_report(run)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="sweep folder (points, CSV, plots)")
    ap.add_argument("--base", default=None,
                    help="a validation.pipeline output holding <scene>-tuned/row.json (the "
                         "cpu-small point, read only); default: make it under OUT/base")
    ap.add_argument("--scene", action="append", choices=SCENES, help="default: both")
    ap.add_argument("--point", action="append", choices=sorted(POINTS),
                    help=f"default: {', '.join(DEFAULT_POINTS)}")
    ap.add_argument("--threads", type=int, default=None, help="Dr.Jit threads")
    ap.add_argument("--figures", default=None, help="also copy the PNGs into this folder")
    ap.add_argument("--wait", action="store_true",
                    help="wait for --base runs that are not finished yet")
    ap.add_argument("--attach", action="append", default=[], metavar="RUN",
                    help="also put the plots into this run folder's speed_error/ and rewrite "
                         "its report (repeatable)")
    ap.add_argument("--plots-only", action="store_true",
                    help="only rewrite the CSV and plots from the finished points")
    args = ap.parse_args(argv)
    claim_out(args.out, "validation.speed_error", ('speed_error.csv',))
    if args.threads:
        import drjit as dr

        dr.set_thread_count(args.threads)
    out = Path(args.out)
    base = Path(args.base) if args.base else None
    if base is not None and not base.is_dir():
        fail(f"--base {base}: no such folder")
    scenes = args.scene or list(SCENES)
    command = "python -m validation.speed_error " + " ".join(argv or sys.argv[1:])
    figures = Path(args.figures) if args.figures else None
    if args.plots_only:
        rows = write_outputs(out, base or out / "base", scenes, figures, command)
    else:
        rows = sweep(out, base, scenes, args.point or list(DEFAULT_POINTS), figures, command,
                     args.wait)
    plots = [out / f"speed_error_{s}.png" for s in scenes
             if (out / f"speed_error_{s}.png").is_file()]
    for run in args.attach:
        print(f"attached to {attach(Path(run), plots, command)}")
    print(markdown(rows, command))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
