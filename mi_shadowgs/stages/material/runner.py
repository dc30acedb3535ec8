"""Stage 4's runner: fit the PBR materials, light map and indirect light of a segmented
surfel model on a dataset's training views, with visibility from the surfels' shadow maps
(stage 3). ``mi_shadowgs.pipeline`` calls it once per variant (full and the ablations).
"""

from __future__ import annotations

import dataclasses

from mi_shadowgs.stages.material import fit
from mi_shadowgs.stages.visibility import shadow_maps


def occluder_bounds(surfels, cameras, quantile: float) -> shadow_maps.SceneBounds:
    """Shadow-map bounds from the surfels themselves (paper: their centroid), robust to
    floaters through ``quantile``."""
    pos = surfels.to_numpy()["position"]
    return shadow_maps.SceneBounds.from_points(pos, cameras, quantile)


def decompose(surfels, train, config: fit.MaterialConfig,
              visibility: shadow_maps.VisibilityConfig, bounds: shadow_maps.SceneBounds,
              labels: str = "material", progress: bool = True,
              **checkpoints) -> fit.MaterialResult:
    """Stage 4 on the training views of ``train`` (a loaded Dataset), on segments labelled
    from ``labels`` (stage 2's label source); ``checkpoints``: ``state`` and
    ``on_checkpoint`` of ``fit_material``."""
    changed = fit.label_source_overrides(config, labels)
    if changed:
        config = dataclasses.replace(config, **changed)
    return fit.fit_material(surfels, train.cameras, [v.image for v in train.views],
                            [v.mask for v in train.views], config, bounds, visibility,
                            progress=progress, **checkpoints)
