"""Local lights (lamps) in shading: a float64 reference of the direct term with 1/r^2
falloff, mixed directional and local sets, and the gradient with respect to a lamp's
position against finite differences."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_shadowgs  # noqa: F401
from mi_shadowgs.core import jit, shading


def _geom(rng, n):
    pts = rng.uniform(-1, 1, (n, 3)) * [1, 0.1, 1]
    nrm = rng.normal(size=(n, 3)) * 0.3 + [0, 1, 0]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    view = np.tile([0.0, 0.6, 0.8], (n, 1))

    def v3(a, t=mi.Vector3f):
        return t(*(jit.array(a[:, k].astype(np.float32)) for k in range(3)))

    geom = shading.PixelGeometry(dr.ones(mi.Float, n), None, None, v3(nrm), v3(view),
                                 v3(pts, mi.Point3f), dr.zeros(mi.Float, n))
    return geom, pts, nrm


def _reference(pts, nrm, albedo, dirs, weights, positions, center):
    """sum_k a / pi (n . l_k)^+ E_k (|p_k - c|^2 / |p_k - x|^2 for lamps), float64."""
    out = np.zeros((len(pts), 3))
    for k in range(len(dirs)):
        if positions is not None and np.all(np.isfinite(positions[k])):
            to = positions[k] - pts
            r2 = np.sum(to ** 2, axis=1)
            l = to / np.sqrt(r2)[:, None]
            fall = np.sum((positions[k] - center) ** 2) / r2
        else:
            l = np.broadcast_to(dirs[k], pts.shape)
            fall = np.ones(len(pts))
        nl = np.maximum(np.sum(nrm * l, axis=1), 0)
        out += albedo / np.pi * (nl * fall * weights[k])[:, None]
    return out


def test_local_and_directional_direct_matches_reference():
    rng = np.random.default_rng(3)
    geom, pts, nrm = _geom(rng, 300)
    center = np.array([0.0, 0.2, 0.0])
    lamp = np.array([1.5, 4.0, -2.0])
    sun = np.array([-0.3, 0.9, 0.3]) / np.linalg.norm([-0.3, 0.9, 0.3])
    positions = np.array([lamp, [np.nan] * 3])
    dirs = np.array([(lamp - center) / np.linalg.norm(lamp - center), sun])
    e = np.array([2.0, 0.5])
    lights = shading.LightSet(dirs, mi.Color3f(*(jit.array(e.astype(np.float32)),) * 3),
                              positions, np.zeros(2), center)
    np.testing.assert_array_equal(lights.local, [True, False])
    assert lights.intensity()[0] == pytest.approx(np.sum((lamp - center) ** 2))
    albedo = np.array([0.7, 0.5, 0.3])
    zero = dr.zeros(mi.Float, 300)
    got = shading.direct(geom, mi.Color3f(*albedo.tolist()), zero, zero, lights, None, False)
    got = np.stack([np.asarray(got[c]) for c in range(3)], 1)
    ref = _reference(pts, nrm, albedo, dirs, e, positions, center)
    np.testing.assert_allclose(got, ref, rtol=2e-5, atol=1e-6)
    # a directional-only set is unchanged by an all-NaN positions array
    only = shading.LightSet(dirs[1:], mi.Color3f(0.5), np.full((1, 3), np.nan), None, center)
    a = shading.direct(geom, mi.Color3f(*albedo.tolist()), zero, zero, only, None, False)
    b = shading.direct(geom, mi.Color3f(*albedo.tolist()), zero, zero,
                       shading.directional_lights(dirs[1:], mi.Color3f(0.5)), None, False)
    np.testing.assert_array_equal(np.asarray(a[0]), np.asarray(b[0]))


def test_local_lights_constructor_checks():
    with pytest.raises(ValueError, match="center"):
        shading.LightSet(np.zeros((1, 3)), mi.Color3f(1.0), np.ones((1, 3)))
    with pytest.raises(ValueError, match="finite"):
        shading.local_lights(np.array([[np.inf, 0, 0]]), mi.Color3f(1.0), np.zeros(3))
    ls = shading.local_lights(np.array([[0.0, 3.0, 4.0]]), mi.Color3f(1.0), np.zeros(3))
    np.testing.assert_allclose(ls.directions, [[0, 0.6, 0.8]])
    assert ls.intensity()[0] == pytest.approx(25.0)


def test_lamp_position_gradient_matches_finite_differences():
    rng = np.random.default_rng(5)
    geom, pts, nrm = _geom(rng, 200)
    center = np.zeros(3)
    p0 = np.array([0.8, 3.0, 1.2])
    zero = dr.zeros(mi.Float, 200)

    def loss(pos):
        lights = shading.LightSet(np.array([p0 / np.linalg.norm(p0)]), mi.Color3f(1.5), pos,
                                  np.zeros(1), center)
        out = shading.direct(geom, mi.Color3f(0.6), zero, zero, lights, None, False)
        return dr.sum(out[0] + 2 * out[1])

    pos = mi.Point3f(*(mi.Float(float(x)) for x in p0))
    dr.enable_grad(pos)
    val = loss(pos)
    dr.backward(val)
    grad = np.array([dr.grad(pos.x)[0], dr.grad(pos.y)[0], dr.grad(pos.z)[0]])
    h = 1e-3
    fd = []
    for k in range(3):
        a, b = p0.copy(), p0.copy()
        a[k] += h
        b[k] -= h
        fd.append((loss(mi.Point3f(*a.tolist()))[0] - loss(mi.Point3f(*b.tolist()))[0])
                  / (2 * h))
    np.testing.assert_allclose(grad, fd, rtol=2e-3, atol=1e-3)


def test_light_json_round_trip_keeps_lamps():
    from mi_shadowgs.stages.material.outputs import local_light_json, local_lights_from_json
    from mi_shadowgs.stages.material.state import LightModel

    pos = np.array([[1.0, 4.0, 2.0], [np.nan] * 3])
    light = LightModel(np.zeros(8), np.array([0, 1]), np.array([[0, 1.0, 0], [0, 0, 1.0]]),
                       np.array([2.0, 0.5]), pos, np.array([0.1, 0.0]), np.zeros(3))
    data = local_light_json(light)
    assert data["positions"][1] is None
    back = local_lights_from_json(data, 2)
    np.testing.assert_array_equal(back[0], pos)
    np.testing.assert_array_equal(back[1], [0.1, 0.0])
    ls = light.light_set()
    np.testing.assert_array_equal(ls.local, [True, False])
    assert local_light_json(LightModel(np.zeros(8), np.array([0]))) == {}
    with pytest.raises(ValueError, match="radii"):
        local_lights_from_json({**data, "radii": [-1, 0]}, 2)
    with pytest.raises(ValueError, match="positions"):
        local_lights_from_json(data, 3)
