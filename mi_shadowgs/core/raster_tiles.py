"""Tiled 2DGS rasterizer: memory O(pixels + surfels + surfel-tile pairs), forward and backward.

``RasterConfig(method="tiles")`` selects it in ``raster.rasterize``; the pair-list renderer
(``raster.py``) stays the reference. Both use ``raster_common``'s projection (``project``),
bounds (``boxes``) and per-pair maths (``pair_eval``), so they composite the same pairs in
the same order:

1. binning (detached): each surfel's pixel box covers a rectangle of screen tiles
   (``RasterConfig.tile_size``); surfel-tile pairs come from a prefix sum over the tile
   counts of the surfels in depth order (one host read), a stable ``dr.argsort`` by tile
   orders them by (tile, centre depth), and each tile gets its [start, end) range;
2. forward: one lane per ``RasterConfig.pixels_per_lane`` pixels of a tile, tile-major so
   that a SIMD packet's lanes share few tiles; a symbolic ``dr.while_loop`` walks the
   tile's list front to back, reading each entry once for the lane's pixels. Each pixel
   skips pairs outside the surfel's box or failing the alpha / cutoff / near tests (the
   pair list drops them), composites with a Float64 transmittance and stops before the
   splat that would take T below ``transmittance_min`` (``raster._scan``); the lane stops
   when all of its pixels have;
3. backward (``_TiledOp``, a ``dr.CustomOp``): the forward keeps per pixel only its final
   T, its stop index and a few Float64 sums; the backward walks each list back to front
   from the largest stop index of the lane's group, each pixel active below its own,
   recovering T_i = T_{i+1} / (1 - alpha_i) in Float64, and chains the output gradients
   through alpha and depth to the 13 projected fields by hand (``pair_eval_grad``); the
   lane sums its pixels' gradients and scatter-adds them per surfel. Dr.Jit's AD then
   carries those gradients from the projected fields to the surfel parameters
   (``raster_common.project``).

Why T is recovered by division rather than recomputed front to back: one pass instead of
two (the back-to-front sum of w_j g_j over later pairs needs the output gradients, so a
front-to-back replay would need a first pass for the total), and with alpha <= alpha_max =
0.99 each division adds ~1e-16 relative error and the error grows linearly in the number
of splats: the T recovered at the front of each pixel is 1 to 8.9e-16 after 1753 splats
(test_raster_tiles's 1e5-surfel stack; 2.2e-16 after 10 splats of opacity 0.3-0.95).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import drjit as dr
import mitsuba as mi

from mi_shadowgs.core import jit
from mi_shadowgs.core.raster_common import (
    AOV_CHANNELS,
    PAIR_FIELDS,
    Proj,
    RasterConfig,
    RasterMemoryError,
    boxes,
    budget_text,
    depth_key,
    distortion_m,
    expand,
    memory_budget,
    pair_eval,
    pair_eval_grad,
    pair_kept,
    total_pairs,
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
    per_lane: int = 1  # pixels of a tile that one lane composites (a divisor of size^2)

    @property
    def lanes_per_tile(self) -> int:
        return self.size * self.size // self.per_lane

    @property
    def lanes(self) -> int:
        return self.ntx * self.nty * self.lanes_per_tile


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
    need = (config.reserve_bytes + lanes * (per_lane + 8 * channels) +
            tile_pairs * (config.bytes_per_tile_pair + 4 * channels))
    if grad:
        # The normal's fields counted whether or not it is rendered: an upper bound.
        need += _grad_copy_bytes(_grad_entries(surfels, True, channels), config)
    mem = memory_budget(config, need)
    if mem is not None and mem[1] + need > mem[0]:
        raise RasterMemoryError(
            f"rasterize (tiles): {tile_pairs} surfel-tile pairs and {lanes} pixels need "
            f"~{need / (1 << 30):.2f} GiB, but {budget_text(config, *mem)}; a smaller "
            f"image lowers it")


def _bin(gd: Proj, width: int, height: int, config: RasterConfig, grad: bool,
         channels: int) -> _Bins | None:
    """Surfel-tile pairs of the detached projected surfels ``gd``; None when there are
    none."""
    x0, y0, bw, bh, count = boxes(gd, width, height, config)
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
        total = total_pairs(ntiles)
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
    by_depth = dr.argsort(depth_key(gd.z2))  # [N]
    pos, local = expand(dr.gather(mi.UInt32, ntiles, by_depth), total)  # [TP]
    sid = dr.gather(mi.UInt32, by_depth, pos)
    w = dr.maximum(dr.gather(mi.UInt32, tw, sid), 1)  # max: see raster_common.expand
    ly = local // w
    tile = ((dr.gather(mi.UInt32, ty0, sid) + ly) * ntx + dr.gather(mi.UInt32, tx0, sid) +
            (local - ly * w))
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
    return _Bins(ts, ntx, nty, sid, box, start, end, math.gcd(config.pixels_per_lane, ts * ts))


@dataclasses.dataclass
class _LanePlan:
    """The pixels the compositing lanes hold, and how the backward groups the lanes.

    A whole image (``_image_plan``): tile-major lanes of ``per_lane`` pixels of one tile.
    Sampled pixels (``_sample_plan``): one pixel per lane, lanes ordered by tile."""

    n: int  # lanes
    tile: mi.UInt32  # [n] the tile whose sorted list a lane walks
    pxs: list  # per pixel k of a lane: x [n] (UInt32)
    pys: list  # ... y [n]
    insides: list  # ... inside the image [n] (Bool)
    out_index: list  # ... the pixel's row in the flat output: its pixel or sample index [n]
    # The backward's walking groups (up to _BACKWARD_GROUP lanes of one tile): group [n]
    # in [0, n_groups).
    group: mi.UInt32
    n_groups: int
    samples: int | None = None  # sampled pixels (outputs [samples * C]); None: the image


def _image_plan(bins: _Bins, width: int, height: int) -> _LanePlan:
    """Every pixel: tile-major lanes, each holding ``bins.per_lane`` consecutive pixels of
    its tile, row-major inside the tile."""
    per_tile = bins.lanes_per_tile
    lane = dr.arange(mi.UInt32, bins.lanes)
    tile = lane // per_tile
    sub = lane - tile * per_tile
    ty = tile // bins.ntx
    tx = tile - ty * bins.ntx
    pxs, pys, insides, pixs = [], [], [], []
    for k in range(bins.per_lane):
        local = sub * bins.per_lane + k
        ly = local // bins.size
        px = tx * bins.size + (local - ly * bins.size)
        py = ty * bins.size + ly
        pxs.append(px)
        pys.append(py)
        insides.append((px < width) & (py < height))
        pixs.append(py * width + px)
    groups_per_tile = -(-per_tile // _BACKWARD_GROUP)
    group = tile * groups_per_tile + sub // _BACKWARD_GROUP
    return _LanePlan(bins.lanes, tile, pxs, pys, insides, pixs, group,
                     bins.ntx * bins.nty * groups_per_tile)


def _sample_plan(bins: _Bins, width: int, pixels: mi.UInt32) -> _LanePlan:
    """One lane per entry of ``pixels`` [P] (flat indices y * width + x inside the image,
    repeats allowed), the lanes ordered by tile (stable) so that a SIMD packet walks few
    lists; a group is a run of up to _BACKWARD_GROUP lanes of one tile."""
    n = dr.width(pixels)
    py0 = pixels // width
    px0 = pixels - py0 * width
    tile0 = (py0 // bins.size) * bins.ntx + px0 // bins.size
    order = dr.argsort(tile0)  # [n] the sample held by each lane
    tile = dr.gather(mi.UInt32, tile0, order)
    lane = dr.arange(mi.UInt32, n)
    prev = dr.gather(mi.UInt32, tile, dr.maximum(lane, 1) - 1)
    run_start = dr.prefix_reduce(dr.ReduceOp.Max, dr.select((lane == 0) | (prev != tile),
                                                             lane, 0), exclusive=False)
    group = run_start + (lane - run_start) // _BACKWARD_GROUP * _BACKWARD_GROUP
    px, py = dr.gather(mi.UInt32, px0, order), dr.gather(mi.UInt32, py0, order)
    dr.eval(tile, px, py, order, group)
    return _LanePlan(n, tile, [px], [py], [dr.full(mi.Bool, True, n)], [order], group, n,
                     samples=n)


def _to_image(vals: list, bins: _Bins, width: int, height: int) -> mi.Float:
    """Lane values (per pixel k of a lane: C arrays [lanes]) -> a flat image [H * W * C],
    gathered from each pixel's lane."""
    c = len(vals[0])
    idx = dr.arange(mi.UInt32, width * height * c)
    pix = idx // c
    ch = idx - pix * c
    py = pix // width
    px = pix - py * width
    ty, tx = py // bins.size, px // bins.size
    local = (py - ty * bins.size) * bins.size + (px - tx * bins.size)
    sub = local // bins.per_lane
    k = local - sub * bins.per_lane
    lane = (ty * bins.ntx + tx) * bins.lanes_per_tile + sub
    out = dr.gather(mi.Float, vals[0][0], lane)
    for kk, vk in enumerate(vals):
        for cc, v in enumerate(vk):
            if kk or cc:
                out = dr.select((k == kk) & (ch == cc), dr.gather(mi.Float, v, lane), out)
    return out


def _to_samples(vals: list, plan: _LanePlan) -> mi.Float:
    """Lane values (one pixel per lane: C arrays [lanes]) -> [samples * C] in the order of
    the sampled pixels."""
    c = len(vals[0])
    out = dr.zeros(mi.Float, plan.samples * c)
    for cc, v in enumerate(vals[0]):
        dr.scatter(out, v, plan.out_index[0] * c + cc)
    return out


def _all_done(pixels: list) -> mi.Bool:
    out = pixels[0]["done"]
    for p in pixels[1:]:
        out = out & p["done"]
    return out


def _sum(values: list):
    out = values[0]
    for v in values[1:]:
        out = out + v
    return out


def _maximum(values: list):
    out = values[0]
    for v in values[1:]:
        out = dr.maximum(out, v)
    return out


def _box_of(bins: _Bins, j: mi.UInt32) -> tuple:
    """Sorted pair j's surfel pixel box, packed (x0 | x1 << 16, y0 | y1 << 16): read once
    per lane and tested for each of its pixels (``_in_box``)."""
    return dr.gather(mi.UInt32, bins.box[0], j), dr.gather(mi.UInt32, bins.box[1], j)


def _in_box(box: tuple, px: mi.UInt32, py: mi.UInt32) -> mi.Bool:
    """Whether pixel (px, py) lies in a pair's box (the pair list holds exactly the box's
    pixels)."""
    bx, by = box
    return ((px >= (bx & 0xFFFF)) & (px <= (bx >> 16)) & (py >= (by & 0xFFFF)) &
            (py <= (by >> 16)))


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
        plan = (_image_plan(bins, ctx.width, ctx.height) if ctx.pixels is None else
                _sample_plan(bins, ctx.width, ctx.pixels))
        tile, pxs, pys, insides = plan.tile, plan.pxs, plan.pys, plan.insides
        pxf = [mi.Float(px) + 0.5 for px in pxs]
        pyf = [mi.Float(py) + 0.5 for py in pys]
        aovs = ctx.aovs
        want_depth = "depth" in aovs
        want_med = "median_depth" in aovs
        want_normal = "normal" in aovs
        want_dist = "distortion" in aovs
        want_count = "count" in aovs
        n = plan.n
        zf = dr.zeros(mi.Float, n)
        z64 = dr.zeros(mi.Float64, n)
        first = dr.gather(mi.UInt32, bins.start, tile)
        end = dr.gather(mi.UInt32, bins.end, tile)
        pixels = []  # the compositing state of each pixel of a lane
        for inside in insides:
            p = {"T": dr.ones(mi.Float64, n), "done": ~inside,
                 # Where the pixel stopped (the first pair not composited), else its end.
                 "stop": dr.select(inside, end, first),
                 "chans": {name: [zf] * len(v) for name, v in self.sorted_chans.items()}}
            if want_depth:
                p["depth"] = zf
            if want_med:
                p["med"] = zf
                p["med_j"] = dr.full(mi.UInt32, 0xFFFFFFFF, n)
            if want_normal:
                p["normal"] = [zf, zf, zf]
            if want_dist:
                p["m1"], p["m2"], p["dist"] = z64, z64, z64
            if want_count:
                p["count"] = zf
            pixels.append(p)
        state = {"j": first, "pixels": pixels}
        q_names = PAIR_FIELDS + (_NORMAL_FIELDS if want_normal else ())

        def cond(s):
            return (s["j"] < end) & ~_all_done(s["pixels"])

        def body(s):
            j = s["j"]
            # One read of the entry per lane, shared by its pixels.
            q = {k: dr.gather(mi.Float, self.sorted[k], j) for k in q_names}
            box = _box_of(bins, j)
            chan_vals = {name: [dr.gather(mi.Float, arr, j) for arr in arrs]
                         for name, arrs in self.sorted_chans.items()}
            out_pixels = []
            for k, p in enumerate(s["pixels"]):
                alpha, rho, depth = pair_eval(q, pxf[k], pyf[k], config)
                keep = (~p["done"] & pair_kept(alpha, rho, depth, config) &
                        _in_box(box, pxs[k], pys[k]))
                a64 = mi.Float64(alpha)
                t_before = p["T"]
                t_after = t_before * (1.0 - a64)
                stop = keep & (t_after < config.transmittance_min)
                comp = keep & ~stop
                # A dropped pair's depth may be inf (an edge-on plane): 0 * inf is NaN.
                depth = dr.select(comp, depth, config.near)
                w64 = t_before * a64
                w = dr.select(comp, mi.Float(w64), 0.0)
                o = dict(p)
                o["chans"] = {name: [acc + w * v for acc, v in zip(accs, chan_vals[name],
                                                                   strict=True)]
                              for name, accs in p["chans"].items()}
                if want_depth:
                    o["depth"] = p["depth"] + w * depth
                if want_med:
                    sel = comp & (t_before > 0.5)
                    o["med"] = dr.select(sel, depth, p["med"])
                    o["med_j"] = dr.select(sel, j, p["med_j"])
                if want_normal:
                    o["normal"] = [acc + w * q[f]
                                   for acc, f in zip(p["normal"], _NORMAL_FIELDS, strict=True)]
                if want_dist:
                    m = distortion_m(depth, config)
                    wm = dr.select(comp, w64 * m, 0.0)
                    front = 1.0 - t_before  # sum of the weights in front
                    o["dist"] = p["dist"] + dr.select(
                        comp, w64 * (m * m * front + p["m2"] - 2.0 * m * p["m1"]), 0.0)
                    o["m1"] = p["m1"] + wm
                    o["m2"] = p["m2"] + wm * m
                if want_count:
                    o["count"] = p["count"] + dr.select(comp, 1.0, 0.0)
                o["T"] = dr.select(comp, t_after, t_before)
                o["done"] = p["done"] | stop
                o["stop"] = dr.select(stop, j, p["stop"])  # the stopping pair: not composited
                out_pixels.append(o)
            return ({"j": j + 1, "pixels": out_pixels},)

        (s,) = dr.while_loop((state,), cond, body, label="raster_tiles_forward")
        pixels = s["pixels"]
        t_final = [p["T"] for p in pixels]  # [lanes] Float64 per pixel of a lane
        alpha_img = [mi.Float(1.0 - t) for t in t_final]  # = sum of the weights
        lane_out = {}  # name -> per pixel k: C arrays [lanes]
        for name in self.sorted_chans:
            vals = [p["chans"][name] for p in pixels]
            if name in ctx.background:
                vals = [[v + jit.opaque(b) * mi.Float(t)
                         for v, b in zip(vk, ctx.background[name], strict=True)]
                        for vk, t in zip(vals, t_final, strict=True)]
            lane_out[name] = vals
        if "alpha" in aovs:
            lane_out["alpha"] = [[a] for a in alpha_img]
        depth_img = None
        if want_depth:
            depth_img = [dr.select(a > 0, p["depth"] / dr.select(a > 0, a, 1.0), 0.0)
                         for p, a in zip(pixels, alpha_img, strict=True)]
            lane_out["depth"] = [[d] for d in depth_img]
        if want_med:
            lane_out["median_depth"] = [[p["med"]] for p in pixels]
        if want_normal:
            lane_out["normal"] = [p["normal"] for p in pixels]
        if want_dist:
            lane_out["distortion"] = [[mi.Float(p["dist"])] for p in pixels]
        if want_count:
            lane_out["count"] = [[p["count"]] for p in pixels]
        # What the backward pass needs, per pixel: O(pixels).
        self.plan = plan
        self.t_final, self.stop = t_final, [p["stop"] for p in pixels]
        self.alpha_img = alpha_img
        self.depth_img = depth_img
        self.med_j = [p["med_j"] for p in pixels] if want_med else None
        self.m_sums = [(p["m1"], p["m2"]) for p in pixels] if want_dist else None
        # Everything the loop yields in one kernel (a later evaluation of any loop output
        # would run the loop again), then the images by a scatter from the lanes.
        dr.eval(self.t_final, self.stop, lane_out, self.med_j, self.m_sums)
        if plan.samples is not None:
            return {name: _to_samples(vals, plan) for name, vals in lane_out.items()}
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
    pixels: mi.UInt32 | None = None  # [P] only these pixels (``_sample_plan``); None: all


def _grad_entries(surfels: int, normal: bool, channels: int) -> int:
    """Floats of the backward's per-surfel gradient sums: the pair fields, the normal's
    when it is rendered, and every channel."""
    return surfels * (len(PAIR_FIELDS) + len(_NORMAL_FIELDS) * normal + channels)


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
    plan = op.plan
    tile, pxs, pys, insides = plan.tile, plan.pxs, plan.pys, plan.insides
    pxf = [mi.Float(px) + 0.5 for px in pxs]
    pyf = [mi.Float(py) + 0.5 for py in pys]
    n = plan.n

    def lane_grad(name, c, k):  # [lanes] per component of an output's gradient at pixel k
        g = grads_out.get(name)
        if g is None or dr.width(g) == 0:
            return [dr.zeros(mi.Float, n)] * c
        return [dr.gather(mi.Float, g, plan.out_index[k] * c + ch, active=insides[k])
                for ch in range(c)]

    # What each pixel k of a lane needs from the output gradients: pixel[k][...].
    pixel = []
    for k in range(len(pxs)):
        pk = {"chans": {name: lane_grad(name, c, k) for name, c in ctx.widths.items()}}
        # dL/d(sum of weights): alpha, the backgrounds' (1 - alpha), the depth's division.
        g_wsum = lane_grad("alpha", 1, k)[0] if "alpha" in aovs else dr.zeros(mi.Float, n)
        for name, bg in ctx.background.items():
            for g, b in zip(pk["chans"][name], bg, strict=True):
                g_wsum = g_wsum - jit.opaque(b) * g
        alpha_img = op.alpha_img[k]
        ok = alpha_img > 0
        if "depth" in aovs:
            g_dimg = lane_grad("depth", 1, k)[0]
            pk["g_dacc"] = dr.select(ok, g_dimg / dr.select(ok, alpha_img, 1.0), 0.0)
            g_wsum = g_wsum - pk["g_dacc"] * op.depth_img[k]
        pk["g_wsum"] = g_wsum
        pk["g_med"] = lane_grad("median_depth", 1, k)[0] if "median_depth" in aovs else None
        pk["g_normal"] = lane_grad("normal", 3, k) if "normal" in aovs else None
        if "distortion" in aovs:
            pk["g_dist"] = mi.Float64(lane_grad("distortion", 1, k)[0])
            pk["m1"], pk["m2"] = op.m_sums[k]
            pk["wsum64"] = 1.0 - op.t_final[k]
        pixel.append(pk)
    normal = "normal" in aovs
    q_names = PAIR_FIELDS + (_NORMAL_FIELDS if normal else ())
    nsurf = ctx.nsurfels
    geometry_grad = ctx.geometry_grad
    acc = {k: dr.zeros(mi.Float, nsurf) for k in q_names} if geometry_grad else {}
    acc_chans = {name: dr.zeros(mi.Float, nsurf * c) for name, c in ctx.widths.items()}
    reduce_mode = _grad_reduce_mode(
        _grad_entries(nsurf, normal, sum(ctx.widths.values())), config)

    # The lanes of a group (up to _BACKWARD_GROUP consecutive lanes of one tile: a SIMD
    # packet) walk down together from the group's largest stop index, each pixel active
    # below its own: the packet reads one sorted entry per iteration (coherent gathers).
    # Any grouping is correct (a pixel composites only entries in [its tile's start, its
    # stop)), but a group across tiles would walk through the other tiles' lists: 25x
    # slower with 2x2 tiles.
    first = dr.gather(mi.UInt32, bins.start, tile)
    own_stop = op.stop
    lane_stop = _maximum([dr.select(ins, st, first)
                          for ins, st in zip(insides, own_stop, strict=True)])
    group_stop = dr.zeros(mi.UInt32, plan.n_groups)
    dr.scatter_reduce(dr.ReduceOp.Max, group_stop, lane_stop, plan.group)
    state = {"j": dr.gather(mi.UInt32, group_stop, plan.group),
             "T": list(op.t_final),
             # opaque: a literal zero that stays zero (median depth alone: every dL/dw is
             # 0) trips the loop's constant-state check.
             "S": [dr.opaque(mi.Float64, 0.0, n) for _ in pixel]}

    def cond(s):
        return s["j"] > first

    def body(s):
        j = s["j"]
        i = j - 1
        # One read of the entry per lane, shared by its pixels.
        q = {k: dr.gather(mi.Float, op.sorted[k], i)
             for k in (q_names if geometry_grad else PAIR_FIELDS)}
        box = _box_of(bins, i)
        sid = dr.gather(mi.UInt32, bins.sid, i)
        chan_vals = {name: [dr.gather(mi.Float, arr, i) for arr in arrs]
                     for name, arrs in op.sorted_chans.items()} if geometry_grad else {}
        comps, ws, t_out, s_out, g_fields = [], [], [], [], []
        for k, pk in enumerate(pixel):
            alpha, rho, depth = pair_eval(q, pxf[k], pyf[k], config)
            # Every kept pair before the stop index was composited (T only decreases).
            comp = ((i < own_stop[k]) & insides[k] & pair_kept(alpha, rho, depth, config) &
                    _in_box(box, pxs[k], pys[k]))
            # Pairs that are not composited pass through with alpha 0 and a finite depth.
            depth = dr.select(comp, depth, config.near)
            a64 = mi.Float64(dr.select(comp, alpha, 0.0))
            one_minus = 1.0 - a64
            t_before = s["T"][k] / one_minus
            w64 = t_before * a64
            w = mi.Float(w64)
            comps.append(comp)
            ws.append(w)
            t_out.append(dr.select(comp, t_before, s["T"][k]))
            if geometry_grad:
                g64, fg = geometry_grad_of(k, pk, i, q, chan_vals, pxf[k], pyf[k], depth, w,
                                           w64, t_before, one_minus, s["S"][k])
                s_out.append(dr.select(comp, s["S"][k] + w64 * g64, s["S"][k]))
                g_fields.append({f: dr.select(comp, v, 0.0) for f, v in fg.items()})
            else:
                s_out.append(s["S"][k])
        any_comp = comps[0]
        for c in comps[1:]:
            any_comp = any_comp | c
        # The pixels' sums, then one scatter per field (w is 0 where a pixel did not
        # composite the pair).
        for name, c in ctx.widths.items():  # the channels' gradients: w_i dL/d(image)
            for ch in range(c):
                v = _sum([w * pk["chans"][name][ch] for w, pk in zip(ws, pixel, strict=True)])
                dr.scatter_reduce(dr.ReduceOp.Add, acc_chans[name], v, sid * c + ch,
                                  active=any_comp, mode=reduce_mode)
        if geometry_grad:
            for f in g_fields[0]:
                dr.scatter_reduce(dr.ReduceOp.Add, acc[f], _sum([g[f] for g in g_fields]),
                                  sid, active=any_comp, mode=reduce_mode)
        return ({"j": i, "T": t_out, "S": s_out},)

    def geometry_grad_of(k, pk, i, q, chan_vals, px, py, depth, w, w64, t_before, one_minus,
                         suffix):
        """Pixel k's (g64, gradients of the projected fields, the normal's too) for pair
        i: g64 = dL/dw_i, whose running sum over later pairs is the state's S
        (``suffix``)."""
        # g: dL/dw of this pair (every output is linear in w but the distortion);
        # g_z: dL/ddepth at fixed w.
        g = pk["g_wsum"]
        g_z = dr.zeros(mi.Float, n)
        for name, gs in pk["chans"].items():
            for gk, v in zip(gs, chan_vals[name], strict=True):
                g = g + gk * v
        if "depth" in aovs:
            g = g + pk["g_dacc"] * depth
            g_z = g_z + w * pk["g_dacc"]
        grads = {}
        if pk["g_normal"] is not None:
            for f, gk in zip(_NORMAL_FIELDS, pk["g_normal"], strict=True):
                g = g + gk * q[f]
                grads[f] = w * gk
        g64 = mi.Float64(g)
        if pk["g_med"] is not None:
            g_z = g_z + dr.select(i == op.med_j[k], pk["g_med"], 0.0)
        if "distortion" in aovs:
            # d = W M2 - M1^2 over the pixel's totals (W = sum w, M1 = sum w m, M2 = sum w
            # m^2): dd/dw_i = sum_j w_j (m_i - m_j)^2, dd/dm_i = 2 w_i (W m_i - M1).
            m = distortion_m(depth, config)
            m1, m2, wsum64 = pk["m1"], pk["m2"], pk["wsum64"]
            g64 = g64 + pk["g_dist"] * (m2 + wsum64 * m * m - 2.0 * m1 * m)
            near, far = config.distortion_near, config.distortion_far
            dm_dz = (far * near / (far - near)) / (mi.Float64(depth) * depth)
            g_z = g_z + mi.Float(pk["g_dist"] * 2.0 * w64 * (wsum64 * m - m1) * dm_dz)
        # dw_i/dalpha_i = T_i; dw_j/dalpha_i = -w_j / (1 - alpha_i) for every later j.
        g_alpha = mi.Float(t_before * g64 - suffix / one_minus)
        grads.update(pair_eval_grad(q, px, py, g_alpha, g_z, config))
        return g64, grads

    dr.while_loop((state,), cond, body, label="raster_tiles_backward")
    dr.eval(*acc.values(), *acc_chans.values())
    if geometry_grad:
        op.set_grad_in("fields", {k: acc[k] for k in ctx.field_names})
    if acc_chans:
        op.set_grad_in("chans", acc_chans)


def render_tiles(g: Proj, gd: Proj, W: int, H: int, chans: dict, aovs: Sequence[str],
                 bg: dict, config: RasterConfig, grad: bool,
                 pixels: mi.UInt32 | None = None) -> dict[str, mi.Float]:
    """Every output of ``rasterize``, flat ([H * W * C] each), by the tiled renderer; ``g``
    the projected surfels with AD, ``gd`` detached. With ``pixels`` [P] (flat indices
    inside the image) only those pixels: outputs [P * C], each pixel composited exactly as
    in the whole image (the same operations in the same order)."""
    if max(W, H) > _BOX_MAX:
        raise ValueError(f"rasterize (tiles): images up to {_BOX_MAX} pixels a side, got "
                         f"{W} x {H}; use RasterConfig.method='pairs'")
    widths = {name: t.shape[1] for name, t in chans.items()}
    bins = _bin(gd, W, H, config, grad, sum(widths.values())) if dr.width(gd.xc) else None
    npix = W * H if pixels is None else dr.width(pixels)
    if bins is None:
        out = {name: dr.zeros(mi.Float, npix * c) for name, c in widths.items()}
        for name, vals in bg.items():
            out[name] = dr.tile(mi.Float(vals), npix)
        for a in aovs:
            out[a] = dr.zeros(mi.Float, npix * AOV_CHANNELS[a])
        return out
    names = PAIR_FIELDS + (_NORMAL_FIELDS if "normal" in aovs else ())
    fields = {k: getattr(g, k) for k in PAIR_FIELDS}
    if "normal" in aovs:
        fields |= dict(zip(_NORMAL_FIELDS, (g.normal.x, g.normal.y, g.normal.z), strict=True))
    ctx = _TiledCtx(bins, W, H, widths, tuple(aovs), bg, config, names, dr.width(gd.xc),
                    any(dr.grad_enabled(v) for v in fields.values()), pixels)
    return dr.custom(_TiledOp, fields, {name: t.array for name, t in chans.items()}, ctx)


