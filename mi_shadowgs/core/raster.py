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
from collections.abc import Mapping, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster_common import (
    AOV_CHANNELS,
    PAIR_FIELDS,
    RASTER_METHODS,
    Proj,
    RasterConfig,
    RasterMemoryError,
    argsort_bounded,
    boxes,
    budget_text,
    depth_key,
    distortion_m,
    expand,
    face_camera,
    memory_budget,
    pair_eval,
    pair_kept,
    project,
    total_pairs,
)
from mi_shadowgs.core.surfels import Surfels

DEFAULT_CONFIG = RasterConfig()

# The public face of both rasterizers (``RasterConfig`` and the rest live in raster_common).
__all__ = [
    "AOV_CHANNELS",
    "RASTER_METHODS",
    "RasterConfig",
    "RasterMemoryError",
    "depth_key",
    "face_camera",
    "pair_counts",
    "pixel_runs",
    "rasterize",
    "segment_exclusive_sum",
    "splat_pairs",
]


def _plan_bands(g: Proj, width: int, height: int, config: RasterConfig,
                grad: bool) -> tuple[list[tuple[int, int]], int]:
    """(bands, total): bands of rows [r0, r1) whose pair lists fit the memory budget and
    ``max_pairs`` (the whole image when it fits, else consecutive bands when no ``grad``,
    else RasterMemoryError), and the whole image's pair count, which a single band reuses
    (one host read per render)."""
    _, y0, bw, bh, count = boxes(g, width, height, config)
    total = total_pairs(count)
    per_pair = config.bytes_per_pair_grad if grad else config.bytes_per_pair
    need = total * per_pair + config.reserve_bytes
    mem = memory_budget(config, need) if total else None
    over = mem is not None and mem[1] + need > mem[0]
    if not over and total <= config.max_pairs:
        return [(0, height)], total
    hint = "(surfels too large for the image?)"
    why = (f"{budget_text(config, *mem)}" if over else
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
    edges = (np.bincount(np.minimum(y0n, height), w, height + 1)
             - np.bincount(np.minimum(y0n + bhn, height), w, height + 1))
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


def _build_pairs(g: Proj, width: int, height: int, config: RasterConfig,
                 rows: tuple[int, int] | None = None, total: int | None = None):
    """Sorted (surfel id, pixel id) of the pairs that contribute; detached. None if none.

    ``rows`` = (r0, r1) restricts the pairs to those image rows; pixel ids then count from
    row r0 (pixel (x, y) is (y - r0) * width + x). ``total``: their pixel-box pair count
    when the caller already read it (``_plan_bands``)."""
    r0, r1 = (0, height) if rows is None else rows
    x0, y0, bw, _, count = boxes(g, width, height, config,
                                  (dr.opaque(mi.Int32, r0), dr.opaque(mi.Int32, r1)))
    total = total_pairs(count) if total is None else total
    if total > config.max_pairs:
        raise RasterMemoryError(f"rasterize: {total} pixel-splat pairs exceed "
                                f"RasterConfig.max_pairs={config.max_pairs} (surfels too "
                                f"large for the image?)")
    if total == 0:
        return None
    # The pairs laid out surfel by surfel front to back (a stable sort of the N centre
    # depths: equal depths keep surfel order), then a stable sort by pixel alone: each
    # pixel's pairs in (depth, surfel) order, as a sort of 64-bit (pixel, depth) keys over
    # the pairs would leave them, with one counting pass over P instead of 6 radix passes.
    by_depth = dr.argsort(depth_key(g.z2))  # [N]
    pos, local = expand(dr.gather(mi.UInt32, count, by_depth), total)
    sid = dr.gather(mi.UInt32, by_depth, pos)
    # max(., 1): masked-off tail lanes of a gather read 0, and x86 integer division by 0
    # traps (SIGFPE) even in lanes that are discarded.
    w = dr.maximum(dr.gather(mi.UInt32, bw, sid), 1)
    ly = local // w
    lx = local - ly * w
    pxi = dr.gather(mi.UInt32, x0, sid) + lx
    pyi = dr.gather(mi.UInt32, y0, sid) + ly
    q = g.gather(sid, PAIR_FIELDS)
    alpha, rho, depth = pair_eval(q, mi.Float(pxi) + 0.5, mi.Float(pyi) + 0.5, config)
    idx = dr.compress(pair_kept(alpha, rho, depth, config))
    if dr.width(idx) == 0:
        return None
    sid = dr.gather(mi.UInt32, sid, idx)
    pix = dr.gather(mi.UInt32, (pyi - dr.opaque(mi.UInt32, r0)) * width + pxi, idx)
    order = argsort_bounded(pix, (r1 - r0) * width)
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


def splat_pairs(surfels: Surfels, camera: Camera, config: RasterConfig = DEFAULT_CONFIG,
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
        g = project(surfels, camera, config).detach()
        dr.eval(*(getattr(g, f.name) for f in dataclasses.fields(g)))
        w, h = camera.width, camera.height
        bands, total = _plan_bands(g, w, h, config, grad=False) if surfels.count else ([], 0)
        for r0, r1 in bands:
            pairs = _build_pairs(g, w, h, config, (r0, r1),
                                 total if len(bands) == 1 else None)
            if pairs is None:
                continue
            sid, pix = pairs
            q = g.gather(sid, PAIR_FIELDS)
            alpha, _, depth = pair_eval(q, *_centres(pix, w, r0), config)
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


def pair_counts(surfels: Surfels, camera: Camera, config: RasterConfig = DEFAULT_CONFIG
                ) -> tuple[int, int]:
    """(pixel-box pairs, pairs kept after the alpha/cutoff tests) of a view (benchmarks)."""
    with dr.suspend_grad():
        g = project(surfels, camera, config).detach()
        box = boxes(g, camera.width, camera.height, config)[4]
        built = _build_pairs(g, camera.width, camera.height, config)
        return total_pairs(box), 0 if built is None else dr.width(built[0])


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
              config: RasterConfig = DEFAULT_CONFIG,
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
            return ({name: dr.zeros(mi.TensorXf, (0, t.shape[1])) for name, t in chans.items()}
                    | {a: dr.zeros(mi.TensorXf, (0, AOV_CHANNELS[a])) for a in aovs})
        pixels = jit.host(host.astype(np.uint32), mi.UInt32)

    g = project(surfels, camera, config)
    # One per-surfel kernel now, rather than whatever set of pending variables the first
    # gather happens to evaluate (that set varies and defeats the kernel cache).
    dr.eval(*(getattr(g, f.name) for f in dataclasses.fields(g)))
    gd = g.detach()
    grad = (any(dr.grad_enabled(getattr(g, f.name)) for f in dataclasses.fields(g)) or
            any(dr.grad_enabled(t) for t in chans.values()))
    widths = ({name: t.shape[1] for name, t in chans.items()} |
              {a: AOV_CHANNELS[a] for a in aovs})
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


def _render_rows(g: Proj, gd: Proj, r0: int, r1: int, W: int, H: int, chans: dict,
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
    q = g.gather(sid, PAIR_FIELDS)
    alpha, _, depth = pair_eval(q, *_centres(pix, W, r0), config)

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
        m = distortion_m(depth, config)
        wm = w64 * m
        m1 = segment_exclusive_sum(wm, pix, first, npix)
        m2 = segment_exclusive_sum(wm * m, pix, first, npix)
        acc = 1.0 - t_before  # = sum of the weights in front (all of them contribute)
        d = w64 * (m * m * acc + m2 - 2.0 * m * m1)
        out["distortion"] = accumulate([mi.Float(d)], 1)
    if "count" in aovs:
        out["count"] = accumulate([dr.select(contrib, mi.Float(1.0), 0.0)], 1)
    return out
