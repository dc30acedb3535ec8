"""Relit previews of a fitted model under standard lights (a light turntable and env maps),
for data with or without ground truth: what the run's report shows beside the evaluation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.visibility.shadow_maps import SceneBounds, VisibilityConfig


def display(img: np.ndarray, scale: float | None = None) -> np.ndarray:
    """Linear [H, W] or [H, W, 3] -> [H, W, 3] in [0, 1] (optionally divided by scale)."""
    a = np.asarray(img, np.float64)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if scale:
        a = a / scale
    return np.clip(a, 0.0, 1.0)


TURNTABLE_LIGHTS = 8  # azimuths of the previews' light turntable
TURNTABLE_ELEVATION = 45.0


def write_previews(folder: Path, result, cameras, bounds: SceneBounds,
                   vis_config: VisibilityConfig, relight_config: relight.RelightConfig,
                   envmaps=(), cache: relight.RelightCache | None = None) -> dict:
    """Relit previews of a fit under standard lights, for data with or without ground truth:
    a turntable of ``TURNTABLE_LIGHTS`` directional lights at ``TURNTABLE_ELEVATION``
    degrees and every env map of ``envmaps`` ((name, file, scale)), for each of ``cameras``.
    ``result``: stage 4's ``MaterialResult``; ``vis_config`` and ``relight_config``: the
    shadow maps and env-map sampling to render with.

    Exposure: each preview light gives an upward-facing surface the irradiance the fitted
    light gives it (albedo and light are known only up to a common factor, so the fitted
    light is the only scale there is). ``cache``: shadow maps and views' rasterizations
    already made (e.g. by the evaluation's relightings). Writes
    ``preview_<view>_<light>.png`` and one strip per view; returns {"strips": [{"title",
    "file"}], "lights": [...]} for the report.
    """
    from mi_shadowgs.core.envmap import load_envmap as load_emitter
    from mi_shadowgs.io.images import write_png

    vcfg, rcfg = vis_config, relight_config
    fitted = result.light.light_set()
    model = relight.RelightModel(result.surfels, result.specular, result.use_visibility,
                                 fitted, vcfg.receiver_band)
    e_up = relight.upward_irradiance(fitted)
    setups = []
    for name, ls in relight.standard_turntable(TURNTABLE_LIGHTS, TURNTABLE_ELEVATION):
        up = relight.upward_irradiance(ls)
        setups.append(("turntable", name, relight.scale_light_set(ls, e_up / up)))
    cache = cache or relight.RelightCache()  # the env maps share the grid's shadow maps
    for name, path, scale in envmaps:
        ls = relight.grid_light_set(cache.envmap_radiance(load_emitter(path, scale), rcfg),
                                    rcfg.n_directions)
        up = relight.upward_irradiance(ls)
        if ls.count and up > 0:
            setups.append(("envmap", name, relight.scale_light_set(ls, e_up / up)))
    strips, lights = [], []
    for cam_i, cam in enumerate(cameras):
        for kind in ("turntable", "envmap"):
            frames = []
            for k, name, ls in (x for x in setups if x[0] == kind):
                maps = cache.shadow_maps(model, ls, bounds, vcfg)
                img = relight.relight_view(model, cam, ls, maps,
                                           relight.indirect_factor(model, ls, rcfg),
                                           only_rgb=True,
                                           view=cache.view_buffers(model, cam)[0])["rgb"]
                fname = f"preview_{cam_i}_{kind}_{name}.png"
                write_png(folder / fname, display(img))
                frames.append(display(img))
                if cam_i == 0:
                    lights.append({"kind": k, "name": name, "directions": ls.count})
            if frames:
                gap = np.ones((frames[0].shape[0], 2, 3))
                strip = np.concatenate(sum(([f, gap] for f in frames), [])[:-1], axis=1)
                fname = f"preview_{cam_i}_{kind}.png"
                write_png(folder / fname, strip)
                names = [n for k, n, _ in setups if k == kind]
                title = (f"light turntable: {TURNTABLE_LIGHTS} azimuths at "
                         f"{TURNTABLE_ELEVATION:.0f} deg elevation ({', '.join(names)})"
                         if kind == "turntable" else f"env maps: {', '.join(names)}")
                strips.append({"title": title, "file": fname})
    return {"strips": strips, "lights": lights}
