"""Stage 2's library runner: ``run_segmentation(model, data, folder, config, ...)`` trains
per-surfel features on the training label maps, clusters them into segments and writes the
segmented model, the segment maps and their metrics. ``mi-shadowgs segment`` and
``mi_shadowgs.pipeline.run_pipeline`` call it.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from mi_shadowgs.config import to_dict
from mi_shadowgs.dataset.fingerprint import dataset_ref
from mi_shadowgs.io.atomic import write_json
from mi_shadowgs.io.provenance import Output, Provenance, input_ref
from mi_shadowgs.stages.common import (
    StageRun,
    checkpoint_hooks,
    load_training_views,
    settings_dict,
    warn_other_backend,
)


def label_fraction(config, masks: str) -> float:
    """The share of the labelled pixels below which a label does not count for K, for label
    maps from ``masks``: ``config.chromaticity_min_label_fraction`` for colour labels (their
    edge and highlight slivers would each count), else ``config.min_label_fraction``."""
    return (config.chromaticity_min_label_fraction if masks == "chromaticity"
            else config.min_label_fraction)


def overlay(image, seg_map, colors, alpha: float = 0.5):
    """sRGB uint8 [H, W, 3]: the segment colours blended over the (linear) image."""
    from mi_shadowgs.io.images import to_uint8

    base = to_uint8(np.clip(image[..., :3], 0.0, 1.0)).astype(np.float64)
    col = colors[seg_map].astype(np.float64)
    fg = (seg_map > 0)[..., None]
    return np.where(fg, (1 - alpha) * base + alpha * col, base).round().astype(np.uint8)


def _check_model_dataset(model: Path, data, dataset: dict) -> None:
    """ProvenanceError when ``model`` is a stage output (its folder's manifest lists it) made
    from another dataset than ``data``: its segments would be trained on views of another
    scene or capture. A PLY from elsewhere is taken as it is."""
    from mi_shadowgs.io.provenance import MANIFEST_NAME, ProvenanceError, read_manifest

    made = read_manifest(model.parent)
    if not made or model.name not in made["files"] or not made.get("dataset"):
        return
    if made["dataset"].get("fingerprint") != dataset["fingerprint"]:
        raise ProvenanceError(
            f"{model}: was fitted to the dataset {made['dataset'].get('path')} (see "
            f"{model.parent / MANIFEST_NAME}), not to --data {data}: their fingerprints "
            "differ; segment it with its own dataset")


def run_segmentation(model: str | Path, data: str | Path, folder: str | Path, config, *,
                     masks: str, chromaticity=None, preset: str = "",
                     dataset: dict | None = None, split: str = "test", overwrite: bool = False,
                     reuse: bool = False, progress: bool = True, train=None,
                     views=None) -> StageRun:
    """Stage 2: segments of the surfel model ``model`` from ``data``'s training label maps.

    Writes ``model.ply`` (with ``feature_*`` and ``segment``), ``segments/NAME.png`` and
    ``NAME_overlay.png`` per view of ``split``, ``segmentation.json`` and the feature
    training's ``checkpoint/checkpoint.npz`` into ``folder``. An existing output is replaced
    (``overwrite``), returned when finished with the same dataset, model and settings or
    else continued from its checkpoint (``reuse``), or refused. ``train`` / ``views``: the
    training split and ``split``, when the caller has loaded them already. ``chromaticity``:
    the ``ChromaticityConfig`` of label maps from colour (``masks`` "chromaticity");
    ``dataset``: the dataset's fingerprint, when the caller has it; ``preset``: recorded.
    """
    from tqdm import tqdm

    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.io.images import write_png
    from mi_shadowgs.io.ply import load_ply, save_ply
    from mi_shadowgs.stages.segmentation import features as seg
    from mi_shadowgs.stages.segmentation import maps as seg_maps
    from mi_shadowgs.stages.segmentation import masks as masks_mod

    folder, model = Path(folder), Path(model)
    if not model.is_file():
        raise FileNotFoundError(f"model file not found: {model}")
    surfels = load_ply(model)
    train = train if train is not None else load_training_views(data)
    views = views if views is not None else load_dataset(data, split)
    mask_config = chromaticity if chromaticity is not None else masks_mod.ChromaticityConfig()
    settings = {"config": settings_dict(config), "masks": masks, "split": split}
    if masks == "chromaticity":
        settings["mask_config"] = settings_dict(mask_config)
    provenance = Provenance(dataset=dataset or dataset_ref(data),
                            inputs={"model": input_ref(model)}, settings=settings)
    _check_model_dataset(model, data, provenance.dataset)
    out = Output.open(folder, "segment", provenance, overwrite=overwrite, reuse=reuse,
                      inputs=[model, data], continue_flag="--resume")
    if out.complete:
        return StageRun(folder, False, 0.0, f"segment: {folder} is finished, with the same "
                        "dataset, model and settings; nothing to do")
    warn_other_backend(out, made_from=model)
    t0 = time.perf_counter()
    label_maps = masks_mod.masks_for(train, masks, mask_config)
    t_masks = time.perf_counter() - t0
    hooks = checkpoint_hooks(out, seg.FeatureState.from_checkpoint)
    # The training that earlier calls did (a continued stage): counted in seconds_stage as
    # seconds_train counts it, so a resumed stage reports its whole time.
    trained_before = 0.0 if hooks["state"] is None else hooks["state"].elapsed
    result = seg.segment_surfels(surfels, train.cameras, label_maps, config,
                                 min_label_fraction=label_fraction(config, masks),
                                 progress=progress, names=[v.name for v in train.views],
                                 split_support=(config.support_split
                                                if masks == "chromaticity" else "off"),
                                 **hooks)
    t_stage = time.perf_counter() - t0 + trained_before
    stems = [Path(v.name).name for v in views.views]
    with out:
        out.claim("model.ply", *(f"segments/{s}{x}.png" for s in stems
                                 for x in ("", "_overlay")), "segmentation.json")
        save_ply(folder / "model.ply", result.surfels)
        colors = seg_maps.segment_colors(result.k)
        maps = []
        for stem, v in tqdm(list(zip(stems, views.views, strict=True)), desc="segment maps",
                            unit="view", disable=not progress):
            m = seg_maps.render_segment_map(result.surfels, result.segments, result.k, v.camera,
                                       config.segment_alpha)
            maps.append(m)
            write_png(folder / "segments" / f"{stem}.png", colors[m])
            write_png(folder / "segments" / f"{stem}_overlay.png", overlay(v.image, m, colors))
        report = {"model": str(model), "data": str(data), "masks": masks, "preset": preset,
                  "config": to_dict(config), "k": result.k, "surfels": surfels.count,
                  "seconds_masks": t_masks, "seconds_train": result.train.seconds,
                  "seconds_stage": t_stage, "split": split, "views": len(maps)}
        if result.k_scores:
            report["k_silhouette"] = {str(k): v for k, v in result.k_scores.items()}
        if result.planes:  # the segments' plane fits (SegmentationConfig.planes)
            report["planes"] = result.planes
        if result.support:  # the support's plane (SegmentationConfig.support_split)
            report["support_split"] = result.support
        if all(v.material is not None for v in views.views):
            report.update(_segmentation_metrics(maps, views))
        write_json(folder / "segmentation.json", report)
        out.finish()
    summary = {k: round(v, 4) for k, v in report.get("metrics", {}).items()
               if isinstance(v, float)}
    line = (f"segmented {surfels.count} surfels into {result.k} segments in {t_stage:.1f} s; "
            f"wrote {folder} {json.dumps(summary) if summary else ''}").rstrip()
    return StageRun(folder, True, time.perf_counter() - t0, line)


def _segmentation_metrics(maps: list, views) -> dict:
    """ARI / mIoU against the material ids, and the lit/shadowed check of the base."""
    from mi_shadowgs.stages.segmentation import metrics as seg_metrics

    gt = [v.material for v in views.views]
    out = {"metrics": seg_metrics.evaluate_maps(maps, gt)}
    mats = (views.info or {}).get("materials") or []
    base = next((m["id"] for m in mats if m.get("name") == "base"), None)
    if base is None:
        base = int(max(int(g.max()) for g in gt))
    if all(v.visibility is not None for v in views.views):
        try:
            out["base_shadow"] = seg_metrics.shadow_consistency(
                maps, gt, [v.visibility for v in views.views], int(base))
        except seg_metrics.NoPixelsToCompare as exc:  # no shadowed base pixel in these views
            out["base_shadow"] = {"error": str(exc)}
    return out
