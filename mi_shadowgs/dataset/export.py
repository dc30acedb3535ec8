"""Copies of a dataset in the public layouts with the images, masks and cameras only: what
a NeRF-synthetic or TensoIR download gives a user. ``run`` must finish on them,
scoring only what needs no ground truth.

- ``"nerf"``: ``transforms_{train,test}.json`` (OpenGL camera-to-world in Blender's Z-up
  world, ``camera_angle_x``, no ``w``/``h``, no ``world_up``) and ``<split>/r_<i>.png``
  8-bit sRGB RGBA, as NeRF-synthetic ships them.
- ``"nerfstudio"``: one ``transforms.json`` as nerfstudio's own format takes it: Blender's
  Z-up world (nerfstudio's viewer is Z-up), per-file intrinsics (``fl_x``, ``fl_y``, ``cx``,
  ``cy``, ``w``, ``h``, ``camera_model``), ``applied_transform`` (the 3x4 that took our
  Y-up world to this one), ``train_filenames``/``val_filenames``/``test_filenames`` (val =
  test), the ``scene_box`` in this world, and ``<split>/r_<i>.png`` straight-alpha RGBA.
- ``"tensoir"``: ``<split>_<i>/metadata.json`` (Blender Z-up ``cam_transform_mat`` as a
  comma-separated string, ``cam_angle_x``, ``imw``, ``imh``) and ``rgba.png``.

No albedo, normals, depth, material ids, visibility, irradiance, relit images,
``lights.json`` or ``dataset.json`` is copied.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.loader import BLENDER_TO_YUP, load_dataset
from mi_shadowgs.io.atomic import atomic_dir
from mi_shadowgs.io.images import write_png

LAYOUTS = ("nerf", "tensoir", "nerfstudio")
# Our Y-up world -> Blender's / nerfstudio's Z-up one (x, y, z = x, -z, y)
YUP_TO_ZUP = BLENDER_TO_YUP.T


def export_without_ground_truth(src: str | Path, dst: str | Path, kind: str) -> Path:
    """Write the ``kind`` copy of dataset ``src`` into the new folder ``dst``."""
    if kind not in LAYOUTS:
        raise ValueError(f"export layout must be one of {LAYOUTS}, got {kind!r}")
    dst = Path(dst)
    if dst.exists():
        raise FileExistsError(f"{dst}: exists; the copy goes into a new folder")
    if kind == "nerfstudio":
        return _export_nerfstudio(Path(src), dst)
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


def _straight_rgba(src: Path, view) -> np.ndarray:
    """[H, W, 4] straight-alpha RGBA of a view: its EXR (premultiplied, with the true
    coverage) when there is one, else its image with the mask as alpha."""
    from mi_shadowgs.io.images import read_exr

    exr = src / (view.name + layout.IMAGE_EXR)
    if exr.is_file():
        rgba = read_exr(exr).astype(np.float64)
        rgb, a = rgba[..., :3], rgba[..., 3:4]
    else:
        rgb, a = np.asarray(view.image, np.float64), view.mask[..., None].astype(np.float64)
        return np.concatenate([np.clip(rgb, 0.0, 1.0), a], axis=-1)
    straight = np.where(a > 0, rgb / np.maximum(a, 1e-12), 0.0)
    return np.concatenate([np.clip(straight, 0.0, 1.0), a], axis=-1)


def _export_nerfstudio(src: Path, dst: Path) -> Path:
    frames, names = [], {}
    with atomic_dir(dst) as tmp:
        for split in layout.SPLITS:
            data = load_dataset(src, split)
            names[split] = []
            for i, v in enumerate(data.views):
                name = f"{split}/r_{i}.png"
                write_png(tmp / name, _straight_rgba(src, v))
                cam = v.camera
                fx = 0.5 * cam.width / np.tan(0.5 * cam.fov_x)
                frames.append({
                    "file_path": name,
                    "transform_matrix": (YUP_TO_ZUP @ np.asarray(cam.c2w, np.float64)).tolist(),
                    "fl_x": fx, "fl_y": cam.focal_y or fx,
                    "cx": cam.width / 2.0 if cam.cx is None else cam.cx,
                    "cy": cam.height / 2.0 if cam.cy is None else cam.cy,
                    "w": int(cam.width), "h": int(cam.height), "camera_model": "OPENCV"})
                names[split].append(name)
        meta = {"frames": frames,
                "applied_transform": YUP_TO_ZUP[:3].tolist(),
                "train_filenames": names["train"], "val_filenames": names["test"],
                "test_filenames": names["test"]}
        info = data.info or {}
        if "scene_box" in info:
            corners = np.array(np.meshgrid(*np.array(info["scene_box"]).T)).reshape(3, -1).T
            turned = corners @ YUP_TO_ZUP[:3, :3].T
            meta["scene_box"] = [turned.min(0).tolist(), turned.max(0).tolist()]
        (tmp / "transforms.json").write_text(json.dumps(meta, indent=1))
    return dst


def main(argv=None) -> int:
    """``python -m mi_shadowgs.dataset.export SRC DST --layout {nerf,tensoir,nerfstudio}``."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m mi_shadowgs.dataset.export",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("src", help="a dataset (our layout)")
    parser.add_argument("dst", help="the new folder of the copy")
    parser.add_argument("--layout", choices=LAYOUTS, default="nerf")
    args = parser.parse_args(argv)
    try:
        out = export_without_ground_truth(args.src, args.dst, args.layout)
    except (ValueError, FileExistsError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({args.layout} layout)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
