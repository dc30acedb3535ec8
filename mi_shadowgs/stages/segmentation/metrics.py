"""Stage 2's metrics against material ids: the adjusted Rand index, the mIoU of the best
one-to-one match, and the lit/shadowed check of one material's pixels."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _pairs(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return x * (x - 1.0) / 2.0


def contingency(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Contingency table [n_a_classes, n_b_classes] of two label arrays of equal size."""
    a = np.asarray(a).ravel()
    b = np.asarray(b).ravel()
    if a.shape != b.shape:
        raise ValueError(f"contingency: label arrays differ in size ({a.size} vs {b.size})")
    _, ia = np.unique(a, return_inverse=True)
    _, ib = np.unique(b, return_inverse=True)
    table = np.zeros((ia.max(initial=-1) + 1, ib.max(initial=-1) + 1), np.int64)
    np.add.at(table, (ia, ib), 1)
    return table


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """Adjusted Rand index (Hubert and Arabie) of two labelings of the same items."""
    t = contingency(a, b)
    n = t.sum()
    if n < 2:
        return 1.0
    index = _pairs(t).sum()
    sa, sb = _pairs(t.sum(1)).sum(), _pairs(t.sum(0)).sum()
    expected = sa * sb / _pairs(n)
    top = 0.5 * (sa + sb)
    if top == expected:  # both labelings are one cluster (or all singletons): identical
        return 1.0
    return float((index - expected) / (top - expected))


def miou_hungarian(pred: np.ndarray, gt: np.ndarray) -> tuple[float, dict[int, int]]:
    """Mean IoU over the ground-truth classes after the one-to-one matching of predicted to
    ground-truth classes that maximises the summed IoU; unmatched ground-truth classes
    count 0. Returns (mIoU, {gt class: matched pred class})."""
    from scipy.optimize import linear_sum_assignment

    pred = np.asarray(pred).ravel()
    gt = np.asarray(gt).ravel()
    if pred.shape != gt.shape:
        raise ValueError(f"miou_hungarian: {pred.size} predictions for {gt.size} labels")
    gv, pv = np.unique(gt), np.unique(pred)
    inter = contingency(gt, pred).astype(np.float64)  # [gt classes, predicted classes]
    union = inter.sum(1, keepdims=True) + inter.sum(0, keepdims=True) - inter
    iou = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
    rows, cols = linear_sum_assignment(-iou)
    return (float(iou[rows, cols].sum() / max(gv.size, 1)),
            {int(gv[r]): int(pv[c]) for r, c in zip(rows, cols, strict=True)})


def evaluate_maps(pred_maps: Sequence[np.ndarray],
                  gt_maps: Sequence[np.ndarray]) -> dict[str, float]:
    """ARI and Hungarian mIoU pooled over the pixels whose ground truth is not background
    (gt > 0); a predicted background (0) there counts as a class of its own."""
    p = np.concatenate([np.asarray(m).ravel() for m in pred_maps])
    g = np.concatenate([np.asarray(m).ravel() for m in gt_maps])
    keep = g > 0
    if not keep.any():
        raise ValueError("evaluate_maps: the ground truth has no foreground pixel")
    miou, _ = miou_hungarian(p[keep], g[keep])
    return {"ari": adjusted_rand_index(p[keep], g[keep]), "miou": miou,
            "pixels": int(keep.sum()), "pred_background": float((p[keep] == 0).mean())}


class NoPixelsToCompare(ValueError):
    """``shadow_consistency``: the surface has no lit or no shadowed pixel in the views (a
    fact of the data, reported as such; any other error propagates)."""


def shadow_consistency(pred_maps: Sequence[np.ndarray], gt_maps: Sequence[np.ndarray],
                       visibility: Sequence[np.ndarray], label: int) -> dict[str, float]:
    """Do shadowed and lit pixels of the surface with ground-truth id ``label`` fall in one
    segment? Shadowed: occluded from some training light (visibility < 0.5); lit: visible
    from all. Returns the segment taken by most lit pixels and the fractions of lit and of
    shadowed pixels that carry it."""
    p = np.concatenate([np.asarray(m).ravel() for m in pred_maps])
    g = np.concatenate([np.asarray(m).ravel() for m in gt_maps])
    v = np.concatenate([np.asarray(m).reshape(-1, np.asarray(m).shape[-1]).min(-1)
                        for m in visibility])
    on = g == label
    lit, shadow = on & (v >= 0.5), on & (v < 0.5)
    if not lit.any() or not shadow.any():
        raise NoPixelsToCompare(f"shadow_consistency: surface {label} has no "
                         f"{'lit' if not lit.any() else 'shadowed'} pixel in these views")
    major = int(np.bincount(p[lit]).argmax())
    return {"segment": major, "lit_fraction": float((p[lit] == major).mean()),
            "shadow_fraction": float((p[shadow] == major).mean()),
            "lit_pixels": int(lit.sum()), "shadow_pixels": int(shadow.sum())}
