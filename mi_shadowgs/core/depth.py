"""Depth-map maths on Dr.Jit arrays: world points and pixel footprints of a rendered z-depth
image. Shading (receiver positions) and visibility (receiver offsets) both use them.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit
from mi_shadowgs.core.camera import Camera


def pixel_footprint(depth: mi.TensorXf, camera: Camera) -> mi.Float:
    """World size [H * W] of a pixel at the z-depth [H, W, 1] of each pixel."""
    if camera.is_ortho:
        return dr.full(mi.Float, camera.ortho_width / camera.width, dr.width(depth.array))
    return depth.array * (1.0 / camera.focal)


def unproject_depth(depth: mi.TensorXf, camera: Camera) -> mi.Point3f:
    """World points [H * W] of a z-depth image [H, W, 1] (row-major pixel order)."""
    h, w = depth.shape[0], depth.shape[1]
    idx = dr.arange(mi.UInt32, h * w)
    px = mi.Float(idx % w) + 0.5
    py = mi.Float(idx // w) + 0.5
    z = depth.array
    # Opaque: a new camera reuses the kernels (``core.jit``).
    cx, cy = (jit.opaque(v) for v in camera.principal_point)
    fx, fy = (jit.opaque(v) for v in camera.focal_xy)
    if camera.is_ortho:
        xc, yc = (px - cx) / fx, (py - cy) / fy
    else:
        xc, yc = (px - cx) / fx * z, (py - cy) / fy * z
    m = jit.opaque_matrix(np.linalg.inv(camera.world_to_cv())[:3])
    return mi.Point3f(*(m[i][0] * xc + m[i][1] * yc + m[i][2] * z + m[i][3] for i in range(3)))
