"""Stage 4 (mi_shadowgs.stages.material, mi_shadowgs.core.shading): kernels and a tiny fit."""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowgs.config import ConfigError, with_overrides
from mi_shadowgs.core import shading
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import light_grid, solid_angle
from mi_shadowgs.core.frames import frame_to_quaternion
from mi_shadowgs.core.raster import rasterize
from mi_shadowgs.core.surfels import Surfels, eval_sh
from mi_shadowgs.presets import material_config as get_config
from mi_shadowgs.stages.material.channels import (
    DETAIL_CHANNEL,
    _clamp_channels,
    albedo_scale_factor,
    detailed_albedo,
    hold_albedo_scale,
    init_channels,
    segment_average,
    segment_ids,
)
from mi_shadowgs.stages.material.config import MaterialConfig, label_source_overrides
from mi_shadowgs.stages.material.fit import (
    detail_gates,
    fit_material,
    fit_result,
    setup_fit,
    start_detail,
)
from mi_shadowgs.stages.material.lights import (
    candidate_directions,
    merge_directions,
    refine_directions,
)
from mi_shadowgs.stages.material.normals import normal_step, start_normal_phase, with_surfel_normals
from mi_shadowgs.stages.material.scoring import _candidate_scores
from mi_shadowgs.stages.material.views import (
    indirect_floor_penalty,
    prepare_view,
    surfel_support,
    view_loss,
    view_maps,
)
from mi_shadowgs.stages.visibility.shadow_maps import (
    SceneBounds,
    VisibilityConfig,
    render_shadow_maps,
)


def test_presets_and_paper_defaults():
    p = get_config("paper")
    assert (p.iterations, p.lambda_ind2, p.lambda_tv, p.lambda_brdf, p.lambda_reg) == \
        (5000, 0.01, 0.01, 1.0, 0.001)
    assert (p.n_directions, p.sh_degree) == (128, 2)
    assert get_config("cpu-small").iterations < p.iterations
    # Not in the paper: the albedo TV across segments and the albedo scale held.
    assert p.albedo_tv_with_segments and p.albedo_scale == 0.0
    with pytest.raises(ValueError, match="albedo_scale"):
        MaterialConfig(albedo_scale=1.5)
    with pytest.raises(ConfigError):
        get_config("nope")
    with pytest.raises(ValueError, match="specular"):
        MaterialConfig(specular="maybe")
    with pytest.raises(ValueError, match="backdrop_surfels"):
        MaterialConfig(backdrop_surfels="drop")
    with pytest.raises(ValueError, match="refine_passes"):
        MaterialConfig(refine_passes=((2.0, 4.0),))
    # a pass's own map resolution: an integer of at least 8 texels
    for bad in ((8.0, 2.0, 4), (8.0, 2.0, 256.5), (8.0, 2.0, 256, 1)):
        with pytest.raises(ValueError, match="map resolution"):
            MaterialConfig(refine_passes=(bad,))
    assert MaterialConfig(refine_passes=((8.0, 2.0, 256), (2.0, 0.5))).refine_passes[0][2] == 256
    # cpu-small's second global pass needs the global pass: not silently dropped
    with pytest.raises(ValueError, match="refine_again_global needs the global pass"):
        dataclasses.replace(get_config("cpu-small"), refine_global=0)
    assert not dataclasses.replace(get_config("cpu-small"), refine_global=0,
                                   refine_again_global=False).refine_global


def test_segment_average_exact():
    rng = np.random.default_rng(3)
    n, k = 1000, 7
    vals = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    seg = rng.integers(0, k, n)
    seg[seg == 4] = 5  # an empty segment id must not break anything
    out = segment_average(
        mi.TensorXf(vals), mi.UInt32(seg.astype(np.uint32)), k
    ).numpy()
    ref = np.zeros_like(vals, dtype=np.float64)
    for s in np.unique(seg):
        ref[seg == s] = vals[seg == s].astype(np.float64).mean(0)
    # float32 sums of ~150 values in [0, 1]: a few ulps of the sum.
    np.testing.assert_allclose(out, ref, rtol=0, atol=2e-6)
    # Idempotent: averaging an averaged field changes nothing.
    again = segment_average(
        mi.TensorXf(out), mi.UInt32(seg.astype(np.uint32)), k
    ).numpy()
    np.testing.assert_allclose(again, out, rtol=0, atol=2e-6)


def test_segment_channel_errors():
    s = _plane_scene()[0]
    del s.channels["segment"]
    with pytest.raises(ValueError, match="segment"):
        segment_ids(s)
    s.channels["segment"] = mi.TensorXf(np.full((s.count, 1), -1.0, np.float32))
    with pytest.raises(ValueError, match="non-negative integer"):
        segment_ids(s)


# -- a tiny synthetic scene: a floor with an occluding tile above it ------------------------
def _grid_surfels(center, half, n, normal, opacity=0.99):
    u = (np.arange(n) + 0.5) / n * 2 - 1
    uu, vv = np.meshgrid(u * half, u * half)
    pos = np.stack([uu.ravel(), np.zeros(n * n), vv.ravel()], -1) + np.asarray(center)
    sigma = 0.8 * 2 * half / n
    return pos, np.full((n * n, 2), sigma), np.tile(normal, (n * n, 1))


def _plane_scene():
    floor = _grid_surfels([0, 0, 0], 1.0, 48, [0, 1, 0])
    tile = _grid_surfels([0.1, 0.45, -0.05], 0.25, 16, [0, 1, 0])
    pos = np.concatenate([floor[0], tile[0]])
    scale = np.concatenate([floor[1], tile[1]])
    nrm = np.concatenate([floor[2], tile[2]])
    seg = np.concatenate([np.zeros(len(floor[0])), np.ones(len(tile[0]))])
    albedo = np.where(seg[:, None] == 0, [[0.6, 0.5, 0.3]], [[0.2, 0.4, 0.7]])
    s = Surfels.from_numpy(
        pos,
        scale,
        frame_to_quaternion(nrm),
        np.full(len(pos), 0.99),
        channels={"segment": seg[:, None].astype(np.float32), "albedo_gt": albedo},
    )
    cams = [
        Camera.look_at(
            np.array([2.2 * math.cos(a), 2.0, 2.2 * math.sin(a)]),
            np.zeros(3),
            fov_x=0.9,
            width=48,
            height=48,
        )
        for a in np.linspace(0, 2 * math.pi, 4, endpoint=False)
    ]
    bounds = SceneBounds((0.0, 0.2, 0.0), 1.5, 3.0)
    return s, cams, bounds


def test_splat_matches_rasterize():
    s, cams, _ = _plane_scene()
    vals = mi.TensorXf(np.random.default_rng(0).uniform(0, 1, (s.count, 4)).astype(np.float32))
    pairs = shading.splat_pairs(s, cams[1])
    got = shading.splat(pairs, vals).numpy()
    ref = rasterize(s, cams[1], {"v": vals}, aovs=())["v"].numpy().reshape(-1)
    # Same pairs and weights; only the summation order of the scatter may differ.
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5)
    assert ref.max() > 0.5


def test_indirect_irradiance_against_numpy():
    rng = np.random.default_rng(2)
    npx = 50
    coef = rng.normal(size=(npx, 27)).astype(np.float32)
    n = rng.normal(size=(npx, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    got = eval_sh(mi.TensorXf(coef), mi.Vector3f(*(n[:, k].astype(np.float32)
                                                   for k in range(3))), offset=0.0).numpy()
    x, y, z = n.T
    c0, c1 = 0.28209479177387814, 0.4886025119029199
    c2 = (
        1.0925484305920792,
        -1.0925484305920792,
        0.31539156525252005,
        -1.0925484305920792,
        0.5462742152960396,
    )
    basis = np.stack(
        [
            np.full(npx, c0),
            -c1 * y,
            c1 * z,
            -c1 * x,
            c2[0] * x * y,
            c2[1] * y * z,
            c2[2] * (2 * z * z - x * x - y * y),
            c2[3] * x * z,
            c2[4] * (x * x - y * y),
        ],
        -1,
    )
    ref = np.maximum(np.einsum("pk,pkc->pc", basis, coef.reshape(npx, 9, 3).astype(np.float64)), 0)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)


def _render_truth(s, cams, bounds, directions, irradiance, vcfg):
    """Targets rendered by the model itself with the true albedo and lights ([L, 3] or [3]
    directions, [L] or scalar irradiance)."""
    d = np.atleast_2d(np.asarray(directions, np.float64))
    maps = render_shadow_maps(s, d, bounds, vcfg)
    e = mi.Float(np.broadcast_to(np.asarray(irradiance, np.float32), len(d)))
    lights = shading.LightSet(d, mi.Color3f(e, e, e))
    truth = dict(s.channels)
    truth["albedo"] = s.channels["albedo_gt"]
    imgs, masks = [], []
    for cam in cams:
        pairs = shading.splat_pairs(s, cam)
        geom = shading.pixel_geometry(s, cam)
        a = shading.splat(pairs, truth["albedo"])
        albedo = mi.Color3f(*(shading.channel(a, 3, c) for c in range(3)))
        zero = dr.zeros(mi.Float, dr.width(geom.alpha))
        vis = maps.evaluate(geom.points, geom.normal, geom.footprint)
        rgb = shading.shade(geom, albedo, zero + 1.0, zero, lights, vis, None, False)
        imgs.append(
            np.stack([np.asarray(rgb[c]) for c in range(3)], -1).reshape(cam.height, cam.width, 3)
        )
        masks.append(geom.alpha.numpy().reshape(cam.height, cam.width) > 0.5)
    return imgs, masks


def test_tiny_decomposition_recovers_albedo_and_light():
    """Floor + occluding tile, one light on a grid direction, no indirect light.

    Albedo (up to the global albedo x light scale) and the light direction must come back:
    the shadow of the tile on the floor is what pins the direction down.
    """
    s, cams, bounds = _plane_scene()
    vcfg = VisibilityConfig(resolution=128)
    k_true = int(np.argmin(np.abs(light_grid(128)[:, 1] - 0.75)))  # ~49 degrees elevation
    e_true = 2.0
    imgs, masks = _render_truth(s, cams, bounds, light_grid(128)[k_true], e_true, vcfg)
    cfg = with_overrides(
        get_config("cpu-small"),
        {"iterations": 250, "warmup": 80, "specular": "off", "log_every": 50},
        "material",
    )
    # One thread: with more, float atomics add in a varying order, and this unconverged fit
    # amplifies that (a fresh clone once measured ratio[0] 1.54 where this one gives 2.4).
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        res = fit_material(s, cams, imgs, masks, cfg, bounds, vcfg,
                           progress=False)
    finally:
        dr.set_thread_count(threads)
    # Light: the true direction dominates the fitted map.
    gt_map = np.zeros(128)
    gt_map[k_true] = e_true / solid_angle(128)
    est = res.light.radiance
    cos = est @ gt_map / (np.linalg.norm(est) * np.linalg.norm(gt_map))
    # Neighbouring grid directions cast nearly the same shadow at 40 px: 0.6 still means the
    # peak is at the right place (a wrong direction gives < 0.2).
    assert cos > 0.6, cos
    assert int(np.argmax(est)) == k_true
    # Pruning dropped most of the 128 directions.
    assert len(res.light.active) < 40
    # The light log: the warm-up's pruning first (at its step), the final lights last.
    log = res.light.active, res.light_log
    assert res.light_log[0]["event"] == "prune" and res.light_log[0]["step"] == 80, log
    assert len(res.light_log[-1]["directions"]) == len(res.light.directions), log
    # Albedo: one segment-constant value each; their per-channel ratio is scale-free.
    a = res.surfels.channels["albedo"].numpy()
    seg = res.surfels.channels["segment"].numpy()[:, 0]
    a0, a1 = a[seg == 0].mean(0), a[seg == 1].mean(0)
    assert np.ptp(a[seg == 0], axis=0).max() < 1e-6  # the hard constraint holds exactly
    ratio, ratio_true = a0 / a1, np.array([0.6, 0.5, 0.3]) / np.array([0.2, 0.4, 0.7])
    # 250 steps of a 4-view 32 px fit are not converged (L1 ~0.02, measured ratio on one
    # thread [2.73, 1.22, 0.49] vs [3, 1.25, 0.43]): the colours must separate the right way
    # (with the indirect light fitted from step 0 they did not: ratio [1, 1, 1]).
    assert ratio[0] > 2.0 and 0.85 < ratio[1] < 1.5 and ratio[2] < 0.8, (ratio, ratio_true)
    assert res.history[-1][1] < 0.5 * res.history[0][1]  # the loss went down


def test_merge_directions_recovers_an_off_grid_light():
    """A light between grid directions, fitted as its neighbours' energies, merges back to
    (nearly) its own direction; lights far apart stay apart."""
    grid = light_grid(128)
    a = 40
    b = int(np.argsort(-(grid @ grid[a]))[1])  # a's nearest neighbour on the grid
    # The light sits between them; a fit spreads its energy over the two in proportion.
    w = np.array([0.6, 0.4])
    true = w[0] * grid[a] + w[1] * grid[b]
    true /= np.linalg.norm(true)
    near = np.array([a, b])
    cos = grid @ true
    far = grid[np.argmin(cos)]  # the grid direction farthest from the light
    dirs = np.concatenate([grid[near], far[None]])
    energy = np.concatenate([w * 10.0, [1.0]])
    merged, e = merge_directions(dirs, energy, 20.0)
    assert len(merged) == 2
    # Weighted mean of unit vectors, renormalised: exact for the least-squares weights.
    assert np.degrees(np.arccos(np.clip(merged[0] @ true, -1, 1))) < 0.01
    assert np.allclose(merged[1], far) and math.isclose(e[1], 1.0)
    assert math.isclose(e.sum(), energy.sum())
    # Nothing merges when the angle is below the grid spacing (~13 degrees).
    assert len(merge_directions(dirs, energy, 5.0)[0]) == len(dirs)


def test_candidate_directions_grid():
    d = light_grid(128)[60]
    cand = candidate_directions(d, 8.0, 2.0)
    assert np.allclose(cand[0], d)  # the current direction is a candidate (ties keep it)
    np.testing.assert_allclose(np.linalg.norm(cand, axis=1), 1.0, atol=1e-12)
    ang = np.degrees(np.arccos(np.clip(cand @ d, -1, 1)))
    # The grid is gnomonic: the angle of (i, j) steps is atan(hypot(tan i s, tan j s)) <=
    # the radius, and the axis neighbours sit exactly one step away.
    assert ang.max() <= 8.0 + 1e-9 and len(cand) == 1 + sum(
        1 for i in range(-4, 5) for j in range(-4, 5) if (i or j) and math.hypot(i, j) <= 4
    )
    assert np.isclose(np.sort(ang)[1], 2.0)
    # A light at the horizon keeps only the candidates above it.
    low = candidate_directions(np.array([1.0, 0.01, 0.0]), 8.0, 2.0)
    assert (low[:, 1] > 0).all() and 0 < len(low) < len(cand)
    # ...and one exactly on it keeps at least itself.
    flat = candidate_directions(np.array([1.0, 0.0, 0.0]), 8.0, 2.0)
    assert np.allclose(flat[0], [1.0, 0.0, 0.0]) and (flat[1:, 1] > 0).all()


def _one_light_views(s, cams, bounds, direction, irradiance, vcfg):
    """Training views of ``s`` (true albedo, no indirect light) under one directional light,
    with the channels that produced them."""
    d = np.asarray(direction, np.float64)[None]
    maps = render_shadow_maps(s, d, bounds, vcfg)
    e = mi.Float(float(irradiance))
    lights = shading.LightSet(d, mi.Color3f(e, e, e))
    n = s.count
    ch = {
        "albedo": s.channels["albedo_gt"],
        "roughness": mi.TensorXf(np.ones((n, 1), np.float32)),
        "metallic": mi.TensorXf(np.zeros((n, 1), np.float32)),
    }
    cfg = get_config("cpu-small")
    views = []
    for cam in cams:
        geom = shading.pixel_geometry(s, cam)
        albedo, rough, metal, _ = view_maps(
            shading.splat_pairs(s, cam), ch, shading.facing_normals(s, cam)
        )
        rgb = shading.shade(
            geom,
            albedo,
            rough,
            metal,
            lights,
            maps.evaluate(geom.points, geom.normal, geom.footprint),
            None,
            False,
        )
        img = np.stack([np.asarray(rgb[c]) for c in range(3)], -1)
        mask = geom.alpha.numpy() > 0.5
        views.append(
            prepare_view(
                s,
                cam,
                img.reshape(cam.height, cam.width, 3),
                mask.reshape(cam.height, cam.width),
                cfg,
            )
        )
    return views, ch


def test_refine_directions_recovers_a_light_between_grid_directions():
    """The grid search moves a light that starts 6 degrees off back onto the true direction
    (the tile's shadow on the floor and the floor's n . l pin it), and refits its
    irradiance; the true direction scores ~0 under the "segment" score (the views are
    rendered by it) and near its floor under cpu-small's "albedo" score.

    On two threads this failed 2 runs of 16: with one light the albedo score
    is flat in E, and round-off (one pixel's last bit, from a float atomic's order in the
    albedo splat) chose E, and with it the score (``albedo_errors``)."""
    from mi_shadowgs.core.directions import direction_from_angles

    s, _, bounds = _plane_scene()
    cams = [
        Camera.look_at(
            np.array([2.2 * math.cos(a), 2.0, 2.2 * math.sin(a)]),
            np.zeros(3),
            fov_x=0.9,
            width=64,
            height=64,
        )
        for a in np.linspace(0, 2 * math.pi, 4, endpoint=False)
    ]
    vcfg = VisibilityConfig(resolution=256, projection="orthographic")
    true = direction_from_angles(47.0, 52.0)
    views, ch = _one_light_views(s, cams, bounds, true, 2.0, vcfg)
    start = direction_from_angles(52.0, 48.0)
    assert np.degrees(np.arccos(start @ true)) > 5.0

    def render(dirs, resolution=None):
        return render_shadow_maps(s, dirs, bounds, vcfg, resolution)

    cfg = get_config("cpu-small")
    assert cfg.refine_score == "albedo"
    lights = shading.LightSet(start[None], mi.Color3f(1.5))
    maps, cand = render(start[None]), render(np.stack([true, start]))

    def scores(config):
        return _candidate_scores(views, ch, lights, maps, 0, cand, config, False)

    # "segment" (the fitted albedo, here the true one): round-off only, float32 sums per
    # view; the error s_rr - 2 E s_rb + E^2 s_bb cancels to ~1e-6 of s_rr.
    err, fit = scores(dataclasses.replace(cfg, refine_score="segment"))
    assert err[0] < 1e-4 * err[1] and abs(fit[0] - 2.0) < 1e-3, (err, fit)
    # "albedo" (one albedo per segment and channel): no other light, so it holds whatever
    # E. Its floor at the truth (1.0e-3 of err[1]) is the ~60 pixels whose purity is
    # 0.9-0.99: they blend the two segments' albedos (5e-5 at purity 0.99).
    err, fit = scores(cfg)
    assert 5e-4 * err[1] < err[0] < 2e-3 * err[1] and abs(fit[0] - 2.0) < 1e-3, (err, fit)
    dirs, irr = refine_directions(
        views, ch, start[None], np.array([1.5]), render(start[None]), render, cfg, False
    )
    ang = np.degrees(np.arccos(np.clip(dirs[0] @ true, -1, 1)))
    # The fine pass steps by 0.5 degrees: the optimum is within half a step per axis.
    assert ang < 0.5, ang
    assert abs(irr[0] - 2.0) < 0.05 * 2.0, irr


def test_overrides_reach_nested_settings():
    """A stage's nested config (the rasterizer's) takes its own dict of overrides, checked
    like the top level, instead of being replaced by a dict that fails much later."""
    from mi_shadowgs.presets import geometry_config

    cfg = with_overrides(
        geometry_config("cpu-small"),
        {"iterations": 10, "raster": {"lowpass_inv_var": 8.0}},
        "geometry",
    )
    assert cfg.iterations == 10 and cfg.raster.lowpass_inv_var == 8.0
    assert cfg.raster.alpha_max == geometry_config("cpu-small").raster.alpha_max
    with pytest.raises(ConfigError, match=r"geometry\.raster.*lowpass"):
        with_overrides(geometry_config("cpu-small"), {"raster": {"lowpass": 8.0}}, "geometry")
    with pytest.raises(ConfigError, match="takes a dict"):
        with_overrides(geometry_config("cpu-small"), {"raster": 8.0}, "geometry")


@pytest.mark.parametrize("field, value, message", [
    ("refine_again_global", "false", "takes True or False"),  # a truthy string
    ("refine_again_global", 0, "takes True or False"),
    ("refine_global", "128", "takes a number"),
    ("refine_global", True, "takes a number"),
])
def test_overrides_of_the_wrong_type_are_refused_by_name(field, value, message):
    """``refine_again_global="false"`` from a command line once replaced the switch with a
    truthy string, silently keeping it on."""
    with pytest.raises(ConfigError, match=f"{field}.*{message}"):
        with_overrides(get_config("cpu-small"), {field: value}, "material")
    ok = with_overrides(get_config("cpu-small"),
                        {"refine_again_global": False, "refine_global": 64}, "material")
    assert ok.refine_again_global is False and ok.refine_global == 64


def test_hold_albedo_scale_keeps_the_diffuse_image_and_sets_the_albedo():
    """The albedo x light (and albedo x indirect) scale: scaling the albedo to the held value
    and the light and indirect by the inverse leaves the rendered diffuse image as it was
    (float32 rounding only), and the largest albedo (quantile 1) at that value."""
    s, cams, bounds = _plane_scene()
    vcfg = VisibilityConfig(resolution=64)
    d = light_grid(128)[int(np.argmin(np.abs(light_grid(128)[:, 1] - 0.75)))]
    maps = render_shadow_maps(s, d[None], bounds, vcfg)
    cfg = get_config("cpu-small")
    ch = init_channels(s, cfg)
    rng = np.random.default_rng(3)
    alb = rng.uniform(0.3, 0.99, (s.count, 3)).astype(np.float32)
    ch["albedo"] = mi.TensorXf(alb)
    ind = ch[shading.INDIRECT_CHANNEL]
    ch[shading.INDIRECT_CHANNEL] = mi.TensorXf(
        rng.uniform(0.0, 0.3, ind.shape).astype(np.float32))
    opt = mi.ad.Adam(lr=0.1)
    dw = solid_angle(128)
    opt["log_light"] = mi.Float(np.log(np.full(1, 2.5 / dw, np.float32)))  # irradiance 2.5

    def image(ch):
        e = dr.exp(dr.detach(opt["log_light"])) * dw
        lights = shading.LightSet(d[None], mi.Color3f(e, e, e))
        cam = cams[1]
        pairs = shading.splat_pairs(s, cam)
        geom = shading.pixel_geometry(s, cam)
        albedo, rough, metal, ind = view_maps(pairs, ch,
                                              shading.facing_normals(s, cam))
        vis = maps.evaluate(geom.points, geom.normal, geom.footprint)
        rgb = shading.shade(geom, albedo, rough, metal, lights, vis, ind, False)
        return np.stack([np.asarray(rgb[c], np.float64) for c in range(3)], -1)

    before = image(ch)
    support = np.ones(s.count)
    held = dataclasses.replace(cfg, albedo_scale=0.8, albedo_scale_quantile=1.0)
    hold_albedo_scale(ch, opt, albedo_scale_factor(
        ch["albedo"].numpy(), support, held))
    after = image(ch)
    assert ch["albedo"].numpy().max() == pytest.approx(0.8, rel=1e-6)
    np.testing.assert_allclose(ch["albedo"].numpy(), alb * (0.8 / alb.max()), rtol=1e-6)
    # float32: a few ulps (exp, log and the scale each round once).
    np.testing.assert_allclose(after, before, rtol=1e-5, atol=1e-7)
    assert before.max() > 0.5  # a lit image, not an empty one
    # Held both ways: an albedo below the value is brought up to it.
    a0 = ch["albedo"].numpy()
    up = dataclasses.replace(held, albedo_scale=0.9)
    hold_albedo_scale(ch, opt, albedo_scale_factor(a0, support, up))
    np.testing.assert_allclose(ch["albedo"].numpy(), a0 * (0.9 / 0.8), rtol=1e-6)
    np.testing.assert_allclose(image(ch), before, rtol=1e-5, atol=1e-7)


def test_albedo_scale_is_not_set_by_a_few_percent_of_the_support_at_the_box():
    """The ficus at stage-1 seed 1, per segment: support share and brightest
    albedo channel. Two small segments around the pot, with little direct light in the
    model, ran to the box with 1.65% of the support; the hold must follow the base (91%),
    not them: at the 0.99 quantile they held it and the light ran 7x too bright."""
    shares = np.array([0.9125, 0.0207, 0.0209, 0.0091, 0.0295, 0.0074])
    top = np.array([0.135, 0.011, 0.007, 0.863, 0.014, 0.963])
    counts = np.array([1500, 250, 270, 170, 270, 440])  # surfels per segment
    albedo = np.repeat(top, counts)[:, None] * np.ones(3)
    support = np.repeat(shares / counts, counts)
    cfg = get_config("cpu-small")
    assert albedo_scale_factor(albedo, support, cfg) == pytest.approx(0.9 / 0.135)
    old = dataclasses.replace(cfg, albedo_scale_quantile=0.99)
    assert albedo_scale_factor(albedo, support, old) == pytest.approx(0.9 / 0.863)


def test_albedo_scale_is_set_by_what_the_views_see():
    """A bright segment no view supervises (surfels under the base) must not set the
    albedo scale: the quantile is weighted by each surfel's blending weight in the views."""
    s, cams, _ = _plane_scene()
    cfg = with_overrides(get_config("cpu-small"), {"specular": "off"}, "material")
    views = [prepare_view(s, c, np.zeros((c.height, c.width, 3)),
                          np.ones((c.height, c.width), bool), cfg) for c in cams]
    support = surfel_support(views, s.count)
    # Against a float64 sum over the pair lists.
    want = np.zeros(s.count)
    for v in views:
        sup = v.weight.numpy()[v.pairs.pix.numpy()]
        np.add.at(want, v.pairs.sid.numpy(), v.pairs.weight.numpy() * sup)
    np.testing.assert_allclose(support, want, rtol=1e-5, atol=1e-6)
    albedo = np.full((s.count, 3), 0.3)
    albedo[:, 0] = 0.45  # the brightest channel: 0.45 everywhere seen
    hidden = np.zeros(s.count, bool)
    hidden[:40] = True
    albedo[hidden] = 0.99
    support[hidden] = 0.0  # as surfels below the floor
    held = dataclasses.replace(cfg, albedo_scale=0.9)
    assert albedo_scale_factor(albedo, support, held) == pytest.approx(2.0)
    # Unweighted, 40 of the surfels would be past the 0.99 quantile and set it.
    flat = dataclasses.replace(held, albedo_scale_quantile=1.0)
    assert albedo_scale_factor(albedo, np.ones(s.count), flat) == \
        pytest.approx(0.9 / 0.99)


def test_albedo_tv_across_segments_only_where_configured():
    """With the segment constraint the albedo is constant per segment, so its TV is only
    the pull across segment borders: ``albedo_tv_with_segments=False`` drops it (the loss is
    then the same for any pair of segment colours with the same image error), and without
    the segment constraint (the ablation) the TV applies either way."""
    s, cams, bounds = _plane_scene()
    cam = cams[0]
    cfg = with_overrides(get_config("cpu-small"),
                         {"specular": "off", "albedo_tv_with_segments": True}, "material")
    target = np.full((cam.height, cam.width, 3), 0.3, np.float32)
    view = prepare_view(s, cam, target, np.ones((cam.height, cam.width), bool),
                        cfg)
    ch = init_channels(s, cfg)
    del ch[shading.INDIRECT_CHANNEL]
    seg = s.channels["segment"].numpy()[:, 0]
    d = light_grid(128)[int(np.argmin(np.abs(light_grid(128)[:, 1] - 0.75)))]
    e = mi.Float(2.0)
    lights = shading.LightSet(d[None], mi.Color3f(e, e, e))

    def loss(c, albedo):
        ch["albedo"] = mi.TensorXf(np.where(seg[:, None] == 0, albedo[0], albedo[1])
                                   .astype(np.float32))
        return float(view_loss(view, ch, lights, None, c, False)[0])

    same, apart = [[0.4] * 3, [0.4] * 3], [[0.4] * 3, [0.9, 0.1, 0.4]]
    no_tv = dataclasses.replace(cfg, albedo_tv_with_segments=False)
    l1_only = dataclasses.replace(cfg, lambda_brdf=0.0)
    ablation = dataclasses.replace(no_tv, segment_average=False)
    for albedo in (same, apart):
        # Off: the image term alone. The ablation keeps the TV whatever the flag says.
        assert loss(no_tv, albedo) == pytest.approx(loss(l1_only, albedo), rel=1e-6)
        assert loss(ablation, albedo) == pytest.approx(loss(cfg, albedo), rel=1e-6)
    # On: the TV grows with the colour difference across the tile's border (one albedo
    # everywhere still has TV at the silhouettes, where the blended albedo falls off).
    tv_same = loss(cfg, same) - loss(l1_only, same)
    tv_apart = loss(cfg, apart) - loss(l1_only, apart)
    assert tv_apart > tv_same + 1e-3, (tv_apart, tv_same)


def _sh2_reference(n: np.ndarray) -> np.ndarray:
    """The 9 real SH basis values of degree 2 (3DGS's signs) [N, 9], float64, from the
    textbook constants."""
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    c0, c1 = 0.5 / math.sqrt(math.pi), math.sqrt(3.0 / (4.0 * math.pi))
    c2, c3, c4 = (0.5 * math.sqrt(15.0 / math.pi), 0.25 * math.sqrt(5.0 / math.pi),
                  0.25 * math.sqrt(15.0 / math.pi))
    return np.stack([np.full_like(x, c0), -c1 * y, c1 * z, -c1 * x, c2 * x * y, -c2 * y * z,
                     c3 * (2 * z * z - x * x - y * y), -c2 * x * z, c4 * (x * x - y * y)], -1)


def test_indirect_sh_is_evaluated_per_surfel_at_its_camera_facing_normal():
    """facing_normals flips each surfel's normal toward the camera as the rasterizer does
    (its rendered normal at a one-surfel pixel), and eval_sh at offset 0 is max(0, SH(n))
    per surfel against a float64 reference; its gradient is the basis where unclamped."""
    rng = np.random.default_rng(5)
    n = 40
    q = rng.standard_normal((n, 4))
    s = Surfels.from_numpy(rng.uniform(-0.5, 0.5, (n, 3)), np.full((n, 2), 0.05), q,
                           np.full(n, 0.9))
    cam = Camera.look_at([1.5, 1.2, 2.0], [0, 0, 0], fov_x=0.8, width=32, height=32)
    nrm = shading.facing_normals(s, cam)
    got_n = np.stack([np.asarray(nrm[c], np.float64) for c in range(3)], -1)
    _, _, axis = s.tangent_frame()
    axis = np.stack([np.asarray(axis[c], np.float64) for c in range(3)], -1)
    pos = s.to_numpy()["position"]
    facing = np.sum(axis * (np.asarray(cam.origin) - pos), -1) >= 0
    np.testing.assert_allclose(got_n, np.where(facing[:, None], axis, -axis), atol=1e-6)
    one = Surfels.from_numpy(pos[:1], np.full((1, 2), 0.3), q[:1], np.full(1, 0.99))
    img = rasterize(one, cam, None, aovs=("alpha", "normal"))
    a = np.asarray(img["alpha"].array).reshape(-1)
    rendered = np.asarray(img["normal"].array).reshape(-1, 3)[a.argmax()] / a.max()
    np.testing.assert_allclose(rendered, got_n[0], atol=1e-4)

    sh = rng.normal(0.0, 0.3, (n, 27)).astype(np.float32)
    sh_t = mi.TensorXf(sh)
    dr.enable_grad(sh_t)
    irr = eval_sh(sh_t, nrm, offset=0.0)
    basis = _sh2_reference(got_n)  # [N, 9]
    want = np.maximum(np.einsum("nk,nkc->nc", basis, sh.astype(np.float64).reshape(n, 9, 3)),
                      0.0)
    np.testing.assert_allclose(irr.numpy(), want, atol=1e-6)
    assert (want > 0).any() and (want == 0).any()  # both sides of the clamp are tested
    dr.backward(dr.sum(irr.array))
    grad = dr.grad(sh_t).numpy().reshape(n, 9, 3)
    np.testing.assert_allclose(grad, basis[:, :, None] * (want > 0)[:, None, :], atol=1e-6)

    # Unclamped (floor None): SH(n) itself. On the clamp itself (SH(n) = 0 exactly: the DC
    # term alone, at 0) the gradient is the one from above, as for any value over it.
    raw = np.einsum("nk,nkc->nc", basis, sh.astype(np.float64).reshape(n, 9, 3))
    np.testing.assert_allclose(eval_sh(mi.TensorXf(sh), nrm, 0.0, None).numpy(), raw,
                               atol=1e-6)
    zero = mi.TensorXf(np.zeros((n, 27), np.float32))
    dr.enable_grad(zero)
    dr.backward(dr.sum(eval_sh(zero, nrm, offset=0.0).array))
    np.testing.assert_allclose(dr.grad(zero).numpy().reshape(n, 9, 3), basis[:, :, None]
                               * np.ones((1, 1, 3)), atol=1e-6)

    # The floor's pull (lambda_ind_floor): mean of min(SH(n), 0)^2 against the float64
    # reference; its gradient reaches exactly the clamped values, and raises them.
    sh_t = mi.TensorXf(sh)
    dr.enable_grad(sh_t)
    pen = indirect_floor_penalty(sh_t, nrm)
    np.testing.assert_allclose(pen[0], np.mean(np.minimum(raw, 0.0) ** 2), rtol=1e-5)
    dr.backward(pen)
    grad = dr.grad(sh_t).numpy().reshape(n, 9, 3)
    want_grad = 2.0 * np.minimum(raw, 0.0)[:, None, :] * basis[:, :, None] / raw.size
    np.testing.assert_allclose(grad, want_grad, atol=1e-7)
    # a small step against it raises every clamped value and leaves the others
    step = sh - 1e-1 * grad.reshape(n, 27) / np.abs(grad).max()
    after = np.einsum("nk,nkc->nc", basis, step.astype(np.float64).reshape(n, 9, 3))
    assert np.all(after[raw < 0] > raw[raw < 0]) and np.allclose(after[raw > 0], raw[raw > 0])


def _tilted_tile_truth():
    """The floor + tile scene whose tile is shaded with normals tilted 25 degrees about x
    (its geometry flat), one light at 50 degrees elevation: what the normal phase must find."""
    from mi_shadowgs.core.directions import direction_from_angles

    s, cams, bounds = _plane_scene()
    seg = s.channels["segment"].numpy()[:, 0]
    # The floor as stage 2 leaves a planar segment: its shading normal its plane's (here 1
    # degree off its surfels' rotation normals), which the phase holds.
    flat = math.radians(1.0)
    start = np.tile([0.0, 1.0, 0.0], (s.count, 1))
    start[seg == 0] = [math.sin(flat), math.cos(flat), 0.0]
    tilt = math.radians(25.0)
    normals = start.copy()
    normals[seg == 1] = [0.0, math.cos(tilt), math.sin(tilt)]
    truth = s.with_channels({shading.SHADING_NORMAL_CHANNEL:
                             mi.TensorXf(normals.astype(np.float32))})
    s = s.with_channels({shading.SHADING_NORMAL_CHANNEL: mi.TensorXf(start.astype(np.float32))})
    light = direction_from_angles(60.0, 50.0)
    vcfg = VisibilityConfig(resolution=128)
    imgs, masks = _render_truth(truth, cams, bounds, light, 2.0, vcfg)
    return s, cams, bounds, vcfg, imgs, masks, light, normals, seg


def test_surfel_normals_blend_as_the_rasterizer_blends_them():
    """The normal phase's pixel normals (a splat of the per-surfel normals facing the camera)
    are the rasterizer's normal image where nothing moved: one code path for both."""
    s, cams, _ = _plane_scene()
    rng = np.random.default_rng(4)
    n = rng.normal(size=(s.count, 3)) + [0.0, 3.0, 0.0]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    s = s.with_channels({shading.SHADING_NORMAL_CHANNEL: mi.TensorXf(n.astype(np.float32))})
    cfg = get_config("cpu-small")
    for cam in cams[:2]:
        view = prepare_view(s, cam, np.zeros((48, 48, 3)), np.ones((48, 48)), cfg)
        got = with_surfel_normals(
            view, shading.unit_rows(s.channels[shading.SHADING_NORMAL_CHANNEL]),
            s.position).geom.normal
        ref = view.geom.normal  # the rasterizer's blended shading normals, normalised
        np.testing.assert_allclose(np.stack([np.asarray(got[k]) for k in range(3)], -1),
                                   np.stack([np.asarray(ref[k]) for k in range(3)], -1),
                                   atol=2e-5)


def test_normal_phase_finds_the_shading_the_geometry_lacks():
    """Lights and albedo as the truth's, the tile's geometry flat but its shading tilted: the
    normal phase must bring the tile's n . l to the truth's (what one light identifies) and
    leave the floor's normals where they were."""
    s, cams, bounds, vcfg, imgs, masks, light, normals, seg = _tilted_tile_truth()
    cfg = dataclasses.replace(get_config("cpu-small"), iterations=0, warmup=0,
                              normal_steps=300, log_every=50)
    fit, state = setup_fit(s, cams, imgs, masks, cfg, bounds, vcfg,
                           progress=False)
    e = 2.0
    state.directions = light[None]
    state.opt["log_light"] = mi.Float(math.log(e / solid_angle(cfg.n_directions)))
    state.opt["albedo"] = s.channels["albedo_gt"]
    state.channels[shading.INDIRECT_CHANNEL] = mi.TensorXf(
        np.zeros(state.channels[shading.INDIRECT_CHANNEL].shape, np.float32))
    fit.maps = fit.shadow_maps(state.directions)
    start_normal_phase(fit, state)
    assert set(state.opt.keys()) == {"log_light", shading.SHADING_NORMAL_CHANNEL}
    while state.step < cfg.normal_steps:
        normal_step(fit, state)
    res = fit_result(fit, state)
    got = res.surfels.channels[shading.SHADING_NORMAL_CHANNEL].numpy()
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)
    # The light is held: the phase moves the normals only.
    np.testing.assert_allclose(res.light.weights, e, rtol=1e-6)
    # The tile's n . l: 0.77 flat, 0.46 tilted; the phase must close most of the gap (0.02
    # left, measured).
    tile = seg == 1
    before = abs(np.mean(normals[tile] @ light) - light[1])
    after = abs(np.mean(got[tile] @ light) - np.mean(normals[tile] @ light))
    assert before > 0.1 and after < 0.25 * before, (before, after)
    # The floor is held exactly: stage 2 flattened it.
    np.testing.assert_allclose(got[~tile], normals[~tile], atol=1e-6)
    assert state.history[-1][1] < 0.5 * state.history[0][1], state.history
    # Not held, the floor's pixels are explained already: its normals stay near (the prior).
    fit.config = dataclasses.replace(cfg, normal_hold_planar=False)
    fit.start_normals = fit.held_normals = None
    start_normal_phase(fit, state)
    state.step = 0
    while state.step < 100:
        normal_step(fit, state)
    free = fit_result(fit, state).surfels.channels[
        shading.SHADING_NORMAL_CHANNEL].numpy()
    floor_err = np.degrees(np.arccos(np.clip(np.sum(free[~tile] * normals[~tile], 1), -1, 1)))
    assert 0.0 < np.percentile(floor_err, 90) < 2.0, np.percentile(floor_err, [50, 90, 99])


def test_normal_phase_settings_are_checked_and_off_in_the_paper():
    assert get_config("paper").normal_steps == 0
    assert get_config("cpu-small").normal_steps > 0
    for bad in ({"normal_steps": -1}, {"lr_normal": 0.0}, {"lambda_normal_prior": -1.0}):
        with pytest.raises(ValueError, match="normal_steps >= 0"):
            MaterialConfig(**bad)


def test_a_pixel_covered_in_part_shades_its_surface_not_a_diluted_one():
    """Hard case (silhouettes): pixel 0 is covered whole by surfel 0, pixel 1 to 0.6 by
    surfel 1 of the same material. The albedo carries the coverage (the photo's colour is
    premultiplied); roughness, metallic and the indirect irradiance are the surface's own.
    Blended as the albedo, pixel 1 was a smoother (0.18), less metallic (0.6) surface with
    0.6^2 of its indirect light. Float64 by hand."""
    pairs = shading.SplatPairs(mi.UInt32([0, 1]), mi.UInt32([0, 1]), mi.Float([1.0, 0.6]),
                               1, 2)
    dc = np.array([0.4, 0.2, 0.1])
    channels = {"albedo": mi.TensorXf(np.full((2, 3), 0.5, np.float32)),
                "roughness": mi.TensorXf(np.full((2, 1), 0.3, np.float32)),
                "metallic": mi.TensorXf(np.ones((2, 1), np.float32)),
                shading.INDIRECT_CHANNEL: mi.TensorXf(np.tile(dc, (2, 1)).astype(np.float32))}
    normals = mi.Vector3f([0.0, 0.0], [1.0, 1.0], [0.0, 0.0])
    albedo, rough, metal, ind = view_maps(pairs, channels, normals, True)
    np.testing.assert_allclose(np.array(albedo), [[0.5, 0.3]] * 3, rtol=1e-6)  # [3, pixels]
    np.testing.assert_allclose(np.array(rough), [0.3, 0.3], rtol=1e-6)
    np.testing.assert_allclose(np.array(metal), [1.0, 1.0], rtol=1e-6)
    sh_c0 = 0.28209479177387814  # the DC basis function
    np.testing.assert_allclose(np.array(ind), np.tile(sh_c0 * dc[:, None], (1, 2)), rtol=1e-6)
    # An empty pixel stays 0 (no division by its zero coverage).
    empty = shading.SplatPairs(mi.UInt32([0]), mi.UInt32([0]), mi.Float([1.0]), 1, 2)
    _, rough, metal, ind = view_maps(empty, channels, normals, True)
    assert np.array(rough)[1] == 0 and np.array(metal)[1] == 0 and not np.array(ind)[:, 1].any()


def _detail_view():
    """The plane scene's first view with a flat target, its channels (no indirect light)
    with a random albedo detail, and one light."""
    s, cams, _ = _plane_scene()
    cam = cams[0]
    cfg = with_overrides(get_config("cpu-small"), {"specular": "off"}, "material")
    target = np.full((cam.height, cam.width, 3), 0.3, np.float32)
    view = prepare_view(s, cam, target, np.ones((cam.height, cam.width), bool),
                        cfg)
    ch = init_channels(s, cfg)
    del ch[shading.INDIRECT_CHANNEL]
    rng = np.random.default_rng(5)
    ch[DETAIL_CHANNEL] = mi.TensorXf(
        rng.uniform(-0.3, 0.3, (s.count, 3)).astype(np.float32))
    d = light_grid(128)[int(np.argmin(np.abs(light_grid(128)[:, 1] - 0.75)))]
    e = mi.Float(2.0)
    return s, view, ch, shading.LightSet(d[None], mi.Color3f(e, e, e)), cfg


def test_albedo_detail_takes_gradients_only_where_its_gate_is_open():
    """The gate changes no pixel's value, only which pixels move the detail: the gradients
    under a gate and under its complement add up to the ungated one, a closed gate gives
    none, and the segment albedo's gradient is the same under every gate (to round-off)."""
    s, view, ch, lights, cfg = _detail_view()
    npix = view.pairs.height * view.pairs.width
    left = (np.arange(npix) % view.pairs.width < view.pairs.width // 2).astype(np.float32)

    def grads(gate):
        c = dict(ch)
        for k in ("albedo", DETAIL_CHANNEL):
            c[k] = mi.TensorXf(ch[k])
            dr.enable_grad(c[k])
        v = dataclasses.replace(view, detail_gate=None if gate is None else mi.Float(gate))
        loss = view_loss(v, c, lights, None, cfg, False)
        dr.backward(loss)
        return (float(loss[0]), dr.grad(c[DETAIL_CHANNEL]).numpy(),
                dr.grad(c["albedo"]).numpy())

    loss_all, d_all, a_all = grads(None)
    loss_left, d_left, a_left = grads(left)
    loss_right, d_right, a_right = grads(1.0 - left)
    loss_none, d_none, _ = grads(np.zeros(npix, np.float32))
    assert loss_all == loss_left == loss_right == loss_none
    assert np.abs(d_all).max() > 1e-6
    assert not d_none.any()
    # float32 sums over a view's pixels in another grouping: a few ulps of the largest
    np.testing.assert_allclose(d_left + d_right, d_all, rtol=0, atol=1e-6 * np.abs(d_all).max())
    # the gated albedo is two splats' select, summed in another order than one splat's
    for a in (a_left, a_right):
        np.testing.assert_allclose(a, a_all, rtol=0, atol=1e-5 * np.abs(a_all).max())


def test_albedo_detail_is_projected_to_zero_mean_per_segment_within_its_bound():
    """After a step the detail is its segment's deviation (the segment albedo keeps the
    scale) clipped to +-detail_max; float64 by hand. The detailed albedo stays in [0, 1]."""
    s, _, ch, _, cfg = _detail_view()
    cfg = dataclasses.replace(cfg, detail_prior=0.3, detail_max=0.2)
    seg = s.channels["segment"].numpy()[:, 0].astype(int)
    raw = np.asarray(ch[DETAIL_CHANNEL].numpy(), np.float64)
    raw[seg == 1] += 0.5  # a segment whose detail drifted: its mean goes back to the albedo
    ch[DETAIL_CHANNEL] = mi.TensorXf(raw.astype(np.float32))
    _clamp_channels(ch, segment_ids(s), 2, cfg, False)
    ref = raw.copy()
    for k in (0, 1):
        ref[seg == k] -= raw[seg == k].mean(0)
    np.testing.assert_allclose(ch[DETAIL_CHANNEL].numpy(), np.clip(ref, -0.2, 0.2),
                               rtol=0, atol=2e-6)
    bright = detailed_albedo(mi.TensorXf(np.full((s.count, 3), 0.9, np.float32)),
                             ch[DETAIL_CHANNEL]).numpy()
    assert bright.max() == 1.0 and bright.min() == pytest.approx(0.9 * math.exp(-0.2), 1e-6)


def test_albedo_detail_recovers_a_printed_floor_and_is_off_in_every_preset():
    """Hard case (a capture's textured mat): the floor carries a checker print (albedo x 1.4
    / 0.6) that one albedo per segment cannot hold. With the detail on, the fitted floor
    albedo follows the print; off (every preset), the segment constraint holds exactly."""
    for name in ("paper", "cpu-small", "cpu-medium", "gpu-large"):
        assert get_config(name).detail_prior == 0.0
    for bad in ({"detail_prior": -0.1}, {"detail_prior": math.inf},
                {"detail_prior": math.nan}, {"detail_max": 0.0}, {"lr_detail": 0.0},
                {"detail_edge_px": -1}):
        with pytest.raises(ValueError, match="detail_prior >= 0"):
            MaterialConfig(**bad)
    s, cams, bounds = _plane_scene()
    seg = s.channels["segment"].numpy()[:, 0]
    x = np.stack([np.asarray(c) for c in s.position], -1)  # [N, 3]
    tex = 1.0 + 0.4 * np.sign(np.sin(x[:, 0] * 12) * np.sin(x[:, 2] * 12))
    truth = np.where(seg[:, None] == 0, s.channels["albedo_gt"].numpy() * tex[:, None],
                     s.channels["albedo_gt"].numpy())
    s.channels["albedo_gt"] = mi.TensorXf(truth.astype(np.float32))
    vcfg = VisibilityConfig(resolution=128)
    k_true = int(np.argmin(np.abs(light_grid(128)[:, 1] - 0.75)))
    imgs, masks = _render_truth(s, cams, bounds, light_grid(128)[k_true], 2.0, vcfg)
    floor = seg == 0
    for prior in (0.0, 0.3):
        cfg = with_overrides(get_config("cpu-small"),
                             {"iterations": 200, "warmup": 60, "log_every": 50,
                              "normal_steps": 0, "detail_prior": prior}, "material")
        res = fit_material(s, cams, imgs, masks, cfg, bounds, vcfg,
                           progress=False)
        a = res.surfels.channels["albedo"].numpy()
        assert DETAIL_CHANNEL not in res.surfels.channels
        if prior == 0:
            assert np.ptp(a[floor], axis=0).max() < 1e-6
            continue
        # Measured 0.79 at 300 steps; the floor's far side, outside every view, stays flat.
        corr = np.corrcoef(a[floor, 0], truth[floor, 0])[0, 1]
        assert corr > 0.6, corr


def test_albedo_detail_gates_follow_the_lights_it_joined_with():
    """The gates close near shadow edges, and they are made from the lights recorded when
    the detail joined: a fit resumed after a light was pruned makes the same gates (else
    the resumed fit differs from one that was not stopped)."""
    from mi_shadowgs.core.directions import direction_from_angles

    s, cams, bounds = _plane_scene()
    vcfg = VisibilityConfig(resolution=128)
    dirs = np.array([direction_from_angles(47.0, 52.0), direction_from_angles(200.0, 35.0)])
    imgs, masks = _render_truth(s, cams, bounds, dirs, [2.0, 1.5], vcfg)
    cfg = with_overrides(get_config("cpu-small"), {"detail_prior": 0.1},
                         "material")
    fit, state = setup_fit(s, cams, imgs, masks, cfg, bounds, vcfg,
                           progress=False)
    state.directions = dirs
    fit.maps = fit.shadow_maps(dirs)
    dw = solid_angle(cfg.n_directions)
    state.opt["log_light"] = mi.Float(np.log(np.array([2.0, 1.5]) / dw).astype(np.float32))
    start_detail(fit, state)
    first = [v.detail_gate.numpy().copy() for v in fit.views]
    sup = [v.weight.numpy() > 0 for v in fit.views]
    share = np.mean([g[m].mean() for g, m in zip(first, sup, strict=True)])
    assert 0.5 < share < 0.98, share  # the pixels at the tile's shadows' edges are closed
    # Later: the second light pruned, the first brighter.
    state.directions = dirs[:1]
    fit.maps = fit.shadow_maps(dirs[:1])
    state.opt["log_light"] = mi.Float(np.log(np.array([20.0]) / dw).astype(np.float32))
    detail_gates(fit, state)
    for g, v in zip(first, fit.views, strict=True):
        np.testing.assert_array_equal(v.detail_gate.numpy(), g)


def test_label_source_overrides_change_only_chromaticity_fits():
    """Material-id segments keep the preset; chromaticity ones take its chromaticity_*
    settings (only those that differ); an unknown source is refused by name."""
    cfg = get_config("cpu-small")
    assert label_source_overrides(cfg, "material") == {}
    assert label_source_overrides(cfg, "chromaticity") == {
        "normal_steps": cfg.chromaticity_normal_steps,
        "refine_score": cfg.chromaticity_refine_score}
    same = dataclasses.replace(cfg, normal_steps=cfg.chromaticity_normal_steps)
    assert label_source_overrides(same, "chromaticity") == {
        "refine_score": cfg.chromaticity_refine_score}
    with pytest.raises(ValueError, match="label source must be one of"):
        label_source_overrides(cfg, "auto")
    with pytest.raises(ValueError, match="chromaticity_normal_steps must be >= 0"):
        dataclasses.replace(cfg, chromaticity_normal_steps=-1)
    with pytest.raises(ValueError, match="chromaticity_refine_score 'albedo' needs specular"):
        dataclasses.replace(cfg, refine_score="segment", chromaticity_refine_score="albedo",
                            specular="on")
