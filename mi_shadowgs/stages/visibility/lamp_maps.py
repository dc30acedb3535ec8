"""Shadow maps from a lamp: perspective maps rendered from the lamp's position, and their lookup.

A local light (a lamp at position ``p`` with a radius ``R``; ``core.shading.LightSet``) has
the natural shadow map of the method: a perspective camera at ``p`` looking at the scene
centre, whose field of view just covers the occluders' bounding sphere (``SceneBounds``).
A receiver outside that cone cannot be shadowed by an occluder inside the sphere, since
the segment from it to the lamp stays outside the cone. The maps hold z-depth along the
lamp camera's axis, as every map of the method does, and a texel's world size at z-depth
``z`` is ``z / focal``: the depth threshold (``bias_texels``), the normal offset and the
occluder layer's slack use that size where the directional maps use the texel at the
scene centre.

A lamp with a radius casts soft shadows: ``VisibilityConfig.lamp_samples`` maps, each from
a point of its disc facing the scene centre (Vogel's sunflower, equal areas), and ``V`` is
the mean of their hard lookups; exact in the limit of many points for the lamp's disc as
the scene centre sees it. The horizon test uses the direction to the lamp's centre.

A lamp too near the occluders is refused (``ValueError`` naming it): its map would need a
field of view over ``MAX_LAMP_FOV_DEG``, and a texel at the edge of such a map grows
without bound (a cube map is not built; a lamp inside the object is not a capture).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit
from mi_shadowgs.core.camera import Camera

MAX_LAMP_FOV_DEG = 120.0  # the widest map of a lamp: lamps nearer the occluders are refused


def checked_lamps(positions, radii, count: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(positions [L, 3] with NaN rows for directional lights, radii [L] zero there) of
    ``count`` lights; None when no light is local. ``ValueError`` names the lamp and the
    field of a bad entry."""
    if positions is None:
        if radii is not None and np.any(np.asarray(radii, np.float64) != 0):
            raise ValueError("shadow maps: lamp radii given without lamp positions")
        return None
    pos = np.asarray(positions, np.float64)
    if pos.shape != (count, 3):
        raise ValueError(f"shadow maps: lamp positions must be [{count}, 3] (one row per "
                         f"light, NaN for a directional light), got {pos.shape}")
    finite = np.isfinite(pos)
    local = finite.all(axis=1)
    bad = np.flatnonzero(finite.any(axis=1) & ~local)
    if len(bad):
        raise ValueError(f"shadow maps: lamp {bad[0]} position {pos[bad[0]].tolist()} is "
                         f"neither a point (3 finite numbers) nor a directional light (NaN)")
    rad = np.zeros(count) if radii is None else np.asarray(radii, np.float64).reshape(-1)
    if rad.shape != (count,):
        raise ValueError(f"shadow maps: lamp radii must be [{count}], got {rad.shape}")
    rad = np.where(local, rad, 0.0)
    bad = np.flatnonzero(local & ~(np.isfinite(rad) & (rad >= 0)))
    if len(bad):
        raise ValueError(f"shadow maps: lamp {bad[0]} radius must be >= 0 (world units), "
                         f"got {rad[bad[0]]:g}")
    if not local.any():
        return None
    return np.where(local[:, None], pos, np.nan), rad


def lamp_arguments(lights) -> dict:
    """``positions`` and ``radii`` of a ``LightSet``'s local lights (NaN rows for its
    directional ones) as ``render_shadow_maps`` and ``MapCache.maps`` take them; empty when
    every light is directional."""
    if lights.positions is None:
        return {}
    pos = lights.positions
    if not isinstance(pos, np.ndarray):  # a differentiable mi.Point3f: every light local
        pos = np.stack([np.asarray(c, np.float64) for c in (pos.x, pos.y, pos.z)], axis=1)
    pos = np.asarray(pos, np.float64).reshape(-1, 3)
    if not np.isfinite(pos).all(axis=1).any():
        return {}
    radii = (np.zeros(len(pos)) if lights.radii is None
             else np.nan_to_num(np.asarray(lights.radii, np.float64).reshape(-1)))
    return {"positions": pos, "radii": radii}


def disc_points(count: int) -> np.ndarray:
    """[count, 2] points evenly over the unit disc (Vogel's sunflower), each the centre of
    an equal area."""
    k = np.arange(count) + 0.5
    r = np.sqrt(k / count)
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi)], -1)


def lamp_points(position: np.ndarray, radius: float, center: np.ndarray,
                samples: int) -> np.ndarray:
    """[S, 3] where a lamp's maps are rendered from: its centre alone (a point lamp, or
    ``samples`` 0), else ``samples`` points of its disc of ``radius`` facing ``center``."""
    p = np.asarray(position, np.float64)
    if radius <= 0 or samples <= 0:
        return p[None]
    w = p - np.asarray(center, np.float64)
    w /= np.linalg.norm(w)
    a = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(w, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(w, e1)
    d = disc_points(samples) * radius
    return p + d[:, :1] * e1 + d[:, 1:] * e2


def lamp_camera(position: np.ndarray, center: np.ndarray, reach: float, resolution: int,
                name: str = "lamp") -> Camera:
    """The perspective camera at ``position`` looking at ``center``, its field of view just
    covering the sphere of radius ``reach`` there; ``resolution`` texels a side. A
    ``ValueError`` names ``name`` when the lamp is inside or too near that sphere."""
    p = np.asarray(position, np.float64)
    c = np.asarray(center, np.float64)
    dist = float(np.linalg.norm(p - c))
    half_max = math.radians(0.5 * MAX_LAMP_FOV_DEG)
    if not dist * math.sin(half_max) > reach:
        raise ValueError(
            f"{name} at {np.round(p, 4).tolist()} is {dist:.4g} from the scene centre, "
            f"inside or too near the occluders' bounding sphere of radius {reach:.4g}: its "
            f"shadow map would need a field of view over {MAX_LAMP_FOV_DEG:g} degrees; a "
            f"lamp must stand more than {reach / math.sin(half_max):.4g} from the centre")
    fwd = (c - p) / dist
    up = np.array([0.0, 1.0, 0.0]) if abs(fwd[1]) < 0.99 else np.array([0.0, 0.0, -1.0])
    fov = 2.0 * math.asin(reach / dist)
    return Camera.look_at(p, c, up, fov_x=fov, width=resolution, height=resolution,
                          near=max(1e-4, 0.5 * (dist - reach)), far=dist + 2.0 * reach)


def lamp_raster(raster, camera: Camera):
    """``raster`` with its near plane at ``camera``'s (``lamp_camera``: halfway to the
    occluders) where that is nearer: the rasterizer culls z-depths below ``near``, and a
    lamp may stand nearer the occluders than the training renders' 0.2 units."""
    import dataclasses

    return (raster if camera.near >= raster.near
            else dataclasses.replace(raster, near=camera.near))


class LampLookup:
    """The per-map and per-light arrays of a mixed set's lookup (built once per maps)."""

    def __init__(self, maps):
        cams = maps.cameras
        n_maps = len(cams)
        light = (np.arange(n_maps) if maps.map_light is None
                 else np.asarray(maps.map_light, np.int64))
        w2c = np.stack([c.world_to_cv()[:3, :4] for c in cams])  # [M, 3, 4]
        self.rows = [jit.array(w2c[:, i, j]) for i in range(3) for j in range(4)]
        self.focal = jit.array(np.array([c.focal for c in cams]))
        self.cx = jit.array(np.array([c.principal_point[0] for c in cams]))
        pos = (np.full((maps.count, 3), np.nan) if maps.positions is None
               else np.asarray(maps.positions, np.float64))
        local_l = np.isfinite(pos).all(axis=1)
        local_m = local_l[light]
        origins = np.stack([c.origin for c in cams])
        # per map: the lamp point it is rendered from, or the light's direction
        vec_m = np.where(local_m[:, None], origins, np.asarray(maps.directions)[light])
        self.map_local = jit.array(local_m, mi.Bool)
        self.map_vec = [jit.array(vec_m[:, k]) for k in range(3)]
        vec_l = np.where(local_l[:, None], np.nan_to_num(pos), maps.directions)
        self.light_local = jit.array(local_l, mi.Bool)
        self.light_vec = [jit.array(vec_l[:, k]) for k in range(3)]
        counts = np.bincount(light, minlength=maps.count)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        if np.any(np.diff(light) < 0):
            raise ValueError("shadow maps: a light's maps must be consecutive")
        self.start = jit.array(starts.astype(np.uint32), mi.UInt32)
        self.count = jit.array(counts.astype(np.uint32), mi.UInt32)


def _gather3(arrays, index) -> mi.Vector3f:
    return mi.Vector3f(*(dr.gather(mi.Float, a, index) for a in arrays))


def lamp_visibility(points: mi.Point3f, maps, normals: mi.Vector3f | None = None) -> mi.Float:
    """V [P * L] (point-major) of a set with local lights (``point_visibility``'s, whose
    receivers are already lifted): each light's V is the mean of its maps' hard (or PCF)
    lookups; directional maps are looked up as ``point_visibility`` does. A light's maps
    are walked by one symbolic loop: its kernel is the same for any number of maps (16
    unrolled maps compiled for ~1 s, 64 for ~18 s)."""
    cfg = maps.config
    if maps._lookup is None:
        maps._lookup = LampLookup(maps)
    lk = maps._lookup
    n_lights = maps.count
    idx = dr.arange(mi.UInt32, dr.width(points) * n_lights)
    pi, li = idx // n_lights, idx % n_lights
    p0 = dr.gather(mi.Point3f, points, pi)
    centre = _gather3(lk.light_vec, li)
    l_hor = dr.select(dr.gather(mi.Bool, lk.light_local, li), dr.normalize(centre - p0), centre)
    facing = mi.Bool(True)
    n = None
    if normals is not None:
        n = dr.gather(mi.Vector3f, normals, pi)
        facing = dr.dot(n, l_hor) > cfg.horizon_cos
    start = dr.gather(mi.UInt32, lk.start, li)
    count = dr.gather(mi.UInt32, lk.count, li)

    def body(s, total):
        return s + 1, total + _map_lookup(maps, lk, start + s, p0, n)

    _, total = dr.while_loop(state=(mi.UInt32(0), mi.Float(0.0)),
                             cond=lambda s, total: s < count, body=body,
                             labels=("sample", "total"), label="lamp_visibility")
    return dr.select(facing, total / mi.Float(count), 0.0)


def _map_lookup(maps, lk: LampLookup, index: mi.UInt32, p0: mi.Point3f,
                n: mi.Vector3f | None) -> mi.Float:
    """The hard (or PCF) visibility of ``p0`` in map ``index``, after the normal offset."""
    cfg = maps.config
    r = maps.resolution
    m = [dr.gather(mi.Float, row, index) for row in lk.rows]
    focal = dr.gather(mi.Float, lk.focal, index)
    c = dr.gather(mi.Float, lk.cx, index)
    local = dr.gather(mi.Bool, lk.map_local, index)
    p = p0
    if n is not None and cfg.normal_offset > 0:
        vec = _gather3(lk.map_vec, index)
        z0 = m[8] * p0.x + m[9] * p0.y + m[10] * p0.z + m[11]
        l_m = dr.select(local, dr.normalize(vec - p0), vec)
        cos = dr.dot(n, l_m)
        sin = dr.safe_sqrt(1.0 - dr.square(dr.clip(cos, -1.0, 1.0)))
        scale = dr.select(local, cfg.normal_offset * (z0 / focal),
                          cfg.normal_offset * maps.texel)
        p = p0 + n * (scale * sin)
    x = m[0] * p.x + m[1] * p.y + m[2] * p.z + m[3]
    y = m[4] * p.x + m[5] * p.y + m[6] * p.z + m[7]
    z = m[8] * p.x + m[9] * p.y + m[10] * p.z + m[11]
    inv_z = dr.rcp(dr.maximum(z, 1e-12))
    u, v = focal * x * inv_z + c, focal * y * inv_z + c
    if cfg.projection == "orthographic":  # the directional maps'; a lamp's is perspective
        u = dr.select(local, u, focal * x + c)
        v = dr.select(local, v, focal * y + c)
    front = ~local | (z > 0)  # a point behind the lamp is lit by it
    absolute = cfg.bias_texels is not None
    if absolute:
        bias = dr.select(local, cfg.bias_texels * (z / focal), cfg.bias_texels * maps.texel)
    else:
        bias = mi.Float(cfg.tau)
    return window_lookup(maps, cfg, index * (r * r), u, v, z, bias, front, absolute)


def window_lookup(maps, cfg, base, u, v, z, bias, front, absolute: bool) -> mi.Float:
    """Eq. 6-7 (or the absolute test) at the texel of (u, v) of the map at ``base``,
    averaged over the PCF window; 1 where not ``front`` or outside the map (an inf map
    depth gives -inf: visible). The directional and the lamp maps' lookup."""
    r = maps.resolution
    radius = cfg.pcf
    acc = mi.Float(0.0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            ix = mi.Int32(dr.floor(u)) + dx
            iy = mi.Int32(dr.floor(v)) + dy
            inside = (ix >= 0) & (ix < r) & (iy >= 0) & (iy < r) & front
            tex = base + mi.UInt32(dr.clip(iy, 0, r - 1)) * r + mi.UInt32(dr.clip(ix, 0, r - 1))
            d_g = dr.gather(mi.Float, maps.depth, tex, inside)
            d_g = dr.select(inside, d_g, dr.inf)
            delta = (z - d_g) if absolute else (z - d_g) / (z + cfg.eps)
            if maps.alpha is not None:  # fractional: the occluder lets 1 - alpha through
                a_g = dr.gather(mi.Float, maps.alpha, tex, inside)
                acc += dr.select(delta <= bias, 1.0, 1.0 - a_g)
            else:
                acc += dr.select(delta <= bias, 1.0, 0.0)
    return acc / float((2 * radius + 1) ** 2)
