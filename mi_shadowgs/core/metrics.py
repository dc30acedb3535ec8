"""Evaluation metrics in NumPy float64 (every stage's evaluation uses these).

Images are [H, W, C] arrays (linear RGB in [0, 1] unless stated); masks [H, W] bool.
"""

from __future__ import annotations

import numpy as np

from mi_shadowgs.core.losses import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW, gaussian_window


def _as_image(a, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3:
        raise ValueError(f"{what}: expected an image [H, W, C], got shape {a.shape}")
    return a


def _pair(a, b, what: str) -> tuple[np.ndarray, np.ndarray]:
    a, b = _as_image(a, what), _as_image(b, what)
    if a.shape != b.shape:
        raise ValueError(f"{what}: shapes differ: {a.shape} vs {b.shape}")
    return a, b


def mse(a, b, mask=None) -> float:
    a, b = _pair(a, b, "mse")
    d = (a - b) ** 2
    if mask is not None:
        d = d[np.asarray(mask, bool)]
    return float(np.mean(d)) if d.size else float("nan")


def psnr(a, b, mask=None, peak: float = 1.0) -> float:
    """PSNR in dB (``peak`` = the signal range); over ``mask`` pixels when given."""
    m = mse(a, b, mask)
    return float(10.0 * np.log10(peak * peak / max(m, 1e-30)))


def _blur(x: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Separable zero-padded convolution of [H, W, C] along W then H."""
    r = len(taps) // 2
    h, w, _ = x.shape
    p = np.pad(x, ((0, 0), (r, r), (0, 0)))
    out = sum(t * p[:, k:k + w] for k, t in enumerate(taps))
    p = np.pad(out, ((r, r), (0, 0), (0, 0)))
    return sum(t * p[k:k + h] for k, t in enumerate(taps))


def ssim_map(a, b, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """Per-pixel SSIM [H, W, C] (Gaussian window, zero padding, as the training loss)."""
    a, b = _pair(a, b, "ssim")
    g = gaussian_window(window, sigma)
    mu_a, mu_b = _blur(a, g), _blur(b, g)
    saa = _blur(a * a, g) - mu_a ** 2
    sbb = _blur(b * b, g) - mu_b ** 2
    sab = _blur(a * b, g) - mu_a * mu_b
    return (((2 * mu_a * mu_b + SSIM_C1) * (2 * sab + SSIM_C2))
            / ((mu_a ** 2 + mu_b ** 2 + SSIM_C1) * (saa + sbb + SSIM_C2)))


def ssim(a, b) -> float:
    return float(np.mean(ssim_map(a, b)))


def normal_angles_deg(pred, gt, mask) -> np.ndarray:
    """Angles in degrees [M] between normal maps [H, W, 3] over ``mask`` pixels.

    Predicted normals are renormalised (rendered normals are alpha-weighted sums); a zero
    predicted normal counts as 90 degrees (no information).
    """
    p, g = _pair(pred, gt, "normal error")
    m = np.asarray(mask, bool)
    p, g = p[m], g[m]
    pn = np.linalg.norm(p, axis=-1)
    gn = np.linalg.norm(g, axis=-1)
    cos = np.einsum("ij,ij->i", p, g) / np.maximum(pn * gn, 1e-30)
    cos = np.where(pn > 0, cos, 0.0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def depth_errors(pred, gt, mask) -> dict[str, float]:
    """Absolute z-depth errors over ``mask`` pixels: mean, median and mean relative."""
    p = np.asarray(pred, np.float64).reshape(np.shape(mask))
    g = np.asarray(gt, np.float64).reshape(np.shape(mask))
    m = np.asarray(mask, bool) & (g > 0)
    if not m.any():
        return {"mean_abs": float("nan"), "median_abs": float("nan"), "mean_rel": float("nan")}
    e = np.abs(p[m] - g[m])
    return {"mean_abs": float(e.mean()), "median_abs": float(np.median(e)),
            "mean_rel": float(np.mean(e / g[m]))}


def mask_iou(pred, gt) -> float:
    """Intersection over union of two boolean masks [H, W] (1.0 when both are empty)."""
    p, g = np.asarray(pred, bool), np.asarray(gt, bool)
    if p.shape != g.shape:
        raise ValueError(f"mask IoU: shapes differ: {p.shape} vs {g.shape}")
    union = np.logical_or(p, g).sum()
    return 1.0 if union == 0 else float(np.logical_and(p, g).sum() / union)
