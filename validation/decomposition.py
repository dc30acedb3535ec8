"""Stage 4-5 end to end on the ground-truth-geometry stand-in.

Surfels are sampled on the dataset scene's true shapes (``mi_shadowgs.dataset.standin``; segment =
shape), so the decomposition and relighting are measured independently of stage 1. For the
full method and the two ablations (w/o visibility, w/o segmentation) it fits stage 4 on the
training views, then on the test views evaluates albedo PSNR/SSIM (per-region per-channel
median alignment), light cosine, shadow IoU (direct irradiance < 0.5 x median), relighting
PSNR/SSIM for each directional relighting of ``lights.json`` and the relighting render time.

    python -m validation.decomposition DATA --out OUT [--preset cpu-small] [--no-ablations]

Writes ``OUT/summary.json`` and PNGs per variant: albedo (estimate | GT), irradiance
(estimate | GT), light map 22x12 (estimate | GT), relit (estimate | GT). Each variant is a
unit of its own (``validation.units``, ``OUT/units/<variant>/``, with stage 4's checkpoint):
a killed call, run again, continues the variant in progress and reuses the finished ones;
``--overwrite`` fits them again.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np  # noqa: I001

import mi_shadowgs  # noqa: F401  (finds libLLVM, selects the variant)
from mi_shadowgs import presets as run_presets
from mi_shadowgs.config import ConfigError, with_overrides
from mi_shadowgs.core.directions import map_to_blocks
from mi_shadowgs.dataset.fingerprint import dataset_ref
from mi_shadowgs.dataset.loader import DatasetError, load_dataset
from mi_shadowgs.dataset.scene import SceneError, dataset_scene
from mi_shadowgs.dataset.standin import standin_surfels
from mi_shadowgs.io.atomic import write_bytes, write_json
from mi_shadowgs.io.images import write_png
from mi_shadowgs.io.provenance import Provenance
from mi_shadowgs.presets import material_config as get_config
from mi_shadowgs.stages import evaluation, material
from mi_shadowgs.stages.common import checkpoint_hooks
from mi_shadowgs.stages.material.state import MaterialState
from mi_shadowgs.stages.visibility import shadow_maps
from validation import claim_out, fail
from validation.units import run_unit, settings_of

STUDY = "validation.decomposition"

VARIANTS = run_presets.VARIANTS
# Bounds of the occluders' shadow maps: the object's sphere times this covers the shadows it
# casts on the base down to ~30 degrees of light elevation.
BOUNDS_FACTOR = 2.5


def scene_bounds(setup, cameras) -> shadow_maps.SceneBounds:
    c = np.asarray(setup.object_center, np.float64)
    return shadow_maps.SceneBounds(tuple(c.tolist()), BOUNDS_FACTOR * float(setup.object_radius),
                         shadow_maps.mean_camera_distance(cameras, c))


def run_variant(name, overrides, surfels, train, test, bounds, preset, extra,
                checkpoints=None) -> dict:
    """Fit one variant on the stand-in and evaluate it (``mi_shadowgs.pipeline``);
    ``checkpoints``: ``state`` and ``on_checkpoint`` of stage 4."""
    t0 = time.perf_counter()
    cfg = with_overrides(get_config(preset), {**overrides, **extra}, "material")
    res = material.decompose(surfels, train, cfg, run_presets.visibility_config(preset), bounds,
                             **(checkpoints or {}))
    fit_s = time.perf_counter() - t0
    out, images = evaluation.evaluate_decomposition(res, train, test, bounds,
                                                    run_presets.visibility_config(preset),
                                                    run_presets.relight_config(preset))
    out.update(fit_s=fit_s, timings=res.timings, history=res.history)
    steps_w = min(cfg.warmup, cfg.iterations)
    if steps_w and "warmup_total_s" in res.timings:
        out["step_ms_warmup"] = 1e3 * res.timings["warmup_total_s"] / steps_w
    if cfg.iterations > cfg.warmup and "main_s" in res.timings:
        out["step_ms_main"] = 1e3 * res.timings["main_s"] / (cfg.iterations - cfg.warmup)
    figs = {"albedo": (images["albedo"][0], images["gt/albedo"][0]),
            "irradiance": (images["irradiance"][0], images["gt/irradiance"][0]),
            "light_map": (map_to_blocks(images["light_map"]),
                          map_to_blocks(images["gt/light_map"]))}
    for key in images:
        if key.startswith("relit/"):
            figs[f"relit_{key[6:]}"] = (images[key][0], images[f"gt/{key}"][0])
    return out, figs


def _side_by_side(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.ndim == 2:
        a, b = a[..., None].repeat(3, -1), b[..., None].repeat(3, -1)
    gap = np.ones((a.shape[0], 2, 3))
    return np.concatenate([a, gap, b], axis=1)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("data", help="dataset folder (mi-shadowgs generate)")
    p.add_argument("--out", required=True)
    p.add_argument("--preset", default="cpu-small")
    p.add_argument("--no-ablations", action="store_true")
    p.add_argument("--iterations", type=int, default=None)
    p.add_argument("--overwrite", action="store_true")
    args = p.parse_args(argv)
    try:
        run_presets.get_config(args.preset)  # the preset named before any work
        train = load_dataset(args.data, "train")
        test = load_dataset(args.data, "test")
        setup = dataset_scene(args.data)
    except (ConfigError, DatasetError, SceneError) as exc:
        fail(str(exc))
    claim_out(args.out, STUDY, ("summary.json",), inputs=(args.data,))
    surfels = standin_surfels(setup)
    bounds = scene_bounds(setup, train.cameras)
    extra = {} if args.iterations is None else {"iterations": args.iterations}
    variants = {"full": {}} if args.no_ablations else VARIANTS
    data_ref = dataset_ref(args.data)
    summary = {"data": str(Path(args.data).resolve()), "preset": args.preset,
               "surfels": surfels.count, "date": time.strftime("%Y-%m-%d %H:%M"),
               "variants": {}}
    for name, ov in variants.items():
        def fit_variant(unit, name=name, ov=ov) -> dict:
            hooks = checkpoint_hooks(unit, MaterialState.from_checkpoint)
            res, figs = run_variant(name, ov, surfels, train, test, bounds, args.preset,
                                    extra, hooks)
            res["resumed"] = hooks["state"] is not None  # fit_s: this call's part only
            for fig, (a, b) in figs.items():
                img = _side_by_side(a, b)
                if fig in ("irradiance", "light_map"):
                    img = img / max(np.percentile(img, 99), 1e-6)
                write_png(unit.path(f"{fig}.png"), np.clip(img, 0, 1))
            return res

        provenance = Provenance(data_ref, settings=settings_of(
            preset=args.preset, variant=ov, overrides=extra, surfels=surfels.count))
        res = run_unit(args.out, name, STUDY, provenance, fit_variant,
                       overwrite=args.overwrite)
        summary["variants"][name] = res
        for png in sorted((Path(args.out) / "units" / name).glob("*.png")):
            # Beside summary.json, where the figures always were.
            write_bytes(Path(args.out) / f"{name}_{png.name}", png.read_bytes())
        print(name, json.dumps({k: v for k, v in res.items()
                                if k not in ("history", "relighting", "timings")}))
    write_json(Path(args.out) / "summary.json", summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
