"""Stage 5: relighting and evaluation (Sec. III-E, V-A3): the fitted model rendered under new
lights with shadows recomputed from the surfels, and measured against ground truth.

``render``: config, light sets and relit views; ``evaluation``: the metrics (albedo, light
cosine, shadow IoU); ``evaluate``: evaluate a decomposition on a dataset and write its
figures and light JSON.
"""

from __future__ import annotations

from mi_shadowgs.stages.relight.evaluate import (
    check_evaluation_inputs,
    evaluate_decomposition,
    light_map_image,
    write_figures,
)
from mi_shadowgs.stages.relight.render import (
    PRESETS,
    RelightConfig,
    RelightModel,
    directional_light_set,
    get_config,
    lights_from_json,
    relight_view,
    relight_views,
)

__all__ = [
    "PRESETS",
    "RelightConfig",
    "RelightModel",
    "check_evaluation_inputs",
    "directional_light_set",
    "evaluate_decomposition",
    "get_config",
    "light_map_image",
    "lights_from_json",
    "relight_view",
    "relight_views",
    "write_figures",
]
