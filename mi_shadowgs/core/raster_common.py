"""What the two rasterizers share: ``RasterConfig``, the per-surfel projection (``project``,
``Proj``), the pixel boxes and pair counts, the memory budget, and the per-pixel splat maths
(``pair_eval``, ``pair_kept``, ``distortion_m``). ``raster`` (the pixel-splat pair list) and
``raster_tiles`` (the tiled renderer, its screen-tile binning in ``raster_bins``) build on
it, and neither imports the other's internals.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import drjit as dr
import mitsuba as mi

from mi_shadowgs.core import jit, memory
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.surfels import Surfels

AOV_CHANNELS = {"alpha": 1, "depth": 1, "median_depth": 1, "normal": 3, "distortion": 1,
                "count": 1}


@dataclasses.dataclass(frozen=True)
class RasterConfig:
    """Rasterizer settings; the defaults are those of the 2DGS reference implementation,
    except the low-pass filter (``lowpass_inv_var``)."""

    alpha_max: float = 0.99  # clamp of a splat's alpha (keeps log(1 - alpha) finite)
    alpha_min: float = 1.0 / 255.0  # pairs below this alpha are dropped
    transmittance_min: float = 1e-4  # a splat that would bring T below this ends the pixel
    # Screen-space filter: alpha uses min(rho3d, rho2d), rho2d = lowpass_inv_var |d|^2 (d in
    # pixels); 12: std 1/sqrt(12) px, a one-pixel box's (2DGS: 2; docs/decisions.md).
    lowpass_inv_var: float = 12.0
    cutoff_sigma: float = 3.0  # pairs with rho > cutoff_sigma^2 are dropped; sets the box
    near: float = 0.2  # centres and intersections with z-depth below this are culled
    distortion_near: float = 0.2  # NDC-like depth mapping of the distortion term (2DGS)
    distortion_far: float = 100.0
    scale_min: float = 1e-20  # surfels with a smaller tangent std-dev are culled (no plane)
    edge_on_eps: float = 1e-6  # |s_z| <= eps (|s_x|+|s_y|): ray ~ parallel to the plane
    box_margin: float = 0.01  # pixels; covers float32 rounding of the bounding box
    # Tiled renderer: list a splat only in the tiles its kept region reaches (``reaches_rect``),
    # not every tile of its box; the images are the same (docs/decisions.md).
    cull_tiles: bool = True
    max_pairs: int = 1 << 30  # most pairs in one list (< 2^32: UInt32 pair indices)
    # Memory guard (``raster._plan_bands``). A render's peak memory is about reserve_bytes
    # (kernel compilation, images) plus a cost per pixel-box pair (measured 14 MiB + 52 B
    # forward, 32 MiB + 87 B forward+backward over every AOV: ``bm_raster_memory``). A
    # render that would take this process's resident memory past the budget is drawn in
    # bands of image rows when nothing needs its gradient, and refused (RasterMemoryError)
    # when something does: the AD graph would keep every band's pairs alive until the
    # backward pass.
    memory_budget_bytes: int | None = None  # None: resident now + fraction of MemAvailable
    memory_budget_fraction: float = 0.5
    bytes_per_pair: int = 64  # forward only
    bytes_per_pair_grad: int = 112  # with gradients
    reserve_bytes: int = 48 << 20
    # "pairs": the pixel-splat pair list above (the reference; memory grows with the pairs).
    # "tiles" (default): the tiled renderer (``raster_tiles``): surfels binned to tile_size^2 pixel
    # tiles, one compositing loop per pixel, a hand-written backward; memory O(pixels +
    # surfel-tile pairs). Its guard counts bytes per surfel-tile pair (key, sort, packed
    # entries; measured 113 B forward, 130 B forward+backward over every AOV and 3 channels:
    # ``bm_raster_memory --method tiles``) and per pixel lane (saved state, images,
    # gradient images: estimated from the arrays held), plus per channel 4 bytes per pair
    # and 8 per lane.
    method: str = "tiles"
    tile_size: int = 4  # tile edge in pixels of the tiled renderer (docs/decisions.md)
    # Pixels of a tile that one lane of the tiled loops composites, reading each entry once
    # for all (a power of two; fewer where the tile has fewer; docs/decisions.md).
    pixels_per_lane: int = 2
    bytes_per_tile_pair: int = 160
    bytes_per_pixel: int = 96  # forward only
    bytes_per_pixel_grad: int = 256  # with gradients
    # The tiled backward's per-surfel gradient sums: a private copy per thread (Dr.Jit's
    # ReduceMode.Expand) up to this many bytes, else atomics after a pre-reduction in the
    # SIMD packet (Local; docs/decisions.md).
    expand_grad_bytes: int = 64 << 20

    def __post_init__(self):
        if self.method not in RASTER_METHODS:
            raise ValueError(f"RasterConfig.method must be one of {RASTER_METHODS}, got "
                             f"{self.method!r}")
        if not 1 <= self.tile_size <= 256:
            raise ValueError(f"RasterConfig.tile_size must be in [1, 256], got "
                             f"{self.tile_size}")
        k = self.pixels_per_lane
        if not (1 <= k <= 256 and k & (k - 1) == 0):
            raise ValueError(f"RasterConfig.pixels_per_lane must be a power of two in "
                             f"[1, 256], got {k}")


RASTER_METHODS = ("pairs", "tiles")


class RasterMemoryError(MemoryError, ValueError):
    """A render's pair list does not fit the memory budget or ``max_pairs``; a ValueError
    too, so that the CLI reports it in one line with exit status 2."""


# A finite stand-in for rho3d when the ray misses the plane (edge-on): the filter wins.
_RHO_NONE = 1e30


@dataclasses.dataclass
class Proj:
    """Per-surfel projected quantities [N] (all differentiable)."""

    valid: mi.Bool
    xc: mi.Float
    yc: mi.Float
    a0: mi.Float
    a1: mi.Float
    b0: mi.Float
    b1: mi.Float
    t20: mi.Float
    t21: mi.Float
    t22: mi.Float
    z0: mi.Float
    z1: mi.Float
    z2: mi.Float
    opacity: mi.Float
    normal: mi.Vector3f  # world space, facing the camera

    def detach(self) -> Proj:
        return Proj(*(dr.detach(getattr(self, f.name)) for f in dataclasses.fields(self)))

    def gather(self, idx: mi.UInt32, names: Sequence[str]) -> dict:
        out = {}
        for name in names:
            v = getattr(self, name)
            out[name] = dr.gather(type(v), v, idx)
        return out


def project(surfels: Surfels, camera: Camera, config: RasterConfig) -> Proj:
    # Opaque: a new camera reuses the kernels (``core.jit``).
    rows = jit.opaque_matrix(camera.world_to_cv()[:3])
    r, t = [row[:3] for row in rows], [row[3] for row in rows]

    def to_cam_vec(v):
        return [r[i][0] * v.x + r[i][1] * v.y + r[i][2] * v.z for i in range(3)]

    p = surfels.position
    pc = to_cam_vec(p)
    pc = [pc[i] + t[i] for i in range(3)]
    t_u, t_v, nrm = surfels.tangent_frame()
    tu, tv = to_cam_vec(t_u), to_cam_vec(t_v)
    s = surfels.scale()
    su, sv = s.x, s.y
    # The one place the rasterizer maps camera space to pixels: focal lengths (fx, fy) and
    # principal point (cx, cy) of the camera, so real pinholes project where they should.
    fx, fy = (jit.opaque(v) for v in camera.focal_xy)
    cx, cy = (jit.opaque(c) for c in camera.principal_point)
    z0, z1, z2 = su * tu[2], sv * tv[2], pc[2]
    if camera.is_ortho:
        xc, yc = fx * pc[0] + cx, fy * pc[1] + cy
        a0, a1 = fx * su * tu[0], fx * sv * tv[0]
        b0, b1 = fy * su * tu[1], fy * sv * tv[1]
        zero = dr.zeros(mi.Float, dr.width(p))
        t20, t21, t22 = zero, zero, zero + 1.0
    else:
        # Guarded 1/z: culled surfels (z < near) must not put inf into the gradient.
        zs = dr.select(pc[2] > config.near, pc[2], 1.0)
        mx, my = pc[0] / zs, pc[1] / zs
        xc, yc = fx * mx + cx, fy * my + cy
        a0, a1 = fx * su * (tu[0] - mx * tu[2]), fx * sv * (tv[0] - mx * tv[2])
        b0, b1 = fy * su * (tu[1] - my * tu[2]), fy * sv * (tv[1] - my * tv[2])
        t20, t21, t22 = z0, z1, zs
    valid = (pc[2] >= config.near) & (su > config.scale_min) & (sv > config.scale_min)
    valid &= dr.isfinite(xc) & dr.isfinite(yc) & dr.isfinite(su) & dr.isfinite(sv)
    return Proj(valid, xc, yc, a0, a1, b0, b1, t20, t21, t22, z0, z1, z2,
                 surfels.opacity(), face_camera(nrm, p, camera))


def face_camera(normal: mi.Vector3f, position: mi.Point3f, camera: Camera) -> mi.Vector3f:
    """Surfel normals [N] flipped to face ``camera``: 2DGS flips each by the direction from
    the camera to the surfel's centre (orthographic: by the view axis). The rasterized
    normals and stage 4's per-surfel indirect light (``shading.facing_normals``) use it."""
    if camera.is_ortho:
        view = mi.Vector3f(*(jit.opaque(v) for v in camera.forward))
    else:
        view = mi.Vector3f(position - mi.Point3f(*(jit.opaque(v) for v in camera.origin)))
    return dr.select(dr.dot(normal, view) > 0, -normal, normal)


def boxes(g: Proj, width: int, height: int, config: RasterConfig, rows=None):
    """Integer pixel boxes [x0, x1] x [y0, y1] (inclusive) per surfel, clipped to the image
    (and to the rows [r0, r1) of ``rows``, a pair of opaque Int32): (x0, y0, box width, box
    height, pixel count). A splat larger than the image thus counts at most H * W pixels.

    The box bounds rho <= k^2 with k^2 = min(cutoff_sigma^2, 2 ln(opacity / alpha_min)):
    beyond the second, alpha = opacity exp(-rho / 2) < alpha_min and ``pair_kept`` drops
    the pair anyway, so a faint splat's smaller box leaves every image and gradient as it
    was (0.2x the area at the 0.01 opacity of a reset; none below alpha_min)."""
    k2 = opacity_cutoff2(g.opacity, config)
    live = g.valid & (k2 > 0)
    k2 = dr.select(live, k2, 1.0)
    # Dual conic of the k-sigma ellipse, in pixel offsets from the projected centre.
    c00 = g.a0 * g.a0 + g.a1 * g.a1
    c11 = g.b0 * g.b0 + g.b1 * g.b1
    c02 = g.a0 * g.t20 + g.a1 * g.t21
    c12 = g.b0 * g.t20 + g.b1 * g.t21
    c22 = g.t20 * g.t20 + g.t21 * g.t21 - g.t22 * g.t22 / k2
    bounded = c22 < 0  # else the ellipse reaches the camera plane: its image is unbounded
    c22s = dr.select(bounded, c22, -1.0)
    ox, oy = c02 / c22s, c12 / c22s
    hx = dr.sqrt(dr.maximum(ox * ox - c00 / c22s, 0.0))
    hy = dr.sqrt(dr.maximum(oy * oy - c11 / c22s, 0.0))
    big = 4.0 * (width + height)
    hx = dr.select(bounded, hx, big)
    hy = dr.select(bounded, hy, big)
    ox = dr.select(bounded, ox, 0.0)
    oy = dr.select(bounded, oy, 0.0)
    rf = (dr.sqrt(k2) / math.sqrt(config.lowpass_inv_var) if config.lowpass_inv_var > 0
          else 0.0)
    m = config.box_margin
    xmin = g.xc + dr.minimum(ox - hx, -rf) - m
    xmax = g.xc + dr.maximum(ox + hx, rf) + m
    ymin = g.yc + dr.minimum(oy - hy, -rf) - m
    ymax = g.yc + dr.maximum(oy + hy, rf) + m

    # Pixel i has its centre at i + 0.5; clamp in float before the int conversion.
    def lo(v, n):
        return mi.Int32(dr.ceil(dr.clip(v - 0.5, -1.0, n + 1.0)))

    def hi(v, n):
        return mi.Int32(dr.floor(dr.clip(v - 0.5, -2.0, n + 1.0)))

    x0 = dr.maximum(lo(xmin, width), 0)
    x1 = dr.minimum(hi(xmax, width), width - 1)
    y0 = dr.maximum(lo(ymin, height), 0)
    y1 = dr.minimum(hi(ymax, height), height - 1)
    if rows is not None:
        y0 = dr.maximum(y0, rows[0])
        y1 = dr.minimum(y1, rows[1] - 1)
    bw = dr.maximum(x1 - x0 + 1, 0)
    bh = dr.maximum(y1 - y0 + 1, 0)
    count = dr.select(live, mi.UInt32(bw * bh), 0)
    return mi.UInt32(x0), mi.UInt32(y0), mi.UInt32(bw), mi.UInt32(bh), count


def opacity_cutoff2(opacity: mi.Float, config: RasterConfig) -> mi.Float:
    """Per splat, the rho that bounds its kept pairs: min(cutoff_sigma^2, 2 ln(opacity /
    alpha_min)), the second widened by 1e-3 (relative and absolute) against float32
    rounding of alpha near alpha_min; <= 0 where opacity < alpha_min (no pair kept)."""
    k2 = config.cutoff_sigma ** 2
    if config.alpha_min <= 0:
        return dr.full(mi.Float, k2, dr.width(opacity))
    fade = 2.0 * dr.log(dr.maximum(opacity, 1e-30) / config.alpha_min)
    return dr.minimum(k2, fade * (1.0 + 1e-3) + 1e-3)


def conic_of(g: Proj, config: RasterConfig) -> dict:
    """Per splat, what ``reaches_rect`` reads: its centre (xc, yc); the map d -> s = s0 +
    d_x sx + d_y sy of ``pair_eval`` (d: the pixel offset from the centre, s0 = (0, 0,
    s0z)); kk, its ``opacity_cutoff2`` widened by 1e-4 against float32 rounding; and the
    inverse curvatures 1 / F(sx), 1 / F(sy) of F(d) = s_x^2 + s_y^2 - kk s_z^2 along x and
    y, 0 where F <= 0 is not an ellipse (unbounded: then every tile is reached)."""
    a0, a1, b0, b1 = g.a0, g.a1, g.b0, g.b1
    t20, t21, t22 = g.t20, g.t21, g.t22
    sx = (t22 * b1, -t22 * b0, t21 * b0 - t20 * b1)
    sy = (-t22 * a1, t22 * a0, a1 * t20 - a0 * t21)
    kk = opacity_cutoff2(g.opacity, config) * (1.0 + 1e-4)
    fxx = sx[0] * sx[0] + sx[1] * sx[1] - kk * sx[2] * sx[2]
    fyy = sy[0] * sy[0] + sy[1] * sy[1] - kk * sy[2] * sy[2]
    fxy = sx[0] * sy[0] + sx[1] * sy[1] - kk * sx[2] * sy[2]
    ellipse = (fxx > 0) & (fyy > 0) & (fxx * fyy > fxy * fxy)
    return {"xc": g.xc, "yc": g.yc, "sx0": sx[0], "sx1": sx[1], "sx2": sx[2],
            "sy0": sy[0], "sy1": sy[1], "sy2": sy[2], "s0z": a0 * b1 - a1 * b0, "kk": kk,
            "ix": dr.select(ellipse, dr.rcp(fxx), 0.0), "iy": dr.select(ellipse, dr.rcp(fyy), 0.0)}


def reaches_rect(c: dict, xa: mi.Float, xb: mi.Float, ya: mi.Float, yb: mi.Float,
                 config: RasterConfig) -> mi.Bool:
    """Whether a splat (``conic_of``: per splat or gathered per pair) can be kept
    (``pair_kept``) at a pixel centre in [xa, xb] x [ya, yb] (pixel coordinates):
    conservative, exact up to float32 rounding.

    ``pair_eval`` keeps rho3d = (s_x^2 + s_y^2) / s_z^2 <= k2, i.e. F(d) <= 0, or rho2d =
    lowpass_inv_var |d|^2 <= k2. Where F <= 0 is an ellipse, it holds the centre (F(0) =
    -k2 s_z^2 <= 0) and meets the rectangle iff the rectangle holds the centre or F <= 0
    somewhere on its edges; F along an edge is a convex quadratic, least at its stationary
    point clamped to the edge."""
    xa, xb = xa - config.box_margin - c["xc"], xb + config.box_margin - c["xc"]
    ya, yb = ya - config.box_margin - c["yc"], yb + config.box_margin - c["yc"]
    sx = (c["sx0"], c["sx1"], c["sx2"])
    sy = (c["sy0"], c["sy1"], c["sy2"])
    kk = c["kk"]

    def edge(x, y, d, inv, lo, hi):  # min over t in [lo, hi] of F(s(x, y) + t d)
        v = (x * sx[0] + y * sy[0], x * sx[1] + y * sy[1], c["s0z"] + x * sx[2] + y * sy[2])
        t = dr.clip(-(v[0] * d[0] + v[1] * d[1] - kk * v[2] * d[2]) * inv, lo, hi)
        v = tuple(vi + t * di for vi, di in zip(v, d, strict=True))
        return v[0] * v[0] + v[1] * v[1] - kk * v[2] * v[2]

    lowest = dr.minimum(dr.minimum(edge(xa, 0.0, sy, c["iy"], ya, yb),
                                   edge(xb, 0.0, sy, c["iy"], ya, yb)),
                        dr.minimum(edge(0.0, ya, sx, c["ix"], xa, xb),
                                   edge(0.0, yb, sx, c["ix"], xa, xb)))
    out = ((c["ix"] == 0) | ((xa <= 0) & (xb >= 0) & (ya <= 0) & (yb >= 0)) |
           (lowest <= 0))
    if config.lowpass_inv_var > 0:
        nx, ny = dr.clip(0.0, xa, xb), dr.clip(0.0, ya, yb)
        out |= config.lowpass_inv_var * (nx * nx + ny * ny) <= kk
    return out


def total_pairs(count: mi.UInt32) -> int:
    """Sum of per-surfel pair counts, in 64 bits (a UInt32 sum wraps past 4G pairs)."""
    return int(dr.sum(mi.UInt64(count))[0]) if dr.width(count) else 0


def memory_budget(config: RasterConfig, need: int) -> tuple[int, int] | None:
    """(budget, resident) in bytes for a render that needs ``need`` more, or None where the
    figures cannot be read (no /proc)."""
    def read():
        resident = memory.resident_bytes()
        budget = config.memory_budget_bytes
        if budget is None and resident is not None:
            avail = memory.available_bytes()
            budget = (None if avail is None else
                      resident + int(config.memory_budget_fraction * avail))
        return None if resident is None or budget is None else (budget, resident)

    got = read()
    if got is not None and got[1] + need > got[0]:
        dr.flush_malloc_cache()  # Dr.Jit's cache of freed blocks counts as resident
        got = read()
    return got


def budget_text(config: RasterConfig, budget: int, resident: int) -> str:
    gib = 1 << 30
    setting = (f"RasterConfig.memory_budget_bytes={config.memory_budget_bytes}"
               if config.memory_budget_bytes is not None else
               (f"RasterConfig.memory_budget_bytes=None: {config.memory_budget_fraction:g} of "
                f"MemAvailable"))
    return (f"the memory budget ({setting}) is {budget / gib:.2f} GiB and this process "
            f"already holds {resident / gib:.2f} GiB")


def pair_eval(q: dict, px: mi.Float, py: mi.Float, config: RasterConfig):
    """2DGS ray-splat intersection for pairs: (alpha, rho, depth, rho3d <= rho2d)."""
    dx = px - q["xc"]
    dy = py - q["yc"]
    sx = q["t22"] * (dx * q["b1"] - dy * q["a1"])
    sy = q["t22"] * (dy * q["a0"] - dx * q["b0"])
    sz = ((q["a0"] * q["b1"] - q["a1"] * q["b0"]) + dx * (q["t21"] * q["b0"] - q["t20"] * q["b1"])
          + dy * (q["a1"] * q["t20"] - q["a0"] * q["t21"]))
    # Edge-on: the ray (nearly) parallel to the plane; guard the division so that neither
    # the value nor the gradient sees inf, and let the low-pass filter take over.
    hit = dr.abs(sz) > config.edge_on_eps * (dr.abs(sx) + dr.abs(sy))
    szs = dr.select(hit, sz, 1.0)
    u = sx / szs
    v = sy / szs
    rho3d = dr.select(hit, u * u + v * v, _RHO_NONE)
    rho2d = config.lowpass_inv_var * (dx * dx + dy * dy)
    use3d = rho3d <= rho2d
    rho = dr.minimum(rho3d, rho2d)
    depth = dr.select(use3d, q["z2"] + u * q["z0"] + v * q["z1"], q["z2"])
    alpha = dr.minimum(config.alpha_max, q["opacity"] * dr.exp(-0.5 * rho))
    return alpha, rho, depth


def pair_eval_grad(q: dict, px, py, g_alpha, g_depth, config: RasterConfig) -> dict:
    """Reverse-mode derivative of ``pair_eval`` by hand: (dL/dalpha, dL/ddepth) of
    pairs -> dL/d of each of the 13 projected fields (``PAIR_FIELDS``). Follows the same
    branches: the alpha_max clamp, the min(rho3d, rho2d) switch and the edge-on guard."""
    a0, a1, b0, b1 = q["a0"], q["a1"], q["b0"], q["b1"]
    t20, t21, t22 = q["t20"], q["t21"], q["t22"]
    dx = px - q["xc"]
    dy = py - q["yc"]
    ex = dx * b1 - dy * a1
    ey = dy * a0 - dx * b0
    sx = t22 * ex
    sy = t22 * ey
    cx = t21 * b0 - t20 * b1
    cy = a1 * t20 - a0 * t21
    sz = (a0 * b1 - a1 * b0) + dx * cx + dy * cy
    hit = dr.abs(sz) > config.edge_on_eps * (dr.abs(sx) + dr.abs(sy))
    inv_sz = 1.0 / dr.select(hit, sz, 1.0)
    u = sx * inv_sz
    v = sy * inv_sz
    rho3d = dr.select(hit, u * u + v * v, _RHO_NONE)
    rho2d = config.lowpass_inv_var * (dx * dx + dy * dy)
    use3d = rho3d <= rho2d
    rho = dr.minimum(rho3d, rho2d)
    gauss = dr.exp(-0.5 * rho)
    raw = q["opacity"] * gauss
    g_raw = dr.select(raw < config.alpha_max, g_alpha, 0.0)  # the clamp passes nothing
    g_rho = -0.5 * g_raw * raw
    # rho and depth through the plane (use3d) or the filter / the centre's depth.
    g_u = dr.select(use3d, 2.0 * u * g_rho + g_depth * q["z0"], 0.0)
    g_v = dr.select(use3d, 2.0 * v * g_rho + g_depth * q["z1"], 0.0)
    g_rho2d = dr.select(use3d, 0.0, g_rho * config.lowpass_inv_var * 2.0)
    g_sx = g_u * inv_sz
    g_sy = g_v * inv_sz
    g_sz = -(g_u * u + g_v * v) * inv_sz
    g_dx = g_rho2d * dx + g_sx * t22 * b1 - g_sy * t22 * b0 + g_sz * cx
    g_dy = g_rho2d * dy - g_sx * t22 * a1 + g_sy * t22 * a0 + g_sz * cy
    return {
        "xc": -g_dx,
        "yc": -g_dy,
        "a0": g_sy * t22 * dy + g_sz * (b1 - dy * t21),
        "a1": -g_sx * t22 * dy + g_sz * (dy * t20 - b0),
        "b0": -g_sy * t22 * dx + g_sz * (dx * t21 - a1),
        "b1": g_sx * t22 * dx + g_sz * (a0 - dx * t20),
        "t20": g_sz * (dy * a1 - dx * b1),
        "t21": g_sz * (dx * b0 - dy * a0),
        "t22": g_sx * ex + g_sy * ey,
        "z0": dr.select(use3d, g_depth * u, 0.0),
        "z1": dr.select(use3d, g_depth * v, 0.0),
        "z2": g_depth,
        "opacity": g_raw * gauss,
    }


def pair_kept(alpha, rho, depth, config: RasterConfig):
    """Whether a pair contributes at all: alpha above alpha_min, inside the cutoff ellipse,
    in front of the near plane (both renderers drop the others)."""
    return ((alpha >= config.alpha_min) & (rho <= config.cutoff_sigma ** 2) &
            (depth >= config.near))


def distortion_m(depth, config: RasterConfig):
    """2DGS's NDC-like depth mapping m(z) of the distortion term (Float64)."""
    near, far = config.distortion_near, config.distortion_far
    return mi.Float64(far / (far - near)) * (1.0 - near / mi.Float64(depth))


PAIR_FIELDS = ("xc", "yc", "a0", "a1", "b0", "b1", "t20", "t21", "t22", "z0", "z1", "z2",
                "opacity")


# Most key bits that one counting pass of ``argsort_bounded`` sorts (65536 buckets).
SORT_PASS_BITS = 16


def argsort_bounded(keys: mi.UInt32, bound: int) -> mi.UInt32:
    """``dr.argsort(keys)`` (stable) of keys below ``bound``: on the LLVM backend one
    counting pass per SORT_PASS_BITS bits of ``bound - 1`` (a tile or pixel index: one
    pass), where ``dr.argsort`` makes three 11-bit passes over any 32-bit key; 3-5x faster
    at 0.2-1.8M keys. Elsewhere ``dr.argsort``."""
    n = dr.width(keys)
    if n <= 1 or dr.backend_v(keys) != dr.JitBackend.LLVM:
        return dr.argsort(keys) if n > 1 else dr.arange(mi.UInt32, n)
    bits = max(int(bound - 1).bit_length(), 1)
    passes = -(-bits // SORT_PASS_BITS)
    width = -(-bits // passes)
    index, k = dr.arange(mi.UInt32, n), keys
    for p in range(passes):
        digit = (k >> (p * width)) & ((1 << width) - 1) if passes > 1 else k
        dr.eval(digit)
        perm = dr.detail.block_mkperm(digit, n, bound if passes == 1 else 1 << width)
        if p + 1 < passes:
            k = dr.gather(mi.UInt32, k, perm)
        index = dr.gather(mi.UInt32, index, perm)
    return index


def depth_key(z: mi.Float) -> mi.UInt32:
    """Order-preserving uint of a float (negatives too)."""
    b = dr.reinterpret_array(mi.UInt32, z)
    return dr.select(b >= 0x80000000, ~b, b | 0x80000000)


def expand(count: mi.UInt32, total: int) -> tuple[mi.UInt32, mi.UInt32]:
    """(item id, index within its item) [total] of ``count`` [N] items laid end to end
    (``total`` = sum of ``count`` <= max_pairs < 2^32, so UInt32 offsets are safe)."""
    offsets = dr.prefix_sum(count)
    # Mark each non-empty item's first entry with its index and carry it forward with a
    # max-scan (ids increase along the list).
    sid = dr.zeros(mi.UInt32, total)
    dr.scatter(sid, dr.arange(mi.UInt32, dr.width(count)), offsets, active=count > 0)
    sid = dr.prefix_reduce(dr.ReduceOp.Max, sid, exclusive=False)
    return sid, dr.arange(mi.UInt32, total) - dr.gather(mi.UInt32, offsets, sid)
