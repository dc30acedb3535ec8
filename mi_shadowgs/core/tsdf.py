"""Truncated signed distance fusion of z-depth maps on a regular voxel grid (Dr.Jit).

Each voxel centre ``p`` is projected into every view; with ``z`` its z-depth there and ``d``
the depth map at its pixel, the observed signed distance along the view axis is
``sdf = d - z`` (positive in front of the surface), truncated to ``min(1, sdf / trunc)``;
observations with ``sdf < -trunc`` (well behind the surface, unseen) are skipped. Each
voxel keeps the running mean of its observations and their count (Curless and Levoy 1996;
the scheme of Open3D's ``ScalableTSDFVolume``, which 2DGS uses for mesh extraction).

Pixels without depth (``d <= 0``: background) count as free space when ``carve`` is set:
voxels that project there observe +1, which removes floaters seen against the background
(our masks cover everything that is not empty space). Voxels outside a view's image or
behind its camera get no observation from it.
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core.camera import Camera


@dataclasses.dataclass(frozen=True)
class VoxelGrid:
    """Voxel centres ``origin + voxel * (i, j, k)`` for ``0 <= (i, j, k) < shape``."""

    origin: tuple[float, float, float]  # world position of voxel (0, 0, 0)'s centre
    voxel: float  # edge length (scene units)
    shape: tuple[int, int, int]  # (nx, ny, nz)

    def __post_init__(self):
        if not (self.voxel > 0 and np.isfinite(self.voxel)):
            raise ValueError(f"VoxelGrid.voxel must be finite and > 0, got {self.voxel}")
        if len(self.shape) != 3 or min(self.shape) < 2:
            raise ValueError(f"VoxelGrid.shape needs 3 sizes >= 2, got {self.shape}")

    @property
    def count(self) -> int:
        return int(np.prod(self.shape))

    @staticmethod
    def around(lo, hi, voxel: float, pad: float = 0.0) -> VoxelGrid:
        """The grid of edge ``voxel`` covering the box [lo, hi] grown by ``pad`` each side."""
        lo = np.asarray(lo, np.float64) - pad
        hi = np.asarray(hi, np.float64) + pad
        shape = tuple(int(v) for v in np.maximum(np.ceil((hi - lo) / voxel), 1) + 1)
        return VoxelGrid(tuple(float(v) for v in lo), float(voxel), shape)


def _voxel_centres(grid: VoxelGrid) -> mi.Point3f:
    """World centres [N] in C order (i slowest, k fastest), as numpy reshapes [nx, ny, nz]."""
    nx, ny, nz = grid.shape
    idx = dr.arange(mi.UInt32, grid.count)
    k = idx % nz
    j = (idx // nz) % ny
    i = idx // (ny * nz)
    o = grid.origin
    return mi.Point3f(o[0] + grid.voxel * mi.Float(i), o[1] + grid.voxel * mi.Float(j),
                      o[2] + grid.voxel * mi.Float(k))


def fuse_tsdf(grid: VoxelGrid, depths, cameras: list[Camera], trunc: float,
              carve: bool = True, progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """TSDF [nx, ny, nz] in [-1, 1] (1 where nothing was observed) and the observation
    count [nx, ny, nz] of the z-depth maps ``depths`` ([H, W] each, 0 = background) seen
    by ``cameras`` (perspective or orthographic)."""
    from tqdm import tqdm

    if len(depths) != len(cameras):
        raise ValueError(f"fuse_tsdf: {len(depths)} depth maps for {len(cameras)} cameras")
    if not trunc > 0:
        raise ValueError(f"fuse_tsdf: trunc must be > 0, got {trunc}")
    p = _voxel_centres(grid)
    total = dr.zeros(mi.Float, grid.count)
    weight = dr.zeros(mi.Float, grid.count)
    for depth, cam in tqdm(list(zip(depths, cameras, strict=True)), desc="tsdf",
                           disable=not progress):
        d_img = np.ascontiguousarray(np.asarray(depth, np.float32))
        if d_img.shape != (cam.height, cam.width):
            raise ValueError(f"fuse_tsdf: depth map {d_img.shape} does not match the camera's "
                             f"{cam.height}x{cam.width}")
        w2c = cam.world_to_cv()
        r = [[float(w2c[a, b]) for b in range(4)] for a in range(3)]
        x, y, z = (r[a][0] * p.x + r[a][1] * p.y + r[a][2] * p.z + r[a][3] for a in range(3))
        f = cam.focal
        cx, cy = cam.principal_point
        if cam.is_ortho:
            u, v = f * x + cx, f * y + cy
        else:
            zs = dr.select(z > 0, z, 1.0)
            u, v = f * x / zs + cx, f * y / zs + cy
        inside = (z > cam.near) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
        px = mi.UInt32(dr.clip(mi.Int32(dr.floor(u)), 0, cam.width - 1))
        py = mi.UInt32(dr.clip(mi.Int32(dr.floor(v)), 0, cam.height - 1))
        d = dr.gather(mi.Float, mi.Float(d_img.ravel()), py * cam.width + px, inside)
        sdf = d - z
        seen = inside & (d > 0) & (sdf >= -trunc)
        obs = dr.minimum(sdf / trunc, 1.0)
        if carve:
            empty = inside & (d <= 0)
            seen |= empty
            obs = dr.select(empty, 1.0, obs)
        total += dr.select(seen, obs, 0.0)
        weight += dr.select(seen, 1.0, 0.0)
        dr.eval(total, weight)
    tsdf = dr.select(weight > 0, total / dr.maximum(weight, 1.0), 1.0)
    return (tsdf.numpy().reshape(grid.shape), weight.numpy().reshape(grid.shape))
