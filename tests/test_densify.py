"""Density control: the screen-space gradient statistic, clone/split/prune and opacity reset."""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.optim import SurfelAdam
from mi_shadowgs.stages.geometry.densify import DensifyConfig, DensifyStrategy

LR = {"position": 1e-3, "log_scale": 1e-3, "rotation": 1e-3, "opacity_logit": 1e-2,
      "sh_dc": 1e-3}


def _params(n: int, rng) -> dict:
    q = rng.standard_normal((n, 4))
    return {"position": rng.standard_normal((n, 3)).astype(np.float32),
            "log_scale": np.log(np.full((n, 2), 0.01)).astype(np.float32),
            "rotation": (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
            "opacity_logit": np.full((n, 1), 1.0, np.float32),
            "sh_dc": rng.standard_normal((n, 3)).astype(np.float32)}


def test_observe_screen_space_gradient_matches_numpy():
    rng = np.random.default_rng(0)
    cam = Camera.look_at((0, 1, 4), (0, 0, 0), fov_x=0.7, width=64, height=48)
    p = _params(5, rng)
    p["position"] *= 0.3
    opt = SurfelAdam(p, LR)
    g = rng.standard_normal((5, 3)).astype(np.float32)
    dr.set_grad(opt.params["position"], mi.TensorXf(g))
    strat = DensifyStrategy(DensifyConfig(), extent=4.0, count=5)
    strat.observe(opt.params["position"], opt.params["log_scale"], cam)
    strat.observe(opt.params["position"], opt.params["log_scale"], cam)
    w2c = cam.world_to_cv()
    pc = p["position"].astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    gc = g.astype(np.float64) @ w2c[:3, :3].T
    ref = np.hypot(gc[:, 0] * 32, gc[:, 1] * 24) * pc[:, 2] / cam.focal  # NDC units
    np.testing.assert_allclose(np.array(strat.grad_accum), 2 * ref, rtol=1e-5)  # float32
    np.testing.assert_allclose(np.array(strat.denom), 2.0)
    radius = 3 * 0.01 * cam.focal / pc[:, 2]
    np.testing.assert_allclose(np.array(strat.max_radii), radius, rtol=1e-5)


def test_clone_split_prune():
    rng = np.random.default_rng(1)
    p = _params(4, rng)
    p["log_scale"][1] = np.log([0.5, 0.2])  # big: split
    p["opacity_logit"][3] = -5.0  # transparent: pruned
    cfg = DensifyConfig(grad_threshold=0.1, percent_dense=0.01, min_opacity=0.05)
    opt = SurfelAdam(p, LR)
    # Give surfel 2 (not hot) distinctive moments: they must survive with it.
    m = {k: np.zeros_like(a) for k, a in p.items()}
    m["position"][2] = 7.0
    opt.load(p, m, None)
    strat = DensifyStrategy(cfg, extent=4.0, count=4, seed=3)
    # Hot: 0 (small -> clone) and 1 (big -> split); 2 cold; 3 hot but transparent.
    strat.grad_accum = mi.Float([0.4, 0.4, 0.01, 0.4])
    strat.denom = mi.Float([2.0, 2.0, 2.0, 2.0])
    strat.densify_and_prune(opt, 500, big_prune=False)
    out, mo, _ = opt.to_numpy()
    # kept originals (0, 2), then clone of 0 (and of 3, pruned), then 2 split children of 1
    assert out["position"].shape[0] == 5
    np.testing.assert_array_equal(out["position"][:2], p["position"][[0, 2]])
    np.testing.assert_array_equal(out["position"][2], p["position"][0])  # clone: same place
    kids = out["position"][3:]
    np.testing.assert_allclose(np.exp(out["log_scale"][3:]), [[0.5 / 1.6, 0.2 / 1.6]] * 2,
                               rtol=1e-6)
    # The parent's frame from SciPy (quaternion (w, x, y, z), docs/conventions.md): columns
    # t_u, t_v, n.
    q = p["rotation"][1].astype(np.float64)
    frame = Rotation.from_quat(q[[1, 2, 3, 0]] / np.linalg.norm(q)).as_matrix()
    off = kids - p["position"][1]
    # Children stay in the parent's tangent plane (float32 positions: 1e-6) ...
    np.testing.assert_allclose(off @ frame[:, 2], 0.0, atol=1e-5)
    assert np.all(np.linalg.norm(off, axis=1) > 0)
    # ... at draws of the parent's Gaussian: within 5 sigma along each axis (a draw beyond
    # has probability ~6e-7), not at the scale of the scene or of a wrong axis' units.
    tangent = (off @ frame[:, :2]) / np.array([0.5, 0.2])  # [2, 2] in parent sigmas
    assert np.all(np.abs(tangent) < 5.0), tangent
    np.testing.assert_array_equal(mo["position"][1], 7.0)  # surfel 2's moments kept
    np.testing.assert_array_equal(mo["position"][2:], 0.0)  # new surfels start afresh
    assert dr.width(strat.grad_accum) == 5 and float(dr.sum(strat.grad_accum)[0]) == 0


def test_max_surfels_and_big_prune():
    rng = np.random.default_rng(2)
    p = _params(6, rng)
    p["log_scale"][5] = np.log([2.0, 0.1])  # world-size prune: 2 > 0.1 * extent
    cfg = DensifyConfig(grad_threshold=0.1, max_surfels=8)
    opt = SurfelAdam(p, LR)
    strat = DensifyStrategy(cfg, extent=4.0, count=6)
    strat.grad_accum = mi.Float([0.9, 0.8, 0.7, 0.6, 0.5, 0.0])
    strat.denom = mi.Float([1.0] * 6)
    strat.densify_and_prune(opt, 500, big_prune=True)
    # Room for 2 clones (the two hottest), then the big surfel is pruned: 6 + 2 - 1.
    assert opt.count == 7
    np.testing.assert_array_equal(opt.to_numpy()[0]["position"][5:], p["position"][:2])


def test_screen_space_prune_and_without_it():
    # Surfel 1 spanned 25 px (3-sigma) in some view since the last densify: after the first
    # opacity reset 2DGS's rule prunes it (> 20 px); the paper preset, without that rule,
    # keeps it. Nothing is hot, so nothing is cloned or split.
    from mi_shadowgs.presets import GEOMETRY as PRESETS

    rng = np.random.default_rng(4)
    p = _params(3, rng)
    for threshold, kept in ((20.0, [0, 2]), (None, [0, 1, 2])):
        opt = SurfelAdam(p, LR)
        cfg = DensifyConfig(grad_threshold=0.1, screen_size_threshold=threshold)
        strat = DensifyStrategy(cfg, extent=4.0, count=3)
        strat.max_radii = mi.Float([5.0, 25.0, 19.9])
        strat.densify_and_prune(opt, 3100, big_prune=True)
        np.testing.assert_array_equal(opt.to_numpy()[0]["position"], p["position"][kept])
    assert PRESETS["paper"].densify.screen_size_threshold is None
    assert PRESETS["cpu-small"].densify.screen_size_threshold == 20.0


def test_without_opacity_resets_large_surfels_are_still_pruned():
    # Views without masks train without opacity resets (GeometryConfig.unmasked), but the
    # world-space prune still acts, from where the first reset would have been, so that no
    # surfel grows into a sheet over a lab capture's backdrop; the screen-space prune stays
    # with the resets.
    from mi_shadowgs.presets import GEOMETRY as PRESETS
    from mi_shadowgs.stages.geometry.config import unmasked

    cpu = PRESETS["cpu-small"]
    free = unmasked(cpu).densify
    assert free.opacity_reset_interval == 0
    assert free.world_prune_after == cpu.densify.opacity_reset_interval == 1000
    kept_resets = unmasked(dataclasses.replace(cpu, unmasked_opacity_reset=True)).densify
    assert (kept_resets.opacity_reset_interval, kept_resets.world_prune_after) == (1000, None)
    rng = np.random.default_rng(5)
    p = _params(3, rng)
    p["log_scale"][1] = np.log([2.0, 0.1])  # 2 > 0.1 * extent
    cfg = dataclasses.replace(free, start=100, stop=1800, interval=100, grad_threshold=0.1)
    for iteration, kept in ((1000, [0, 1, 2]), (1100, [0, 2])):
        opt = SurfelAdam(p, LR)
        strat = DensifyStrategy(cfg, extent=4.0, count=3)
        strat.max_radii = mi.Float([5.0, 5.0, 25.0])  # surfel 2: large on screen, kept
        assert strat.step(iteration, opt)
        np.testing.assert_array_equal(opt.to_numpy()[0]["position"], p["position"][kept])


def test_opacity_reset_and_schedule():
    rng = np.random.default_rng(3)
    p = _params(3, rng)
    p["opacity_logit"][:, 0] = [-6.0, 0.5, 4.0]
    opt = SurfelAdam(p, LR)
    cfg = dataclasses.replace(DensifyConfig(), start=100, stop=1000, interval=100,
                              opacity_reset_interval=300)
    strat = DensifyStrategy(cfg, extent=4.0, count=3)
    dr.set_grad(opt.params["opacity_logit"], mi.TensorXf(np.ones((3, 1), np.float32)))
    opt.step()
    assert not strat.step(150, opt)  # not on the interval
    assert strat.step(300, opt)  # densify + reset
    o = opt.to_numpy()[0]["opacity_logit"][:, 0]
    cap = np.log(0.01 / 0.99)
    assert np.all(o <= cap + 1e-6) and o.min() < cap  # capped, lower ones untouched
    np.testing.assert_array_equal(opt.to_numpy()[1]["opacity_logit"], 0.0)
    assert not strat.step(1000, opt)  # stop reached


def test_bad_extent():
    with pytest.raises(ValueError, match="extent"):
        DensifyStrategy(DensifyConfig(), extent=0.0, count=1)


def test_no_opacity_reset_in_the_last_interval_of_the_schedule():
    """`train --iterations 1000` at cpu-small reset every opacity at step 1000 and saved that
    transparent model (test mask IoU 0.0009). A reset now needs a whole interval after it;
    the presets' own schedules keep every reset they had."""
    from mi_shadowgs.presets import GEOMETRY as PRESETS

    def resets(config, iterations):
        strat = DensifyStrategy(config.densify, extent=4.0, count=3, iterations=iterations)
        return [t for t in range(1, iterations + 1) if strat.reset_due(t)]

    small = PRESETS["cpu-small"]
    assert resets(small, small.iterations) == [1000]
    assert resets(small, 1000) == [] and resets(small, 1999) == []
    assert resets(small, 2000) == [1000]
    paper = PRESETS["paper"]
    assert resets(paper, paper.iterations)[-1] < paper.densify.stop
    assert DensifyStrategy(small.densify, extent=4.0, count=3).reset_due(1000)  # no length
