"""Screen tiles of the tiled rasterizer (``raster_tiles``): surfel-tile pairs sorted by
(tile, depth) (``bin_surfels``), the memory budget that sets the tile size
(``check_tile_budget``), the pixels each compositing lane holds (``image_plan``,
``sample_plan``) and the way back from the lanes to flat outputs (``to_image``,
``to_samples``).
"""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi

from mi_shadowgs.core.packed import Packed, packet_widths
from mi_shadowgs.core.raster_common import (
    PAIR_FIELDS,
    Proj,
    RasterConfig,
    RasterMemoryError,
    argsort_bounded,
    boxes,
    budget_text,
    conic_of,
    depth_key,
    expand,
    memory_budget,
    reaches_rect,
    total_pairs,
)

# Projected per-surfel fields the compositing loops read: the pair maths plus the normal.
NORMAL_FIELDS = ("nx", "ny", "nz")
# Lanes that start the backward walk together (``raster_tiles``): an AVX-512 packet.
BACKWARD_GROUP = 16
# Largest tile edge that ``bin_surfels`` grows to when the configured tiles' pairs do not
# fit the memory budget (64: 4096 lanes, 256 SIMD packets per tile list; the tests cover it).
MAX_TILE_SIZE = 64
# Pixel boxes are packed as two 16-bit coordinates per UInt32 (``Bins.box``).
BOX_MAX = 0xFFFF


@dataclasses.dataclass
class Bins:
    """Surfel-tile pairs sorted by (tile, depth), and the tile grid."""

    size: int  # tile edge in pixels
    ntx: int  # tiles per row
    nty: int  # tiles per column
    rank: mi.UInt32  # [TP] surfel of each sorted pair, as its entry (place in ``entries``)
    entries: mi.UInt32  # [N] the surfels by (first tile, depth): the compositing tables' order
    entry_of: mi.UInt32  # [N] each surfel's place in ``entries`` (its inverse)
    box: tuple  # ([N] x0 | x1 << 16, [N] y0 | y1 << 16): each surfel's pixel box
    start: mi.UInt32  # [tiles] first sorted pair of each tile
    end: mi.UInt32  # [tiles] one past its last
    per_lane: int = 1  # pixels of a tile that one lane composites (a divisor of size^2)

    @property
    def lanes_per_tile(self) -> int:
        return self.size * self.size // self.per_lane

    @property
    def lanes(self) -> int:
        return self.ntx * self.nty * self.lanes_per_tile


def grad_entries(surfels: int, normal: bool, channels: int) -> int:
    """Floats of the backward's per-surfel gradient sums: the pair fields, the normal's
    when it is rendered, and every channel, in packets (``core.packed``)."""
    return surfels * sum(packet_widths(len(PAIR_FIELDS) + len(NORMAL_FIELDS) * normal +
                                       channels))


def grad_copy_bytes(entries: int, config: RasterConfig) -> int:
    """Bytes of the per-thread copies of ``entries`` gradient floats under ReduceMode.Expand,
    or 0 where they exceed ``config.expand_grad_bytes`` (then Local:
    ``raster_tiles._grad_reduce_mode``)."""
    copies = entries * 4 * max(dr.thread_count(), 1)
    return copies if copies <= config.expand_grad_bytes else 0


def check_tile_budget(tile_pairs: int, lanes: int, config: RasterConfig, grad: bool,
                      channels: int, surfels: int) -> None:
    """RasterMemoryError when the tiled render would not fit the memory budget or
    ``max_pairs``: its memory is O(lanes + surfel-tile pairs), both known before binning,
    plus the backward's per-thread gradient copies (``grad_copy_bytes``)."""
    if tile_pairs > config.max_pairs:
        raise RasterMemoryError(
            f"rasterize (tiles): {tile_pairs} surfel-tile pairs exceed "
            f"RasterConfig.max_pairs={config.max_pairs} (surfels too large for the image?)")
    per_lane = config.bytes_per_pixel_grad if grad else config.bytes_per_pixel
    need = (config.reserve_bytes + lanes * (per_lane + 8 * channels) +
            tile_pairs * (config.bytes_per_tile_pair + 4 * channels))
    if grad:
        # The normal's fields counted whether or not it is rendered: an upper bound.
        need += grad_copy_bytes(grad_entries(surfels, True, channels), config)
    mem = memory_budget(config, need)
    if mem is not None and mem[1] + need > mem[0]:
        raise RasterMemoryError(
            f"rasterize (tiles): {tile_pairs} surfel-tile pairs and {lanes} pixels need "
            f"~{need / (1 << 30):.2f} GiB, but {budget_text(config, *mem)}; a smaller "
            f"image lowers it")


def bin_surfels(gd: Proj, width: int, height: int, config: RasterConfig, grad: bool,
                channels: int) -> Bins | None:
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
            check_tile_budget(total, ntx * nty * ts * ts, config, grad, channels,
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
    ntiles_all = ntx * nty
    # The compositing loops' tables hold one entry per surfel, by its first (top-left) tile
    # and then depth, so that the entries of a tile's list lie close together.
    first_tile = dr.gather(mi.UInt32, dr.select(live, ty0 * ntx + tx0, ntiles_all), by_depth)
    entries = dr.gather(mi.UInt32, by_depth, argsort_bounded(first_tile, ntiles_all + 1))
    entry_of = dr.zeros(mi.UInt32, dr.width(entries))  # each surfel's place in entries
    dr.scatter(entry_of, dr.arange(mi.UInt32, dr.width(entries)), entries)
    # What the pairs read of their surfel, packed (one cache line per surfel) in depth
    # order: a surfel's pairs lie together there, so that their reads go through memory in
    # order.
    per = {"tw": tw, "tx0": tx0, "ty0": ty0, "entry": entry_of}
    if config.cull_tiles:
        per |= conic_of(gd, config)
    packed = Packed.of([v if isinstance(v, mi.Float) else dr.reinterpret_array(mi.Float, v)
                        for v in per.values()]).permuted(by_depth)
    pos, local = expand(dr.gather(mi.UInt32, ntiles, by_depth), total)  # [TP]
    pair = dict(zip(per, packed.read(pos, total), strict=True))
    tw_, tx0_, ty0_, entry_ = (dr.reinterpret_array(mi.UInt32, pair[k])
                               for k in ("tw", "tx0", "ty0", "entry"))
    w = dr.maximum(tw_, 1)  # max: see raster_common.expand
    ly = local // w
    tx = tx0_ + (local - ly * w)
    ty = ty0_ + ly
    tile = ty * ntx + tx
    if config.cull_tiles:
        # A tile of the box that the splat's kept region misses sorts past the last tile
        # (ntiles_all), outside every tile's [start, end).
        xa, ya = mi.Float(tx * ts) + 0.5, mi.Float(ty * ts) + 0.5
        reach = reaches_rect(pair, xa, xa + (ts - 1), ya, ya + (ts - 1), config)
        tile = dr.select(reach, tile, ntiles_all)
    dr.eval(tile, entry_)
    order = argsort_bounded(tile, ntiles_all + 1 if config.cull_tiles else ntiles_all)
    rank = dr.gather(mi.UInt32, entry_, order)
    tile = dr.gather(mi.UInt32, tile, order)
    ar = dr.arange(mi.UInt32, total)
    last_idx = dr.opaque(mi.UInt32, total - 1)
    prev = dr.gather(mi.UInt32, tile, dr.maximum(ar, 1) - 1)
    nxt = dr.gather(mi.UInt32, tile, dr.minimum(ar + 1, last_idx))
    start = dr.zeros(mi.UInt32, ntiles_all)
    end = dr.zeros(mi.UInt32, ntiles_all)
    listed = tile < ntiles_all
    dr.scatter(start, ar, tile, active=listed & ((ar == 0) | (prev != tile)))
    dr.scatter(end, ar + 1, tile, active=listed & ((ar == last_idx) | (nxt != tile)))
    x1 = x0 + bw - 1  # inclusive; only read for live surfels
    y1 = y0 + bh - 1
    box = (x0 | (x1 << 16), y0 | (y1 << 16))  # per surfel: packed per pair with its fields
    dr.eval(rank, entries, entry_of, start, end, *box)
    return Bins(ts, ntx, nty, rank, entries, entry_of, box, start, end,
                math.gcd(config.pixels_per_lane, ts * ts))


@dataclasses.dataclass
class LanePlan:
    """The pixels the compositing lanes hold, and how the backward groups the lanes.

    A whole image (``image_plan``): tile-major lanes of ``per_lane`` pixels of one tile.
    Sampled pixels (``sample_plan``): one pixel per lane, lanes ordered by tile."""

    n: int  # lanes
    tile: mi.UInt32  # [n] the tile whose sorted list a lane walks
    pxs: list  # per pixel k of a lane: x [n] (UInt32)
    pys: list  # ... y [n]
    insides: list  # ... inside the image [n] (Bool)
    out_index: list  # ... the pixel's row in the flat output: its pixel or sample index [n]
    # The backward's walking groups (up to BACKWARD_GROUP lanes of one tile): group [n]
    # in [0, n_groups).
    group: mi.UInt32
    n_groups: int
    samples: int | None = None  # sampled pixels (outputs [samples * C]); None: the image


def image_plan(bins: Bins, width: int, height: int) -> LanePlan:
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
    groups_per_tile = -(-per_tile // BACKWARD_GROUP)
    group = tile * groups_per_tile + sub // BACKWARD_GROUP
    return LanePlan(bins.lanes, tile, pxs, pys, insides, pixs, group,
                     bins.ntx * bins.nty * groups_per_tile)


def sample_plan(bins: Bins, width: int, pixels: mi.UInt32) -> LanePlan:
    """One lane per entry of ``pixels`` [P] (flat indices y * width + x inside the image,
    repeats allowed), the lanes ordered by tile (stable) so that a SIMD packet walks few
    lists; a group is a run of up to BACKWARD_GROUP lanes of one tile."""
    n = dr.width(pixels)
    py0 = pixels // width
    px0 = pixels - py0 * width
    tile0 = (py0 // bins.size) * bins.ntx + px0 // bins.size
    order = argsort_bounded(tile0, bins.ntx * bins.nty)  # [n] the sample held by each lane
    tile = dr.gather(mi.UInt32, tile0, order)
    lane = dr.arange(mi.UInt32, n)
    prev = dr.gather(mi.UInt32, tile, dr.maximum(lane, 1) - 1)
    run_start = dr.prefix_reduce(dr.ReduceOp.Max, dr.select((lane == 0) | (prev != tile),
                                                             lane, 0), exclusive=False)
    group = run_start + (lane - run_start) // BACKWARD_GROUP * BACKWARD_GROUP
    px, py = dr.gather(mi.UInt32, px0, order), dr.gather(mi.UInt32, py0, order)
    dr.eval(tile, px, py, order, group)
    return LanePlan(n, tile, [px], [py], [dr.full(mi.Bool, True, n)], [order], group, n,
                     samples=n)


def to_image(vals: list, plan: LanePlan, width: int, height: int) -> mi.Float:
    """Lane values (per pixel k of a lane: C arrays [lanes]) -> a flat image [H * W * C],
    each pixel scattered from its lane (one write per output value; every pixel of the
    image is some lane's pixel ``image_plan``)."""
    c = len(vals[0])
    out = dr.zeros(mi.Float, width * height * c)
    for k, vk in enumerate(vals):
        for cc, v in enumerate(vk):
            dr.scatter(out, v, plan.out_index[k] * c + cc, active=plan.insides[k])
    return out


def to_samples(vals: list, plan: LanePlan) -> mi.Float:
    """Lane values (one pixel per lane: C arrays [lanes]) -> [samples * C] in the order of
    the sampled pixels."""
    c = len(vals[0])
    out = dr.zeros(mi.Float, plan.samples * c)
    for cc, v in enumerate(vals[0]):
        dr.scatter(out, v, plan.out_index[0] * c + cc)
    return out


def in_box(box: tuple, px: mi.UInt32, py: mi.UInt32) -> mi.Bool:
    """Whether pixel (px, py) lies in a pair's box (the pair list holds exactly the box's
    pixels)."""
    bx, by = box
    return ((px >= (bx & 0xFFFF)) & (px <= (bx >> 16)) & (py >= (by & 0xFFFF)) &
            (py <= (by >> 16)))


