"""TensoIR/NeRF-synthetic camera placement around a normalised object (Y-up world).

Training views: random directions on the upper hemisphere (uniform in solid angle between
two elevations), looking at the object's centre. Test views: a spiral, one turn in azimuth
while the elevation swings between two bounds, as TensoIR's test paths do.
"""

from __future__ import annotations

import math

import numpy as np

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import direction_from_angles


def _camera(direction: np.ndarray, target: np.ndarray, distance: float, fov_x: float,
            width: int, height: int) -> Camera:
    return Camera.look_at(target + distance * direction, target, fov_x=fov_x, width=width,
                          height=height)


def train_cameras(n: int, rng: np.random.Generator, target, distance: float, fov_x: float,
                  width: int, height: int, min_elevation_deg: float,
                  max_elevation_deg: float) -> list[Camera]:
    """``n`` cameras at ``distance`` from ``target`` [3], directions uniform in solid angle."""
    y_lo, y_hi = math.sin(math.radians(min_elevation_deg)), math.sin(math.radians(
        max_elevation_deg))
    target = np.asarray(target, dtype=np.float64)
    cams = []
    for _ in range(n):
        y = rng.uniform(y_lo, y_hi)
        phi = rng.uniform(0.0, 2.0 * math.pi)
        r = math.sqrt(max(0.0, 1.0 - y * y))
        d = np.array([r * math.cos(phi), y, -r * math.sin(phi)])
        cams.append(_camera(d, target, distance, fov_x, width, height))
    return cams


def test_cameras(n: int, target, distance: float, fov_x: float, width: int, height: int,
                 min_elevation_deg: float, max_elevation_deg: float) -> list[Camera]:
    """``n`` cameras on a spiral: azimuth over one turn, elevation swinging between bounds."""
    target = np.asarray(target, dtype=np.float64)
    cams = []
    for i in range(n):
        t = i / max(n, 1)
        az = 360.0 * t
        el = min_elevation_deg + (max_elevation_deg - min_elevation_deg) * 0.5 * (
            1.0 - math.cos(2.0 * math.pi * t))
        cams.append(_camera(direction_from_angles(az, el), target, distance, fov_x, width,
                            height))
    return cams
