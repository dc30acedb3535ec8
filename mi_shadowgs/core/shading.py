"""Deferred, image-space PBR shading of rasterized surfel buffers (paper Eq. 16-17).

Geometry is fixed in stages 4-5, so each view's pixel-splat pairs and blending weights are
computed once (``splat_pairs``); a material channel image is then a gather and a
``scatter_reduce`` over those pairs (``splat``), linear in the per-surfel values and
differentiable with respect to them. Shading works per pixel on the rendered buffers:

    L_o(x) = sum_k f_r(l_k, v, x) (n . l_k)^+ V(x, l_k) E_k + (1 - m) a L_ind(x)

where the lights are a ``LightSet`` of K directions with RGB weights E_k (for the grid light
map E_k = L_dir(l_k) dw with dw = 2 pi / N_l; for a directional light E_k is its
irradiance). ``L_ind(x)`` is the paper's view- and light-independent indirect radiance, an
RGB SH of degree 2 per surfel, evaluated at the surfel's normal facing the view
(``facing_normals``: indirect light depends on where the surface faces) and blended
into the pixel like a channel. Evaluated per pixel at the blended normal instead, a view
splatted 27 coefficients per pixel-splat pair rather than 3, which made a stage-4 step
2.2x slower, and the six-scene table fit no better that way.
Being independent of ``l`` it
is integrated in closed form over the normal's hemisphere: its diffuse part is
(1 - m) a / pi * pi L_ind; its specular part is left out (the grid covers only the upper
hemisphere, so Eq. 17's grid sum would cut a vertical surface's hemisphere in half).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import brdf, jit
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster import RasterConfig, face_camera, rasterize
from mi_shadowgs.core.surfels import Surfels

MATERIAL_CHANNELS = ("albedo", "roughness", "metallic")
INDIRECT_CHANNEL = "indirect_sh"
# Optional per-surfel unit normals [N, 3] that shading uses in place of the surfels' own
# (their rotations still set the geometry: coverage, depth, shadow-map occluders). Stage 2
# writes them where a segment is planar (``stages.segmentation.planes``).
SHADING_NORMAL_CHANNEL = "shading_normal"
DEFAULT_RASTER = RasterConfig()  # [N, 3 (d + 1)^2] coefficient-major, like "sh"


@dataclasses.dataclass
class LightSet:
    """K lights: directional (a direction and an irradiance) or local (a lamp at a position).

    Every light's weight is an irradiance at normal incidence (W/m^2-like): for a
    directional light, or a grid direction L dw, everywhere; for a local light, at the
    reference point ``center``, with ``directions`` pointing from ``center`` to the lamp.
    A local light k lights a point x from l = (p_k - x) / |p_k - x| with the irradiance
    E_k |p_k - c|^2 / |p_k - x|^2 (radiant intensity E_k |p_k - c|^2, 1/r^2 falloff),
    times its spot cone's falloff where it has one (``spot_falloff``, Mitsuba's ``spot``).
    """

    directions: np.ndarray  # [K, 3] unit, toward the light (for a lamp: from center)
    weights: mi.Color3f  # [K] irradiance carried by each light (L dw, E, or E at center)
    # [K, 3] world positions of local lights; NaN rows are directional lights; None: all
    # directional. May be a differentiable mi.Point3f [K] when every light is local.
    positions: np.ndarray | mi.Point3f | None = None
    radii: np.ndarray | None = None  # [K] lamp radius, world units (0: a point light)
    center: np.ndarray | None = None  # [3] where a local light's weight is its irradiance
    # [K, 5] spot cones of local lights: the unit axis the spot shines along (x, y, z), its
    # cutoff and full-beam half-angles (radians); NaN rows have none; None: no spot.
    cones: np.ndarray | None = None

    def __post_init__(self):
        if self.positions is not None and self.center is None:
            raise ValueError("LightSet: local lights need the reference point 'center'")
        if self.cones is not None and self.positions is None:
            raise ValueError("LightSet: spot cones need the lights' positions")

    @property
    def count(self) -> int:
        return len(self.directions)

    @property
    def local(self) -> np.ndarray:
        """[K] bool: which lights are local (have a position)."""
        if self.positions is None:
            return np.zeros(self.count, bool)
        if isinstance(self.positions, np.ndarray):
            return np.all(np.isfinite(np.asarray(self.positions, np.float64)), axis=1)
        return np.ones(self.count, bool)

    def intensity(self) -> np.ndarray:
        """[K] radiant intensity factor |p_k - c|^2 of local lights (W/sr per unit weight),
        inf for directional ones."""
        out = np.full(self.count, np.inf)
        if self.positions is None:
            return out
        pos = _numpy_rows(self.positions)
        loc = self.local
        out[loc] = np.sum((pos[loc] - np.asarray(self.center, np.float64)) ** 2, axis=1)
        return out


def directional_lights(directions: np.ndarray, weights: mi.Color3f) -> LightSet:
    """A LightSet of directional lights only."""
    return LightSet(np.asarray(directions, np.float64).reshape(-1, 3), weights)


def local_lights(positions: np.ndarray, weights: mi.Color3f, center: np.ndarray,
                 radii: np.ndarray | None = None) -> LightSet:
    """A LightSet of lamps at ``positions`` [K, 3] whose ``weights`` are their irradiance
    at ``center`` [3]."""
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    c = np.asarray(center, np.float64).reshape(3)
    d = pos - c
    dist = np.linalg.norm(d, axis=1)
    if np.any(dist <= 0) or not np.all(np.isfinite(pos)):
        raise ValueError("local_lights: every lamp position must be finite and away from "
                         "the reference point")
    radii = np.zeros(len(pos)) if radii is None else np.asarray(radii, np.float64).reshape(-1)
    return LightSet(d / dist[:, None], weights, pos, radii, c)


def _numpy_rows(v) -> np.ndarray:
    if isinstance(v, np.ndarray):
        return np.asarray(v, np.float64).reshape(-1, 3)
    return np.stack([np.asarray(c, np.float64) for c in (v.x, v.y, v.z)], axis=1)


def spot_falloff(cos_theta, cutoff, beam):
    """Mitsuba's ``spot`` profile at cos_theta = axis . (x - p) / |x - p|: 1 inside the
    beam (cos_theta >= cos(beam)), falling linearly in angle to 0 at the cutoff, 0 beyond.
    Works on Dr.Jit floats and, for references, NumPy arrays."""
    if isinstance(cos_theta, np.ndarray):
        ang = np.arccos(np.clip(cos_theta, -1.0, 1.0))
        ramp = (cutoff - ang) / np.maximum(cutoff - beam, 1e-12)
        f = np.where(cos_theta >= np.cos(beam), 1.0, ramp)
        return np.where(cos_theta > np.cos(cutoff), f, 0.0)
    ang = dr.acos(dr.clip(cos_theta, -1.0, 1.0))
    ramp = (cutoff - ang) / dr.maximum(cutoff - beam, 1e-12)
    f = dr.select(cos_theta >= dr.cos(beam), 1.0, ramp)
    return dr.select(cos_theta > dr.cos(cutoff), f, 0.0)


def _cone_factor(l_loc: mi.Vector3f, li: mi.UInt32, cones) -> mi.Float | None:
    """The spot falloff [P] of light ``li`` toward ``-l_loc``; None when no light has a cone."""
    cn = np.asarray(cones, np.float64).reshape(-1, 5)
    has = np.all(np.isfinite(cn), axis=1)
    if not has.any():
        return None
    safe = np.where(has[:, None], cn, [0.0, 0.0, 1.0, np.pi, np.pi]).astype(np.float32)
    axis = mi.Vector3f(*(dr.gather(mi.Float, jit.array(safe[:, k]), li) for k in range(3)))
    cut, beam = (dr.gather(mi.Float, jit.array(safe[:, k]), li) for k in (3, 4))
    f = spot_falloff(-dr.dot(axis, l_loc), cut, beam)
    return dr.select(dr.gather(mi.Bool, mi.Bool(has), li), f, 1.0)


def light_vectors(points: mi.Point3f, li: mi.UInt32, directions: np.ndarray,
                  positions=None, center=None, cones=None
                  ) -> tuple[mi.Vector3f, mi.Float | None]:
    """The unit direction toward light ``li`` [P] from ``points`` [P], and the irradiance
    factor (|p - c|^2 / |p - x|^2 for local lights, times a spot's cone falloff; 1 for
    directional; None when every light is directional).

    ``directions`` [K, 3]; ``positions``: None, [K, 3] with NaN rows for directional
    lights, or a differentiable mi.Point3f [K] (every light local); ``center`` [3];
    ``cones``: None or [K, 5] (``LightSet.cones``).
    """
    d = np.asarray(directions, np.float32).reshape(-1, 3)
    l_dir = mi.Vector3f(*(dr.gather(mi.Float, jit.array(d[:, c]), li) for c in range(3)))
    if positions is None:
        return l_dir, None
    c = np.asarray(center, np.float64).reshape(3)
    if isinstance(positions, np.ndarray):
        pos = np.asarray(positions, np.float64).reshape(-1, 3)
        is_local = np.all(np.isfinite(pos), axis=1)
        if not is_local.any():
            return l_dir, None
        safe = np.where(is_local[:, None], pos, c + 1.0).astype(np.float32)
        p = mi.Point3f(*(dr.gather(mi.Float, jit.array(safe[:, k]), li) for k in range(3)))
        flag = dr.gather(mi.Bool, mi.Bool(is_local), li)
        ref = np.where(is_local, np.sum((safe - c) ** 2, axis=1), 1.0).astype(np.float32)
        r2c = dr.gather(mi.Float, jit.array(ref), li)
    else:
        p = dr.gather(mi.Point3f, positions, li)
        flag = mi.Bool(True)
        r2c = dr.squared_norm(p - mi.Point3f(*c.tolist()))
    to_lamp = p - points
    r2 = dr.maximum(dr.squared_norm(to_lamp), 1e-12)
    l_loc = to_lamp * dr.rsqrt(r2)
    falloff = r2c / r2
    cone = None if cones is None else _cone_factor(l_loc, li, cones)
    if cone is not None:
        falloff = falloff * cone
    return dr.select(flag, l_loc, l_dir), dr.select(flag, falloff, 1.0)


@dataclasses.dataclass
class SplatPairs:
    """A view's contributing (surfel, pixel) pairs and blending weights T_i alpha_i."""

    sid: mi.UInt32  # [P]
    pix: mi.UInt32  # [P]
    weight: mi.Float  # [P] detached
    height: int
    width: int

    @functools.cached_property
    def coverage(self) -> mi.Float:
        """sum_i T_i alpha_i per pixel [H * W], the coverage ``splat`` blends with: made
        once per view (the pairs and weights are fixed while stage 4 fits)."""
        out = dr.zeros(mi.Float, self.height * self.width)
        dr.scatter_reduce(dr.ReduceOp.Add, out, self.weight, self.pix)
        dr.eval(out)
        return out


@dataclasses.dataclass
class PixelGeometry:
    """Per-pixel geometry of a view (detached), row-major [H * W]."""

    alpha: mi.Float
    depth: mi.TensorXf  # [H, W, 1]
    normal_img: mi.TensorXf  # [H, W, 3] as rasterized
    normal: mi.Vector3f  # unit (zero where alpha = 0)
    view: mi.Vector3f  # unit, toward the camera
    points: mi.Point3f  # world
    footprint: mi.Float  # world size of each pixel at its depth (visibility's receiver offset)
    # With receivers on the median surface (``surface_aovs``): the pairs that blend them,
    # whose weights are 0 off that surface (what a differentiable normal must splat).
    surface_pairs: SplatPairs | None = None


def splat_pairs(surfels: Surfels, camera: Camera,
                config: RasterConfig = DEFAULT_RASTER) -> SplatPairs:
    """The pair list and weights the rasterizer blends for ``camera`` (no gradient); with
    them ``splat`` reproduces ``rasterize`` channel images exactly (tested)."""
    from mi_shadowgs.core.raster import splat_pairs as raster_pairs

    sid, pix, weight = raster_pairs(surfels, camera, config)
    return SplatPairs(sid, pix, weight, camera.height, camera.width)


def splat(pairs: SplatPairs, values: mi.TensorXf) -> mi.Float:
    """sum_i T_i alpha_i c_i per pixel of per-surfel ``values`` [N, C]: flat [H * W * C]."""
    c = values.shape[1]
    out = dr.zeros(mi.Float, pairs.height * pairs.width * c)
    base = pairs.sid * c
    for k in range(c):
        v = pairs.weight * dr.gather(mi.Float, values.array, base + k)
        dr.scatter_reduce(dr.ReduceOp.Add, out, v, pairs.pix * c + k)
    return out


def per_surface(flat: mi.Float, cover: mi.Float) -> mi.Float:
    """A splatted [H * W * C] image divided by each pixel's coverage ``cover`` [H * W]
    (sum_i T_i alpha_i; 0 where nothing covers it): the blended surface's own value.

    What a pixel covered in part needs for the quantities that do not scale with coverage:
    a roughness or metallic blended over alpha 0.6 is not a smoother, less metallic
    surface, and the indirect irradiance multiplies the albedo, which carries the coverage
    already (alpha^2 otherwise)."""
    c = dr.width(flat) // dr.width(cover)
    idx = dr.arange(mi.UInt32, dr.width(flat))
    w = dr.gather(mi.Float, cover, idx // c)
    return dr.select(w > 0.0, flat / dr.maximum(w, 1e-30), 0.0)


def channel(flat: mi.Float, c: int, k: int) -> mi.Float:
    """Column ``k`` [H * W] of a flat [H * W * C] image."""
    n = dr.width(flat) // c
    return dr.gather(mi.Float, flat, dr.arange(mi.UInt32, n) * c + k)


def pixel_geometry(surfels: Surfels, camera: Camera, config: RasterConfig = DEFAULT_RASTER,
                   surface_band: float = 0.0, pairs: tuple | None = None) -> PixelGeometry:
    """Rasterized alpha, expected depth and normals of a view, plus points and view dirs
    (the normals of ``SHADING_NORMAL_CHANNEL`` where the model has it). ``surface_band`` > 0:
    the depth and normals of the pixel's median surface instead (``surface_aovs``; ``pairs``:
    the view's ``splat_pairs_with_depth`` when the caller has them)."""
    chans, aovs = geometry_request(surfels, camera, surface_band)
    with dr.suspend_grad():
        out = rasterize(surfels, camera, chans, aovs=aovs, config=config)
        pairs = with_surface_aovs(out, surfels, camera, config, surface_band, pairs)
    return dataclasses.replace(geometry_from_aovs(out, camera), surface_pairs=pairs)


def geometry_request(surfels: Surfels, camera: Camera, surface_band: float
                     ) -> tuple[dict, tuple[str, ...]]:
    """(channels, AOVs) a render needs for ``geometry_from_aovs``: the blend's depth and
    normals (and shading normals), or with ``surface_band`` > 0 alpha alone, as
    ``with_surface_aovs`` then adds the median surface's."""
    if surface_band > 0:
        return {}, ("alpha",)
    return geometry_channels(surfels, camera), ("alpha", "depth", "normal")


def with_surface_aovs(out: dict, surfels: Surfels, camera: Camera, config: RasterConfig,
                      surface_band: float, pairs: tuple | None = None) -> SplatPairs | None:
    """Add the median surface's "depth" and "normal" (``surface_aovs``, blended from the
    shading normals) to a render's ``out`` when ``surface_band`` > 0 and return its pairs;
    else leave ``out`` (the blend's, ``geometry_request``) and return None."""
    if surface_band <= 0:
        return None
    surface, aovs = surface_aovs(surfels, camera, surface_band, config, pairs)
    out.update(aovs)
    return surface


def surface_aovs(surfels: Surfels, camera: Camera, band: float,
                 config: RasterConfig = DEFAULT_RASTER, pairs: tuple | None = None
                 ) -> tuple[SplatPairs, dict]:
    """A view's receivers on each pixel's median surface: (the pairs with weights T_i
    alpha_i on that surface and 0 elsewhere, {"depth" [H, W, 1], "normal" [H, W, 3]}); the
    normal is the shading normals facing the camera, blended with those weights and not
    renormalised. A pixel's median surface is its splats whose ray intersection lies within
    ``band`` pixel footprints of the median one's, where the weights, summed front to back
    by intersection depth, reach 0.5 (the last splat where they never do). ``pairs``: the
    view's ``splat_pairs_with_depth``, when the caller has them (else made here).

    The alpha-blended depth and normal of ``rasterize`` mix every surface a pixel overlaps:
    over an object's edge a base pixel's normal bends toward the object's and its point
    floats between them, and over leaves smaller than a pixel the point lies between leaves.
    Stage 5 scores the shadows of the surface at the pixel's centre. The compositing order
    (centre depths) is not the order along the ray for tilted splats, hence the re-sort:
    taken in compositing order, the median lost half of its gain (docs/decisions.md,
    "Receivers on each pixel's median surface")."""
    from mi_shadowgs.core.depth import pixel_footprint
    from mi_shadowgs.core.raster import (
        argsort_bounded,
        depth_key,
        pixel_runs,
        segment_exclusive_sum,
    )

    h, w = camera.height, camera.width
    npix = h * w
    with dr.suspend_grad():
        sid, pix, weight, z = pairs or splat_pairs_with_depth(surfels, camera, config)
        if dr.width(pix) == 0:  # nothing in view (a zero-width array cannot be sorted)
            return SplatPairs(sid, pix, weight, h, w), {
                "depth": mi.TensorXf(dr.zeros(mi.Float, npix), (h, w, 1)),
                "normal": mi.TensorXf(dr.zeros(mi.Float, npix * 3), (h, w, 3))}
        # Each pixel's pairs by intersection depth: a stable sort by depth, then a stable
        # sort by pixel (the order of one sort of 64-bit (pixel, depth) keys, in 3 + 1
        # counting passes instead of 6).
        by_depth = dr.argsort(depth_key(z))
        order = dr.gather(mi.UInt32, by_depth,
                          argsort_bounded(dr.gather(mi.UInt32, pix, by_depth), npix))
        sid, pix, weight, z = (dr.gather(type(x), x, order) for x in (sid, pix, weight, z))
        _, _, first, last = pixel_runs(pix)
        w64 = mi.Float64(weight)
        before = segment_exclusive_sum(w64, pix, first, npix)  # [P] weight in front
        median = (before < 0.5) & ((before + w64 >= 0.5) | last)  # one pair per pixel
        med = dr.zeros(mi.Float, npix)
        dr.scatter(med, z, pix, active=median)
        reach = band * pixel_footprint(mi.TensorXf(med, (h, w, 1)), camera)  # [H * W] world
        near = dr.abs(z - dr.gather(mi.Float, med, pix)) <= dr.gather(mi.Float, reach, pix)
        pairs = SplatPairs(sid, pix, dr.select(near, weight, 0.0), h, w)
        # > 0 wherever a splat covers the pixel: its median pair is on the surface.
        sw = dr.zeros(mi.Float, npix)
        dr.scatter_reduce(dr.ReduceOp.Add, sw, pairs.weight, pix)
        depth = dr.zeros(mi.Float, npix)
        dr.scatter_reduce(dr.ReduceOp.Add, depth, pairs.weight * z, pix)
        depth = depth / dr.select(sw > 0, sw, 1.0)
        n = facing_normals(surfels, camera)
        normal = splat(pairs, mi.TensorXf(dr.ravel(n), (surfels.count, 3)))  # [H * W * 3]
        dr.eval(pairs.weight, depth, normal)
    return pairs, {"depth": mi.TensorXf(depth, (h, w, 1)),
                   "normal": mi.TensorXf(normal, (h, w, 3))}


def splat_pairs_with_depth(surfels: Surfels, camera: Camera,
                           config: RasterConfig = DEFAULT_RASTER) -> tuple:
    """(surfel id, pixel id, weight T_i alpha_i, z-depth) [P] of a view's pairs, detached,
    in compositing order."""
    from mi_shadowgs.core.raster import splat_pairs as raster_pairs

    return raster_pairs(surfels, camera, config, with_depth=True)


def geometry_channels(surfels: Surfels, camera: Camera) -> dict:
    """The channels ``geometry_from_aovs`` reads beside the AOVs: the shading normals
    facing ``camera`` ({} without them)."""
    if SHADING_NORMAL_CHANNEL not in surfels.channels:
        return {}
    n = facing_normals(surfels, camera)
    return {SHADING_NORMAL_CHANNEL: mi.TensorXf(dr.ravel(n), (surfels.count, 3))}


def shading_normals(surfels: Surfels) -> mi.Vector3f:
    """Unit normals [N] for shading: ``SHADING_NORMAL_CHANNEL`` when the model has it, else
    the rotations' third column."""
    if SHADING_NORMAL_CHANNEL in surfels.channels:
        return unit_rows(surfels.channels[SHADING_NORMAL_CHANNEL])
    return surfels.tangent_frame()[2]


def unit_or_zero(v: mi.Vector3f) -> mi.Vector3f:
    """``v`` [P] normalised, 0 where it is (nearly) zero: a blended normal where nothing
    covers the pixel."""
    n2 = dr.squared_norm(v)
    ok = n2 > 1e-12
    return dr.select(ok, v * dr.rsqrt(dr.select(ok, n2, 1.0)), 0.0)


def unit_rows(t: mi.TensorXf) -> mi.Vector3f:
    """The rows of an [N, 3] tensor as unit vectors [N] (differentiable)."""
    return dr.normalize(mi.Vector3f(*(channel(t.array, 3, k) for k in range(3))))


def geometry_from_aovs(out: dict, camera: Camera) -> PixelGeometry:
    """PixelGeometry from a ``rasterize`` result holding "alpha", "depth" and "normal"
    (and the shading normals' channel, when rendered, which then gives the normals)."""
    from mi_shadowgs.core.depth import pixel_footprint, unproject_depth

    with dr.suspend_grad():
        nimg = out.get(SHADING_NORMAL_CHANNEL, out["normal"])
        n = unit_or_zero(mi.Vector3f(*(channel(nimg.array, 3, k) for k in range(3))))
        pts = unproject_depth(out["depth"], camera)
        o = camera.origin
        alpha = out["alpha"].array
        to_cam = mi.Vector3f(mi.Point3f(*(jit.opaque(float(x)) for x in o)) - pts)
        d2 = dr.squared_norm(to_cam)
        # Empty pixels unproject onto the camera centre: no direction there (not NaN).
        ok = (alpha > 0) & (d2 > 0)
        view = dr.select(ok, to_cam * dr.rsqrt(dr.select(ok, d2, 1.0)), 0.0)
        footprint = pixel_footprint(out["depth"], camera)
        dr.eval(n, pts, view, alpha, footprint)
    return PixelGeometry(alpha, out["depth"], nimg, n, view, pts, footprint)


def facing_normals(surfels: Surfels, camera: Camera) -> mi.Vector3f:
    """Each surfel's unit normal [N] flipped to face ``camera`` as the rasterizer flips it
    (``raster.face_camera``), evaluated and detached: where stage 4 and relighting evaluate
    the surfel's indirect light (``eval_sh(sh, normal, offset=0.0)``: max(0, SH(n)) per
    surfel, then blended; a view splats 3 values per pixel-splat pair, not 3 K, and in stage
    4 the backward's scatter-adds of the 27 degree-2 coefficients were most of a step)."""
    with dr.suspend_grad():
        n = face_camera(shading_normals(surfels), dr.detach(surfels.position), camera)
        dr.eval(n)
    return n


def _pixel_light_pairs(geom: PixelGeometry, directions: np.ndarray, positions, center, cones
                       ) -> tuple[mi.UInt32, mi.Vector3f, mi.Vector3f, mi.Float | None]:
    """Per (pixel, light) pair [H * W * K], pixel-major: (the pixel's index, its normal, the
    unit direction toward the light, the light's irradiance factor: ``light_vectors``)."""
    k_count = len(directions)
    idx = dr.arange(mi.UInt32, dr.width(geom.alpha) * k_count)
    pi, li = idx // k_count, idx % k_count
    points = None if positions is None else dr.gather(mi.Point3f, geom.points, pi)
    l_dir, falloff = light_vectors(points, li, directions, positions, center, cones)
    return pi, dr.gather(mi.Vector3f, geom.normal, pi), l_dir, falloff


def direct_per_light(geom: PixelGeometry, albedo: mi.Color3f, roughness: mi.Float,
                     metallic: mi.Float, directions: np.ndarray, vis: mi.Float | None,
                     with_specular: bool, positions=None, center=None,
                     cones=None) -> mi.Color3f:
    """f_r (n . l_k)^+ V_k per pixel and light, unit weight: [H * W * K] pixel-major.

    ``directions`` [K, 3]; ``vis`` [H * W * K] pixel-major (None: V = 1). With
    ``positions`` and ``center`` (see ``light_vectors``), local lights shine from their
    position with 1/r^2 falloff, their unit weight being the irradiance at ``center``;
    ``cones`` (``LightSet.cones``) shape the spots among them.
    """
    pi, n, l_dir, falloff = _pixel_light_pairs(geom, directions, positions, center, cones)
    a = dr.gather(mi.Color3f, albedo, pi)
    m = dr.gather(mi.Float, metallic, pi)
    if with_specular:
        v = dr.gather(mi.Vector3f, geom.view, pi)
        r = dr.gather(mi.Float, roughness, pi)
        f = brdf.cook_torrance(n, l_dir, v, a, r, m, with_specular=True)
    else:
        f = brdf.diffuse(n, l_dir, a, m)
    if falloff is not None:
        f = f * falloff
    return f * vis if vis is not None else f


def cosine_per_light(geom: PixelGeometry, directions: np.ndarray, vis: mi.Float | None,
                     positions=None, center=None, cones=None) -> mi.Float:
    """(n . l_k)^+ V_k per pixel and light, times a local light's falloff: [H * W * K]
    pixel-major (``direct_per_light``'s diffuse term without (1 - m) a / pi)."""
    _, n, l_dir, falloff = _pixel_light_pairs(geom, directions, positions, center, cones)
    out = dr.maximum(dr.dot(n, l_dir), 0.0)
    if falloff is not None:
        out = out * falloff
    return out * vis if vis is not None else out


def direct(geom: PixelGeometry, albedo: mi.Color3f, roughness: mi.Float, metallic: mi.Float,
           lights: LightSet, vis: mi.Float | None, with_specular: bool) -> mi.Color3f:
    """sum_k f_r (n . l_k)^+ V_k E_k per pixel [H * W]; ``vis`` is [H * W * K] pixel-major
    (None: V = 1, the "w/o visibility" ablation). Without the lobe, (1 - m) a / pi leaves
    the sum: the per-(pixel, light) kernels, forward and backward, then touch no material."""
    k_count = lights.count
    npix = dr.width(geom.alpha)
    li = dr.arange(mi.UInt32, npix * k_count) % k_count
    e = dr.gather(mi.Color3f, lights.weights, li)
    if with_specular:
        contrib = direct_per_light(geom, albedo, roughness, metallic, lights.directions, vis,
                                   True, lights.positions, lights.center, lights.cones) * e
    else:
        contrib = cosine_per_light(geom, lights.directions, vis, lights.positions,
                                   lights.center, lights.cones) * e
    # The three channels in one kernel: each block_reduce evaluates its own input, and left
    # lazy every channel would redo the per-light shading and shadow-map lookups [H * W * K]
    # (at K = 128, the warm-up's and an env map's grid, 3x the work).
    dr.eval(contrib)
    out = mi.Color3f(*(dr.block_reduce(dr.ReduceOp.Add, contrib[c], k_count)
                       for c in range(3)))
    return out if with_specular else albedo * ((1.0 - metallic) / math.pi) * out


def shade(geom: PixelGeometry, albedo: mi.Color3f, roughness: mi.Float, metallic: mi.Float,
          lights: LightSet, vis: mi.Float | None, indirect: mi.Color3f | None,
          with_specular: bool) -> mi.Color3f:
    """Outgoing radiance per pixel (Eq. 17 with the closed-form indirect term)."""
    out = direct(geom, albedo, roughness, metallic, lights, vis, with_specular)
    if indirect is not None:
        out = out + (1.0 - metallic) * albedo * indirect
    return out
