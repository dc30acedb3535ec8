"""The shared rasterizer benchmark workload: Gaussians on a sphere standing on a plane.

One ``Workload`` (float64 NumPy arrays) feeds both renderers, so the comparison is fair:
our 2D surfel rasterizer gets the tangent scales ``(s, s)``; Mitsuba's ``ellipsoids`` shape
gets ``(s, s, thickness_factor * s)`` because it misses flatter ellipsoids in float32.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import direction_from_angles
from mi_shadowgs.core.frames import frame_to_quaternion

# Real SH band-0 constant: both renderers map a DC coefficient c to colour SH_C0 * c + 0.5.
SH_C0 = 0.28209479177387814
# Plastic-number R2 sequence: low-discrepancy points, so plane spacing is even without a grid.
_PLASTIC = 1.324717957244746


@dataclasses.dataclass(frozen=True)
class WorkloadConfig:
    """One benchmark scene; field defaults are the issue's workload."""

    n: int = 20_000  # total Gaussians, split between sphere and plane by area
    resolution: int = 128  # square image side in pixels
    sphere_radius: float = 0.5
    sphere_center_y: float = 0.5  # the sphere stands on the plane y = 0
    plane_half_size: float = 1.0  # plane spans [-1, 1]^2 in x, z
    sigma_factor: float = 1.5  # in-plane std-dev / mean spacing
    thickness_factor: float = 0.3  # Mitsuba ellipsoids' third scale / in-plane scale
    opacity: float = 0.8
    camera_distance: float = 2.5  # from the sphere centre
    fov_deg: float = 40.0  # full horizontal field of view
    camera_azimuth_deg: float = 30.0
    camera_elevation_deg: float = 25.0
    target_value: float = 0.5  # the constant image of the L1 loss
    nudge: float = 1e-4  # per-iteration position offset (scene units), alternating sign
    seed: int = 0

    def __post_init__(self):
        if self.n < 2:
            raise ValueError(f"WorkloadConfig.n must be >= 2, got {self.n}")
        if self.resolution < 1:
            raise ValueError(f"WorkloadConfig.resolution must be >= 1, got {self.resolution}")
        if not 0.0 < self.opacity < 1.0:
            raise ValueError(f"WorkloadConfig.opacity must be in (0, 1), got {self.opacity}")


@dataclasses.dataclass(frozen=True)
class Workload:
    config: WorkloadConfig
    position: np.ndarray  # [N, 3] centres
    scale: np.ndarray  # [N, 2] tangent std-devs (activated)
    rotation: np.ndarray  # [N, 4] unit quaternions, (w, x, y, z)
    opacity: np.ndarray  # [N]
    color: np.ndarray  # [N, 3] linear RGB in [0, 1]
    n_sphere: int
    n_plane: int
    spacing: float  # mean spacing between neighbouring centres
    camera: Camera

    @property
    def n(self) -> int:
        return len(self.position)

    def ellipsoid_scales(self) -> np.ndarray:
        """[N, 3] scales for Mitsuba's ellipsoids: (s_u, s_v, thickness * s_u)."""
        t = self.config.thickness_factor * self.scale[:, :1]
        return np.concatenate([self.scale, t], axis=-1)

    def quaternions_xyzw(self) -> np.ndarray:
        """[N, 4] the rotations in Mitsuba/Dr.Jit's (x, y, z, w) order."""
        return self.rotation[:, [1, 2, 3, 0]]

    def sh_dc(self) -> np.ndarray:
        """[N, 3] degree-0 SH coefficients that evaluate to ``color``."""
        return (self.color - 0.5) / SH_C0


def _fibonacci_sphere(n: int) -> np.ndarray:
    """[n, 3] unit vectors evenly spread over the sphere (golden-angle spiral)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=-1)


def _r2_square(n: int, offset: float) -> np.ndarray:
    """[n, 2] low-discrepancy points in [0, 1)^2."""
    a = np.array([1.0 / _PLASTIC, 1.0 / _PLASTIC**2])
    i = np.arange(1, n + 1, dtype=np.float64)[:, None]
    return (offset + i * a) % 1.0


def split_by_area(config: WorkloadConfig) -> tuple[int, int]:
    """(n_sphere, n_plane): the Gaussians split between the two surfaces by area."""
    a_sphere = 4.0 * math.pi * config.sphere_radius**2
    a_plane = (2.0 * config.plane_half_size) ** 2
    n_sphere = int(round(config.n * a_sphere / (a_sphere + a_plane)))
    n_sphere = min(max(n_sphere, 1), config.n - 1)
    return n_sphere, config.n - n_sphere


def workload_camera(config: WorkloadConfig) -> Camera:
    center = np.array([0.0, config.sphere_center_y, 0.0])
    eye = center + config.camera_distance * direction_from_angles(
        config.camera_azimuth_deg, config.camera_elevation_deg)
    return Camera.look_at(eye, center, width=config.resolution, height=config.resolution,
                          fov_x=math.radians(config.fov_deg))


def build_workload(config: WorkloadConfig | None = None, **overrides) -> Workload:
    """The benchmark scene for ``config`` (fields may be overridden by keyword)."""
    config = dataclasses.replace(config or WorkloadConfig(), **overrides)
    rng = np.random.default_rng(config.seed)
    n_sphere, n_plane = split_by_area(config)
    a_total = 4.0 * math.pi * config.sphere_radius**2 + (2.0 * config.plane_half_size) ** 2
    spacing = math.sqrt(a_total / config.n)
    sigma = config.sigma_factor * spacing

    dirs = _fibonacci_sphere(n_sphere)  # [Ns, 3] outward normals
    sphere_pos = dirs * config.sphere_radius + np.array([0.0, config.sphere_center_y, 0.0])
    uv = _r2_square(n_plane, rng.uniform()) * 2.0 - 1.0  # [Np, 2] in [-1, 1)
    plane_pos = np.stack([uv[:, 0], np.zeros(n_plane), uv[:, 1]], axis=-1)
    plane_pos[:, [0, 2]] *= config.plane_half_size
    plane_nrm = np.tile([0.0, 1.0, 0.0], (n_plane, 1))

    position = np.concatenate([sphere_pos, plane_pos])
    rotation = frame_to_quaternion(np.concatenate([dirs, plane_nrm]))
    return Workload(
        config=config,
        position=position,
        scale=np.full((config.n, 2), sigma),
        rotation=rotation,
        opacity=np.full(config.n, config.opacity),
        color=rng.uniform(0.0, 1.0, size=(config.n, 3)),
        n_sphere=n_sphere,
        n_plane=n_plane,
        spacing=spacing,
        camera=workload_camera(config),
    )
