"""Stage 5, relighting (Sec. III-E): the fitted model rendered under new lights, with shadows
recomputed from the surfels.

``render``: config, light sets and relit views; ``previews``: relit previews of a fit under
standard lights (the run's report); ``runner``: ``mi-shadowgs relight`` on a finished run.
"""

from __future__ import annotations

from mi_shadowgs.stages.relight.previews import write_previews
from mi_shadowgs.stages.relight.render import (
    RelightConfig,
    RelightModel,
    directional_light_set,
    lights_from_json,
    point_light_set,
    relight_view,
    relight_views,
)

__all__ = [
    "RelightConfig",
    "RelightModel",
    "directional_light_set",
    "lights_from_json",
    "point_light_set",
    "relight_view",
    "relight_views",
    "write_previews",
]
