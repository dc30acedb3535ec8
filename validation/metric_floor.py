"""What stage 5's albedo and shadow metrics can tell apart at a dataset's resolution.

The dataset's ground truth is point-sampled: each pixel holds the albedo and irradiance at
the hit of its centre ray. The photos, and anything fitted to them, are box-filtered over
the pixel. Here the exact scene itself is scored as an estimate: its box-filtered albedo and
irradiance (``dataset.generate.box_filtered_ground_truth``, ``--samples``^2 rays per pixel,
Mitsuba ray tracing) against the point-sampled truth, with stage 5's own metrics
(``stages.relight.evaluation``: shadow IoU of the direct irradiance under the training lights,
albedo PSNR with per-region and with one per-channel scale). Where a thin or small part
spans a few pixels, the two references disagree, and an estimate that resolves the scene to
the pixel scores about what the filtered truth scores; at larger view sizes (``--sizes``,
the same cameras) the disagreement shrinks.

    python -m validation.metric_floor --data DATA [--data DATA ...] --out DIR
        [--sizes 128 256 512] [--views N] [--samples 4]

``--sizes`` defaults to the dataset's own size; ``--views``, to all its test views (the
views stage 5 scores). Writes (atomically) ``metric_floor.json`` and ``metric_floor.md`` into
``--out``, replacing only a folder that holds a ``metric_floor.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM, selects the variant)
from mi_shadowgs.dataset.generate import box_filtered_ground_truth, trace_ground_truth
from mi_shadowgs.stages.relight import evaluation


def dataset_floor(data: Path, sizes: list[int] | None, views: int | None, samples: int,
                  progress: bool = True) -> list[dict]:
    """One row per view size: the filtered truth's shadow IoU and albedo PSNR against the
    point-sampled truth on the test views of ``data`` (a generated dataset)."""
    from tqdm import tqdm

    from mi_shadowgs.dataset.loader import load_dataset
    from validation.visibility import dataset_scene

    test = load_dataset(data, "test")
    cams = test.cameras[:views] if views else test.cameras
    if not cams:
        raise ValueError(f"{data}: no test views")
    setup = dataset_scene(data)  # its lights are the dataset's training lights
    name = data.parent.name if data.name == "data" else data.name
    rows = []
    for size in tqdm(sizes or [cams[0].width], desc=f"{name}: sizes", disable=not progress):
        t0 = time.perf_counter()
        at = [c.with_size(size, round(size * c.height / c.width)) for c in cams]
        point = trace_ground_truth(setup, at)
        box = box_filtered_ground_truth(setup, at, samples=samples)
        mask = point["mask"].astype(bool)  # [V, H, W]
        iou = evaluation.shadow_iou(box["irradiance"].sum(axis=3).mean(-1),
                                    point["irradiance"].sum(axis=3).mean(-1), mask)
        alb = evaluation.albedo_metrics(box["albedo"], point["albedo"], point["material"],
                                        mask)
        rows.append({"dataset": name, "data": str(data), "size": size, "views": len(at),
                     "samples": samples, "shadow_iou": iou, "albedo_psnr": alb["psnr"],
                     "albedo_psnr_global": alb["psnr_global"],
                     "partly_covered_share": float(np.mean(box["coverage"][mask] < 1.0)),
                     "wall_s": time.perf_counter() - t0})
    return rows


def markdown(rows: list[dict]) -> str:
    lines = ["The exact scene, box-filtered over each pixel, scored by stage 5's metrics "
             "against the dataset's point-sampled ground truth:", "",
             "| dataset | view size | views | shadow IoU | albedo PSNR per region | "
             "albedo PSNR one scale | mask pixels partly covered |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['dataset']} | {r['size']} | {r['views']} | {r['shadow_iou']:.3f} | "
                     f"{r['albedo_psnr']:.2f} | {r['albedo_psnr_global']:.2f} | "
                     f"{r['partly_covered_share']:.3f} |")
    return "\n".join(lines)


def run(out_dir: Path, datas: list[Path], sizes: list[int] | None = None,
        views: int | None = None, samples: int = 4, progress: bool = True,
        command: list[str] | None = None) -> dict:
    """Every dataset's rows into ``out_dir`` (written atomically; an existing folder is
    replaced only when it holds a metric_floor.json). Returns {"rows", "markdown"}."""
    from mi_shadowgs.io.atomic import atomic_dir, write_json, write_text

    out_dir = Path(out_dir)
    if out_dir.exists() and not (out_dir / "metric_floor.json").is_file():
        raise FileExistsError(f"{out_dir}: exists and holds no metric_floor.json; not "
                              "replacing it")
    rows = []
    for d in datas:
        rows += dataset_floor(Path(d), sizes, views, samples, progress)
    md = markdown(rows) if rows else "No dataset to score."
    with atomic_dir(out_dir, overwrite=True) as tmp:
        write_json(tmp / "metric_floor.json", {"rows": rows, "command": command or sys.argv,
                                               "loadavg": list(os.getloadavg())})
        write_text(tmp / "metric_floor.md", md + "\n")
    return {"rows": rows, "markdown": "## What the metrics can tell apart\n\n" + md}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Score the exact scene's box-filtered albedo "
                                 "and irradiance with stage 5's metrics against the "
                                 "point-sampled ground truth.")
    ap.add_argument("--data", type=Path, action="append", required=True,
                    help="a generated dataset (repeat for several)")
    ap.add_argument("--out", type=Path, required=True,
                    help="output folder (replaced only when it holds a metric_floor.json)")
    ap.add_argument("--sizes", type=int, nargs="*", default=None,
                    help="view widths to score at (default: the dataset's own)")
    ap.add_argument("--views", type=int, default=None, help="first N test views only")
    ap.add_argument("--samples", type=int, default=4,
                    help="sub-pixel rays per pixel side for the box filter (default 4)")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    if args.samples < 1:
        ap.error(f"--samples must be >= 1, got {args.samples}")
    if args.views is not None and args.views < 1:
        ap.error(f"--views must be >= 1, got {args.views}")
    if any(s < 1 for s in args.sizes or []):
        ap.error(f"--sizes must be >= 1, got {args.sizes}")
    for d in args.data:
        if not (d / "dataset.json").is_file():
            ap.error(f"{d / 'dataset.json'}: not found (--data takes a dataset made by "
                     "`mi-shadowgs generate`, whose scene can be reloaded)")
    try:  # run refuses a folder it did not write before any work
        summary = run(args.out, args.data, args.sizes, args.views, args.samples,
                      not args.quiet)
    except FileExistsError as e:
        ap.error(str(e))
    print(markdown(summary["rows"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
