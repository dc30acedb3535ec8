"""TSDF fusion (``core.tsdf``) against a float64 NumPy reference, and mesh extraction
(``stages.export.mesh``) on a surfel model whose true surface is known."""

from __future__ import annotations

import numpy as np
import pytest

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.tsdf import VoxelGrid, fuse_tsdf
from mi_shadowgs.stages.export import mesh
from tests import synthetic_asset as syn


def reference_tsdf(grid: VoxelGrid, depths, cameras, trunc, carve):
    """Voxel by voxel, view by view, in float64 (Camera.project), the rules of core.tsdf."""
    nx, ny, nz = grid.shape
    total = np.zeros(grid.shape)
    count = np.zeros(grid.shape)
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                p = np.asarray(grid.origin) + grid.voxel * np.array([i, j, k])
                for d_img, cam in zip(depths, cameras, strict=True):
                    uv, z = cam.project(p[None])
                    u, v, z = uv[0, 0], uv[0, 1], z[0]
                    if not (z > cam.near and 0 <= u < cam.width and 0 <= v < cam.height):
                        continue
                    d = d_img[int(np.floor(v)), int(np.floor(u))]
                    if d <= 0:
                        if carve:
                            total[i, j, k] += 1.0
                            count[i, j, k] += 1
                        continue
                    if d - z < -trunc:
                        continue
                    total[i, j, k] += min(1.0, (d - z) / trunc)
                    count[i, j, k] += 1
    return np.where(count > 0, total / np.maximum(count, 1), 1.0), count


@pytest.mark.parametrize("carve", [False, True])
def test_fusion_matches_float64_reference(carve):
    rng = np.random.default_rng(3)
    cams = [Camera.look_at(o, (0, 0, 0), width=12, height=10, fov_x=0.9)
            for o in ([0, 0.5, 3.0], [2.5, 1.0, -1.0], [-1.0, 2.8, 0.5])]
    cams.append(Camera.look_at([0, 3, 0.01], (0, 0, 0), width=8, height=8, ortho_width=2.0))
    depths = []
    for cam in cams:  # a bumpy surface near the origin, some background holes
        d = np.linalg.norm(cam.origin) + 0.3 * rng.standard_normal((cam.height, cam.width))
        d[rng.random(d.shape) < 0.15] = 0.0
        depths.append(d.astype(np.float32))
    grid = VoxelGrid((-0.6, -0.5, -0.55), 0.17, (7, 6, 8))
    tsdf, count = fuse_tsdf(grid, depths, cams, trunc=0.25, carve=carve)
    ref, ref_count = reference_tsdf(grid, depths, cams, 0.25, carve)
    # Voxels within float32 rounding of a pixel edge or of the truncation may be counted
    # differently; none should be at these random positions (checked: exact agreement).
    np.testing.assert_array_equal(count, ref_count)
    # float32 world->camera transform and division: ~1e-6 relative on distances of ~3,
    # divided by trunc 0.25: 1e-4 is ample and far below any rule change (>= 0.1).
    np.testing.assert_allclose(tsdf, ref, atol=1e-4)
    assert count.max() >= 3 and (ref < 0).any() and (ref > 0).any()  # the test bites


def test_voxel_grid_rejects_bad_settings():
    with pytest.raises(ValueError, match="voxel"):
        VoxelGrid((0, 0, 0), 0.0, (4, 4, 4))
    with pytest.raises(ValueError, match="shape"):
        VoxelGrid((0, 0, 0), 0.1, (4, 1, 4))


def test_depth_edges_are_dropped():
    d = np.full((6, 6), 2.0, np.float32)
    d[:, 3:] = 3.0  # a step of 1 between columns 2 and 3
    d[0, 0] = 0.0  # background
    out = mesh.drop_depth_edges(d, 0.5)
    assert (out[:, 2] == 0).all() and (out[:, 3] == 0).all()
    assert out[0, 1] == 0 and out[1, 0] == 0  # beside the background
    assert (out[2:, 0] == 2.0).all() and (out[:, 5] == 3.0).all()


def test_unobserved_voxels_make_no_walls():
    """A plane TSDF (x < 2 negative) observed only for z < 5: one sheet at x = 2.5 voxels,
    none along the border of the observed region."""
    tsdf = np.broadcast_to(np.clip((np.arange(8)[:, None, None] - 2.5) / 2, -1, 1),
                           (8, 8, 10)).copy()
    weight = np.ones_like(tsdf)
    weight[:, :, 5:] = 0
    tsdf[:, :, 5:] = 1.0  # as fuse_tsdf leaves unobserved voxels
    grid = VoxelGrid((0.0, 0.0, 0.0), 1.0, tsdf.shape)
    v, f = mesh.marching_cubes(tsdf, weight, grid)
    np.testing.assert_allclose(v[:, 0], 2.5, atol=1e-5)
    assert v[:, 2].max() <= 4.0 + 1e-6


def test_clean_up_keeps_big_parts_and_splits_the_base():
    import trimesh

    big = trimesh.creation.icosphere(3, radius=0.4)
    big.apply_translation([-0.6, 0.6, 0])
    other = trimesh.creation.icosphere(3, radius=0.3)
    other.apply_translation([0.6, 0.5, 0])
    speck = trimesh.creation.icosphere(1, radius=0.02)
    speck.apply_translation([0, 1.5, 0])
    base = trimesh.creation.box((3, 0.001, 3))
    m = trimesh.util.concatenate([big, other, speck, base])
    obj, floor = mesh.clean_up(np.asarray(m.vertices, np.float32),
                               np.asarray(m.faces, np.int32), 0.01, mesh.MeshConfig(), True)
    assert len(obj.faces) == len(big.faces) + len(other.faces)  # speck gone, both kept
    assert obj.vertices[:, 1].min() > 0.05 and np.abs(floor.vertices[:, 1]).max() < 0.01
    obj2, none = mesh.clean_up(np.asarray(m.vertices, np.float32),
                               np.asarray(m.faces, np.int32), 0.01, mesh.MeshConfig(), False)
    assert none is None and len(obj2.faces) == len(m.faces) - len(speck.faces)


def test_materials_follow_the_nearest_surfels():
    model = syn.sphere_on_plane(n_sphere=2000, n_plane=400)
    arrays = mesh.surfel_arrays(model.to_surfels())
    part = mesh.MeshPart(model.position[:5].copy(), np.zeros((0, 3), np.int32),
                         np.zeros((5, 3), np.float32))
    mesh.project_materials(part, arrays, voxel=0.01, neighbours=8)
    np.testing.assert_allclose(part.albedo, model.channels["albedo"][:5], atol=1e-5)
    np.testing.assert_allclose(part.roughness, model.channels["roughness"][:5, 0], atol=1e-5)
    np.testing.assert_allclose(part.metallic, model.channels["metallic"][:5, 0], atol=1e-5)


@pytest.fixture(scope="module")
def sphere_mesh():
    model = syn.sphere_on_plane()
    cfg = mesh.MeshConfig(resolution=160)
    return mesh.extract_mesh(model.to_surfels(), syn.ring_cameras(), cfg, base_known=True)


def test_mesh_of_a_known_surface(sphere_mesh):
    """The object is the sphere: within half a voxel on average (TSDF + marching cubes of the
    rendered depth of a surfel sphere; measured 0.35 voxel = 0.5 % of the radius), outward
    normals, its albedo; the base is the plane."""
    obj, base, info = sphere_mesh
    voxel = info["voxel"]
    v = obj.vertices.astype(np.float64)
    r = np.linalg.norm(v - syn.CENTER, axis=1)
    assert np.abs(r - syn.RADIUS).mean() < 0.5 * voxel
    # No floaters; the worst vertices sit where the sphere nears the plane (measured 2.2 voxels).
    assert np.abs(r - syn.RADIUS).max() < 3.0 * voxel
    # Every vertex of a closed sphere (but the band near the plane, seen at grazing angles).
    outward = np.einsum("ij,ij->i", obj.normals, (v - syn.CENTER) / r[:, None])
    assert (outward > 0.5).mean() > 0.99
    # Vertex count of a ~one-voxel mesh of the sphere: a second (inner) shell would double it.
    assert len(v) < 1.5 * 4 * np.pi * syn.RADIUS ** 2 / voxel ** 2
    top, bottom = v[:, 1] > syn.CENTER[1] + 0.1, v[:, 1] < syn.CENTER[1] - 0.1
    np.testing.assert_allclose(obj.albedo[top].mean(0), syn.TOP_ALBEDO, atol=0.01)
    np.testing.assert_allclose(obj.albedo[bottom].mean(0), syn.BOTTOM_ALBEDO, atol=0.01)
    assert base is not None and np.abs(base.vertices[:, 1]).max() < 2.0 * info["base_voxel"]
    # Facing up (the plane's open border and the sphere's contact shadow are rougher).
    assert np.median(base.normals[:, 1]) > 0.95 and (base.normals[:, 1] > 0.9).mean() > 0.85
    np.testing.assert_allclose(base.albedo.mean(0), syn.PLANE_ALBEDO, atol=0.01)
