"""Stage-5 evaluation (paper Sec. V-A3): albedo, light, shadows, relighting, render time.

NumPy float64 over [V, H, W, ...] stacks of test views; PSNR and SSIM are those of
``mi_shadowgs.core.metrics`` (SSIM: 11x11 Gaussian window, sigma 1.5), LPIPS that of
``lpips.py`` (AlexNet v0.1 on sRGB display images, background set to 0 like SSIM). LPIPS is
``None``, with the reason in ``lpips_skipped``, where it cannot be computed: views smaller
than ``lpips.MIN_SIZE`` or the ``eval`` extra not installed.

Albedo and shadows are scored on ``surface_pixels``: the test mask where the ground truth
has a surface (material id > 0). The photo's mask is its coverage, while the ground-truth
buffers hold the hit of the pixel centre's ray, which misses at some silhouette pixels
(9-40 of ~250k masked pixels on three rows of the six-scene table, 970 on ficus-low). Their
albedo 0 cost bunny-low 8 dB of a 53.5 dB albedo figure. Relit images are scored on the
whole mask.

- **Albedo**: the estimate is the albedo of the surface each pixel sees
  (``surface_albedo``): the rasterized albedo is alpha-blended, so at a pixel the fit
  covers in part it is the surface's albedo times the coverage, while the ground truth is
  the albedo at the pixel centre's hit, whatever the coverage. Dividing by the pixel's
  alpha compares like with like; compared as rendered, the silhouette's pixels alone cost
  the bunny 11 dB. It is then aligned to
  the ground truth by a per-channel scale per region
  (the paper extends the usual single-object alignment to every object): for each region id
  r > 0 (the dataset's material ids: each object part and the base) and channel c,
  s_rc = median over the region's pixels in all evaluated views of gt_c / est_c (pixels with
  est_c > ``EST_MIN``), then est_c *= s_rc there. PSNR per view over the mask pixels, SSIM
  per view on both images with the background set to 0, each averaged over the views.
  Beside it, ``psnr_global``: the same PSNR with one per-channel scale over all mask pixels
  (the relighting's alignment). Per-region scales forgive a wrong hue or brightness between
  regions (a fit whose regions are all grey can score 34 dB); one global scale does not.
- **Light cosine**: cosine between the estimated and the ground-truth light distributions,
  each a set of directions with their irradiance (RGB reduced to the mean: the estimated
  light is white), smoothed by the kernel k(d, e) = exp(kappa (d.e - 1)), so that
  <f, g> = sum_ij f_i g_j k(d_i, e_j). Putting each light into its nearest grid cell first
  (``light_map_cosine``, kept for reference) made the figure jump from 1 to ~0.2 when a light
  moved a fraction of a degree across a cell border. With the kernel a perfect fit scores 1.0
  and a 1-degree error costs ~0.005. Beside it: each true light's angular error to the fitted
  light it is matched with (Hungarian matching on angles), and the share of the fitted
  irradiance in unmatched (spurious) lights. A fitted lamp's direction is taken from the
  true lamps' centre, as the truth's is (``seen_from``).
- **Shadow IoU**: a pixel is in shadow when its direct diffuse irradiance (white, summed
  over the lights) is below ``SHADOW_THRESHOLD`` times the median direct irradiance over
  the view's mask; the threshold is relative so that the estimate's global scale (albedo
  and light are only known up to a common factor) does not matter. IoU of the estimated and
  ground-truth shadow masks inside the mask, per view, averaged over views. Beside it,
  **shadow IoU (decided)**: the same over the pixels whose true irradiance is not within
  ``SHADOW_UNDECIDED_BAND`` of the threshold. There the truth itself is decided by round-off:
  on the default scene under the tuned pair one face of the block, lit by the strong light
  alone, lies at 1.0002 x the threshold (2.4% of the scored pixels), and a fit whose
  light ratio is 4% off flips it whole, moving a view's IoU by up to 0.2.
- **Relighting**: PSNR per view over the mask, SSIM and LPIPS per view with the background
  at 0.
"""

from __future__ import annotations

import numpy as np

from mi_shadowgs.core import metrics

EST_MIN = 1e-4  # estimated albedo below this carries no usable ratio
# A pixel the fit covers less than this holds no surface of the fit (a hole, scored as
# rendered): dividing its near-zero albedo by its alpha would only amplify stray splats.
ALPHA_MIN = 0.05
SHADOW_THRESHOLD = 0.5  # shadow: direct irradiance < 0.5 x the view's median over the mask
# "Shadow IoU (decided)" leaves out the pixels whose true irradiance is within 2% of the
# threshold: 2% is below what an albedo x light fit holds (its ratio of two lights moved 4-10%
# over seeds), above round-off.
SHADOW_UNDECIDED_BAND = 0.02


def _stack(x, what: str, ndim: int) -> np.ndarray:
    a = np.asarray(x, np.float64)
    if a.ndim == ndim - 1:
        a = a[None]
    if a.ndim != ndim:
        raise ValueError(f"{what}: expected {ndim - 1} or {ndim} dimensions, got {a.shape}")
    return a


def surface_albedo(albedo, alpha) -> np.ndarray:
    """The albedo of the surface each pixel sees [V, H, W, 3]: the alpha-blended albedo
    [V, H, W, 3] divided by the pixel's alpha [V, H, W] where that is >= ``ALPHA_MIN``, as
    rendered elsewhere."""
    a = _stack(albedo, "albedo estimate", 4)
    w = np.asarray(alpha, np.float64).reshape(a.shape[:3])[..., None]
    return np.where(w >= ALPHA_MIN, a / np.maximum(w, ALPHA_MIN), a)


def surface_pixels(mask, material=None) -> np.ndarray:
    """The test pixels the albedo and shadow metrics score [V, H, W]: inside the mask and,
    where the dataset has material ids, on a ground-truth surface (id > 0).

    The mask is the photo's coverage (alpha > 0.5), while the ground-truth buffers hold what
    the ray through the pixel's centre hits. At a silhouette pixel that ray can miss: the
    ground truth there is albedo 0 and irradiance 0, a black albedo and a false shadow that no
    estimate should be scored against. Without material ids the mask is used as it is.
    """
    m = np.asarray(mask, bool)
    if material is None:
        return m
    return m & (np.asarray(material).reshape(m.shape) > 0)


def albedo_scales(est, gt, regions, mask) -> dict[int, np.ndarray]:
    """Per-region per-channel median scale gt / est: {region id: [3]}."""
    est = _stack(est, "albedo estimate", 4)
    gt = _stack(gt, "albedo ground truth", 4)
    reg = np.asarray(regions).reshape(est.shape[:3])
    m = np.asarray(mask, bool).reshape(est.shape[:3])
    out = {}
    for r in np.unique(reg[m]):
        if r <= 0:
            continue
        sel = m & (reg == r)
        s = np.ones(3)
        for c in range(3):
            e, g = est[..., c][sel], gt[..., c][sel]
            ok = e > EST_MIN
            if ok.any():
                s[c] = float(np.median(g[ok] / e[ok]))
        out[int(r)] = s
    return out


def align_albedo(est, regions, scales: dict[int, np.ndarray]) -> np.ndarray:
    est = _stack(est, "albedo estimate", 4).copy()
    reg = np.asarray(regions).reshape(est.shape[:3])
    for r, s in scales.items():
        est[reg == r] *= s
    return est


def image_metrics(est, gt, mask) -> dict:
    """Mean over views of PSNR (mask pixels), SSIM and LPIPS (background zeroed in both),
    and the per-view values under ``per_view`` (views with an empty mask are left out)."""
    est = _stack(est, "estimate", 4)
    gt = _stack(gt, "ground truth", 4)
    m = np.asarray(mask, bool).reshape(est.shape[:3])
    if est.shape != gt.shape:
        raise ValueError(f"image metrics: shapes differ: {est.shape} vs {gt.shape}")
    psnrs, ssims = [], []
    keep = m.reshape(len(m), -1).any(axis=1)  # [V]
    for e, g, mm in zip(est[keep], gt[keep], m[keep], strict=True):
        psnrs.append(metrics.psnr(e, g, mm))
        ssims.append(metrics.ssim(e * mm[..., None], g * mm[..., None]))
    lpips_values, skipped = _lpips_per_view(est[keep], gt[keep], m[keep])
    out = {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)),
           "lpips": None if lpips_values is None else float(np.mean(lpips_values)),
           "per_view": {"psnr": psnrs, "ssim": ssims, "lpips": lpips_values}}
    if skipped:
        out["lpips_skipped"] = skipped
    return out


def _lpips_per_view(est, gt, mask) -> tuple[list[float] | None, str | None]:
    """LPIPS per view, or (None, why not)."""
    from mi_shadowgs.stages.evaluation import lpips

    if min(est.shape[1:3]) < lpips.MIN_SIZE:
        return (None, f"views of {est.shape[2]}x{est.shape[1]} px are below LPIPS's "
                      f"{lpips.MIN_SIZE} px")
    try:
        return lpips.lpips_views(est, gt, mask=mask).tolist(), None
    except lpips.LPIPSUnavailable as exc:
        return None, str(exc)


def albedo_metrics(est, gt, regions, mask) -> dict:
    """Image metrics of the per-region aligned albedo, plus ``psnr_global`` (mean over views
    of the PSNR with one per-channel scale, ``global_albedo_scale``) and both scales."""
    scales = albedo_scales(est, gt, regions, mask)
    out = image_metrics(align_albedo(est, regions, scales), gt, mask)
    out["scales"] = {str(k): v.tolist() for k, v in scales.items()}
    g = global_albedo_scale(est, gt, mask)
    m = np.asarray(mask, bool).reshape(np.shape(est)[:3])
    aligned = _stack(est, "albedo estimate", 4) * g
    gt = _stack(gt, "albedo ground truth", 4)
    out["psnr_global"] = float(np.mean([metrics.psnr(e, t, mm) for e, t, mm
                                        in zip(aligned, gt, m, strict=True) if mm.any()]))
    out["global_scale"] = g.tolist()
    return out


def global_albedo_scale(est, gt, mask) -> np.ndarray:
    """One per-channel median scale gt / est over all mask pixels [3] (for relighting)."""
    est = _stack(est, "albedo estimate", 4)
    gt = _stack(gt, "albedo ground truth", 4)
    m = np.asarray(mask, bool).reshape(est.shape[:3])
    return np.array([np.median(gt[..., c][m & (est[..., c] > EST_MIN)]
                               / est[..., c][m & (est[..., c] > EST_MIN)]) for c in range(3)])


# Half height at 12 deg, about the spacing of the 128-direction grid (sqrt(2 pi / 128) rad).
LIGHT_KERNEL_KAPPA = float(np.log(2.0) / (1.0 - np.cos(np.radians(12.0))))


def _mean_weights(w, k: int) -> np.ndarray:
    w = np.asarray(w, np.float64)
    w = w.mean(-1) if w.ndim == 2 else w
    if w.shape != (k,):
        raise ValueError(f"light weights: expected {k} values (or [{k}, 3]), got {w.shape}")
    return w


def light_cosine(est_dirs, est_w, gt_dirs, gt_w, kappa: float = LIGHT_KERNEL_KAPPA) -> float:
    """Kernel-smoothed cosine of two light sets: directions [K, 3] (unit, toward the light)
    and irradiance [K] or [K, 3]. Continuous in the directions; 1.0 for a perfect fit."""
    d, e = np.asarray(est_dirs, np.float64), np.asarray(gt_dirs, np.float64)
    a, b = _mean_weights(est_w, len(d)), _mean_weights(gt_w, len(e))

    def gram(x, y):  # [K, M]
        return np.exp(kappa * (np.clip(x @ y.T, -1.0, 1.0) - 1.0))

    ab, aa, bb = a @ gram(d, e) @ b, a @ gram(d, d) @ a, b @ gram(e, e) @ b
    return float(ab / np.sqrt(aa * bb)) if aa > 0 and bb > 0 else 0.0


def seen_from(est_dirs, est_positions, gt_lights: list[dict]) -> np.ndarray:
    """The fitted lights' directions [K, 3] as the truth's are given: a fitted lamp's as the
    direction from the true lamps' centre (a true lamp's position less its direction times
    its distance) to its position, a directional light's as it is. A fitted lamp's stored
    direction is from the fit's own scene centre, which is not the object's: at 6 object
    radii, a centre 0.1 radii off turns it by up to a degree. Without a true lamp, or
    without fitted lamps, the stored directions."""
    d = np.asarray(est_dirs, np.float64).reshape(-1, 3)
    lamps = [lt for lt in gt_lights if lt.get("position") is not None]
    if est_positions is None or not lamps:
        return d
    pos = np.asarray(est_positions, np.float64).reshape(-1, 3)
    local = np.all(np.isfinite(pos), axis=1)
    true = lamps[0]
    centre = (np.asarray(true["position"], np.float64)
              - np.asarray(true["direction"], np.float64) * float(true["distance"]))
    v = pos - centre
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.where(local[:, None] & (n > 0), v / np.where(n > 0, n, 1.0), d)


def light_angular_errors(est_dirs, est_w, gt_dirs) -> dict:
    """Each true light's angle (degrees) to the fitted light matched with it (Hungarian
    matching on angles), and the share of fitted irradiance in unmatched lights."""
    from scipy.optimize import linear_sum_assignment

    d, e = np.asarray(est_dirs, np.float64), np.asarray(gt_dirs, np.float64)
    a = _mean_weights(est_w, len(d))
    angles = np.degrees(np.arccos(np.clip(e @ d.T, -1.0, 1.0)))  # [G, K]
    rows, cols = linear_sum_assignment(angles)
    errors = np.full(len(e), np.nan)
    errors[rows] = angles[rows, cols]
    total = a.sum()
    spurious = 1.0 - a[cols].sum() / total if total > 0 else 0.0
    return {"angular_error_deg": errors.tolist(),
            "angular_error_max_deg": float(np.nanmax(errors)) if len(e) else 0.0,
            "fitted_lights": int(len(d)),
            "spurious_irradiance_fraction": float(spurious)}


def lamp_errors(est_dirs, est_w, est_positions, gt_lights: list[dict]) -> dict:
    """Each true lamp (a ``lights.json`` entry with a ``position``) against the fitted light
    matched with it (Hungarian matching on the directions): its position error as a share of
    the lamp's distance (None where the matched light is directional), and the strongest
    fitted light's share of the fitted irradiance."""
    from scipy.optimize import linear_sum_assignment

    d = np.asarray(est_dirs, np.float64).reshape(-1, 3)
    a = _mean_weights(est_w, len(d))
    out = {"strongest_light_share": float(a.max() / a.sum()) if a.sum() > 0 else 0.0}
    lamps = [lt for lt in gt_lights if lt.get("position") is not None]
    if not lamps:
        return out
    pos = (np.full((len(d), 3), np.nan) if est_positions is None
           else np.asarray(est_positions, np.float64).reshape(-1, 3))
    e = np.array([lt["direction"] for lt in lamps], np.float64)
    rows, cols = linear_sum_assignment(np.degrees(np.arccos(np.clip(e @ d.T, -1.0, 1.0))))
    errors: list = [None] * len(lamps)
    for r, c in zip(rows, cols, strict=True):
        if np.all(np.isfinite(pos[c])):
            true = np.asarray(lamps[r]["position"], np.float64)
            centre = true - e[r] * float(lamps[r]["distance"])
            errors[r] = float(np.linalg.norm(pos[c] - true) / np.linalg.norm(true - centre))
    out["lamp_position_error"] = errors
    return out


def light_map_cosine(est, gt) -> float:
    """Cosine similarity of two light maps over the grid ([n] or [n, 3]; RGB -> mean)."""
    e, g = (np.asarray(x, np.float64) for x in (est, gt))
    e = e.mean(-1) if e.ndim == 2 else e
    g = g.mean(-1) if g.ndim == 2 else g
    if e.shape != g.shape:
        raise ValueError(f"light cosine: map sizes differ: {e.shape} vs {g.shape}")
    ne, ng = np.linalg.norm(e), np.linalg.norm(g)
    return float(e @ g / (ne * ng)) if ne > 0 and ng > 0 else 0.0


def _shadow_level(irr: np.ndarray, m: np.ndarray, threshold: float) -> float:
    """The irradiance under which a pixel of the non-empty mask ``m`` is shadow."""
    return threshold * float(np.median(irr[m]))


def shadow_mask(irradiance, mask, threshold: float = SHADOW_THRESHOLD) -> np.ndarray:
    """Shadow pixels [H, W]: irradiance < threshold x median irradiance over the mask."""
    irr = np.asarray(irradiance, np.float64)
    m = np.asarray(mask, bool)
    if not m.any():
        return np.zeros_like(m)
    return m & (irr < _shadow_level(irr, m, threshold))


def undecided_pixels(irradiance, mask, threshold: float = SHADOW_THRESHOLD,
                     band: float = SHADOW_UNDECIDED_BAND) -> np.ndarray:
    """Pixels [H, W] of ``mask`` whose irradiance lies within ``band`` (relative) of
    ``shadow_mask``'s level; none for a band of 0."""
    irr = np.asarray(irradiance, np.float64)
    m = np.asarray(mask, bool)
    if not m.any():
        return np.zeros_like(m)
    level = _shadow_level(irr, m, threshold)
    return m & (np.abs(irr - level) < band * level)


def shadow_iou(est_irr, gt_irr, mask, threshold: float = SHADOW_THRESHOLD,
               undecided_band: float = 0.0) -> float:
    """Mean over views of the IoU of the shadow masks of two direct-irradiance stacks; with
    ``undecided_band`` > 0, counted only on the pixels whose true irradiance is outside that
    band around the threshold (the masks and their medians are the whole mask's)."""
    e = _stack(est_irr, "estimated irradiance", 3)
    g = _stack(gt_irr, "ground-truth irradiance", 3)
    m = np.asarray(mask, bool).reshape(e.shape)
    ious = []
    for ee, gg, mm in zip(e, g, m, strict=True):
        if not mm.any():
            continue
        decided = ~undecided_pixels(gg, mm, threshold, undecided_band)
        ious.append(metrics.mask_iou(shadow_mask(ee, mm, threshold) & decided,
                                     shadow_mask(gg, mm, threshold) & decided))
    return float(np.mean(ious))
