"""Camera poses, intrinsics and image encodings checked as the loader reads them
(docs/robustness.md, "Poses, intrinsics and image encodings")."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from mi_shadowgs import cli
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.dataset.loader import DatasetError, load_cameras, load_dataset
from mi_shadowgs.dataset.poses import ORTHONORMAL_TOLERANCE, PoseError, check_pose
from mi_shadowgs.io.images import write_png

CAM = Camera.look_at([0, 1, 4], [0, 0, 0], fov_x=0.7, width=8, height=6)


def _folder(tmp_path, matrices, meta_extra=None, files=None) -> None:
    (tmp_path / "train").mkdir(exist_ok=True)
    img = np.full((6, 8, 4), 128, np.uint8)
    img[..., 3] = 255
    names = files or [f"./train/r_{i}" for i in range(len(matrices))]
    for name in set(names):
        write_png(tmp_path / (name + ".png"), img)
    meta = {"camera_angle_x": 0.7, "frames": [
        {"file_path": n, "transform_matrix": np.asarray(m).tolist()}
        for n, m in zip(names, matrices, strict=True)]}
    meta.update(meta_extra or {})
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))


def _shear(k: float) -> np.ndarray:
    s = np.eye(4)
    s[0, 1] = k
    return CAM.c2w @ s


def _bottom(row) -> np.ndarray:
    m = CAM.c2w.copy()
    m[3] = row
    return m


@pytest.mark.parametrize("matrix, message", [
    (_shear(0.2), "has a rotation that is not orthonormal"),
    (CAM.c2w @ np.diag([1.0, 1.0, -1.0, 1.0]), "has a mirrored rotation (determinant -1"),
    (_bottom([0, 0, 0, 2]), "has bottom row 0 0 0 2, not 0 0 0 1"),
    (_bottom([0, 0.1, 0, 1]), "has bottom row 0 0.1 0 1"),
    (CAM.c2w @ np.diag([1.0, 2.0, 1.0, 1.0]), "has a rotation that is not orthonormal"),
])
def test_a_pose_that_is_no_rigid_transform_names_file_frame_and_field(tmp_path, matrix,
                                                                      message):
    _folder(tmp_path, [CAM.c2w, matrix])
    with pytest.raises(DatasetError) as err:
        load_cameras(tmp_path / "transforms_train.json")
    assert f"transforms_train.json: field 'frames[1].transform_matrix' {message}" in \
        str(err.value)


def test_a_uniformly_scaled_rotation_is_taken_without_its_scale_said_once(tmp_path, capsys):
    scaled = CAM.c2w.copy()
    scaled[:3, :3] *= 2.5
    _folder(tmp_path, [CAM.c2w, scaled, scaled])
    capsys.readouterr()
    for _ in range(2):
        cams = load_cameras(tmp_path / "transforms_train.json")
    np.testing.assert_allclose(cams[1][1].c2w, cams[0][1].c2w, atol=1e-12)
    err = capsys.readouterr().err
    assert err.count("orthonormal up to a uniform scale") == 1, err
    assert "2 frame(s) (1, 2)" in err and "(2.5 to 2.5); taken without it" in err
    # A pose of scale 1 is kept bit for bit.
    exact, scale = check_pose(CAM.c2w)
    assert scale is None and np.array_equal(exact, CAM.c2w)


def test_two_frames_on_one_image_file_are_refused(tmp_path):
    _folder(tmp_path, [CAM.c2w, _shear(0.0)], files=["./train/r_0", "train/r_0.png"])
    with pytest.raises(DatasetError, match=re.escape(
            "frames 0 and 1 name one image file ('train/r_0.png', field "
            "'frames[1].file_path')")):
        load_cameras(tmp_path / "transforms_train.json")


@pytest.mark.parametrize("extra, message", [
    ({"fl_x": 1e12}, "field 'fl_x/fl_y' (frame 0): fl_x = 1e+12 px gives a 4.58e-10 degree"),
    ({"fl_x": 1e-3}, "fl_x = 0.001 px gives a 180 degree"),
    ({"fl_x": 8.0, "fl_y": 80.0}, "fl_y / fl_x = 10"),
    ({"camera_angle_x": 1e-9}, "field 'camera_angle_x' (frame 0): fl_x ="),
])
def test_focal_lengths_no_camera_has_are_named(tmp_path, extra, message):
    _folder(tmp_path, [CAM.c2w], meta_extra=extra)
    with pytest.raises(DatasetError, match=re.escape(message)):
        load_cameras(tmp_path / "transforms_train.json")


def test_a_tensoir_pose_is_checked_as_well(tmp_path):
    folder = tmp_path / "train_000"
    folder.mkdir()
    m = CAM.c2w @ np.diag([1.0, 1.0, -1.0, 1.0])
    (folder / "metadata.json").write_text(json.dumps({
        "cam_transform_mat": ",".join(str(v) for v in m.ravel()), "cam_angle_x": 0.7,
        "imw": 8, "imh": 6}))
    with pytest.raises(DatasetError, match="metadata.json: field 'cam_transform_mat' has a "
                                           "mirrored rotation"):
        load_dataset(tmp_path, "train")


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    """A camera pose spoilt by one of the faults a hand-edited or foreign file has."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = q, rng.normal(size=3) * 3
    kind = rng.integers(7)
    if kind == 0:  # shear
        s = np.eye(4)
        s[rng.integers(3), rng.integers(3)] += rng.normal() * 10.0 ** rng.uniform(-5, 0)
        m = m @ s
    elif kind == 1:  # reflection
        m = m @ np.diag([*rng.permutation([1.0, 1.0, -1.0]), 1.0])
    elif kind == 2:  # uniform scale
        m[:3, :3] *= 10.0 ** rng.uniform(-3, 3)
    elif kind == 3:  # uneven scale
        m[:3, :3] *= 10.0 ** rng.uniform(-2, 2, size=3)
    elif kind == 4:  # projective bottom row
        m[3] = rng.normal(size=4) * 10.0 ** rng.uniform(-7, 0)
        m[3, 3] += 1.0
    elif kind == 5:  # NaN or Inf somewhere
        m[rng.integers(4), rng.integers(4)] = rng.choice([np.nan, np.inf, -np.inf])
    # kind 6: a clean pose
    return m


def test_fuzzed_poses_load_as_rigid_cameras_or_are_named(tmp_path):
    """Seeded fuzz of pose matrices: each loads as a rigid camera (rotation orthonormal,
    det +1, bottom row 0 0 0 1) or is refused with a DatasetError naming the file, the frame
    and the field; nothing else happens."""
    rng = np.random.default_rng(66)
    loaded = refused = 0
    for trial in range(150):
        m = _random_pose(rng)
        try:
            fixed, _ = check_pose(m)
        except PoseError:
            refused += 1
        else:
            loaded += 1
            r = fixed[:3, :3]
            assert np.max(np.abs(r.T @ r - np.eye(3))) <= ORTHONORMAL_TOLERANCE * 1.01
            assert np.linalg.det(r) > 0 and np.array_equal(fixed[3], [0, 0, 0, 1])
        if trial % 10 == 0:  # through the loader too, the pose as frame 1
            _folder(tmp_path, [CAM.c2w, m])
            path = tmp_path / "transforms_train.json"
            try:
                cams = load_cameras(path)
            except DatasetError as exc:
                assert f"{path}: field 'frames[1].transform_matrix'" in str(exc), exc
            else:
                assert np.isfinite(cams[1][1].c2w).all()
    assert loaded > 20 and refused > 60, (loaded, refused)


def test_train_refuses_a_sheared_pose_and_trains_on_a_scaled_one(tmp_path, tiny_presets,
                                                                 capsys):
    from mi_shadowgs.scenes import scene_path

    data = tmp_path / "data"
    assert cli.main(["generate", str(scene_path("default")), "--out", str(data), "--preset",
                     "test-tiny", "--no-progress"]) == 0
    path = data / "transforms_train.json"
    meta = json.loads(path.read_text())
    good = json.dumps(meta)
    m = np.asarray(meta["frames"][2]["transform_matrix"])
    meta["frames"][2]["transform_matrix"] = (m @ np.diag([1.0, 1.3, 1.0, 1.0])).tolist()
    path.write_text(json.dumps(meta))
    capsys.readouterr()
    train = ["train", str(data), "--out", str(tmp_path / "run"), "--preset", "test-tiny",
             "--no-progress", "--no-eval"]
    assert cli.main(train) == 2
    err = capsys.readouterr().err
    assert f"{path}: field 'frames[2].transform_matrix' has a rotation that is not " \
        "orthonormal" in err, err
    assert not (tmp_path / "run").exists()
    meta = json.loads(good)
    m = np.asarray(meta["frames"][2]["transform_matrix"])
    m[:3, :3] *= 0.5
    meta["frames"][2]["transform_matrix"] = m.tolist()
    path.write_text(json.dumps(meta))
    assert cli.main([*train, "--overwrite"]) == 0
    assert "orthonormal up to a uniform scale" in capsys.readouterr().err


# -- image encodings ----------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["L", "L16", "LA", "RGBA16"])
def test_grey_grey_alpha_and_16_bit_pngs_are_converted(tmp_path, mode):
    import imageio.v3 as iio

    _folder(tmp_path, [CAM.c2w])
    png = tmp_path / "train" / "r_0.png"
    if mode == "L":
        img = np.full((6, 8), 128, np.uint8)
    elif mode == "L16":
        img = np.full((6, 8), 128 * 257, np.uint16)
    elif mode == "LA":
        img = np.stack([np.full((6, 8), 128, np.uint8), np.full((6, 8), 255, np.uint8)], -1)
        img[0, 0, 1] = 0
    else:
        img = np.full((6, 8, 4), 128 * 257, np.uint16)
        img[..., 3] = 65535
    if img.dtype == np.uint16 and img.ndim == 3:  # Pillow cannot write 16-bit RGBA
        _write_png16(png, img)
    else:
        iio.imwrite(png, img, extension=".png")
    view = load_dataset(tmp_path, "train").views[0]
    assert view.image.shape == (6, 8, 3)
    np.testing.assert_allclose(view.image, 0.21586, atol=1e-4)  # sRGB 128/255 -> linear
    assert view.mask.sum() == (47 if mode == "LA" else 48)


def _write_png16(path, img: np.ndarray) -> None:
    """A 16-bit RGBA PNG, written by hand."""
    import struct
    import zlib

    h, w, _ = img.shape

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + \
            struct.pack(">I", zlib.crc32(kind + data))

    rows = b"".join(b"\x00" + img[y].astype(">u2").tobytes() for y in range(h))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 6, 0,
                                                                          0, 0))
                     + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))
