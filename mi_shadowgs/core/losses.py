"""Differentiable image losses over Dr.Jit tensors (stage 1 and later stages).

Images are ``mi.TensorXf`` of shape [H, W, C] (row 0 at the top). Every loss returns a
scalar ``mi.Float`` (width 1), the mean over pixels (and channels), so that its gradient
does not depend on the resolution's pixel count. Nothing here reads back to the host.

- ``l1``, ``ssim``/``d_ssim`` (11x11 Gaussian window, sigma 1.5, separable, zero padding as
  2DGS's ``F.conv2d(padding=5)``);
- ``normal_consistency``: 2DGS's ``1 - n_rendered . n_from_depth`` with the depth normal
  weighted by the (detached) accumulated opacity;
- ``distortion_loss``: mean of the rasterizer's "distortion" AOV (2DGS);
- ``mask_bce``: Eq. 13 of the paper on the accumulated opacity.
"""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2  # (K1 * L)^2 with L = 1 (images in [0, 1])
SSIM_C2 = 0.03 ** 2
# Opacity is clamped to [eps, 1 - eps] inside the BCE log (keeps the loss finite at 0 / 1).
BCE_EPS = 1e-6


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """The normalised 1D Gaussian [size] of SSIM (float64)."""
    x = np.arange(size, dtype=np.float64) - (size // 2)
    g = np.exp(-x * x / (2.0 * sigma * sigma))
    return g / g.sum()


def _check_image(t: mi.TensorXf, what: str) -> tuple[int, int, int]:
    if not isinstance(t, mi.TensorXf) or len(t.shape) != 3:
        shape = tuple(t.shape) if hasattr(t, "shape") else type(t).__name__
        raise ValueError(f"{what}: expected a TensorXf [H, W, C], got {shape}")
    return tuple(int(s) for s in t.shape)


def _mean(x) -> mi.Float:
    return dr.mean(x.array if isinstance(x, mi.TensorXf) else x)


def l1(render: mi.TensorXf, target: mi.TensorXf) -> mi.Float:
    """Mean absolute difference of two [H, W, C] images."""
    if _check_image(render, "l1 render") != _check_image(target, "l1 target"):
        raise ValueError(f"l1: shapes differ: {tuple(render.shape)} vs {tuple(target.shape)}")
    return _mean(dr.abs(render.array - target.array))


def _blur_axis(x: mi.Float, base: mi.UInt32, stride: int, length: int, taps: np.ndarray,
               size: int) -> mi.Float:
    """A zero-padded blur along one axis of ``x`` [size]: lane l walks the line of ``length``
    values at base[l] + i * stride and writes out[base + i * stride] = sum_k taps[k] x[base +
    (i + k - r) * stride]. A symbolic loop keeps the window in registers: one gather and one
    scatter per value, where one gather per tap read each value len(taps) times."""
    dr.eval(x)  # gathered from: an unevaluated x would be recomputed at every read
    r = len(taps) // 2
    lanes = dr.width(base)

    def read(i: mi.Int32) -> mi.Float:
        ok = (i >= 0) & (i < length)
        return dr.gather(mi.Float, x, base + mi.UInt32(dr.maximum(i, 0)) * stride, ok)

    out = dr.zeros(mi.Float, size)

    def body(i, window):
        window = window + [read(i + r)]  # the values at i - r .. i + r
        acc = mi.Float(0.0)
        for wk, v in zip(taps, window, strict=True):
            acc += float(wk) * v
        dr.scatter(out, acc, base + mi.UInt32(i) * stride)
        return i + 1, window[1:]

    i0 = dr.zeros(mi.Int32, lanes)
    dr.while_loop((i0, [read(i0 + (k - r)) for k in range(2 * r)]),
                  lambda i, window: i < length, body, label="blur_axis")
    dr.eval(out)
    return out


def _blur_rows(x: mi.Float, layers: int, h: int, w: int, c: int, taps: np.ndarray
               ) -> mi.Float:
    """The x pass of the separable blur over ``layers`` stacked [H, W, C] images
    ([layers * H * W * C], zero padding), evaluated: one lane per row and channel."""
    lane = dr.arange(mi.UInt32, layers * h * c)
    line = lane // c  # layer * h + row
    return _blur_axis(x, line * (w * c) + (lane - line * c), c, w, taps, layers * h * w * c)


def _blur_columns(t: mi.Float, layers: int, h: int, w: int, c: int, taps: np.ndarray
                  ) -> list[mi.Float]:
    """The y pass over the x pass ``t`` of ``layers`` stacked images: each layer's blur
    [H * W * C] (one lane per column and channel)."""
    n = h * w * c
    lane = dr.arange(mi.UInt32, layers * w * c)
    layer = lane // (w * c)
    out = _blur_axis(t, layer * n + (lane - layer * (w * c)), w * c, h, taps, layers * n)
    if layers == 1:
        return [out]
    idx = dr.arange(mi.UInt32, n)
    return [dr.gather(mi.Float, out, idx + k * n) for k in range(layers)]


def _blur_gather(x: mi.Float, h: int, w: int, c: int, taps: np.ndarray) -> mi.Float:
    """Separable zero-padded convolution of a flat [H, W, C] image with ``taps`` (odd)."""
    return _blur_columns(_blur_rows(x, 1, h, w, c, taps), 1, h, w, c, taps)[0]


class _BlurOp(dr.CustomOp):
    """``_blur_gather`` with its adjoint by hand. A zero-padded convolution with symmetric
    taps is self-adjoint, so the backward pass blurs the output gradient with the same
    gathers; Dr.Jit's own derivative of the gathers would scatter-add every tap (atomics:
    the D-SSIM term cost ~12 ms of a 47 ms stage-1 step at 128^2)."""

    def eval(self, x, h, w, c, taps):
        self.args = (h, w, c, taps)
        return _blur_gather(x, h, w, c, taps)

    def forward(self):
        self.set_grad_out(_blur_gather(self.grad_in("x"), *self.args))

    def backward(self):
        self.set_grad_in("x", _blur_gather(self.grad_out(), *self.args))

    def name(self):
        return "ssim_blur"


def _blur(x: mi.Float, h: int, w: int, c: int, taps: np.ndarray) -> mi.Float:
    """``_blur_gather`` with a self-adjoint derivative (``_BlurOp``); ``taps`` symmetric."""
    if not np.allclose(taps, taps[::-1]):
        raise ValueError("_blur: the taps must be symmetric (the adjoint is the same blur)")
    if not dr.grad_enabled(x):
        return _blur_gather(x, h, w, c, taps)
    return dr.custom(_BlurOp, x, h, w, c, taps)


@dataclasses.dataclass(frozen=True)
class SsimTarget:
    """A fixed image's SSIM statistics (``ssim_target``): a training view's target is
    compared with a new render at every step, and its two blurs need computing only once
    (two of the five blurs of ``ssim_map``'s forward pass)."""

    image: mi.TensorXf  # [H, W, C]
    mean: mi.Float  # [H * W * C] the blurred image
    variance: mi.Float  # [H * W * C] the blurred square minus the mean's square
    window: int
    sigma: float


def ssim_target(b: mi.TensorXf, window: int = SSIM_WINDOW,
                sigma: float = SSIM_SIGMA) -> SsimTarget:
    """``b``'s SSIM statistics, evaluated now, for ``ssim_map(a, target)``."""
    h, w, c = _check_image(b, "ssim target")
    taps = gaussian_window(window, sigma)
    y = dr.detach(b.array)
    mean = _blur(y, h, w, c, taps)
    variance = _blur(y * y, h, w, c, taps) - mean * mean
    dr.eval(mean, variance)
    return SsimTarget(b, mean, variance, window, sigma)


def ssim_map(a: mi.TensorXf, b: mi.TensorXf | SsimTarget, window: int = SSIM_WINDOW,
             sigma: float = SSIM_SIGMA) -> mi.TensorXf:
    """Per-pixel, per-channel SSIM [H, W, C] of two images (Gaussian window, zero padding).
    ``b`` may be an ``SsimTarget`` (its statistics computed once; not differentiated)."""
    target = b if isinstance(b, SsimTarget) else None
    if target is not None:
        if (target.window, target.sigma) != (window, sigma):
            raise ValueError(f"ssim: the target's statistics are for window {target.window}, "
                             f"sigma {target.sigma}, not {window}, {sigma}")
        b = target.image
    shape = _check_image(a, "ssim a")
    if shape != _check_image(b, "ssim b"):
        raise ValueError(f"ssim: shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    h, w, c = shape
    taps = gaussian_window(window, sigma)
    x, y = a.array, b.array
    mu_x = _blur(x, h, w, c, taps)
    if target is not None:
        mu_y, syy = target.mean, target.variance
    else:
        mu_y = _blur(y, h, w, c, taps)
        syy = _blur(y * y, h, w, c, taps) - mu_y * mu_y
    sxx = _blur(x * x, h, w, c, taps) - mu_x * mu_x
    sxy = _blur(x * y, h, w, c, taps) - mu_x * mu_y
    num = (2.0 * mu_x * mu_y + SSIM_C1) * (2.0 * sxy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sxx + syy + SSIM_C2)
    return mi.TensorXf(num / den, shape=shape)


def ssim(a: mi.TensorXf, b: mi.TensorXf | SsimTarget) -> mi.Float:
    """Mean SSIM of two [H, W, C] images."""
    return _mean(ssim_map(a, b))


class _DssimOp(dr.CustomOp):
    """1 - mean SSIM of a render against an ``SsimTarget``, forward and backward by hand.

    Forward: one blur of the stacked (x, x^2, x y), then the SSIM formula and its mean.
    Backward: with S = A1 A2 / (B1 B2) of the blurred moments m1 = G x, m2 = G x^2,
    m12 = G x y (sxx = m2 - m1^2, sxy = m12 - m1 mu_y), dL/dx = G a + 2 x G b + y G c
    for the per-pixel a = dL/dm1, b = dL/dm2, c = dL/dm12 (the zero-padded symmetric blur
    is self-adjoint). Two kernels forward and three backward, for the six blurs that Dr.Jit's
    AD of ``ssim_map`` (the reference) ran in three times the time."""

    def eval(self, x, target: SsimTarget, h: int, w: int, c: int):
        self.args = (target, h, w, c)
        self.x = x
        taps = gaussian_window(target.window, target.sigma)
        y = dr.detach(target.image.array)
        n = h * w * c
        idx = dr.arange(mi.UInt32, 3 * n)
        layer = idx // n
        src = dr.gather(mi.Float, x, idx - layer * n)
        other = dr.gather(mi.Float, y, idx - layer * n)
        stacked = dr.select(layer == 0, src, src * dr.select(layer == 1, src, other))
        m1, m2, m12 = _blur_columns(_blur_rows(stacked, 3, h, w, c, taps), 3, h, w, c, taps)
        self.moments = (m1, m2, m12)
        s = _ssim_terms(m1, m2, m12, target)[0]
        dr.eval(m1, m2, m12)
        return 1.0 - dr.mean(s)

    def backward(self):
        target, h, w, c = self.args
        taps = gaussian_window(target.window, target.sigma)
        n = h * w * c
        g = -self.grad_out() / n  # dL/dS per pixel and channel
        m1, m2, m12 = self.moments
        s, a1, a2, b1, b2 = _ssim_terms(m1, m2, m12, target)
        mu_y = target.mean
        # b1 >= C1 and b2 >= C2 are positive; a2 (2 sxy + C2) may be 0, so never divided by.
        q = dr.rcp(b1 * b2)
        da = 2.0 * g * (mu_y * (a2 - a1) * q + m1 * s * (dr.rcp(b2) - dr.rcp(b1)))  # dL/dm1
        db = -g * s * dr.rcp(b2)  # dL/dm2
        dc = 2.0 * g * a1 * q  # dL/dm12
        idx = dr.arange(mi.UInt32, 3 * n)
        layer = idx // n
        local = idx - layer * n
        stacked = dr.select(layer == 0, dr.gather(mi.Float, da, local),
                            dr.select(layer == 1, dr.gather(mi.Float, db, local),
                                      dr.gather(mi.Float, dc, local)))
        dr.eval(stacked)
        ga, gb, gc = _blur_columns(_blur_rows(stacked, 3, h, w, c, taps), 3, h, w, c, taps)
        y = dr.detach(target.image.array)
        self.set_grad_in("x", ga + 2.0 * self.x * gb + y * gc)

    def name(self):
        return "d_ssim"


def _ssim_terms(m1, m2, m12, target: SsimTarget) -> tuple:
    """(S, A1, A2, B1, B2) per pixel and channel from the render's blurred moments."""
    mu_y, syy = target.mean, target.variance
    a1 = 2.0 * m1 * mu_y + SSIM_C1
    a2 = 2.0 * (m12 - m1 * mu_y) + SSIM_C2
    b1 = m1 * m1 + mu_y * mu_y + SSIM_C1
    b2 = (m2 - m1 * m1) + syy + SSIM_C2
    return a1 * a2 / (b1 * b2), a1, a2, b1, b2


def d_ssim(a: mi.TensorXf, b: mi.TensorXf | SsimTarget) -> mi.Float:
    """1 - SSIM (the D-SSIM term of 3DGS/2DGS's photometric loss). Against an
    ``SsimTarget`` (a training view's) by ``_DssimOp``, otherwise by ``ssim_map``."""
    if not isinstance(b, SsimTarget):
        return 1.0 - ssim(a, b)
    h, w, c = _check_image(a, "ssim a")
    if (h, w, c) != tuple(int(s) for s in b.image.shape):
        raise ValueError(f"ssim: shapes differ: {tuple(a.shape)} vs {tuple(b.image.shape)}")
    return dr.custom(_DssimOp, a.array, b, h, w, c)


def _camera_rotation(camera) -> list[list[mi.Float]]:
    """World -> CV camera rotation as opaque scalars (new cameras reuse the kernels)."""
    return jit.opaque_matrix(camera.world_to_cv()[:3, :3])


DEPTH_NORMAL_DIFFERENCES = ("central", "same_plane")


def depth_normals(depth: mi.TensorXf, camera, differences: str = "central"
                  ) -> tuple[mi.Vector3f, mi.Bool]:
    """Unit normals [H*W] (CV camera frame, facing the camera) from a z-depth map [H, W, 1].

    Points are unprojected at pixel centres; the normal is the cross product of central
    differences (``differences="central"``, 2DGS's ``depth_to_normal``) or, per axis, of the
    one-sided difference on the side where the surface stays planar (``"same_plane"``): at a
    crease or an occluding edge the central difference spans both surfaces and tilts the
    normal, while one side lies on the pixel's own surface. A plane's inverse depth is
    affine in pixel coordinates, so the side whose second difference of 1/z is smaller is
    taken (the 2-pixel ring falls back to central differences). Border pixels, and pixels
    with a zero-depth neighbour, are invalid (second return value False) and get a zero
    normal.
    """
    if differences not in DEPTH_NORMAL_DIFFERENCES:
        raise ValueError(f"depth_normals: differences must be one of "
                         f"{DEPTH_NORMAL_DIFFERENCES}, got {differences!r}")
    h, w, c = _check_image(depth, "depth_normals depth")
    if c != 1:
        raise ValueError(f"depth_normals: depth must be [H, W, 1], got {tuple(depth.shape)}")
    if camera.is_ortho:
        raise ValueError("depth_normals: perspective cameras only")
    fx, fy = (jit.opaque(v) for v in camera.focal_xy)
    cx, cy = (jit.opaque(v) for v in camera.principal_point)
    z = depth.array
    idx = dr.arange(mi.UInt32, h * w)
    yi = idx // w
    xi = idx - yi * w
    # [H*W] camera-frame points
    px = (mi.Float(xi) + 0.5 - cx) / fx * z
    py = (mi.Float(yi) + 0.5 - cy) / fy * z
    pts = mi.Vector3f(px, py, z)
    inner = (xi > 0) & (xi < w - 1) & (yi > 0) & (yi < h - 1)

    def at(off):
        return dr.gather(mi.Vector3f, pts, mi.UInt32(mi.Int32(idx) + off), inner)

    right, left, down, up = at(1), at(-1), at(w), at(-w)
    valid = inner & (right.z > 0) & (left.z > 0) & (down.z > 0) & (up.z > 0) & (z > 0)
    if differences == "central":
        n = dr.cross(right - left, down - up)
    else:
        # The side is a choice made on detached depth, not a quantity to differentiate.
        zd = dr.detach(z)
        inv = dr.select(zd > 0, dr.rcp(dr.select(zd > 0, zd, 1.0)), 0.0)
        inner2 = (xi > 1) & (xi < w - 2) & (yi > 1) & (yi < h - 2)

        def inv_at(off):
            return dr.gather(mi.Float, inv, mi.UInt32(mi.Int32(idx) + off), inner2)

        def forward_side(step):  # True: the +step side is the planar one
            a, b = inv_at(step), inv_at(2 * step)
            c, d = inv_at(-step), inv_at(-2 * step)
            return dr.abs(b - 2.0 * a + inv) <= dr.abs(inv - 2.0 * c + d)

        right_planar, down_planar = forward_side(1), forward_side(w)
        dx = dr.select(~inner2, right - left, dr.select(right_planar, right - pts, pts - left))
        dy = dr.select(~inner2, down - up, dr.select(down_planar, down - pts, pts - up))
        n = dr.cross(dx, dy)
    n2 = dr.squared_norm(n)
    valid &= n2 > 0
    n = n * dr.rsqrt(dr.select(valid, n2, 1.0))
    # Face the camera: the view ray is +pts in the camera frame.
    n = dr.select(dr.dot(n, pts) > 0, -n, n)
    return dr.select(valid, n, 0.0), valid


def normal_consistency(normal: mi.TensorXf, depth: mi.TensorXf, alpha: mi.TensorXf,
                       camera, differences: str = "central") -> mi.Float:
    """2DGS's normal consistency: mean over pixels of 1 - n_rend . (alpha * n_depth).

    ``normal`` [H, W, 3] is the rasterizer's world-space normal AOV (alpha-weighted, facing
    the camera), ``depth`` [H, W, 1] its expected z-depth, ``alpha`` [H, W, 1] its opacity
    (detached here, as 2DGS does). Gradients reach both the normals and the depth.
    """
    h, w, _ = _check_image(normal, "normal_consistency normal")
    nd, _ = depth_normals(depth, camera, differences)  # [H*W] camera frame
    r = _camera_rotation(camera)
    nw = dr.unravel(mi.Vector3f, normal.array)  # [H*W] world
    nc = mi.Vector3f(*(r[i][0] * nw.x + r[i][1] * nw.y + r[i][2] * nw.z for i in range(3)))
    a = dr.detach(alpha.array)
    return dr.mean(1.0 - a * dr.dot(nc, nd))


def distortion_loss(distortion: mi.TensorXf) -> mi.Float:
    """Mean of the rasterizer's depth-distortion AOV [H, W, 1] (2DGS L_d)."""
    _check_image(distortion, "distortion_loss")
    return _mean(distortion)


def mask_bce(alpha: mi.TensorXf, mask: mi.TensorXf) -> mi.Float:
    """Eq. 13: mean of -M log O - (1 - M) log(1 - O), O = accumulated opacity [H, W, 1].

    ``mask`` [H, W, 1] holds values in [0, 1] (binary or soft coverage).
    """
    if _check_image(alpha, "mask_bce alpha") != _check_image(mask, "mask_bce mask"):
        raise ValueError(f"mask_bce: shapes differ: {tuple(alpha.shape)} vs "
                         f"{tuple(mask.shape)}")
    o = dr.clip(alpha.array, BCE_EPS, 1.0 - BCE_EPS)
    m = mask.array
    return dr.mean(-m * dr.log(o) - (1.0 - m) * dr.log(1.0 - o))


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of images in [0, 1] for a mean squared error (host-side helper)."""
    return 10.0 * math.log10(1.0 / max(mse, 1e-20))
