"""Generated datasets as NeRF tools read them: nerfstudio's Blender dataparser's reading rules
(restated here from its public ``blender_dataparser.py``; nerfstudio is not installed) on a
tiny generated dataset, straight alpha in the PNGs, the scene box in the files, old
premultiplied PNGs refused by name, and the ``--layout nerfstudio`` copy in nerfstudio's
Z-up convention."""

from __future__ import annotations

import json
import subprocess
import sys

import imageio
import numpy as np
import pytest
import tiny_cli

from mi_shadowgs import cli
from mi_shadowgs.dataset.loader import DatasetError, load_cameras, load_dataset
from mi_shadowgs.io.images import read_exr
from mi_shadowgs.scenes import scene_path

BLENDER_BOX = 1.5  # nerfstudio's Blender dataparser: SceneBox aabb [-1.5, 1.5]^3, fixed


def srgb(x):
    x = np.clip(np.asarray(x, np.float64), 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:
        for table, config in tiny_cli.presets():
            mp.setitem(table, tiny_cli.TINY, config)
        out = tmp_path_factory.mktemp("nerf_tools") / "data"
        assert cli.main(["generate", str(scene_path("default")), "--out", str(out),
                         "--preset", tiny_cli.TINY, "--no-progress"]) == 0
    return out


def blender_dataparser(data, split, scale_factor=1.0):
    """nerfstudio's Blender dataparser's rules: ``transforms_{split}.json``; each frame's
    image is ``data / (file_path without "./") + ".png"``, read with imageio; poses float32
    [N, 4, 4] of which the top 3 rows are used, their translations times ``scale_factor``;
    the first image gives H, W; focal = 0.5 W / tan(0.5 camera_angle_x); cx, cy the
    centre; the scene box is [-1.5, 1.5]^3."""
    meta = json.loads((data / f"transforms_{split}.json").read_text())
    files = [data / (frame["file_path"].replace("./", "") + ".png") for frame in meta["frames"]]
    poses = np.array([np.array(frame["transform_matrix"]) for frame in meta["frames"]])
    poses = poses.astype(np.float32)[:, :3]
    poses[..., 3] *= scale_factor
    img0 = imageio.v2.imread(files[0])
    h, w = img0.shape[:2]
    focal = 0.5 * w / np.tan(0.5 * float(meta["camera_angle_x"]))
    images = [imageio.v2.imread(f) for f in files]  # what its dataset then loads
    return {"files": files, "c2w": poses, "focal": focal, "cx": w / 2.0, "cy": h / 2.0,
            "images": images, "meta": meta}


def test_every_split_loads_by_the_blender_dataparsers_rules(data):
    for split in ("train", "val", "test"):
        out = blender_dataparser(data, split)
        assert len(out["files"]) > 0 and all(img.shape[-1] == 4 for img in out["images"])
    # val is the test split; our own loader reads it too
    assert blender_dataparser(data, "val")["meta"]["frames"] == \
        blender_dataparser(data, "test")["meta"]["frames"]
    assert len(load_dataset(data, "val").views) == len(load_dataset(data, "test").views)


def test_pngs_hold_straight_alpha(data):
    """NeRF-synthetic's PNGs are straight: colour / coverage. Edge pixels (coverage in
    (0.05, 0.95)) of ours carry the colour of the EXR divided by its alpha, not the dimmed
    premultiplied one (what gave silhouettes a dark fringe)."""
    edges = 0
    for split in ("train", "test"):
        for frame in blender_dataparser(data, split)["meta"]["frames"]:
            stem = data / frame["file_path"].replace("./", "")
            png = imageio.v2.imread(stem.with_suffix(".png")).astype(np.float64) / 255.0
            exr = read_exr(stem.with_suffix(".exr")).astype(np.float64)
            a = exr[..., 3:]
            np.testing.assert_allclose(png[..., 3:], a, atol=0.5 / 255 + 1e-6)
            edge = ((a > 0.05) & (a < 0.95))[..., 0]
            straight = srgb(exr[..., :3] / np.maximum(a, 1e-12))
            assert np.abs(png[..., :3][edge] - straight[edge]).max() <= 1.0 / 255 + 1e-6
            edges += int(edge.sum())
    assert edges > 0


def test_the_scene_box_is_in_the_files_and_holds_the_scene(data):
    info = json.loads((data / "dataset.json").read_text())
    assert info["png_alpha"] == "straight"
    box = np.array(info["scene_box"])
    for split in ("train", "val", "test"):
        assert json.loads((data / f"transforms_{split}.json").read_text())["scene_box"] == \
            info["scene_box"]
    centre, radius = np.array(info["object"]["center"]), info["object"]["radius"]
    # the object's bounding sphere meets the box's top only where the object is: its centre
    # inside, its radius within the box's horizontal extent; the base is y = 0
    assert np.all(box[0] <= centre) and np.all(centre <= box[1])
    assert box[0][1] <= 1e-6 and box[1][1] <= centre[1] + radius + 1e-6
    assert np.all(box[0][[0, 2]] <= -radius) and np.all(box[1][[0, 2]] >= radius)
    # The Blender dataparser's box is fixed at +-1.5: the recorded box says which of its
    # scale_factor puts the whole scene inside (the default scene's base reaches +-1.6).
    scale = min(1.0, BLENDER_BOX / np.abs(box).max())
    scaled = blender_dataparser(data, "train", scale_factor=scale)
    assert np.all(np.abs(box * scale) <= BLENDER_BOX + 1e-6)
    assert np.all(np.linalg.norm(scaled["c2w"][:, :, 3], axis=1) > np.abs(box * scale).max())


def test_old_premultiplied_pngs_are_refused_by_name(data, tmp_path):
    import shutil

    old = tmp_path / "old"
    shutil.copytree(data, old)
    info = json.loads((old / "dataset.json").read_text())
    del info["png_alpha"]
    (old / "dataset.json").write_text(json.dumps(info))
    assert len(load_dataset(old, "train").views) > 0  # the EXRs are read: fine
    (old / "train" / "r_000.exr").unlink()
    with pytest.raises(DatasetError, match=r"png_alpha.*train/r_000\.png.*premultiplied"):
        load_dataset(old, "train")


def test_nerfstudio_layout_is_z_up_with_applied_transform(data, tmp_path):
    dst = tmp_path / "ns"
    res = subprocess.run([sys.executable, "-m", "mi_shadowgs.dataset.export", str(data),
                          str(dst), "--layout", "nerfstudio"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    meta = json.loads((dst / "transforms.json").read_text())
    applied = np.array(meta["applied_transform"])
    assert applied.shape == (3, 4)
    # nerfstudio's rules: file_path relative to the folder; the split lists name frames
    names = [f["file_path"] for f in meta["frames"]]
    for split in ("train", "val", "test"):
        assert set(meta[f"{split}_filenames"]) <= set(names)
    ours = {split: [c for _, c in load_cameras(data / f"transforms_{split}.json")]
            for split in ("train", "test")}
    by_name = {f["file_path"]: f for f in meta["frames"]}
    for split, cams in ours.items():
        for i, cam in enumerate(cams):
            fr = by_name[f"{split}/r_{i}.png"]
            c2w = np.array(fr["transform_matrix"])
            # Z-up: every camera looks at the scene from above the base (z > 0)
            assert c2w[2, 3] > 0
            np.testing.assert_allclose(applied[:, :3] @ cam.c2w[:3], c2w[:3], atol=1e-12)
            img = imageio.v2.imread(dst / fr["file_path"])
            assert img.shape == (fr["h"], fr["w"], 4)
    assert meta["scene_box"][0][2] <= 1e-6  # the base at z = 0
