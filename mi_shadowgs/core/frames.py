"""Small geometry helpers shared by the stages: rotations and frames (NumPy, float64)."""

from __future__ import annotations

import numpy as np


def orthonormal_frame(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents [M, 3] each, completing unit ``normals`` [M, 3] to a right-handed frame.

    Uses the branchless construction of Duff et al. (2017), stable for every direction.
    """
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t1 = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=-1)
    t2 = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=-1)
    return t1, t2


def matrix_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """Rotation matrices [M, 3, 3] -> unit quaternions [M, 4] in (w, x, y, z) order."""
    r = np.asarray(rot, dtype=np.float64)
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    # Pick, per matrix, the numerically largest of the four candidate components.
    cands = np.stack([1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22,
                      1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], axis=-1)
    k = np.argmax(cands, axis=-1)
    q = np.empty((len(r), 4))
    s = 0.5 / np.sqrt(np.maximum(cands[np.arange(len(r)), k], 1e-300))
    w = k == 0
    q[w] = np.stack([0.25 / s[w], (r[w, 2, 1] - r[w, 1, 2]) * s[w],
                     (r[w, 0, 2] - r[w, 2, 0]) * s[w], (r[w, 1, 0] - r[w, 0, 1]) * s[w]], -1)
    x = k == 1
    q[x] = np.stack([(r[x, 2, 1] - r[x, 1, 2]) * s[x], 0.25 / s[x],
                     (r[x, 0, 1] + r[x, 1, 0]) * s[x], (r[x, 0, 2] + r[x, 2, 0]) * s[x]], -1)
    y = k == 2
    q[y] = np.stack([(r[y, 0, 2] - r[y, 2, 0]) * s[y], (r[y, 0, 1] + r[y, 1, 0]) * s[y],
                     0.25 / s[y], (r[y, 1, 2] + r[y, 2, 1]) * s[y]], -1)
    z = k == 3
    q[z] = np.stack([(r[z, 1, 0] - r[z, 0, 1]) * s[z], (r[z, 0, 2] + r[z, 2, 0]) * s[z],
                     (r[z, 1, 2] + r[z, 2, 1]) * s[z], 0.25 / s[z]], -1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[:, :1] < 0.0, -q, q)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions [M, 4] (w, x, y, z), any norm (zero -> identity) -> rotations [M, 3, 3]."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(norm > 0.0, q / np.where(norm > 0.0, norm, 1.0), np.array([1.0, 0, 0, 0]))
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=-2)


def frame_to_quaternion(normals: np.ndarray) -> np.ndarray:
    """Quaternions [M, 4] (w, x, y, z) whose rotation's third column is ``normals`` [M, 3]."""
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    t1, t2 = orthonormal_frame(n)
    return matrix_to_quaternion(np.stack([t1, t2, n], axis=-1))
