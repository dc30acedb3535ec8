"""The method's five stages, one package each, in order: ``geometry`` (1), ``segmentation``
(2), ``visibility`` (3), ``material`` (4), ``relight`` (5); then what uses a fitted model:
``evaluation`` (metrics against ground truth), ``export`` (splat PLYs, mesh) and ``viewer``
(the browser viewer). Each package names its public API (its config, its maths,
its runner); a package imports only the ones before it. Beside them, ``common`` (what every
stage shares) and ``render`` (a surfel model's views, ``mi-shadowgs render``, for any model).
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
