"""Stage 4-5 end to end on the ground-truth-geometry stand-in (issue 7 acceptance, Table 3).

Surfels are sampled on the dataset scene's true shapes (``mi_shadowgs.standin``; segment =
shape), so the decomposition and relighting are measured independently of stage 1. For the
full method and the two ablations (w/o visibility, w/o segmentation) it fits stage 4 on the
training views, then on the test views evaluates albedo PSNR/SSIM (per-region per-channel
median alignment), light cosine, shadow IoU (direct irradiance < 0.5 x median), relighting
PSNR/SSIM for each directional relighting of ``lights.json`` and the relighting render time.

    python -m validation.decomposition DATA --out OUT [--preset cpu-small] [--no-ablations]

Writes (atomically) ``OUT/summary.json`` and PNGs per variant: albedo (estimate | GT),
irradiance (estimate | GT), light map 22x12 (estimate | GT), relit (estimate | GT).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np  # noqa: I001

import mi_shadowgs  # noqa: F401  (finds libLLVM, selects the variant)
from mi_shadowgs import evaluation as E
from mi_shadowgs import relight as R
from mi_shadowgs import stage_material as SM
from mi_shadowgs import visibility as V
from mi_shadowgs.atomic import atomic_dir, write_json
from mi_shadowgs.config import with_overrides
from mi_shadowgs.dataset.loader import load_dataset
from mi_shadowgs.dataset.scene import load_scene
from mi_shadowgs.directions import map_to_blocks
from mi_shadowgs.imageio import write_png
from mi_shadowgs.standin import standin_surfels

VARIANTS = {"full": {}, "no_visibility": {"use_visibility": False},
            "no_segmentation": {"segment_average": False}}
# Bounds of the occluders' shadow maps: the object's sphere times this covers the shadows it
# casts on the base down to ~30 degrees of light elevation.
BOUNDS_FACTOR = 2.5


def scene_bounds(setup, cameras) -> V.SceneBounds:
    c = np.asarray(setup.object_center, np.float64)
    return V.SceneBounds(tuple(c.tolist()), BOUNDS_FACTOR * float(setup.object_radius),
                         V.mean_camera_distance(cameras, c))


def run_variant(name, overrides, surfels, train, test, bounds, preset, extra) -> dict:
    cfg = with_overrides(SM.get_config(preset), {**overrides, **extra}, "material")
    vcfg = V.preset(preset)
    t0 = time.perf_counter()
    res = SM.fit_material(surfels, train.cameras, [v.image for v in train.views],
                          [v.mask for v in train.views], cfg, bounds, vcfg)
    fit_s = time.perf_counter() - t0
    model = R.RelightModel(res.surfels, res.specular, res.use_visibility,
                           res.light.light_set())
    # Decomposition under the estimated training light, on the test views.
    views, _ = R.relight_views(model, test.cameras, res.light.light_set(), bounds,
                               R.get_config(preset), vcfg)
    mask = test.stack("mask")
    est_alb = np.stack([v["albedo"] for v in views])
    gt_alb = test.stack("albedo")
    alb = E.albedo_metrics(est_alb, gt_alb, test.stack("material"), mask)
    est_irr = np.stack([v["direct_irradiance"] for v in views])
    gt_irr = test.stack("irradiance").sum(axis=3).mean(-1)  # [V, H, W]
    gt_map = np.asarray(train.lights["training"]["light_map"]["radiance"])
    out = {"albedo_psnr": alb["psnr"], "albedo_ssim": alb["ssim"],
           "light_cosine": E.light_cosine(res.light.radiance, gt_map),
           "shadow_iou": E.shadow_iou(est_irr, gt_irr, mask),
           "fit_s": fit_s, "specular": res.specular,
           "active_directions": int(len(res.light.active)), "timings": res.timings,
           "history": res.history}
    steps_w = min(cfg.warmup, cfg.iterations)
    if steps_w and "warmup_total_s" in res.timings:
        out["step_ms_warmup"] = 1e3 * res.timings["warmup_total_s"] / steps_w
    if cfg.iterations > cfg.warmup and "main_s" in res.timings:
        out["step_ms_main"] = 1e3 * res.timings["main_s"] / (cfg.iterations - cfg.warmup)
    # Relighting: albedo rescaled by one global per-channel factor (estimate vs GT).
    scale = E.global_albedo_scale(est_alb, gt_alb, mask)
    scaled = dataclasses.replace(model.surfels, channels=dict(model.surfels.channels))
    import mitsuba as mi

    a = scaled.channels["albedo"].numpy() * scale[None].astype(np.float32)
    scaled.channels["albedo"] = mi.TensorXf(np.clip(a, 0, None).astype(np.float32))
    smodel = dataclasses.replace(model, surfels=scaled)
    relit = {}
    figs = {"albedo": (est_alb[0], gt_alb[0]), "irradiance": (est_irr[0], gt_irr[0])}
    for entry in train.lights.get("relightings", []):
        if entry.get("type") != "directional":
            continue
        lights = R.lights_from_json(entry)
        rv, secs = R.relight_views(smodel, test.cameras, lights, bounds, R.get_config(preset),
                                   vcfg)
        est = np.stack([v["rgb"] for v in rv])
        gt = np.stack([v.relit[entry["name"]] for v in test.views])
        m = E.image_metrics(est, gt, mask)
        relit[entry["name"]] = {**m, "render_s": secs, "views": len(rv)}
        figs[f"relit_{entry['name']}"] = (est[0], gt[0])
    out["relighting"] = relit
    out["relight_psnr"] = float(np.mean([r["psnr"] for r in relit.values()]))
    out["relight_ssim"] = float(np.mean([r["ssim"] for r in relit.values()]))
    out["relight_render_s"] = float(np.median([r["render_s"] for r in relit.values()]))
    figs["light_map"] = (map_to_blocks(res.light.radiance), map_to_blocks(gt_map.mean(1)))
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
    train = load_dataset(args.data, "train")
    test = load_dataset(args.data, "test")
    if not train.info or "scene" not in train.info:
        raise SystemExit(f"{args.data}: dataset.json has no 'scene' (need a generated dataset)")
    setup = load_scene(train.info["scene"], train.info.get("parameters"))
    surfels = standin_surfels(setup)
    bounds = scene_bounds(setup, train.cameras)
    extra = {} if args.iterations is None else {"iterations": args.iterations}
    variants = {"full": {}} if args.no_ablations else VARIANTS
    summary = {"data": str(Path(args.data).resolve()), "preset": args.preset,
               "surfels": surfels.count, "date": time.strftime("%Y-%m-%d %H:%M"),
               "variants": {}}
    with atomic_dir(args.out, overwrite=args.overwrite) as tmp:
        for name, ov in variants.items():
            res, figs = run_variant(name, ov, surfels, train, test, bounds, args.preset, extra)
            summary["variants"][name] = res
            for fig, (a, b) in figs.items():
                img = _side_by_side(a, b)
                if fig in ("irradiance", "light_map"):
                    img = img / max(np.percentile(img, 99), 1e-6)
                write_png(tmp / f"{name}_{fig}.png", np.clip(img, 0, 1))
            print(name, json.dumps({k: v for k, v in res.items()
                                    if k not in ("history", "relighting", "timings")}))
        write_json(tmp / "summary.json", summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
