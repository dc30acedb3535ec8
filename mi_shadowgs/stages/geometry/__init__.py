"""Stage 1: 2DGS geometry (Sec. III-A): surfels fitted to the views with photometric, mask,
normal-consistency and depth-distortion losses, densified and pruned as they train.

``config``: the settings; ``train``: losses and the optimisation loop; ``densify``:
clone/split/prune; ``runner``: ``run_geometry``, which writes the stage's files.
"""

from __future__ import annotations

from mi_shadowgs.stages.geometry.config import GeometryConfig
from mi_shadowgs.stages.geometry.runner import run_geometry
from mi_shadowgs.stages.geometry.train import TrainState, evaluate, render_view, train_geometry

__all__ = [
    "GeometryConfig",
    "TrainState",
    "evaluate",
    "render_view",
    "run_geometry",
    "train_geometry",
]
