"""Cook-Torrance BRDF (mi_shadowgs.core.brdf) against an independent float64 NumPy reference."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowgs.core import brdf

# float32 evaluation of formulas whose float64 values span ~1e-3..1e5 (D near a sharp peak):
# relative 1e-4 covers a few float32 roundings through the ~20 operations of the lobe.
RTOL = 1e-4
ATOL = 1e-6


# -- float64 reference --------------------------------------------------------------------
def ref_cook_torrance(n, l, v, a, rough, metal, spec=True):
    """f_r (n . l)^+ : [P, 3], written from the formulas (paper Eq. 4-5), float64."""
    n, l, v, a = (np.asarray(x, np.float64) for x in (n, l, v, a))
    rough = np.maximum(np.asarray(rough, np.float64), brdf.ROUGHNESS_MIN)[:, None]
    metal = np.asarray(metal, np.float64)[:, None]
    nl = np.clip(np.sum(n * l, -1), 0, 1)[:, None]
    nv = np.clip(np.sum(n * v, -1), 0, 1)[:, None]
    out = (1 - metal) * a / np.pi * nl
    if not spec:
        return out
    h = l + v
    hn = np.linalg.norm(h, axis=-1, keepdims=True)
    h = np.where(hn > 1e-6, h / np.maximum(hn, 1e-300), 0.0)
    nh = np.clip(np.sum(n * h, -1), 0, 1)[:, None]
    vh = np.clip(np.sum(v * h, -1), 0, 1)[:, None]
    alpha = rough ** 2
    d = alpha ** 2 / (np.pi * (nh ** 2 * (alpha ** 2 - 1) + 1) ** 2)
    f0 = 0.04 * (1 - metal) + a * metal
    f = f0 + (1 - f0) * (1 - vh) ** 5

    def g1(x):
        return 2 * x / (x + np.sqrt(alpha ** 2 + (1 - alpha ** 2) * x ** 2))

    g = g1(nl) * g1(nv)
    with np.errstate(divide="ignore", invalid="ignore"):
        lobe = np.where((nl > 0) & (nv > 0) & (hn > 1e-6), d * f * g / (4 * nl * nv) * nl, 0.0)
    # At n . v = 0 the reference's G / (4 nl nv) is 0/0; its limit is the finite Vis form.
    lim = (nl > 0) & (nv == 0) & (hn > 1e-6)
    vis = 1 / ((nl + np.sqrt(alpha ** 2 + (1 - alpha ** 2) * nl ** 2)) * alpha)
    lobe = np.where(lim, d * f * vis * nl, lobe)
    return out + lobe


def _unit(x):
    x = np.asarray(x, np.float64)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _v3(x):
    x = np.asarray(x, np.float32)
    return mi.Vector3f(x[:, 0], x[:, 1], x[:, 2])


def _c3(x):
    x = np.asarray(x, np.float32)
    return mi.Color3f(x[:, 0], x[:, 1], x[:, 2])


def _np3(c):
    return np.stack([np.asarray(c[k], np.float64) for k in range(3)], -1)


def _eval(n, l, v, a, r, m, spec=True):
    out = brdf.cook_torrance(_v3(n), _v3(l), _v3(v), _c3(a), mi.Float(np.float32(r)),
                             mi.Float(np.float32(m)), with_specular=spec)
    return _np3(out)


def _random_case(rng, p):
    n = np.tile([0.0, 0.0, 1.0], (p, 1))
    l = _unit(rng.normal(size=(p, 3)) + [0, 0, 0.8])
    v = _unit(rng.normal(size=(p, 3)) + [0, 0, 0.8])
    # Rotate the frame so the normal is not an axis (catches swapped components).
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    n, l, v = n @ q.T, l @ q.T, v @ q.T
    a = rng.uniform(0.02, 1.0, (p, 3))
    r = rng.uniform(0.05, 1.0, p)
    m = rng.uniform(0.0, 1.0, p)
    return n, l, v, a, r, m


def test_matches_float64_reference():
    rng = np.random.default_rng(1)
    case = _random_case(rng, 4000)
    got = _eval(*case)
    ref = ref_cook_torrance(*case)
    np.testing.assert_allclose(got, ref, rtol=RTOL, atol=ATOL)
    got_d = _eval(*case, spec=False)
    np.testing.assert_allclose(got_d, ref_cook_torrance(*case, spec=False), rtol=RTOL, atol=ATOL)
    # The case must exercise the specular lobe, not only the diffuse part.
    assert np.max(ref - ref_cook_torrance(*case, spec=False)) > 0.5


def test_grazing_and_degenerate_angles_are_finite():
    """n . l = 0, n . v = 0, l = -v, light below the horizon, roughness 0 (clamped)."""
    n = np.tile([0.0, 1.0, 0.0], (6, 1))
    l = np.array([[1, 0, 0], [0, 1, 0], [1, 0, 0], [0.6, 0.8, 0], [0, -1, 0], [0, 1, 0]], float)
    v = np.array([[0, 1, 0], [1, 0, 0], [-1, 0, 0], [-0.6, 0.8, 0], [0, 1, 0], [0, 1, 0]], float)
    a = np.full((6, 3), 0.7)
    r = np.array([0.5, 0.5, 0.5, 0.0, 0.3, 0.0])  # roughness 0: clamped to ROUGHNESS_MIN
    m = np.array([0.0, 1.0, 0.5, 1.0, 0.0, 1.0])
    got = _eval(n, l, v, a, r, m)
    assert np.all(np.isfinite(got))
    assert np.allclose(got[0], 0.0)  # n . l = 0: no contribution
    assert np.allclose(got[2], 0.0)  # l = -v and n . l = 0
    assert np.allclose(got[4], 0.0)  # light below the horizon
    # n . v = 0 with the light overhead: finite, equal to the float64 limit.
    np.testing.assert_allclose(got[1], ref_cook_torrance(n, l, v, a, r, m)[1], rtol=1e-3)
    # Mirror configuration at roughness 0: the clamped peak, D = 1 / (pi alpha^2).
    np.testing.assert_allclose(got[3], ref_cook_torrance(n, l, v, a, r, m)[3], rtol=1e-3)
    assert got[5].max() > 1e4  # the peak really is the sharp clamped lobe, yet finite
    # Gradients at these points are finite too.
    rr = mi.Float(np.float32(r))
    dr.enable_grad(rr)
    out = brdf.cook_torrance(_v3(n), _v3(l), _v3(v), _c3(a), rr, mi.Float(np.float32(m)))
    dr.backward(dr.sum(out[0] + out[1] + out[2]))
    assert np.all(np.isfinite(np.asarray(dr.grad(rr))))


def _hemisphere(n_theta=400, n_phi=400):
    """Midpoint quadrature of the upper (z) hemisphere: directions [M, 3], weights [M]."""
    t = (np.arange(n_theta) + 0.5) / n_theta * (np.pi / 2)
    p = (np.arange(n_phi) + 0.5) / n_phi * (2 * np.pi)
    tt, pp = np.meshgrid(t, p, indexing="ij")
    d = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
    w = np.sin(tt) * (np.pi / 2 / n_theta) * (2 * np.pi / n_phi)
    return d.reshape(-1, 3), w.reshape(-1)


def test_ggx_d_normalised():
    d, w = _hemisphere()
    for r in (0.3, 0.6, 1.0):
        val = np.asarray(brdf.ggx_d(mi.Float(np.float32(d[:, 2])), r), np.float64)
        # Quadrature error of a 400 x 400 midpoint rule on a lobe of width alpha >= 0.09.
        assert abs(np.sum(val * d[:, 2] * w) - 1.0) < 5e-3, r


@pytest.mark.parametrize("rough", [0.2, 0.5, 1.0])
@pytest.mark.parametrize("cos_v", [1.0, 0.5, 0.1])
def test_white_furnace_bounds(rough, cos_v):
    """Directional albedo: diffuse white = 1; the specular lobe with F = 1 lies in (0, 1]."""
    d, w = _hemisphere()
    p = len(d)
    n = np.tile([0.0, 0.0, 1.0], (p, 1))
    v = np.tile([math.sqrt(1 - cos_v ** 2), 0.0, cos_v], (p, 1))
    white = np.ones((p, 3))
    diff = _eval(n, d, v, white, np.full(p, rough), np.zeros(p), spec=False)
    assert abs(np.sum(diff[:, 0] * w) - 1.0) < 1e-3  # midpoint rule error on cos
    # m = 1 and albedo 1 make F0 = 1 (F = 1): the lobe's energy is the masking loss only.
    spec = _eval(n, d, v, white, np.full(p, rough), np.ones(p))
    e = np.sum(spec[:, 0] * w)
    # Single-scattering GGX with separable Smith loses energy at high roughness (alpha = 1,
    # normal view: 1 - ln 2 = 0.307 exactly) and never gains any: <= 1 up to the quadrature
    # error (2e-2 for the sharpest lobe).
    assert 0.25 < e < 1.0 + 2e-2, e
    if rough == 1.0 and cos_v == 1.0:
        assert abs(e - (1.0 - math.log(2.0))) < 1e-3  # closed form: D = 1/pi, F = 1
    if rough == 0.2 and cos_v == 1.0:
        assert e > 0.99  # a sharp lobe at normal view loses almost nothing


def test_normal_gradient_matches_finite_differences():
    """Stage 4's normal phase optimises shading normals through this lobe: AD of the lobe
    at normalize(n) (float32) vs central differences of the float64 reference, the normal
    nudged along each axis and renormalised. Cases with n . l and n . v above 0.05 (the
    clamps' kinks lie at 0), roughness away from its clamp."""
    rng = np.random.default_rng(11)
    n, l, v, a, r, m = _random_case(rng, 256)
    keep = (np.sum(n * l, -1) > 0.05) & (np.sum(n * v, -1) > 0.05)
    n, l, v, a, r, m = n[keep], l[keep], v[keep], a[keep], np.clip(r[keep], 0.15, 1.0), m[keep]
    assert len(n) > 64  # enough cases left to mean something
    ad_n = _v3(n)
    dr.enable_grad(ad_n)
    out = brdf.cook_torrance(dr.normalize(ad_n), _v3(l), _v3(v), _c3(a),
                             mi.Float(np.float32(r)), mi.Float(np.float32(m)))
    dr.backward(dr.sum(out[0] + out[1] + out[2]))
    g_n = _np3(dr.grad(ad_n))
    h = 1e-6
    fd = np.zeros_like(n)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd[:, k] = (ref_cook_torrance(_unit(n + e), l, v, a, r, m).sum(-1)
                    - ref_cook_torrance(_unit(n - e), l, v, a, r, m).sum(-1)) / (2 * h)
    # As for the other parameters: float32 AD through sharp lobes, relative 1e-3 of the
    # largest derivative (measured here: 3.9e-7 of the largest).
    np.testing.assert_allclose(g_n, fd, rtol=1e-3, atol=1e-3 * np.abs(fd).max())


def test_gradients_match_finite_differences():
    """AD (float32) vs central differences of the float64 reference."""
    rng = np.random.default_rng(7)
    n, l, v, a, r, m = _random_case(rng, 64)
    r = np.clip(r, 0.15, 1.0)  # away from the clamp's kink
    ad_a, ad_r, ad_m = mi.Color3f(_c3(a)), mi.Float(np.float32(r)), mi.Float(np.float32(m))
    dr.enable_grad(ad_a, ad_r, ad_m)
    out = brdf.cook_torrance(_v3(n), _v3(l), _v3(v), ad_a, ad_r, ad_m)
    dr.backward(dr.sum(out[0] + out[1] + out[2]))
    g_r = np.asarray(dr.grad(ad_r), np.float64)
    g_m = np.asarray(dr.grad(ad_m), np.float64)
    g_a = _np3(dr.grad(ad_a))
    h = 1e-6

    def total(a_, r_, m_):
        return ref_cook_torrance(n, l, v, a_, r_, m_).sum(-1)

    fd_r = (total(a, r + h, m) - total(a, r - h, m)) / (2 * h)
    fd_m = (total(a, r, m + h) - total(a, r, m - h)) / (2 * h)
    fd_a0 = (ref_cook_torrance(n, l, v, a + [h, 0, 0], r, m)[:, 0]
             - ref_cook_torrance(n, l, v, a - [h, 0, 0], r, m)[:, 0]) / (2 * h)
    # float32 AD through sharp lobes: relative 1e-3 of the largest derivative magnitude.
    for g, fd in ((g_r, fd_r), (g_m, fd_m), (g_a[:, 0], fd_a0)):
        np.testing.assert_allclose(g, fd, rtol=1e-3, atol=1e-3 * np.abs(fd).max())


def test_roughness_at_its_clamp_has_the_gradient_from_above():
    """Stage 4 projects roughness onto [ROUGHNESS_MIN, 1] after each step: a surfel on the
    clamp must still feel the pull toward rougher. AD at exactly ROUGHNESS_MIN vs the
    one-sided forward difference of the float64 reference (h = 1e-6: its truncation error,
    ~h |f''|, is far below the tolerance); below the clamp the lobe is constant (zero)."""
    rng = np.random.default_rng(5)
    n, l, v, a, _, m = _random_case(rng, 64)
    at = np.full(len(n), brdf.ROUGHNESS_MIN, np.float32)
    for r, expect_zero in ((at, False), (at * np.float32(0.5), True)):
        ad_r = mi.Float(r)
        dr.enable_grad(ad_r)
        out = brdf.cook_torrance(_v3(n), _v3(l), _v3(v), _c3(a), ad_r, mi.Float(np.float32(m)))
        dr.backward(dr.sum(out[0] + out[1] + out[2]))
        g = np.asarray(dr.grad(ad_r), np.float64)
        if expect_zero:
            assert np.all(g == 0.0)
            continue
        h = 1e-6
        r64 = r.astype(np.float64)
        fd = (ref_cook_torrance(n, l, v, a, r64 + h, m).sum(-1)
              - ref_cook_torrance(n, l, v, a, r64, m).sum(-1)) / h
        assert np.count_nonzero(np.abs(fd) > 1e-3) > 8  # the lobe depends on it here
        # float32 AD through the sharpest lobe the clamp allows: relative 1e-3 of the
        # largest derivative, as for the other parameters
        np.testing.assert_allclose(g, fd, rtol=1e-3, atol=1e-3 * np.abs(fd).max())


@pytest.mark.parametrize("metallic", [0.0, 0.3])
def test_diffuse_direct_and_its_gradients_match_float64(metallic):
    """``shading.direct`` without the lobe takes (1 - m) a / pi out of the sum over the lights
    (the per-pixel-and-light kernels then touch no material): its value and its gradients
    in the albedo, the metallic and the lights' irradiance are those of the sum written out,
    in float64."""
    from mi_shadowgs.core import jit, shading

    npix, k = 48, 6
    rng = np.random.default_rng(5)
    normal = rng.standard_normal((npix, 3))
    normal[:, 1] = np.abs(normal[:, 1]) + 0.3
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    dirs = rng.standard_normal((k, 3))
    dirs[:, 1] = np.abs(dirs[:, 1])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    a = rng.uniform(0.2, 0.8, (3, npix))
    m = np.full(npix, metallic)
    e = rng.uniform(0.5, 2.0, (3, k))
    vis = rng.uniform(0.0, 1.0, (npix, k))
    w = rng.uniform(-1.0, 1.0, (3, npix))  # the loss: sum of w * out
    zeros = dr.zeros(mi.Float, npix)
    geom = shading.PixelGeometry(dr.ones(mi.Float, npix), None, None,
                                 mi.Vector3f(*(jit.array(normal[:, c]) for c in range(3))),
                                 None, None, zeros)
    albedo = mi.Color3f(*(jit.array(x) for x in a))
    metal = jit.array(m.astype(np.float32))
    weights = mi.Color3f(*(jit.array(x) for x in e))
    dr.enable_grad(albedo, metal, weights)
    out = shading.direct(geom, albedo, zeros, metal, shading.LightSet(dirs, weights),
                         jit.array(vis.reshape(-1)), False)
    dr.backward(sum(dr.sum(out[c] * jit.array(w[c])) for c in range(3)))
    cos_v = np.maximum(normal @ dirs.T, 0.0) * vis  # [P, K]
    irr = cos_v @ e.T  # [P, 3]: sum_k (n . l_k)^+ V_k E_k
    want = ((1.0 - m)[:, None] * a.T / np.pi * irr).T  # [3, P]
    for c in range(3):
        np.testing.assert_allclose(out[c].numpy(), want[c], rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(dr.grad(albedo)[c].numpy(),
                                   w[c] * (1.0 - m) / np.pi * irr[:, c], rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(
            dr.grad(weights)[c].numpy(),
            ((w[c] * (1.0 - m) * a[c] / np.pi)[:, None] * cos_v).sum(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(dr.grad(metal).numpy(),
                               -(w * a / np.pi * irr.T).sum(0), rtol=1e-5, atol=1e-6)
