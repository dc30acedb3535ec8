"""Copies of a dataset in the public layouts with the images, masks and cameras only: what
a NeRF-synthetic or TensoIR download gives a user (issue 17). ``run`` must finish on them,
scoring only what needs no ground truth.

- ``"nerf"``: ``transforms_{train,test}.json`` (OpenGL camera-to-world in Blender's Z-up
  world, ``camera_angle_x``, no ``w``/``h``, no ``world_up``) and ``<split>/r_<i>.png``
  8-bit sRGB RGBA, as NeRF-synthetic ships them.
- ``"tensoir"``: ``<split>_<i>/metadata.json`` (Blender Z-up ``cam_transform_mat`` as a
  comma-separated string, ``cam_angle_x``, ``imw``, ``imh``) and ``rgba.png``.

No albedo, normals, depth, material ids, visibility, irradiance, relit images,
``lights.json`` or ``dataset.json`` is copied.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.loader import BLENDER_TO_YUP, load_dataset
from mi_shadowgs.io.atomic import atomic_dir
from mi_shadowgs.io.images import write_png

LAYOUTS = ("nerf", "tensoir")


def export_without_ground_truth(src: str | Path, dst: str | Path, kind: str) -> Path:
    """Write the ``kind`` copy of dataset ``src`` into the new folder ``dst``."""
    if kind not in LAYOUTS:
        raise ValueError(f"export layout must be one of {LAYOUTS}, got {kind!r}")
    dst = Path(dst)
    if dst.exists():
        raise FileExistsError(f"{dst}: exists; the copy goes into a new folder")
    with atomic_dir(dst) as tmp:
        for split in layout.SPLITS:
            data = load_dataset(src, split)
            frames = []
            for i, v in enumerate(data.views):
                rgba = np.concatenate([np.clip(v.image, 0.0, 1.0),
                                       v.mask[..., None].astype(np.float64)], axis=-1)
                if kind == "nerf":
                    stem = f"{split}/r_{i}"
                    write_png(tmp / f"{stem}.png", rgba)
                    # NeRF-synthetic is Blender's Z-up world; the loader turns it back
                    c2w_blender = BLENDER_TO_YUP.T @ np.asarray(v.camera.c2w, np.float64)
                    frames.append({"file_path": f"./{stem}",
                                   "transform_matrix": c2w_blender.tolist()})
                else:
                    folder = tmp / f"{split}_{i:03d}"
                    write_png(folder / "rgba.png", rgba)
                    c2w_blender = BLENDER_TO_YUP.T @ np.asarray(v.camera.c2w, np.float64)
                    meta = {"cam_transform_mat": ",".join(repr(float(x))
                                                          for x in c2w_blender.ravel()),
                            "cam_angle_x": float(v.camera.fov_x),
                            "imw": int(v.camera.width), "imh": int(v.camera.height)}
                    (folder / "metadata.json").write_text(json.dumps(meta, indent=1))
            if kind == "nerf":
                meta = {"camera_angle_x": float(data.views[0].camera.fov_x), "frames": frames}
                (tmp / layout.transforms_name(split)).write_text(json.dumps(meta, indent=1))
    return dst
