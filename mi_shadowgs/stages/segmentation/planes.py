"""Planar segments (not in the paper): a segment whose surfels lie on one plane is shaded flat.

At 128^2 the base's surfels scatter about its plane: a surfel's normal is 6 deg off the
plane's at the median and 23 deg at the 90th percentile (the default scene's stage-1 fit),
and the rasterized normals of the base are 0.5 deg off at the median but several degrees at
the 90th percentile. Under a grazing light that matters: the base's regions lit by one light
of a pair sit near the shadow metric's threshold of half the median irradiance (0.44 and 0.56
of it under the table's low pair), and a few degrees of n . l flip whole patches. With the
true plane's normal on the base's pixels, the low-pair shadow IoU of four table rows rose by
0.03-0.10 (docs/decisions.md, "Planar segments shaded flat").

After stage 2's K-means, each segment's surfels get a plane by opacity-weighted PCA of their
centres, refitted ``iterations`` times on the inliers: surfels whose centre lies within
``distance_scales`` of the segment's median surfel std-dev from the plane and whose normal is
within ``max_angle_deg`` of the plane's. A segment is planar when its inliers carry at least
``min_inlier_share`` of its opacity; then each inlier gets the plane's normal (on its own
side) as its shading normal (``shading.SHADING_NORMAL_CHANNEL``), every other surfel its own.
The geometry is left as it is: coverage, depth and the shadow maps' occluders. Turning the
inliers themselves, or moving their centres onto the plane as well, changed what covers the
base's rim and where it meets the object (bunny, low pair: albedo PSNR 36.05 dB as fitted,
35.4 turned, 32.4 turned and moved).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mi_shadowgs.core import jit
from mi_shadowgs.core.frames import quaternion_to_matrix
from mi_shadowgs.core.shading import SHADING_NORMAL_CHANNEL
from mi_shadowgs.core.surfels import Surfels

# The support's plane (``support_split``): RANSAC trials; the inlier distance as a share of
# the surfels' 90th-percentile distance from their median; the band (in inlier distances)
# within which a surfel is the support's; the least share of the surfels the plane holds.
SUPPORT_TRIALS = 200
SUPPORT_TOLERANCE = 0.01
SUPPORT_BAND = 3.0
SUPPORT_MIN_SHARE = 0.3


@dataclasses.dataclass(frozen=True)
class PlaneConfig:
    """Which segments are made flat; see the module docstring. Off in the paper preset."""

    enabled: bool = False
    # Inliers: centre within this many of the segment's median surfel std-dev of the plane.
    # The default scene's and the bunny's bases, low pair, run's lights held: 1.0 left
    # 21-25% of the base's opacity out (not planar at 0.8), 1.5 gave shadow IoU +0.020 /
    # +0.049, 3 and 5 less (+0.018 / +0.042, +0.015 / +0.035): the fuzz above the plane.
    distance_scales: float = 1.5
    # ... and normal within this angle of the plane's: keeps an object's side surfels that
    # touch the base out (45-90 deg scored alike).
    max_angle_deg: float = 60.0
    # Of the segment's opacity: planar segments hold most of it, curved ones at most about
    # two thirds (docs/decisions.md, "Planar segments shaded flat").
    min_inlier_share: float = 0.75
    min_surfels: int = 100  # smaller segments are left alone
    iterations: int = 4  # PCA refits on the inliers

    def __post_init__(self):
        if (self.distance_scales <= 0 or not 0 < self.max_angle_deg <= 90
                or not 0 < self.min_inlier_share <= 1 or self.min_surfels < 3
                or self.iterations < 1):
            raise ValueError(f"PlaneConfig: distance_scales > 0, max_angle_deg in (0, 90], "
                             f"min_inlier_share in (0, 1], min_surfels >= 3, iterations >= 1; "
                             f"got {self}")


@dataclasses.dataclass(frozen=True)
class PlaneFit:
    """One segment's plane: unit ``normal`` [3] and a ``point`` [3] on it, the ``inliers``
    [m] (bool, over the segment's surfels) and their share of its opacity."""

    normal: np.ndarray
    point: np.ndarray
    inliers: np.ndarray
    inlier_share: float


def fit_plane(points: np.ndarray, normals: np.ndarray, weights: np.ndarray,
              distance: float, max_angle_deg: float, iterations: int) -> PlaneFit | None:
    """The plane of ``points`` [m, 3] (weights [m] >= 0, unit ``normals`` [m, 3]): weighted
    PCA, refitted on the inliers (within ``distance`` of the plane, normal within
    ``max_angle_deg`` of its axis); None when the points carry no weight."""
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    w = np.asarray(weights, np.float64)
    cos_min = math.cos(math.radians(max_angle_deg))
    inl = np.ones(len(p), bool)
    normal = centre = None
    for _ in range(iterations):
        ww = np.where(inl, w, 0.0)
        total = ww.sum()
        if total <= 0:  # no inlier left: not a plane (None when nothing had weight)
            break
        centre = (ww[:, None] * p).sum(0) / total
        d = p - centre
        cov = (ww[:, None] * d).T @ d  # [3, 3]
        normal = np.linalg.eigh(cov)[1][:, 0]  # the smallest spread's axis
        inl = (np.abs(d @ normal) <= distance) & (np.abs(n @ normal) >= cos_min)
    if normal is None:
        return None
    share = float(w[inl].sum() / w.sum())
    return PlaneFit(normal, centre, inl, share)


def planar_shading_normals(surfels: Surfels, segments: np.ndarray, config: PlaneConfig
                           ) -> tuple[Surfels, list[dict]]:
    """(``surfels`` with a shading-normal channel: each planar segment's inliers take its
    plane's normal, one report per segment fitted: segment, surfels, plane normal and point,
    inlier share, planar, flattened). Unchanged (the same object) when ``config.enabled``
    is off, and when no segment is planar."""
    if not config.enabled or surfels.count == 0:
        return surfels, []
    seg = np.asarray(segments).reshape(-1)
    if seg.shape[0] != surfels.count:
        raise ValueError(f"planar_shading_normals: {seg.shape[0]} segment ids for "
                         f"{surfels.count} surfels")
    a = surfels.to_numpy()
    pos, quat, scale, opacity = a["position"], a["rotation"], a["scale"], a["opacity"]
    normals = quaternion_to_matrix(quat)[:, :, 2]  # [N, 3]
    size = scale.mean(1)  # [N] the surfels' mean tangent std-dev
    shading_normal = normals.copy()
    reports = []
    for k in np.unique(seg):
        idx = np.flatnonzero(seg == k)
        if idx.size < config.min_surfels:
            continue
        fit = fit_plane(pos[idx], normals[idx], opacity[idx],
                        config.distance_scales * float(np.median(size[idx])),
                        config.max_angle_deg, config.iterations)
        if fit is None:
            continue
        planar = fit.inlier_share >= config.min_inlier_share
        j = idx[fit.inliers] if planar else idx[:0]
        side = np.where(normals[j] @ fit.normal >= 0, 1.0, -1.0)[:, None]  # each on its own
        shading_normal[j] = side * fit.normal
        reports.append({"segment": int(k), "surfels": int(idx.size),
                        "normal": fit.normal.tolist(), "point": fit.point.tolist(),
                        "inlier_share": fit.inlier_share, "planar": bool(planar),
                        "flattened": int(j.size)})
    if not any(r["flattened"] for r in reports):
        return surfels, reports
    return surfels.with_channels(
        {SHADING_NORMAL_CHANNEL: jit.tensor(shading_normal)}), reports


SUPPORT_SPLITS = ("off", "on", "auto")  # SegmentationConfig.support_split's modes


def support_split_applies(mode: str, segments: int, forced: bool = False) -> bool:
    """Whether ``SegmentationConfig.support_split`` ``mode`` splits a segmentation of
    ``segments`` segments: "on" always, "auto" when colour found a single segment (only the
    geometry then tells an object from its support) and the count was not ``forced`` (a
    user's ``n_segments``), "off" never."""
    if mode not in SUPPORT_SPLITS:
        raise ValueError(f"support_split must be one of {SUPPORT_SPLITS}, got {mode!r}")
    return mode == "on" or (mode == "auto" and segments == 1 and not forced)


def support_split(positions: np.ndarray, segments: np.ndarray, seed: int = 0
                  ) -> tuple[np.ndarray, dict | None]:
    """(segment ids [N], renumbered 0..S'-1, a report or None): every segment of
    ``segments`` [N] split into its surfels on the scene's dominant plane (the support the
    object stands on) and those off it, where that plane holds at least
    ``SUPPORT_MIN_SHARE`` of the surfels ``positions`` [N, 3]; else ``segments`` as they are
    and None. The plane: the import's RANSAC plane fit (``world_frame.fit_plane``, inliers
    within ``SUPPORT_TOLERANCE`` of the surfels' 90th-percentile spread); a surfel is the
    support's within ``SUPPORT_BAND`` such distances of it."""
    from mi_shadowgs.dataset.world_frame import WorldFrameError
    from mi_shadowgs.dataset.world_frame import fit_plane as ransac_plane

    p = np.asarray(positions, np.float64).reshape(-1, 3)
    seg = np.asarray(segments).reshape(-1).astype(np.int64)
    tol = SUPPORT_TOLERANCE * float(np.percentile(
        np.linalg.norm(p - np.median(p, 0), axis=1), 90)) if len(p) >= 3 else 0.0
    if tol <= 0:
        return seg, None
    try:
        normal, offset, _ = ransac_plane(p, tol, SUPPORT_TRIALS, np.random.default_rng(seed))
    except WorldFrameError:  # collinear: no plane
        return seg, None
    on = np.abs(p @ normal - offset) <= SUPPORT_BAND * tol
    share = float(on.mean())
    if share < SUPPORT_MIN_SHARE or on.all():
        return seg, None
    split = np.unique(seg * 2 + ~on, return_inverse=True)[1].reshape(-1)
    return split, {"normal": normal.tolist(), "point": (offset * normal).tolist(),
                   "share": share, "segments_before": int(len(np.unique(seg))),
                   "segments_after": int(split.max()) + 1}
