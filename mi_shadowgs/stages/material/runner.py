"""Stage 4's runner: fit the PBR materials, light map and indirect light of a segmented
surfel model on a dataset's training views, with visibility from the surfels' shadow maps
(stage 3), and save the fit (``fit_or_reuse``). ``mi_shadowgs.pipeline`` calls it once per
variant (full and the ablations).
"""

from __future__ import annotations

import json
import time

from mi_shadowgs.stages.material.config import MaterialConfig
from mi_shadowgs.stages.material.fit import fit_material
from mi_shadowgs.stages.material.outputs import FIT_FILES, fit_from_files, save_fit
from mi_shadowgs.stages.material.state import MaterialResult, MaterialState
from mi_shadowgs.stages.visibility import shadow_maps
from mi_shadowgs.stages.visibility.shadow_maps import VisibilityConfig


def occluder_bounds(surfels, cameras, quantile: float) -> shadow_maps.SceneBounds:
    """Shadow-map bounds from the surfels themselves (paper: their centroid), robust to
    floaters through ``quantile``."""
    pos = surfels.to_numpy()["position"]
    return shadow_maps.SceneBounds.from_points(pos, cameras, quantile)


def decompose(surfels, train, config: MaterialConfig, vis_config: VisibilityConfig,
              bounds: shadow_maps.SceneBounds, progress: bool = True, gains=None,
              past=None, **checkpoints) -> MaterialResult:
    """Stage 4 on the training views of ``train`` (a loaded Dataset) with the shadow maps of
    ``vis_config``; ``gains``: stage 1's RGB gain [3] per training view, held, or None;
    ``past``: the pixels left out (``fit_material``); ``checkpoints``: ``state`` and
    ``on_checkpoint`` of ``fit_material``."""
    return fit_material(surfels, train.cameras, [v.image for v in train.views],
                        [v.mask for v in train.views], config, bounds, vis_config,
                        progress=progress, gains=gains, past=past, **checkpoints)


def fit_or_reuse(out, surfels, train, config: MaterialConfig, vis_config: VisibilityConfig,
                 bounds: shadow_maps.SceneBounds, progress: bool = True, gains=None,
                 past=None) -> tuple[MaterialResult, float]:
    """Stage 4 into the open ``Output`` ``out``: (result, fit seconds). A reused output that
    holds a finished fit (``FIT_FILES``) is read back instead of fitted again; otherwise the
    fit runs with checkpoints in ``out`` (continuing one it holds) and is saved before any
    evaluation, so that a run that fails in evaluation keeps it. ``gains`` and ``past``: as
    ``decompose``'s."""
    from mi_shadowgs.stages.common import checkpoint_hooks

    files = [out.folder / name for name in FIT_FILES]
    if out.reused and all(f.is_file() for f in files):
        res = fit_from_files(*files[:3], use_visibility=config.use_visibility)
        return res, json.loads(files[3].read_text())["fit_s"]
    checkpoints = checkpoint_hooks(out, MaterialState.from_checkpoint)
    t0 = time.perf_counter()
    res = decompose(surfels, train, config, vis_config, bounds, progress, gains, past,
                    **checkpoints)
    fit_s = time.perf_counter() - t0
    save_fit(out, res, vis_config, fit_s)
    return res, fit_s
