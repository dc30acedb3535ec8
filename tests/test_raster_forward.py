"""Forward pass of the Dr.Jit 2DGS rasterizer against an independent float64 NumPy reference."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from raster_reference import random_scene, reference, to_surfels
from scipy.spatial.transform import Rotation

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster import RasterConfig, rasterize
from mi_shadowgs.core.surfels import Surfels, eval_sh, sh_colors

AOVS = ("alpha", "depth", "median_depth", "normal", "distortion", "count")
CFG = RasterConfig()
# Both rasterizers (the tiled default and the pair list) against the float64 reference.
METHODS = ("tiles", "pairs")


def cameras():
    persp = Camera.look_at([0.4, 0.9, 2.6], [0.0, 0.0, 0.0], width=24, height=20, fov_x=0.8)
    ortho = Camera.look_at([-2.5, 1.2, 1.0], [0.0, 0.0, 0.0], width=24, height=20,
                           ortho_width=1.9)
    return {"perspective": persp, "orthographic": ortho}


def render_both(camera, raw, method="tiles"):
    s = to_surfels(raw)
    out = rasterize(s, camera, s.channels, aovs=AOVS, config=RasterConfig(method=method))
    got = {k: np.array(v, dtype=np.float64) for k, v in out.items()}
    return got, reference(camera, raw, CFG)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_forward_matches_reference(kind, seed, method):
    camera = cameras()[kind]
    raw = random_scene(40, seed)
    got, ref = render_both(camera, raw, method)
    ok = ~ref["unsure"]
    # Pixels with a pair within 1e-4 (relative) of a discrete threshold may take the other
    # branch in float32; they must stay rare, or the comparison would prove little.
    assert ok.mean() > 0.9, f"{(~ok).sum()} unsure pixels"
    assert ref["alpha"][ok].max() > 0.9 and (ref["count"][ok] >= 3).sum() > 50  # non-trivial
    assert got["color"].shape == (20, 24, 3)
    # Acceptance: 1e-4 absolute on colour and alpha (float32 sums of O(10) terms ~1e-6).
    np.testing.assert_allclose(got["color"][ok], ref["color"][ok], rtol=0, atol=1e-4)
    np.testing.assert_allclose(got["alpha"][ok, 0], ref["alpha"][ok], rtol=0, atol=1e-4)
    # Acceptance: 1e-4 relative on depth (float32 has ~6e-8; the intersection adds a little).
    np.testing.assert_allclose(got["depth"][ok, 0], ref["depth"][ok], rtol=1e-4, atol=0)
    np.testing.assert_allclose(got["median_depth"][ok, 0], ref["median_depth"][ok],
                               rtol=1e-4, atol=0)
    np.testing.assert_allclose(got["normal"][ok], ref["normal"][ok], rtol=0, atol=1e-4)
    np.testing.assert_array_equal(got["count"][ok, 0], ref["count"][ok])
    # Distortion is a sum of float32 weights times squared differences of m (peak ~1e-4
    # here); the Float64 scans keep its error near 1e-10, 1e-5 of max(peak, 1e-3) is ample.
    scale = max(ref["distortion"].max(), 1e-3)
    np.testing.assert_allclose(got["distortion"][ok, 0], ref["distortion"][ok],
                               rtol=0, atol=1e-5 * scale)


def test_background_and_sh_channel():
    camera = cameras()["perspective"]
    raw = random_scene(40, 2)
    s = to_surfels(raw)
    k = 4  # SH degree 1: 4 coefficients per colour, coefficient-major
    sh = np.random.default_rng(0).normal(0.0, 0.3, (40, k * 3)).astype(np.float32)
    s.channels = {"sh": mi.TensorXf(sh), "albedo": s.channels["color"]}
    bg = [0.2, 0.4, 0.6]
    chans = {"rgb": sh_colors(s, camera.origin), "albedo": s.channels["albedo"]}
    out = rasterize(s, camera, chans, aovs=("alpha",), background={"rgb": bg})
    assert set(out) == {"rgb", "albedo", "alpha"}
    assert set(rasterize(s, camera, None, aovs=("depth",))) == {"depth"}
    a = np.array(out["alpha"], np.float64)
    ref = reference(camera, raw, CFG)
    ok = ~ref["unsure"]
    np.testing.assert_allclose(np.array(out["albedo"])[ok], ref["color"][ok], atol=1e-4)
    # "rgb": SH colours (from the camera to each centre) composited, then the background.
    d = raw["position"] - camera.origin
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    basis = np.stack([np.full(40, 0.28209479177387814), -0.4886025119029199 * d[:, 1],
                      0.4886025119029199 * d[:, 2], -0.4886025119029199 * d[:, 0]], axis=1)
    rgb = np.maximum(np.einsum("nk,nkc->nc", basis, sh.reshape(40, k, 3)) + 0.5, 0.0)
    want = reference(camera, {**raw, "colors": rgb}, CFG)["color"] + np.array(bg) * (1 - a)
    np.testing.assert_allclose(np.array(out["rgb"])[ok], want[ok], atol=1e-4)
    with pytest.raises(ValueError, match="background"):
        rasterize(s, camera, chans, background={"nope": bg})
    with pytest.raises(ValueError, match="unknown AOV"):
        rasterize(s, camera, chans, aovs=("depht",))


def test_eval_sh_degree3_matches_numpy():
    rng = np.random.default_rng(1)
    n = 64
    sh = rng.normal(0.0, 0.5, (n, 16 * 3))
    d = rng.normal(size=(n, 3))
    got = np.array(eval_sh(mi.TensorXf(sh.astype(np.float32)),
                           mi.Vector3f(*(d[:, i].astype(np.float32) for i in range(3)))))
    x, y, z = (d / np.linalg.norm(d, axis=1, keepdims=True)).T
    # The real SH basis in 3DGS's sign convention, written out from its polynomials.
    c1, c2, c3 = 0.4886025119029199, 1.0925484305920792, 0.5900435899266435
    basis = np.stack([
        np.full(n, 0.28209479177387814), -c1 * y, c1 * z, -c1 * x,
        c2 * x * y, -c2 * y * z, 0.31539156525252005 * (3 * z * z - 1), -c2 * x * z,
        0.5462742152960396 * (x * x - y * y),
        -c3 * y * (3 * x * x - y * y), 2.890611442640554 * x * y * z,
        -0.4570457994644658 * y * (5 * z * z - 1), 0.3731763325901154 * z * (5 * z * z - 3),
        -0.4570457994644658 * x * (5 * z * z - 1), 1.445305721320277 * z * (x * x - y * y),
        -c3 * x * (x * x - 3 * y * y)], axis=1)
    want = np.maximum(np.einsum("nk,nkc->nc", basis, sh.reshape(n, 16, 3)) + 0.5, 0.0)
    np.testing.assert_allclose(got, want, atol=1e-5)  # float32 sums of 16 O(1) terms
    assert (want == 0).any() and (want > 0.5).any()  # the clamp is exercised


def test_surfels_numpy_round_trip_and_params():
    rng = np.random.default_rng(2)
    n = 7
    q = rng.normal(size=(n, 4))
    s = Surfels.from_numpy(rng.normal(size=(n, 3)), rng.uniform(0.0, 1.0, (n, 2)), q,
                           rng.uniform(0.0, 1.0, n), {"albedo": rng.uniform(size=(n, 3)),
                                                       "segment": np.arange(n)})
    back = s.to_numpy()
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(back["rotation"], qn, atol=1e-6)  # float32 storage
    assert back["segment"].shape == (n, 1)
    t_u, t_v, nrm = (np.array(v, np.float64).reshape(3, n).T for v in s.tangent_frame())
    m = np.stack([t_u, t_v, nrm], axis=2)  # columns
    np.testing.assert_allclose(np.einsum("nij,nik->njk", m, m), np.broadcast_to(np.eye(3),
                               (n, 3, 3)), atol=1e-6)  # orthonormal to float32 precision
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-5)  # a rotation, not a flip
    ref_m = Rotation.from_quat(qn[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(m, ref_m, atol=1e-6)
    p = s.params()
    assert set(p) == {"position", "log_scale", "rotation", "opacity_logit", "channels.albedo",
                      "channels.segment"}
    assert p["position"] is s.position
    s.set_params({"opacity_logit": mi.Float(np.zeros(n, np.float32))})
    np.testing.assert_allclose(s.to_numpy()["opacity"], 0.5)
    with pytest.raises(ValueError, match="scale"):
        Surfels.from_numpy(np.zeros((2, 3)), -np.ones((2, 2)), np.ones((2, 4)), [0.5, 0.5])


@pytest.mark.cuda
def test_cuda_matches_llvm(cuda_variant):
    """Forward and backward on cuda_ad_rgb agree with llvm_ad_rgb (same float32 maths)."""
    from mi_shadowgs import backend

    camera = cameras()["perspective"]
    raw = random_scene(40, 3)

    def run():
        s = to_surfels(raw)
        params = s.params()
        for v in params.values():
            dr.enable_grad(v)
        out = rasterize(s, camera, s.channels, aovs=AOVS)
        dr.backward(sum((dr.sum(v.array) for k, v in out.items() if k != "count"),
                        mi.Float(0.0)))
        return ({k: np.array(v) for k, v in out.items()},
                {k: np.array(dr.grad(v)) for k, v in params.items()})

    cuda_out, cuda_grad = run()
    backend.set_variant("llvm_ad_rgb")
    llvm_out, llvm_grad = run()
    for k in llvm_out:  # float32 on both; atomics and FMA contraction differ: 1e-4
        np.testing.assert_allclose(cuda_out[k], llvm_out[k], atol=1e-4, rtol=1e-4)
    for k in llvm_grad:
        scale = np.abs(llvm_grad[k]).max()
        np.testing.assert_allclose(cuda_grad[k], llvm_grad[k], atol=1e-4 * scale)
