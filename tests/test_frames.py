"""core.frames (rotations and frames, float64) against SciPy's Rotation as the reference.

SciPy orders a quaternion (x, y, z, w); ours is (w, x, y, z) (docs/conventions.md).
Tolerances: float64 maths on O(1) values, a few operations deep: 1e-12.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from mi_shadowgs.core.frames import (
    frame_to_quaternion,
    matrix_to_quaternion,
    orthonormal_frame,
    quaternion_to_matrix,
)

TOL = 1e-12


def _to_scipy(q_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.asarray(q_wxyz)[:, [1, 2, 3, 0]])


def _hard_rotations() -> Rotation:
    """Random rotations plus those near the branches of the matrix -> quaternion conversion:
    the identity and half-turns about x, y, z and a diagonal (w ~ 0), where a trace-only
    formula loses its digits."""
    rng = np.random.default_rng(0)
    axes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], np.float64)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    near_half_turns = Rotation.from_rotvec(axes * (np.pi - 1e-9))
    return Rotation.concatenate([Rotation.random(200, random_state=1),
                                 Rotation.identity(1), near_half_turns,
                                 Rotation.from_rotvec(axes * np.pi),
                                 Rotation.from_rotvec(rng.normal(size=(4, 3)) * 1e-9)])


def test_quaternion_to_matrix_matches_scipy_at_any_norm():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(300, 4)) * rng.uniform(1e-3, 1e3, (300, 1))  # not unit
    np.testing.assert_allclose(quaternion_to_matrix(q), _to_scipy(q).as_matrix(),
                               rtol=0, atol=TOL)
    # A zero quaternion (a surfel whose rotation collapsed) reads as the identity.
    np.testing.assert_array_equal(quaternion_to_matrix(np.zeros((1, 4)))[0], np.eye(3))


def test_matrix_to_quaternion_matches_scipy_with_w_positive():
    rot = _hard_rotations()
    got = matrix_to_quaternion(rot.as_matrix())
    want = rot.as_quat()[:, [3, 0, 1, 2]]  # (w, x, y, z)
    want = np.where(want[:, :1] < 0.0, -want, want)  # q and -q: the same rotation
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, rtol=0, atol=TOL)
    assert np.all(got[:, 0] >= 0.0)
    # At w = 0 exactly (half-turns) both signs are canonical: compare as rotations there.
    same_sign = np.abs(want[:, 0]) > 1e-6
    np.testing.assert_allclose(got[same_sign], want[same_sign], rtol=0, atol=TOL)
    np.testing.assert_allclose(_to_scipy(got).as_matrix(), rot.as_matrix(), rtol=0, atol=TOL)


def test_frames_are_right_handed_with_the_normal_third():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(500, 3))
    # The construction's hard directions: the poles and just either side of -z.
    n = np.concatenate([n, [[0, 0, 1], [0, 0, -1], [1e-9, 0, -1], [0, -1e-9, -1],
                            [1, 0, 0], [0, 1, 0]]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1, t2 = orthonormal_frame(n)
    frame = np.stack([t1, t2, n], axis=-1)  # [M, 3, 3], columns t1, t2, n
    np.testing.assert_allclose(np.einsum("mji,mjk->mik", frame, frame),
                               np.broadcast_to(np.eye(3), frame.shape), rtol=0, atol=TOL)
    np.testing.assert_allclose(np.linalg.det(frame), 1.0, rtol=0, atol=TOL)
    # The quaternion of that frame: SciPy's rotation of it has n as its third column.
    rot = _to_scipy(frame_to_quaternion(n)).as_matrix()
    np.testing.assert_allclose(rot[:, :, 2], n, rtol=0, atol=TOL)
    np.testing.assert_allclose(rot, frame, rtol=0, atol=TOL)
