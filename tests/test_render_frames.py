"""``mi-shadowgs render`` never guesses a world frame: a model and cameras in a foreign frame
(another tool's, NeRF-synthetic's Blender Z-up) render right or exit 2, checked against an
independent float64 projection of the scene (no project code in the reference)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mi_shadowgs import cli
from mi_shadowgs.io import ply
from mi_shadowgs.io.images import read_exr

W, H, FOV = 64, 48, 0.7
# Three small discs, red, green and blue, placed asymmetrically in Blender's Z-up world.
POINTS_BLENDER = np.array([[0.45, 0.1, 0.0], [-0.2, 0.0, 0.5], [0.0, 0.3, -0.25]])
EYE_BLENDER = np.array([0.6, -3.0, 1.1])
# Blender Z-up -> our Y-up: x, y, z = x_b, z_b, -y_b (docs/conventions.md)
TO_YUP = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])


def _c2w_gl(eye, target, up) -> np.ndarray:
    """OpenGL camera-to-world (looks down -Z, +Y up) from first principles."""
    back = (eye - target) / np.linalg.norm(eye - target)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(back, right), back, eye
    return m


def _quat(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (Shepperd's method, trace branch suffices here)."""
    w = 0.5 * math.sqrt(max(1e-12, 1.0 + np.trace(r)))
    return np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w),
                     (r[1, 0] - r[0, 1]) / (4 * w)])


def _expected_pixels(points, c2w) -> np.ndarray:
    """[3, 2] pixel (column, row) of each point: the pinhole of the transforms file."""
    f = 0.5 * W / math.tan(0.5 * FOV)
    cam = (np.linalg.inv(c2w) @ np.c_[points, np.ones(len(points))].T)[:3].T
    return np.stack([f * cam[:, 0] / -cam[:, 2] + 0.5 * W,
                     -f * cam[:, 1] / -cam[:, 2] + 0.5 * H], axis=-1)


def _model(points, c2w) -> ply.PlyModel:
    """Opaque discs at ``points`` facing the camera (normal = camera +Z), one colour each."""
    q = _quat(c2w[:3, :3])
    dc = np.full((3, 3), -0.5 / ply.SH_C0) + np.eye(3) / ply.SH_C0  # colour = C0 f + 0.5
    return ply.PlyModel(position=points.astype(np.float32),
                        log_scale=np.full((3, 2), math.log(0.04), np.float32),
                        rotation=np.tile(q, (3, 1)).astype(np.float32),
                        opacity_logit=np.full(3, 6.0, np.float32),
                        channels={"sh": dc.astype(np.float32)})


def _centroids(rgb: np.ndarray) -> np.ndarray:
    rows, cols = np.mgrid[0:H, 0:W] + 0.5
    out = []
    for c in range(3):
        w = rgb[..., c]
        if w.sum() < 1.0:  # a disc out of view
            return np.full((3, 2), np.inf)
        out.append([(w * cols).sum() / w.sum(), (w * rows).sum() / w.sum()])
    return np.array(out)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("frames")
    c2w_b = _c2w_gl(EYE_BLENDER, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    expected = _expected_pixels(POINTS_BLENDER, c2w_b)
    assert np.all((expected > 4) & (expected < [W - 4, H - 4]))
    frame = {"file_path": "./test/r_0", "transform_matrix": c2w_b.tolist()}
    # NeRF-synthetic's layout: no world_up, no dataset.json beside it
    (root / "foreign").mkdir()
    (root / "foreign" / "transforms_test.json").write_text(json.dumps(
        {"camera_angle_x": FOV, "w": W, "h": H, "frames": [frame]}))
    ply.write_ply_model(root / "foreign.ply", _model(POINTS_BLENDER, c2w_b))  # no record
    # The same cameras recorded as Blender's
    (root / "blender").mkdir()
    (root / "blender" / "transforms_test.json").write_text(json.dumps(
        {"camera_angle_x": FOV, "w": W, "h": H, "world_up": "+z", "frames": [frame]}))
    # The scene in our Y-up world: model saved with its record, cameras with theirs
    c2w_y = np.eye(4)
    c2w_y[:3, :3], c2w_y[:3, 3] = TO_YUP @ c2w_b[:3, :3], TO_YUP @ c2w_b[:3, 3]
    ours = _model(POINTS_BLENDER @ TO_YUP.T, c2w_y)
    ply.save_ply(root / "ours.ply", ours.to_surfels())
    (root / "ours").mkdir()
    (root / "ours" / "transforms_test.json").write_text(json.dumps(
        {"camera_angle_x": FOV, "w": W, "h": H, "world_up": "+y",
         "frames": [{**frame, "transform_matrix": c2w_y.tolist()}]}))
    # Our model exported in the splat tools' frame, with its records
    ply.write_ply_model(root / "opencv.ply", ply.to_frame(ours, "opencv"),
                        {ply.FRAME_KEY: "opencv"})
    return root, expected


def _render(root, out, model, cameras, *extra) -> int:
    return cli.main(["render", str(root / model), "--cameras",
                     str(root / cameras / "transforms_test.json"), "--out", str(root / out),
                     *extra])


def _error(root, out, expected) -> float:
    rgba = read_exr(root / out / "r_0.exr")
    return float(np.abs(_centroids(rgba[..., :3]) - expected).max())


def test_neither_records_a_frame_exits_2_asking_for_world_up(scene, capsys):
    root, _ = scene
    assert _render(root, "none", "foreign.ply", "foreign") == 2
    err = capsys.readouterr().err
    assert "--world-up" in err and "foreign.ply" in err and "transforms_test.json" in err
    assert not (root / "none").exists()


@pytest.mark.parametrize("model, cameras, extra", [
    ("foreign.ply", "foreign", ["--world-up", "+z"]),  # as given, both Blender's
    ("foreign.ply", "blender", []),  # the model taken in its cameras' recorded frame
    ("ours.ply", "foreign", []),  # our recorded model, NeRF-synthetic's cameras turned
    ("ours.ply", "blender", []),
    ("ours.ply", "ours", []),
    ("opencv.ply", "foreign", []),  # the splat tools' frame, read back into ours
    ("opencv.ply", "ours", []),
])
def test_every_recorded_or_stated_frame_renders_right(scene, model, cameras, extra):
    root, expected = scene
    out = f"{model}-{cameras}-{len(extra)}"
    assert _render(root, out, model, cameras, *extra) == 0
    assert _error(root, out, expected) < 0.35  # pixels; the wrong frame is off by tens


def test_the_wrong_stated_frame_is_a_different_render_never_a_silent_one(scene, capsys):
    """--world-up +y says the foreign model is Y-up: the cameras are turned and the discs
    leave the view; a recorded model refuses a --world-up that contradicts its record."""
    root, expected = scene
    assert _render(root, "wrong", "foreign.ply", "foreign", "--world-up", "+y") == 0
    assert _error(root, "wrong", expected) > 3
    assert _render(root, "contra", "ours.ply", "foreign", "--world-up", "+z") == 2
    assert "records its world frame" in capsys.readouterr().err


def test_splat_conventions_read_an_export_that_lost_its_records(scene, tmp_path):
    root, expected = scene
    model = ply.read_ply_model(root / "opencv.ply", frame="y-up")  # the stored values
    model.channels["sh"] = ply.sh_to_srgb(model.channels["sh"])
    ply.write_ply_model(tmp_path / "stripped.ply", model)  # as splat-transform writes it
    (tmp_path / "foreign").symlink_to(root / "foreign")
    assert _render(tmp_path, "a", "stripped.ply", "foreign", "--splat-conventions") == 0
    assert _error(tmp_path, "a", expected) < 0.35


def test_frames_turn_exactly_and_the_sh_turn_with_them():
    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.core.surfels import eval_sh

    rng = np.random.default_rng(3)
    n = 50
    model = ply.PlyModel(position=rng.normal(size=(n, 3)).astype(np.float32),
                         log_scale=rng.normal(size=(n, 2)).astype(np.float32),
                         rotation=rng.normal(size=(n, 4)).astype(np.float32),
                         opacity_logit=rng.normal(size=n).astype(np.float32),
                         channels={"sh": rng.normal(size=(n, 48)).astype(np.float32),
                                   "shading_normal": rng.normal(size=(n, 3)).astype(np.float32)})
    cv = ply.to_frame(model, "opencv")
    back = ply.from_frame(cv, "opencv")
    for a, b in ((model.position, back.position), (model.rotation, back.rotation),
                 (model.channels["sh"], back.channels["sh"]),
                 (model.channels["shading_normal"], back.channels["shading_normal"])):
        np.testing.assert_array_equal(a, b)
    flip = np.array([1.0, -1.0, -1.0])
    np.testing.assert_allclose(cv.normals(), model.normals() * flip, atol=1e-6)
    d = rng.normal(size=(n, 3))
    before = eval_sh(mi.TensorXf(model.channels["sh"]), mi.Vector3f(*d.T.astype(np.float32)),
                     floor=None)
    after = eval_sh(mi.TensorXf(cv.channels["sh"]),
                    mi.Vector3f(*(d * flip).T.astype(np.float32)), floor=None)
    dr.eval(before, after)
    np.testing.assert_allclose(after.numpy(), before.numpy(), atol=1e-5)


def test_view_files_are_named_without_the_frames_image_extension():
    """nerfstudio's file_path carries the image's extension, NeRF-synthetic's does not: the
    render's files are NAME.exr either way; equal names from two folders are numbered."""
    from mi_shadowgs.stages.render import view_stems

    assert view_stems(["train/r_000.png", "./test/r_1", "a/b.JPG", "c/d.tar", ""]) == [
        "r_000", "r_1", "b", "d.tar", "view_004"]
    assert view_stems(["train/r_0.png", "test/r_0.png"]) == ["000_r_0", "001_r_0"]
