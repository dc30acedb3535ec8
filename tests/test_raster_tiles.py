"""The tiled rasterizer (RasterConfig.method="tiles") against the pair-list reference.

Both renderers composite the same pairs in the same order with the same per-pair float32
maths, so outputs agree to float32 summation order and gradients to float32 rounding of
two different (hand-written vs Dr.Jit AD) backward passes. The finite-difference test of
test_raster_grad.py (on the pair list there) runs on the tiled path too.
"""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import test_raster_grad
from raster_reference import random_scene, reference, to_surfels
from test_raster_hard_cases import (
    edge_on_surfels,
    one_pixel_stack,
    raw_surfels,
    render_checked,
    sphere_surfels,
)

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.packed import PACKET_MAX, Packed, packet_widths
from mi_shadowgs.core.raster import RasterConfig, RasterMemoryError, rasterize
from mi_shadowgs.core.raster_bins import bin_surfels
from mi_shadowgs.core.raster_common import (
    argsort_bounded,
    boxes,
    conic_of,
    opacity_cutoff2,
    project,
    reaches_rect,
)

AOVS = ("alpha", "depth", "median_depth", "normal", "distortion", "count")
PAIRS = RasterConfig(method="pairs")
TILES = RasterConfig(method="tiles")
assert RasterConfig().method == "tiles"  # the default: the hard-case and stage tests run it
BACKGROUND = {"color": [0.1, 0.2, 0.3]}


def cameras(width=24, height=20):
    persp = Camera.look_at([0.4, 0.9, 2.6], [0.0, 0.0, 0.0], width=width, height=height,
                           fov_x=0.8)
    ortho = Camera.look_at([-2.5, 1.2, 1.0], [0.0, 0.0, 0.0], width=width, height=height,
                           ortho_width=1.9)
    return {"perspective": persp, "orthographic": ortho}


def render(surfels, camera, config, aovs=AOVS, background=None, grad_outputs=None):
    """(outputs, raw-parameter gradients or None) as float64 numpy. ``grad_outputs``: the
    outputs in a loss with fixed pseudo-random weights (None: no backward pass)."""
    params = surfels.params()
    if grad_outputs is not None:
        for v in params.values():
            dr.enable_grad(v)
    out = rasterize(surfels, camera, surfels.channels, aovs=aovs, config=config,
                    background=background)
    res = {k: np.array(v, np.float64) for k, v in out.items()}
    if grad_outputs is None:
        return res, None
    loss = mi.Float(0.0)
    for k in grad_outputs:
        img = out[k].array
        # Weights of both signs; distortion values are ~1e-4: scaled to the others' size.
        w = dr.sin(dr.arange(mi.Float, dr.width(img)) * 0.7 + 0.3)
        loss += dr.sum(img * w) * (1e3 if k == "distortion" else 1.0)
    # AllowNoGrad: a render where nothing is visible does not depend on the parameters.
    dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    return res, {k: np.array(dr.grad(v), np.float64) for k, v in params.items()}


# float32 summation order: the pair list adds float32 weights with scatter-adds, the tiled
# loop in compositing order and alpha = 1 - T in Float64; measured differences <= 2e-7 on
# O(1) colours, 7e-7 on depths of ~3 (2.4e-7 relative), 7e-12 on distortions of 1e-4.
# Distortion is w_i (m_i^2 W + M2 - 2 m_i M1) with O(1) terms, so both paths carry an
# absolute error of ~1e-12 (seen 7e-12 where every m ~ 1: the far camera's ~1e-12 images):
# as test_raster_forward, 1e-5 of max(peak, 1e-3).
COLOUR_ATOL = 2e-6
DEPTH_RTOL = 2e-6
DISTORTION_RTOL = 1e-5
DISTORTION_FLOOR = 1e-3


def assert_outputs_equal(got, want):
    assert set(got) == set(want)
    for k, w in want.items():
        g = got[k]
        assert g.shape == w.shape, k
        if k in ("depth", "median_depth"):
            np.testing.assert_allclose(g, w, rtol=DEPTH_RTOL, atol=0, err_msg=k)
        elif k == "count":
            np.testing.assert_array_equal(g, w, err_msg=k)
        elif k == "distortion":
            atol = DISTORTION_RTOL * max(np.abs(w).max(), DISTORTION_FLOOR)
            np.testing.assert_allclose(g, w, rtol=0, atol=atol, err_msg=k)
        else:
            np.testing.assert_allclose(g, w, rtol=0, atol=COLOUR_ATOL, err_msg=k)


# Gradients: two float32 backward passes over the same pairs; measured differences <=
# 4e-7 of the largest |gradient| of the loss (over every parameter group: a group whose
# gradient is analytically 0, log-scales under the median depth, holds rounding noise of
# ~1e-8 of it); a missing or wrong term is >= 1e-3 of its group.
GRAD_RTOL = 1e-5


def assert_grads_equal(got, want, outputs=None, rtol=GRAD_RTOL):
    top = max(np.abs(w).max() for w in want.values())
    assert top > 0  # the comparison must test something
    for k, w in want.items():
        if k == "channels.color" and outputs is not None and "color" not in outputs:
            assert np.abs(got[k]).max() == 0.0, k
            continue
        np.testing.assert_allclose(got[k], w, rtol=0, atol=rtol * top,
                                   err_msg=f"{k} ({outputs})")


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_forward_matches_pairs(kind, seed):
    camera = cameras()[kind]
    raw = random_scene(40, seed)
    want, _ = render(to_surfels(raw), camera, PAIRS, background=BACKGROUND)
    got, _ = render(to_surfels(raw), camera, TILES, background=BACKGROUND)
    assert want["alpha"].max() > 0.9 and (want["count"] >= 3).sum() > 50  # non-trivial
    assert_outputs_equal(got, want)


@pytest.mark.parametrize("tile_size", [1, 3, 5, 16, 64])
def test_tile_size_does_not_change_the_image(tile_size):
    # 24 x 20 pixels: partial tiles at 3 (rows), 5, 16 and a single tile larger than the
    # image at 64; 1 puts every pixel in its own tile; 5 has two backward walking groups
    # per tile (25 lanes), 1 and 3 one group of fewer than 16 lanes.
    camera = cameras()["perspective"]
    raw = random_scene(40, 2)
    aovs = tuple(a for a in AOVS if a != "count")
    want, gw = render(to_surfels(raw), camera, PAIRS, aovs, BACKGROUND, ("color", "depth"))
    got, gg = render(to_surfels(raw), camera, dataclasses.replace(TILES, tile_size=tile_size),
                     aovs, BACKGROUND, ("color", "depth"))
    assert_outputs_equal(got, want)
    assert_grads_equal(gg, gw)


@pytest.mark.parametrize("tile_size,per_lane", [(4, 1), (4, 2), (4, 16), (8, 4), (8, 64),
                                                (3, 4), (5, 16)])
def test_pixels_per_lane_do_not_change_the_image(tile_size, per_lane):
    # A lane composites per_lane pixels of its tile (3 and 5: odd tiles take 1 per lane);
    # 16 at 4x4 and 64 at 8x8 tiles: one lane per tile, whose packet spans 16 tiles' lists.
    # Every output and every gradient against the pair list.
    camera = cameras()["perspective"]
    raw = random_scene(40, 3)
    aovs = tuple(a for a in AOVS if a != "count")
    outputs = GRAD_CASES[-1]
    config = dataclasses.replace(TILES, tile_size=tile_size, pixels_per_lane=per_lane)
    want, gw = render(to_surfels(raw), camera, PAIRS, aovs, BACKGROUND, outputs)
    got, gg = render(to_surfels(raw), camera, config, aovs, BACKGROUND, outputs)
    assert_outputs_equal(got, want)
    assert_grads_equal(gg, gw, outputs)
    counts, _ = render(to_surfels(raw), camera, config, ("count",))
    np.testing.assert_array_equal(counts["count"], render(to_surfels(raw), camera, PAIRS,
                                                          ("count",))[0]["count"])


def test_forward_matches_reference():
    """The tiled path against the float64 NumPy reference directly (as test_raster_forward)."""
    camera = cameras()["orthographic"]
    raw = random_scene(40, 3)
    got, _ = render(to_surfels(raw), camera, TILES)
    ref = reference(camera, raw, PAIRS)
    ok = ~ref["unsure"]
    assert ok.mean() > 0.9
    np.testing.assert_allclose(got["color"][ok], ref["color"][ok], atol=1e-4)
    np.testing.assert_allclose(got["depth"][ok, 0], ref["depth"][ok], rtol=1e-4)
    np.testing.assert_array_equal(got["count"][ok, 0], ref["count"][ok])


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
def test_faint_splats_have_smaller_boxes_and_the_same_image(kind):
    """Splats of opacity 0.004-0.3: each box bounds rho <= 2 ln(opacity / alpha_min) instead
    of the 3-sigma cutoff (beyond it alpha < alpha_min), and the image still equals the
    float64 reference, which has no boxes; the gradients equal the pair list's."""
    camera = cameras()[kind]
    raw = random_scene(60, 5, scale=(0.03, 0.1), opacity=(0.004, 0.3))
    surfels = to_surfels(raw)
    g = project(surfels, camera, TILES)
    faint = boxes(g, camera.width, camera.height, TILES)[4]
    full = boxes(dataclasses.replace(g, opacity=dr.full(mi.Float, 1.0, dr.width(g.xc))),
                 camera.width, camera.height, TILES)[4]
    assert int(dr.sum(faint)[0]) < 0.85 * int(dr.sum(full)[0])
    k2 = opacity_cutoff2(mi.Float([0.001, 0.01, 0.1, 0.5, 1.0]), TILES).numpy()
    assert k2[0] <= 0 and k2[-2] == k2[-1] == 9.0
    np.testing.assert_allclose(k2[1:3], 2 * np.log(np.array([0.01, 0.1]) * 255), rtol=2e-3)
    got, grads = render(surfels, camera, TILES, grad_outputs=("color", "depth"))
    ref = reference(camera, raw, PAIRS)
    ok = ~ref["unsure"]
    assert ok.mean() > 0.9 and ref["count"][ok].max() >= 3
    np.testing.assert_allclose(got["color"][ok], ref["color"][ok], atol=1e-4)
    np.testing.assert_array_equal(got["count"][ok, 0], ref["count"][ok])
    _, want = render(to_surfels(raw), camera, PAIRS, grad_outputs=("color", "depth"))
    assert_grads_equal(grads, want)


GRAD_CASES = [("color",), ("alpha",), ("depth",), ("median_depth",), ("normal",),
              ("distortion",), ("color", "alpha", "depth", "median_depth", "normal",
                                "distortion")]


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
@pytest.mark.parametrize("outputs", GRAD_CASES, ids="+".join)
def test_gradients_match_pairs(kind, outputs):
    camera = cameras()[kind]
    raw = random_scene(40, 1)
    aovs = tuple(a for a in AOVS if a != "count")
    _, want = render(to_surfels(raw), camera, PAIRS, aovs, BACKGROUND, outputs)
    _, got = render(to_surfels(raw), camera, TILES, aovs, BACKGROUND, outputs)
    assert_grads_equal(got, want, outputs)


@pytest.mark.parametrize("expand_grad_bytes", [0, 1 << 30])
def test_both_gradient_reduce_modes_match_pairs(expand_grad_bytes):
    # 0: no room for per-thread copies, so atomics after a packet pre-reduction (Local);
    # 1 GiB: per-thread copies (Expand). Both must give the pair list's gradients.
    from mi_shadowgs.core.raster_tiles import _grad_reduce_mode
    config = dataclasses.replace(TILES, expand_grad_bytes=expand_grad_bytes)
    assert _grad_reduce_mode(40 * 19, config) == \
        (dr.ReduceMode.Expand if expand_grad_bytes else dr.ReduceMode.Local)
    camera = cameras()["perspective"]
    raw = random_scene(40, 2)
    aovs = ("alpha", "depth", "normal", "distortion")
    outputs = ("color", "alpha", "depth", "normal", "distortion")
    _, want = render(to_surfels(raw), camera, PAIRS, aovs, BACKGROUND, outputs)
    _, got = render(to_surfels(raw), camera, config, aovs, BACKGROUND, outputs)
    assert_grads_equal(got, want, outputs)


@pytest.mark.parametrize("kind,outputs", [
    ("perspective", test_raster_grad.OUTPUTS), ("orthographic", test_raster_grad.OUTPUTS),
    ("perspective", ("distortion",)), ("orthographic", ("depth", "median_depth", "normal"))])
def test_gradients_match_finite_differences(kind, outputs, monkeypatch):
    # test_raster_grad's float64 finite differences, with its renders on the tiled path
    # (the reference reads only RasterConfig's numbers, which are the same).
    assert test_raster_grad.CFG.method != TILES.method  # else this only repeats that test
    monkeypatch.setattr(test_raster_grad, "CFG", TILES)
    test_raster_grad.test_gradients_match_finite_differences(kind, outputs)


# -- tiles of a box that the splat misses ------------------------------------------------
def _cull_scenes():
    """(camera, a function making the surfels) with splats of every shape: random, edge-on,
    faint, crossing the near plane, and an orthographic view."""
    persp, ortho = cameras(48, 40)["perspective"], cameras(48, 40)["orthographic"]
    raw = random_scene(300, 7, scale=(0.01, 0.3), opacity=(0.003, 0.99))
    raw["rotation"][:40] = np.tile([1.0, 0.9, 0.0, 0.0], (40, 1))  # steep to the views
    near = dict(random_scene(12, 8, extent=0.6, scale=(0.1, 0.5)))
    near["position"][:4] = [[0.3, 0.8, 2.4], [0.5, 0.9, 2.5], [0.35, 0.85, 2.45],
                            [0.4, 0.9, 2.6]]  # at or behind the near plane of persp
    edge_on = edge_on_surfels(persp.origin)
    return [(persp, lambda: to_surfels(raw)), (ortho, lambda: to_surfels(raw)),
            (persp, lambda: to_surfels(near)),
            (persp.with_size(32, 32), lambda: raw_surfels(*edge_on))]


def _tile_rho(q: dict, xa, ya, ts: int, n: int) -> np.ndarray:
    """[tiles, n * n] ``pair_eval``'s min(rho3d, rho2d) in float64 at n x n points over each
    tile of ts x ts pixel centres from (xa, ya); ``q``: each tile's splat's fields [tiles, 1]."""
    u = np.linspace(0.0, ts - 1.0, n)
    gx, gy = (g.ravel() for g in np.meshgrid(u, u))
    dx, dy = xa[:, None] + gx - q["xc"], ya[:, None] + gy - q["yc"]
    sx = q["t22"] * (dx * q["b1"] - dy * q["a1"])
    sy = q["t22"] * (dy * q["a0"] - dx * q["b0"])
    sz = (q["a0"] * q["b1"] - q["a1"] * q["b0"] + dx * (q["t21"] * q["b0"] - q["t20"] * q["b1"])
          + dy * (q["a1"] * q["t20"] - q["a0"] * q["t21"]))
    with np.errstate(divide="ignore", invalid="ignore"):
        r3 = np.where(sz != 0, (sx * sx + sy * sy) / (sz * sz), np.inf)
    return np.minimum(r3, TILES.lowpass_inv_var * (dx * dx + dy * dy))


def test_reaches_rect_keeps_every_reached_tile_and_drops_the_missed():
    """Against a float64 brute force over the pixel centres of 3x3-pixel tiles of each
    splat's box: every tile with a pixel that ``pair_kept``'s rho test passes is kept, and
    of the tiles that the float64 conic misses by a margin (5% of k2, on a dense grid of the
    tile), at most 1% are kept. The edge-on splats (last scene) are left out of the second
    count: their conics are too thin for float32 to place, and their tiles are kept."""
    kept_by_miss, misses, reached_total = 0, 0, 0
    for scene, (camera, surfels) in enumerate(_cull_scenes()):
        g = project(surfels(), camera, TILES).detach()
        x0, y0, bw, bh, count = (v.numpy().astype(np.int64) for v in boxes(
            g, camera.width, camera.height, TILES))
        f = {k: getattr(g, k).numpy().astype(np.float64)
             for k in ("xc", "yc", "a0", "a1", "b0", "b1", "t20", "t21", "t22")}
        k2 = opacity_cutoff2(g.opacity, TILES).numpy().astype(np.float64)
        ts = 3
        rows = [(i, tx, ty) for i in np.flatnonzero(count > 0)
                for ty in range(y0[i] // ts, (y0[i] + bh[i] - 1) // ts + 1)
                for tx in range(x0[i] // ts, (x0[i] + bw[i] - 1) // ts + 1)]
        i, tx, ty = (np.array(c) for c in zip(*rows, strict=True))
        xa, ya = tx * ts + 0.5, ty * ts + 0.5
        conic = {k: dr.gather(mi.Float, v, mi.UInt32(i)) for k, v in conic_of(g, TILES).items()}
        got = reaches_rect(conic, mi.Float(xa), mi.Float(xa + ts - 1), mi.Float(ya),
                           mi.Float(ya + ts - 1), TILES).numpy()
        q = {k: v[i][:, None] for k, v in f.items()}
        reached = (_tile_rho(q, xa, ya, ts, ts) <= k2[i][:, None]).any(axis=1)
        assert not np.any(reached & ~got)
        reached_total += int(reached.sum())
        missed = (_tile_rho(q, xa, ya, ts, 25) > 1.05 * k2[i][:, None]).all(axis=1)
        if scene < 3:
            kept_by_miss += int((missed & got).sum())
            misses += int(missed.sum())
    assert reached_total > 1000 and misses > 500 and kept_by_miss <= 0.01 * misses


def test_culling_tiles_changes_no_image_and_lists_fewer_pairs():
    """``RasterConfig.cull_tiles``: the same images to the bit and the same gradients as
    without, from fewer listed pairs (3x3 tiles; culled pairs sort past the last tile)."""
    for camera, surfels in _cull_scenes():
        config = dataclasses.replace(TILES, tile_size=3)
        plain = dataclasses.replace(config, cull_tiles=False)
        want, gw = render(surfels(), camera, plain, grad_outputs=GRAD_CASES[-1])
        got, gg = render(surfels(), camera, config, grad_outputs=GRAD_CASES[-1])
        for k, w in want.items():
            np.testing.assert_array_equal(got[k], w, err_msg=k)
        assert_grads_equal(gg, gw)
        gd = project(surfels(), camera, config).detach()
        bins = bin_surfels(gd, camera.width, camera.height, config, False, 3)
        full = bin_surfels(gd, camera.width, camera.height, plain, False, 3)
        listed = int(dr.sum(bins.end - bins.start)[0])
        assert dr.width(bins.rank) == dr.width(full.rank) == int(dr.sum(full.end - full.start)[0])
        assert listed < dr.width(bins.rank)


# -- hard cases (tests/test_raster_hard_cases.py), tiles against pairs ----------------------
def both(surfels_fn, camera, config=PAIRS, grad_rtol=GRAD_RTOL):
    """render_checked (finite outputs and gradients) of both paths, compared."""
    want, gw = render_checked(surfels_fn(), camera, config)
    got, gg = render_checked(surfels_fn(), camera, dataclasses.replace(config, method="tiles"))
    assert_outputs_equal(got, want)
    assert_grads_equal(gg, gw, rtol=grad_rtol)
    return got, gg


def test_edge_on_surfels():
    ortho = Camera.look_at([3.0, 0.0, 0.0], [0.0, 0.0, 0.0], width=9, height=9,
                           ortho_width=0.9)
    persp = Camera.look_at([3.0, 0.0, 0.0], [0.0, 0.0, 0.0], width=9, height=9, fov_x=0.3)

    def one():
        return raw_surfels([[0.0, 0.0, 0.0]], [[math.log(0.1)] * 2], [[1.0, 0.0, 0.0, 0.0]],
                           [0.0])

    for cam in (ortho, persp):
        for k in (2.0, PAIRS.lowpass_inv_var):
            got, _ = both(one, cam, dataclasses.replace(PAIRS, lowpass_inv_var=k))
            assert got["alpha"][4, 4, 0] == pytest.approx(0.5, abs=1e-6)
    # Random surfels turned almost edge-on to their view rays (as the hard-case test).
    edge_on = edge_on_surfels(persp.origin)
    got, _ = both(lambda: raw_surfels(*edge_on), persp.with_size(32, 32))
    assert got["alpha"].max() > 0.5


def test_degenerate_scales_and_near_opaque_stack():
    cam = Camera.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], width=12, height=10, fov_x=0.6)
    bad = [[-np.inf, -np.inf], [-np.inf, math.log(0.1)], [-100.0, -100.0],
           [-88.0, math.log(0.1)], [-120.0, -3.0]]
    pos = [[0.05, 0.0, 0.0]] + [[0.0, 0.02 * i, 0.1] for i in range(len(bad))]
    ls = [[math.log(0.1)] * 2] + bad
    got, g = both(lambda: raw_surfels(pos, ls, [[1.0, 0.2, 0.1, 0.0]] * 6, [1.0] * 6), cam)
    assert np.all(g["position"].reshape(3, 6)[:, 1:] == 0) and got["alpha"].max() > 0.5
    # Saturated opacities (alpha clamped to alpha_max) stacked 8 deep: at the centre the
    # third splat would take T to 5e-5 < transmittance_min (the stop, after 2), towards
    # the edges all 8 are composited; the clamp and the stop are both exercised.
    ortho = Camera.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], width=9, height=9,
                           ortho_width=0.9)
    zs = np.linspace(0.0, -0.7, 8)
    got, g = both(lambda: raw_surfels([[0.01 * i, 0.0, z] for i, z in enumerate(zs)],
                                      [[math.log(0.3)] * 2] * 8, [[1.0, 0.0, 0.0, 0.0]] * 8,
                                      [60.0, 0.0, 60.0, 3.0, 60.0, 60.0, 1.0, 60.0]), ortho)
    assert got["count"][4, 4, 0] == 2 and got["count"].max() == 8
    assert np.abs(g["position"]).max() > 0


def test_1e5_surfels_stacked_on_one_pixel():
    cam, raw = one_pixel_stack(100_000)
    got, _ = both(lambda: raw_surfels(*raw), cam)
    assert got["count"][2, 2, 0] > 1000  # the stop happens deep into the stack


def test_behind_camera_and_near_plane():
    cam = Camera.look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], width=16, height=12, fov_x=1.2)
    raw = random_scene(12, seed=5, extent=0.6, scale=(0.1, 0.4))
    raw["position"][:3, 2] = [2.0, 1.5, 1.1]
    raw["position"][3] = [0.0, 0.0, 0.85]
    raw["position"][4] = [0.05, 0.0, 0.7]  # crosses the near plane: its box is the image
    raw["log_scale"][4] = np.log([0.4, 0.4])
    raw["rotation"][4] = [1.0, 0.6, 0.0, 0.0]
    _, g = both(lambda: to_surfels(raw), cam)
    g = g["position"].reshape(3, -1)
    assert np.all(g[:, :4] == 0) and np.abs(g[:, 4]).max() > 0


def test_far_virtual_camera():
    raw = {k: v.astype(np.float32).astype(np.float64) for k, v in sphere_surfels(3000).items()}
    d = np.array([0.3, 0.5, 0.81])
    d /= np.linalg.norm(d)
    fov = 2 * math.atan(math.tan(math.radians(20)) / 30.0)
    cam = Camera.look_at(75.0 * d, [0, 0, 0], width=48, height=48, fov_x=fov)
    # 75 units away the projected fields' gradients are large and cancel over the pixels
    # of a splat: float32 scatter-adds in two different orders differ by up to 3.2e-5 of
    # the largest position gradient (10 of 9000 entries above 1e-5): 1e-4 here.
    got, _ = both(lambda: to_surfels(raw), cam, grad_rtol=1e-4)
    assert (got["alpha"] > 0.5).sum() > 300


# -- set-up, guards ---------------------------------------------------------------------
def test_nothing_visible_renders_background_with_zero_gradients():
    cam = cameras()["perspective"]
    raw = random_scene(5, 1)
    raw["position"][:, 2] = 5.0  # all behind the camera (it sits at z = 2.6)
    for config in (PAIRS, TILES):
        out, g = render(to_surfels(raw), cam, config, ("alpha", "depth"), BACKGROUND,
                        ("color", "alpha"))
        np.testing.assert_allclose(out["color"], np.broadcast_to(BACKGROUND["color"],
                                                                 (20, 24, 3)), atol=1e-7)
        assert out["alpha"].max() == 0 and all(np.abs(v).max() == 0 for v in g.values())


def test_config_is_validated():
    with pytest.raises(ValueError, match="RasterConfig.method"):
        RasterConfig(method="tile")
    with pytest.raises(ValueError, match="RasterConfig.tile_size"):
        RasterConfig(method="tiles", tile_size=0)
    with pytest.raises(ValueError, match="RasterConfig.pixels_per_lane"):
        RasterConfig(pixels_per_lane=3)


def test_memory_guard_names_the_setting():
    cam = cameras()["perspective"]
    s = to_surfels(random_scene(40, 1))
    small = dataclasses.replace(TILES, memory_budget_bytes=1 << 20)  # below what we hold
    with pytest.raises(RasterMemoryError, match="RasterConfig.memory_budget_bytes"):
        rasterize(s, cam, s.channels, config=small)
    few = dataclasses.replace(TILES, max_pairs=10)
    for v in s.params().values():
        dr.enable_grad(v)
    with pytest.raises(RasterMemoryError, match="RasterConfig.max_pairs=10"):
        rasterize(s, cam, s.channels, config=few)
    # Without gradients, a render whose tiles do not fit falls back to the pair list in
    # bands of rows, which refuses only when one row does not fit (here: 10 pairs).
    with dr.suspend_grad(), pytest.raises(RasterMemoryError, match="one image row holds"):
        rasterize(s, cam, s.channels, config=few)


def test_tiles_grow_when_their_pairs_do_not_fit():
    # Every surfel covers the whole 24 x 20 image: 4x4 tiles make 30 pairs per surfel, 8x8
    # 12, 16x16 4, 32x32 1. A max_pairs of 2 surfels' worth at 16x16 forces 16x16 tiles
    # (then the same image as the pair list); 1 pair per surfel (40) is below every size
    # but the largest, which must still render.
    cam = cameras()["perspective"]
    raw = random_scene(40, 1)
    raw["log_scale"][:] = math.log(50.0)
    aovs = ("alpha", "depth")
    want, _ = render(to_surfels(raw), cam, PAIRS, aovs)
    for max_pairs in (40 * 4, 40):
        got, _ = render(to_surfels(raw), cam, dataclasses.replace(TILES, max_pairs=max_pairs),
                        aovs, grad_outputs=("color",))
        assert_outputs_equal(got, want)


def test_tiles_grown_for_a_tight_budget_render_the_same_bytes(monkeypatch):
    # A forward render over its memory budget (`render --memory-budget`, or the default's
    # share of MemAvailable, which no manifest records) takes larger tiles: a render
    # continued or reused under another budget must be the same bytes, not only close to
    # the pair list. Each pixel composites the same surfels in the same order whatever its
    # tile. (Gradient sums do change with the tiles, at float32 rounding: 2.8e-7 relative
    # on the demo's stage-1 model at 8x8 against 4x4.) max_pairs forces the sizes as a
    # budget would, without depending on this process's memory.
    from mi_shadowgs.core import raster_tiles

    sizes = []
    real = raster_tiles.bin_surfels

    def spy(*args, **kw):
        bins = real(*args, **kw)
        sizes.append(bins.size)
        return bins

    monkeypatch.setattr(raster_tiles, "bin_surfels", spy)
    cam = cameras(64, 48)["perspective"]
    raw = random_scene(300, 4)  # 10016 surfel-tile pairs at 4x4, 3328 at 8x8, 1348, 751, 300
    want, _ = render(to_surfels(raw), cam, TILES, AOVS, BACKGROUND)
    grown = []
    for max_pairs in (5000, 2000, 1000, 500):
        sizes.clear()
        got, _ = render(to_surfels(raw), cam, dataclasses.replace(TILES, max_pairs=max_pairs),
                        AOVS, BACKGROUND)
        grown.append(sizes[-1])
        for k in want:
            np.testing.assert_array_equal(got[k], want[k], err_msg=f"{k} at {sizes[-1]}^2")
    assert grown == [8, 16, 32, 64]  # every size a budget can take


@pytest.mark.parametrize("which", ["channels", "geometry"])
def test_gradients_of_part_of_the_inputs(which):
    # Only the channels (fixed geometry, as the material stage) or only the geometry need
    # gradients: the custom op gets inputs without AD on one side.
    camera = cameras()["perspective"]
    raw = random_scene(40, 2)
    grads = {}
    for config in (PAIRS, TILES):
        s = to_surfels(raw)
        leaf = s.channels["color"] if which == "channels" else s.position
        dr.enable_grad(leaf)
        out = rasterize(s, camera, s.channels, aovs=("alpha", "depth"), config=config)
        dr.backward(dr.sum(out["color"].array * dr.arange(mi.Float, 20 * 24 * 3) / 1e3)
                    + dr.sum(out["depth"].array))
        grads[config.method] = np.array(dr.grad(leaf), np.float64)
    assert np.abs(grads["pairs"]).max() > 0
    assert_grads_equal({"g": grads["tiles"]}, {"g": grads["pairs"]})


def test_forward_mode_is_refused_clearly():
    camera = cameras()["perspective"]
    s = to_surfels(random_scene(10, 1))
    dr.enable_grad(s.position)
    out = rasterize(s, camera, s.channels, config=TILES)
    with pytest.raises(Exception, match="forward-mode derivatives"):
        dr.forward_from(s.position)
        dr.eval(dr.grad(out["color"].array))


def test_packet_widths():
    """The packed layouts of the compositing loops (``core.packed``): powers of two
    up to PACKET_MAX floats, the last zero padded. The test below spans two packets both
    ways: 13 fields, box, surfel id and 6 channel values (16 + 8) and 6 + 13 gradient
    sums (16 + 4)."""
    assert PACKET_MAX == 16
    assert [packet_widths(n) for n in (1, 3, 16, 19, 22, 33)] == [
        [1], [4], [16], [16, 4], [16, 8], [16, 16, 1]]


@pytest.mark.parametrize("count", [1, 5, 16, 20, 33])
def test_packed_values_permuted_and_read_back(count):
    """``Packed.permuted``: entry i of the result is entry index[i] of the original, every
    value of it, across packets; ``column`` and ``read`` agree with the arrays packed."""
    rng = np.random.default_rng(count)
    values = rng.random((count, 50)).astype(np.float32)
    index = rng.permutation(50)[:37].astype(np.uint32)
    packed = Packed.of([mi.Float(v) for v in values])
    moved = packed.permuted(mi.UInt32(index))
    assert moved.size == 37 and moved.count == count
    for k in range(count):
        np.testing.assert_array_equal(moved.column(k).numpy(), values[k, index])
        np.testing.assert_array_equal(packed.column(k).numpy(), values[k])
    read = moved.read(mi.UInt32([3, 0, 36]), 3)
    np.testing.assert_array_equal(np.array([r.numpy() for r in read]),
                                  values[:, index[[3, 0, 36]]])


@pytest.mark.parametrize("n, bound", [(0, 5), (1, 5), (2, 1), (1000, 3), (5000, 1 << 16),
                                      (5000, (1 << 16) + 1), (20000, 1 << 20),
                                      (100, (1 << 32) - 1)])
def test_argsort_bounded_is_a_stable_argsort(n, bound):
    """The binning's and the pair lists' sort of tile and pixel ids: one counting pass up
    to 16 bits of the bound, more above, the order NumPy's stable argsort gives."""
    keys = np.random.default_rng(n).integers(0, bound, n, dtype=np.int64).astype(np.uint32)
    np.testing.assert_array_equal(argsort_bounded(mi.UInt32(keys), bound).numpy(),
                                  np.argsort(keys, kind="stable"))


def test_several_channel_tensors():
    # Two channel tensors of widths 1 and 5 beside the AOVs, one with a background: the
    # loop carries one accumulator per component and the backward one scatter each.
    camera = cameras()["orthographic"]
    raw = random_scene(40, 3)
    extra = np.random.default_rng(4).uniform(-1.0, 1.0, (40, 5)).astype(np.float32)
    grads, outs = {}, {}
    for config in (PAIRS, TILES):
        s = to_surfels(raw)
        chans = {"grey": mi.TensorXf(np.ascontiguousarray(raw["colors"][:, :1], np.float32)),
                 "feat": mi.TensorXf(extra)}
        for t in chans.values():
            dr.enable_grad(t)
        dr.enable_grad(s.position)
        out = rasterize(s, camera, chans, aovs=("alpha",), background={"feat": [0.5] * 5},
                        config=config)
        loss = dr.sum(out["grey"].array) + dr.sum(out["feat"].array *
                                                  dr.arange(mi.Float, 20 * 24 * 5) / 1e3)
        dr.backward(loss)
        outs[config.method] = {k: np.array(v, np.float64) for k, v in out.items()}
        grads[config.method] = {"grey": np.array(dr.grad(chans["grey"]), np.float64),
                                "feat": np.array(dr.grad(chans["feat"]), np.float64),
                                "position": np.array(dr.grad(s.position), np.float64)}
    assert outs["tiles"]["feat"].shape == (20, 24, 5)
    assert_outputs_equal(outs["tiles"], outs["pairs"])
    assert_grads_equal(grads["tiles"], grads["pairs"])
    assert all(np.abs(g).max() > 0 for g in grads["pairs"].values())


def _render_at(surfels, camera, config, pixels, aovs, outputs):
    """Like ``render`` for ``rasterize(..., pixels=)``: outputs [P, C] and the gradients of
    a loss weighting each sample by ``_weights`` of its output row."""
    params = surfels.params()
    for v in params.values():
        dr.enable_grad(v)
    out = rasterize(surfels, camera, surfels.channels, aovs=aovs, config=config,
                    background=BACKGROUND, pixels=pixels)
    loss = mi.Float(0.0)
    for k in outputs:
        loss += dr.sum(out[k].array * mi.Float(_weights(out[k].shape)))
    dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    return ({k: np.array(v, np.float64) for k, v in out.items()},
            {k: np.array(dr.grad(v), np.float64) for k, v in params.items()})


def _weights(shape) -> np.ndarray:
    return np.sin(np.arange(int(np.prod(shape))) * 0.7 + 0.3).astype(np.float32)


@pytest.mark.parametrize("tile_size,per_lane", [(4, 2), (4, 1), (3, 4), (5, 16), (1, 1)])
def test_sampled_pixels_equal_the_image(tile_size, per_lane):
    """rasterize(pixels=): each sampled pixel's outputs are the whole image's, bit for bit
    (the same compositing), and the gradients of a loss over the samples are those of the
    same loss over the image (the samples as weights on its pixels; float32 summation
    order apart). Repeats and every tile's and lane's position are among the samples."""
    camera = cameras()["perspective"]
    raw = random_scene(40, 2)
    aovs = tuple(a for a in AOVS if a != "count")
    outputs = GRAD_CASES[-1]
    config = dataclasses.replace(TILES, tile_size=tile_size, pixels_per_lane=per_lane)
    rng = np.random.default_rng(tile_size)
    npix = camera.width * camera.height
    pixels = np.concatenate([rng.permutation(npix)[:150], rng.integers(0, npix, 60),
                             [0, npix - 1, 5, 5]]).astype(np.uint32)
    image, _ = render(to_surfels(raw), camera, config, aovs, BACKGROUND)
    got, g_got = _render_at(to_surfels(raw), camera, config, pixels, aovs, outputs)
    for k, img in image.items():
        flat = img.reshape(npix, -1)
        np.testing.assert_array_equal(got[k], flat[pixels], err_msg=k)
    # The same loss written on the image: the samples' weights scattered onto their pixels.
    surfels = to_surfels(raw)
    params = surfels.params()
    for v in params.values():
        dr.enable_grad(v)
    out = rasterize(surfels, camera, surfels.channels, aovs=aovs, config=config,
                    background=BACKGROUND)
    loss = mi.Float(0.0)
    for k in outputs:
        c = out[k].shape[2]
        w = np.zeros((npix, c), np.float64)
        np.add.at(w, pixels, _weights((len(pixels), c)).reshape(-1, c))
        loss += dr.sum(out[k].array * mi.Float(w.astype(np.float32).reshape(-1)))
    dr.backward(loss)
    want = {k: np.array(dr.grad(v), np.float64) for k, v in params.items()}
    assert_grads_equal(g_got, want, outputs)


def test_sampled_pixels_pairs_and_checks():
    """The pair list gathers the same pixels from its image (the reference); indices
    outside the image are refused, naming the image size."""
    camera = cameras()["orthographic"]
    raw = random_scene(40, 3)
    pixels = np.array([7, 300, 479, 7], np.uint32)
    aovs = ("alpha", "depth", "normal")
    want, _ = render(to_surfels(raw), camera, PAIRS, aovs, BACKGROUND)
    got = rasterize(to_surfels(raw), camera, to_surfels(raw).channels, aovs=aovs,
                    config=PAIRS, background=BACKGROUND, pixels=pixels)
    for k, img in want.items():
        np.testing.assert_array_equal(np.array(got[k]), img.reshape(480, -1)[pixels], k)
    tiles = rasterize(to_surfels(raw), camera, to_surfels(raw).channels, aovs=aovs,
                      config=TILES, background=BACKGROUND, pixels=mi.UInt32(pixels))
    assert_outputs_equal({k: np.array(v, np.float64) for k, v in tiles.items()},
                         {k: np.array(v, np.float64) for k, v in got.items()})
    for config in (TILES, PAIRS):  # no pixels: empty outputs of the right width
        none = rasterize(to_surfels(raw), camera, to_surfels(raw).channels, aovs=aovs,
                         config=config, pixels=np.zeros(0, np.uint32))
        assert {k: tuple(v.shape) for k, v in none.items()} == \
            {"color": (0, 3), "alpha": (0, 1), "depth": (0, 1), "normal": (0, 3)}
    for bad in (np.array([480], np.uint32), np.array([-1]), np.zeros((2, 2), np.uint32)):
        with pytest.raises(ValueError, match=r"pixels must be flat indices in \[0, 480\) "
                                             r"of the 24x20 image"):
            rasterize(to_surfels(raw), camera, None, aovs=aovs, pixels=bad)
