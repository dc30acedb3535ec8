"""Camera poses and intrinsics checked as a loader reads them.

A camera-to-world matrix is a rigid transform: its 3x3 block a rotation (orthonormal, det
+1) and its bottom row ``0 0 0 1``. Anything else (a shear, a mirror, a projective row) is
still a finite, invertible matrix, and trained on it gave a wrong model without a word
(a sheared rotation: 14.96 dB against 16.9; a bottom row ``0 0 0 2``: mask IoU 0.40). Each
is refused naming the file, the frame and the field. A rotation scaled uniformly (some
exporters bake a scene scale into the pose) is orthonormal up to that scale: it is divided
out, and the loader says so once per file.
"""

from __future__ import annotations

import math

import numpy as np

# |R^T R - I| (largest entry) a rotation may have, after a uniform scale is divided out:
# float32 poses written with 6-7 digits reach 1e-6; 1e-3 is a shear of 0.06 degrees.
ORTHONORMAL_TOLERANCE = 1e-3
# A uniform scale within this of 1 is left as it is (the matrix kept bit for bit).
SCALE_TOLERANCE = 1e-6
BOTTOM_ROW_TOLERANCE = 1e-6
# Fields of view a camera may have: below 0.5 degrees a focal length is a typo (fl_x = 1e12
# trained to a mask IoU of 0.008), above 175 it is no pinhole.
MIN_FOV_DEG = 0.5
MAX_FOV_DEG = 175.0
# fl_y / fl_x: square pixels give 1; anamorphic sensors stay well within this.
MAX_PIXEL_ASPECT = 4.0


class PoseError(ValueError):
    """A pose or intrinsic that is no camera; the message says what is wrong (the caller
    adds the file and the field)."""


def check_pose(m: np.ndarray) -> tuple[np.ndarray, float | None]:
    """(the pose, the uniform scale divided out of its rotation or None) of a finite 4x4
    camera-to-world ``m``. PoseError when it is not a rigid transform (up to that scale)."""
    m = np.asarray(m, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise PoseError("holds NaN or Inf")
    bottom = m[3]
    if np.max(np.abs(bottom - (0.0, 0.0, 0.0, 1.0))) > BOTTOM_ROW_TOLERANCE:
        raise PoseError(f"has bottom row {_row(bottom)}, not 0 0 0 1 (a camera pose is a "
                        "rigid transform, not a projective one)")
    r = m[:3, :3]
    det = float(np.linalg.det(r))
    if not math.isfinite(det) or abs(det) < 1e-12:
        raise PoseError("is singular (not a camera pose)")
    if det < 0:
        raise PoseError(f"has a mirrored rotation (determinant {det:.3g} < 0): a camera "
                        "pose turns, it does not reflect")
    scale = det ** (1.0 / 3.0)
    rn = r / scale
    error = float(np.max(np.abs(rn.T @ rn - np.eye(3))))
    if error > ORTHONORMAL_TOLERANCE:
        norms = np.linalg.norm(r, axis=0)
        raise PoseError(f"has a rotation that is not orthonormal (|R^T R - I| = {error:.3g} "
                        f"after its scale is taken out, over {ORTHONORMAL_TOLERANCE:g}; column "
                        f"lengths {_row(norms)}): a shear or an uneven scale")
    if not np.array_equal(bottom, (0.0, 0.0, 0.0, 1.0)):  # round-off of a written row
        m = m.copy()
        m[3] = (0.0, 0.0, 0.0, 1.0)
    if abs(scale - 1.0) <= SCALE_TOLERANCE:
        return m, None
    out = m.copy()
    out[:3, :3] = rn
    return out, scale


def check_intrinsics(width: int, height: int, fx: float, fy: float) -> None:
    """PoseError when focal lengths ``fx``, ``fy`` (pixels) give no sane pinhole for a
    ``width`` x ``height`` image (principal points are checked by the caller)."""
    for name, f, size in (("fl_x", fx, width), ("fl_y", fy, height)):
        if not math.isfinite(f) or f <= 0:
            raise PoseError(f"{name} must be a finite number > 0, got {f}")
        fov = math.degrees(2.0 * math.atan(0.5 * size / f))
        if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
            raise PoseError(f"{name} = {f:g} px gives a {fov:.3g} degree field of view over "
                            f"{size} px; a camera has {MIN_FOV_DEG:g} to {MAX_FOV_DEG:g}")
    if not 1.0 / MAX_PIXEL_ASPECT <= fy / fx <= MAX_PIXEL_ASPECT:
        raise PoseError(f"fl_y / fl_x = {fy / fx:.3g}: pixels that much taller than wide (or "
                        f"wider than tall) are no camera's; at most {MAX_PIXEL_ASPECT:g}")


def _row(values) -> str:
    return " ".join(f"{float(v):.6g}" for v in values)


def scaled_note(path, frames: list[int], scales: list[float]) -> str:
    """The one line saying that ``frames`` of ``path`` had their rotation's scale divided
    out."""
    shown = ", ".join(str(i) for i in frames[:8]) + (" ..." if len(frames) > 8 else "")
    return (f"{path}: the rotations of {len(frames)} frame(s) ({shown}) are orthonormal up to "
            f"a uniform scale ({min(scales):.6g} to {max(scales):.6g}); taken without it")


def duplicate_images(names: list[str]) -> tuple[int, int] | None:
    """(first, second) indices of two frames naming one image file, or None."""
    seen: dict[str, int] = {}
    for i, name in enumerate(names):
        if name in seen:
            return seen[name], i
        seen[name] = i
    return None
