"""Stage-1 losses and the evaluation metrics against float64 NumPy references, and the
losses' gradients against central finite differences."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowgs.core import losses, metrics
from mi_shadowgs.core.camera import Camera


def _t(a) -> mi.TensorXf:
    return mi.TensorXf(np.ascontiguousarray(a, dtype=np.float32))


def _ssim_ref(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Direct (non-separable) 11x11 Gaussian-window SSIM, zero padding, float64."""
    x = np.arange(11) - 5.0
    g = np.exp(-x * x / (2 * 1.5 ** 2))
    g /= g.sum()
    win = np.outer(g, g)
    h, w, c = a.shape

    def conv(img):
        p = np.pad(img, ((5, 5), (5, 5), (0, 0)))
        out = np.zeros_like(img)
        for i in range(11):
            for j in range(11):
                out += win[i, j] * p[i:i + h, j:j + w]
        return out

    mu_a, mu_b = conv(a), conv(b)
    saa = conv(a * a) - mu_a ** 2
    sbb = conv(b * b) - mu_b ** 2
    sab = conv(a * b) - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) *
                                                        (saa + sbb + c2))


@pytest.fixture
def images():
    rng = np.random.default_rng(1)
    a = rng.random((13, 17, 3))
    b = np.clip(a + 0.1 * rng.standard_normal(a.shape), 0, 1)
    return a, b


def test_l1_matches_numpy(images):
    a, b = images
    got = float(losses.l1(_t(a), _t(b))[0])
    # float32 inputs: |a - b| mean within 1e-6 of float64.
    assert got == pytest.approx(np.mean(np.abs(a.astype(np.float32) - b.astype(np.float32))),
                                abs=1e-6)


def test_ssim_matches_direct_2d_window(images):
    a, b = images
    ref = _ssim_ref(a.astype(np.float32).astype(np.float64),
                    b.astype(np.float32).astype(np.float64))
    got = losses.ssim_map(_t(a), _t(b)).numpy()
    # float32 variances (E[x^2] - mu^2 of values <= 1) lose ~1e-6; SSIM ratios amplify it
    # where variances are small: 1e-4 absolute is well above that and far below any bug.
    np.testing.assert_allclose(got, ref, atol=1e-4)
    np.testing.assert_allclose(metrics.ssim_map(a, b), _ssim_ref(a, b), atol=1e-12)
    assert float(losses.ssim(_t(a), _t(a))[0]) == pytest.approx(1.0, abs=1e-5)
    assert metrics.ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_mask_bce_matches_numpy():
    rng = np.random.default_rng(2)
    o = rng.random((9, 7, 1)) * 0.98 + 0.01
    m = (rng.random((9, 7, 1)) > 0.5).astype(np.float64)
    ref = np.mean(-m * np.log(o) - (1 - m) * np.log(1 - o))
    got = float(losses.mask_bce(_t(o), _t(m))[0])
    assert got == pytest.approx(ref, rel=1e-5)  # float32 logs: ~1e-7 relative each
    # Opacity exactly 0 or 1 stays finite (clamped at BCE_EPS).
    edge = float(losses.mask_bce(_t(np.zeros((2, 2, 1))), _t(np.ones((2, 2, 1))))[0])
    assert edge == pytest.approx(-np.log(losses.BCE_EPS), rel=1e-4)


def _cam(w=12, h=10):
    return Camera.look_at((0.3, 2.0, 3.0), (0.0, 0.2, 0.0), fov_x=0.8, width=w, height=h)


def _plane_depth(cam: Camera, n: np.ndarray, d: float) -> np.ndarray:
    """z-depth [H, W] of the plane n . x = d seen by ``cam``."""
    pix = cam.pixel_grid()
    p1 = cam.unproject(pix, np.ones(len(pix)))  # points at z = 1
    o = cam.origin
    t = (d - o @ n) / ((p1 - o) @ n)  # z-depth scales linearly along the ray
    return t.reshape(cam.height, cam.width)


def _depth_normals_ref(depth, cam: Camera, differences: str = "central") -> np.ndarray:
    """float64 world-space normals [H, W, 3] (0 on the 1-pixel border), facing the camera:
    unproject with Camera.unproject; central differences, or per pixel and axis the
    one-sided difference on the side whose inverse depth has the smaller second difference
    (central on the 2-pixel ring)."""
    h, w = depth.shape
    pts = cam.unproject(cam.pixel_grid(), depth.ravel()).reshape(h, w, 3)
    inv = 1.0 / depth
    nd = np.zeros((h, w, 3))
    for y in range(1, h - 1):
        for x in range(1, w - 1):
            p = pts[y, x]
            dx, dy = pts[y, x + 1] - pts[y, x - 1], pts[y + 1, x] - pts[y - 1, x]
            if differences == "same_plane" and 1 < x < w - 2 and 1 < y < h - 2:
                fwd = abs(inv[y, x + 2] - 2 * inv[y, x + 1] + inv[y, x])
                bwd = abs(inv[y, x] - 2 * inv[y, x - 1] + inv[y, x - 2])
                dx = pts[y, x + 1] - p if fwd <= bwd else p - pts[y, x - 1]
                fwd = abs(inv[y + 2, x] - 2 * inv[y + 1, x] + inv[y, x])
                bwd = abs(inv[y, x] - 2 * inv[y - 1, x] + inv[y - 2, x])
                dy = pts[y + 1, x] - p if fwd <= bwd else p - pts[y - 1, x]
            n = np.cross(dx, dy)
            n /= np.linalg.norm(n)
            nd[y, x] = -n if n @ (p - cam.origin) > 0 else n
    return nd


def _normal_consistency_ref(normal, depth, alpha, cam: Camera,
                            differences: str = "central") -> float:
    """float64 2DGS normal consistency with ``_depth_normals_ref``."""
    nd = _depth_normals_ref(depth, cam, differences)
    return float(np.mean(1.0 - alpha * np.sum(normal * nd, -1)))


def test_depth_normals_of_a_plane():
    cam = _cam()
    target = np.array([0.0, 0.2, 0.0])
    n = cam.origin - target + np.array([0.5, 0.0, -0.4])  # tilted, but facing the camera
    n /= np.linalg.norm(n)
    depth = _plane_depth(cam, n, float(n @ target))
    assert depth.min() > 0
    nd, valid = losses.depth_normals(_t(depth[..., None]), cam)
    r = cam.world_to_cv()[:3, :3]
    n_cam = r @ n
    n_cam = -n_cam if n_cam @ (r @ (target - cam.origin)) > 0 else n_cam
    got = np.array(nd).reshape(3, -1).T.reshape(cam.height, cam.width, 3)
    v = np.array(valid).reshape(cam.height, cam.width)
    assert v[1:-1, 1:-1].all() and not v[0].any() and not v[:, -1].any()
    # A plane's depth is exact up to float32 (~1e-7 relative); differences of neighbours
    # lose ~3 digits: 1e-3 on unit normals.
    np.testing.assert_allclose(got[1:-1, 1:-1], np.broadcast_to(n_cam, got[1:-1, 1:-1].shape),
                               atol=1e-3)


def test_d_ssim_blurs_stay_separable(images):
    """The training loss's D-SSIM, forward and backward, runs its 11x11 window as two
    passes along the lines: no kernel recomputes the x pass at each of the y pass's taps (a
    gather from an unevaluated array does; that kernel had 4374 operations and took 5 ms
    of a 25 ms stage-1 step at 128^2), nor the stacked moments at each tap of the x pass.
    The largest kernel here, a pass's loop, has ~110."""
    a, b = images
    x = _t(a)
    target = losses.ssim_target(_t(b))
    dr.enable_grad(x)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        dr.backward(losses.d_ssim(x, target))
        dr.eval(dr.grad(x))
        dr.sync_thread()
        ops = [k["operation_count"] for k in dr.kernel_history()
               if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert ops and max(ops) < 250, ops


@pytest.mark.parametrize("differences", losses.DEPTH_NORMAL_DIFFERENCES)
def test_normal_consistency_matches_numpy(differences):
    cam = _cam()
    rng = np.random.default_rng(3)
    depth = 3.0 + 0.3 * rng.random((cam.height, cam.width))
    normal = rng.standard_normal((cam.height, cam.width, 3))
    alpha = rng.random((cam.height, cam.width))
    ref = _normal_consistency_ref(normal, depth, alpha, cam, differences)
    got = float(losses.normal_consistency(_t(normal), _t(depth[..., None]),
                                          _t(alpha[..., None]), cam, differences)[0])
    # Random depth: central differences of float32 depths (~3e-7 abs) over ~0.1 steps.
    assert got == pytest.approx(ref, abs=1e-4)
    with pytest.raises(ValueError, match="differences"):
        losses.depth_normals(_t(depth[..., None]), cam, "sobel")


@pytest.mark.parametrize("crease", ["concave", "convex"])
def test_same_plane_depth_normals_at_a_crease(crease):
    """Hard case: two planes meeting in a crease (a ground under a wall: concave; a box's
    edge: convex). Central differences span both planes on each side of the crease and
    tilt the normal there by up to ~45 degrees (2DGS's fillets at an object's contact with
    its base); ``same_plane`` gives each pixel its own plane's normal but where both of its
    sides cross the crease. The reference is checked on the same pixels."""
    cam = Camera.look_at((0.3, 2.0, 3.0), (0.0, 0.2, 0.0), fov_x=0.8, width=40, height=32)
    n_ground = np.array([0.0, 1.0, 0.0])
    n_wall = np.array([0.0, 0.3, 1.0]) / np.linalg.norm([0.0, 0.3, 1.0])
    z_ground = _plane_depth(cam, n_ground, 0.0)
    z_wall = _plane_depth(cam, n_wall, float(n_wall @ np.array([0.0, 0.0, -0.2])))
    assert (z_ground > 0).all() and (z_wall > 0).all()
    # Seen from the camera, a concave crease shows the nearer plane, a convex one the farther.
    on_ground = z_ground <= z_wall if crease == "concave" else z_ground >= z_wall
    depth = np.where(on_ground, z_ground, z_wall)
    r = cam.world_to_cv()[:3, :3]
    true = np.where(on_ground[..., None], r @ n_ground, r @ n_wall)  # [H, W, 3] camera frame
    off = {}
    for mode in losses.DEPTH_NORMAL_DIFFERENCES:
        nd, valid = losses.depth_normals(_t(depth[..., None]), cam, mode)
        got = np.array(nd).reshape(3, -1).T.reshape(cam.height, cam.width, 3)
        v = np.array(valid).reshape(cam.height, cam.width)
        t = np.where(np.sum(true * got, -1, keepdims=True) < 0, -true, true)
        err = np.degrees(np.arccos(np.clip(np.sum(t * got, -1), -1.0, 1.0)))[v]
        off[mode] = int(np.sum(err > 2.0))
        ref = _depth_normals_ref(depth, cam, mode) @ r.T  # world -> camera frame
        # float32 differences of neighbours: 1e-3 on unit normals (the plane test's bound).
        np.testing.assert_allclose(got[v], ref[v], atol=1e-3)
    # The crease crosses every inner column: central differences tilt ~2 pixels a column.
    columns = int(np.sum(np.any(on_ground[1:] != on_ground[:-1], axis=0)[1:-1]))
    assert off["central"] >= 1.5 * columns
    assert off["same_plane"] <= off["central"] // 8


def _fd_check(fn, x0: np.ndarray, idx, eps: float, rtol: float, atol: float):
    x = _t(x0)
    dr.enable_grad(x)
    val = fn(x)
    dr.backward(val)
    g = np.asarray(dr.grad(x).numpy()).reshape(-1)
    flat = x0.reshape(-1)
    for i in idx:
        hi, lo = flat.copy(), flat.copy()
        hi[i] += eps
        lo[i] -= eps
        fd = (float(fn(_t(hi.reshape(x0.shape)))[0]) -
              float(fn(_t(lo.reshape(x0.shape)))[0])) / (2 * eps)
        assert g[i] == pytest.approx(fd, rel=rtol, abs=atol), f"entry {i}"


# Finite differences run in float32: with eps = 1e-2 the rounding of a loss of size ~1 is
# ~1e-7 / 1e-2 = 1e-5 on the gradient, and the truncation error is O(eps^2) ~ 1e-4 relative:
# rel 2e-2 / abs 2e-4 leave room for both and still catch a wrong factor or sign.
FD = dict(eps=1e-2, rtol=2e-2, atol=2e-4)


def test_d_ssim_gradient(images):
    a, b = images
    tb = _t(b)
    _fd_check(lambda x: losses.d_ssim(x, tb) + losses.l1(x, tb), a, [0, 40, 333, 600], **FD)


def test_ssim_with_the_targets_statistics_computed_once(images):
    """``ssim_target`` (the target's two blurs evaluated once per training view) gives the
    plain call's SSIM map and D-SSIM gradient: the same float32 operations, only evaluated
    earlier. Against a target, D-SSIM is the hand-written ``_DssimOp``: its value is checked
    against the float64 reference and its gradient against Dr.Jit's AD of ``ssim_map`` and
    finite differences, which catch a target whose statistics were differentiated or whose
    variance lost its mean term."""
    a, b = images
    tb = _t(b)
    target = losses.ssim_target(tb)
    np.testing.assert_allclose(losses.ssim_map(_t(a), target).numpy(),
                               losses.ssim_map(_t(a), tb).numpy(), atol=1e-6)
    np.testing.assert_allclose(losses.ssim_map(_t(a), target).numpy(),
                               _ssim_ref(a.astype(np.float32).astype(np.float64),
                                         b.astype(np.float32).astype(np.float64)), atol=1e-4)
    ref = _ssim_ref(a.astype(np.float32).astype(np.float64),
                    b.astype(np.float32).astype(np.float64))
    assert float(losses.d_ssim(_t(a), target)[0]) == pytest.approx(1.0 - ref.mean(), abs=1e-6)
    grads = []
    for other in (tb, target):
        x = _t(a)
        dr.enable_grad(x)
        dr.backward(losses.d_ssim(x, other))
        grads.append(dr.grad(x).numpy())
    np.testing.assert_allclose(grads[1], grads[0], atol=1e-7)
    _fd_check(lambda x: losses.d_ssim(x, target), a, [0, 40, 333, 600], **FD)
    with pytest.raises(ValueError, match="window"):
        losses.ssim_map(_t(a), target, window=7)


@pytest.mark.parametrize("differences", losses.DEPTH_NORMAL_DIFFERENCES)
def test_normal_consistency_gradient_wrt_depth_and_normal(differences):
    cam = _cam(8, 7)
    rng = np.random.default_rng(4)
    depth = 3.0 + 0.3 * rng.random((7, 8, 1))
    normal = rng.standard_normal((7, 8, 3))
    alpha = _t(rng.random((7, 8, 1)))
    tn, td = _t(normal), _t(depth)
    # "same_plane" picks a side per pixel; the steps below move no choice (random depth:
    # second differences of 1/z differ by ~1e-2, far above the depth step's ~1e-4).
    _fd_check(lambda d: losses.normal_consistency(tn, d, alpha, cam, differences), depth,
              [9, 18, 27, 30], eps=1e-3, rtol=3e-2, atol=3e-4)  # depth: a smaller step
    _fd_check(lambda n: losses.normal_consistency(n, td, alpha, cam, differences), normal,
              [30, 31, 50, 80], **FD)


def test_mask_bce_gradient():
    rng = np.random.default_rng(5)
    o = rng.random((5, 6, 1)) * 0.8 + 0.1
    m = _t((rng.random((5, 6, 1)) > 0.5).astype(np.float32))
    _fd_check(lambda x: losses.mask_bce(x, m), o, [0, 7, 13, 29], eps=1e-3, rtol=2e-2,
              atol=2e-4)


def test_metrics_known_values():
    a = np.zeros((4, 4, 3))
    b = np.full((4, 4, 3), 0.1)
    assert metrics.psnr(a, b) == pytest.approx(20.0, abs=1e-9)  # MSE 0.01
    m1 = np.zeros((4, 4), bool)
    m1[:2] = True
    m2 = np.zeros((4, 4), bool)
    m2[1:3] = True
    assert metrics.mask_iou(m1, m2) == pytest.approx(4 / 12)
    n_gt = np.zeros((1, 2, 3))
    n_gt[..., 2] = 1
    n_pred = np.array([[[0, 1, 1], [0, 0, 2.0]]])  # 45 degrees; 0 (unnormalised)
    ang = metrics.normal_angles_deg(n_pred, n_gt, np.ones((1, 2), bool))
    np.testing.assert_allclose(ang, [45.0, 0.0], atol=1e-9)
    d = metrics.depth_errors(np.array([[1.0, 2.5]]), np.array([[1.5, 2.0]]),
                             np.ones((1, 2), bool))
    assert d["mean_abs"] == pytest.approx(0.5) and d["mean_rel"] == pytest.approx(
        (0.5 / 1.5 + 0.5 / 2.0) / 2)
