"""``mi-shadowgs segment RUN_OR_MODEL --data DATA --out OUT``: stage 2, material segments.

RUN_OR_MODEL is a surfel model PLY, or a run folder holding ``geometry/model.ply``.
Trains per-surfel features on the training views' label maps (``--masks material``: the
dataset's material ids; ``chromaticity``: shadow-invariant automatic masks), clusters
them, and writes to OUT:

- ``model.ply``: the model with channels ``feature_0..D-1`` and ``segment`` (id 0..K-1);
- ``segments/NAME.png``: the rendered segment map of every view of ``--split``
  (colour-coded, black = background), ``segments/NAME_overlay.png``: it over the image;
- ``segmentation.json``: settings, K, timings, and where the split has material ids, the
  adjusted Rand index, mIoU (Hungarian matching) and the lit/shadowed check of the base.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", metavar="RUN_OR_MODEL",
                        help="surfel model PLY, or a run folder with geometry/model.ply")
    parser.add_argument("--data", required=True, help="dataset folder (training views)")
    parser.add_argument("--out", required=True, help="output folder (created)")
    parser.add_argument("--preset", default="cpu-small", help="cpu-small (default) or paper")
    parser.add_argument("--masks", default="material", choices=("material", "chromaticity"),
                        help="label maps to train on (default: the dataset's material ids)")
    parser.add_argument("--k", type=int, default=None,
                        help="number of segments (default: the number of mask labels)")
    parser.add_argument("--split", default="test",
                        help="views to render segment maps of (default: test)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a segmentation setting (repeatable)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def resolve_model(path: str | Path) -> Path:
    """The model PLY of a run folder or a PLY path (FileNotFoundError naming it)."""
    p = Path(path)
    if p.is_dir():
        cand = p / "geometry" / "model.ply"
        if not cand.is_file():
            raise FileNotFoundError(f"{p}: run folder without geometry/model.ply")
        return cand
    if not p.is_file():
        raise FileNotFoundError(f"model file not found: {p}")
    return p


def _parse_sets(items: list[str]) -> dict:
    import dataclasses

    from .segmentation import SegmentationConfig

    kinds = {f.name: f.type for f in dataclasses.fields(SegmentationConfig)}
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE")
        if key not in kinds:
            raise ValueError(f"--set: unknown segmentation setting {key!r}; known: "
                             f"{sorted(kinds)}")
        kind = str(kinds[key])
        if value.lower() == "none" and "None" in kind:
            out[key] = None
        elif kind.startswith("int"):
            out[key] = int(value)
        else:
            out[key] = float(value)
    return out


def overlay(image, seg_map, colors, alpha: float = 0.5):
    """sRGB uint8 [H, W, 3]: the segment colours blended over the (linear) image."""
    import numpy as np

    from .imageio import to_uint8

    base = to_uint8(np.clip(image[..., :3], 0.0, 1.0)).astype(np.float64)
    col = colors[seg_map].astype(np.float64)
    fg = (seg_map > 0)[..., None]
    return np.where(fg, (1 - alpha) * base + alpha * col, base).round().astype(np.uint8)


def run(args) -> int:
    from tqdm import tqdm

    from . import masks as masks_mod
    from . import segmentation as seg
    from .atomic import write_json
    from .config import to_dict, with_overrides
    from .dataset.loader import load_dataset
    from .imageio import write_png
    from .ply import load_ply, save_ply

    model = resolve_model(args.model)
    config = seg.get_config(args.preset)
    overrides = _parse_sets(args.set)
    if args.k is not None:
        overrides["n_segments"] = args.k
    if args.masks == "chromaticity":  # see SegmentationConfig.min_label_fraction
        overrides.setdefault("min_label_fraction", 0.005)
    config = with_overrides(config, overrides, "segmentation")
    surfels = load_ply(model)
    train = load_dataset(args.data, "train")
    views = load_dataset(args.data, args.split)
    t0 = time.perf_counter()
    label_maps = masks_mod.masks_for(train, args.masks, masks_mod.get_config(args.preset))
    t_masks = time.perf_counter() - t0
    result = seg.segment_surfels(surfels, train.cameras, label_maps, config,
                                 progress=not args.quiet, names=[v.name for v in train.views])
    t_stage = time.perf_counter() - t0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_ply(out / "model.ply", result.surfels)

    colors = seg.segment_colors(result.k)
    maps = []
    for v in tqdm(views.views, desc="segment maps", unit="view", disable=args.quiet):
        m = seg.render_segment_map(result.surfels, result.segments, result.k, v.camera,
                                   config.segment_alpha)
        maps.append(m)
        stem = Path(v.name).name
        write_png(out / "segments" / f"{stem}.png", colors[m])
        write_png(out / "segments" / f"{stem}_overlay.png", overlay(v.image, m, colors))
    report = {"model": str(model), "data": str(args.data), "masks": args.masks,
              "preset": args.preset, "config": to_dict(config), "k": result.k,
              "surfels": surfels.count, "seconds_masks": t_masks,
              "seconds_train": result.train.seconds, "seconds_stage": t_stage,
              "split": args.split, "views": len(maps)}
    if all(v.material is not None for v in views.views):
        gt = [v.material for v in views.views]
        report["metrics"] = seg.evaluate_maps(maps, gt)
        info = views.info or {}
        mats = info.get("materials") or []
        base = next((m["id"] for m in mats if m.get("name") == "base"), None)
        if base is None:
            base = int(max(int(g.max()) for g in gt))
        if all(v.visibility is not None for v in views.views):
            try:
                report["base_shadow"] = seg.shadow_consistency(
                    maps, gt, [v.visibility for v in views.views], int(base))
            except ValueError as exc:  # no shadowed base pixel in these views
                report["base_shadow"] = {"error": str(exc)}
    write_json(out / "segmentation.json", report)
    summary = {k: round(v, 4) for k, v in report.get("metrics", {}).items()
               if isinstance(v, float)}
    print(f"segmented {surfels.count} surfels into {result.k} segments in {t_stage:.1f} s; "
          f"wrote {out} {json.dumps(summary) if summary else ''}".rstrip())
    return 0
