"""Reverse-mode gradients of the 2DGS rasterizer against central finite differences.

The finite differences are taken on the independent float64 NumPy reference
(tests/raster_reference.py) with a tiny step, so they carry no float32 noise; components
whose +-step changes a discrete choice of the reference (a pair crossing alpha_min, the
cutoff, the rho3d/rho2d depth switch, the transmittance stop or T = 0.5) are skipped, and
the test asserts that few are.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from raster_reference import random_scene, reference, structure_equal, to_surfels

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster import RasterConfig, rasterize

# The pair list, the rasterizer's reference path; test_raster_tiles.py runs this test on the
# tiled default by setting CFG to its config.
CFG = RasterConfig(method="pairs")
# Outputs in the loss; each gets its own random weights.
OUTPUTS = ("color", "alpha", "depth", "median_depth", "normal", "distortion")
EPS = 1e-6  # float64 central differences: truncation ~EPS^2, rounding ~1e-16 / EPS


def loss_weights(shapes, seed=7):
    rng = np.random.default_rng(seed)
    w = {k: rng.uniform(-1.0, 1.0, shapes[k]) for k in OUTPUTS}
    w["distortion"] *= 1e3  # its values are ~1e-4: bring its gradients to the others' size
    return w


def ref_loss(camera, raw, weights):
    ref = reference(camera, raw, CFG)
    total = 0.0
    for k in OUTPUTS:
        total += np.sum(weights[k] * ref[k].reshape(weights[k].shape))
    return total, ref


def drjit_grads(camera, raw, weights):
    s = to_surfels(raw)
    params = s.params()
    for v in params.values():
        dr.enable_grad(v)
    out = rasterize(s, camera, s.channels, config=CFG,
                    aovs=("alpha", "depth", "median_depth", "normal", "distortion"))
    loss = mi.Float(0.0)
    for k in OUTPUTS:
        img = out[k]
        w = mi.Float(weights[k].reshape(-1).astype(np.float32))
        loss += dr.sum(img.array * w)
    dr.backward(loss)
    n = s.count

    def grad(key, cols):
        g = np.array(dr.grad(params[key]), dtype=np.float64)
        return g.reshape(cols, n).T if cols > 1 else g.reshape(n)

    return {"position": grad("position", 3), "log_scale": grad("log_scale", 2),
            "rotation": grad("rotation", 4), "opacity_logit": grad("opacity_logit", 1),
            "colors": np.array(dr.grad(params["channels.color"]), np.float64).reshape(n, -1)}


def scenes():
    persp = Camera.look_at([0.3, 0.6, 2.4], [0.0, 0.0, 0.0], width=16, height=14, fov_x=0.7)
    ortho = Camera.look_at([2.0, 1.0, -1.5], [0.0, 0.0, 0.0], width=16, height=14,
                           ortho_width=1.4)
    return {"perspective": persp, "orthographic": ortho}


@pytest.mark.parametrize("kind,outputs", [
    ("perspective", OUTPUTS), ("orthographic", OUTPUTS),
    # Alone, so that their small values are not swamped by the colour terms.
    ("perspective", ("distortion",)), ("orthographic", ("depth", "median_depth", "normal"))])
def test_gradients_match_finite_differences(kind, outputs):
    camera = scenes()[kind]
    # Smooth configuration: few, broad, half-transparent surfels, so that T stays far above
    # transmittance_min and most pairs sit far from the discrete thresholds.
    raw = random_scene(10, seed=11, extent=0.4, scale=(0.15, 0.35), opacity=(0.3, 0.7))
    shapes = {k: v.shape for k, v in reference(camera, raw, CFG).items() if k in OUTPUTS}
    weights = {k: (v if k in outputs else 0.0 * v) for k, v in loss_weights(shapes).items()}
    got = drjit_grads(camera, raw, weights)
    _, base = ref_loss(camera, raw, weights)
    checked = skipped = 0
    for key, g in got.items():
        fd = np.zeros_like(g)
        valid = np.zeros(g.shape, bool)
        for idx in np.ndindex(*g.shape):
            plus = {k: v.copy() for k, v in raw.items()}
            minus = {k: v.copy() for k, v in raw.items()}
            plus[key][idx] += EPS
            minus[key][idx] -= EPS
            lp, rp = ref_loss(camera, plus, weights)
            lm, rm = ref_loss(camera, minus, weights)
            valid[idx] = structure_equal(rp, base) and structure_equal(rm, base)
            fd[idx] = (lp - lm) / (2 * EPS)
        checked += valid.sum()
        skipped += (~valid).sum()
        scale = np.abs(fd[valid]).max()
        if key == "colors" and "color" not in outputs:
            assert scale == 0.0 and np.abs(g).max() == 0.0
            continue
        assert scale > 1e-2, f"{key}: gradient too small to test"
        # float32 forward and backward over <= 10 splats per pixel and ~200 pixels: measured
        # errors are <= 6e-6 of the group's largest gradient; 1e-4 leaves room for other
        # scenes and still catches any missing or wrong term (those are O(1e-2) or more).
        err = np.abs(g - fd)[valid]
        assert err.max() <= 1e-4 * scale, (key, outputs, err.max(), scale)
    assert skipped <= 0.05 * (checked + skipped), (checked, skipped)
