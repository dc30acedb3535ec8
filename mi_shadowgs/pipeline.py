"""The whole method end to end (``mi-shadowgs run``): stage 1 (geometry), stage 2
(segmentation), then stages 3-5 per variant (visibility and the material/light
decomposition, evaluation and relighting), the summary and the report.

``run_pipeline`` calls each stage's library runner; each stage is resumable, and a stage
whose outputs are complete and were made from the same inputs is not run again.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from mi_shadowgs.config import get_preset
from mi_shadowgs.io.atomic import atomic_dir, write_json
from mi_shadowgs.stages import geometry, segmentation
from mi_shadowgs.stages.material import fit as material_fit
from mi_shadowgs.stages.material.runner import decompose, material_config, occluder_bounds
from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.relight.evaluate import (
    check_evaluation_inputs,
    evaluate_decomposition,
    light_json,
    write_figures,
)
from mi_shadowgs.stages.visibility import shadow_maps

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


def material_stage(top, name: str, overrides: dict, data: Path, surfels, train, test,
                   bounds: shadow_maps.SceneBounds, config: RunConfig, overwrite: bool,
                   progress: bool) -> tuple[dict, float | None]:
    """Stages 3-5 of one variant into ``material/<name>`` of the run ``top`` (an Output);
    returns (metrics, fit seconds), the seconds None when a finished output of the same
    provenance is reused."""
    from mi_shadowgs.io.ply import save_ply
    from mi_shadowgs.io.provenance import Output, Provenance, dataset_ref, input_ref
    from mi_shadowgs.stages.common import checkpoint_hooks

    folder = top.folder / "material" / name
    seg_model = top.folder / "segmentation" / "model.ply"
    cfg = material_config(config.preset, overrides)
    settings = {"variant": name, "material": dataclasses.asdict(cfg),
                "visibility": dataclasses.asdict(shadow_maps.get_config(config.preset)),
                "relight": dataclasses.asdict(relight.get_config(config.preset)),
                "bounds_quantile": config.bounds_quantile, "figure_views": config.figure_views}
    provenance = Provenance(dataset=dataset_ref(data), inputs={"model": input_ref(seg_model)},
                            settings=settings)
    top.add_part(f"material/{name}")
    with Output.open(folder, "run", provenance, overwrite=overwrite, reuse=True,
                     inputs=[data, seg_model]) as out:
        if out.complete:
            return json.loads((folder / "metrics.json").read_text()), None
        checkpoints = checkpoint_hooks(out, material_fit.MaterialState.from_checkpoint)
        res, fit_s = _timed(lambda: decompose(surfels, train, config.preset, bounds, overrides,
                                              progress, **checkpoints))
        metrics, images = evaluate_decomposition(res, train, test, bounds, config.preset)
        metrics["fit_s"] = fit_s
        save_ply(out.path("model.ply"), res.surfels)
        write_json(out.path("light.json"), light_json(res))
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
    from mi_shadowgs.stages.common import load_training_views

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
        geo = geometry.run_geometry(data, run / "geometry", geometry.get_config(config.preset),
                                    preset=config.preset, reuse=True, overwrite=overwrite,
                                    progress=progress, train=train, test=test)
        done("geometry", geo)
        top.add_part("segmentation")
        seg = segmentation.run_segmentation(
            run / "geometry" / "model.ply", data, run / "segmentation",
            segmentation.segmentation_config(config.preset, masks), masks=masks,
            preset=config.preset, overwrite=overwrite, reuse=True, progress=progress,
            train=train, views=test)
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
    cols = ["variant", "albedo PSNR", "albedo SSIM", "albedo LPIPS", "light cosine",
            "shadow IoU", "relight PSNR", "relight SSIM", "relight LPIPS", "relight time (s)"]
    rows = [[name, r.get("albedo_psnr"), r.get("albedo_ssim"), r.get("albedo_lpips"),
             r.get("light_cosine"), r.get("shadow_iou"), r.get("relight_psnr"),
             r.get("relight_ssim"), r.get("relight_lpips"), r.get("relight_render_s")]
            for name, r in results.items()]
    skipped = sorted({r["lpips_skipped"] for r in results.values() if r.get("lpips_skipped")})
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
                            "direct irradiance below half the view's median; LPIPS: AlexNet "
                            "v0.1 on sRGB views, background at 0."
                            + "".join(f" LPIPS not computed: {why}." for why in skipped)}],
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
