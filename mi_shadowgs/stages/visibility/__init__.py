"""Stage 3: pixelwise directional visibility (Sec. III-C) from shadow maps rasterized from
the surfels' depth, one per light direction, reused by every view.

``shadow_maps``: config, shadow cameras, maps and lookups; ``lamp_maps``: the maps of local
lights (perspective from the lamp, soft from its disc); ``baselines``: the ray-traced and
other visibility estimates it is compared with (validation).
"""

from __future__ import annotations

from mi_shadowgs.stages.visibility.lamp_maps import lamp_arguments
from mi_shadowgs.stages.visibility.shadow_maps import (
    SceneBounds,
    ShadowMaps,
    VisibilityConfig,
    point_visibility,
    render_shadow_maps,
    view_visibility,
)

__all__ = [
    "SceneBounds",
    "ShadowMaps",
    "VisibilityConfig",
    "lamp_arguments",
    "point_visibility",
    "render_shadow_maps",
    "view_visibility",
]
