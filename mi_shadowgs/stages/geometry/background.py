"""Which dark pixels of views without masks are background: where stage 1's dark-alpha
prior (``GeometryConfig.lambda_dark_alpha``) asks for transparency.

A dark pixel is not always empty space. Under one lamp a deep cast shadow on the mat is as
dark as a black backdrop, and a prior on every dark pixel makes it a hole in the ground.
What tells them apart is where the pixel's ray goes, and what the other views see there:

- the *ground*: the convex outline of the SfM points on y = 0 (an import's frame), stray
  points dropped (``inliers``). The mat has points all round its shadows, a black backdrop
  has none, so a dark pixel whose ray meets the outline is the mat's;
- the *body*: the convex hull of the SfM points above the ground and of what is left of the
  object's bound after carving (``carve``). SfM finds few points on a plain object, but the
  frame puts the object within the cylinder of radius 1 and height 2 about the Y axis
  (``dataset.world_frame``); its cells that most views that see them see as background
  (dark, off the ground) are empty space, the others may be the object;
- ``prior_pixels``: per view, the dark pixels (every channel <= ``dark_max``) whose rays
  meet neither (with ``dark_alpha_support`` "points"), or every dark pixel ("none").

A lit room's backdrop is dark but not black. Without masks, stage 1 composites its render
over one backdrop colour (``GeometryConfig.backdrop``, ``estimate_backdrop``): the median of
the pixels whose rays meet neither the ground's outline nor the object's bound (the frame's
cylinder with the body's points), so that the model needs no surfels before the cameras to
show the room; the prior's dark pixels are then those within ``BACKDROP_SLACK`` times it.

Ground and body are hulls of their own: one hull of both would also hold the empty space
between the object's top and the mat's far corners, through which some rays that see the
backdrop pass. A dark hollow of the object lies within its hull: kept. Each is grown by
``dark_alpha_margin``; rays are tested in float64 (``rays_meet_ground``; the body by its
projected outline, ``hull_pixels``, or where the camera is not wholly before it face by
face, ``rays_meet_hull``).
"""

from __future__ import annotations

import dataclasses
import functools

import drjit as dr
import mitsuba as mi
import numpy as np

# A neighbourhood of this many points tells a stray SfM point from a sparse surface ...
NEIGHBOURS = 8
# ... which is kept while its NEIGHBOURS-th neighbour is within this many times the median.
STRAY_DISTANCE = 5.0
# Points within this height of y = 0 (object radii) are the ground's; a plane holds at least
# this share of the points (``world_frame``'s plane test).
GROUND_HEIGHT = 0.05
GROUND_SHARE = 0.15
# The object's bound is carved in cells of 2 / CELLS object radii; a cell is empty space when
# at least this share of the views that see it see background there.
CELLS = 24
CARVE_SHARE = 0.5
# The backdrop is estimated from at least this share of the views' pixels (else black) ...
BACKDROP_MIN_SHARE = 0.01
# ... and a pixel is as dark as the backdrop up to this factor of it (a photo's exposure
# moves it by +-30%).
BACKDROP_SLACK = 1.5


@dataclasses.dataclass(frozen=True)
class Support:
    """Where a surface may be. ``ground``: half-planes [F, 3] (a, b, c: ``a x + b z + c <=
    0``) of the ground's outline at y = 0, or None; ``body``: half-spaces [F, 4] (n, d:
    ``n . p + d <= 0``) of the body's hull, or None."""

    ground: np.ndarray | None
    body: np.ndarray | None

    @functools.cached_property
    def body_vertices(self) -> np.ndarray | None:
        """The body's vertices (``hull_vertices``), found once for all the views."""
        return None if self.body is None else hull_vertices(self.body)


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


def split_points(points: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """(the ground's points [G, 3] or None where no plane holds ``GROUND_SHARE`` of them,
    the others [B, 3]) of SfM ``points`` [M, 3], non-finite and stray points dropped."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    pts = pts[inliers(pts)]
    on_ground = np.abs(pts[:, 1]) <= GROUND_HEIGHT
    if len(pts) == 0 or on_ground.mean() < GROUND_SHARE:
        return None, pts
    return pts[on_ground], pts[pts[:, 1] > GROUND_HEIGHT]


def object_cells(cells: int = CELLS) -> np.ndarray:
    """[V, 3] the centres of the cells of size 2 / ``cells`` within the frame's object bound
    (the cylinder of radius 1 from y = 0 to 2 about the Y axis)."""
    g = (np.arange(cells) + 0.5) / cells
    x, y, z = np.meshgrid(2 * g - 1, 2 * g, 2 * g - 1, indexing="ij")
    c = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=-1)
    return c[np.hypot(c[:, 0], c[:, 2]) <= 1.0]


def carve(cells: np.ndarray, cameras, background: list[np.ndarray]) -> np.ndarray:
    """[V] bool: the ``cells`` [V, 3] kept, those that fewer than ``CARVE_SHARE`` of the
    views that see them (the cell's centre in front, within the image) see as
    ``background`` ([H, W] bool per camera) there; a cell no view sees is kept."""
    seen = np.zeros(len(cells))
    empty = np.zeros(len(cells))
    for cam, bg in zip(cameras, background, strict=True):
        value, inside = cam.lookup(bg, cells)
        seen += inside
        empty += value & inside
    return (seen == 0) | (empty < CARVE_SHARE * seen)


def _rays(camera) -> tuple[np.ndarray, np.ndarray]:
    """(origins [P, 3], directions [P, 3]) of the pixel centres' rays, row-major; a pinhole's
    origins are one point, broadcast (read-only)."""
    px = camera.pixel_grid()
    if camera.is_ortho:
        o = camera.unproject(px, np.zeros(len(px)))
        return o, camera.unproject(px, np.ones(len(px))) - o
    c2w = np.linalg.inv(camera.world_to_cv())
    (cx, cy), (fx, fy) = camera.principal_point, camera.focal_xy
    d = np.stack([(px[:, 0] - cx) / fx, (px[:, 1] - cy) / fy, np.ones(len(px))], -1)
    return np.broadcast_to(c2w[:3, 3], d.shape), d @ c2w[:3, :3].T


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
    """[H, W] bool: the pixels of ``camera`` whose centre rays meet ``support``. The body's
    pixels are those inside its projected outline (``hull_pixels``) where it lies wholly in
    front of the camera, else each ray is tested against its faces (``rays_meet_hull``)."""
    body = (None if support.body is None else
            hull_pixels(camera, support.body, support.body_vertices))
    out = np.zeros(camera.width * camera.height, bool) if body is None else body
    by_faces = support.body is not None and body is None
    if support.ground is not None or by_faces:
        o, d = _rays(camera)
        for a in range(0, len(o), chunk):
            b = min(a + chunk, len(o))
            if support.ground is not None:
                out[a:b] |= rays_meet_ground(o[a:b], d[a:b], support.ground)
            if by_faces:
                out[a:b] |= rays_meet_hull(o[a:b], d[a:b], support.body)
    return out.reshape(camera.height, camera.width)


def hull_vertices(planes: np.ndarray) -> np.ndarray | None:
    """The vertices [K, 3] of the polytope of half-spaces ``planes`` [F, 4] (``_hull``), or
    None where it has no interior."""
    from scipy.optimize import linprog
    from scipy.spatial import HalfspaceIntersection, QhullError

    # Chebyshev centre: the deepest interior point, max r with n . x + d + r <= 0 (|n| = 1).
    res = linprog([0.0, 0.0, 0.0, -1.0], A_ub=np.hstack([planes[:, :3], np.ones((len(planes),
                                                                                1))]),
                  b_ub=-planes[:, 3], bounds=[(None, None)] * 3 + [(0.0, None)])
    if not res.success or res.x[3] <= 1e-9:
        return None
    try:
        return HalfspaceIntersection(planes, res.x[:3]).intersections
    except QhullError:
        return None


def hull_pixels(camera, planes: np.ndarray, vertices: np.ndarray | None = None,
                chunk: int = 65536) -> np.ndarray | None:
    """[H * W] bool: the pixels whose centres lie inside the outline of the polytope of
    half-spaces ``planes`` [F, 4] (its ``vertices`` when the caller has them, else found
    here) as ``camera`` sees it, or None where that is not its rays' test (the polytope not
    wholly in front of the camera, or no interior). A convex polytope before a pinhole
    projects to the convex hull of its projected vertices, so a pixel's ray meets it exactly
    when its centre lies in that hull: one test per outline edge instead of one per face
    (``rays_meet_hull``)."""
    from scipy.spatial import ConvexHull, QhullError

    verts = hull_vertices(planes) if vertices is None else vertices
    if verts is None:
        return None
    uv, z = camera.project(verts)
    if not np.all(z > camera.near) or not np.all(np.isfinite(uv)):
        return None
    try:
        outline = ConvexHull(uv).equations  # [E, 3]: a x + b y + c <= 0 inside
    except QhullError:  # seen edge-on: no area
        return None
    px = camera.pixel_grid()
    out = np.zeros(len(px), bool)
    lo, hi = uv.min(axis=0), uv.max(axis=0)  # only the outline's bounding box is tested
    box = np.flatnonzero(np.all((px >= lo) & (px <= hi), axis=1))
    for a in range(0, len(box), chunk):
        idx = box[a:a + chunk]
        out[idx] = np.all(px[idx] @ outline[:, :2].T + outline[:, 2] <= 0.0, axis=1)
    return out


def dark_pixels(image: np.ndarray, dark_max, backdrop: np.ndarray | None = None
                ) -> np.ndarray:
    """[H, W] bool: the pixels of ``image`` [H, W, 3] whose channels are all <= ``dark_max``,
    plus ``BACKDROP_SLACK`` times ``backdrop`` [3] (a lit room's colour) when given."""
    limit = np.asarray(dark_max, np.float64)
    if backdrop is not None:
        limit = limit + BACKDROP_SLACK * np.asarray(backdrop, np.float64).reshape(3)
    return np.all(np.asarray(image) <= limit, axis=-1)


def read_points(path) -> np.ndarray:
    """The SfM points [M, 3] of an import's ``points3d.ply``."""
    from mi_shadowgs.io.ply import read_ply_vertices

    v = read_ply_vertices(path)
    return np.stack([v["x"], v["y"], v["z"]], axis=-1).astype(np.float64)


def support_of(points: np.ndarray, cameras, dark: list[np.ndarray], margin: float
               ) -> Support:
    """The support (module doc) of SfM ``points`` [M, 3] in an import's frame, its body
    carved by the views' ``cameras`` and their ``dark`` pixels ([H, W] bool each), ground
    and body grown by ``margin`` (object radii; the carved cells by their half-size too)."""
    ground_pts, body_pts = split_points(points)
    ground = None if ground_pts is None else _hull(ground_pts[:, [0, 2]], margin)
    off_ground = [d & ~supported_pixels(cam, Support(ground, None)) if ground is not None
                  else d for cam, d in zip(cameras, dark, strict=True)]
    cells = object_cells()
    kept = cells[carve(cells, cameras, off_ground)]
    return Support(ground, _hull(np.concatenate([body_pts, kept]), margin + 1.0 / CELLS))


def estimate_backdrop(dataset, config) -> np.ndarray | None:
    """The backdrop's linear RGB [3] under ``config`` (``GeometryConfig.backdrop`` "auto"):
    the per-channel median of the pixels, in the training views without masks, whose rays
    meet neither the ground's outline nor the object's bound (``object_cells`` with the SfM
    points above the ground, grown by ``dark_alpha_margin`` and a cell); None when the
    setting is "black", every view has a mask, the dataset has no SfM points, fewer than
    ``BACKDROP_MIN_SHARE`` of the pixels are such, or their median is black (at most
    ``dark_max``)."""
    unmasked = [v for v in dataset.views if not getattr(v, "has_mask", True)]
    points = getattr(dataset, "points", None)
    if config.backdrop == "black" or not unmasked or points is None:
        return None
    ground_pts, body_pts = split_points(read_points(points))
    margin = config.dark_alpha_margin
    ground = None if ground_pts is None else _hull(ground_pts[:, [0, 2]], margin)
    body = _hull(np.concatenate([body_pts, object_cells()]), margin + 1.0 / CELLS)
    support = Support(ground, body)
    seen = [np.asarray(v.image)[~supported_pixels(v.camera, support)] for v in unmasked]
    pixels = np.concatenate(seen).reshape(-1, 3)
    if len(pixels) < BACKDROP_MIN_SHARE * sum(v.image[..., 0].size for v in unmasked):
        return None
    colour = np.median(pixels, axis=0).astype(np.float64)
    return None if colour.max() <= config.dark_max else colour


def over_backdrop(rgb: mi.TensorXf, alpha: mi.TensorXf, colour: mi.TensorXf) -> mi.TensorXf:
    """The premultiplied render ``rgb`` [H, W, 3] over ``colour`` [3] where its ``alpha``
    [H, W, 1] leaves it uncovered. Differentiable in all three."""
    i = dr.arange(mi.UInt32, dr.width(rgb.array))
    a = dr.gather(mi.Float, alpha.array, i // 3)
    return mi.TensorXf(dr.fma(1.0 - a, dr.gather(mi.Float, colour.array, i % 3), rgb.array),
                       rgb.shape)


def composite(render: dict, backdrop: np.ndarray | None) -> np.ndarray:
    """NumPy: ``render_view``'s rgb over ``backdrop`` [3] (None: over black, as rendered)."""
    if backdrop is None:
        return render["rgb"]
    return render["rgb"] + (1.0 - render["alpha"])[..., None] * np.asarray(
        backdrop, np.float32).reshape(3)


def prior_pixels(dataset, config, backdrop: np.ndarray | None = None
                 ) -> list[np.ndarray | None]:
    """Per training view of ``dataset``, the [H, W] bool pixels the dark-alpha prior acts on
    under ``config`` (``GeometryConfig``; see the module doc), or None (a view with a mask,
    or the prior off); dark is up to ``dark_max`` plus ``BACKDROP_SLACK`` times the
    ``backdrop`` [3] when given. ``dark_alpha_support`` "points" without SfM points
    (``dataset.points`` None) falls back to every dark pixel, as "none" does; the stage's
    runner says so."""
    views = dataset.views
    if config.lambda_dark_alpha <= 0:
        return [None] * len(views)
    unmasked, dark, support = _unmasked_support(dataset, config, backdrop,
                                                config.dark_alpha_support == "points")
    if support is not None:
        for v, d in zip(unmasked, dark, strict=True):
            if d.any():
                d &= ~supported_pixels(v.camera, support)
    by_view = {id(v): d for v, d in zip(unmasked, dark, strict=True)}
    return [by_view.get(id(v)) for v in views]


def _unmasked_support(dataset, config, backdrop: np.ndarray | None, with_support: bool = True
                      ) -> tuple[list, list[np.ndarray], Support | None]:
    """(``dataset``'s views without masks, their dark pixels under ``config`` and
    ``backdrop`` (``dark_pixels``), the support of its SfM points carved by them
    (``support_of``), or None: ``with_support`` False, no SfM points or no such view)."""
    unmasked = [v for v in dataset.views if not getattr(v, "has_mask", True)]
    dark = [dark_pixels(v.image, config.dark_max, backdrop) for v in unmasked]
    points = getattr(dataset, "points", None)
    support = None
    if with_support and points is not None and unmasked:
        support = support_of(read_points(points), [v.camera for v in unmasked], dark,
                             config.dark_alpha_margin)
    return unmasked, dark, support


@dataclasses.dataclass(frozen=True)
class PastTheGround:
    """Where stage 1 grew surfels over the room seen past the ground; stage 4 leaves those
    surfels and their pixels out. Beyond the mat's far edge a dim room looks like a dark
    surface: the photos cannot tell surfels of the backdrop's colour from the backdrop
    itself, so some stay. Lit by a fitted light they would be bright where the photos are
    dark, the light fit would bend to keep them dark, and relit views would show them. A
    pixel (or a surfel) is such when its surface lies outside the support (``support_of``:
    above or beside the ground's outline, and outside the body's hull) and it is as dark as
    the backdrop (``BACKDROP_SLACK``). A cast shadow on the mat lies within the outline, the
    object within the body's hull, and a lit floor past the mat is not dark."""

    support: Support
    backdrop: np.ndarray  # [3] linear RGB, before each view's gain
    dark_max: float  # ``GeometryConfig.dark_max``

    @staticmethod
    def of(dataset, config, backdrop: np.ndarray | None) -> PastTheGround | None:
        """The rule for ``dataset``'s views without masks under ``config`` (a
        ``GeometryConfig``: ``dark_max``, ``dark_alpha_margin``): None without such views,
        SfM points, a ground plane among them or a backdrop colour
        (``estimate_backdrop``)."""
        if backdrop is None:
            return None
        support = _unmasked_support(dataset, config, backdrop)[2]
        if support is None or support.ground is None or support.body is None:
            return None
        return PastTheGround(support, np.asarray(backdrop, np.float64), config.dark_max)

    def pixels(self, points: np.ndarray, rgb: np.ndarray) -> np.ndarray:
        """[P] bool: of surface ``points`` [P, 3] and their colours ``rgb`` [P, 3] (linear,
        divided by the view's gain), those past the ground."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        ground, body = self.support.ground, self.support.body
        off_ground = np.any(p[:, [0, 2]] @ ground[:, :2].T + ground[:, 2] > 0, axis=1)
        off_body = np.any(p @ body[:, :3].T + body[:, 3] > 0, axis=1)
        dark = dark_pixels(np.asarray(rgb).reshape(-1, 3), self.dark_max, self.backdrop)
        return off_ground & off_body & dark

    def surfels(self, surfels) -> np.ndarray:
        """[N] bool: the ``surfels`` (a ``Surfels``) past the ground, by their centres and
        the mean colour stage 1 gave them (the SH's DC band, linear, before gains); none
        without an "sh" channel."""
        from mi_shadowgs.core.surfels import SH_C0

        arrays = surfels.to_numpy()
        if "sh" not in arrays:
            return np.zeros(surfels.count, bool)
        return self.pixels(arrays["position"], SH_C0 * arrays["sh"][:, :3] + 0.5)
