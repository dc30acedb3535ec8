"""Stage 2's segment maps: the segment each pixel of a view shows, and their colours."""

from __future__ import annotations

import drjit as dr
import numpy as np

from mi_shadowgs.core import jit
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster import RasterConfig, rasterize
from mi_shadowgs.core.surfels import Surfels

_RASTER = RasterConfig()


def render_segment_map(surfels: Surfels, segments: np.ndarray, k: int, camera: Camera,
                       alpha_min: float = 0.5,
                       raster: RasterConfig = _RASTER) -> np.ndarray:
    """[H, W] int map: 1 + the segment with the largest rendered one-hot weight, 0 where
    the rendered alpha is below ``alpha_min`` (background)."""
    seg = np.asarray(segments).reshape(-1).astype(np.int64)
    if seg.size != surfels.count or (seg.size and (seg.min() < 0 or seg.max() >= k)):
        raise ValueError(f"render_segment_map: need {surfels.count} segment ids in [0, {k})")
    onehot = np.zeros((seg.size, k), np.float32)
    onehot[np.arange(seg.size), seg] = 1.0
    with dr.suspend_grad():
        out = rasterize(surfels, camera, {"onehot": jit.tensor(onehot)}, aovs=("alpha",),
                        config=raster)
    w = np.asarray(out["onehot"].numpy()).reshape(camera.height, camera.width, k)
    alpha = np.asarray(out["alpha"].numpy()).reshape(camera.height, camera.width)
    return np.where(alpha >= alpha_min, w.argmax(-1) + 1, 0).astype(np.int32)


def segment_colors(k: int) -> np.ndarray:
    """[k + 1, 3] sRGB uint8 colours: index 0 (background) black, then well-spread hues."""
    cols = np.zeros((k + 1, 3), np.uint8)
    for i in range(k):
        h = (i * 0.618033988749895) % 1.0  # golden-ratio hue steps
        s, v = (0.75, 0.95) if i % 2 == 0 else (0.55, 0.75)
        hsv = np.array([h, s, v])
        cols[i + 1] = np.round(_hsv_to_rgb(hsv) * 255).astype(np.uint8)
    return cols


def _hsv_to_rgb(hsv: np.ndarray) -> np.ndarray:
    h, s, v = hsv
    i = int(h * 6.0) % 6
    f = h * 6.0 - int(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])
