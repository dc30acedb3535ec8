"""The rasterizer fuzzer (``python -m validation.fuzz``): 50 seeded cases in the suite, a
check that it can fail at all, and the hard cases it found."""

from __future__ import annotations

import numpy as np

from mi_shadowgs.core import surfels
from mi_shadowgs.core.camera import Camera
from validation.fuzz import run_fuzz


def test_fuzz_50_seeded_cases():
    result = run_fuzz(50, seed_value=0)
    assert result.failures == 0, result.summary()
    assert result.cases == 50


def test_fuzz_finds_a_broken_kernel(monkeypatch):
    # Without quaternion_frame's guard a zero quaternion normalises to 0/0 = NaN: the
    # fuzzer draws zero quaternions and must report it.
    monkeypatch.setattr(surfels, "_QUAT_NORM2_MIN", -1.0)
    result = run_fuzz(30, seed_value=0, shrink=False)
    assert result.failures >= 1 and result.minimal is not None
    assert any("NaN" in p for p in result.problems), result.problems
    assert any(not any(q) for q in result.minimal.rotation)


def test_look_at_along_up_and_z():
    # Found by the fuzzer: looking along +-Z with up = +-Z gave a NaN camera (the fallback
    # up was +Z itself).
    for d in ((0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)):
        cam = Camera.look_at((0.0, 0.0, 0.0), d, up=d, width=4, height=4, fov_x=1.0)
        r = cam.c2w[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(cam.forward, d, atol=1e-12)
