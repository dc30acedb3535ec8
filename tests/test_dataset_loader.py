"""The dataset loader: round trip of a generated dataset, NeRF-synthetic and TensoIR layouts,
and clear errors on malformed or missing files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.generate import trace_ground_truth
from mi_shadowgs.dataset.loader import BLENDER_TO_YUP, DatasetError, load_cameras, load_dataset
from mi_shadowgs.dataset.scene import load_scene
from mi_shadowgs.dataset.writer import write_dataset
from mi_shadowgs.io.images import read_exr, write_png
from mi_shadowgs.presets import generate_config as get_config
from mi_shadowgs.scenes import scene_path


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "tiny"
    cfg = get_config("cpu-small")
    cfg = type(cfg)(**{**cfg.__dict__, "width": 40, "height": 32, "n_train": 3, "n_test": 2,
                       "spp": 4, "envmaps": "sky"})
    write_dataset(scene_path("default"), out, cfg, "cpu-small", seed=3, progress=False)
    return out, cfg


def test_round_trip(generated):
    out, cfg = generated
    train = load_dataset(out, "train")
    test = load_dataset(out, "test")
    assert (len(train), len(test)) == (3, 2)
    v = train.views[0]
    assert v.image.shape == (32, 40, 3) and v.camera.width == 40 and v.camera.height == 32
    assert v.camera.fov_x == pytest.approx(layout.NERF_CAMERA_ANGLE_X)
    assert v.visibility.shape == (32, 40, 2) and v.irradiance.shape == (32, 40, 2, 3)
    # The loaded buffers equal a fresh trace of the loaded cameras (float32 EXR round trip).
    gt = trace_ground_truth(load_scene(scene_path("default")), train.cameras)
    np.testing.assert_allclose(train.stack("depth"), gt["depth"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(train.stack("normal"), gt["normal"], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(train.stack("material"), gt["material"])
    np.testing.assert_array_equal(train.stack("object_mask"), gt["object"])
    np.testing.assert_array_equal(train.stack("visibility"), gt["visibility"])
    # image alpha (coverage > 0.5) agrees with the traced mask except at silhouette pixels
    assert np.mean(train.stack("mask") == gt["mask"]) > 0.97
    assert set(test.views[0].relit) == {"sun_high", "sun_low", "pair_cross", "env_sky_envmap"}
    assert train.lights["training"]["lights"][0]["name"] == "light0"
    assert train.info["seed"] == 3
    np.testing.assert_allclose(train.views[0].image, read_exr(out / "train/r_000.exr")[..., :3])


def _nerf_folder(tmp_path, frames=None, meta_extra=None, alpha=255):
    (tmp_path / "train").mkdir(exist_ok=True)
    img = np.zeros((6, 8, 4), np.uint8)
    img[..., :3] = 128
    img[..., 3] = alpha
    write_png(tmp_path / "train" / "r_0.png", img)
    cam = Camera.look_at([0, 1, 4], [0, 0, 0], fov_x=0.7, width=8, height=6)
    meta = {"camera_angle_x": 0.7,
            "frames": frames if frames is not None else
            [{"file_path": "./train/r_0", "transform_matrix": cam.c2w.tolist()}]}
    meta.update(meta_extra or {})
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    return cam


def test_nerf_layout_size_from_image(tmp_path):
    cam = _nerf_folder(tmp_path)
    (name, got), = load_cameras(tmp_path / "transforms_train.json")
    assert name == "./train/r_0" and (got.width, got.height) == (8, 6)
    # NeRF-synthetic's world is Blender's (Z-up): turned to ours, the camera's height (z)
    # becomes y, and the Blender camera's "up" (its local +Y) turns with the world.
    np.testing.assert_allclose(got.c2w, BLENDER_TO_YUP @ cam.c2w)
    np.testing.assert_allclose(got.origin, [0.0, 4.0, -1.0])
    ds = load_dataset(tmp_path, "train")
    assert ds.views[0].image.shape == (6, 8, 3)
    # sRGB 128 decodes to linear 0.2158
    assert ds.views[0].image[0, 0, 0] == pytest.approx(0.21586, abs=1e-4)
    assert ds.views[0].albedo is None


@pytest.mark.parametrize("frames, field", [
    ([{"file_path": "./train/r_0", "transform_matrix": [[1, 0], [0, 1]]}],
     "frames[0].transform_matrix"),
    ([{"file_path": "./train/r_0"}], "frames[0].transform_matrix"),
    ([{"transform_matrix": np.eye(4).tolist()}], "frames[0].file_path"),
    ([], "frames"),
])
def test_malformed_transforms_names_file_and_field(tmp_path, frames, field):
    _nerf_folder(tmp_path, frames=frames, meta_extra={"w": 8, "h": 6})
    with pytest.raises(DatasetError) as err:
        load_cameras(tmp_path / "transforms_train.json")
    assert "transforms_train.json" in str(err.value) and field in str(err.value)


def test_bad_json_and_angle(tmp_path):
    p = tmp_path / "transforms_train.json"
    p.write_text("{not json")
    with pytest.raises(DatasetError, match="transforms_train.json: malformed JSON"):
        load_cameras(p)
    _nerf_folder(tmp_path, meta_extra={"camera_angle_x": "wide"})
    with pytest.raises(DatasetError, match="'camera_angle_x'"):
        load_cameras(p)


def test_missing_frame_and_empty_mask(tmp_path):
    cam = _nerf_folder(tmp_path, alpha=0)
    with pytest.raises(DatasetError, match="mask .* empty"):
        load_dataset(tmp_path, "train")
    assert len(load_dataset(tmp_path, "train", require_mask=False)) == 1
    frames = [{"file_path": "./train/r_0", "transform_matrix": cam.c2w.tolist()},
              {"file_path": "./train/r_1", "transform_matrix": cam.c2w.tolist()}]
    _nerf_folder(tmp_path, frames=frames, meta_extra={"w": 8, "h": 6})
    with pytest.raises(DatasetError, match=r"frame 1 \('./train/r_1'\) is missing"):
        load_dataset(tmp_path, "train", require_mask=False)


def test_tensoir_layout_turns_z_up_into_y_up(tmp_path):
    # A Blender camera at (0, -4, 0) (Z-up) looking at the origin, up = +Z.
    c2w = np.array([[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]], float)
    folder = tmp_path / "test_000"
    folder.mkdir()
    (folder / "metadata.json").write_text(json.dumps({
        "cam_transform_mat": ",".join(str(x) for x in c2w.ravel()),
        "cam_angle_x": 0.8575560450553894, "imw": 4, "imh": 4}))
    rgba = np.full((4, 4, 4), 255, np.uint8)
    write_png(folder / "rgba.png", rgba)
    write_png(folder / "rgba_city.png", rgba)
    normal = np.zeros((4, 4, 4), np.uint8)
    normal[..., 2] = 255  # Blender +Z (up) as a [0, 1] colour: (0.5, 0.5, 1)
    normal[..., :2] = 128
    normal[..., 3] = 255
    write_png(folder / "normal.png", normal)
    ds = load_dataset(tmp_path, "test")
    assert ds.layout == "tensoir" and len(ds) == 1
    cam = ds.views[0].camera
    np.testing.assert_allclose(cam.origin, [0, 0, 4], atol=1e-12)
    np.testing.assert_allclose(cam.forward, [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(cam.c2w[:3, 1], [0, 1, 0], atol=1e-12)  # image up = world +Y
    assert cam.fov_x == pytest.approx(0.8575560450553894)
    # PNG normals carry 8-bit quantisation: (128/255)*2-1 = 0.0039
    np.testing.assert_allclose(ds.views[0].normal[0, 0], [0, 1, 0], atol=0.01)
    assert set(ds.views[0].relit) == {"city"}
    assert math.isclose(float(ds.views[0].image.max()), 1.0)


def test_nerf_synthetic_copy_in_blender_frame_loads_as_the_original(generated, tmp_path):
    """Our dataset turned into Blender's Z-up world (no dataset.json, no world_up) loads back
    to the same Y-up cameras and normals: the loader recognises NeRF-synthetic's frame."""
    from validation.nerf_synthetic_copy import blender_copy

    out, _ = generated
    blender_copy(out, tmp_path / "blender")
    meta = json.loads((tmp_path / "blender" / "transforms_train.json").read_text())
    raw = np.array(meta["frames"][0]["transform_matrix"])
    assert raw[2, 3] > 0.5  # in the copy the cameras stand above the z = 0 plane
    a, b = load_dataset(out, "train"), load_dataset(tmp_path / "blender", "train")
    for va, vb in zip(a.views, b.views, strict=True):
        np.testing.assert_allclose(vb.camera.c2w, va.camera.c2w, atol=1e-12)
        np.testing.assert_allclose(vb.normal, va.normal, atol=1e-6)
        np.testing.assert_array_equal(vb.image, va.image)


def test_copy_without_masks_loads_without_masks(generated, tmp_path):
    """``validation.without_masks``'s copy: the same training images and cameras with no
    mask (no alpha, no object masks, ``"masks": false``), and the test split untouched, so
    that both stage-1 runs are scored against the same ground truth."""
    from validation.without_masks import unmasked_copy

    out, _ = generated
    unmasked_copy(out, tmp_path / "nomask")
    a, b = load_dataset(out, "train"), load_dataset(tmp_path / "nomask", "train")
    assert all(v.has_mask for v in a.views) and not any(v.has_mask for v in b.views)
    assert all(v.object_mask is None for v in b.views)
    for va, vb in zip(a.views, b.views, strict=True):
        np.testing.assert_array_equal(vb.camera.c2w, va.camera.c2w)
        np.testing.assert_array_equal(vb.image, va.image)
    ta, tb = load_dataset(out, "test"), load_dataset(tmp_path / "nomask", "test")
    for va, vb in zip(ta.views, tb.views, strict=True):
        np.testing.assert_array_equal(vb.mask, va.mask)
        assert vb.has_mask
    with pytest.raises(FileExistsError):
        unmasked_copy(out, tmp_path / "nomask")


@pytest.mark.parametrize("name, field, value, message", [
    ("lights.json", "training", 5, "field 'training' must be an object, got 5"),
    ("lights.json", "training", {"lights": {"a": 1}}, "field 'training.lights' must be a list"),
    ("lights.json", "relightings", [3], "field 'relightings' must be a list of objects"),
    ("dataset.json", "materials", 5, "field 'materials' must be a list of objects, got 5"),
])
def test_a_field_of_the_wrong_kind_names_its_file_and_field(generated, tmp_path, name, field,
                                                             value, message):
    """A number where an object or a list belongs, in a field the loader or the stages read
    by name: a DatasetError naming it at load time (it was a TypeError or AttributeError,
    the materials' only after stages 1 and 2 had trained)."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(generated[0], data)
    doc = json.loads((data / name).read_text())
    doc[field] = value
    (data / name).write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=f"{name}: {message}"):
        load_dataset(data, "train")
