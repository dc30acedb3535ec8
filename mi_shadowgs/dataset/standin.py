"""Stage-1-independent stand-in geometry: surfels on the true shapes of a dataset's scene.

Stages 4-5 are developed and validated with it: every surfel lies on a true
surface, with its shape index as the "segment" channel (one segment per Mitsuba shape,
i.e. per material part) and the shape's diffuse reflectance as "albedo_gt".
"""

from __future__ import annotations

import math

import numpy as np

from mi_shadowgs.core.frames import frame_to_quaternion
from mi_shadowgs.core.sampling import sample_surface
from mi_shadowgs.core.surfels import Surfels


def standin_surfels(setup, object_count: int = 20_000, base_count: int = 6_000,
                    base_inner_radius: float = 2.0, base_outer_count: int = 3_000,
                    sigma_factor: float = 0.7, seed: int = 0) -> Surfels:
    """Surfels on ``setup``'s shapes (``dataset.scene.SceneSetup``): the object parts
    with ``object_count`` samples, the base densely within ``base_inner_radius`` object
    radii of the object's axis and sparsely (``base_outer_count`` over its whole area)
    beyond, so that the far base the cameras see at low elevation is covered too.
    Channels: "segment" [N, 1] (shape index), "albedo_gt" [N, 3]."""
    shapes = list(setup.scene.shapes())
    ids = [s.id() for s in shapes]
    obj = [i for i, n in enumerate(ids) if n.startswith("object_")]
    base = [i for i, n in enumerate(ids) if n == "base"]
    pos, nrm, sig, seg, alb = [], [], [], [], []

    def add(s, keep, sigma, index_map):
        pos.append(s.position[keep])
        nrm.append(s.normal[keep])
        sig.append(np.full(int(keep.sum()), sigma))
        seg.append(index_map[s.shape_index[keep]])
        alb.append(s.albedo[keep])

    if obj:
        s = sample_surface([shapes[i] for i in obj], object_count, seed)
        add(s, np.ones(len(s.position), bool), sigma_factor * math.sqrt(s.total_area /
                                                                          object_count),
            np.asarray(obj))
    if base:
        b = [shapes[i] for i in base]
        c = np.asarray(setup.object_center, np.float64)
        r_in = base_inner_radius * float(setup.object_radius)
        area = sum(float(np.asarray(x.surface_area()).ravel()[0]) for x in b)
        disk = math.pi * r_in ** 2
        # Dense inner disc: sample the whole base at the disc's density, keep the disc.
        total = int(base_count * max(1.0, area / disk))
        s = sample_surface(b, total, seed + 1)
        d = np.linalg.norm((s.position - c)[:, [0, 2]], axis=1)
        add(s, d <= r_in, sigma_factor * math.sqrt(s.total_area / total), np.asarray(base))
        if base_outer_count:
            s = sample_surface(b, base_outer_count, seed + 2)
            d = np.linalg.norm((s.position - c)[:, [0, 2]], axis=1)
            add(s, d > r_in, sigma_factor * math.sqrt(s.total_area / base_outer_count),
                np.asarray(base))
    p = np.concatenate(pos)
    sg = np.concatenate(sig)
    return Surfels.from_numpy(p, np.stack([sg, sg], 1), frame_to_quaternion(np.concatenate(nrm)),
                              np.full(len(p), 0.99),
                              channels={"segment": np.concatenate(seg).astype(np.float32)[:, None],
                                        "albedo_gt": np.concatenate(alb)})
