"""The light-direction grid used by the decomposition, the datasets and the reports.

Defined once, here. World space is Y-up (docs/conventions.md). A *light direction* ``l``
points from the surface toward the light (the ``l`` of ``n . l``); Mitsuba's
``directional`` emitter takes the propagation direction, which is ``-l``.
"""

from __future__ import annotations

import math

import numpy as np

N_LIGHT_DIRECTIONS = 128
UP = np.array([0.0, 1.0, 0.0])
# The paper's 22 x 12 block visualisation of a light map (azimuth x elevation).
MAP_WIDTH, MAP_HEIGHT = 22, 12
_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def light_grid(n: int = N_LIGHT_DIRECTIONS) -> np.ndarray:
    """Unit directions over the upper hemisphere (y > 0), equal-area (Fibonacci), [n, 3].

    Each direction stands for the same solid angle, ``solid_angle(n) = 2 pi / n`` (paper
    Sec. V-A1). Deterministic: index k is always the same direction.
    """
    if n < 1:
        raise ValueError(f"light grid needs at least one direction, got n={n}")
    k = np.arange(n, dtype=np.float64)
    y = (k + 0.5) / n  # uniform in height => uniform in solid angle on the hemisphere
    r = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = k * _GOLDEN_ANGLE
    return np.stack([r * np.cos(phi), y, -r * np.sin(phi)], axis=-1)


def solid_angle(n: int = N_LIGHT_DIRECTIONS) -> float:
    """Solid angle of one grid direction: 2 pi / n."""
    return 2.0 * math.pi / n


def direction_from_angles(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit direction from azimuth (about +Y, from +X toward -Z) and elevation above y = 0."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.sin(el), -math.cos(el) * math.sin(az)])


def parse_number_fields(text, option: str, usage: str, layouts: dict[int, tuple[str, ...]]
                        ) -> tuple[list[float], tuple[str, ...], str]:
    """The finite numbers of comma-separated fields given to ``option`` (a string, or a
    sequence of numbers): ``layouts`` maps each allowed count of fields to the fields'
    names; ``usage`` is the form the message shows. Returns (values, their names, the
    option and value as messages name them); ValueError naming the field at fault."""
    parts = ([p.strip() for p in text.split(",")] if isinstance(text, str)
             else [str(p).strip() for p in text])
    shown = f"{option} {','.join(parts)!r}"
    names = layouts.get(len(parts))
    if names is None:
        raise ValueError(f"{shown}: expected {usage}, got {len(parts)} field(s)")
    values = []
    for name, part in zip(names, parts, strict=True):
        try:
            value = float(part)
        except ValueError:
            raise ValueError(f"{shown}: field {name} must be a number, got {part!r}") from None
        if not math.isfinite(value):
            raise ValueError(f"{shown}: field {name} must be finite, got {part!r}")
        values.append(value)
    return values, names, shown


def parse_angle_fields(text, option: str, usage: str, layouts: dict[int, tuple[str, ...]],
                       elevation: tuple[float, float, bool] = (-90.0, 90.0, True)
                       ) -> list[float]:
    """The numbers of a light given as ``AZ,EL[,...]`` (``parse_number_fields``), the
    first two azimuth and elevation in degrees. The elevation lies in [lo, hi] with
    ``elevation = (lo, hi, True)``, in (lo, hi] with ``(lo, hi, False)``. ValueError naming
    ``option``, the value and the field at fault."""
    values, _, shown = parse_number_fields(text, option, usage, layouts)
    lo, hi, closed = elevation
    el = values[1]
    if not ((lo <= el if closed else lo < el) and el <= hi):
        span = f"{'[' if closed else '('}{lo:g}, {hi:g}]"
        raise ValueError(f"{shown}: field elevation must be in {span} degrees, got {el:g}")
    return values


def angles_from_direction(direction) -> tuple[float, float]:
    """(azimuth in [0, 360), elevation) in degrees of a direction [3]: the inverse of
    ``direction_from_angles``."""
    d = np.asarray(direction, np.float64).reshape(3)
    d = d / np.linalg.norm(d)
    az = math.degrees(math.atan2(-d[2], d[0])) % 360.0
    return az, math.degrees(math.asin(float(np.clip(d[1], -1.0, 1.0))))


_NEAREST_CHUNK = 16384


def nearest_grid_index(directions: np.ndarray, grid: np.ndarray | None = None) -> np.ndarray:
    """Index of the grid direction closest in angle to each of ``directions`` [M, 3] -> [M]."""
    grid = light_grid() if grid is None else grid
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    out = np.empty(len(d), np.int64)
    for s in range(0, len(d), _NEAREST_CHUNK):  # [chunk, n] cosines stay in the cache
        out[s:s + _NEAREST_CHUNK] = np.argmax(d[s:s + _NEAREST_CHUNK] @ grid.T, axis=-1)
    return out


def directional_lights_to_map(directions: np.ndarray, irradiance: np.ndarray,
                              n: int = N_LIGHT_DIRECTIONS) -> np.ndarray:
    """Radiance map [n, 3] over the grid that stands for directional lights.

    A directional light of irradiance E (W/m^2 at normal incidence, RGB) becomes radiance
    E / solid_angle(n) at its nearest grid direction, so that the grid's quadrature
    ``sum_k L_k (n . l_k) dw`` gives back E (n . l) up to the snapping error.
    Lights below the horizon cannot be represented and raise ValueError.
    """
    directions = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    irradiance = np.atleast_2d(np.asarray(irradiance, dtype=np.float64))
    if irradiance.shape[-1] == 1:
        irradiance = np.repeat(irradiance, 3, axis=-1)
    if np.any(directions[:, 1] <= 0):
        raise ValueError("a directional light below the horizon has no cell on the light grid")
    grid = light_grid(n)
    out = np.zeros((n, 3))
    for k, e in zip(nearest_grid_index(directions, grid), irradiance, strict=True):
        out[k] += e / solid_angle(n)
    return out


def map_to_blocks(values: np.ndarray, width: int = MAP_WIDTH, height: int = MAP_HEIGHT,
                  grid: np.ndarray | None = None) -> np.ndarray:
    """Average grid values [n] or [n, C] into a width x height lat-long block image.

    Rows run from the zenith (row 0) down to the horizon; columns over azimuth [0, 360).
    Blocks with no grid direction stay zero.
    """
    values = np.asarray(values, dtype=np.float64)
    grid = light_grid(len(values)) if grid is None else grid
    flat = values.reshape(len(values), -1)
    az = (np.degrees(np.arctan2(-grid[:, 2], grid[:, 0])) % 360.0) / 360.0
    el = np.degrees(np.arcsin(np.clip(grid[:, 1], -1.0, 1.0))) / 90.0
    col = np.minimum((az * width).astype(int), width - 1)
    row = np.minimum(((1.0 - el) * height).astype(int), height - 1)
    acc = np.zeros((height, width, flat.shape[1]))
    cnt = np.zeros((height, width, 1))
    np.add.at(acc, (row, col), flat)
    np.add.at(cnt, (row, col), 1.0)
    out = np.where(cnt > 0, acc / np.maximum(cnt, 1.0), 0.0)
    return out.reshape((height, width) + values.shape[1:])
