"""The report's figures of an evaluated fit: per test view the decomposition beside its
ground truth with error maps (``write_figures``), and the light map in the paper's block
view (``light_map_image``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_shadowgs.core.directions import map_to_blocks
from mi_shadowgs.stages.relight.previews import display


def figure_picks(n: int, count: int) -> list[int]:
    """``count`` view indices of ``n`` views, spread over them (the first is 0)."""
    return sorted({int(round(i * n / max(count, 1))) % n for i in range(count)})


def _error(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Colour-mapped |est - gt| of two linear images, compared as displayed (sRGB)."""
    from mi_shadowgs.io.images import linear_to_srgb
    from mi_shadowgs.io.plots import error_colors

    return error_colors(linear_to_srgb(display(est)), linear_to_srgb(display(gt)))


def light_map_image(radiance: np.ndarray, block: int = 8) -> np.ndarray:
    """The paper's 22 x 12 block view of a grid light map, normalised, upscaled [H, W, 3]."""
    blocks = map_to_blocks(np.asarray(radiance, np.float64))  # [12, 22]
    peak = blocks.max()
    img = blocks / peak if peak > 0 else blocks
    img = np.repeat(np.repeat(img, block, 0), block, 1)
    return np.repeat(img[..., None], 3, axis=-1)


def write_figures(folder: Path, test, images: dict, count: int,
                  segments: dict[str, np.ndarray] | None = None) -> dict:
    """PNG figures of the first ``count`` test views (spread over the split); returns the
    report grid (rows of relative paths). The decomposition: input, albedo, roughness,
    metallic, normals, irradiance, the visibility of the strongest fitted lights and the
    segments (``segments``: view stem -> sRGB uint8 [H, W, 3], e.g. stage 2's maps); each
    ground truth the dataset has beside its estimate, with its error map: |estimate -
    ground truth| as displayed (sRGB), colour-mapped by ``io.plots.error_colors`` (0 to
    ``io.plots.ERROR_MAX``)."""
    from mi_shadowgs.io.images import write_png

    picks = figure_picks(len(test.views), count)
    relits = sorted(k[len("relit/"):] for k in images if k.startswith("relit/"))
    has_alb, has_irr = "gt/albedo" in images, "gt/irradiance" in images
    vis_names = [f"visibility az {az:.0f} el {el:.0f}"
                 for az, el in images.get("visibility_lights", [])]
    columns = ["input", "albedo"] + (["albedo (GT)", "albedo error"] if has_alb else [])
    columns += ["roughness", "metallic", "normal", "irradiance"]
    columns += ["irradiance (GT)"] if has_irr else []
    columns += vis_names
    segments = segments or {}
    if any(Path(test.views[i].name).name in segments for i in picks):
        columns.append("segments")
    for name in relits:
        columns += [f"relit {name}", f"relit {name} (GT)", f"relit {name} error"]
    # One exposure for estimate and ground truth of a kind, so that they compare.
    irr_scale = float(np.percentile(images["irradiance"], 99)) or 1.0
    gt_irr_scale = (float(np.percentile(images["gt/irradiance"], 99)) or 1.0 if has_irr
                    else 1.0)
    linear_cols = ("irradiance", "roughness", "metallic", "normal", "visibility", "segments")
    rows = []
    for i in picks:
        stem = Path(test.views[i].name).name
        cells = {"input": test.views[i].image, "albedo": images["albedo"][i],
                 "roughness": images["roughness"][i], "metallic": images["metallic"][i],
                 "normal": np.where(np.any(images["normal"][i] != 0, -1, keepdims=True),
                                    images["normal"][i] * 0.5 + 0.5, 0.0),
                 "irradiance": display(images["irradiance"][i], irr_scale)}
        if has_alb:
            cells["albedo (GT)"] = images["gt/albedo"][i]
            cells["albedo error"] = _error(images["albedo"][i], images["gt/albedo"][i])
        if has_irr:
            cells["irradiance (GT)"] = display(images["gt/irradiance"][i], gt_irr_scale)
        for k, col in enumerate(vis_names):
            cells[col] = images["visibility"][i][..., k]
        if "segments" in columns:
            seg = segments.get(stem)
            cells["segments"] = (np.zeros(test.views[i].image.shape) if seg is None else
                                 np.asarray(seg, np.float64)[..., :3] / 255.0)
        for name in relits:
            cells[f"relit {name}"] = images[f"relit/{name}"][i]
            cells[f"relit {name} (GT)"] = images[f"gt/relit/{name}"][i]
            cells[f"relit {name} error"] = _error(images[f"relit/{name}"][i],
                                                  images[f"gt/relit/{name}"][i])
        paths = []
        for col in columns:
            fname = f"{stem}_{col.replace(' ', '_').replace('(', '').replace(')', '')}.png"
            srgb = not (col.startswith(linear_cols) or col.endswith(" error"))
            write_png(folder / fname, display(cells[col]), srgb=srgb)
            paths.append(fname)
        rows.append({"label": stem, "cells": paths})
    est = light_map_image(images["light_map"])
    if "gt/light_map" in images:
        gap = np.ones((est.shape[0], 4, 3))
        est = np.concatenate([est, gap, light_map_image(images["gt/light_map"])], axis=1)
    write_png(folder / "light_map.png", est, srgb=False)
    return {"columns": columns, "rows": rows}
