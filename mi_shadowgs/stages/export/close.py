"""Closing an extracted mesh: the open loops of its border capped with triangles on the
existing vertices (ear clipping), so that the object is watertight for mesh tools.

The object mesh is cut where it stands on the base (``mesh.clean_up``): its foot is an open
loop (or one per part) lying on y = 0. Those loops are always capped, facing down; other
holes (surface no training view saw) only when they have at most ``hole_edges`` edges, as a
cap across a large hole would invent a surface. What stays open is said in the returned
info (``export.json``). Caps add faces only: vertices, their normals and materials stay.
"""

from __future__ import annotations

import numpy as np


def boundary_loops(faces: np.ndarray) -> tuple[list[np.ndarray], bool]:
    """(loops, manifold): each closed loop of border edges as vertex indices in the order
    of the faces' own edges (a cap must run through them backwards); ``manifold`` False
    when a vertex starts two border edges (the loops through it are left out)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = e[:, 0].astype(np.int64) * (int(faces.max()) + 1) + e[:, 1]
    rev = e[:, 1].astype(np.int64) * (int(faces.max()) + 1) + e[:, 0]
    border = e[~np.isin(key, rev)]
    starts, counts = np.unique(border[:, 0], return_counts=True)
    bad = set(starts[counts > 1].tolist())
    nxt = {int(a): int(b) for a, b in border if int(a) not in bad}
    loops, seen = [], set()
    for v0 in list(nxt):
        if v0 in seen:
            continue
        loop, v = [], v0
        while v in nxt and v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        if v == v0 and len(loop) >= 3:
            loops.append(np.array(loop))
    return loops, not bad


def ear_clip(points: np.ndarray) -> np.ndarray:
    """Triangles [n-2, 3] (indices into ``points`` [n, 2], a simple polygon in either
    orientation) wound as the polygon is."""
    p = np.asarray(points, np.float64)
    x, y = p[:, 0], p[:, 1]
    sign = 1.0 if np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) >= 0 else -1.0
    idx = list(range(len(p)))
    tris = []
    while len(idx) > 3:
        q = p[idx]
        a, c = np.roll(q, 1, axis=0), np.roll(q, -1, axis=0)
        turn = sign * ((q[:, 0] - a[:, 0]) * (c[:, 1] - q[:, 1])
                       - (q[:, 1] - a[:, 1]) * (c[:, 0] - q[:, 0]))
        m = len(idx)
        ear = None
        for i in np.argsort(-turn):  # sharpest convex corners first
            if turn[i] <= 0:
                break
            others = np.ones(m, bool)
            others[[(i - 1) % m, i, (i + 1) % m]] = False
            if not _inside(q[others], a[i], q[i], c[i], sign).any():
                ear = int(i)
                break
        if ear is None:  # no clean ear (a self-touching loop): the widest corner
            ear = int(np.argmax(turn))
        tris.append([idx[(ear - 1) % m], idx[ear], idx[(ear + 1) % m]])
        del idx[ear]
    tris.append(idx)
    return np.array(tris, np.int64)


def _inside(pts, a, b, c, sign) -> np.ndarray:
    def side(p, u, v):
        return sign * ((v[0] - u[0]) * (p[:, 1] - u[1]) - (v[1] - u[1]) * (p[:, 0] - u[0]))

    return (side(pts, a, b) >= 0) & (side(pts, b, c) >= 0) & (side(pts, c, a) >= 0)


def _plane_coords(v: np.ndarray) -> np.ndarray:
    """2D coordinates of points [n, 3] in their best-fit plane."""
    centred = v - v.mean(axis=0)
    basis = np.linalg.svd(centred, full_matrices=False)[2][:2]
    return centred @ basis.T


def close_mesh(vertices: np.ndarray, faces: np.ndarray, base_band: float | None,
               hole_edges: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """(vertices, faces with the caps added, info). A loop whose vertices all lie below
    ``base_band`` (None: no base) is the foot: put on y = 0 and capped there; other loops
    are capped when they have at most ``hole_edges`` edges. info says whether the result
    is watertight and, if not, why."""
    import trimesh

    loops, manifold = boundary_loops(faces)
    vertices = vertices.copy()
    caps, foot, holes, left = [], 0, 0, []
    for loop in loops:
        on_base = base_band is not None and bool(np.all(vertices[loop, 1] < base_band))
        if not on_base and len(loop) > hole_edges:
            left.append(len(loop))
            continue
        if on_base:
            vertices[loop, 1] = 0.0  # the cut edge down onto the base: no light leaks under
        ring = loop[::-1]  # the cap runs through the border edges backwards
        v = vertices[ring].astype(np.float64)
        caps.append(ring[ear_clip(v[:, [0, 2]] if on_base else _plane_coords(v))])
        foot, holes = foot + on_base, holes + (not on_base)
    out = np.concatenate([faces, *caps]).astype(np.int32) if caps else faces
    mesh = trimesh.Trimesh(vertices, out, process=False)
    info = {"watertight": bool(mesh.is_watertight), "capped_base_loops": int(foot),
            "capped_holes": int(holes)}
    if not info["watertight"]:
        why = []
        if left:
            why.append(f"{len(left)} open loop(s) off the base with more than {hole_edges} "
                       f"edges (up to {max(left)}; surface no training view saw) are left "
                       "open rather than invented")
        if not manifold or not mesh.is_winding_consistent:
            why.append("marching cubes and the vertex weld left non-manifold edges or "
                       "vertices, which no cap can close")
        info["not_watertight_because"] = "; ".join(why) or "open or non-manifold edges remain"
    return vertices, out, info
