"""Stages 3-5 over a fitted geometry, and the whole method end to end (``mi-shadowgs run``).

``decompose`` fits stage 4 (visibility from the surfels' shadow maps, Cook-Torrance
materials, the light map, indirect SH) on the training views; ``evaluate_decomposition``
measures it on the test views the way the paper does (Sec. V-A3) and relights them under
every setup of ``lights.json``. ``run_pipeline`` chains stage 1 (geometry), stage 2
(segmentation), these, the figures and the report, each stage resumable: a stage whose
outputs are complete is not run again.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from mi_shadowgs.config import get_preset, with_overrides
from mi_shadowgs.core.directions import map_to_blocks
from mi_shadowgs.io.atomic import atomic_dir, write_json
from mi_shadowgs.stages.material import fit as SM
from mi_shadowgs.stages.relight import evaluation as E
from mi_shadowgs.stages.relight import render as R
from mi_shadowgs.stages.visibility import shadow_maps as V

VARIANTS = {
    "full": {},
    "no_visibility": {"use_visibility": False},  # paper Table 3, "w/o visibility"
    "no_segmentation": {"segment_average": False},  # "w/o segmentation"
}
MASK_SOURCES = ("auto", "material", "chromaticity")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """What ``mi-shadowgs run`` does beyond each stage's own preset."""

    preset: str = "cpu-small"  # the preset of every stage
    masks: str = "auto"  # segmentation labels: material ids when the dataset has them
    ablations: bool = False  # also fit the Table 3 variants (two more stage-4 fits)
    bounds_quantile: float = 0.98  # shadow-map bound: this quantile of surfel distances
    figure_views: int = 4  # test views shown in the report's figure grid
    material_iterations: int | None = None  # override of the stage-4 preset

    def __post_init__(self):
        if self.masks not in MASK_SOURCES:
            raise ValueError(f"RunConfig.masks must be one of {MASK_SOURCES}, got {self.masks!r}")


PRESETS = {
    "cpu-small": RunConfig(),
    "paper": RunConfig(preset="paper", ablations=True),
}


def get_config(name: str) -> RunConfig:
    return get_preset(PRESETS, name, "run")


# -- stage 4 ------------------------------------------------------------------------------
def occluder_bounds(surfels, cameras, quantile: float) -> V.SceneBounds:
    """Shadow-map bounds from the surfels themselves (paper: their centroid), robust to
    floaters through ``quantile``."""
    pos = surfels.to_numpy()["position"]
    return V.SceneBounds.from_points(pos, cameras, quantile)


def material_config(preset: str, overrides: dict | None = None) -> SM.MaterialConfig:
    return with_overrides(SM.get_config(preset), overrides, "material")


def decompose(surfels, train, preset: str, bounds: V.SceneBounds, overrides: dict | None = None,
              progress: bool = True, **checkpoints) -> SM.MaterialResult:
    """Stage 4 on the training views of ``train`` (a loaded Dataset); ``checkpoints``:
    ``state`` and ``on_checkpoint`` of ``fit_material``."""
    cfg = material_config(preset, overrides)
    return SM.fit_material(surfels, train.cameras, [v.image for v in train.views],
                           [v.mask for v in train.views], cfg, bounds, V.preset(preset),
                           progress=progress, **checkpoints)


def _scaled_albedo_model(model: R.RelightModel, scale: np.ndarray) -> R.RelightModel:
    """The model with its albedo times a per-channel factor (ground-truth alignment)."""
    import mitsuba as mi

    surf = dataclasses.replace(model.surfels, channels=dict(model.surfels.channels))
    a = surf.channels["albedo"].numpy() * scale[None].astype(np.float32)
    surf.channels["albedo"] = mi.TensorXf(np.clip(a, 0.0, None).astype(np.float32))
    return dataclasses.replace(model, surfels=surf)


def evaluate_decomposition(result: SM.MaterialResult, train, test, bounds: V.SceneBounds,
                           preset: str) -> tuple[dict, dict]:
    """Paper Sec. V-A3 metrics on the test views, and the images behind them.

    Returns (metrics, images): images hold [V, H, W, ...] stacks "albedo", "irradiance" and
    "relit/<setup>" with their ground truth under "gt/...", and the light maps.
    """
    vcfg = V.preset(preset)
    rcfg = R.get_config(preset)
    model = R.RelightModel(result.surfels, result.specular, result.use_visibility,
                           result.light.light_set())
    views, decomp_s = R.relight_views(model, test.cameras, result.light.light_set(), bounds,
                                      rcfg, vcfg)
    mask = test.stack("mask")
    est_alb = np.stack([v["albedo"] for v in views])
    gt_alb = test.stack("albedo")
    alb = E.albedo_metrics(est_alb, gt_alb, test.stack("material"), mask)
    est_irr = np.stack([v["direct_irradiance"] for v in views])
    gt_irr = test.stack("irradiance").sum(axis=3).mean(-1)  # [V, H, W] white direct
    gt_map = np.asarray(train.lights["training"]["light_map"]["radiance"])
    metrics = {
        "albedo_psnr": alb["psnr"], "albedo_ssim": alb["ssim"],
        "light_cosine": E.light_cosine(result.light.radiance, gt_map),
        "shadow_iou": E.shadow_iou(est_irr, gt_irr, mask),
        "specular": result.specular, "active_directions": int(len(result.light.active)),
        "decomposition_render_s": decomp_s,
    }
    images = {"albedo": E.align_albedo(est_alb, test.stack("material"),
                                       E.albedo_scales(est_alb, gt_alb, test.stack("material"),
                                                       mask)),
              "gt/albedo": gt_alb, "irradiance": est_irr, "gt/irradiance": gt_irr,
              "light_map": result.light.radiance, "gt/light_map": gt_map.mean(-1)}
    # Relighting: the albedo is aligned to ground truth by one global per-channel factor.
    smodel = _scaled_albedo_model(model, E.global_albedo_scale(est_alb, gt_alb, mask))
    relit = {}
    for entry in train.lights.get("relightings", []):
        if entry.get("type") != "directional":
            continue  # env-map relighting needs the emitter: see relight.envmap_light_set
        name = entry["name"]
        rv, secs = R.relight_views(smodel, test.cameras, R.lights_from_json(entry), bounds,
                                   rcfg, vcfg)
        est = np.stack([v["rgb"] for v in rv])
        gt = np.stack([v.relit[name] for v in test.views])
        relit[name] = {**E.image_metrics(est, gt, mask), "render_s": secs, "views": len(rv)}
        images[f"relit/{name}"] = est
        images[f"gt/relit/{name}"] = gt
    if relit:
        metrics["relight_psnr"] = float(np.mean([r["psnr"] for r in relit.values()]))
        metrics["relight_ssim"] = float(np.mean([r["ssim"] for r in relit.values()]))
        metrics["relight_render_s"] = float(np.median([r["render_s"] for r in relit.values()]))
    metrics["relighting"] = relit
    return metrics, images


# -- figures --------------------------------------------------------------------------------
def _display(img: np.ndarray, scale: float | None = None) -> np.ndarray:
    """Linear [H, W] or [H, W, 3] -> [H, W, 3] in [0, 1] (optionally divided by scale)."""
    a = np.asarray(img, np.float64)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if scale:
        a = a / scale
    return np.clip(a, 0.0, 1.0)


def light_map_image(radiance: np.ndarray, block: int = 8) -> np.ndarray:
    """The paper's 22 x 12 block view of a grid light map, normalised, upscaled [H, W, 3]."""
    blocks = map_to_blocks(np.asarray(radiance, np.float64))  # [12, 22]
    peak = blocks.max()
    img = blocks / peak if peak > 0 else blocks
    img = np.repeat(np.repeat(img, block, 0), block, 1)
    return np.repeat(img[..., None], 3, axis=-1)


def write_figures(folder: Path, test, images: dict, count: int) -> dict:
    """PNG figures of the first ``count`` test views (spread over the split); returns the
    report grid (rows of relative paths)."""
    from mi_shadowgs.io.images import write_png

    n = len(test.views)
    picks = sorted({int(round(i * n / max(count, 1))) % n for i in range(count)})
    relits = sorted(k[len("relit/"):] for k in images if k.startswith("relit/"))
    columns = ["input", "albedo", "albedo (GT)", "irradiance", "irradiance (GT)"]
    for name in relits:
        columns += [f"relit {name}", f"relit {name} (GT)"]
    # One exposure for estimate and ground truth of a kind, so that they compare.
    irr_scale = float(np.percentile(images["irradiance"], 99)) or 1.0
    gt_irr_scale = float(np.percentile(images["gt/irradiance"], 99)) or 1.0
    rows = []
    for i in picks:
        stem = Path(test.views[i].name).name
        cells = {"input": test.views[i].image, "albedo": images["albedo"][i],
                 "albedo (GT)": images["gt/albedo"][i],
                 "irradiance": _display(images["irradiance"][i], irr_scale),
                 "irradiance (GT)": _display(images["gt/irradiance"][i], gt_irr_scale)}
        for name in relits:
            cells[f"relit {name}"] = images[f"relit/{name}"][i]
            cells[f"relit {name} (GT)"] = images[f"gt/relit/{name}"][i]
        paths = []
        for col in columns:
            fname = f"{stem}_{col.replace(' ', '_').replace('(', '').replace(')', '')}.png"
            srgb = not col.startswith("irradiance")
            write_png(folder / fname, _display(cells[col]), srgb=srgb)
            paths.append(fname)
        rows.append({"label": stem, "cells": paths})
    est, gt = light_map_image(images["light_map"]), light_map_image(images["gt/light_map"])
    gap = np.ones((est.shape[0], 4, 3))
    write_png(folder / "light_map.png", np.concatenate([est, gap, gt], axis=1), srgb=False)
    return {"columns": columns, "rows": rows}


# -- end to end -----------------------------------------------------------------------------
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
    for entry in train.lights.get("relightings", []):
        if entry.get("type") == "directional":
            missing = [v.name for v in test.views if entry.get("name") not in v.relit]
            if missing:
                raise DatasetError(f"{test.root}: test view {missing[0]!r} has no relit image "
                                   f"for relighting {entry.get('name')!r} of {path.name}")


def material_stage(top, name: str, overrides: dict, data: Path, surfels, train, test,
                   bounds: V.SceneBounds, config: RunConfig, overwrite: bool,
                   progress: bool) -> tuple[dict, float | None]:
    """Stages 3-5 of one variant into ``material/<name>`` of the run ``top`` (an Output);
    returns (metrics, fit seconds), the seconds None when a finished output of the same
    provenance is reused."""
    from mi_shadowgs.io.ply import save_ply
    from mi_shadowgs.io.provenance import Output, Provenance, dataset_ref, input_ref
    from mi_shadowgs.stages.geometry.runner import checkpoint_hooks

    folder = top.folder / "material" / name
    seg_model = top.folder / "segmentation" / "model.ply"
    cfg = material_config(config.preset, overrides)
    settings = {"variant": name, "material": dataclasses.asdict(cfg),
                "visibility": dataclasses.asdict(V.preset(config.preset)),
                "relight": dataclasses.asdict(R.get_config(config.preset)),
                "bounds_quantile": config.bounds_quantile, "figure_views": config.figure_views}
    provenance = Provenance(dataset=dataset_ref(data), inputs={"model": input_ref(seg_model)},
                            settings=settings)
    top.add_part(f"material/{name}")
    with Output.open(folder, "run", provenance, overwrite=overwrite, reuse=True,
                     inputs=[data, seg_model]) as out:
        if out.complete:
            return json.loads((folder / "metrics.json").read_text()), None
        checkpoints = checkpoint_hooks(out, SM.MaterialState.from_checkpoint)
        res, fit_s = _timed(lambda: decompose(surfels, train, config.preset, bounds, overrides,
                                              progress, **checkpoints))
        metrics, images = evaluate_decomposition(res, train, test, bounds, config.preset)
        metrics["fit_s"] = fit_s
        save_ply(out.path("model.ply"), res.surfels)
        write_json(out.path("light.json"), {
            "radiance": res.light.radiance.tolist(), "active": res.light.active.tolist(),
            "directions": np.asarray(res.light.light_set().directions).tolist(),
            "irradiance": res.light.weights.tolist() if res.light.weights is not None
            else None, "specular": res.specular})
        with atomic_dir(folder / "figures", overwrite=True) as tmp:
            grid = write_figures(tmp, test, images, config.figure_views)
            out.claim(*(f"figures/{p.name}" for p in sorted(tmp.iterdir())))
        write_json(out.path("grid.json"), grid)
        write_json(out.path("metrics.json"), metrics)
        out.finish()
    return metrics, fit_s


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def run_pipeline(data: str | Path, out: str | Path, config: RunConfig, progress: bool = True,
                 overwrite: bool = False, log=print) -> dict:
    """Stages 1-5 on dataset ``data`` into run folder ``out``; returns the summary.

    Every input (both splits, ground truth, lights.json) is read and checked first. Each
    stage's output is reused when it is finished and was made from the same dataset, input
    model and settings; stages 1, 2 and 4 continue from their last checkpoints after an
    interruption (a kill loses at most their ``checkpoint_seconds``);
    anything else exits with a ProvenanceError naming what differs, unless ``overwrite``
    removes the run's files first. ``log`` takes the stages' one-line summaries.
    """
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.io.provenance import Output, Provenance, dataset_ref
    from mi_shadowgs.io.report import write_report
    from mi_shadowgs.stages.geometry import train as stage_geometry
    from mi_shadowgs.stages.geometry.runner import (
        load_training_views,
        run_geometry,
        run_segmentation,
        segmentation_config,
    )

    data, run = Path(data), Path(out)
    t_start = time.perf_counter()
    train = load_training_views(data)
    test = load_dataset(data, "test")
    check_evaluation_inputs(train, test)
    masks = config.masks
    if masks == "auto":
        masks = "material" if all(v.material is not None for v in train.views) else \
            "chromaticity"
    provenance = Provenance(dataset=dataset_ref(data), settings=dataclasses.asdict(config))
    stages = []

    def done(name: str, stage) -> None:
        if stage.ran:
            stages.append((name, stage.seconds))
            if stage.summary and log:
                log(stage.summary)

    with Output.open(run, "run", provenance, overwrite=overwrite, reuse=True,
                     compare=("dataset",), inputs=[data],
                     parts=("geometry", "segmentation", "material")) as top:
        top.add_part("geometry")
        geo = run_geometry(data, run / "geometry", stage_geometry.get_config(config.preset),
                           preset=config.preset, reuse=True, overwrite=overwrite,
                           progress=progress, train=train, test=test)
        done("geometry", geo)
        top.add_part("segmentation")
        seg = run_segmentation(run / "geometry" / "model.ply", data, run / "segmentation",
                               segmentation_config(config.preset, masks), masks=masks,
                               preset=config.preset, overwrite=overwrite, reuse=True,
                               progress=progress, train=train, views=test)
        done("segmentation", seg)
        surfels = load_ply(run / "segmentation" / "model.ply")
        bounds = occluder_bounds(surfels, train.cameras, config.bounds_quantile)
        overrides = {} if config.material_iterations is None else \
            {"iterations": config.material_iterations}

        # Stages 3-5 per variant: visibility + decomposition, then evaluation and relighting.
        variants = VARIANTS if config.ablations else {"full": VARIANTS["full"]}
        results = {}
        for name, ov in variants.items():
            results[name], fit_s = material_stage(top, name, {**overrides, **ov}, data,
                                                  surfels, train, test, bounds, config,
                                                  overwrite, progress)
            if fit_s is not None:
                stages.append((f"material ({name})", fit_s))
        summary = build_summary(run, data, config, results, stages,
                                time.perf_counter() - t_start)
        write_json(top.path("summary.json"), summary)
        top.claim("report.html")
        write_report(run)
        top.finish()
    return summary


def _json_or_empty(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def build_summary(run: Path, data: Path, config: RunConfig, results: dict, stages: list,
                  seconds: float) -> dict:
    """The report's ``summary.json`` (see ``mi_shadowgs.io.report``) from the run's files."""
    import mitsuba as mi

    geo = _json_or_empty(run / "geometry" / "metrics.json")
    seg = _json_or_empty(run / "segmentation" / "segmentation.json")
    cols = ["variant", "albedo PSNR", "albedo SSIM", "light cosine", "shadow IoU",
            "relight PSNR", "relight SSIM", "relight time (s)"]
    rows = [[name, r.get("albedo_psnr"), r.get("albedo_ssim"), r.get("light_cosine"),
             r.get("shadow_iou"), r.get("relight_psnr"), r.get("relight_ssim"),
             r.get("relight_render_s")] for name, r in results.items()]
    secs = {name: s for name, s in stages}
    info = _json_or_empty(data / "dataset.json")
    scene = Path(str(info.get("scene", data.name))).stem
    summary = {
        "title": f"mi_shadowgs run: {scene} ({data.name})",
        "dataset": str(data.resolve()), "preset": config.preset, "variant": mi.variant(),
        "date": time.strftime("%Y-%m-%d %H:%M"), "total_seconds": seconds,
        "tables": [{"title": "Decomposition and relighting (paper Tables 1 and 3)",
                    "columns": cols, "rows": rows,
                    "note": "Albedo: per-channel median scale per material region; relit "
                            "views: one global per-channel albedo scale; shadow IoU: "
                            "direct irradiance below half the view's median. LPIPS is left "
                            "out: no offline LPIPS network is available here."}],
        "stages": [],
    }
    if geo:
        scalars = {k: v for k, v in geo.items() if not isinstance(v, (list, dict))}
        summary["stages"].append({"name": "Stage 1: geometry", "seconds": secs.get("geometry"),
                                  "metrics": scalars, "figures": _previews(run)})
    if seg:
        m = dict(seg.get("metrics", {}))
        m.update({"K": seg.get("k"), "masks": seg.get("masks")})
        segs = sorted((run / "segmentation" / "segments").glob("*_overlay.png"))[:4]
        summary["stages"].append({
            "name": "Stage 2: material segmentation", "seconds": secs.get("segmentation"),
            "metrics": m, "figures": [{"title": p.stem, "path": str(p.relative_to(run))}
                                      for p in segs]})
    full = run / "material" / "full"
    if (full / "grid.json").is_file():
        grid = json.loads((full / "grid.json").read_text())
        grid["rows"] = [{"label": r["label"],
                         "cells": [f"material/full/figures/{c}" for c in r["cells"]]}
                        for r in grid["rows"]]
        grid["title"] = "Input, albedo, irradiance and relighting (cf. paper Fig. 3)"
        summary["grid"] = grid
        summary["stages"].append({
            "name": "Stages 3-5: visibility, decomposition, relighting",
            "seconds": secs.get("material (full)"),
            "metrics": {k: v for k, v in results.get("full", {}).items()
                        if not isinstance(v, (dict, list))},
            "figures": [{"title": "light map 22x12: estimate | ground truth",
                         "path": "material/full/figures/light_map.png"}]})
    return summary


def _previews(run: Path) -> list[dict]:
    prev = sorted((run / "geometry" / "previews").glob("*.png"))
    return [{"title": f"training preview {p.stem}", "path": str(p.relative_to(run))}
            for p in prev[-1:]]
