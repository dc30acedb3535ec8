"""Tiled 2DGS rasterizer: memory O(pixels + surfels + surfel-tile pairs), forward and backward.

``RasterConfig(method="tiles")`` selects it in ``raster.rasterize``; the pair-list renderer
(``raster.py``) stays the reference. Same projection (``_project``), bounds (``_boxes``) and
per-pair maths (``_pair_eval``), so both composite the same pairs in the same order:

1. binning (detached): each surfel's pixel box covers a rectangle of screen tiles
   (``RasterConfig.tile_size``); surfel-tile pairs come from a prefix sum over the tile
   counts of the surfels in depth order (one host read), a stable ``dr.argsort`` by tile
   orders them by (tile, centre depth), and each tile gets its [start, end) range;
2. forward: one lane per pixel, tile-major so that a SIMD packet shares one tile and reads
   the same sorted entry in every iteration; a symbolic ``dr.while_loop`` walks the tile's
   list front to back, skips pairs outside the surfel's box or failing the alpha / cutoff /
   near tests (the pair list drops them), composites with a Float64 transmittance and stops
   before the splat that would take T below ``transmittance_min`` (``raster._scan``);
3. backward (``_TiledOp``, a ``dr.CustomOp``): the forward keeps per pixel only its final
   T, its stop index and a few Float64 sums; the backward walks each list back to front
   from the stop index, recovering T_i = T_{i+1} / (1 - alpha_i) in Float64, and chains
   the output gradients through alpha and depth to the 13 projected fields by hand
   (``_pair_eval_grad``), scatter-adding per surfel. Dr.Jit's AD then carries those
   gradients from the projected fields to the surfel parameters (``_project``).

Why T is recovered by division rather than recomputed front to back: one pass instead of
two (the back-to-front sum of w_j g_j over later pairs needs the output gradients, so a
front-to-back replay would need a first pass for the total), and with alpha <= alpha_max =
0.99 each division adds ~1e-16 relative error and the error grows linearly in the number
of splats: the T recovered at the front of each pixel is 1 to 8.9e-16 after 1753 splats
(test_raster_tiles's 1e5-surfel stack; 2.2e-16 after 10 splats of opacity 0.3-0.95).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import drjit as dr
import mitsuba as mi

from mi_shadowgs.core import jit
from mi_shadowgs.core.raster import (
    _PAIR_FIELDS,
    _RHO_NONE,
    AOV_CHANNELS,
    RasterConfig,
    RasterMemoryError,
    _boxes,
    _budget_text,
    _depth_key,
    _distortion_m,
    _expand,
    _memory,
    _pair_eval,
    _pair_kept,
    _Proj,
    _total,
)

# Projected per-surfel fields the compositing loops read: the pair maths plus the normal.
_NORMAL_FIELDS = ("nx", "ny", "nz")
# Lanes that start the backward walk together (``_tiled_backward``): an AVX-512 packet.
_BACKWARD_GROUP = 16
# Largest tile edge that ``_bin`` grows to when the configured tiles' pairs do not fit the
# memory budget (64: 4096 lanes, 256 SIMD packets per tile list; the tests cover it).
MAX_TILE_SIZE = 64
# Pixel boxes are packed as two 16-bit coordinates per UInt32 (``_Bins.box``).
_BOX_MAX = 0xFFFF


@dataclasses.dataclass
class _Bins:
    """Surfel-tile pairs sorted by (tile, depth), and the tile grid."""

    size: int  # tile edge in pixels
    ntx: int  # tiles per row
    nty: int  # tiles per column
    sid: mi.UInt32  # [TP] surfel of each sorted pair
    box: tuple  # ([TP] x0 | x1 << 16, [TP] y0 | y1 << 16): the surfel's pixel box
    start: mi.UInt32  # [tiles] first sorted pair of each tile
    end: mi.UInt32  # [tiles] one past its last

    @property
    def lanes(self) -> int:
        return self.ntx * self.nty * self.size * self.size


def _check_tile_budget(tile_pairs: int, lanes: int, config: RasterConfig, grad: bool,
                       channels: int, surfels: int) -> None:
    """RasterMemoryError when the tiled render would not fit the memory budget or
    ``max_pairs``: its memory is O(lanes + surfel-tile pairs), both known before binning,
    plus the backward's per-thread gradient copies (``_grad_copy_bytes``)."""
    if tile_pairs > config.max_pairs:
        raise RasterMemoryError(
            f"rasterize (tiles): {tile_pairs} surfel-tile pairs exceed "
            f"RasterConfig.max_pairs={config.max_pairs} (surfels too large for the image?)")
    per_lane = config.bytes_per_pixel_grad if grad else config.bytes_per_pixel
    need = config.reserve_bytes + lanes * (per_lane + 8 * channels) + \
        tile_pairs * (config.bytes_per_tile_pair + 4 * channels)
    if grad:
        # The normal's fields counted whether or not it is rendered: an upper bound.
        need += _grad_copy_bytes(_grad_entries(surfels, True, channels), config)
    mem = _memory(config, need)
    if mem is not None and mem[1] + need > mem[0]:
        raise RasterMemoryError(
            f"rasterize (tiles): {tile_pairs} surfel-tile pairs and {lanes} pixels need "
            f"~{need / (1 << 30):.2f} GiB, but {_budget_text(config, *mem)}; a smaller "
            f"image lowers it")


def _bin(gd: _Proj, width: int, height: int, config: RasterConfig, grad: bool,
         channels: int) -> _Bins | None:
    """Surfel-tile pairs of the detached projected surfels ``gd``; None when there are
    none."""
    x0, y0, bw, bh, count = _boxes(gd, width, height, config)
    live = count > 0
    # Tiles of config.tile_size pixels; where their pairs would not fit the memory budget
    # (surfels covering much of the image), tiles twice as large, up to MAX_TILE_SIZE:
    # large splats make ~1/ts^2 as many pairs, at the cost of lanes testing pixels outside
    # the smaller splats' boxes.
    ts = config.tile_size
    while True:
        ntx, nty = -(-width // ts), -(-height // ts)
        # bw, bh >= 1 on live surfels; max(., 1) keeps the dead ones' arithmetic in range.
        tx0, ty0 = x0 // ts, y0 // ts
        tw = dr.select(live, (x0 + dr.maximum(bw, 1) - 1) // ts - tx0 + 1, 0)
        th = dr.select(live, (y0 + dr.maximum(bh, 1) - 1) // ts - ty0 + 1, 0)
        ntiles = tw * th  # [N]
        total = _total(ntiles)
        try:
            _check_tile_budget(total, ntx * nty * ts * ts, config, grad, channels,
                               dr.width(gd.xc))
            break
        except RasterMemoryError:
            if ts >= max(MAX_TILE_SIZE, config.tile_size) or ts >= max(width, height):
                raise
            ts = min(2 * ts, max(MAX_TILE_SIZE, config.tile_size))
    if total == 0:
        return None
    # Surfels front to back (stable: equal depths keep surfel order, as in the pair list),
    # their pairs laid out in that order, then a stable sort by tile: two 32-bit sorts
    # (N and TP keys) instead of one of 64-bit (tile, depth) keys over TP.
    by_depth = dr.argsort(_depth_key(gd.z2))  # [N]
    pos, local = _expand(dr.gather(mi.UInt32, ntiles, by_depth), total)  # [TP]
    sid = dr.gather(mi.UInt32, by_depth, pos)
    w = dr.maximum(dr.gather(mi.UInt32, tw, sid), 1)  # max: see _expand
    ly = local // w
    tile = (dr.gather(mi.UInt32, ty0, sid) + ly) * ntx + dr.gather(mi.UInt32, tx0, sid) + \
        (local - ly * w)
    order = dr.argsort(tile)
    sid = dr.gather(mi.UInt32, sid, order)
    tile = dr.gather(mi.UInt32, tile, order)
    ar = dr.arange(mi.UInt32, total)
    last_idx = dr.opaque(mi.UInt32, total - 1)
    prev = dr.gather(mi.UInt32, tile, dr.maximum(ar, 1) - 1)
    nxt = dr.gather(mi.UInt32, tile, dr.minimum(ar + 1, last_idx))
    start = dr.zeros(mi.UInt32, ntx * nty)
    end = dr.zeros(mi.UInt32, ntx * nty)
    dr.scatter(start, ar, tile, active=(ar == 0) | (prev != tile))
    dr.scatter(end, ar + 1, tile, active=(ar == last_idx) | (nxt != tile))
    x1 = x0 + bw - 1  # inclusive; only read for live surfels
    y1 = y0 + bh - 1
    box = (dr.gather(mi.UInt32, x0 | (x1 << 16), sid), dr.gather(mi.UInt32, y0 | (y1 << 16), sid))
    dr.eval(sid, start, end, *box)
    return _Bins(ts, ntx, nty, sid, box, start, end)


def _lanes(bins: _Bins, width: int, height: int):
    """Per lane (tile-major, row-major inside a tile): (tile, pixel x, pixel y, inside)."""
    ts2 = bins.size * bins.size
    lane = dr.arange(mi.UInt32, bins.lanes)
    tile = lane // ts2
    local = lane - tile * ts2
    ty = tile // bins.ntx
    ly = local // bins.size
    px = (tile - ty * bins.ntx) * bins.size + (local - ly * bins.size)
    py = ty * bins.size + ly
    inside = (px < width) & (py < height)
    return tile, px, py, inside


def _lane_of_pixel(bins: _Bins, width: int, height: int) -> mi.UInt32:
    """[H * W] the lane (``_lanes``) of each pixel, row-major."""
    pix = dr.arange(mi.UInt32, width * height)
    py = pix // width
    px = pix - py * width
    ty, tx = py // bins.size, px // bins.size
    local = (py - ty * bins.size) * bins.size + (px - tx * bins.size)
    return (ty * bins.ntx + tx) * (bins.size * bins.size) + local


def _to_image(vals: list, bins: _Bins, width: int, height: int) -> mi.Float:
    """Lane values (C arrays [lanes]) -> a flat image [H * W * C]."""
    c = len(vals)
    lane = _lane_of_pixel(bins, width, height)
    if c == 1:
        return dr.gather(mi.Float, vals[0], lane)
    idx = dr.arange(mi.UInt32, width * height * c)
    pix = idx // c
    k = idx - pix * c
    lane = dr.gather(mi.UInt32, lane, pix)
    out = dr.gather(mi.Float, vals[0], lane)
    for i in range(1, c):
        out = dr.select(k == i, dr.gather(mi.Float, vals[i], lane), out)
    return out


def _in_box(bins: _Bins, j: mi.UInt32, px: mi.UInt32, py: mi.UInt32) -> mi.Bool:
    """Whether pixel (px, py) lies in the box of sorted pair j's surfel (the pair list
    holds exactly the box's pixels)."""
    bx = dr.gather(mi.UInt32, bins.box[0], j)
    by = dr.gather(mi.UInt32, bins.box[1], j)
    return (px >= (bx & 0xFFFF)) & (px <= (bx >> 16)) & (py >= (by & 0xFFFF)) & \
        (py <= (by >> 16))


class _TiledOp(dr.CustomOp):
    """Forward: every requested image (flat, [H * W * C]); backward: gradients of the
    projected fields and the channel values (``_TiledCtx`` holds the non-differentiable
    set-up)."""

    def eval(self, fields: dict, chans: dict, ctx: _TiledCtx):
        self.ctx = ctx
        bins, config = ctx.bins, ctx.config
        # [TP] the fields in sorted order: the loop reads them sequentially.
        self.sorted = {k: dr.gather(mi.Float, v, bins.sid) for k, v in fields.items()}
        self.sorted_chans = {
            name: [dr.gather(mi.Float, arr, bins.sid * c + k) for k in range(c)]
            for (name, arr), c in zip(chans.items(), ctx.widths.values(), strict=True)}
        tile, px, py, inside = _lanes(bins, ctx.width, ctx.height)
        pxf, pyf = mi.Float(px) + 0.5, mi.Float(py) + 0.5
        aovs = ctx.aovs
        want_depth = "depth" in aovs
        want_med = "median_depth" in aovs
        want_normal = "normal" in aovs
        want_dist = "distortion" in aovs
        want_count = "count" in aovs
        n = bins.lanes
        zf = dr.zeros(mi.Float, n)
        z64 = dr.zeros(mi.Float64, n)
        state = {
            "j": dr.gather(mi.UInt32, bins.start, tile),
            "T": dr.ones(mi.Float64, n),
            "done": ~inside,
            "chans": {name: [zf] * len(v) for name, v in self.sorted_chans.items()},
        }
        if want_depth:
            state["depth"] = zf
        if want_med:
            state["med"] = zf
            state["med_j"] = dr.full(mi.UInt32, 0xFFFFFFFF, n)
        if want_normal:
            state["normal"] = [zf, zf, zf]
        if want_dist:
            state["m1"], state["m2"], state["dist"] = z64, z64, z64
        if want_count:
            state["count"] = zf
        end = dr.gather(mi.UInt32, bins.end, tile)
        q_names = _PAIR_FIELDS + (_NORMAL_FIELDS if want_normal else ())

        def cond(s):
            return (s["j"] < end) & ~s["done"]

        def body(s):
            j = s["j"]
            q = {k: dr.gather(mi.Float, self.sorted[k], j) for k in q_names}
            alpha, rho, depth = _pair_eval(q, pxf, pyf, config)
            keep = _pair_kept(alpha, rho, depth, config) & _in_box(bins, j, px, py)
            a64 = mi.Float64(alpha)
            t_before = s["T"]
            t_after = t_before * (1.0 - a64)
            stop = keep & (t_after < config.transmittance_min)
            comp = keep & ~stop
            # A dropped pair's depth may be inf (an edge-on plane): 0 * inf would be NaN.
            depth = dr.select(comp, depth, config.near)
            w64 = t_before * a64
            w = dr.select(comp, mi.Float(w64), 0.0)
            out = dict(s)
            out["chans"] = {
                name: [acc + w * dr.gather(mi.Float, self.sorted_chans[name][k], j)
                       for k, acc in enumerate(accs)]
                for name, accs in s["chans"].items()}
            if want_depth:
                out["depth"] = s["depth"] + w * depth
            if want_med:
                sel = comp & (t_before > 0.5)
                out["med"] = dr.select(sel, depth, s["med"])
                out["med_j"] = dr.select(sel, j, s["med_j"])
            if want_normal:
                out["normal"] = [acc + w * q[k]
                                 for acc, k in zip(s["normal"], _NORMAL_FIELDS, strict=True)]
            if want_dist:
                m = _distortion_m(depth, config)
                wm = dr.select(comp, w64 * m, 0.0)
                front = 1.0 - t_before  # sum of the weights in front
                out["dist"] = s["dist"] + dr.select(
                    comp, w64 * (m * m * front + s["m2"] - 2.0 * m * s["m1"]), 0.0)
                out["m1"] = s["m1"] + wm
                out["m2"] = s["m2"] + wm * m
            if want_count:
                out["count"] = s["count"] + dr.select(comp, 1.0, 0.0)
            out["T"] = dr.select(comp, t_after, t_before)
            out["done"] = s["done"] | stop
            out["j"] = dr.select(stop, j, j + 1)  # the stopping pair is not composited
            return (out,)

        (s,) = dr.while_loop((state,), cond, body, label="raster_tiles_forward")
        t_final = s["T"]  # [lanes] Float64
        alpha_img = mi.Float(1.0 - t_final)  # = sum of the weights (telescoping)
        pix = py * ctx.width + px
        lane_out = {}
        for name, accs in s["chans"].items():
            vals = accs
            if name in ctx.background:
                tf = mi.Float(t_final)
                vals = [v + jit.opaque(b) * tf
                        for v, b in zip(accs, ctx.background[name], strict=True)]
            lane_out[name] = vals
        if "alpha" in aovs:
            lane_out["alpha"] = [alpha_img]
        if want_depth:
            ok = alpha_img > 0
            depth_img = dr.select(ok, s["depth"] / dr.select(ok, alpha_img, 1.0), 0.0)
            lane_out["depth"] = [depth_img]
        if want_med:
            lane_out["median_depth"] = [s["med"]]
        if want_normal:
            lane_out["normal"] = s["normal"]
        if want_dist:
            lane_out["distortion"] = [mi.Float(s["dist"])]
        if want_count:
            lane_out["count"] = [s["count"]]
        # What the backward pass needs, per lane: O(pixels).
        self.lanes = (tile, px, py, inside, pix)
        self.t_final, self.stop = t_final, s["j"]
        self.alpha_img = alpha_img
        self.depth_img = lane_out["depth"][0] if want_depth else None
        self.med_j = s["med_j"] if want_med else None
        self.m_sums = (s["m1"], s["m2"]) if want_dist else None
        # Everything the loop yields in one kernel (a later evaluation of any loop output
        # would run the loop again), then the images by a gather from the lanes.
        dr.eval(self.t_final, self.stop, *(v for vals in lane_out.values() for v in vals),
                *([self.med_j] if want_med else []), *(self.m_sums or ()))
        return {name: _to_image(vals, bins, ctx.width, ctx.height)
                for name, vals in lane_out.items()}

    def backward(self):
        _tiled_backward(self)

    def forward(self):
        raise NotImplementedError(
            "rasterize: forward-mode derivatives (dr.forward*) are not implemented for "
            "RasterConfig.method='tiles' (reverse mode is); use method='pairs'")

    def name(self):
        return "rasterize_tiles"


@dataclasses.dataclass
class _TiledCtx:
    """The non-differentiable inputs of ``_TiledOp``."""

    bins: _Bins
    width: int
    height: int
    widths: dict  # channel name -> C
    aovs: tuple
    background: dict  # channel name -> list of C floats
    config: RasterConfig
    field_names: tuple  # keys of the op's ``fields`` input
    nsurfels: int
    # Whether any projected field needs a gradient: without (fixed geometry, stage 2's
    # features) the backward skips the pair maths' derivative and its 13-16 scatters.
    geometry_grad: bool = True


def _pair_eval_grad(q: dict, px, py, g_alpha, g_depth, config: RasterConfig) -> dict:
    """Reverse-mode derivative of ``raster._pair_eval`` by hand: (dL/dalpha, dL/ddepth) of
    pairs -> dL/d of each of the 13 projected fields (``_PAIR_FIELDS``). Follows the same
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


def _grad_entries(surfels: int, normal: bool, channels: int) -> int:
    """Floats of the backward's per-surfel gradient sums: the pair fields, the normal's
    when it is rendered, and every channel."""
    return surfels * (len(_PAIR_FIELDS) + len(_NORMAL_FIELDS) * normal + channels)


def _grad_copy_bytes(entries: int, config: RasterConfig) -> int:
    """Bytes of the per-thread copies of ``entries`` gradient floats under ReduceMode.Expand,
    or 0 where they exceed ``config.expand_grad_bytes`` (then Local: ``_grad_reduce_mode``)."""
    copies = entries * 4 * max(dr.thread_count(), 1)
    return copies if copies <= config.expand_grad_bytes else 0


def _grad_reduce_mode(entries: int, config: RasterConfig) -> dr.ReduceMode:
    """dr.ReduceMode of the backward's per-surfel scatter-adds into ``entries`` floats.

    Expand (LLVM: a private copy of the gradient arrays per thread, non-atomic updates,
    summed at the end) where the copies fit ``config.expand_grad_bytes``; otherwise Local
    (every lane of a packet reads the same sorted entry, so a pre-reduction in the packet
    leaves one atomic per scatter). CUDA treats Expand as Auto."""
    return dr.ReduceMode.Expand if _grad_copy_bytes(entries, config) else dr.ReduceMode.Local


def _tiled_backward(op: _TiledOp) -> None:
    ctx = op.ctx
    bins, config = ctx.bins, ctx.config
    aovs = ctx.aovs
    grads_out = {k: dr.detach(v) for k, v in op.grad_out().items()}
    tile, px, py, inside, pix = op.lanes
    pxf, pyf = mi.Float(px) + 0.5, mi.Float(py) + 0.5
    n = bins.lanes

    def lane_grad(name, c):  # [lanes] per component of an output's gradient image
        g = grads_out.get(name)
        if g is None or dr.width(g) == 0:
            return [dr.zeros(mi.Float, n)] * c
        return [dr.gather(mi.Float, g, pix * c + k, active=inside) for k in range(c)]

    g_chans = {name: lane_grad(name, c) for name, c in ctx.widths.items()}
    # dL/d(sum of weights): alpha, the backgrounds' (1 - alpha) and the depth's division.
    g_wsum = lane_grad("alpha", 1)[0] if "alpha" in aovs else dr.zeros(mi.Float, n)
    for name, bg in ctx.background.items():
        for g, b in zip(g_chans[name], bg, strict=True):
            g_wsum = g_wsum - jit.opaque(b) * g
    alpha_img = op.alpha_img
    ok = alpha_img > 0
    if "depth" in aovs:
        g_dimg = lane_grad("depth", 1)[0]
        g_dacc = dr.select(ok, g_dimg / dr.select(ok, alpha_img, 1.0), 0.0)  # dL/d sum w z
        g_wsum = g_wsum - g_dacc * op.depth_img
    g_med = lane_grad("median_depth", 1)[0] if "median_depth" in aovs else None
    g_normal = lane_grad("normal", 3) if "normal" in aovs else None
    if "distortion" in aovs:
        g_dist = mi.Float64(lane_grad("distortion", 1)[0])
        m1, m2 = op.m_sums
        wsum64 = 1.0 - op.t_final
    q_names = _PAIR_FIELDS + (_NORMAL_FIELDS if g_normal is not None else ())
    nsurf = ctx.nsurfels
    geometry_grad = ctx.geometry_grad
    acc = {k: dr.zeros(mi.Float, nsurf) for k in q_names} if geometry_grad else {}
    acc_chans = {name: dr.zeros(mi.Float, nsurf * c) for name, c in ctx.widths.items()}
    reduce_mode = _grad_reduce_mode(
        _grad_entries(nsurf, g_normal is not None, sum(ctx.widths.values())), config)

    # The lanes of a group (up to _BACKWARD_GROUP consecutive lanes of one tile: a SIMD
    # packet) walk down together from the group's largest stop index, each active below
    # its own: the packet reads one sorted entry per iteration (coherent gathers, one
    # atomic per scatter after the local pre-reduction). Any grouping is correct (a lane
    # composites only entries in [its tile's start, its stop)), but a group across tiles
    # would walk through the other tiles' lists: 25x slower with 2x2 tiles.
    ts2 = bins.size * bins.size
    per_tile = -(-ts2 // _BACKWARD_GROUP)
    lane = dr.arange(mi.UInt32, n)
    slot = lane // ts2
    group = slot * per_tile + (lane - slot * ts2) // _BACKWARD_GROUP
    group_stop = dr.zeros(mi.UInt32, (n // ts2) * per_tile)
    dr.scatter_reduce(dr.ReduceOp.Max, group_stop, op.stop, group, active=inside)
    first = dr.gather(mi.UInt32, bins.start, tile)
    own_stop = op.stop
    state = {"j": dr.select(inside, dr.gather(mi.UInt32, group_stop, group), first),
             # opaque: a literal zero that stays zero (median depth alone: every dL/dw is
             # 0) trips the loop's constant-state check.
             "T": op.t_final, "S": dr.opaque(mi.Float64, 0.0, n)}

    def cond(s):
        return s["j"] > first

    def body(s):
        j = s["j"]
        i = j - 1
        q = {k: dr.gather(mi.Float, op.sorted[k], i)
             for k in (q_names if geometry_grad else _PAIR_FIELDS)}
        alpha, rho, depth = _pair_eval(q, pxf, pyf, config)
        # Every kept pair before the stop index was composited (T only decreases).
        comp = (i < own_stop) & _pair_kept(alpha, rho, depth, config) & _in_box(bins, i, px, py)
        # Pairs that are not composited pass through with alpha 0 and a finite depth.
        depth = dr.select(comp, depth, config.near)
        a64 = mi.Float64(dr.select(comp, alpha, 0.0))
        one_minus = 1.0 - a64
        t_before = s["T"] / one_minus
        w64 = t_before * a64
        w = mi.Float(w64)
        sid = dr.gather(mi.UInt32, bins.sid, i)
        for name, gs in g_chans.items():  # the channels' gradients: w_i dL/d(image)
            c = len(gs)
            for k, gk in enumerate(gs):
                dr.scatter_reduce(dr.ReduceOp.Add, acc_chans[name], w * gk, sid * c + k,
                                  active=comp, mode=reduce_mode)
        out = dict(s)
        out["T"] = dr.select(comp, t_before, s["T"])
        out["j"] = i
        if geometry_grad:
            g64 = geometry_step(i, sid, q, comp, depth, w, w64, t_before, one_minus, s["S"])
            out["S"] = dr.select(comp, s["S"] + w64 * g64, s["S"])
        return (out,)

    def geometry_step(i, sid, q, comp, depth, w, w64, t_before, one_minus, suffix):
        """Scatter pair i's gradients of the projected fields (and the normal's); return
        g64 = dL/dw_i, whose running sum over later pairs is the state's S (``suffix``)."""
        # g: dL/dw of this pair (every output is linear in w but the distortion);
        # g_z: dL/ddepth at fixed w.
        g = g_wsum
        g_z = dr.zeros(mi.Float, n)
        for name, gs in g_chans.items():
            for k, gk in enumerate(gs):
                g = g + gk * dr.gather(mi.Float, op.sorted_chans[name][k], i)
        if "depth" in aovs:
            g = g + g_dacc * depth
            g_z = g_z + w * g_dacc
        if g_normal is not None:
            for k, gk in zip(_NORMAL_FIELDS, g_normal, strict=True):
                g = g + gk * q[k]
                dr.scatter_reduce(dr.ReduceOp.Add, acc[k], w * gk, sid, active=comp,
                                  mode=reduce_mode)
        g64 = mi.Float64(g)
        if g_med is not None:
            g_z = g_z + dr.select(i == op.med_j, g_med, 0.0)
        if "distortion" in aovs:
            # d = W M2 - M1^2 over the pixel's totals (W = sum w, M1 = sum w m, M2 = sum w
            # m^2): dd/dw_i = sum_j w_j (m_i - m_j)^2, dd/dm_i = 2 w_i (W m_i - M1).
            m = _distortion_m(depth, config)
            g64 = g64 + g_dist * (m2 + wsum64 * m * m - 2.0 * m1 * m)
            near, far = config.distortion_near, config.distortion_far
            dm_dz = (far * near / (far - near)) / (mi.Float64(depth) * depth)
            g_z = g_z + mi.Float(g_dist * 2.0 * w64 * (wsum64 * m - m1) * dm_dz)
        # dw_i/dalpha_i = T_i; dw_j/dalpha_i = -w_j / (1 - alpha_i) for every later j.
        g_alpha = mi.Float(t_before * g64 - suffix / one_minus)
        fg = _pair_eval_grad(q, pxf, pyf, g_alpha, g_z, config)
        for k in _PAIR_FIELDS:
            dr.scatter_reduce(dr.ReduceOp.Add, acc[k], fg[k], sid, active=comp,
                              mode=reduce_mode)
        return g64

    dr.while_loop((state,), cond, body, label="raster_tiles_backward")
    dr.eval(*acc.values(), *acc_chans.values())
    if geometry_grad:
        op.set_grad_in("fields", {k: acc[k] for k in ctx.field_names})
    if acc_chans:
        op.set_grad_in("chans", acc_chans)


def render_tiles(g: _Proj, gd: _Proj, W: int, H: int, chans: dict, aovs: Sequence[str],
                 bg: dict, config: RasterConfig, grad: bool) -> dict[str, mi.Float]:
    """Every output of ``rasterize``, flat ([H * W * C] each), by the tiled renderer; ``g``
    the projected surfels with AD, ``gd`` detached."""
    if max(W, H) > _BOX_MAX:
        raise ValueError(f"rasterize (tiles): images up to {_BOX_MAX} pixels a side, got "
                         f"{W} x {H}; use RasterConfig.method='pairs'")
    widths = {name: t.shape[1] for name, t in chans.items()}
    bins = _bin(gd, W, H, config, grad, sum(widths.values())) if dr.width(gd.xc) else None
    npix = W * H
    if bins is None:
        out = {name: dr.zeros(mi.Float, npix * c) for name, c in widths.items()}
        for name, vals in bg.items():
            out[name] = dr.tile(mi.Float(vals), npix)
        for a in aovs:
            out[a] = dr.zeros(mi.Float, npix * AOV_CHANNELS[a])
        return out
    names = _PAIR_FIELDS + (_NORMAL_FIELDS if "normal" in aovs else ())
    fields = {k: getattr(g, k) for k in _PAIR_FIELDS}
    if "normal" in aovs:
        fields |= dict(zip(_NORMAL_FIELDS, (g.normal.x, g.normal.y, g.normal.z), strict=True))
    ctx = _TiledCtx(bins, W, H, widths, tuple(aovs), bg, config, names, dr.width(gd.xc),
                    any(dr.grad_enabled(v) for v in fields.values()))
    return dr.custom(_TiledOp, fields, {name: t.array for name, t in chans.items()}, ctx)


