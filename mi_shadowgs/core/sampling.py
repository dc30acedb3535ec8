"""Surfels sampled on the true surfaces of a Mitsuba scene.

Used where a stage must be checked independently of stage 1 (e.g. visibility against ray
tracing with "surfels sampled on the ground-truth mesh"), and by benchmarks.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mi_shadowgs.core.frames import frame_to_quaternion

_R2_A1, _R2_A2 = 0.7548776662466927, 0.5698402909980532  # the R2 low-discrepancy sequence


@dataclasses.dataclass
class SurfaceSamples:
    position: np.ndarray  # [M, 3] world
    normal: np.ndarray  # [M, 3] unit, the shape's shading-frame normal
    albedo: np.ndarray  # [M, 3] diffuse reflectance of the shape's BSDF at the point
    shape_index: np.ndarray  # [M] index into the list of shapes that were sampled
    total_area: float


def _r2_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """n well-spread points in [0, 1)^2 (randomly shifted R2 sequence), [n, 2]."""
    k = np.arange(1, n + 1, dtype=np.float64)
    shift = rng.random(2)
    return np.stack([(shift[0] + k * _R2_A1) % 1.0, (shift[1] + k * _R2_A2) % 1.0], axis=-1)


def sample_surface(shapes, count: int, seed: int = 0) -> SurfaceSamples:
    """Area-proportional, well-spread samples over Mitsuba ``shapes`` (a list of mi.Shape)."""
    import mitsuba as mi

    shapes = list(shapes)
    if not shapes:
        raise ValueError("sample_surface: no shapes to sample")
    if count < 1:
        raise ValueError(f"sample_surface: count must be >= 1, got {count}")
    areas = np.array([float(dr_scalar(s.surface_area())) for s in shapes])
    total = float(areas.sum())
    if not total > 0:
        raise ValueError("sample_surface: the shapes have zero total area")
    rng = np.random.default_rng(seed)
    # Largest-remainder apportionment of the samples by area.
    quota = areas / total * count
    per_shape = np.floor(quota).astype(int)
    per_shape[np.argsort(quota - per_shape)[::-1][: count - per_shape.sum()]] += 1
    out_p, out_n, out_a, out_i = [], [], [], []
    for index, (shape, m) in enumerate(zip(shapes, per_shape.tolist(), strict=True)):
        if m == 0:
            continue
        uv = _r2_points(int(m), rng)
        ps = shape.sample_position(0.0, mi.Point2f(uv[:, 0], uv[:, 1]))
        si = mi.SurfaceInteraction3f(ps, mi.Color0f())
        si.shape = mi.ShapePtr(shape)
        # Every Mitsuba BSDF answers the query (0 for conductors and dielectrics, the
        # weighted sum for blends); a shape given none renders with Mitsuba's default
        # diffuse BSDF, of reflectance 0.5. An error in the query is not swallowed: it
        # would stand a plausible 0.5 in for the ground truth.
        bsdf = shape.bsdf()
        albedo = (np.full((m, 3), 0.5) if bsdf is None
                  else _to_numpy3(bsdf.eval_diffuse_reflectance(si), m))
        out_p.append(_to_numpy3(ps.p, m))
        out_n.append(_to_numpy3(ps.n, m))
        out_a.append(albedo)
        out_i.append(np.full(m, index))
    normal = np.concatenate(out_n)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return SurfaceSamples(np.concatenate(out_p), normal, np.concatenate(out_a),
                          np.concatenate(out_i), total)


def surfels_on_surface(shapes, count: int, seed: int = 0, sigma_factor: float = 1.0,
                       opacity: float = 0.99, extra_channels: dict | None = None):
    """Surfels tangent to the shapes, one per sample.

    Each surfel's two standard deviations are ``sigma_factor`` times the mean sample spacing
    ``sqrt(area / count)``; channels: "albedo" [N, 3] (the BSDF's diffuse reflectance) plus
    ``extra_channels``.
    """
    from mi_shadowgs.core.surfels import Surfels

    s = sample_surface(shapes, count, seed)
    spacing = math.sqrt(s.total_area / count)
    n = len(s.position)
    channels = {"albedo": s.albedo}
    channels.update(extra_channels or {})
    return Surfels.from_numpy(
        position=s.position,
        scale=np.full((n, 2), sigma_factor * spacing),
        rotation=frame_to_quaternion(s.normal),
        opacity=np.full(n, opacity),
        channels=channels,
    )


def dr_scalar(x) -> float:
    arr = np.asarray(x, dtype=np.float64).ravel()
    return float(arr[0])


def _to_numpy3(v, m: int) -> np.ndarray:
    """A Dr.Jit 3-vector array (numpy view [3, m] or [3, 1] when constant) -> [m, 3]."""
    a = np.asarray(v, dtype=np.float64).reshape(3, -1).T
    return np.ascontiguousarray(np.broadcast_to(a, (m, 3)))
