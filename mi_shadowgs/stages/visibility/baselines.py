"""Baseline visibility methods for the paper's Table 2, behind the shadow-map interface.

Each is built from surfels, light directions [L, 3] and ``visibility.SceneBounds`` and then
answers ``evaluate(points [P], normals [P] | None) -> V [P * L]`` (point-major), like
``visibility.ShadowMaps``, so ``visibility.view_visibility`` accepts any of them.

- **Gaussian-based** (IRGS-style, ``trace_surfels``): shadow rays are ray-traced through the
  surfels themselves. Each surfel becomes a quad of half-size ``extent`` sigma in one
  ``mi.Mesh`` that Embree traces; a hit's alpha ``opacity * exp(-(u^2 + v^2) / 2)`` is
  computed in Dr.Jit from the surfel index and the hit's local coordinates, and the
  transmittance is the product of ``1 - alpha`` over the successive hits (at most
  ``max_hits``). Surfels sampled on one plane are coplanar, so their quads would be hit at
  the same distance and all but the first skipped; each quad is therefore moved along its
  normal by a small random per-surfel stagger (a fraction of sigma) that separates them in t.
- **Voxel-based** (GS-IR-style, ``voxelize_surfels``): the surfels' opacity is splatted into
  an occupancy grid over the occluders' bounding cube; a shadow ray marches through the grid
  (trilinear lookups) and accumulates optical depth ``density * occupancy / voxel`` per
  unit length; ``V = exp(-optical depth)``. The march starts ``start_offset`` voxels away
  from the surface so that the receiver's own voxel does not shadow it.

Both return hard visibility (T >= 0.5) unless ``soft`` is set, and V = 0 where normals are
given and ``n . l <= 0`` (the convention of ``visibility.point_visibility``).
"""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit
from mi_shadowgs.core.frames import quaternion_to_matrix
from mi_shadowgs.stages.visibility.shadow_maps import lift_receivers


# -- configs ------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class GaussianTraceConfig:
    """Ray tracing through the surfels (IRGS-like "Gaussian-based" visibility)."""

    extent: float = 3.0  # quad half-size in standard deviations (alpha < 1.1% beyond it)
    max_hits: int = 32  # bound on successive hits per shadow ray
    alpha_min: float = 1.0 / 255.0  # surfels with a lower opacity are not traced
    alpha_max: float = 0.99  # as the rasterizer: keeps one hit from being fully opaque
    offset: float = 1.0  # ray origin pushed along the normal by this many median sigmas
    receiver_offset: float = 0.0  # as VisibilityConfig.receiver_offset (pixel footprints)
    stagger: float = 0.2  # per-surfel random normal shift range, in median sigmas (module doc)
    seed: int = 0  # of the stagger
    soft: bool = False  # return the transmittance instead of [T >= 0.5]
    t_min: float = 1e-3  # (soft) a ray whose transmittance falls below this stops

    def __post_init__(self):
        if self.extent <= 0 or self.max_hits < 1 or not 0 < self.alpha_max < 1:
            raise ValueError(f"invalid GaussianTraceConfig: {self}")
        if self.offset < 0 or self.stagger < 0 or self.t_min < 0:
            raise ValueError(f"invalid GaussianTraceConfig: {self}")


@dataclasses.dataclass(frozen=True)
class VoxelConfig:
    """Occupancy-grid visibility (GS-IR-like "voxel-based")."""

    resolution: int = 64  # grid cells per axis over the occluders' bounding cube
    margin: float = 1.05  # the cube's half-size is the bounding radius times this
    density: float = 3.0  # optical depth of one fully occupied voxel crossed straight
    step: float = 0.5  # march step in voxels
    start_offset: float = 1.5  # march starts this many voxels off the surface
    receiver_offset: float = 0.0  # as VisibilityConfig.receiver_offset (pixel footprints)
    splat_sigma: float = 1.0  # each surfel splats 5 points: centre and +-this sigma on t_u, t_v
    soft: bool = False  # return exp(-optical depth) instead of [V >= 0.5]
    tau_stop: float = 7.0  # (soft) a march stops above this optical depth (T < 1e-3)

    def __post_init__(self):
        if self.resolution < 2 or self.margin <= 0 or self.density <= 0 or self.step <= 0:
            raise ValueError(f"invalid VoxelConfig: {self}")
        if self.start_offset < 0 or self.tau_stop <= 0:
            raise ValueError(f"invalid VoxelConfig: {self}")


# -- shared helpers -----------------------------------------------------------------------
def _directions(directions) -> np.ndarray:
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    if d.ndim != 2 or d.shape[1] != 3 or len(d) == 0:
        raise ValueError(f"visibility baselines: directions must be [L, 3], got {d.shape}")
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    if not np.all(np.isfinite(d)) or np.any(norm == 0):
        raise ValueError("visibility baselines: directions hold NaN/Inf or zero vectors")
    return d / norm


def _surfel_arrays(surfels) -> dict[str, np.ndarray]:
    """Activated float64 surfel values with the frame: position, scale, opacity, t_u, t_v, n."""
    s = surfels.to_numpy()
    for key in ("position", "scale", "opacity"):
        if not np.all(np.isfinite(s[key])):
            raise ValueError(f"visibility baselines: surfel {key} holds NaN/Inf")
    rot = quaternion_to_matrix(s["rotation"])  # [N, 3, 3], columns t_u, t_v, n
    return {"position": s["position"], "scale": s["scale"], "opacity": s["opacity"],
            "t_u": rot[:, :, 0], "t_v": rot[:, :, 1], "n": rot[:, :, 2]}


def _rays(points: mi.Point3f, normals: mi.Vector3f | None, directions: np.ndarray):
    """Point-major expansion: origin [P*L], light direction [P*L], normal or None, facing."""
    n_lights = len(directions)
    idx = dr.arange(mi.UInt32, dr.width(points) * n_lights)
    pi, li = idx // n_lights, idx % n_lights
    p = dr.gather(mi.Point3f, points, pi)
    d = mi.Vector3f(*(dr.gather(mi.Float, jit.array(directions[:, k]), li) for k in range(3)))
    if normals is None:
        return p, d, None, mi.Bool(True)
    n = dr.gather(mi.Vector3f, normals, pi)
    return p, d, n, dr.dot(n, d) > 0.0


def _vec3(a: np.ndarray) -> mi.Vector3f:
    a = np.asarray(a, dtype=np.float32)
    return mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])


# -- Gaussian-based: ray tracing the surfels ----------------------------------------------
def surfel_quads(arrays: dict[str, np.ndarray], config: GaussianTraceConfig
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Quad proxy of each surfel: vertices [4N, 3], faces [2N, 3], the staggered centres
    [N, 3] (the planes that are traced) and the median standard deviation."""
    p, s = arrays["position"], arrays["scale"]
    n_surf = len(p)
    sigma = float(np.median(s)) if n_surf else 0.0
    shift = np.random.default_rng(config.seed).uniform(-0.5, 0.5, n_surf) * config.stagger
    centre = p + arrays["n"] * (shift * sigma)[:, None]
    a = arrays["t_u"] * (config.extent * s[:, :1])  # [N, 3]
    b = arrays["t_v"] * (config.extent * s[:, 1:])  # [N, 3]
    verts = np.stack([centre - a - b, centre + a - b, centre + a + b, centre - a + b], 1)
    base = 4 * np.arange(n_surf, dtype=np.uint32)[:, None]
    faces = np.concatenate([base + np.array([0, 1, 2], np.uint32),
                            base + np.array([0, 2, 3], np.uint32)], axis=1)  # [N, 6]
    return verts.reshape(-1, 3), faces.reshape(-1, 3), centre, sigma


class GaussianVisibility:
    """Shadow rays traced through the surfels' quad proxies (see module doc)."""

    def __init__(self, surfels, directions, bounds, config: GaussianTraceConfig):
        self.directions = _directions(directions)
        self.config = config
        self.bounds = bounds
        arr = _surfel_arrays(surfels)
        keep = (arr["opacity"] >= config.alpha_min) & np.all(arr["scale"] > 0, axis=1)
        arr = {k: v[keep] for k, v in arr.items()}
        self.surfel_count = int(keep.sum())
        verts, faces, centre, sigma = surfel_quads(arr, config)
        self.sigma = sigma
        self.scene = None
        if self.surfel_count:
            mesh = mi.Mesh("surfel_proxy", len(verts), len(faces), has_vertex_normals=False,
                           has_vertex_texcoords=False)
            params = mi.traverse(mesh)
            params["vertex_positions"] = mi.Float(verts.astype(np.float32).ravel())
            params["faces"] = mi.UInt32(faces.ravel())
            params.update()
            self.scene = mi.load_dict({"type": "scene", "proxy": mesh})
        # Per-surfel lookups: local coordinates in sigma units are dot(q - c, t / s).
        self.centre = mi.Point3f(_vec3(centre))
        self.axis_u = _vec3(arr["t_u"] / arr["scale"][:, :1])
        self.axis_v = _vec3(arr["t_v"] / arr["scale"][:, 1:])
        self.opacity = jit.host(np.minimum(arr["opacity"], config.alpha_max).astype(np.float32))
        # Advance past a hit by a hair: above float32 rounding at the scene's scale, far below
        # the stagger range (two overlapping quads closer than this in t count once).
        scale = float(np.max(np.abs(bounds.center))) + bounds.radius
        self.t_eps = 1e-6 * scale

    @property
    def count(self) -> int:
        return len(self.directions)

    def transmittance(self, origin: mi.Point3f, direction: mi.Vector3f,
                      active: mi.Bool) -> mi.Float:
        """Product of (1 - alpha) over the surfels a ray [R] crosses (1 where not active)."""
        cfg = self.config
        width = dr.width(origin)
        trans = dr.full(mi.Float, 1.0, width)
        if self.scene is None:
            return trans
        stop = cfg.t_min if cfg.soft else 0.5
        o = mi.Point3f(origin)
        dr.eval(o, trans)
        idx = dr.compress(mi.Bool(active) | dr.zeros(mi.Bool, width))
        for _ in range(cfg.max_hits):
            if dr.width(idx) == 0:
                break
            ro = dr.gather(mi.Point3f, o, idx)
            rd = dr.gather(mi.Vector3f, direction, idx)
            pre = self.scene.ray_intersect_preliminary(mi.Ray3f(ro, rd))
            hit = pre.is_valid()
            surf = pre.prim_index // 2
            q = ro + rd * pre.t
            rel = q - dr.gather(mi.Point3f, self.centre, surf, hit)
            u = dr.dot(rel, dr.gather(mi.Vector3f, self.axis_u, surf, hit))
            v = dr.dot(rel, dr.gather(mi.Vector3f, self.axis_v, surf, hit))
            alpha = dr.gather(mi.Float, self.opacity, surf, hit) * dr.exp(-0.5 * (u * u + v * v))
            t_new = dr.gather(mi.Float, trans, idx) * dr.select(hit, 1.0 - alpha, 1.0)
            dr.scatter(trans, t_new, idx)
            nxt = q + rd * self.t_eps
            for k in range(3):
                dr.scatter(o[k], nxt[k], idx)
            dr.eval(trans, o)
            idx = dr.gather(mi.UInt32, idx, dr.compress(hit & (t_new >= stop)))
        return trans

    def evaluate(self, points: mi.Point3f, normals: mi.Vector3f | None = None,
                 footprint: mi.Float | None = None) -> mi.Float:
        """V [P * L] (point-major); soft transmittance or [T >= 0.5]."""
        with dr.suspend_grad():
            points = lift_receivers(points, normals, footprint, self.config.receiver_offset)
            p, d, n, facing = _rays(points, normals, self.directions)
            if n is not None:
                p = p + n * (self.config.offset * self.sigma)
            trans = self.transmittance(p, d, facing)
            vis = trans if self.config.soft else dr.select(trans >= 0.5, 1.0, 0.0)
            return dr.select(facing, vis, 0.0)


def trace_surfels(surfels, directions, bounds,
                  config: GaussianTraceConfig = GaussianTraceConfig()) -> GaussianVisibility:
    """The Gaussian-based baseline for ``directions`` [L, 3] (see module doc)."""
    return GaussianVisibility(surfels, directions, bounds, config)


# -- voxel-based: an occupancy grid -------------------------------------------------------
def grid_frame(bounds, config: VoxelConfig) -> tuple[np.ndarray, float]:
    """Lower corner [3] of the grid cube and the voxel size."""
    half = bounds.radius * config.margin
    return np.asarray(bounds.center, dtype=np.float64) - half, 2.0 * half / config.resolution


def occupancy_grid(arrays: dict[str, np.ndarray], bounds, config: VoxelConfig) -> np.ndarray:
    """Occupancy [G, G, G] (index x, y, z) in [0, 1]: the fraction of a voxel's cross-section
    the surfels cover, ``sum opacity * 2 pi s_u s_v / h^2`` clipped to 1.

    Each surfel's coverage is split over five points (its centre and +-``splat_sigma`` along
    each tangent axis) so that a surfel larger than a voxel marks its neighbours too.
    """
    g = config.resolution
    lo, h = grid_frame(bounds, config)
    cover = arrays["opacity"] * 2.0 * math.pi * arrays["scale"][:, 0] * arrays["scale"][:, 1]
    cover = cover / (h * h) / 5.0  # [N]
    k = config.splat_sigma
    offsets = [np.zeros(3)[None]] + [sgn * k * arrays[ax] * arrays["scale"][:, i:i + 1]
                                     for i, ax in enumerate(("t_u", "t_v")) for sgn in (-1, 1)]
    grid = np.zeros((g, g, g))
    for off in offsets:
        cell = np.floor((arrays["position"] + off - lo) / h).astype(np.int64)  # [N, 3]
        inside = np.all((cell >= 0) & (cell < g), axis=1)
        c = cell[inside]
        np.add.at(grid, (c[:, 0], c[:, 1], c[:, 2]), cover[inside])
    return np.minimum(grid, 1.0)


class VoxelVisibility:
    """Shadow rays marched through an occupancy grid (see module doc)."""

    def __init__(self, surfels, directions, bounds, config: VoxelConfig):
        self.directions = _directions(directions)
        self.config = config
        self.bounds = bounds
        self.lower, self.voxel = grid_frame(bounds, config)
        grid = occupancy_grid(_surfel_arrays(surfels), bounds, config)  # [G, G, G]
        self.grid_np = grid
        self.grid = mi.Float(grid.astype(np.float32).ravel())  # x-major: (x * G + y) * G + z

    @property
    def count(self) -> int:
        return len(self.directions)

    def occupancy(self, x: mi.Point3f, active: mi.Bool = True) -> mi.Float:
        """Trilinear occupancy at world points (voxel centres at integer grid coordinates,
        0 outside the grid)."""
        g = self.config.resolution
        gp = (x - mi.Point3f(*self.lower.tolist())) / self.voxel - 0.5
        i0 = mi.Point3i(dr.floor(gp))
        f = gp - mi.Point3f(i0)
        acc = mi.Float(0.0)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    ix, iy, iz = i0.x + dx, i0.y + dy, i0.z + dz
                    ok = (active & (ix >= 0) & (ix < g) & (iy >= 0) & (iy < g) & (iz >= 0)
                          & (iz < g))
                    flat = mi.UInt32((ix * g + iy) * g + iz)
                    w = ((f.x if dx else 1.0 - f.x) * (f.y if dy else 1.0 - f.y)
                         * (f.z if dz else 1.0 - f.z))
                    acc += dr.gather(mi.Float, self.grid, flat, ok) * w
        return acc

    def optical_depth(self, origin: mi.Point3f, direction: mi.Vector3f,
                      active: mi.Bool) -> mi.Float:
        """Optical depth from ``origin`` along ``direction`` [R] until the ray leaves the grid."""
        cfg = self.config
        h = self.voxel
        lo = mi.Point3f(*self.lower.tolist())
        hi = lo + cfg.resolution * h
        # Slab test: where the ray leaves the grid cube (t_far < 0: never inside ahead).
        inv = dr.rcp(dr.select(dr.abs(direction) < 1e-12, 1e-12, direction))
        t0, t1 = (lo - origin) * inv, (hi - origin) * inv
        t_far = dr.min(dr.maximum(t0, t1))
        t_near = dr.maximum(dr.max(dr.minimum(t0, t1)), 0.0)
        step = cfg.step * h
        sigma = cfg.density / h
        stop = cfg.tau_stop if cfg.soft else math.log(2.0)  # hard: V < 0.5 settles it
        max_steps = int(math.ceil(math.sqrt(3.0) * cfg.resolution / cfg.step)) + 2
        t = t_near + 0.5 * step
        tau = dr.zeros(mi.Float, dr.width(origin))
        i = dr.zeros(mi.UInt32, dr.width(origin))
        act = mi.Bool(active) & (t_far > t_near)

        def cond(t, tau, i, act):
            return act & (t < t_far) & (tau < stop) & (i < max_steps)

        def body(t, tau, i, act):
            x = origin + direction * t
            tau = tau + sigma * step * self.occupancy(x)
            return t + step, tau, i + 1, act

        t, tau, i, act = dr.while_loop(state=(t, tau, i, act), cond=cond, body=body,
                                       labels=("t", "tau", "i", "act"))
        return tau

    def evaluate(self, points: mi.Point3f, normals: mi.Vector3f | None = None,
                 footprint: mi.Float | None = None) -> mi.Float:
        """V [P * L] (point-major); soft exp(-optical depth) or its threshold at 0.5."""
        with dr.suspend_grad():
            points = lift_receivers(points, normals, footprint, self.config.receiver_offset)
            p, d, n, facing = _rays(points, normals, self.directions)
            off = self.config.start_offset * self.voxel
            p = p + d * off if n is None else p + n * off
            tau = self.optical_depth(p, d, facing)
            trans = dr.exp(-tau)
            vis = trans if self.config.soft else dr.select(trans >= 0.5, 1.0, 0.0)
            return dr.select(facing, vis, 0.0)


def voxelize_surfels(surfels, directions, bounds,
                     config: VoxelConfig = VoxelConfig()) -> VoxelVisibility:
    """The voxel-based baseline for ``directions`` [L, 3] (see module doc)."""
    return VoxelVisibility(surfels, directions, bounds, config)
