"""The albedo of finished runs scored both ways: per-region scales and one global scale.

Stage 5's albedo PSNR aligns each material region's channels by their own median scale, so
a fit whose regions have the wrong hue or brightness relative to each other can still score
high. Runs evaluated before ``albedo_psnr_global`` existed lack the second figure; this
scores their stage-4 model again (albedo only; nothing in the runs is written)::

    python -m validation.albedo_global /work/table17            # every ROW/{run,data}
    python -m validation.albedo_global ROW... --out albedo.md

A row is a folder with ``run/`` (a finished run) and ``data/`` (its dataset), as
``validation.pipeline`` lays them out.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.io.atomic import write_text


def rows_under(paths: list[Path]) -> list[Path]:
    out = []
    for p in paths:
        if (p / "run").is_dir() and (p / "data").is_dir():
            out.append(p)
        else:
            out += sorted(q for q in p.iterdir() if (q / "run" / "material" / "full" /
                                                       "model.ply").is_file())
    return out


def diffuse_albedo_views(surfels, cameras) -> np.ndarray:
    """A surfel model's diffuse albedo, albedo x (1 - metallic), as stage 5 renders it for
    the albedo metrics: [V, H, W, 3]."""
    from mi_shadowgs.stages.relight import render as relight

    out = []
    for cam in cameras:
        b = relight.view_buffers(surfels, cam)
        out.append(relight.color_image(b.albedo * (1.0 - b.metallic), cam.height, cam.width))
    return np.stack(out)


def score(row: Path, variant: str = "full") -> dict:
    """Albedo PSNR of ``row``'s stage-4 model on its test views, per-region and global."""
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.stages.evaluation import metrics as evaluation
    from mi_shadowgs.stages.evaluation.evaluate import scored_pixels

    model_path = row / "run" / "material" / variant / "model.ply"
    if not model_path.is_file():
        raise FileNotFoundError(f"{model_path}: no finished stage 4")
    test = load_dataset(row / "data", "test")
    est = diffuse_albedo_views(load_ply(model_path), test.cameras)
    m = evaluation.albedo_metrics(est, test.stack("albedo"), test.stack("material"),
                                  scored_pixels(test))
    metrics = row / "run" / "material" / variant / "metrics.json"
    recorded = json.loads(metrics.read_text()).get("albedo_psnr") if metrics.is_file() else None
    return {"row": row.name, "albedo_psnr": m["psnr"], "albedo_psnr_global": m["psnr_global"],
            "global_scale": m["global_scale"], "recorded_albedo_psnr": recorded}


def markdown(results: list[dict]) -> str:
    lines = ["| row | albedo PSNR (per-region scales; the run's own) | albedo PSNR (one "
             "global scale) | global scale R/G/B |", "|---|---|---|---|"]
    for r in results:
        s = "/".join(f"{x:.3g}" for x in r["global_scale"])
        rec = r.get("recorded_albedo_psnr")
        own = "n/a" if rec is None else f"{rec:.2f}"
        lines.append(f"| {r['row']} | {r['albedo_psnr']:.2f} ({own}) | "
                     f"{r['albedo_psnr_global']:.2f} | {s} |")
    if len(results) > 1:
        lines.append(f"| **mean ({len(results)})** | "
                     f"**{np.mean([r['albedo_psnr'] for r in results]):.2f}** | "
                     f"**{np.mean([r['albedo_psnr_global'] for r in results]):.2f}** | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", type=Path, help="rows, or folders of rows")
    ap.add_argument("--variant", default="full")
    ap.add_argument("--out", type=Path, help="also write the table here (a new file)")
    args = ap.parse_args(argv)
    if args.out is not None and args.out.exists():
        print(f"error: --out {args.out} exists; name a new file", file=sys.stderr)
        return 2
    missing = [p for p in args.paths if not p.is_dir()]
    if missing:
        print(f"error: {missing[0]}: no such folder", file=sys.stderr)
        return 2
    rows = rows_under(args.paths)
    if not rows:
        print(f"error: no ROW/run/material/{args.variant}/model.ply under "
              f"{', '.join(map(str, args.paths))}", file=sys.stderr)
        return 2
    try:
        results = [score(r, args.variant) for r in rows]
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    text = markdown(results)
    print(text)
    if args.out is not None:
        write_text(args.out, text + "\n")  # atomic: a cut write never blocks the rerun
    return 0


if __name__ == "__main__":
    sys.exit(main())
