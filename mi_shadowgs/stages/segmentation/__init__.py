"""Stage 2: material segmentation (Sec. III-B): contrastive per-surfel features trained on
2D label maps, then K-means into one segment per surfel.

``features``: config, losses, training and K-means; ``maps``: the segment maps of views;
``metrics``: the segment metrics; ``masks``: the label maps (material ids or chromaticity
regions); ``runner``: ``run_segmentation``.
"""

from __future__ import annotations

from mi_shadowgs.stages.segmentation.features import (
    SegmentationConfig,
    SegmentationResult,
    segment_surfels,
)
from mi_shadowgs.stages.segmentation.masks import masks_for
from mi_shadowgs.stages.segmentation.runner import label_fraction, run_segmentation

__all__ = [
    "SegmentationConfig",
    "SegmentationResult",
    "masks_for",
    "run_segmentation",
    "segment_surfels",
    "label_fraction",
]
