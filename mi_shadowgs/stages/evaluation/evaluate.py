"""Evaluation of a fitted model: relight it on the test views and measure it the way the
paper does (Sec. V-A3), each metric only where the dataset has its ground truth.
``check_evaluation_inputs`` checks what it reads before stage 1 starts.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from mi_shadowgs.core.directions import angles_from_direction
from mi_shadowgs.stages.evaluation import metrics as evaluation
from mi_shadowgs.stages.material.state import MaterialResult
from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.visibility import shadow_maps


def _scaled_albedo_model(model: relight.RelightModel, scale: np.ndarray) -> relight.RelightModel:
    """The model with its albedo times a per-channel factor (ground-truth alignment)."""
    from mi_shadowgs.core import jit

    surf = dataclasses.replace(model.surfels, channels=dict(model.surfels.channels))
    a = surf.channels["albedo"].numpy() * scale[None].astype(np.float32)
    surf.channels["albedo"] = jit.tensor(np.clip(a, 0.0, None))
    return dataclasses.replace(model, surfels=surf)


# What the albedo metrics compare with the ground truth, recorded in metrics.json so that a
# table can tell runs evaluated before it (the alpha-blended albedo as rendered).
ALBEDO_ESTIMATE = "surface albedo (alpha-normalised)"
# Which test pixels the albedo metrics and the shadow IoU score (``evaluation.surface_pixels``),
# recorded likewise: runs evaluated before also scored mask pixels without a ground-truth surface.
SCORED_PIXELS = "mask with a ground-truth surface"

# What each metric needs from the dataset (names as ``ground_truth`` reports them), so
# that a dataset without some ground truth (NeRF-synthetic, TensoIR, captures) still runs
# and the summary says which metrics were skipped and why.
METRIC_NEEDS = {
    "albedo PSNR/SSIM/LPIPS": ("test albedo", "test material ids"),
    "light cosine and angular errors": ("training lights",),
    "light-map cosine": ("training light map",),
    "shadow IoU": ("test irradiance",),
    "relighting PSNR/SSIM/LPIPS": ("relightings", "test relit images", "test albedo"),
}


def material_ids(test) -> np.ndarray | None:
    """The test views' material ids [V, H, W], or None where a view has none."""
    return None if any(v.material is None for v in test.views) else test.stack("material")


def scored_pixels(test) -> np.ndarray:
    """The test pixels that albedo and shadow IoU are scored on [V, H, W]
    (``evaluation.surface_pixels``: the mask where the ground truth has a surface)."""
    return evaluation.surface_pixels(test.stack("mask"), material_ids(test))


def ground_truth(train, test) -> dict[str, str | None]:
    """Which ground truth the dataset has: name -> None when present, else why not."""
    lights = train.lights or {}
    path = train.root / "lights.json"

    def per_view(field: str, what: str) -> str | None:
        missing = [v.name for v in test.views if getattr(v, field) is None]
        if not missing:
            return None
        return (f"no test view has {what}" if len(missing) == len(test.views) else
                f"test view {missing[0]!r} has no {what}")

    relit = [e.get("name") for e in lights.get("relightings", []) or []]
    miss_relit = [(n, v.name) for n in relit for v in test.views if n not in v.relit]
    return {
        "test albedo": per_view("albedo", "albedo"),
        "test material ids": per_view("material", "material ids"),
        "test irradiance": per_view("irradiance", "irradiance"),
        "test normals": per_view("normal", "normals"),
        "test depth": per_view("depth", "depth"),
        "test visibility": per_view("visibility", "visibility"),
        "training lights": None if lights.get("training", {}).get("lights") else
        f"{path.name} with training.lights is absent",
        "training light map": None if lights.get("training", {}).get("light_map") else
        f"{path.name} with training.light_map is absent",
        "relightings": None if relit else f"{path.name} lists no relightings",
        "test relit images": None if relit and not miss_relit else
        (f"test view {miss_relit[0][1]!r} has no relit image {miss_relit[0][0]!r}"
         if miss_relit else "no relighting to compare with"),
    }


def skipped_metrics(available: dict[str, str | None]) -> list[dict]:
    """The metrics of ``METRIC_NEEDS`` whose ground truth is missing, each with what it
    needs and why it was not computed."""
    out = []
    for metric, needs in METRIC_NEEDS.items():
        why = [available[n] for n in needs if available.get(n)]
        if why:
            out.append({"metric": metric, "needs": list(needs), "why": "; ".join(why)})
    return out


def evaluate_decomposition(result: MaterialResult, train, test, bounds: shadow_maps.SceneBounds,
                           vis_config: shadow_maps.VisibilityConfig,
                           relight_config: relight.RelightConfig, figure_lights: int = 3,
                           cache: relight.RelightCache | None = None) -> tuple[dict, dict]:
    """Paper Sec. V-A3 metrics on the test views, each computed only when the dataset has
    the ground truth it needs (``METRIC_NEEDS``; ``metrics["skipped"]`` lists the others
    with the reason), and the images behind them.

    Returns (metrics, images): images hold [V, H, W, ...] stacks "albedo" (aligned to the
    ground truth when there is one), "irradiance", "roughness", "metallic", "normal",
    "visibility" (the ``figure_lights`` strongest fitted lights, with "visibility_lights"
    their (azimuth, elevation)), "relit/<setup>", their ground truth under "gt/...", and the
    light maps. ``cache`` (``render.RelightCache``) keeps the shadow maps for the caller,
    e.g. for ``relight.previews.write_previews`` of the same fit. ``vis_config``: the shadow
    maps stage 4 fitted with (their receiver band too); ``relight_config``: the env-map
    sampling of the relightings.
    """
    vcfg, rcfg = vis_config, relight_config
    avail = ground_truth(train, test)
    skipped = skipped_metrics(avail)
    gone = {s["metric"] for s in skipped}
    est_light = result.light.light_set()
    model = relight.RelightModel(result.surfels, result.specular, result.use_visibility,
                                 est_light, vcfg.receiver_band)
    t0 = time.perf_counter()
    maps = (relight.shadow_maps_for(model, est_light, bounds, vcfg) if cache is None else
            cache.shadow_maps(model, est_light, bounds, vcfg))
    factor = relight.indirect_factor(model, est_light, rcfg)
    views = [relight.relight_view(model, cam, est_light, maps, factor, buffers=True,
                                  view=None if cache is None else
                                  cache.view_buffers(model, cam)[0])
             for cam in test.cameras]
    decomp_s = time.perf_counter() - t0  # relight_view reads back to numpy: synced
    mask = test.stack("mask")  # relit images: the photo's coverage
    material = material_ids(test)
    scored = evaluation.surface_pixels(mask, material)  # albedo and shadows: a true surface
    # The surface's albedo, as the ground truth holds it (not weighted by the coverage).
    est_alb = evaluation.surface_albedo(np.stack([v["albedo"] for v in views]),
                                        np.stack([v["alpha"] for v in views]))
    est_irr = np.stack([v["direct_irradiance"] for v in views])
    est_light_w = np.asarray(est_light.weights, np.float64).T  # [K, 3]
    order = np.argsort(-est_light_w.mean(-1))[:figure_lights]  # strongest lights first
    metrics = {"specular": result.specular, "active_directions": int(len(result.light.active)),
               "decomposition_render_s": decomp_s, "skipped": skipped,
               "scored_pixels": SCORED_PIXELS if material is not None else "mask"}
    images = {"albedo": est_alb, "irradiance": est_irr, "light_map": result.light.radiance,
              "roughness": np.stack([v["roughness"] for v in views]),
              "metallic": np.stack([v["metallic"] for v in views]),
              "normal": np.stack([v["normal"] for v in views]),
              "visibility": np.stack([v["visibility"][..., order] for v in views]),
              "visibility_lights": [angles_from_direction(est_light.directions[k])
                                    for k in order]}
    for metric in METRIC_NEEDS:  # a skipped metric is there as None, named in "skipped"
        if metric in gone:
            keys = {"albedo PSNR/SSIM/LPIPS": ("albedo_psnr", "albedo_ssim", "albedo_lpips",
                                               "albedo_psnr_global"),
                    "light cosine and angular errors": ("light_cosine",),
                    "light-map cosine": ("light_map_cosine",),
                    "shadow IoU": ("shadow_iou", "shadow_iou_decided",
                                   "shadow_undecided_fraction"),
                    "relighting PSNR/SSIM/LPIPS": ("relight_psnr", "relight_ssim",
                                                   "relight_lpips")}[metric]
            metrics.update(dict.fromkeys(keys))
    if "albedo PSNR/SSIM/LPIPS" not in gone:
        _albedo_scores(est_alb, test, material, scored, metrics, images)
    if "light cosine and angular errors" not in gone:
        gt_lights = train.lights["training"]["lights"]
        gt_dirs = np.array([lt["direction"] for lt in gt_lights], np.float64)  # [G, 3]
        gt_irr_w = np.array([lt["irradiance"] for lt in gt_lights], np.float64)  # [G, 3]
        seen = evaluation.seen_from(est_light.directions, est_light.positions, gt_lights)
        metrics["light_cosine"] = evaluation.light_cosine(seen, est_light_w, gt_dirs, gt_irr_w)
        metrics.update(evaluation.light_angular_errors(seen, est_light_w, gt_dirs))
        metrics.update(evaluation.lamp_errors(seen, est_light_w, est_light.positions,
                                              gt_lights))
    if "light-map cosine" not in gone:
        gt_map = np.asarray(train.lights["training"]["light_map"]["radiance"])
        metrics["light_map_cosine"] = evaluation.light_map_cosine(result.light.radiance,
                                                                  gt_map)
        images["gt/light_map"] = gt_map.mean(-1) if gt_map.ndim == 2 else gt_map
    if "shadow IoU" not in gone:
        _shadow_scores(est_irr, test, scored, metrics, images)
    relit = {}
    if "relighting PSNR/SSIM/LPIPS" not in gone:
        # The albedo is aligned to ground truth by one global per-channel factor.
        smodel = _scaled_albedo_model(model, evaluation.global_albedo_scale(
            est_alb, test.stack("albedo"), scored))
        relit = _relit_scores(smodel, train, test, bounds, vcfg, rcfg, cache, mask, images)
    if relit:
        metrics["relight_psnr"] = float(np.mean([r["psnr"] for r in relit.values()]))
        metrics["relight_ssim"] = float(np.mean([r["ssim"] for r in relit.values()]))
        lp = [r["lpips"] for r in relit.values()]
        metrics["relight_lpips"] = None if None in lp else float(np.mean(lp))
        metrics["relight_render_s"] = float(np.median([r["render_s"] for r in relit.values()]))
    metrics["relighting"] = relit
    metrics["test_views"] = [Path(v.name).name for v in test.views]  # order of per_view
    return metrics, images


def _albedo_scores(est_alb, test, material, scored, metrics: dict, images: dict) -> None:
    """The albedo metrics (per material region, aligned by a scale per region) into
    ``metrics``, the aligned albedo and its truth into ``images``."""
    gt_alb = test.stack("albedo")
    alb = evaluation.albedo_metrics(est_alb, gt_alb, material, scored)
    metrics.update({"albedo_estimate": ALBEDO_ESTIMATE,
                    "albedo_psnr": alb["psnr"], "albedo_ssim": alb["ssim"],
                    "albedo_lpips": alb["lpips"], "albedo_per_view": alb["per_view"],
                    "albedo_psnr_global": alb["psnr_global"]})
    if "lpips_skipped" in alb:
        metrics["lpips_skipped"] = alb["lpips_skipped"]
    scales = evaluation.albedo_scales(est_alb, gt_alb, material, scored)
    images["albedo"] = evaluation.align_albedo(est_alb, material, scales)
    images["gt/albedo"] = gt_alb


def _shadow_scores(est_irr, test, scored, metrics: dict, images: dict) -> None:
    """The shadow IoU, its decided form and the undecided share into ``metrics``; the true
    white direct irradiance into ``images``."""
    gt_irr = test.stack("irradiance").sum(axis=3).mean(-1)  # [V, H, W] white direct
    metrics["shadow_iou"] = evaluation.shadow_iou(est_irr, gt_irr, scored)
    metrics["shadow_iou_decided"] = evaluation.shadow_iou(
        est_irr, gt_irr, scored, undecided_band=evaluation.SHADOW_UNDECIDED_BAND)
    metrics["shadow_undecided_fraction"] = float(np.mean([
        evaluation.undecided_pixels(g, m).sum() / max(int(m.sum()), 1)
        for g, m in zip(gt_irr, scored, strict=True)]))
    images["gt/irradiance"] = gt_irr


def _relit_scores(smodel, train, test, bounds, vcfg, rcfg, cache, mask, images: dict) -> dict:
    """Each of the dataset's relightings rendered with ``smodel`` and scored against its
    ground truth: {name: metrics}; the renders and truths into ``images``."""
    relit = {}
    for entry in train.lights.get("relightings", []):
        name = entry["name"]
        if entry.get("type") == "envmap":  # its 128-direction light set, shadows included
            lights = relight.envmap_light_set(load_envmap(entry, train.root), rcfg)
        else:  # directional lights, or lamps weighted at the scene's centre
            lights = relight.lights_from_json(entry, bounds.center)
        # Only the relit colours are scored: no irradiance pass (for an env map, a second
        # shading over its 128 directions).
        rv, secs = relight.relight_views(smodel, test.cameras, lights, bounds, rcfg, vcfg,
                                         cache=cache, only_rgb=True)
        est = np.stack([v["rgb"] for v in rv])
        gt = np.stack([v.relit[name] for v in test.views])
        relit[name] = {**evaluation.image_metrics(est, gt, mask), "render_s": secs,
                       "views": len(rv), "type": entry.get("type", "directional"),
                       "light_directions": lights.count}
        images[f"relit/{name}"] = est
        images[f"gt/relit/{name}"] = gt
    return relit


def check_evaluation_inputs(train, test) -> dict[str, str | None]:
    """What ``evaluate_decomposition`` reads, checked before stage 1 starts: ground truth
    that is present but malformed is a DatasetError naming the file or field; ground truth
    that is absent only skips the metrics that need it. Returns ``ground_truth``."""
    from mi_shadowgs.dataset.loader import DatasetError

    path = train.root / "lights.json"
    lights = train.lights or {}
    training = lights.get("training", {})
    if not isinstance(training, dict):
        raise DatasetError(f"{path}: field 'training' must be an object")
    if "light_map" in training:
        try:
            np.asarray(training["light_map"]["radiance"], np.float64)
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{path}: missing or malformed field "
                               "'training.light_map.radiance'") from None
    try:
        for lt in training.get("lights", []):
            np.asarray(lt["direction"], np.float64).reshape(3)
            np.asarray(lt["irradiance"], np.float64).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{path}: missing or malformed field 'training.lights' (each with "
                           "a direction and an RGB irradiance)") from None
    for entry in lights.get("relightings", []):
        kind = entry.get("type")
        if kind not in RELIGHT_TYPES:
            raise DatasetError(f"{path}: relighting {entry.get('name')!r} has type {kind!r}; "
                               f"known: {', '.join(RELIGHT_TYPES)}")
        if kind == "envmap":
            envmap_file(entry, train.root)
        if kind == "point":
            from mi_shadowgs.stages.relight.lamps import lamps_from_json

            try:
                lamps_from_json(entry, str(path))
            except ValueError as exc:
                raise DatasetError(str(exc)) from None
    return ground_truth(train, test)


RELIGHT_TYPES = ("directional", "envmap", "point")


def envmap_file(entry: dict, root: Path) -> Path:
    """The env-map file of a ``lights.json`` relighting (absolute, or relative to the
    dataset); DatasetError naming it when it is missing."""
    from mi_shadowgs.dataset.loader import DatasetError, envmap_path

    if not entry.get("path"):
        raise DatasetError(f"{root / 'lights.json'}: env-map relighting {entry.get('name')!r} "
                           "has no 'path'")
    path = envmap_path(entry, root)
    if not path.is_file():
        raise DatasetError(f"{path}: env map of relighting {entry.get('name')!r} not found "
                           f"({root / 'lights.json'})")
    return path


def load_envmap(entry: dict, root: Path):
    """The Mitsuba ``envmap`` emitter of a ``lights.json`` relighting (Y-up lat-long,
    identity to_world, as the generator rendered it)."""
    from mi_shadowgs.core.envmap import load_envmap

    return load_envmap(envmap_file(entry, root), float(entry.get("scale", 1.0)))
