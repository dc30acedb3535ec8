"""Differentiable 2DGS rasterizer in pure Dr.Jit (a pixel-splat pair list, fully traced).

Pipeline (one ``rasterize`` call):
1. per surfel: activate, build the tangent frame, move to the CV camera frame, project,
   and bound the ``cutoff_sigma`` ellipse and the low-pass footprint by a pixel box;
2. pair list: box sizes -> prefix sum -> (surfel, pixel) per pair (one host read of P);
   when the list would not fit the memory budget (``RasterConfig``), steps 2-4 run per band
   of image rows (forward renders) or the render is refused (renders with gradients);
3. per pair, detached: the 2DGS ray-splat intersection, low-pass filter and alpha; pairs
   that cannot contribute are compressed away, the rest sorted by (pixel, centre depth);
4. per kept pair, with AD: alpha again, a Float64 prefix sum of log(1 - alpha) segmented
   per pixel gives the transmittance, and ``scatter_reduce`` accumulates the images.

``RasterConfig(method="tiles")``, the default, replaces steps 2-4 by the tiled renderer of
``raster_tiles`` (surfels binned to screen tiles, a compositing loop per pixel, a
hand-written backward): the same images and gradients in memory O(pixels + surfel-tile
pairs), 3-5x faster. The pair list (``method="pairs"``) stays the reference in the tests,
the path of forward-mode derivatives, and the fallback of forward renders whose tiles do
not fit the memory budget.

The ray-splat intersection is the homogeneous one of 2DGS written relative to the
projected centre: with T the 3x3 map (u, v, 1) -> homogeneous pixel, A = T0 - xc T2 and
B = T1 - yc T2 are the projection's Jacobian applied to the scaled tangents, so pixel
offsets (dx, dy) from the centre enter without cancellation (far shadow-map cameras).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.config import get_preset
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
    # Screen-space filter: rho2d = lowpass_inv_var * |d|^2 (d in pixels), the splat's alpha
    # uses min(rho3d, rho2d). 12 is a filter of std 1/sqrt(12) px, that of a one-pixel box.
    # 2DGS's 2 (std 0.71 px) dilates every splat, and stage 1 pays for the dilation by
    # moving surfaces back along the view rays: surfels placed on the true default scene and
    # trained 600 steps drifted 0.04 units (~1.4 px) inside at 2, ~0.02 at 8, < 0.01 at 32
    # (BENCHMARKS.md, "Stage 1: the low-pass filter").
    lowpass_inv_var: float = 12.0
    cutoff_sigma: float = 3.0  # pairs with rho > cutoff_sigma^2 are dropped; sets the box
    near: float = 0.2  # centres and intersections with z-depth below this are culled
    distortion_near: float = 0.2  # NDC-like depth mapping of the distortion term (2DGS)
    distortion_far: float = 100.0
    scale_min: float = 1e-20  # surfels with a smaller tangent std-dev are culled (no plane)
    edge_on_eps: float = 1e-6  # |s_z| <= eps (|s_x|+|s_y|): ray ~ parallel to the plane
    box_margin: float = 0.01  # pixels; covers float32 rounding of the bounding box
    max_pairs: int = 1 << 30  # most pairs in one list (< 2^32: UInt32 pair indices)
    # Memory guard (``_plan_bands``). A render's peak memory is about reserve_bytes (kernel
    # compilation, images) plus a cost per pixel-box pair (measured 14 MiB + 52 B forward,
    # 32 MiB + 87 B forward+backward over every AOV: BENCHMARKS.md, "Rasterizer memory per
    # pixel-splat pair"). A render that would take this process's resident memory past the
    # budget is drawn in bands of image rows when nothing needs its gradient, and refused
    # (RasterMemoryError) when something does: the AD graph would keep every band's pairs
    # alive until the backward pass.
    memory_budget_bytes: int | None = None  # None: resident now + fraction of MemAvailable
    memory_budget_fraction: float = 0.5
    bytes_per_pair: int = 64  # forward only
    bytes_per_pair_grad: int = 112  # with gradients
    reserve_bytes: int = 48 << 20
    # "pairs": the pixel-splat pair list above (the reference; memory grows with the pairs).
    # "tiles" (default): the tiled renderer (``raster_tiles``): surfels binned to tile_size^2 pixel
    # tiles, one compositing loop per pixel, a hand-written backward; memory O(pixels +
    # surfel-tile pairs). Its guard counts bytes per surfel-tile pair (key, sort, sorted
    # fields; measured 95 B forward, 108 B forward+backward over every AOV and 3 channels:
    # ``bm_raster_memory --method tiles``) and per pixel lane (saved state, images,
    # gradient images: estimated from the arrays held), plus per channel 4 bytes per pair
    # and 8 per lane.
    method: str = "tiles"
    # Tiles of 4x4 pixels: one AVX-512 packet (16 lanes) per tile, so a packet reads one
    # sorted entry per iteration and pays for few pixels outside each splat's box. fwd+bwd
    # CPU ms at 1 thread, bm_raster workload 128^2/20k: 51 (2), 35 (4), 45 (5), 52 (8),
    # 158 (16); at 256^2/20k: 93 (4), 101 (8); the pair list: 123 and 503.
    tile_size: int = 4
    # Pixels of a tile that one lane of the tiled loops composites (a power of two; fewer
    # where the tile has fewer pixels). The lane reads each sorted entry once for all of
    # them and sums their gradients before one scatter per field; more pixels hold more
    # loop state per lane. Stage-1 step on the default scene (27.5k surfels, 128^2, 2
    # threads): 51.8-54.9 ms (1), 49.2-49.8 (2), 51.2-53.6 (4), 60-62 (8); a 512^2 shadow
    # map 37-38 ms (1), 30-31 (2 and 4) (BENCHMARKS.md, "Session 17").
    pixels_per_lane: int = 2
    bytes_per_tile_pair: int = 128
    bytes_per_pixel: int = 96  # forward only
    bytes_per_pixel_grad: int = 256  # with gradients
    # The tiled backward's per-surfel gradient sums: a private copy per thread (Dr.Jit's
    # ReduceMode.Expand, non-atomic) while the copies take at most this many bytes, atomics
    # after a pre-reduction in the SIMD packet (Local) above. Stage-1 step on the default
    # scene (27k surfels, 2 threads): backward loop 17.7 ms with Expand, 24.0 with Local,
    # 59.4 with plain atomics (``dr.kernel_history``; BENCHMARKS.md, "Session 8").
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


PRESETS = {"paper": RasterConfig(), "cpu-small": RasterConfig(), "cpu-medium": RasterConfig(),
           "gpu-large": RasterConfig()}


def get_config(name: str) -> RasterConfig:
    return get_preset(PRESETS, name, "raster")


# A finite stand-in for rho3d when the ray misses the plane (edge-on): the filter wins.
_RHO_NONE = 1e30


@dataclasses.dataclass
class _Proj:
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

    def detach(self) -> _Proj:
        return _Proj(*(dr.detach(getattr(self, f.name)) for f in dataclasses.fields(self)))

    def gather(self, idx: mi.UInt32, names: Sequence[str]) -> dict:
        out = {}
        for name in names:
            v = getattr(self, name)
            out[name] = dr.gather(type(v), v, idx)
        return out


def _project(surfels: Surfels, camera: Camera, config: RasterConfig) -> _Proj:
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
    return _Proj(valid, xc, yc, a0, a1, b0, b1, t20, t21, t22, z0, z1, z2,
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


def _boxes(g: _Proj, width: int, height: int, config: RasterConfig, rows=None):
    """Integer pixel boxes [x0, x1] x [y0, y1] (inclusive) per surfel, clipped to the image
    (and to the rows [r0, r1) of ``rows``, a pair of opaque Int32): (x0, y0, box width, box
    height, pixel count). A splat larger than the image thus counts at most H * W pixels."""
    k2 = config.cutoff_sigma ** 2
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
    rf = config.cutoff_sigma / math.sqrt(config.lowpass_inv_var) if config.lowpass_inv_var > 0 \
        else 0.0
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
    count = dr.select(g.valid, mi.UInt32(bw * bh), 0)
    return mi.UInt32(x0), mi.UInt32(y0), mi.UInt32(bw), mi.UInt32(bh), count


def _total(count: mi.UInt32) -> int:
    """Sum of per-surfel pair counts, in 64 bits (a UInt32 sum wraps past 4G pairs)."""
    return int(dr.sum(mi.UInt64(count))[0]) if dr.width(count) else 0


def _memory(config: RasterConfig, need: int) -> tuple[int, int] | None:
    """(budget, resident) in bytes for a render that needs ``need`` more, or None where the
    figures cannot be read (no /proc)."""
    def read():
        resident = memory.resident_bytes()
        budget = config.memory_budget_bytes
        if budget is None and resident is not None:
            avail = memory.available_bytes()
            budget = None if avail is None else \
                resident + int(config.memory_budget_fraction * avail)
        return None if resident is None or budget is None else (budget, resident)

    got = read()
    if got is not None and got[1] + need > got[0]:
        dr.flush_malloc_cache()  # Dr.Jit's cache of freed blocks counts as resident
        got = read()
    return got


def _budget_text(config: RasterConfig, budget: int, resident: int) -> str:
    gib = 1 << 30
    setting = f"RasterConfig.memory_budget_bytes={config.memory_budget_bytes}" \
        if config.memory_budget_bytes is not None else \
        (f"RasterConfig.memory_budget_bytes=None: {config.memory_budget_fraction:g} of "
         f"MemAvailable")
    return (f"the memory budget ({setting}) is {budget / gib:.2f} GiB and this process "
            f"already holds {resident / gib:.2f} GiB")


def _plan_bands(g: _Proj, width: int, height: int, config: RasterConfig,
                grad: bool) -> tuple[list[tuple[int, int]], int]:
    """(bands, total): bands of rows [r0, r1) whose pair lists fit the memory budget and
    ``max_pairs`` (the whole image when it fits, else consecutive bands when no ``grad``,
    else RasterMemoryError), and the whole image's pair count, which a single band reuses
    (one host read per render)."""
    _, y0, bw, bh, count = _boxes(g, width, height, config)
    total = _total(count)
    per_pair = config.bytes_per_pair_grad if grad else config.bytes_per_pair
    need = total * per_pair + config.reserve_bytes
    mem = _memory(config, need) if total else None
    over = mem is not None and mem[1] + need > mem[0]
    if not over and total <= config.max_pairs:
        return [(0, height)], total
    hint = "(surfels too large for the image?)"
    why = (f"{_budget_text(config, *mem)}" if over else
           f"RasterConfig.max_pairs is {config.max_pairs}")
    if grad:
        raise RasterMemoryError(
            f"rasterize: {total} pixel-splat pairs need ~{need / (1 << 30):.2f} GiB, but "
            f"{why}; a render with gradients is not split into bands {hint}")
    limit = config.max_pairs
    if over:
        budget, resident = mem
        limit = min(limit, (budget - resident - config.reserve_bytes) // per_pair)
    # Pairs per row: each box adds its width to its rows y0 .. y0 + bh - 1.
    y0n, bwn, bhn, cn = (np.asarray(v, np.int64) for v in (y0, bw, bh, count))
    w = np.where(cn > 0, bwn, 0).astype(np.float64)
    edges = np.bincount(np.minimum(y0n, height), w, height + 1) \
        - np.bincount(np.minimum(y0n + bhn, height), w, height + 1)
    per_row = np.cumsum(edges)[:height]  # [H], exact integers in float64
    if per_row.max() > limit:
        raise RasterMemoryError(
            f"rasterize: one image row holds {int(per_row.max())} pixel-splat pairs "
            f"(~{per_row.max() * per_pair / (1 << 30):.2f} GiB), but {why} "
            f"{hint}")
    bands, start, acc = [], 0, 0.0
    for r, c in enumerate(per_row):
        if acc + c > limit:
            bands.append((start, r))
            start, acc = r, 0.0
        acc += c
    bands.append((start, height))
    return bands, total


def _pair_eval(q: dict, px: mi.Float, py: mi.Float, config: RasterConfig):
    """2DGS ray-splat intersection for pairs: (alpha, rho, depth, rho3d <= rho2d)."""
    dx = px - q["xc"]
    dy = py - q["yc"]
    sx = q["t22"] * (dx * q["b1"] - dy * q["a1"])
    sy = q["t22"] * (dy * q["a0"] - dx * q["b0"])
    sz = (q["a0"] * q["b1"] - q["a1"] * q["b0"]) + dx * (q["t21"] * q["b0"] - q["t20"] * q["b1"]) \
        + dy * (q["a1"] * q["t20"] - q["a0"] * q["t21"])
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


def _pair_kept(alpha, rho, depth, config: RasterConfig):
    """Whether a pair contributes at all: alpha above alpha_min, inside the cutoff ellipse,
    in front of the near plane (both renderers drop the others)."""
    return (alpha >= config.alpha_min) & (rho <= config.cutoff_sigma ** 2) & \
        (depth >= config.near)


def _distortion_m(depth, config: RasterConfig):
    """2DGS's NDC-like depth mapping m(z) of the distortion term (Float64)."""
    near, far = config.distortion_near, config.distortion_far
    return mi.Float64(far / (far - near)) * (1.0 - near / mi.Float64(depth))


_PAIR_FIELDS = ("xc", "yc", "a0", "a1", "b0", "b1", "t20", "t21", "t22", "z0", "z1", "z2",
                "opacity")


def depth_key(z: mi.Float) -> mi.UInt32:
    """Order-preserving uint of a float (negatives too)."""
    b = dr.reinterpret_array(mi.UInt32, z)
    return dr.select(b >= 0x80000000, ~b, b | 0x80000000)


def _expand(count: mi.UInt32, total: int) -> tuple[mi.UInt32, mi.UInt32]:
    """(item id, index within its item) [total] of ``count`` [N] items laid end to end
    (``total`` = sum of ``count`` <= max_pairs < 2^32, so UInt32 offsets are safe)."""
    offsets = dr.prefix_sum(count)
    # Mark each non-empty item's first entry with its index and carry it forward with a
    # max-scan (ids increase along the list).
    sid = dr.zeros(mi.UInt32, total)
    dr.scatter(sid, dr.arange(mi.UInt32, dr.width(count)), offsets, active=count > 0)
    sid = dr.prefix_reduce(dr.ReduceOp.Max, sid, exclusive=False)
    return sid, dr.arange(mi.UInt32, total) - dr.gather(mi.UInt32, offsets, sid)


def _build_pairs(g: _Proj, width: int, height: int, config: RasterConfig,
                 rows: tuple[int, int] | None = None, total: int | None = None):
    """Sorted (surfel id, pixel id) of the pairs that contribute; detached. None if none.

    ``rows`` = (r0, r1) restricts the pairs to those image rows; pixel ids then count from
    row r0 (pixel (x, y) is (y - r0) * width + x). ``total``: their pixel-box pair count
    when the caller already read it (``_plan_bands``)."""
    r0, r1 = (0, height) if rows is None else rows
    x0, y0, bw, _, count = _boxes(g, width, height, config,
                                  (dr.opaque(mi.Int32, r0), dr.opaque(mi.Int32, r1)))
    total = _total(count) if total is None else total
    if total > config.max_pairs:
        raise RasterMemoryError(f"rasterize: {total} pixel-splat pairs exceed "
                                f"RasterConfig.max_pairs={config.max_pairs} (surfels too "
                                f"large for the image?)")
    if total == 0:
        return None
    # The pairs laid out surfel by surfel front to back (a stable sort of the N centre
    # depths: equal depths keep surfel order), then a stable sort by pixel alone: each
    # pixel's pairs in (depth, surfel) order, as a sort of 64-bit (pixel, depth) keys over
    # the pairs would leave them, with 32-bit keys (3 radix passes over P instead of 6).
    by_depth = dr.argsort(depth_key(g.z2))  # [N]
    pos, local = _expand(dr.gather(mi.UInt32, count, by_depth), total)
    sid = dr.gather(mi.UInt32, by_depth, pos)
    # max(., 1): masked-off tail lanes of a gather read 0, and x86 integer division by 0
    # traps (SIGFPE) even in lanes that are discarded.
    w = dr.maximum(dr.gather(mi.UInt32, bw, sid), 1)
    ly = local // w
    lx = local - ly * w
    pxi = dr.gather(mi.UInt32, x0, sid) + lx
    pyi = dr.gather(mi.UInt32, y0, sid) + ly
    q = g.gather(sid, _PAIR_FIELDS)
    alpha, rho, depth = _pair_eval(q, mi.Float(pxi) + 0.5, mi.Float(pyi) + 0.5, config)
    idx = dr.compress(_pair_kept(alpha, rho, depth, config))
    if dr.width(idx) == 0:
        return None
    sid = dr.gather(mi.UInt32, sid, idx)
    pix = dr.gather(mi.UInt32, (pyi - dr.opaque(mi.UInt32, r0)) * width + pxi, idx)
    order = dr.argsort(pix)
    sid = dr.gather(mi.UInt32, sid, order)
    pix = dr.gather(mi.UInt32, pix, order)
    dr.eval(sid, pix)
    return sid, pix


def segment_exclusive_sum(x: mi.Float64, pix: mi.UInt32, first: mi.Bool, npix: int):
    """Exclusive prefix sum of ``x`` restarted at each pixel's first pair (Float64)."""
    cs = dr.prefix_sum(x)
    base = dr.zeros(mi.Float64, npix)
    dr.scatter_reduce(dr.ReduceOp.Add, base, cs, pix, active=first)
    return cs - dr.gather(mi.Float64, base, pix)


@dataclasses.dataclass
class _Scan:
    """Front-to-back compositing of the sorted pairs [P] (see ``_scan``)."""

    ar: mi.UInt32  # pair index
    last_idx: mi.UInt32  # P - 1, opaque
    first: mi.Bool  # the pixel's first pair
    last: mi.Bool  # the pixel's last pair
    t_before: mi.Float64  # transmittance in front of the pair
    t_after: mi.Float64  # transmittance behind it
    contrib: mi.Bool  # the pair is composited (2DGS early stop)
    w64: mi.Float64  # its weight T alpha (0 where it does not contribute)


def pixel_runs(pix: mi.UInt32) -> tuple[mi.UInt32, mi.UInt32, mi.Bool, mi.Bool]:
    """(pair index, P - 1, first pair of its pixel, last pair of its pixel) [P] of pairs
    grouped by pixel (P >= 1)."""
    npairs = dr.width(pix)
    ar = dr.arange(mi.UInt32, npairs)
    prev_pix = dr.gather(mi.UInt32, pix, dr.maximum(ar, 1) - 1)
    last_idx = dr.opaque(mi.UInt32, npairs - 1)  # opaque: P must not be baked into kernels
    next_pix = dr.gather(mi.UInt32, pix, dr.minimum(ar + 1, last_idx))
    return ar, last_idx, (ar == 0) | (prev_pix != pix), (ar == last_idx) | (next_pix != pix)


def _scan(alpha: mi.Float, pix: mi.UInt32, npix: int, config: RasterConfig) -> _Scan:
    """Transmittance and weights of pairs sorted by (pixel, depth): a Float64 prefix sum of
    log(1 - alpha) restarted at each pixel (differentiable, unlike a product scan)."""
    ar, last_idx, first, last = pixel_runs(pix)
    a64 = mi.Float64(alpha)
    t_before = dr.exp(segment_exclusive_sum(dr.log(1.0 - a64), pix, first, npix))
    t_after = t_before * (1.0 - a64)
    # 2DGS stops a pixel before the splat that would take T below transmittance_min.
    contrib = dr.detach(t_after) >= config.transmittance_min
    w64 = dr.select(contrib, t_before * a64, 0.0)
    return _Scan(ar, last_idx, first, last, t_before, t_after, contrib, w64)


def _centres(pix: mi.UInt32, width: int, r0: int) -> tuple[mi.Float, mi.Float]:
    """Pixel centres (x, y) [P] of band-relative pixel ids (the band starts at row r0)."""
    y = pix // width
    return mi.Float(pix - y * width) + 0.5, mi.Float(y + dr.opaque(mi.UInt32, r0)) + 0.5


def splat_pairs(surfels: Surfels, camera: Camera, config: RasterConfig = RasterConfig(),
                with_depth: bool = False) -> tuple:
    """The contributing (surfel id, pixel id) pairs of a view and their weights T_i alpha_i,
    detached, in compositing order: exactly what ``rasterize`` blends. Stages whose
    geometry is fixed compute them once per view and reuse them (``shading.splat``).
    ``with_depth``: also each pair's z-depth (the ray-splat intersection that "depth" and
    "median_depth" blend). Built in bands of rows when the whole list would not fit the
    memory budget."""
    n_out = 4 if with_depth else 3
    parts = []
    with dr.suspend_grad():
        g = _project(surfels, camera, config).detach()
        dr.eval(*(getattr(g, f.name) for f in dataclasses.fields(g)))
        w, h = camera.width, camera.height
        bands, total = _plan_bands(g, w, h, config, grad=False) if surfels.count else ([], 0)
        for r0, r1 in bands:
            pairs = _build_pairs(g, w, h, config, (r0, r1),
                                 total if len(bands) == 1 else None)
            if pairs is None:
                continue
            sid, pix = pairs
            q = g.gather(sid, _PAIR_FIELDS)
            alpha, _, depth = _pair_eval(q, *_centres(pix, w, r0), config)
            weight = mi.Float(_scan(alpha, pix, (r1 - r0) * w, config).w64)
            keep = dr.compress(weight > 0)
            kept = (sid, pix, weight, depth)[:n_out]
            kept = [dr.gather(type(x), x, keep) for x in kept]
            kept[1] = kept[1] + dr.opaque(mi.UInt32, r0 * w)
            dr.eval(*kept)
            parts.append(tuple(kept))
    if not parts:
        return (mi.UInt32(), mi.UInt32(), mi.Float(), mi.Float())[:n_out]
    if len(parts) == 1:
        return parts[0]
    return tuple(dr.concat([p[k] for p in parts]) for k in range(n_out))


def pair_counts(surfels: Surfels, camera: Camera, config: RasterConfig = RasterConfig()
                ) -> tuple[int, int]:
    """(pixel-box pairs, pairs kept after the alpha/cutoff tests) of a view (benchmarks)."""
    with dr.suspend_grad():
        g = _project(surfels, camera, config).detach()
        box = _boxes(g, camera.width, camera.height, config)[4]
        built = _build_pairs(g, camera.width, camera.height, config)
        return _total(box), 0 if built is None else dr.width(built[0])


def _resolve_channels(surfels: Surfels, channels):
    channels = channels or {}
    n = surfels.count
    out = {}
    for name, t in channels.items():
        if not isinstance(t, mi.TensorXf) or len(t.shape) != 2 or t.shape[0] != n:
            shape = tuple(t.shape) if hasattr(t, "shape") else type(t).__name__
            raise ValueError(f"rasterize: channel {name!r} must be a TensorXf [N={n}, C], "
                             f"got {shape}")
        if name in AOV_CHANNELS:
            raise ValueError(f"rasterize: channel name {name!r} clashes with an AOV name")
        out[name] = t
    return out


def rasterize(surfels: Surfels, camera: Camera,
              channels: Mapping[str, mi.TensorXf] | None = None, *,
              aovs: Sequence[str] = ("alpha", "depth"),
              background: Mapping[str, Sequence[float]] | None = None,
              config: RasterConfig = RasterConfig(),
              pixels: mi.UInt32 | np.ndarray | None = None) -> dict[str, mi.TensorXf]:
    """Render ``surfels`` seen by ``camera``: images [H, W, C] by name.

    ``channels`` maps names to per-surfel values [N, C]; each becomes sum_i T_i alpha_i c_i
    (plus ``background[name] * (1 - alpha)`` when given); ``None`` renders AOVs only. For
    SH colour pass ``{"rgb": sh_colors(surfels, camera.origin)}``.
    ``aovs``: any of "alpha", "depth" (expected z-depth, 0 where alpha = 0), "median_depth",
    "normal" (world space, facing the camera, not renormalised), "distortion" (2DGS depth
    distortion), "count" (contributing splats, no gradient). Differentiable in reverse mode
    with respect to all surfel parameters and channel values.

    A render whose pair list would exceed ``config.memory_budget_bytes`` is drawn in bands of
    rows when no input needs a gradient, and raises RasterMemoryError (a ValueError) when
    one does. ``config.method="tiles"`` renders the same images with the tiled renderer
    (``raster_tiles``; reverse-mode gradients only), whose memory does not grow with the
    pixel-splat pairs; it raises RasterMemoryError when its surfel-tile pairs do not fit.

    ``pixels``: flat indices y * W + x [P] (repeats allowed): only those pixels, outputs
    [P, C] in their order, each pixel's value that of the whole image. The tiled renderer
    composites just those pixels (stage 2 samples 2k of 16k per step); the pair list
    renders the image and gathers them.
    """
    for a in aovs:
        if a not in AOV_CHANNELS:
            raise ValueError(f"rasterize: unknown AOV {a!r}; known: {sorted(AOV_CHANNELS)}")
    if not 0.0 < config.alpha_max < 1.0:
        raise ValueError(f"RasterConfig.alpha_max must be in (0, 1), got {config.alpha_max}")
    chans = _resolve_channels(surfels, channels)
    bg = {}
    for name, value in (background or {}).items():
        if name not in chans:
            raise ValueError(f"rasterize: background given for {name!r}, which is not a "
                             f"rendered channel ({sorted(chans)})")
        vals = [float(v) for v in np.asarray(value, dtype=np.float64).reshape(-1)]
        if len(vals) != chans[name].shape[1]:
            raise ValueError(f"rasterize: background {name!r} has {len(vals)} values, "
                             f"channel has {chans[name].shape[1]}")
        bg[name] = vals
    H, W = camera.height, camera.width
    if pixels is not None:
        host = np.asarray(pixels.numpy() if hasattr(pixels, "numpy") else pixels)
        if host.ndim != 1 or (host.size and (host.min() < 0 or host.max() >= W * H)):
            raise ValueError(f"rasterize: pixels must be flat indices in [0, {W * H}) of the "
                             f"{W}x{H} image, got shape {host.shape}")
        if host.size == 0:  # nothing to composite
            return {name: dr.zeros(mi.TensorXf, (0, t.shape[1])) for name, t in chans.items()} \
                | {a: dr.zeros(mi.TensorXf, (0, AOV_CHANNELS[a])) for a in aovs}
        pixels = mi.UInt32(host.astype(np.uint32))

    g = _project(surfels, camera, config)
    # One per-surfel kernel now, rather than whatever set of pending variables the first
    # gather happens to evaluate (that set varies and defeats the kernel cache).
    dr.eval(*(getattr(g, f.name) for f in dataclasses.fields(g)))
    gd = g.detach()
    grad = any(dr.grad_enabled(getattr(g, f.name)) for f in dataclasses.fields(g)) or \
        any(dr.grad_enabled(t) for t in chans.values())
    widths = {name: t.shape[1] for name, t in chans.items()} | \
        {a: AOV_CHANNELS[a] for a in aovs}
    if config.method == "tiles":
        from mi_shadowgs.core.raster_tiles import render_tiles

        try:
            flat = render_tiles(g, gd, W, H, chans, aovs, bg, config, grad, pixels)
            shape = (H, W) if pixels is None else (dr.width(pixels),)
            return {name: mi.TensorXf(flat[name], shape=(*shape, c))
                    for name, c in widths.items()}
        except RasterMemoryError:
            if grad:
                raise
            # A forward render whose tiles do not fit even at the largest tile size: the
            # pair list below, in bands of rows (the same image).
    bands, total = _plan_bands(gd, W, H, config, grad) if surfels.count else ([(0, H)], 0)
    parts = []
    for r0, r1 in bands:
        part = _render_rows(g, gd, r0, r1, W, H, chans, aovs, bg, config,
                            total if len(bands) == 1 else None)
        if len(bands) > 1:  # free this band's pairs before the next one is built
            dr.eval(*part.values())
            dr.flush_malloc_cache()
        parts.append(part)
    images = {name: mi.TensorXf(parts[0][name] if len(parts) == 1 else
                                dr.concat([p[name] for p in parts]), shape=(H, W, c))
              for name, c in widths.items()}
    if pixels is None:
        return images
    return {name: mi.TensorXf(dr.gather(mi.Float, img.array,
                                        dr.repeat(pixels, c) * c +
                                        dr.tile(dr.arange(mi.UInt32, c), dr.width(pixels))),
                              shape=(dr.width(pixels), c))
            for (name, img), c in zip(images.items(), widths.values(), strict=True)}


def _render_rows(g: _Proj, gd: _Proj, r0: int, r1: int, W: int, H: int, chans: dict,
                 aovs: Sequence[str], bg: dict, config: RasterConfig,
                 total: int | None = None) -> dict[str, mi.Float]:
    """Rows [r0, r1) of every output of ``rasterize``, flat ([(r1 - r0) * W * C] each);
    ``g`` the projected surfels with AD, ``gd`` detached, ``total`` their pair count if
    known."""
    npix = (r1 - r0) * W
    pairs = _build_pairs(gd, W, H, config, (r0, r1), total) if dr.width(gd.xc) else None
    if pairs is None:
        out = {name: dr.zeros(mi.Float, npix * t.shape[1]) for name, t in chans.items()}
        for name, vals in bg.items():
            out[name] = dr.tile(mi.Float(vals), npix)
        for a in aovs:
            out[a] = dr.zeros(mi.Float, npix * AOV_CHANNELS[a])
        return out
    sid, pix = pairs

    # Per-pair quantities with AD, in sorted order.
    q = g.gather(sid, _PAIR_FIELDS)
    alpha, _, depth = _pair_eval(q, *_centres(pix, W, r0), config)

    sc = _scan(alpha, pix, npix, config)
    ar, last_idx, last, first = sc.ar, sc.last_idx, sc.last, sc.first
    t_before, t_after, contrib, w64 = sc.t_before, sc.t_after, sc.contrib, sc.w64
    w = mi.Float(w64)

    def accumulate(values, c):  # values: list of c per-pair Float
        img = dr.zeros(mi.Float, npix * c)
        for k in range(c):
            dr.scatter_reduce(dr.ReduceOp.Add, img, values[k], pix * c + k)
        return img

    need_alpha = bool(bg) or any(a in aovs for a in ("alpha", "depth"))
    alpha_img = accumulate([w], 1) if need_alpha else None
    out = {}
    for name, t in chans.items():
        c = t.shape[1]
        base = sid * c
        vals = [w * dr.gather(mi.Float, t.array, base + k) for k in range(c)]
        img = accumulate(vals, c)
        if name in bg:
            img = img + dr.tile(jit.array(bg[name]), npix) * dr.repeat(1.0 - alpha_img, c)
        out[name] = img
    if "alpha" in aovs:
        out["alpha"] = alpha_img
    if "depth" in aovs:
        acc = accumulate([w * depth], 1)
        ok = alpha_img > 0
        out["depth"] = dr.select(ok, acc / dr.select(ok, alpha_img, 1.0), 0.0)
    if "median_depth" in aovs:
        # The last contributing splat with T > 0.5 in front of it (2DGS).
        nxt_contrib = dr.gather(mi.Bool, contrib, dr.minimum(ar + 1, last_idx))
        end = last | ~nxt_contrib | (dr.detach(t_after) <= 0.5)
        sel = contrib & (dr.detach(t_before) > 0.5) & end
        out["median_depth"] = accumulate([dr.select(sel, depth, 0.0)], 1)
    if "normal" in aovs:
        n = g.gather(sid, ("normal",))["normal"]
        out["normal"] = accumulate([w * n.x, w * n.y, w * n.z], 3)
    if "distortion" in aovs:
        m = _distortion_m(depth, config)
        wm = w64 * m
        m1 = segment_exclusive_sum(wm, pix, first, npix)
        m2 = segment_exclusive_sum(wm * m, pix, first, npix)
        acc = 1.0 - t_before  # = sum of the weights in front (all of them contribute)
        d = w64 * (m * m * acc + m2 - 2.0 * m * m1)
        out["distortion"] = accumulate([mi.Float(d)], 1)
    if "count" in aovs:
        out["count"] = accumulate([dr.select(contrib, mi.Float(1.0), 0.0)], 1)
    return out
