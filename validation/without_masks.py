"""Stage 1 without masks against stage 1 with them, on the same dataset.

``unmasked_copy`` writes a dataset whose training views are what a user without masks has:
RGB images with no alpha and no object masks, and ``"masks": false`` in
``transforms_train.json`` (the loader's flag for an import without masks). The test split is
copied unchanged, so that the test PSNR, mask IoU and normal error are scored against the
same ground truth. ``main`` trains stage 1 on both (or reuses finished runs) and writes the
table::

    python -m validation.without_masks --data DATA --out OUT [--preset cpu-small]
        [--masked RUN/geometry] [-D name=value ...]

``OUT/data`` is the copy, ``OUT/masked`` and ``OUT/unmasked`` the two stage-1 runs,
``OUT/without_masks.json`` and ``.md`` the figures. ``-D`` overrides a stage-1 setting of
the unmasked run only (e.g. ``-D unmasked_lambda_dist=1000``), for trials.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
from pathlib import Path

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)

# Geometry-evaluation figures compared (keys of stage 1's metrics.json).
FIGURES = ("psnr", "ssim", "mask_iou", "normal_error_median_deg", "surfels", "train_s")


def unmasked_copy(src: Path, dst: Path) -> Path:
    """``dst``: ``src`` with its training views' alpha dropped and ``"masks": false``."""
    from mi_shadowgs.dataset import layout
    from mi_shadowgs.io.atomic import atomic_dir
    from mi_shadowgs.io.images import read_exr, write_exr

    if dst.exists():
        raise FileExistsError(f"{dst}: exists; the copy goes into a new folder")
    with atomic_dir(dst) as tmp:
        for f in sorted(src.iterdir()):
            if f.name.startswith(".mi_shadowgs"):
                continue  # generate's manifest describes the original, not this copy
            if f.is_file():
                shutil.copy2(f, tmp / f.name)
            elif f.name != "train":
                shutil.copytree(f, tmp / f.name)
        meta = json.loads((src / layout.transforms_name("train")).read_text())
        meta["masks"] = False
        (tmp / layout.transforms_name("train")).write_text(json.dumps(meta, indent=1))
        (tmp / "train").mkdir()
        stems = {Path(fr["file_path"]).name for fr in meta["frames"]}
        for f in sorted((src / "train").iterdir()):
            if f.suffix == ".exr" and f.stem in stems:  # the training image itself
                write_exr(tmp / "train" / f.name, read_exr(f)[..., :3])
            elif (f.suffix == ".png" and f.stem in stems) or f.name.endswith(layout.MASK):
                continue  # the 8-bit preview carries the alpha too; the object masks
            else:
                shutil.copy2(f, tmp / "train" / f.name)
    return dst


def train(data: Path, out: Path, preset: str, overrides: dict) -> dict:
    """Stage 1 on ``data`` into ``out`` (resumed or reused when it is there); its metrics."""
    from mi_shadowgs.presets import geometry_config as get_config
    from mi_shadowgs.stages.geometry import run_geometry

    config = get_config(preset)
    if overrides:
        from mi_shadowgs.config import with_overrides
        config = with_overrides(config, overrides, "geometry")
    run_geometry(data, out, config, preset=preset, reuse=True)
    return stage_metrics(out)


def stage_metrics(folder: Path) -> dict:
    """A finished stage-1 folder's test metrics, with its training seconds (log.csv)."""
    metrics = json.loads((folder / "metrics.json").read_text())
    with open(folder / "log.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    metrics["train_s"] = float(rows[-1]["time"]) if rows else None
    return metrics


def table(rows: dict[str, dict]) -> str:
    head = "| run | " + " | ".join(FIGURES) + " |"
    lines = [head, "|" + "---|" * (len(FIGURES) + 1)]
    for name, m in rows.items():
        cells = [f"{m[k]:.4g}" if isinstance(m.get(k), float) else str(m.get(k, "")) for k in
                 FIGURES]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    from mi_shadowgs import backend
    from mi_shadowgs.io.atomic import write_json, write_text

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a dataset with masks (generate)")
    ap.add_argument("--out", required=True, help="output folder (resumed)")
    ap.add_argument("--preset", default="cpu-small")
    ap.add_argument("--masked", default=None,
                    help="a finished stage-1 run of DATA to compare with (else trained)")
    ap.add_argument("-D", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                    help="a stage-1 setting of the unmasked run (JSON value)")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    backend.set_variant()
    if args.threads:
        import drjit as dr

        dr.set_thread_count(args.threads)
    out = Path(args.out)
    overrides = {}
    for item in args.overrides:
        name, _, value = item.partition("=")
        overrides[name] = json.loads(value)
    copy = out / "data"
    if not copy.exists():
        unmasked_copy(Path(args.data), copy)
    masked = Path(args.masked) if args.masked else out / "masked"
    rows = {"masked": stage_metrics(masked) if args.masked
            else train(Path(args.data), masked, args.preset, {}),
            "unmasked": train(copy, out / "unmasked", args.preset, overrides)}
    rows["unmasked"]["overrides"] = overrides
    gap = rows["masked"]["psnr"] - rows["unmasked"]["psnr"]
    write_json(out / "without_masks.json", {"rows": rows, "psnr_gap_db": gap})
    text = table(rows) + f"\nTest PSNR gap (masked - unmasked): {gap:.2f} dB\n"
    write_text(out / "without_masks.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
