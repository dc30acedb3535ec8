"""Stage-1 acceptance: train geometry on a dataset, evaluate on its test views.

    python -m validation.geometry --data DATA --out OUT [--preset P]

Writes ``OUT/geometry.json`` (test-view PSNR/SSIM, normal and depth error, mask IoU, wall
times, surfel count, load average, pass/fail of each acceptance item) and
``OUT/previews/<view>.png`` (render | ground truth over normals | ground-truth normals);
the stage itself is ``mi_shadowgs.stages.geometry.run_geometry``'s output in ``OUT/stage/``
(``model.ply``, ``metrics.json``, ``log.csv``, checkpoint). A killed call, run again,
continues the stage from its checkpoint (a finished one is reused) when the dataset and the
settings are the same, and exits 2 naming what differs otherwise; ``--overwrite`` trains it
again. The time item is the stage's training time (``log.csv``), which counts across resumes.
``run(out_dir, quick)`` follows ``validation.run_all``'s interface (default scene, generated
into ``out_dir``).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.config import ConfigError
from mi_shadowgs.io.atomic import atomic_path, write_json
from mi_shadowgs.io.provenance import ProvenanceError
from validation import claim_out, fail

# The acceptance figures at cpu-small. "wall_s" is checked on the stage's training time
# (``train_s``): a resumed stage's call takes only part of it.
ACCEPT = {"psnr": 30.0, "normal_error_median_deg": 10.0, "mask_iou": 0.98, "wall_s": 480.0}


def _preview(view, r) -> np.ndarray:
    from mi_shadowgs.io.images import linear_to_srgb

    def nrm(n, cover):
        return np.where(cover[..., None], np.clip(n * 0.5 + 0.5, 0, 1), 0.0)

    rgb = linear_to_srgb(np.clip(np.concatenate([r["rgb"], view.image], 1), 0, 1))
    n_gt = view.normal if view.normal is not None else np.zeros_like(r["normal"])
    nn = np.concatenate([nrm(r["normal"], r["alpha"] > 0), nrm(n_gt, view.mask)], 1)
    return np.concatenate([rgb, nn], 0)


def validate(data: Path, out: Path, preset: str = "cpu-small", iterations: int | None = None,
             progress: bool = True, overwrite: bool = False) -> dict:
    """Stage 1 through its library runner (``run_geometry``, into ``OUT/stage``: continued
    or reused when its provenance matches, exit 2 naming the difference otherwise), with a
    preview per test view, then the acceptance table ``OUT/geometry.json``."""
    import csv
    import json

    from mi_shadowgs.config import with_overrides
    from mi_shadowgs.io.checkpoint import has_checkpoint
    from mi_shadowgs.io.images import write_png
    from mi_shadowgs.presets import geometry_config as get_config
    from mi_shadowgs.stages.geometry import run_geometry

    try:
        config = get_config(preset)
        if iterations:
            config = with_overrides(config, {"iterations": iterations}, "geometry")
    except ConfigError as exc:
        fail(str(exc))
    load0 = os.getloadavg()
    (out / "previews").mkdir(parents=True, exist_ok=True)

    def on_view(view, r):
        with atomic_path(out / "previews" / f"{Path(view.name).name}.png") as tmp:
            write_png(tmp, _preview(view, r), srgb=False)

    # A checkpoint of an unfinished stage is continued (run_geometry loads it).
    checkpointed = not overwrite and has_checkpoint(out / "stage" / "checkpoint")
    t0 = time.perf_counter()
    try:
        stage = run_geometry(data, out / "stage", config, preset=preset, overwrite=overwrite,
                             reuse=True, progress=progress, on_test_view=on_view)
    except ProvenanceError as exc:
        fail(f"{exc} (validation.geometry)")
    wall = time.perf_counter() - t0
    m = json.loads((stage.folder / "metrics.json").read_text())
    with open(stage.folder / "log.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    # The log's time counts the training across resumes (TrainState.elapsed), not loading
    # or evaluation; this call's wall time is only its part of the stage.
    train_s = float(rows[-1]["time"]) if rows else float("nan")
    m.update(dataset=str(data), preset=preset, iterations=config.iterations,
             model=str(stage.folder / "model.ply"), train_s=train_s, wall_s=wall,
             stage="reused" if not stage.ran else "resumed" if checkpointed else "trained",
             loadavg_start=list(load0), loadavg_end=list(os.getloadavg()))
    m["accept"] = {"psnr": m["psnr"] >= ACCEPT["psnr"],
                   "normal_error_median_deg": m.get("normal_error_median_deg", 1e9) <=
                   ACCEPT["normal_error_median_deg"],
                   "mask_iou": m["mask_iou"] >= ACCEPT["mask_iou"],
                   "wall_s": train_s <= ACCEPT["wall_s"]}
    write_json(out / "geometry.json", m)
    return m


def _markdown(m: dict) -> str:
    ok = m["accept"]
    return (f"| {Path(m['dataset']).name} | {m['psnr']:.2f} ({'ok' if ok['psnr'] else 'FAIL'}) "
            f"| {m['ssim']:.4f} | {m.get('normal_error_median_deg', float('nan')):.2f} "
            f"({'ok' if ok['normal_error_median_deg'] else 'FAIL'}) "
            f"| {m.get('depth_error_mean_abs', float('nan')):.3f} | {m['mask_iou']:.4f} "
            f"({'ok' if ok['mask_iou'] else 'FAIL'}) | {m['train_s']:.0f} s "
            f"({'ok' if ok['wall_s'] else 'FAIL'}) | {m['surfels']} |")


def run(out_dir: Path, quick: bool) -> dict:
    """validation.run_all entry: generate the default scene at cpu-small and validate."""
    from mi_shadowgs.dataset.writer import write_dataset
    from mi_shadowgs.presets import generate_config as gen_config
    from mi_shadowgs.scenes import scene_path

    out_dir = Path(out_dir) / "geometry"
    data = out_dir / "data"
    if not data.exists():
        write_dataset(scene_path("default"), data, gen_config("cpu-small"), "cpu-small",
                      seed=0, progress=False)
    m = validate(data, out_dir, "cpu-small", iterations=200 if quick else None,
                 progress=False)
    header = ("| dataset | PSNR dB | SSIM | median normal err deg | depth err | mask IoU | train "
              "| surfels |\n|---|---|---|---|---|---|---|---|\n")
    m["markdown"] = header + _markdown(m)
    return m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="dataset folder")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--preset", default="cpu-small")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--overwrite", action="store_true",
                    help="train the stage again (default: continue or reuse OUT/stage)")
    args = ap.parse_args(argv)
    claim_out(args.out, "validation.geometry", ('geometry.json',))
    m = validate(Path(args.data), Path(args.out), args.preset, args.iterations,
                 progress=not args.no_progress, overwrite=args.overwrite)
    print(_markdown(m))
    return 0 if all(m["accept"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
