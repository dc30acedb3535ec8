"""The method's five stages, one package each, in order: ``geometry`` (1), ``segmentation``
(2), ``visibility`` (3), ``material`` (4), ``relight`` (5). Each package names its public API
(``get_config(preset)``, its maths, its runner); a stage imports only earlier stages.
"""

from mi_shadowgs.stages import (
    evaluation,
    export,
    geometry,
    material,
    relight,
    segmentation,
    viewer,
    visibility,
)

__all__ = ["geometry", "segmentation", "visibility", "material", "relight", "evaluation",
           "export", "viewer"]
