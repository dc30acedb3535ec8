"""Lens distortion of real cameras (nerfstudio / COLMAP ``OPENCV``) and undistortion of their
images to the pinhole the rest of the project renders.

The model is nerfstudio's ``OPENCV`` with its ``k1..k4``, ``p1``, ``p2`` fields: on
normalised camera coordinates ``(x, y)`` (CV frame, ``r2 = x^2 + y^2``)

    d  = 1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4
    xd = d x + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = d y + 2 p2 x y + p1 (r2 + 2 y^2)

An undistorted image keeps the camera's ``fx, fy, cx, cy``: each of its pixel centres is
distorted forward and the photo sampled there (bilinear), so no inverse is iterated.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from mi_shadowgs.core.camera import Camera

FIELDS = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclasses.dataclass(frozen=True)
class Distortion:
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def is_identity(self) -> bool:
        return all(getattr(self, f) == 0.0 for f in FIELDS)

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """Normalised pinhole coordinates [M, 2] -> distorted ones [M, 2]."""
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        d = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * self.k4)))
        xd = d * x + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = d * y + 2.0 * self.p2 * x * y + self.p1 * (r2 + 2.0 * y * y)
        return np.stack([xd, yd], axis=-1)


def source_pixels(camera: Camera, distortion: Distortion) -> np.ndarray:
    """Where each pixel centre [H*W, 2] of the undistorted image lies in the photo."""
    fx, fy = camera.focal_xy
    cx, cy = camera.principal_point
    pix = camera.pixel_grid()
    xy = np.stack([(pix[:, 0] - cx) / fx, (pix[:, 1] - cy) / fy], axis=-1)
    xyd = distortion.apply(xy)
    return np.stack([xyd[:, 0] * fx + cx, xyd[:, 1] * fy + cy], axis=-1)


def undistort(image: np.ndarray, camera: Camera, distortion: Distortion,
              order: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The pinhole view [H, W, C] of a distorted photo [H, W, C] taken by ``camera``, and
    [H, W] bool: pixels whose source lies inside the photo (the rest are 0)."""
    h, w = image.shape[:2]
    src = source_pixels(camera, distortion)
    # array index = pixel coordinate - 0.5 (pixel centres at half-integers)
    coords = np.stack([src[:, 1] - 0.5, src[:, 0] - 0.5])  # [2, H*W] (row, col)
    inside = ((coords[0] >= -0.5) & (coords[0] <= h - 0.5) & (coords[1] >= -0.5)
              & (coords[1] <= w - 0.5))
    img = image.reshape(h, w, -1)
    out = np.stack([ndimage.map_coordinates(img[..., c].astype(np.float64), coords,
                                            order=order, mode="nearest")
                    for c in range(img.shape[-1])], axis=-1)
    out[~inside] = 0.0
    return out.reshape(image.shape).astype(image.dtype), inside.reshape(h, w)
