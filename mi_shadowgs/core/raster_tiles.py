"""Tiled 2DGS rasterizer: memory O(pixels + surfels + surfel-tile pairs), forward and backward.

``RasterConfig(method="tiles")`` selects it in ``raster.rasterize``; the pair-list renderer
(``raster.py``) stays the reference. Both use ``raster_common``'s projection (``project``),
bounds (``boxes``) and per-pair maths (``pair_eval``), so they composite the same pairs in
the same order:

1. binning (detached, ``raster_bins``): each surfel's pixel box covers a rectangle of screen tiles
   (``RasterConfig.tile_size``); surfel-tile pairs come from a prefix sum over the tile
   counts of the surfels in depth order (one host read), a stable sort by tile
   (``argsort_bounded``) orders them by (tile, centre depth), and each tile gets its
   [start, end) range;
2. forward: one lane per ``RasterConfig.pixels_per_lane`` pixels of a tile, tile-major so
   that a SIMD packet's lanes share few tiles; a symbolic ``dr.while_loop`` walks the
   tile's list front to back, reading each entry once for the lane's pixels (its surfel's
   values packed surfel by surfel, ``_Entries``: one packet gather instead of ~20). Each pixel
   skips pairs outside the surfel's box or failing the alpha / cutoff / near tests (the
   pair list drops them), composites with a Float64 transmittance and stops before the
   splat that would take T below ``transmittance_min`` (``raster._scan``); the lane stops
   when all of its pixels have;
3. backward (``_TiledOp``, a ``dr.CustomOp``): the forward keeps per pixel only its final
   T, its stop index and a few Float64 sums; the backward walks each list back to front
   from the largest stop index of the lane's group, each pixel active below its own,
   recovering T_i = T_{i+1} / (1 - alpha_i) in Float64, and chains the output gradients
   through alpha and depth to the 13 projected fields by hand (``pair_eval_grad``); the
   lane sums its pixels' gradients and scatter-adds them per surfel (packed the same way:
   one packet scatter-add). Dr.Jit's AD then carries those gradients from the projected
   fields to the surfel parameters (``raster_common.project``).

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
from mi_shadowgs.core.packed import Packed
from mi_shadowgs.core.raster_bins import (
    BOX_MAX,
    NORMAL_FIELDS,
    Bins,
    LanePlan,
    bin_surfels,
    grad_copy_bytes,
    grad_entries,
    image_plan,
    in_box,
    sample_plan,
    to_image,
    to_samples,
)
from mi_shadowgs.core.raster_common import (
    AOV_CHANNELS,
    PAIR_FIELDS,
    Proj,
    RasterConfig,
    distortion_m,
    pair_eval,
    pair_eval_grad,
    pair_kept,
)


def _all_done(pixels: list) -> mi.Bool:
    """Whether every pixel of a lane has stopped (the forward state's ``done``)."""
    out = pixels[0]["done"]
    for p in pixels[1:]:
        out = out & p["done"]
    return out


def _sum(values: list):
    """values[0] + values[1] + ..., left to right."""
    out = values[0]
    for v in values[1:]:
        out = out + v
    return out


def _maximum(values: list):
    """The element-wise maximum of ``values``, left to right."""
    out = values[0]
    for v in values[1:]:
        out = dr.maximum(out, v)
    return out


@dataclasses.dataclass
class _Entries:
    """Everything the compositing loops read of a surfel, packed entry by entry
    (``core.packed``): the projected fields, the pixel box and the channel values. A sorted
    pair names its surfel's entry (``Bins.rank``); the SIMD packet's lanes share one or two
    entries: one packet gather reads an entry's ~20 values, where one gather per value
    loaded each address 16 times over. Packed per surfel rather than per pair (a surfel has
    several pairs), in ``Bins.entries``' order (first tile, then depth), so that the entries
    of a tile's list lie close together."""

    packed: Packed  # [N] entries, in ``Bins.entries``' order
    rank: mi.UInt32  # [TP] each sorted pair's entry
    names: tuple  # the projected fields, in order
    chans: dict  # channel name -> (offset, C) in the packed values

    @staticmethod
    def pack(fields: dict, chans: dict, widths: dict, bins: Bins) -> _Entries:
        """The surfels' values in ``bins.entries``' order, evaluated: ``fields`` and
        ``chans`` per surfel."""
        values = list(fields.values()) + [dr.reinterpret_array(mi.Float, b) for b in bins.box]
        offsets = {}
        surfel = dr.arange(mi.UInt32, dr.width(bins.entries))
        for name, arr in chans.items():
            c = widths[name]
            offsets[name] = (len(values), c)
            values += [dr.gather(mi.Float, arr, surfel * c + k) for k in range(c)]
        # Packed in surfel order, then permuted: a packet gather per entry.
        packed = Packed.of(values).permuted(bins.entries)
        return _Entries(packed, bins.rank, tuple(fields), offsets)

    def entry(self, j: mi.UInt32, active: mi.Bool) -> mi.UInt32:
        """The entry of sorted pair j (its surfel's place in ``Bins.entries``); 0 where not
        ``active``. A loop reads the next pair's entry one iteration ahead, so that reading
        an entry's values does not wait on it."""
        return dr.gather(mi.UInt32, self.rank, j, active=active)

    def read(self, rank: mi.UInt32, n: int) -> tuple:
        """(fields by name, pixel box, channel values by name) of entry ``rank`` for each
        of ``n`` lanes."""
        v = self.packed.read(rank, n)
        nf = len(self.names)
        box = tuple(dr.reinterpret_array(mi.UInt32, v[nf + k]) for k in range(2))
        chan_vals = {name: v[o:o + c] for name, (o, c) in self.chans.items()}
        return dict(zip(self.names, v[:nf], strict=True)), box, chan_vals


class _TiledOp(dr.CustomOp):
    """Forward: every requested image (flat, [H * W * C]); backward: gradients of the
    projected fields and the channel values (``_TiledCtx`` holds the non-differentiable
    set-up)."""

    def eval(self, fields: dict, chans: dict, ctx: _TiledCtx):
        """The forward: the sorted fields, the lanes' pixels, the compositing walk, and
        what the backward keeps per pixel; the outputs by name."""
        self.ctx = ctx
        bins = ctx.bins
        # The fields in sorted order, packed entry by entry: the loops read them sequentially.
        self.entries = _Entries.pack(fields, chans, ctx.widths, bins)
        plan = (image_plan(bins, ctx.width, ctx.height) if ctx.pixels is None else
                sample_plan(bins, ctx.width, ctx.pixels))
        pixels = self._composite(plan)
        lane_out, t_final, alpha_img, depth_img = self._lane_outputs(pixels)
        # What the backward pass needs, per pixel: O(pixels).
        self.plan = plan
        self.t_final, self.stop = t_final, [p["stop"] for p in pixels]
        self.alpha_img = alpha_img
        self.depth_img = depth_img
        self.med_j = [p["med_j"] for p in pixels] if "median_depth" in ctx.aovs else None
        self.m_sums = [(p["m1"], p["m2"]) for p in pixels] if "distortion" in ctx.aovs else None
        # Everything the loop yields in one kernel (a later evaluation of any loop output
        # would run the loop again), then the images by a scatter from the lanes.
        dr.eval(self.t_final, self.stop, lane_out, self.med_j, self.m_sums)
        if plan.samples is not None:
            return {name: to_samples(vals, plan) for name, vals in lane_out.items()}
        return {name: to_image(vals, plan, ctx.width, ctx.height)
                for name, vals in lane_out.items()}

    def _start_pixel(self, inside: mi.Bool, first: mi.UInt32, end: mi.UInt32,
                     zf: mi.Float, z64: mi.Float64, n: int) -> dict:
        """The compositing state of one pixel of each lane before its tile's first pair."""
        aovs = self.ctx.aovs
        p = {"T": dr.ones(mi.Float64, n), "done": ~inside,
             # Where the pixel stopped (the first pair not composited), else its end.
             "stop": dr.select(inside, end, first),
             "chans": {name: [zf] * c for name, c in self.ctx.widths.items()}}
        if "depth" in aovs:
            p["depth"] = zf
        if "median_depth" in aovs:
            p["med"] = zf
            p["med_j"] = dr.full(mi.UInt32, 0xFFFFFFFF, n)
        if "normal" in aovs:
            p["normal"] = [zf, zf, zf]
        if "distortion" in aovs:
            p["m1"], p["m2"], p["dist"] = z64, z64, z64
        if "count" in aovs:
            p["count"] = zf
        return p

    def _composite(self, plan: LanePlan) -> list:
        """The forward walk: each lane reads its tile's sorted pairs front to back until
        all of its pixels have stopped; the final state of each pixel of a lane."""
        bins, config = self.ctx.bins, self.ctx.config
        tile, pxs, pys, insides = plan.tile, plan.pxs, plan.pys, plan.insides
        pxf = [mi.Float(px) + 0.5 for px in pxs]
        pyf = [mi.Float(py) + 0.5 for py in pys]
        n = plan.n
        zf = dr.zeros(mi.Float, n)
        z64 = dr.zeros(mi.Float64, n)
        first = dr.gather(mi.UInt32, bins.start, tile)
        end = dr.gather(mi.UInt32, bins.end, tile)
        pixels = [self._start_pixel(inside, first, end, zf, z64, n) for inside in insides]
        entries = self.entries
        state = {"j": first, "r": entries.entry(first, first < end), "pixels": pixels}

        def cond(s):
            return (s["j"] < end) & ~_all_done(s["pixels"])

        def body(s):
            j = s["j"]
            # One read of the entry per lane, shared by its pixels.
            q, box, chan_vals = entries.read(s["r"], n)
            out_pixels = [self._composite_pixel(p, j, q, box, chan_vals, pxs[k], pys[k],
                                                pxf[k], pyf[k], config)
                          for k, p in enumerate(s["pixels"])]
            return ({"j": j + 1, "r": entries.entry(j + 1, j + 1 < end),
                     "pixels": out_pixels},)

        (s,) = dr.while_loop((state,), cond, body, label="raster_tiles_forward")
        return s["pixels"]

    def _composite_pixel(self, p: dict, j: mi.UInt32, q: dict, box: tuple, chan_vals: dict,
                         px: mi.UInt32, py: mi.UInt32, pxf: mi.Float, pyf: mi.Float,
                         config: RasterConfig) -> dict:
        """One pixel's state ``p`` after sorted pair ``j`` (fields ``q``, pixel box
        ``box``, channel values ``chan_vals``): composited, skipped, or the pixel's stop."""
        aovs = self.ctx.aovs
        alpha, rho, depth = pair_eval(q, pxf, pyf, config)
        keep = (~p["done"] & pair_kept(alpha, rho, depth, config) & in_box(box, px, py))
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
        o["chans"] = {name: [acc + w * v for acc, v in zip(accs, chan_vals[name], strict=True)]
                      for name, accs in p["chans"].items()}
        if "depth" in aovs:
            o["depth"] = p["depth"] + w * depth
        if "median_depth" in aovs:
            sel = comp & (t_before > 0.5)
            o["med"] = dr.select(sel, depth, p["med"])
            o["med_j"] = dr.select(sel, j, p["med_j"])
        if "normal" in aovs:
            o["normal"] = [acc + w * q[f]
                           for acc, f in zip(p["normal"], NORMAL_FIELDS, strict=True)]
        if "distortion" in aovs:
            m = distortion_m(depth, config)
            wm = dr.select(comp, w64 * m, 0.0)
            front = 1.0 - t_before  # sum of the weights in front
            o["dist"] = p["dist"] + dr.select(
                comp, w64 * (m * m * front + p["m2"] - 2.0 * m * p["m1"]), 0.0)
            o["m1"] = p["m1"] + wm
            o["m2"] = p["m2"] + wm * m
        if "count" in aovs:
            o["count"] = p["count"] + dr.select(comp, 1.0, 0.0)
        o["T"] = dr.select(comp, t_after, t_before)
        o["done"] = p["done"] | stop
        o["stop"] = dr.select(stop, j, p["stop"])  # the stopping pair: not composited
        return o

    def _lane_outputs(self, pixels: list) -> tuple:
        """(every output per pixel of a lane: name -> per pixel k C arrays [lanes], and the
        pixels' final T (Float64), sums of the weights and depths, which the backward
        reads) from the final compositing states ``pixels``."""
        ctx = self.ctx
        aovs = ctx.aovs
        t_final = [p["T"] for p in pixels]  # [lanes] Float64 per pixel of a lane
        alpha_img = [mi.Float(1.0 - t) for t in t_final]  # = sum of the weights
        lane_out = {}  # name -> per pixel k: C arrays [lanes]
        for name in ctx.widths:
            vals = [p["chans"][name] for p in pixels]
            if name in ctx.background:
                vals = [[v + jit.opaque(b) * mi.Float(t)
                         for v, b in zip(vk, ctx.background[name], strict=True)]
                        for vk, t in zip(vals, t_final, strict=True)]
            lane_out[name] = vals
        if "alpha" in aovs:
            lane_out["alpha"] = [[a] for a in alpha_img]
        depth_img = None
        if "depth" in aovs:
            depth_img = [dr.select(a > 0, p["depth"] / dr.select(a > 0, a, 1.0), 0.0)
                         for p, a in zip(pixels, alpha_img, strict=True)]
            lane_out["depth"] = [[d] for d in depth_img]
        if "median_depth" in aovs:
            lane_out["median_depth"] = [[p["med"]] for p in pixels]
        if "normal" in aovs:
            lane_out["normal"] = [p["normal"] for p in pixels]
        if "distortion" in aovs:
            lane_out["distortion"] = [[mi.Float(p["dist"])] for p in pixels]
        if "count" in aovs:
            lane_out["count"] = [[p["count"]] for p in pixels]
        return lane_out, t_final, alpha_img, depth_img

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

    bins: Bins
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
    pixels: mi.UInt32 | None = None  # [P] only these pixels (``sample_plan``); None: all


def _grad_reduce_mode(entries: int, config: RasterConfig) -> dr.ReduceMode:
    """dr.ReduceMode of the backward's per-surfel scatter-adds into ``entries`` floats.

    Expand (LLVM: a private copy of the gradient arrays per thread, non-atomic updates,
    summed at the end) where the copies fit ``config.expand_grad_bytes``; otherwise Local
    (every lane of a packet reads the same sorted entry, so a pre-reduction in the packet
    leaves one atomic per scatter). CUDA treats Expand as Auto."""
    return dr.ReduceMode.Expand if grad_copy_bytes(entries, config) else dr.ReduceMode.Local


def _tiled_backward(op: _TiledOp) -> None:
    """``_TiledOp``'s backward: the walk back to front (``_BackwardWalk``), then the
    per-surfel gradient sums handed to Dr.Jit's AD."""
    ctx = op.ctx
    grads_out = {k: dr.detach(v) for k, v in op.grad_out().items()}
    walk = _BackwardWalk(op, grads_out)
    dr.while_loop((walk.start(),), walk.cond, walk.body, label="raster_tiles_backward")
    acc, acc_chans = walk.unpacked_sums()
    dr.eval(acc, acc_chans)
    if ctx.geometry_grad:
        op.set_grad_in("fields", {k: acc[k] for k in ctx.field_names})
    if acc_chans:
        op.set_grad_in("chans", acc_chans)


class _BackwardWalk:
    """The state and steps of the backward's ``dr.while_loop``: per pixel of a lane what it
    needs of the output gradients (``pixel``), and the per-surfel gradient sums (``acc``:
    the projected fields, ``acc_chans``: the channels) that the loop scatter-adds into."""

    def __init__(self, op: _TiledOp, grads_out: dict):
        ctx = op.ctx
        self.op, self.ctx, self.grads_out = op, ctx, grads_out
        self.config, self.aovs = ctx.config, ctx.aovs
        plan = self.plan = op.plan
        self.pxf = [mi.Float(px) + 0.5 for px in plan.pxs]
        self.pyf = [mi.Float(py) + 0.5 for py in plan.pys]
        self.n = plan.n
        # What each pixel k of a lane needs from the output gradients: pixel[k][...].
        self.pixel = [self._pixel_grads(k) for k in range(len(plan.pxs))]
        normal = "normal" in self.aovs
        self.q_names = PAIR_FIELDS + (NORMAL_FIELDS if normal else ())
        nsurf = ctx.nsurfels
        # The per-surfel sums, packed (``core.packed``) in the entries' order: every
        # channel's components, then the projected fields', so that a packet
        # scatter-add updates a surfel's at once.
        nsums = sum(ctx.widths.values()) + (len(self.q_names) if ctx.geometry_grad else 0)
        self.sums = Packed.zeros(nsurf, nsums)
        self.reduce_mode = _grad_reduce_mode(
            grad_entries(nsurf, normal, sum(ctx.widths.values())), self.config)

    def _lane_grad(self, name: str, c: int, k: int) -> list:
        """[lanes] per component of output ``name``'s gradient (C = ``c``) at pixel k of
        each lane."""
        g = self.grads_out.get(name)
        if g is None or dr.width(g) == 0:
            return [dr.zeros(mi.Float, self.n)] * c
        plan = self.plan
        return [dr.gather(mi.Float, g, plan.out_index[k] * c + ch, active=plan.insides[k])
                for ch in range(c)]

    def _pixel_grads(self, k: int) -> dict:
        """What pixel k of each lane needs from the output gradients: the channels', dL/d
        of its sum of weights, and those of the depth, median depth, normal, distortion."""
        op, ctx, aovs, n = self.op, self.ctx, self.aovs, self.n
        pk = {"chans": {name: self._lane_grad(name, c, k) for name, c in ctx.widths.items()}}
        # dL/d(sum of weights): alpha, the backgrounds' (1 - alpha), the depth's division.
        g_wsum = self._lane_grad("alpha", 1, k)[0] if "alpha" in aovs else dr.zeros(mi.Float, n)
        for name, bg in ctx.background.items():
            for g, b in zip(pk["chans"][name], bg, strict=True):
                g_wsum = g_wsum - jit.opaque(b) * g
        alpha_img = op.alpha_img[k]
        ok = alpha_img > 0
        if "depth" in aovs:
            g_dimg = self._lane_grad("depth", 1, k)[0]
            pk["g_dacc"] = dr.select(ok, g_dimg / dr.select(ok, alpha_img, 1.0), 0.0)
            g_wsum = g_wsum - pk["g_dacc"] * op.depth_img[k]
        pk["g_wsum"] = g_wsum
        pk["g_med"] = (self._lane_grad("median_depth", 1, k)[0] if "median_depth" in aovs
                       else None)
        pk["g_normal"] = self._lane_grad("normal", 3, k) if "normal" in aovs else None
        if "distortion" in aovs:
            pk["g_dist"] = mi.Float64(self._lane_grad("distortion", 1, k)[0])
            pk["m1"], pk["m2"] = op.m_sums[k]
            pk["wsum64"] = 1.0 - op.t_final[k]
        return pk

    def start(self) -> dict:
        """The loop's first state: each lane's group at its largest stop index, every
        pixel at its final T, no later pairs' sum yet."""
        # The lanes of a group (up to BACKWARD_GROUP consecutive lanes of one tile: a SIMD
        # packet) walk down together from the group's largest stop index, each pixel active
        # below its own: the packet reads one sorted entry per iteration (coherent gathers).
        # Any grouping is correct (a pixel composites only entries in [its tile's start, its
        # stop)), but a group across tiles would walk through the other tiles' lists: 25x
        # slower with 2x2 tiles.
        op, plan = self.op, self.plan
        self.first = dr.gather(mi.UInt32, self.ctx.bins.start, plan.tile)
        lane_stop = _maximum([dr.select(ins, st, self.first)
                              for ins, st in zip(plan.insides, op.stop, strict=True)])
        group_stop = dr.zeros(mi.UInt32, plan.n_groups)
        dr.scatter_reduce(dr.ReduceOp.Max, group_stop, lane_stop, plan.group)
        j = dr.gather(mi.UInt32, group_stop, plan.group)
        return {"j": j, "r": op.entries.entry(j - 1, j > self.first),
                "T": list(op.t_final),
                # opaque: a literal zero that stays zero (median depth alone: every dL/dw
                # is 0) trips the loop's constant-state check.
                "S": [dr.opaque(mi.Float64, 0.0, self.n) for _ in self.pixel]}

    def cond(self, s: dict) -> mi.Bool:
        """Whether a lane's group has pairs left in front of ``j``."""
        return s["j"] > self.first

    def body(self, s: dict) -> tuple:
        """One step back: sorted pair j - 1 for every pixel of the lane, then the lane's
        gradient sums scatter-added to the pair's surfel."""
        op = self.op
        i = s["j"] - 1
        rank = s["r"]
        # One read of the entry per lane, shared by its pixels.
        q, box, chan_vals = op.entries.read(rank, self.n)
        comps, ws, t_out, s_out, g_fields = [], [], [], [], []
        for k, pk in enumerate(self.pixel):
            comp, w, t, sk, fk = self._pixel_step(k, pk, i, q, box, chan_vals, s["T"][k],
                                                  s["S"][k])
            comps.append(comp)
            ws.append(w)
            t_out.append(t)
            s_out.append(sk)
            if fk is not None:
                g_fields.append(fk)
        self._scatter(comps, ws, g_fields, rank)
        return ({"j": i, "r": op.entries.entry(i - 1, i > self.first), "T": t_out,
                 "S": s_out},)

    def _pixel_step(self, k: int, pk: dict, i: mi.UInt32, q: dict, box: tuple,
                    chan_vals: dict, t: mi.Float64, suffix: mi.Float64) -> tuple:
        """Pixel k's step back over pair i: (composited, w_i, T_i, the new S, its
        projected fields' gradients or None without geometry gradients), T_i recovered
        from T_{i+1} = ``t``."""
        config = self.config
        plan = self.plan
        alpha, rho, depth = pair_eval(q, self.pxf[k], self.pyf[k], config)
        # Every kept pair before the stop index was composited (T only decreases).
        comp = ((i < self.op.stop[k]) & plan.insides[k] & pair_kept(alpha, rho, depth, config) &
                in_box(box, plan.pxs[k], plan.pys[k]))
        # Pairs that are not composited pass through with alpha 0 and a finite depth.
        depth = dr.select(comp, depth, config.near)
        a64 = mi.Float64(dr.select(comp, alpha, 0.0))
        one_minus = 1.0 - a64
        t_before = t / one_minus
        w64 = t_before * a64
        w = mi.Float(w64)
        t_new = dr.select(comp, t_before, t)
        if not self.ctx.geometry_grad:
            return comp, w, t_new, suffix, None
        g64, fg = self._geometry_grad(k, pk, i, q, chan_vals, depth, w, w64, t_before,
                                      one_minus, suffix)
        s_new = dr.select(comp, suffix + w64 * g64, suffix)
        return comp, w, t_new, s_new, {f: dr.select(comp, v, 0.0) for f, v in fg.items()}

    def _geometry_grad(self, k, pk, i, q, chan_vals, depth, w, w64, t_before, one_minus,
                       suffix) -> tuple:
        """Pixel k's (g64, gradients of the projected fields, the normal's too) for pair
        i: g64 = dL/dw_i, whose running sum over later pairs is the state's S
        (``suffix``)."""
        aovs, config = self.aovs, self.config
        # g: dL/dw of this pair (every output is linear in w but the distortion);
        # g_z: dL/ddepth at fixed w.
        g = pk["g_wsum"]
        g_z = dr.zeros(mi.Float, self.n)
        for name, gs in pk["chans"].items():
            for gk, v in zip(gs, chan_vals[name], strict=True):
                g = g + gk * v
        if "depth" in aovs:
            g = g + pk["g_dacc"] * depth
            g_z = g_z + w * pk["g_dacc"]
        grads = {}
        if pk["g_normal"] is not None:
            for f, gk in zip(NORMAL_FIELDS, pk["g_normal"], strict=True):
                g = g + gk * q[f]
                grads[f] = w * gk
        g64 = mi.Float64(g)
        if pk["g_med"] is not None:
            g_z = g_z + dr.select(i == self.op.med_j[k], pk["g_med"], 0.0)
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
        grads.update(pair_eval_grad(q, self.pxf[k], self.pyf[k], g_alpha, g_z, config))
        return g64, grads

    def unpacked_sums(self) -> tuple:
        """(projected field -> [N] gradient sums, channel -> [N * C]) from the packed sums,
        in surfel order."""
        entry = self.ctx.bins.entry_of
        k, acc_chans = 0, {}
        for name, c in self.ctx.widths.items():
            comps = [self.sums.column(k + ch, entry) for ch in range(c)]
            acc_chans[name] = dr.ravel(mi.ArrayXf(comps))  # [N * C], component fastest
            k += c
        acc = ({f: self.sums.column(k + i, entry) for i, f in enumerate(self.q_names)}
               if self.ctx.geometry_grad else {})
        return acc, acc_chans

    def _scatter(self, comps: list, ws: list, g_fields: list, rank: mi.UInt32) -> None:
        """The lane's sums over its pixels, then one packet scatter-add of them into the
        pair's entry (w is 0 where a pixel did not composite the pair)."""
        any_comp = comps[0]
        for c in comps[1:]:
            any_comp = any_comp | c
        values = []
        for name, c in self.ctx.widths.items():  # the channels' gradients: w_i dL/d(image)
            for ch in range(c):
                values.append(_sum([w * pk["chans"][name][ch]
                                    for w, pk in zip(ws, self.pixel, strict=True)]))
        if self.ctx.geometry_grad:
            values += [_sum([g[f] for g in g_fields]) for f in self.q_names]
        self.sums.scatter_add(values, rank, any_comp, self.reduce_mode)


def render_tiles(g: Proj, gd: Proj, W: int, H: int, chans: dict, aovs: Sequence[str],
                 bg: dict, config: RasterConfig, grad: bool,
                 pixels: mi.UInt32 | None = None) -> dict[str, mi.Float]:
    """Every output of ``rasterize``, flat ([H * W * C] each), by the tiled renderer; ``g``
    the projected surfels with AD, ``gd`` detached. With ``pixels`` [P] (flat indices
    inside the image) only those pixels: outputs [P * C], each pixel composited exactly as
    in the whole image (the same operations in the same order)."""
    if max(W, H) > BOX_MAX:
        raise ValueError(f"rasterize (tiles): images up to {BOX_MAX} pixels a side, got "
                         f"{W} x {H}; use RasterConfig.method='pairs'")
    widths = {name: t.shape[1] for name, t in chans.items()}
    bins = bin_surfels(gd, W, H, config, grad, sum(widths.values())) if dr.width(gd.xc) else None
    npix = W * H if pixels is None else dr.width(pixels)
    if bins is None:
        out = {name: dr.zeros(mi.Float, npix * c) for name, c in widths.items()}
        for name, vals in bg.items():
            out[name] = dr.tile(mi.Float(vals), npix)
        for a in aovs:
            out[a] = dr.zeros(mi.Float, npix * AOV_CHANNELS[a])
        return out
    names = PAIR_FIELDS + (NORMAL_FIELDS if "normal" in aovs else ())
    fields = {k: getattr(g, k) for k in PAIR_FIELDS}
    if "normal" in aovs:
        fields |= dict(zip(NORMAL_FIELDS, (g.normal.x, g.normal.y, g.normal.z), strict=True))
    ctx = _TiledCtx(bins, W, H, widths, tuple(aovs), bg, config, names, dr.width(gd.xc),
                    any(dr.grad_enabled(v) for v in fields.values()), pixels)
    return dr.custom(_TiledOp, fields, {name: t.array for name, t in chans.items()}, ctx)


