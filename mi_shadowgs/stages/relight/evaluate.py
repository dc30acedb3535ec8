"""Stage 5's evaluation: relight the fitted model, measure it on the test views the way the
paper does (Sec. V-A3), and write what the report shows (figures, the light map image, the
light JSON). ``check_evaluation_inputs`` checks what it reads before stage 1 starts.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from mi_shadowgs.core.directions import map_to_blocks
from mi_shadowgs.stages.material import fit
from mi_shadowgs.stages.relight import evaluation
from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.visibility import shadow_maps


def _scaled_albedo_model(model: relight.RelightModel, scale: np.ndarray) -> relight.RelightModel:
    """The model with its albedo times a per-channel factor (ground-truth alignment)."""
    import mitsuba as mi

    surf = dataclasses.replace(model.surfels, channels=dict(model.surfels.channels))
    a = surf.channels["albedo"].numpy() * scale[None].astype(np.float32)
    surf.channels["albedo"] = mi.TensorXf(np.clip(a, 0.0, None).astype(np.float32))
    return dataclasses.replace(model, surfels=surf)


def evaluate_decomposition(result: fit.MaterialResult, train, test, bounds: shadow_maps.SceneBounds,
                           preset: str) -> tuple[dict, dict]:
    """Paper Sec. V-A3 metrics on the test views, and the images behind them.

    Returns (metrics, images): images hold [V, H, W, ...] stacks "albedo", "irradiance" and
    "relit/<setup>" with their ground truth under "gt/...", and the light maps.
    """
    vcfg = shadow_maps.get_config(preset)
    rcfg = relight.get_config(preset)
    model = relight.RelightModel(result.surfels, result.specular, result.use_visibility,
                           result.light.light_set())
    views, decomp_s = relight.relight_views(model, test.cameras, result.light.light_set(), bounds,
                                      rcfg, vcfg)
    mask = test.stack("mask")
    est_alb = np.stack([v["albedo"] for v in views])
    gt_alb = test.stack("albedo")
    alb = evaluation.albedo_metrics(est_alb, gt_alb, test.stack("material"), mask)
    est_irr = np.stack([v["direct_irradiance"] for v in views])
    gt_irr = test.stack("irradiance").sum(axis=3).mean(-1)  # [V, H, W] white direct
    gt_map = np.asarray(train.lights["training"]["light_map"]["radiance"])
    est_light = result.light.light_set()
    est_light_w = np.asarray(est_light.weights, np.float64).T  # [K, 3]
    gt_lights = train.lights["training"]["lights"]
    gt_dirs = np.array([lt["direction"] for lt in gt_lights], np.float64)  # [G, 3]
    gt_irr_w = np.array([lt["irradiance"] for lt in gt_lights], np.float64)  # [G, 3]
    metrics = {
        "albedo_psnr": alb["psnr"], "albedo_ssim": alb["ssim"], "albedo_lpips": alb["lpips"],
        "albedo_per_view": alb["per_view"],
        "light_cosine": evaluation.light_cosine(est_light.directions, est_light_w,
                                                gt_dirs, gt_irr_w),
        "light_map_cosine": evaluation.light_map_cosine(result.light.radiance, gt_map),
        **evaluation.light_angular_errors(est_light.directions, est_light_w, gt_dirs),
        "shadow_iou": evaluation.shadow_iou(est_irr, gt_irr, mask),
        "specular": result.specular, "active_directions": int(len(result.light.active)),
        "decomposition_render_s": decomp_s,
    }
    regions = test.stack("material")
    scales = evaluation.albedo_scales(est_alb, gt_alb, regions, mask)
    images = {"albedo": evaluation.align_albedo(est_alb, regions, scales),
              "gt/albedo": gt_alb, "irradiance": est_irr, "gt/irradiance": gt_irr,
              "light_map": result.light.radiance, "gt/light_map": gt_map.mean(-1)}
    # Relighting: the albedo is aligned to ground truth by one global per-channel factor.
    smodel = _scaled_albedo_model(model, evaluation.global_albedo_scale(est_alb, gt_alb, mask))
    relit = {}
    for entry in train.lights.get("relightings", []):
        name = entry["name"]
        if entry.get("type") == "envmap":  # its 128-direction light set, shadows included
            lights = relight.envmap_light_set(load_envmap(entry, train.root), rcfg)
        else:
            lights = relight.lights_from_json(entry)
        rv, secs = relight.relight_views(smodel, test.cameras, lights, bounds, rcfg, vcfg)
        est = np.stack([v["rgb"] for v in rv])
        gt = np.stack([v.relit[name] for v in test.views])
        relit[name] = {**evaluation.image_metrics(est, gt, mask), "render_s": secs,
                       "views": len(rv), "type": entry.get("type", "directional"),
                       "light_directions": lights.count}
        images[f"relit/{name}"] = est
        images[f"gt/relit/{name}"] = gt
    if relit:
        metrics["relight_psnr"] = float(np.mean([r["psnr"] for r in relit.values()]))
        metrics["relight_ssim"] = float(np.mean([r["ssim"] for r in relit.values()]))
        lp = [r["lpips"] for r in relit.values()]
        metrics["relight_lpips"] = None if None in lp else float(np.mean(lp))
        metrics["relight_render_s"] = float(np.median([r["render_s"] for r in relit.values()]))
    metrics["relighting"] = relit
    metrics["test_views"] = [Path(v.name).name for v in test.views]  # order of per_view
    if "lpips_skipped" in alb:
        metrics["lpips_skipped"] = alb["lpips_skipped"]
    return metrics, images


def _display(img: np.ndarray, scale: float | None = None) -> np.ndarray:
    """Linear [H, W] or [H, W, 3] -> [H, W, 3] in [0, 1] (optionally divided by scale)."""
    a = np.asarray(img, np.float64)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if scale:
        a = a / scale
    return np.clip(a, 0.0, 1.0)


def _error(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Colour-mapped |est - gt| of two linear images, compared as displayed (sRGB)."""
    from mi_shadowgs.io.images import linear_to_srgb
    from mi_shadowgs.io.plots import error_colors

    return error_colors(linear_to_srgb(_display(est)), linear_to_srgb(_display(gt)))


def light_map_image(radiance: np.ndarray, block: int = 8) -> np.ndarray:
    """The paper's 22 x 12 block view of a grid light map, normalised, upscaled [H, W, 3]."""
    blocks = map_to_blocks(np.asarray(radiance, np.float64))  # [12, 22]
    peak = blocks.max()
    img = blocks / peak if peak > 0 else blocks
    img = np.repeat(np.repeat(img, block, 0), block, 1)
    return np.repeat(img[..., None], 3, axis=-1)


def write_figures(folder: Path, test, images: dict, count: int) -> dict:
    """PNG figures of the first ``count`` test views (spread over the split); returns the
    report grid (rows of relative paths). Beside albedo and each relighting, its error map:
    |estimate - ground truth| as displayed (sRGB), colour-mapped by ``io.plots.error_colors``
    (0 to ``io.plots.ERROR_MAX``)."""
    from mi_shadowgs.io.images import write_png

    n = len(test.views)
    picks = sorted({int(round(i * n / max(count, 1))) % n for i in range(count)})
    relits = sorted(k[len("relit/"):] for k in images if k.startswith("relit/"))
    columns = ["input", "albedo", "albedo (GT)", "albedo error", "irradiance",
               "irradiance (GT)"]
    for name in relits:
        columns += [f"relit {name}", f"relit {name} (GT)", f"relit {name} error"]
    # One exposure for estimate and ground truth of a kind, so that they compare.
    irr_scale = float(np.percentile(images["irradiance"], 99)) or 1.0
    gt_irr_scale = float(np.percentile(images["gt/irradiance"], 99)) or 1.0
    rows = []
    for i in picks:
        stem = Path(test.views[i].name).name
        cells = {"input": test.views[i].image, "albedo": images["albedo"][i],
                 "albedo (GT)": images["gt/albedo"][i],
                 "albedo error": _error(images["albedo"][i], images["gt/albedo"][i]),
                 "irradiance": _display(images["irradiance"][i], irr_scale),
                 "irradiance (GT)": _display(images["gt/irradiance"][i], gt_irr_scale)}
        for name in relits:
            cells[f"relit {name}"] = images[f"relit/{name}"][i]
            cells[f"relit {name} (GT)"] = images[f"gt/relit/{name}"][i]
            cells[f"relit {name} error"] = _error(images[f"relit/{name}"][i],
                                                  images[f"gt/relit/{name}"][i])
        paths = []
        for col in columns:
            fname = f"{stem}_{col.replace(' ', '_').replace('(', '').replace(')', '')}.png"
            srgb = not (col.startswith("irradiance") or col.endswith(" error"))
            write_png(folder / fname, _display(cells[col]), srgb=srgb)
            paths.append(fname)
        rows.append({"label": stem, "cells": paths})
    est, gt = light_map_image(images["light_map"]), light_map_image(images["gt/light_map"])
    gap = np.ones((est.shape[0], 4, 3))
    write_png(folder / "light_map.png", np.concatenate([est, gap, gt], axis=1), srgb=False)
    return {"columns": columns, "rows": rows}


def check_evaluation_inputs(train, test) -> None:
    """What ``evaluate_decomposition`` reads, checked before stage 1 starts (DatasetError
    naming the file or field): the training light map and the test views' ground truth."""
    from mi_shadowgs.dataset.loader import DatasetError

    path = train.root / "lights.json"
    if train.lights is None:
        raise DatasetError(f"{path}: file not found (the evaluation compares the estimated "
                           "light map with its training.light_map)")
    try:
        np.asarray(train.lights["training"]["light_map"]["radiance"], np.float64)
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{path}: missing or malformed field "
                           "'training.light_map.radiance'") from None
    for field in ("albedo", "irradiance", "material"):
        missing = [v.name for v in test.views if getattr(v, field) is None]
        if missing:
            raise DatasetError(f"{test.root}: test view {missing[0]!r} has no {field} ground "
                               "truth, which the evaluation needs")
    try:
        for lt in train.lights["training"]["lights"]:
            np.asarray(lt["direction"], np.float64).reshape(3)
            np.asarray(lt["irradiance"], np.float64).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{path}: missing or malformed field 'training.lights' (each with "
                           "a direction and an RGB irradiance)") from None
    for entry in train.lights.get("relightings", []):
        kind = entry.get("type")
        if kind not in RELIGHT_TYPES:
            raise DatasetError(f"{path}: relighting {entry.get('name')!r} has type {kind!r}; "
                               f"known: {', '.join(RELIGHT_TYPES)}")
        if kind == "envmap":
            envmap_file(entry, train.root)
        missing = [v.name for v in test.views if entry.get("name") not in v.relit]
        if missing:
            raise DatasetError(f"{test.root}: test view {missing[0]!r} has no relit image "
                               f"for relighting {entry.get('name')!r} of {path.name}")


RELIGHT_TYPES = ("directional", "envmap")


def envmap_file(entry: dict, root: Path) -> Path:
    """The env-map file of a ``lights.json`` relighting (absolute, or relative to the
    dataset); DatasetError naming it when it is missing."""
    from mi_shadowgs.dataset.loader import DatasetError

    if not entry.get("path"):
        raise DatasetError(f"{root / 'lights.json'}: env-map relighting {entry.get('name')!r} "
                           "has no 'path'")
    path = Path(entry["path"])
    path = path if path.is_absolute() else root / path
    if not path.is_file():
        raise DatasetError(f"{path}: env map of relighting {entry.get('name')!r} not found "
                           f"({root / 'lights.json'})")
    return path


def load_envmap(entry: dict, root: Path):
    """The Mitsuba ``envmap`` emitter of a ``lights.json`` relighting (Y-up lat-long,
    identity to_world, as the generator rendered it)."""
    from mi_shadowgs.core.envmap import load_envmap

    return load_envmap(envmap_file(entry, root), float(entry.get("scale", 1.0)))


def light_json(result: fit.MaterialResult) -> dict:
    """The fitted light of stage 4 as ``light.json`` holds it: the grid radiance, the active
    directions, their unit vectors and irradiance, and the specular flag."""
    light = result.light
    return {"radiance": light.radiance.tolist(), "active": light.active.tolist(),
            "directions": np.asarray(light.light_set().directions).tolist(),
            "irradiance": light.weights.tolist() if light.weights is not None else None,
            "specular": result.specular}
