"""Pixelwise directional visibility from shadow maps of the surfels' depth (paper Eq. 6-7).

For a light direction ``l`` a virtual camera looks at the scene from far along ``l``
(perspective at ``distance_factor`` times the mean training-camera distance, as in the paper,
or orthographic) and the surfels' depth is rasterized into a shadow map. A view pixel is
unprojected to its surface point ``x``; projected into the map it has depth ``d_l`` and the map
holds ``d_g``; ``V = [(d_l - d_g) / (d_l + eps) <= tau]``. The ``cpu-small`` preset tests
``d_l - d_g <= 1 texel`` instead, with ``d_g`` raised per texel by the occluder layer's slack
(``VisibilityConfig.layer_bias``): tau's fixed margin hides contact shadows.

A shadow map depends on the light, not on the view: ``render_shadow_maps`` renders each once
and every view reuses them. Lookups for all pixels and all directions run in one Dr.Jit pass.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.depth import pixel_footprint, unproject_depth
from mi_shadowgs.core.raster import RasterConfig
from mi_shadowgs.stages.visibility import lamp_maps

PROJECTIONS = ("perspective", "orthographic")
DEPTH_KINDS = ("median", "expected")


@dataclasses.dataclass(frozen=True)
class VisibilityConfig:
    """Shadow-map visibility settings; defaults are the paper's (Sec. V-A1)."""

    resolution: int = 512  # shadow-map width = height, pixels
    projection: str = "perspective"  # "perspective" (paper) or "orthographic"
    distance_factor: float = 30.0  # virtual camera distance / mean training-camera distance
    tau: float = 0.0008  # relative depth threshold of Eq. 6
    # Absolute depth threshold in map texels (not in the paper): V = [d_l - d_g <= bias_texels
    # * texel] replaces Eq. 6-7's relative tau when set. tau is a fraction of the light
    # camera's depth, and that camera stands at distance_factor x the cameras' distance:
    # tau = 8e-4 lets an occluder ~0.1 scene units in front of its receiver through, which
    # erases contact shadows (the hotdog's sausages on their plate). A few texels (~0.01
    # units each at 512^2) cover what the threshold is for: the surfels' own depth spread
    # between the view's and the light's rasterization.
    bias_texels: float | None = None
    # Depth slack per texel from the occluder layer's own thickness (not in the paper; in
    # the spirit of Woo's midpoint shadow maps): each texel's depth becomes median d +
    # min(layer_bias * |E[d] - median d|, layer_cap_texels * texel), both depths rasterized
    # from the light. A fitted surface is a few surfels thick, and a receiver unprojected
    # from a view's median depth can sit anywhere in that layer: where the layer is thick a
    # fixed threshold must be large (tau's ~14 texels) and erases contact shadows, where it
    # is thin a small one suffices. The slack follows the layer texel by texel; the cap
    # keeps silhouettes (where E[d] mixes occluder and background) from opening holes.
    # 0: off (the paper's single depth).
    layer_bias: float = 0.0
    layer_cap_texels: float = 3.0
    # The slack is also at least the depth step to the deepest occupied texel within this
    # many texels (0: the texel alone). At grazing light a surface's map depth changes by
    # several texels per texel, and a receiver looked up one texel off lands behind its own
    # surface: isolated dark specks in relit views. The cap bounds it as above.
    layer_window: int = 0
    eps: float = 1e-6  # the epsilon of Eq. 7
    depth: str = "median"  # which rasterized depth the map holds: "median" or "expected"
    empty_alpha: float = 0.5  # map pixels with less accumulated alpha hold no occluder
    margin: float = 1.02  # the map frustum covers the scene's bounding sphere times this
    # Push each point off its surface by normal_offset * texel * sin(angle(n, l)) before the
    # lookup. A shadow map samples the occluder depth at texel centres, so a surface tilted by
    # that angle differs from its own map depth by up to ~0.71 texel * tan(angle); the offset
    # moves the point 1.5 texel * sin / cos = 1.5 texel * tan in front of its own surface
    # along l, which removes self-shadowing ("acne") at every angle up to the horizon.
    # The paper uses tau alone (normal_offset = 0); that leaves acne at grazing light.
    normal_offset: float = 1.5
    # Receiver points unprojected from a rendered depth map are only known to about the size
    # of their pixel: a fitted surface can be a few pixel-sized surfels thick, and a view's
    # depth blends them. Lift such points by receiver_offset * (the pixel's footprint) along
    # n so that the surfels of their own pixel do not shadow them. Applies only when the
    # caller gives footprints (exact points, e.g. ray-traced depth, get none). 0: since
    # stage 1 weights its distortion term enough to collapse those layers (lambda_d 3e4),
    # the lift only costs contact shadows (stage-1 surfels, default / bunny visibility IoU:
    # 0.882 / 0.837 at 0, 0.883 / 0.817 at 0.5); with the earlier, layered fits 0.5 took the
    # default scene from 0.819 to 0.836 (docs/decisions.md, "No receiver lift").
    receiver_offset: float = 0.0
    # Which surface of a pixel receives the light (not in the paper), in stage 4's fit, stage
    # 5's evaluation, relighting and the viewer alike: 0 (the paper's deferred shading) takes
    # the alpha-blended depth and normal; > 0 only the splats within this many pixel
    # footprints of the pixel's median depth (``shading.surface_aovs``), so that a base
    # pixel beside an object keeps the base's normal and a pixel over leaves one leaf's.
    receiver_band: float = 0.0
    pcf: int = 0  # soft visibility: average over a (2 pcf + 1)^2 texel window (0 = hard)
    # n . l at or below this is "light below the surface's horizon": V = 0. Not exactly 0:
    # float32 normals of a flat surface carry ~1e-7 tilts that would make a light exactly
    # at the horizon flicker between lit and unlit.
    horizon_cos: float = 1e-4
    # Fractional visibility for thin and semi-transparent occluders (not in the paper; an
    # opacity shadow map with one layer): each texel keeps its accumulated alpha a beside its
    # depth, every texel with a >= fractional_min_alpha holds an occluder, and a receiver
    # behind it gets V = 1 - a instead of 0. At 128^2 a leaf a few pixels wide covers a
    # texel partly: the binary test (empty below empty_alpha, else solid) casts a solid blob
    # where the truth is dappled. False: the paper's binary test.
    fractional: bool = False
    fractional_min_alpha: float = 0.05
    # Soft shadows of a lamp with a radius (``lamp_maps``): one map from each of this many
    # points spread evenly over its disc facing the scene, V the mean of their lookups;
    # 0: one map from its centre (hard shadows). Why 16: docs/decisions.md.
    lamp_samples: int = 16
    # The maps' rasterization: forward-only renders of 256^2-512^2 composite faster with
    # larger tiles and more pixels per lane than the views' training renders (which keep
    # 4x4 / 2), and bit-identically (docs/decisions.md).
    raster: RasterConfig = RasterConfig(tile_size=8, pixels_per_lane=4)

    def __post_init__(self):
        if self.projection not in PROJECTIONS:
            raise ValueError(f"visibility projection must be one of {PROJECTIONS}, "
                             f"got {self.projection!r}")
        if self.depth not in DEPTH_KINDS:
            raise ValueError(f"visibility depth must be one of {DEPTH_KINDS}, got {self.depth!r}")
        if (self.resolution < 1 or self.distance_factor <= 1.0 or self.tau < 0 or self.pcf < 0
                or (self.bias_texels is not None and self.bias_texels < 0)
                or self.normal_offset < 0 or self.receiver_offset < 0 or self.receiver_band < 0
                or self.layer_bias < 0 or self.layer_cap_texels < 0 or self.layer_window < 0
                or self.lamp_samples < 0
                or not 0.0 < self.fractional_min_alpha <= 1.0):
            raise ValueError(f"invalid visibility settings: {self}")


@dataclasses.dataclass(frozen=True)
class SceneBounds:
    """Where the occluders are and how far the training cameras stand.

    Every visibility method (shadow maps here, the baselines in ``visibility_baselines``)
    is built from surfels, light directions and these bounds, and then answers
    ``evaluate(points, normals) -> V [P * L]``.
    """

    center: tuple  # [3] centre of the occluders' bounding sphere (paper: surfel centroid)
    radius: float  # radius of that sphere
    mean_camera_distance: float  # mean distance of the training cameras to ``center``

    @staticmethod
    def from_points(points: np.ndarray, cameras: Sequence[Camera], quantile: float = 1.0
                    ) -> SceneBounds:
        """Bounds of points [M, 3] (e.g. surfel centres) around their centroid.

        ``quantile`` < 1 ignores the farthest points (floaters) when sizing the sphere.
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise ValueError(f"SceneBounds.from_points: need points [M, 3], got {pts.shape}")
        center = pts.mean(axis=0)
        radius = float(np.quantile(np.linalg.norm(pts - center, axis=1), quantile))
        return SceneBounds(tuple(center.tolist()), max(radius, 1e-6),
                           mean_camera_distance(cameras, center))


def mean_camera_distance(cameras: Sequence[Camera], center: np.ndarray) -> float:
    if not cameras:
        raise ValueError("mean_camera_distance: no cameras")
    c = np.asarray(center, dtype=np.float64)
    return float(np.mean([np.linalg.norm(cam.origin - c) for cam in cameras]))


@dataclasses.dataclass
class ShadowMaps:
    """Shadow maps for L light directions, rendered once and shared by every view."""

    directions: np.ndarray  # [L, 3] unit, toward the light
    cameras: list[Camera]  # L virtual cameras
    # [L * R * R] map depth (with the layer slack when config.layer_bias > 0), +inf where
    # no occluder
    depth: mi.Float
    resolution: int
    config: VisibilityConfig
    texel: float  # size of one map texel at the scene centre, scene units
    alpha: mi.Float | None = None  # [L * R * R] accumulated alpha (config.fractional only)
    # Local lights (``lamp_maps``): [L, 3] lamp centres, NaN rows for directional lights
    # (None: every light directional), [L] their radii, and [M] the light of each of the M
    # maps (None: one map per light; a soft lamp has several, consecutive). ``cameras``,
    # ``depth`` and ``alpha`` then hold M maps.
    positions: np.ndarray | None = None
    radii: np.ndarray | None = None
    map_light: np.ndarray | None = None
    # The lookup's per-light arrays (``_camera_rows`` and the directions), made at the first
    # ``point_visibility``: a stage-4 step evaluates the same maps again and again, and 128
    # cameras' inverses and host copies cost ~1 ms each time.
    _lookup: tuple | None = dataclasses.field(default=None, init=False, repr=False,
                                              compare=False)

    def lookup_arrays(self) -> tuple:
        """(12 world->CV rows [L], focal [L], principal point [L], direction [L] x, y, z)."""
        if self._lookup is None:
            rows, focal, cx = _camera_rows(self.cameras)
            light = tuple(jit.array(self.directions[:, k]) for k in range(3))
            self._lookup = (rows, focal, cx, light)
        return self._lookup

    @property
    def count(self) -> int:
        """The number of lights (of V's columns)."""
        return len(self.directions)

    def subset(self, keep: np.ndarray) -> ShadowMaps:
        """The maps of the lights ``keep`` [L] bool (no re-rendering: a gather of their
        texels)."""
        idx = np.flatnonzero(keep)
        light = (np.arange(len(self.cameras)) if self.map_light is None
                 else np.asarray(self.map_light))
        maps_idx = np.flatnonzero(np.isin(light, idx))
        r2 = self.resolution * self.resolution
        tex = (maps_idx[:, None] * r2 + np.arange(r2)[None]).reshape(-1).astype(np.uint32)
        depth = dr.gather(mi.Float, self.depth, mi.UInt32(tex))
        alpha = None if self.alpha is None else dr.gather(mi.Float, self.alpha, mi.UInt32(tex))
        dr.eval(depth, alpha)
        local = dict(positions=None, radii=None, map_light=None)
        if self.positions is not None and np.isfinite(self.positions[idx]).all(1).any():
            remap = np.full(len(self.directions), -1)
            remap[idx] = np.arange(len(idx))
            local = dict(positions=self.positions[idx], radii=self.radii[idx],
                         map_light=None if self.map_light is None else remap[light[maps_idx]])
        return dataclasses.replace(self, directions=self.directions[idx],
                                   cameras=[self.cameras[i] for i in maps_idx], depth=depth,
                                   alpha=alpha, **local)

    def evaluate(self, points: mi.Point3f, normals: mi.Vector3f | None = None,
                 footprint: mi.Float | None = None) -> mi.Float:
        """V [P * L] (point-major) for surface points [P], evaluated; see
        ``point_visibility``. Evaluated here because its readers are many: a lazy V would be
        recomputed (the L maps' lookups) in each kernel that reads it, a stage-4 step's
        forward and backward or a relit view's image and irradiance (a third of a warm-up
        step at L = 128)."""
        vis = point_visibility(points, self, normals, footprint)
        dr.eval(vis)
        return vis

    def depth_image(self, index: int) -> np.ndarray:
        """Shadow map ``index`` as [R, R] numpy (inf = empty), for inspection and plots."""
        r = self.resolution
        return (np.asarray(self.depth, dtype=np.float64)[index * r * r:(index + 1) * r * r]
                .reshape(r, r))


def shadow_camera(direction: np.ndarray, center: np.ndarray, radius: float,
                  mean_camera_distance: float, config: VisibilityConfig,
                  resolution: int | None = None) -> Camera:
    """The virtual camera that looks at ``center`` from far along ``direction`` [3], of
    ``resolution`` texels a side (default ``config.resolution``)."""
    resolution = resolution or config.resolution
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    center = np.asarray(center, dtype=np.float64)
    distance = config.distance_factor * mean_camera_distance
    reach = radius * config.margin
    if distance <= reach:
        raise ValueError(f"shadow camera at distance {distance:.3g} lies inside the scene "
                         f"bound of radius {reach:.3g}; increase distance_factor")
    # Up vector: any direction not parallel to d (lights at the zenith are common).
    up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.99 else np.array([0.0, 0.0, -1.0])
    kw = dict(width=resolution, height=resolution,
              near=max(1e-4, distance - 2.0 * reach), far=distance + 2.0 * reach)
    if config.projection == "orthographic":
        return Camera.look_at(center + d * distance, center, up, ortho_width=2.0 * reach, **kw)
    fov = 2.0 * math.asin(min(1.0, reach / distance))
    return Camera.look_at(center + d * distance, center, up, fov_x=fov, **kw)


def render_shadow_maps(surfels, directions: np.ndarray, bounds: SceneBounds,
                       config: VisibilityConfig = VisibilityConfig(),
                       resolution: int | None = None, positions: np.ndarray | None = None,
                       radii: np.ndarray | None = None) -> ShadowMaps:
    """Rasterize the surfels' depth from each of ``directions`` [L, 3] (one map per light),
    ``resolution`` texels a side (default ``config.resolution``; stage 4's coarse maps).

    ``positions`` [L, 3] (NaN rows: directional lights) and ``radii`` [L] make lights local:
    perspective maps from the lamp, ``config.lamp_samples`` of them over the disc of a lamp
    with a radius (``lamp_maps``; ``lamp_arguments`` gives both from a ``LightSet``)."""
    directions = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    center = np.asarray(bounds.center, dtype=np.float64)
    res = resolution or config.resolution
    lamps = lamp_maps.checked_lamps(positions, radii, len(directions))
    if lamps is None:
        cams = [shadow_camera(d, center, bounds.radius, bounds.mean_camera_distance, config,
                              res) for d in directions]
        depth, alpha = _render_depths(surfels, cams, None, bounds, config, res)
        return ShadowMaps(directions, cams, depth, res, config, map_texel(bounds, config, res),
                          alpha)
    pos, rad = lamps
    cams, light, local = [], [], []
    reach = bounds.radius * config.margin
    for k, d in enumerate(directions):
        if not np.isfinite(pos[k]).all():
            cams.append(shadow_camera(d, center, bounds.radius, bounds.mean_camera_distance,
                                      config, res))
            light.append(k)
            local.append(False)
            continue
        for q in lamp_maps.lamp_points(pos[k], rad[k], center, config.lamp_samples):
            cams.append(lamp_maps.lamp_camera(q, center, reach, res, f"lamp {k}"))
            light.append(k)
            local.append(True)
    depth, alpha = _render_depths(surfels, cams, local, bounds, config, res)
    light = np.asarray(light)
    return ShadowMaps(directions, cams, depth, res, config, map_texel(bounds, config, res),
                      alpha, pos, rad, None if len(light) == len(directions) else light)


def _render_depths(surfels, cams: list[Camera], lamps: list[bool] | None, bounds: SceneBounds,
                   config: VisibilityConfig, res: int) -> tuple[mi.Float, mi.Float | None]:
    """The maps' depth [M * R * R] (and alpha with ``config.fractional``) of ``cams``; the
    texel of a lamp's map (``lamps``) is z-depth / focal, the others' ``map_texel``."""
    from mi_shadowgs.core.raster import rasterize

    key = "median_depth" if config.depth == "median" else "depth"
    aovs = ("alpha", "median_depth", "depth") if config.layer_bias > 0 else ("alpha", key)
    texel = map_texel(bounds, config, res)
    min_alpha = config.fractional_min_alpha if config.fractional else config.empty_alpha
    texels = res * res
    depth = dr.empty(mi.Float, len(cams) * texels)  # [M * R * R]
    alpha = dr.empty(mi.Float, len(cams) * texels) if config.fractional else None
    local = dr.arange(mi.UInt32, texels)
    with dr.suspend_grad():
        for i, cam in enumerate(cams):
            is_lamp = lamps is not None and lamps[i]
            raster = lamp_maps.lamp_raster(config.raster, cam) if is_lamp else config.raster
            out = rasterize(surfels, cam, None, aovs=aovs, config=raster)
            d = out[key].array
            empty = (out["alpha"].array < min_alpha) | (d <= 0)
            if config.layer_bias > 0:
                spread = dr.abs(out["depth"].array - out["median_depth"].array)
                slack = config.layer_bias * spread
                if config.layer_window > 0:
                    step = _window_max(dr.select(empty, -dr.inf, d), res,
                                       config.layer_window) - d
                    slack = dr.maximum(slack, step)
                cap = (config.layer_cap_texels / cam.focal) * d if is_lamp else (
                    config.layer_cap_texels * texel)
                d = d + dr.minimum(slack, cap)
            # Each map written into its slice by its own kernel, the same for every map and
            # light count (the offset opaque). Left lazy and joined by dr.concat, the maps'
            # post-processing fused into one kernel whose size (L maps) was in its source:
            # 35k operations and ~11 s to compile for each new count (129 candidates).
            at = local + jit.opaque(i * texels, mi.UInt32)
            dr.scatter(depth, dr.select(empty, dr.inf, d), at)
            if alpha is not None:
                dr.scatter(alpha, dr.clip(out["alpha"].array, 0.0, 1.0), at)
            dr.eval(depth, *(() if alpha is None else (alpha,)))
    return depth, alpha


class MapCache:
    """Shadow maps of one set of occluders by light, rendered once each.

    A map depends on the surfels, the bounds, the visibility settings and its light (a
    direction, or a lamp's position and radius), never on the view or the materials:
    ``maps(directions, config)`` renders only the lights not held (the new ones in one
    ``render_shadow_maps``, each map by its own kernel, so a held map equals a fresh one)
    and assembles the set. Stage 4's refinement asks again for maps it has (the candidates'
    current direction, the lights after a move), and the relighting for every light it has
    seen. At most ``max_bytes`` of maps are held, the least recently used dropped first.
    """

    def __init__(self, surfels, bounds: SceneBounds, max_bytes: int = 256 << 20):
        self.surfels, self.bounds, self.max_bytes = surfels, bounds, max_bytes
        # key -> (cameras, depths, alphas or None, texel): a soft lamp's several maps
        self._maps: dict[tuple, tuple] = {}
        self._bytes = 0
        self.rendered = 0  # maps rendered (not reused), for tests and benchmarks

    @staticmethod
    def _key(config: VisibilityConfig, resolution: int, direction) -> tuple:
        return config, resolution, np.asarray(direction, np.float64).round(12).tobytes()

    @staticmethod
    def _lamp_key(config: VisibilityConfig, resolution: int, position, radius) -> tuple:
        return (config, resolution, "lamp", np.asarray(position, np.float64).round(12).tobytes(),
                round(float(radius), 12))

    def maps(self, directions: np.ndarray, config: VisibilityConfig,
             resolution: int | None = None, positions: np.ndarray | None = None,
             radii: np.ndarray | None = None) -> ShadowMaps:
        """``render_shadow_maps(surfels, directions, bounds, config, resolution, positions,
        radii)``, reusing held maps."""
        resolution = resolution or config.resolution
        dirs = np.atleast_2d(np.asarray(directions, np.float64))
        lamps = lamp_maps.checked_lamps(positions, radii, len(dirs))
        pos, rad = lamps if lamps is not None else (np.full((len(dirs), 3), np.nan),
                                                     np.zeros(len(dirs)))
        local = np.isfinite(pos).all(axis=1)
        keys = [self._lamp_key(config, resolution, pos[i], rad[i]) if local[i]
                else self._key(config, resolution, d) for i, d in enumerate(dirs)]
        todo = list(dict.fromkeys(k for k in keys if k not in self._maps))
        if todo:
            first = [{k: i for i, k in reversed(list(enumerate(keys)))}[k] for k in todo]
            new = render_shadow_maps(self.surfels, dirs[first], self.bounds, config,
                                     resolution, **({} if lamps is None else
                                                    {"positions": pos[first],
                                                     "radii": rad[first]}))
            self._hold(todo, new)
        for k in keys:  # most recently used last
            self._maps[k] = self._maps.pop(k)
        parts = [self._maps[k] for k in keys]
        cams = [c for p in parts for c in p[0]]
        maps = ShadowMaps(dirs, cams, _joined([d for p in parts for d in p[1]]),
                          resolution, config, parts[0][3],
                          None if parts[0][2] is None
                          else _joined([a for p in parts for a in p[2]]))
        if lamps is not None:
            light = np.repeat(np.arange(len(parts)), [len(p[0]) for p in parts])
            maps = dataclasses.replace(maps, positions=pos, radii=rad,
                                       map_light=None if len(light) == len(dirs) else light)
        while self._bytes > self.max_bytes and len(self._maps) > len(set(keys)):
            _, depths, alphas, _ = self._maps.pop(next(iter(self._maps)))
            self._bytes -= 4 * sum(dr.width(d) for d in depths) * (1 if alphas is None else 2)
        return maps

    def _hold(self, todo: list, new: ShadowMaps) -> None:
        """Keep each light's maps of ``new`` (rendered for the lights ``todo``, in order)."""
        r2 = new.resolution * new.resolution
        light = (np.arange(len(new.cameras)) if new.map_light is None
                 else np.asarray(new.map_light))
        for j, k in enumerate(todo):
            depths, alphas = [], None if new.alpha is None else []
            ms = np.flatnonzero(light == j)
            for m in ms:
                part = dr.arange(mi.UInt32, m * r2, (m + 1) * r2)
                one = len(new.cameras) == 1
                depths.append(new.depth if one else dr.gather(mi.Float, new.depth, part))
                if alphas is not None:
                    alphas.append(new.alpha if one else dr.gather(mi.Float, new.alpha, part))
                dr.eval(depths[-1], *(() if alphas is None else (alphas[-1],)))
            self._maps[k] = ([new.cameras[m] for m in ms], depths, alphas, new.texel)
            self._bytes += 4 * r2 * len(ms) * (1 if alphas is None else 2)
        self.rendered += len(new.cameras)


def _joined(parts: list) -> mi.Float:
    """Evaluated arrays of one size laid end to end, evaluated: each copied by the same
    kernel (an opaque offset; ``dr.concat`` compiles one per count of parts)."""
    if len(parts) == 1:
        return parts[0]
    n = dr.width(parts[0])
    out = dr.empty(mi.Float, n * len(parts))
    local = dr.arange(mi.UInt32, n)
    for i, part in enumerate(parts):
        dr.scatter(out, part, local + jit.opaque(i * n, mi.UInt32))
        dr.eval(out)
    return out


def _window_max(image: mi.Float, resolution: int, radius: int) -> mi.Float:
    """Max over the (2 radius + 1)^2 window of each texel of an [R * R] image (clamped at
    the borders)."""
    r = resolution
    idx = dr.arange(mi.Int32, r * r)
    x, y = idx % r, idx // r
    out = image
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dx or dy:
                xx, yy = dr.clip(x + dx, 0, r - 1), dr.clip(y + dy, 0, r - 1)
                out = dr.maximum(out, dr.gather(mi.Float, image, mi.UInt32(yy * r + xx)))
    return out


def map_texel(bounds: SceneBounds, config: VisibilityConfig,
              resolution: int | None = None) -> float:
    """One map texel at the scene centre, scene units: the same for every light direction.
    From the map's design (``shadow_camera``'s distance and reach), not from a light's
    camera: the cameras' origins differ in their last bits from direction to direction, so
    a map's texel would depend on the light that came first in its batch (the relight
    cache keeps maps rendered in other batches)."""
    resolution = resolution or config.resolution
    distance = config.distance_factor * bounds.mean_camera_distance
    reach = bounds.radius * config.margin
    if config.projection == "orthographic":
        return 2.0 * reach / resolution
    half = min(1.0, reach / distance)  # sin of the half field of view
    return 2.0 * half / math.sqrt(max(1.0 - half * half, 1e-12)) * distance / resolution


def _camera_rows(cameras: Sequence[Camera]) -> tuple[list[mi.Float], mi.Float, mi.Float]:
    """Per-light world->CV rows (12 arrays of length L), focal and principal point."""
    w2c = np.stack([c.world_to_cv()[:3, :4] for c in cameras])  # [L, 3, 4]
    rows = [jit.array(w2c[:, i, j]) for i in range(3) for j in range(4)]
    focal = jit.array(np.array([c.focal for c in cameras]))
    cx = jit.array(np.array([c.principal_point[0] for c in cameras]))
    return rows, focal, cx


def lift_receivers(points: mi.Point3f, normals: mi.Vector3f | None,
                   footprint: mi.Float | None, amount: float) -> mi.Point3f:
    """``points`` [P] moved ``amount * footprint`` [P] along ``normals`` [P] (see
    ``VisibilityConfig.receiver_offset``); unchanged without normals or footprints."""
    if normals is None or footprint is None or amount <= 0:
        return points
    return mi.Point3f(points + normals * (footprint * amount))


def point_visibility(points: mi.Point3f, maps: ShadowMaps, normals: mi.Vector3f | None = None,
                     footprint: mi.Float | None = None) -> mi.Float:
    """V(x, l) for P points and the L maps' directions, flattened point-major: [P * L].

    ``points`` [P] are surface points in world space; with ``normals`` [P] the horizon is
    exact (V = 0 where n . l <= horizon_cos) and the normal offset applies; with
    ``footprint`` [P] (points from a rendered depth map) the receiver offset too. Soft (PCF)
    when ``maps.config.pcf > 0``, or for a lamp with a radius, else in {0, 1}. For a lamp
    the direction l is the point's own, toward the lamp (``lamp_maps``).
    """
    cfg = maps.config
    points = lift_receivers(points, normals, footprint, cfg.receiver_offset)
    if maps.positions is not None:
        return lamp_maps.lamp_visibility(points, maps, normals)
    n_lights = maps.count
    n_points = dr.width(points)
    r = maps.resolution
    idx = dr.arange(mi.UInt32, n_points * n_lights)
    pi, li = idx // n_lights, idx % n_lights
    p = dr.gather(mi.Point3f, points, pi)
    rows, focal_l, cx_l, light_l = maps.lookup_arrays()
    m = [dr.gather(mi.Float, row, li) for row in rows]
    focal = dr.gather(mi.Float, focal_l, li)
    c = dr.gather(mi.Float, cx_l, li)  # square maps: cx == cy
    light = mi.Vector3f(*(dr.gather(mi.Float, d, li) for d in light_l))
    facing = mi.Bool(True)
    if normals is not None:
        n = dr.gather(mi.Vector3f, normals, pi)
        cos = dr.dot(n, light)
        facing = cos > cfg.horizon_cos
        if cfg.normal_offset > 0:
            sin = dr.safe_sqrt(1.0 - dr.square(dr.clip(cos, -1.0, 1.0)))
            p = p + n * (cfg.normal_offset * maps.texel * sin)
    x = m[0] * p.x + m[1] * p.y + m[2] * p.z + m[3]
    y = m[4] * p.x + m[5] * p.y + m[6] * p.z + m[7]
    z = m[8] * p.x + m[9] * p.y + m[10] * p.z + m[11]
    if cfg.projection == "orthographic":
        u, v = focal * x + c, focal * y + c
    else:
        inv_z = dr.rcp(dr.maximum(z, 1e-12))
        u, v = focal * x * inv_z + c, focal * y * inv_z + c
    absolute = cfg.bias_texels is not None
    bias = mi.Float(cfg.bias_texels * maps.texel if absolute else cfg.tau)
    vis = lamp_maps.window_lookup(maps, cfg, li * (r * r), u, v, z, bias, mi.Bool(True),
                                  absolute)
    return dr.select(facing, vis, 0.0)


def view_visibility(depth: mi.TensorXf, camera: Camera, maps,
                    normal: mi.TensorXf | None = None, rendered: bool = True) -> mi.TensorXf:
    """Visibility [H, W, L] of a view from its z-depth [H, W, 1] (and normals [H, W, 3]).

    ``maps`` is any visibility method with ``evaluate(points, normals, footprint)`` and
    ``count``. ``rendered``: the depth was rasterized from surfels, so the receiver offset
    applies (False for exact, e.g. ray-traced, depth).
    """
    h, w = depth.shape[0], depth.shape[1]
    points = unproject_depth(depth, camera)
    normals = None
    if normal is not None:
        flat = normal.array
        idx = dr.arange(mi.UInt32, h * w)
        normals = dr.normalize(mi.Vector3f(dr.gather(mi.Float, flat, idx * 3),
                                           dr.gather(mi.Float, flat, idx * 3 + 1),
                                           dr.gather(mi.Float, flat, idx * 3 + 2)))
    footprint = pixel_footprint(depth, camera) if rendered else None
    vis = maps.evaluate(points, normals, footprint)
    return mi.TensorXf(vis, (h, w, maps.count))
