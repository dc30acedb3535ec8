"""A triangle mesh with per-vertex materials from a decomposed surfel model, as 2DGS
extracts meshes: the surfels' rendered depth over the training views fused into a TSDF
(``mi_shadowgs.core.tsdf``), marching cubes (scikit-image), then clean-up.

Clean-up: with a known base (the plane y = 0 of our scenes, docs/conventions.md), the
object is fused on a grid over the surfels above the base, the base on a coarser grid over
everything; triangles below ``base_cut`` voxels above y = 0 belong to the base, the rest to
the object. The object keeps its connected components of at least ``min_component`` times
the largest one's area (the default scene's object has two separate parts, so "largest
only" would drop one), the base its largest component. Without a known base, the whole
mesh (one grid) is the object.

Base outline: fused on its coarse grid, the base's border is a staircase a voxel or two off
the true edge, and in a relit image that edge is where a pixel is either lit base or black
background (measured: the 2-pixel band inside the masks' outline held most of the
path-traced relighting error). With masks, ``outline_base`` cuts the flattened base to
the plane's visual hull (the points of y = 0 whose projection the training views' masks
cover, by vote, on a grid of ``outline_cell`` base voxels) and puts its border vertices on that
hull's contour (marching squares, scikit-image).

Materials: each vertex takes the mean albedo, roughness and metallic of its ``neighbours``
nearest surfels, each weighted by its opacity and its Gaussian at the vertex, in the
surfel's tangent frame (the normal offset measured against one voxel, the mesh's own
uncertainty), the nearest surfel's values where every weight underflows.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mi_shadowgs.config import check_fields
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.tsdf import VoxelGrid, fuse_tsdf

DEPTH_KINDS = ("depth", "median_depth")


@dataclasses.dataclass(frozen=True)
class MeshConfig:
    resolution: int = 160  # voxels along the object grid's longest side (~0.4 % of it)
    # The base (when known) is fused on its own grid of this many object voxels per voxel:
    # it is flat and large, and at the object's resolution it took most of the time.
    base_voxel_factor: float = 2.0
    base_margin: float = 0.02  # surfels this far above y = 0 (x the scene box) are object
    trunc_voxels: float = 4.0  # TSDF truncation, in voxels (Open3D/2DGS use 4-5)
    depth: str = "depth"  # rendered depth fused: expected ("depth") or 2DGS's median
    alpha_min: float = 0.5  # pixels of lower rendered alpha count as background
    # Background pixels as free space (core.tsdf): off, as in 2DGS/Open3D. A voxel deep
    # inside is seen by no view (all skip it) except through a pinhole of low alpha, so one
    # such view would carve it and leave a false wall inside.
    carve: bool = False
    # Depth pixels whose 4-neighbours differ by more than this many voxels are dropped: at a
    # silhouette the rendered depth blends the surface with what lies behind it, and such a
    # pixel would mark the inside of the surface as free space (a false inner wall).
    edge_voxels: float = 4.0
    bounds_quantile: float = 0.995  # grid box: this quantile of opaque surfel centres
    bounds_pad: float = 0.03  # ... grown by this fraction of its diagonal each side
    base_cut: float = 2.0  # voxels above y = 0 below which triangles belong to the base
    min_component: float = 0.02  # object components below this share of the largest go
    flatten_base: bool = True  # a known base is put on y = 0 exactly (extract_mesh)
    neighbours: int = 8  # surfels averaged into each vertex's material
    # Base outline from the training masks (module docstring): the hull's grid cell in base
    # voxels, and how far (in base voxels) a border vertex may move onto the contour.
    outline: bool = True
    outline_cell: float = 0.5
    outline_snap: float = 4.0
    outline_vote: float = 0.5  # share of the views seeing a plane point that must mask it
    weld: float = 0.01  # vertices closer than this many voxels are merged (no slivers)
    outline_weld: float = 0.25  # border vertices snapped closer than this many outline cells
    # Triangles left by a weld with less area than this times the weld radius squared are
    # dropped (a ray hitting one gets NaN barycentrics in Mitsuba).
    sliver_area: float = 1e-3
    # The object is closed (export.close): its foot on the base capped, and other open
    # loops of at most this many edges; larger holes stay open (export.json says so).
    cap_foot: bool = True
    cap_hole_edges: int = 64

    def __post_init__(self):
        if self.depth not in DEPTH_KINDS:
            raise ValueError(f"MeshConfig.depth must be one of {DEPTH_KINDS}, got {self.depth!r}")
        if self.resolution < 8:
            raise ValueError(f"MeshConfig.resolution must be >= 8, got {self.resolution}")
        if not (self.trunc_voxels > 0 and 0 <= self.alpha_min < 1 and self.neighbours >= 1
                and 0.5 < self.bounds_quantile <= 1 and 0 <= self.min_component <= 1):
            raise ValueError(f"MeshConfig: bad settings {self}")
        check_fields(self, (("outline_weld", self.outline_weld >= 0, ">= 0"),
                            ("sliver_area", self.sliver_area >= 0, ">= 0")))


@dataclasses.dataclass
class MeshPart:
    """A triangle mesh with per-vertex normals and materials."""

    vertices: np.ndarray  # [V, 3] float32
    faces: np.ndarray  # [F, 3] int32
    normals: np.ndarray  # [V, 3] unit, outward
    albedo: np.ndarray | None = None  # [V, 3] linear, in [0, 1]
    roughness: np.ndarray | None = None  # [V]
    metallic: np.ndarray | None = None  # [V]

    @property
    def area(self) -> float:
        v = self.vertices.astype(np.float64)[self.faces]
        return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]),
                                          axis=1).sum())


def surfel_arrays(surfels) -> dict[str, np.ndarray]:
    """Activated surfel parameters as float64 numpy: position [N, 3], scale [N, 2],
    frame [N, 3, 3] (columns: tangents, normal), opacity [N], and the material channels."""
    from mi_shadowgs.io.ply import PlyModel

    m = PlyModel.from_surfels(surfels)
    q = m.rotation.astype(np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    w, x, y, z = q.T
    frame = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], -1),
        np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], -1),
        np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=-1)  # [N, 3, 3]: column c is axis c
    out = {"position": m.position.astype(np.float64), "scale": np.exp(m.log_scale.astype(
        np.float64)), "frame": frame, "opacity": 1.0 / (1.0 + np.exp(-m.opacity_logit.astype(
            np.float64)))}
    for name in ("albedo", "roughness", "metallic"):
        if name in m.channels:
            out[name] = m.channels[name].astype(np.float64)
    return out


def _box(pos: np.ndarray, config: MeshConfig) -> tuple[np.ndarray, np.ndarray, float]:
    q = config.bounds_quantile
    lo, hi = np.quantile(pos, 1 - q, axis=0), np.quantile(pos, q, axis=0)
    return lo, hi, config.bounds_pad * float(np.linalg.norm(hi - lo))


def grids_for(surfels, config: MeshConfig, base_known: bool
              ) -> tuple[VoxelGrid, VoxelGrid | None]:
    """(object grid, base grid or None) over the opaque surfels' (quantile) bounding boxes:
    with a known base, the object's box holds the surfels above ``base_margin`` (down to the
    base), the base's box everything at ``base_voxel_factor`` times the voxel."""
    s = surfel_arrays(surfels)
    pos = s["position"][s["opacity"] > 0.5]
    if len(pos) == 0:
        pos = s["position"]
    lo, hi, pad = _box(pos, config)
    if not base_known:
        voxel = float(np.max(hi - lo + 2 * pad)) / config.resolution
        return VoxelGrid.around(lo, hi, voxel, pad), None
    above = pos[pos[:, 1] > config.base_margin * float(np.linalg.norm(hi - lo))]
    if len(above) == 0:
        raise ValueError("mesh extraction: no surfel above the base (the object is missing)")
    olo, ohi, opad = _box(above, config)
    olo[1] = min(olo[1], 0.0)  # down to the base: the object's foot
    voxel = float(np.max(ohi - olo + 2 * opad)) / config.resolution
    base_voxel = voxel * config.base_voxel_factor
    return (VoxelGrid.around(olo, ohi, voxel, opad),
            VoxelGrid.around(lo, hi, base_voxel, max(pad, 2 * base_voxel)))


def drop_depth_edges(depth: np.ndarray, threshold: float) -> np.ndarray:
    """``depth`` [H, W] with 0 where a 4-neighbour (or the background, 0) differs by more
    than ``threshold``; pixels on the image border compare with their inner neighbours."""
    d = np.asarray(depth, np.float64)
    p = np.pad(d, 1, mode="edge")
    h, w = d.shape
    jump = np.zeros(d.shape, bool)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        jump |= np.abs(p[dy:dy + h, dx:dx + w] - d) > threshold
    return np.where(jump, 0.0, d).astype(np.float32)


def render_depths(surfels, cameras: list[Camera], config: MeshConfig,
                  progress: bool = False) -> list[np.ndarray]:
    """Rendered z-depth [H, W] of each camera, 0 where the alpha is below ``alpha_min``."""
    import drjit as dr
    from tqdm import tqdm

    from mi_shadowgs.core.raster import rasterize

    out = []
    with dr.suspend_grad():
        for cam in tqdm(cameras, desc="depth", disable=not progress):
            r = rasterize(surfels, cam, {}, aovs=("alpha", config.depth))
            d = r[config.depth].numpy().reshape(cam.height, cam.width)
            a = r["alpha"].numpy().reshape(cam.height, cam.width)
            out.append(np.where(a >= config.alpha_min, d, 0.0).astype(np.float32))
    return out


def marching_cubes(tsdf: np.ndarray, weight: np.ndarray, grid: VoxelGrid
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The zero level set of ``tsdf`` (negative inside) where it was observed: vertices
    [V, 3] (world) and faces [F, 3], wound counter-clockwise seen from outside."""
    from skimage import measure

    if not (tsdf.min() < 0 < tsdf.max()):
        raise ValueError("mesh extraction: the fused TSDF has no zero crossing (no surface "
                         "in the grid: are the cameras and the model in the same frame?)")
    # A cube counts only when all 8 corners were observed: an unobserved corner holds no
    # distance, and a crossing toward it would be a wall between seen and unseen space.
    # scikit-image reads the mask at a cube's upper corner (cube [i-1, i] x ... at mask[i]).
    seen = weight > 0
    cube = np.zeros_like(seen)
    cube[1:, 1:, 1:] = np.logical_and.reduce(
        [seen[i:i + seen.shape[0] - 1, j:j + seen.shape[1] - 1, k:k + seen.shape[2] - 1]
         for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    verts, faces, _, _ = measure.marching_cubes(
        tsdf, level=0.0, spacing=(grid.voxel,) * 3, mask=cube,
        gradient_direction="descent", allow_degenerate=False)
    return (verts + np.asarray(grid.origin)).astype(np.float32), faces.astype(np.int32)


def _linked(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Connected-component label [n] of n nodes linked by the pairs (a[i], b[i])."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Connected-component label of each face (faces sharing a vertex are connected)."""
    vert_label = _linked(faces.ravel(), faces[:, [1, 2, 0]].ravel(), n_vertices)  # edges
    return vert_label[faces[:, 0]]


def _face_areas(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    t = v.astype(np.float64)[faces]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def _part(v: np.ndarray, faces: np.ndarray) -> MeshPart:
    """The mesh of ``faces`` alone (unused vertices dropped), with area-weighted normals."""
    used, inv = np.unique(faces.ravel(), return_inverse=True)
    f = inv.reshape(-1, 3).astype(np.int32)
    vv = v[used]
    t = vv.astype(np.float64)[f]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])  # [F, 3], |.| = 2 area
    n = np.zeros((len(vv), 3))
    for c in range(3):
        np.add.at(n, f[:, c], fn)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    return MeshPart(vv.astype(np.float32), f, n.astype(np.float32))


def keep_components(verts: np.ndarray, faces: np.ndarray, share: float) -> MeshPart | None:
    """The connected components of at least ``share`` times the largest one's area
    (``share`` 1: the largest alone), or None without faces."""
    if len(faces) == 0:
        return None
    label = _components(faces, len(verts))
    area = np.bincount(label, weights=_face_areas(verts, faces))
    keep = area >= share * area.max() if share < 1 else area == area.max()
    return _part(verts, faces[keep[label]])


def clean_up(verts: np.ndarray, faces: np.ndarray, voxel: float, config: MeshConfig,
             base_known: bool) -> tuple[MeshPart, MeshPart | None]:
    """(object, base or None) of one mesh: see the module docstring."""
    if len(faces) == 0:
        raise ValueError("mesh extraction: marching cubes found no triangles")
    is_base = np.zeros(len(faces), bool)
    if base_known:
        is_base = verts[faces].mean(axis=1)[:, 1] < config.base_cut * voxel
    obj = keep_components(verts, faces[~is_base], config.min_component)
    if obj is None:
        raise ValueError("mesh extraction: nothing above the base (the object is missing)")
    return obj, keep_components(verts, faces[is_base], 1.0)


def project_materials(part: MeshPart, surfels: dict, voxel: float, neighbours: int) -> None:
    """Fill ``part``'s albedo/roughness/metallic from the surfels (module docstring)."""
    from scipy.spatial import cKDTree

    pos = surfels["position"]
    k = min(neighbours, len(pos))
    _, idx = cKDTree(pos).query(part.vertices.astype(np.float64), k=k)
    idx = idx.reshape(len(part.vertices), k)  # [V, k]
    off = part.vertices[:, None, :].astype(np.float64) - pos[idx]  # [V, k, 3]
    local = np.einsum("vkc,vkcd->vkd", off, surfels["frame"][idx])  # tangent, tangent, normal
    s = surfels["scale"][idx]  # [V, k, 2]
    e = ((local[..., 0] / s[..., 0]) ** 2 + (local[..., 1] / s[..., 1]) ** 2 +
         (local[..., 2] / voxel) ** 2)
    w = surfels["opacity"][idx] * np.exp(-0.5 * e)  # [V, k]
    total = w.sum(1, keepdims=True)
    nearest = np.zeros_like(w)
    nearest[:, 0] = 1.0  # query() sorts by distance
    w = np.where(total > 1e-12, w / np.maximum(total, 1e-300), nearest)
    for name in ("albedo", "roughness", "metallic"):
        if name not in surfels:
            raise ValueError(f"mesh materials: the model has no {name!r} channel (run stage 4)")
        vals = np.einsum("vk,vkc->vc", w, surfels[name][idx])
        vals = np.clip(vals, 0.0, 1.0).astype(np.float32)
        setattr(part, name, vals if name == "albedo" else vals[:, 0])


def _fuse(grid: VoxelGrid, depths, cameras, config: MeshConfig, progress: bool):
    """Marching-cubes mesh (vertices, faces) of the depths fused on ``grid``."""
    if config.edge_voxels > 0:
        depths = [drop_depth_edges(d, config.edge_voxels * grid.voxel) for d in depths]
    tsdf, weight = fuse_tsdf(grid, depths, cameras, config.trunc_voxels * grid.voxel,
                             carve=config.carve, progress=progress)
    return marching_cubes(tsdf, weight, grid)


def plane_hull(views: list[tuple[Camera, np.ndarray]], lo: np.ndarray, hi: np.ndarray,
               cell: float, vote: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Visual hull of the plane y = 0 over the box ``lo``..``hi`` ([2]: x, z) from ``views``
    (camera, mask [H, W] bool): (occupancy [Nz, Nx] bool, (cell centres' x [Nx], z [Nz])).
    A cell is in when at least ``vote`` of the views that see it have it inside their mask:
    on a plane nothing hides a point from a view except the object, which the masks
    include, so each view's mask differs from the truth only by its pixels' quantization,
    and a vote, unlike the intersection (which keeps the most shrunken view, up to half a
    pixel inside), is unbiased."""
    xs = np.arange(lo[0] + 0.5 * cell, hi[0], cell)
    zs = np.arange(lo[1] + 0.5 * cell, hi[1], cell)
    gx, gz = np.meshgrid(xs, zs)  # [Nz, Nx]
    pts = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], -1)
    votes = np.zeros(len(pts))
    seen = np.zeros(len(pts))
    for cam, mask in views:
        hit, inside = cam.lookup(np.asarray(mask, bool), pts)
        votes += hit
        seen += inside
    occ = (seen > 0) & (votes >= vote * seen)
    return occ.reshape(gx.shape), (xs, zs)


def _boundary_vertices(faces: np.ndarray) -> np.ndarray:
    """Indices of the vertices on edges that belong to one face only."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    return np.unique(uniq[count == 1].ravel())


def _weld(part: MeshPart, candidates: np.ndarray, radius: float, sliver_area: float
          ) -> MeshPart:
    """``part`` with the ``candidates`` vertices closer than ``radius`` merged (each group
    onto one of them) and the triangles left with a repeated vertex or under ``sliver_area``
    x radius^2 of area dropped."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(part.vertices[candidates].astype(np.float64)).query_pairs(radius,
                                                                            output_type="ndarray")
    target = np.arange(len(part.vertices))
    if len(pairs):
        n = len(candidates)
        label = _linked(pairs[:, 0], pairs[:, 1], n)
        first = np.full(label.max() + 1, -1)
        for k in range(n - 1, -1, -1):  # each group onto its first member
            first[label[k]] = k
        target[candidates] = candidates[first[label]]
    f = target[part.faces]
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[ok]
    area = _face_areas(part.vertices, f)
    return _part(part.vertices, f[area > sliver_area * radius * radius].astype(np.int32))


def outline_base(base: MeshPart, views: list[tuple[Camera, np.ndarray]], voxel: float,
                 config: MeshConfig) -> tuple[MeshPart | None, dict]:
    """The flattened base (on y = 0) cut to the plane's visual hull and its border put on
    the hull's contour (module docstring). Returns (base or None when nothing is left,
    info)."""
    from scipy.spatial import cKDTree
    from skimage.measure import find_contours

    cell = config.outline_cell * voxel
    pad = (config.outline_snap + 2.0) * voxel
    v = base.vertices.astype(np.float64)
    lo = v[:, [0, 2]].min(0) - pad
    hi = v[:, [0, 2]].max(0) + pad
    occ, (xs, zs) = plane_hull(views, lo, hi, cell, config.outline_vote)
    # triangles whose centre lies outside the hull go
    c = v[base.faces].mean(axis=1)
    ix = np.clip(np.floor((c[:, 0] - lo[0]) / cell).astype(np.int64), 0, len(xs) - 1)
    iz = np.clip(np.floor((c[:, 2] - lo[1]) / cell).astype(np.int64), 0, len(zs) - 1)
    kept = base.faces[occ[iz, ix]]
    if len(kept) == 0:
        return None, {"outline_hull_cells": int(occ.sum())}
    part = keep_components(v.astype(np.float32), kept, 1.0)
    # the hull's contour, resampled every quarter cell, in world x, z
    pts = []
    for contour in find_contours(np.pad(occ, 1).astype(np.float32), 0.5):
        rc = contour - 1.0  # undo the padding: (row = z index, col = x index)
        seg = np.diff(rc, axis=0)
        steps = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) * 4.0), 1).astype(int)
        for a, d, n in zip(rc[:-1], seg, steps, strict=True):
            t = np.arange(n)[:, None] / n
            pts.append(a + t * d)
    if not pts:
        return part, {"outline_hull_cells": int(occ.sum()), "outline_moved": 0}
    rc = np.concatenate(pts)
    contour_xz = np.stack([lo[0] + (rc[:, 1] + 0.5) * cell, lo[1] + (rc[:, 0] + 0.5) * cell],
                          -1)
    border = _boundary_vertices(part.faces)
    dist, idx = cKDTree(contour_xz).query(part.vertices[border][:, [0, 2]].astype(np.float64))
    move = dist <= config.outline_snap * voxel
    part.vertices[border[move], 0] = contour_xz[idx[move], 0]
    part.vertices[border[move], 2] = contour_xz[idx[move], 1]
    # Border vertices that landed (almost) on one contour point leave slivers between them;
    # a ray hitting a sliver gets NaN barycentrics in Mitsuba (measured: NaN pixels on the
    # default scene). Weld such vertices and drop the triangles that collapse.
    part = _weld(part, border[move], config.outline_weld * cell, config.sliver_area)
    part.normals[:] = (0.0, 1.0, 0.0)  # the plane's normal (welded slivers had none)
    return part, {"outline_hull_cells": int(occ.sum()), "outline_moved": int(move.sum()),
                  "outline_border_vertices": len(border),
                  "outline_cut_faces": int(len(base.faces) - len(kept))}


def extract_mesh(surfels, cameras: list[Camera], config: MeshConfig, base_known: bool,
                 progress: bool = False, masks: list[np.ndarray] | None = None
                 ) -> tuple[MeshPart, MeshPart | None, dict]:
    """(object, base or None, info) of a decomposed surfel model seen by ``cameras``; info
    holds the grids and the seconds of each step. ``masks`` [H, W] bool per camera (the
    training views' object + base masks) give the base its outline (``outline_base``)."""
    import time

    t = [time.perf_counter()]
    outline_info = {}
    grid, base_grid = grids_for(surfels, config, base_known)
    depths = render_depths(surfels, cameras, config, progress)
    t.append(time.perf_counter())
    verts, faces = _fuse(grid, depths, cameras, config, progress)
    obj, base = clean_up(verts, faces, grid.voxel, config, base_known)
    if base_grid is not None:
        bverts, bfaces = _fuse(base_grid, depths, cameras, config, progress)
        low = bverts[bfaces].mean(axis=1)[:, 1] < config.base_cut * base_grid.voxel
        base = keep_components(bverts, bfaces[low], 1.0)
        if base is not None and config.flatten_base:
            # The base is known to be the plane y = 0: its fused bumps (depth noise) would
            # shadow themselves under a low sun. The object's cut edge goes down onto it, so
            # that no light leaks under the object through the cut.
            base.vertices[:, 1] = 0.0
            base.normals[:] = (0.0, 1.0, 0.0)
            foot = obj.vertices[:, 1] < config.base_cut * grid.voxel
            obj.vertices[foot, 1] = 0.0
            if config.outline and masks is not None:
                base, outline_info = outline_base(base, list(zip(cameras, masks, strict=True)),
                                                  base_grid.voxel, config)
    # Marching cubes puts vertices on grid edges; where the surface passes through a grid
    # vertex, two of them coincide and their triangle is a sliver, on which a ray gets NaN
    # barycentrics in Mitsuba (NaN pixels in the default scene's path-traced relighting).
    obj = _weld(obj, np.arange(len(obj.vertices)), config.weld * grid.voxel,
                config.sliver_area)
    if base is not None:
        flat = config.flatten_base and base_grid is not None
        base = _weld(base, np.arange(len(base.vertices)), config.weld * grid.voxel,
                     config.sliver_area)
        # Welds and the outline cut can leave specks of a few triangles apart from the
        # plane: sliver components, which mesh tools show as stray debris.
        base = keep_components(base.vertices, base.faces, config.min_component)
        if flat:
            base.normals[:] = (0.0, 1.0, 0.0)
    obj = keep_components(obj.vertices, obj.faces, config.min_component)
    close_info = {}
    if config.cap_foot:
        from mi_shadowgs.stages.export.close import close_mesh

        # the foot: loops within twice the cut's height above the (flattened) base
        band = 2.0 * config.base_cut * grid.voxel
        on_base = config.flatten_base and base_grid is not None
        verts, faces, close_info = close_mesh(obj.vertices, obj.faces,
                                              band if on_base else None,
                                              config.cap_hole_edges)
        obj = MeshPart(verts, faces, obj.normals)  # the normals of the surface
    t.append(time.perf_counter())
    arrays = surfel_arrays(surfels)
    for part in (obj, base):
        if part is not None:
            project_materials(part, arrays, grid.voxel, config.neighbours)
    t.append(time.perf_counter())
    info = {"voxel": grid.voxel, "grid": list(grid.shape), "origin": list(grid.origin),
            "base_voxel": None if base_grid is None else base_grid.voxel,
            "base_grid": None if base_grid is None else list(base_grid.shape),
            "seconds": {k: t[i + 1] - t[i] for i, k in enumerate(
                ("depth", "tsdf_marching_cubes", "materials"))},
            "object_vertices": len(obj.vertices), "object_faces": len(obj.faces),
            "base_faces": 0 if base is None else len(base.faces), **outline_info,
            **close_info}
    return obj, base, info
