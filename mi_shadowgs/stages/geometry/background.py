"""Which dark pixels of views without masks are background: where stage 1's dark-alpha
prior (``GeometryConfig.lambda_dark_alpha``) asks for transparency.

A dark pixel is not always empty space. Under one lamp a deep cast shadow on the mat is as
dark as a black backdrop, and a prior on every dark pixel makes it a hole in the ground.
What tells them apart is where the pixel's ray goes: the SfM points mark the surfaces SfM
saw (the mat has points all round its shadows, a black backdrop has none), so

- ``support_from_points``: the SfM points, isolated ones dropped (``inliers``), become a
  *support*: the convex outline of the points on the ground (y = 0 in an import's frame)
  and the convex hull of the points above it, each grown by a margin;
- ``supported_pixels``: a view's pixels whose rays meet the support (a float64 ray test);
- ``prior_pixels``: the pixels the prior acts on, per view: dark (every channel <=
  ``dark_max``) and, with ``dark_alpha_support`` "points", not supported.

The ground and the body are hulls of their own: one hull of all points would also hold the
empty space between the object's top and the mat's far corners, through which some rays
that see the backdrop pass. Where no plane holds enough of the points (no ground), the
body's hull is all there is. A dark hollow of the object lies within its hull: kept.
"""

from __future__ import annotations

import dataclasses

import numpy as np

# A neighbourhood of this many points tells a stray SfM point from a sparse surface ...
NEIGHBOURS = 8
# ... which is kept while its NEIGHBOURS-th neighbour is within this many times the median.
STRAY_DISTANCE = 5.0
# Points within this height of y = 0 (object radii) are the ground's; a plane holds at least
# this share of the points (``world_frame``'s plane test).
GROUND_HEIGHT = 0.05
GROUND_SHARE = 0.15


@dataclasses.dataclass(frozen=True)
class Support:
    """Where the SfM points say a surface may be. ``ground``: half-planes [F, 3] (a, b, c:
    ``a x + b z + c <= 0``) of the ground's outline at y = 0, or None; ``body``: half-spaces
    [F, 4] (n, d: ``n . p + d <= 0``) of the hull of the points above it, or None."""

    ground: np.ndarray | None
    body: np.ndarray | None


def inliers(points: np.ndarray) -> np.ndarray:
    """[M] bool: the points whose ``NEIGHBOURS``-th nearest neighbour lies within
    ``STRAY_DISTANCE`` times the median such distance (the others are SfM's strays)."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) <= NEIGHBOURS:
        return np.ones(len(pts), bool)
    dist, _ = cKDTree(pts).query(pts, k=NEIGHBOURS + 1)
    kth = dist[:, -1]
    return kth <= STRAY_DISTANCE * max(float(np.median(kth)), 1e-12)


def _hull(points: np.ndarray, margin: float) -> np.ndarray | None:
    """Half-spaces [F, D + 1] (unit normal, offset; inside: ``n . p + d <= 0``) of the convex
    hull of ``points`` [M, D] grown by ``margin``; None when they span no D-volume."""
    from scipy.spatial import ConvexHull, QhullError

    dim = points.shape[1]
    if len(points) <= dim:
        return None
    try:
        eq = ConvexHull(points).equations.copy()  # unit outward normals
    except QhullError:  # flat or degenerate: no volume to test rays against
        return None
    eq[:, -1] -= margin
    return eq


def support_from_points(points: np.ndarray, margin: float) -> Support:
    """The support of SfM ``points`` [M, 3] (in an import's frame: y up, ground at y = 0,
    object radius 1) grown by ``margin`` (object radii). See the module doc."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    pts = pts[inliers(pts)]
    on_ground = np.abs(pts[:, 1]) <= GROUND_HEIGHT
    if len(pts) and on_ground.mean() >= GROUND_SHARE:
        ground = _hull(pts[on_ground][:, [0, 2]], margin)
        body = _hull(pts[pts[:, 1] > GROUND_HEIGHT], margin)
    else:
        ground, body = None, _hull(pts, margin)
    return Support(ground, body)


def _rays(camera) -> tuple[np.ndarray, np.ndarray]:
    """(origins [P, 3], directions [P, 3]) of the pixel centres' rays, row-major."""
    px = camera.pixel_grid()
    o = camera.unproject(px, np.zeros(len(px)))
    return o, camera.unproject(px, np.ones(len(px))) - o


def rays_meet_hull(origins: np.ndarray, dirs: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """[P] bool: the rays ``origins + t dirs`` (t >= 0) that meet the convex polytope of
    half-spaces ``planes`` [F, 4] (``n . p + d <= 0``)."""
    s = origins @ planes[:, :3].T + planes[:, 3]  # [P, F]: n . o + d
    v = dirs @ planes[:, :3].T  # [P, F]: n . dir
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -s / v
    # Entering faces (v < 0) raise the near bound, leaving ones (v > 0) lower the far bound;
    # a face the ray runs along holds it wholly in or wholly out.
    t_near = np.max(np.where(v < 0, t, 0.0), axis=1)
    t_far = np.min(np.where(v > 0, t, np.inf), axis=1)
    parallel_out = np.any((v == 0) & (s > 0), axis=1)
    return (t_near <= t_far) & ~parallel_out


def rays_meet_ground(origins: np.ndarray, dirs: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """[P] bool: the rays that meet the plane y = 0 (ahead of them) inside the outline of
    half-planes ``lines`` [F, 3] (``a x + b z + c <= 0``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -origins[:, 1] / dirs[:, 1]
    ahead = np.isfinite(t) & (t > 0)
    t = np.where(ahead, t, 0.0)
    x = origins[:, 0] + t * dirs[:, 0]
    z = origins[:, 2] + t * dirs[:, 2]
    inside = np.all(x[:, None] * lines[:, 0] + z[:, None] * lines[:, 1] + lines[:, 2] <= 0,
                    axis=1)
    return ahead & inside


def supported_pixels(camera, support: Support, chunk: int = 65536) -> np.ndarray:
    """[H, W] bool: the pixels of ``camera`` whose centre rays meet ``support``."""
    o, d = _rays(camera)
    out = np.zeros(len(o), bool)
    for a in range(0, len(o), chunk):
        b = min(a + chunk, len(o))
        if support.ground is not None:
            out[a:b] |= rays_meet_ground(o[a:b], d[a:b], support.ground)
        if support.body is not None:
            out[a:b] |= rays_meet_hull(o[a:b], d[a:b], support.body)
    return out.reshape(camera.height, camera.width)


def dark_pixels(image: np.ndarray, dark_max: float) -> np.ndarray:
    """[H, W] bool: the pixels of ``image`` [H, W, 3] whose channels are all <= ``dark_max``."""
    return np.all(np.asarray(image) <= dark_max, axis=-1)


def read_points(path) -> np.ndarray:
    """The SfM points [M, 3] of an import's ``points3d.ply``."""
    from mi_shadowgs.io.ply import read_ply_vertices

    v = read_ply_vertices(path)
    return np.stack([v["x"], v["y"], v["z"]], axis=-1).astype(np.float64)


def prior_pixels(dataset, config) -> list[np.ndarray | None]:
    """Per training view of ``dataset``, the [H, W] bool pixels the dark-alpha prior acts on
    under ``config`` (``GeometryConfig``), or None (a view with a mask, or the prior off).
    ``dark_alpha_support`` "points" without SfM points (``dataset.points`` None) falls back
    to every dark pixel, as "none" does; the stage's runner says so."""
    if config.lambda_dark_alpha <= 0:
        return [None] * len(dataset.views)
    support = None
    points = getattr(dataset, "points", None)
    if config.dark_alpha_support == "points" and points is not None:
        support = support_from_points(read_points(points), config.dark_alpha_margin)
    out = []
    for view in dataset.views:
        if getattr(view, "has_mask", True):
            out.append(None)
            continue
        dark = dark_pixels(view.image, config.dark_max)
        if support is not None and dark.any():
            dark &= ~supported_pixels(view.camera, support)
        out.append(dark)
    return out
