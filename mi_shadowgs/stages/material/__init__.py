"""Stage 4: the PBR material and light decomposition (Sec. III-D): Cook-Torrance albedo,
roughness and metallic per surfel (averaged per segment), a 128-direction light map and
indirect SH, fitted to the training views with stage 3's visibility.

``fit``: config, loss and the optimisation loop; ``runner``: ``decompose`` on a dataset.
"""

from __future__ import annotations

from mi_shadowgs.stages.material.fit import (
    PRESETS,
    MaterialConfig,
    MaterialResult,
    MaterialState,
    fit_material,
    get_config,
)
from mi_shadowgs.stages.material.runner import decompose, occluder_bounds

__all__ = [
    "MaterialConfig",
    "MaterialResult",
    "MaterialState",
    "PRESETS",
    "decompose",
    "fit_material",
    "get_config",
    "occluder_bounds",
]
