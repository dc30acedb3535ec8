"""Evaluation of a fitted model (Sec. V-A3): relit test views measured against the dataset's
ground truth, each metric only where the dataset has what it needs.

``metrics``: the metrics themselves (albedo, light cosine, shadow IoU; NumPy only);
``lpips``: the LPIPS network; ``evaluate``: a fit evaluated on a dataset; ``figures``: the
report's figures; ``runner``: one variant of a run evaluated into its output folder.
"""

from __future__ import annotations

from mi_shadowgs.stages.evaluation.evaluate import (
    METRIC_NEEDS,
    check_evaluation_inputs,
    evaluate_decomposition,
    ground_truth,
    scored_pixels,
)
from mi_shadowgs.stages.evaluation.figures import light_map_image, write_figures
from mi_shadowgs.stages.evaluation.runner import evaluate_variant

__all__ = [
    "METRIC_NEEDS",
    "check_evaluation_inputs",
    "evaluate_decomposition",
    "evaluate_variant",
    "ground_truth",
    "light_map_image",
    "scored_pixels",
    "write_figures",
]
