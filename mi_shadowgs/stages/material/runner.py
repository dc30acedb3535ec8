"""Stage 4's runner: fit the PBR materials, light map and indirect light of a segmented
surfel model on a dataset's training views, with visibility from the surfels' shadow maps
(stage 3). ``mi_shadowgs.pipeline`` calls it once per variant (full and the ablations).
"""

from __future__ import annotations

from mi_shadowgs.config import with_overrides
from mi_shadowgs.stages.material import fit
from mi_shadowgs.stages.material.config import MaterialConfig, get_config
from mi_shadowgs.stages.material.state import MaterialResult
from mi_shadowgs.stages.visibility import shadow_maps


def occluder_bounds(surfels, cameras, quantile: float) -> shadow_maps.SceneBounds:
    """Shadow-map bounds from the surfels themselves (paper: their centroid), robust to
    floaters through ``quantile``."""
    pos = surfels.to_numpy()["position"]
    return shadow_maps.SceneBounds.from_points(pos, cameras, quantile)


def material_config(preset: str, overrides: dict | None = None) -> MaterialConfig:
    return with_overrides(get_config(preset), overrides, "material")


def decompose(surfels, train, preset: str, bounds: shadow_maps.SceneBounds,
              overrides: dict | None = None, progress: bool = True,
              **checkpoints) -> MaterialResult:
    """Stage 4 on the training views of ``train`` (a loaded Dataset); ``checkpoints``:
    ``state`` and ``on_checkpoint`` of ``fit_material``."""
    cfg = material_config(preset, overrides)
    return fit.fit_material(surfels, train.cameras, [v.image for v in train.views],
                            [v.mask for v in train.views], cfg, bounds,
                            shadow_maps.get_config(preset), progress=progress, **checkpoints)
