"""``mi-shadowgs render``: EXR/PNG outputs per view, AOVs, background, clear errors."""

from __future__ import annotations

import json
import os
import shutil
import signal

import numpy as np
import pytest

from mi_shadowgs import cli
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.render import render_surfels
from mi_shadowgs.io import ply
from mi_shadowgs.io.images import read_exr, read_png
from mi_shadowgs.io.provenance import MANIFEST_NAME
from tests.conftest import signal_on_call

W, H = 20, 16


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("render_cli")
    rng = np.random.default_rng(0)
    n = 60
    model = ply.PlyModel(
        position=rng.uniform(-0.5, 0.5, size=(n, 3)).astype(np.float32),
        log_scale=np.log(rng.uniform(0.08, 0.15, size=(n, 2))).astype(np.float32),
        rotation=rng.normal(size=(n, 4)).astype(np.float32),
        opacity_logit=np.full(n, 2.0, np.float32),
        channels={"sh": (0.3 * rng.normal(size=(n, 12))).astype(np.float32),
                  "albedo": rng.uniform(size=(n, 3)).astype(np.float32)})
    ply.write_ply_model(root / "model.ply", model)
    cams = [Camera.look_at(o, (0, 0, 0), width=W, height=H, fov_x=0.8)
            for o in ((0.3, 0.4, 2.5), (-2.0, 0.5, 1.0))]
    meta = {"camera_angle_x": 0.8, "w": W, "h": H, "world_up": "+y",
            "frames": [c.to_frame_json(f"./test/r_{i}") for i, c in enumerate(cams)]}
    # The cameras sit in a dataset folder of their own: no output may go into one.
    (root / "data").mkdir()
    (root / "data" / "transforms_test.json").write_text(json.dumps(meta))
    return root, cams


def test_render_writes_views_and_aovs(setup):
    root, cams = setup
    out = root / "out"
    rc = cli.main(["render", str(root / "model.ply"), "--cameras",
                   str(root / "data" / "transforms_test.json"), "--out", str(out),
                   "--aov", "depth", "--aov", "normal", "--aov", "albedo"])
    assert rc == 0
    surfels = ply.load_ply(root / "model.ply")
    for i, cam in enumerate(cams):
        ref = {k: np.asarray(v) for k, v in
               render_surfels(surfels, cam, aovs=["depth", "normal", "albedo"]).items()}
        rgba = read_exr(out / f"r_{i}.exr")
        assert rgba.shape == (H, W, 4)
        # EXR is float32: the values are stored exactly.
        np.testing.assert_array_equal(rgba[..., :3], ref["rgb"])
        np.testing.assert_array_equal(rgba[..., 3:], ref["alpha"])
        assert 0 < ref["alpha"].mean() < 1
        np.testing.assert_array_equal(read_exr(out / f"r_{i}_depth.exr"), ref["depth"])
        np.testing.assert_array_equal(read_exr(out / f"r_{i}_normal.exr"), ref["normal"])
        np.testing.assert_array_equal(read_exr(out / f"r_{i}_albedo.exr"), ref["albedo"])
        png = read_png(out / f"r_{i}.png")
        assert png.shape == (H, W, 4)
        np.testing.assert_array_equal(png[..., 3], np.round(ref["alpha"][..., 0] * 255))
        depth_png = read_png(out / f"r_{i}_depth.png")[..., 0]
        covered = ref["alpha"][..., 0] > 0
        # min-max normalised over covered pixels into [0.1, 1]; background black.
        assert depth_png[covered].max() == 255 and depth_png[covered].min() == 26
        assert (depth_png[~covered] == 0).all()


def test_background_composites(setup):
    root, cams = setup
    out = root / "out_bg"
    rc = cli.main(["render", str(root / "model.ply"), "--cameras",
                   str(root / "data" / "transforms_test.json"), "--out", str(out),
                   "--background", "1,0.5,0", "--color-channel", "albedo"])
    assert rc == 0
    surfels = ply.load_ply(root / "model.ply")
    ref = {k: np.asarray(v) for k, v in render_surfels(surfels, cams[0],
                                                       color_channel="albedo").items()}
    rgba = read_exr(out / "r_0.exr")
    expect = ref["rgb"] + np.array([1.0, 0.5, 0.0], np.float32) * (1 - ref["alpha"])
    # float32 rounding of rgb + bg * (1 - alpha) in a different order.
    np.testing.assert_allclose(rgba[..., :3], expect, atol=1e-6)
    assert read_png(out / "r_0.png").shape == (H, W, 3)


def test_sh_space_is_a_setting_of_the_render(setup, tmp_path):
    """`--sh-space srgb` renders display SH (another tool's PLY) as the linear SH they came
    from, and is part of the render's settings: the same folder is not reused for a render
    read the other way."""
    root, cams = setup
    model = ply.read_ply_model(root / "model.ply")
    model.channels["sh"] = ply.sh_to_srgb(model.channels["sh"])
    ply.write_ply_model(tmp_path / "display.ply", model)  # no record, as another tool's
    cameras = str(root / "data" / "transforms_test.json")

    def render(out, *extra):
        return cli.main(["render", str(tmp_path / "display.ply"), "--cameras", cameras,
                         "--out", str(tmp_path / out), *extra])

    assert render("srgb", "--sh-space", "srgb") == 0
    ref = render_surfels(ply.load_ply(tmp_path / "display.ply", "srgb"), cams[0])
    np.testing.assert_array_equal(read_exr(tmp_path / "srgb" / "r_0.exr")[..., :3],
                                  np.asarray(ref["rgb"]))
    manifest = json.loads((tmp_path / "srgb" / MANIFEST_NAME).read_text())
    assert manifest["settings"]["sh_space"] == "srgb"
    assert render("srgb") == 2  # read as linear: another render, not this folder's
    assert render("srgb", "--sh-space", "srgb") == 0  # the same: reused
    # A render made before the setting existed read every PLY as linear: reused as that.
    assert render("old") == 0
    manifest = json.loads((tmp_path / "old" / MANIFEST_NAME).read_text())
    del manifest["settings"]["sh_space"]
    (tmp_path / "old" / MANIFEST_NAME).write_text(json.dumps(manifest))
    assert render("old") == 0 and render("old", "--sh-space", "srgb") == 2


def test_errors_name_the_input(setup, tmp_path, capsys):
    root, _ = setup
    cams = str(root / "data" / "transforms_test.json")
    rc = cli.main(["render", str(tmp_path / "none.ply"), "--cameras", cams, "--out",
                   str(tmp_path / "o")])
    assert rc == 2 and "none.ply" in capsys.readouterr().err
    rc = cli.main(["render", str(root / "model.ply"), "--cameras", str(tmp_path / "t.json"),
                   "--out", str(tmp_path / "o")])
    assert rc == 2 and "t.json" in capsys.readouterr().err
    rc = cli.main(["render", str(root / "model.ply"), "--cameras", cams, "--out",
                   str(tmp_path / "o"), "--aov", "bogus"])
    assert rc == 2 and "unknown AOV 'bogus'" in capsys.readouterr().err
    rc = cli.main(["render", str(root / "model.ply"), "--cameras", cams, "--out",
                   str(tmp_path / "o"), "--background", "1,2"])
    assert rc == 2 and "--background" in capsys.readouterr().err
    # A colour channel of another width is named before any view (it failed at the first).
    wide = ply.read_ply_model(root / "model.ply")
    wide.channels["feature"] = np.zeros((wide.count, 16), np.float32)
    ply.write_ply_model(tmp_path / "wide.ply", wide)
    rc = cli.main(["render", str(tmp_path / "wide.ply"), "--cameras", cams, "--out",
                   str(tmp_path / "o"), "--color-channel", "feature"])
    err = capsys.readouterr().err
    assert rc == 2 and "--color-channel: colour channel 'feature' has 16 columns" in err, err
    assert not (tmp_path / "o").exists()  # nothing written on bad input


def _render(root, out, *extra, cameras=None):
    return cli.main(["render", str(root / "model.ply"), "--cameras",
                     str(cameras or root / "data" / "transforms_test.json"), "--out", str(out),
                     *extra])


def test_render_never_writes_into_a_dataset_or_over_its_input(setup, tmp_path, capsys):
    root, _ = setup
    data = tmp_path / "data"
    shutil.copytree(root / "data", data)
    (data / "test").mkdir()
    (data / "test" / "r_0.png").write_bytes(b"ground truth")
    for out in (data, data / "test", data / "new"):
        assert _render(root, out, cameras=data / "transforms_test.json") == 2
        assert "outputs never go into a dataset" in capsys.readouterr().err
    assert (data / "test" / "r_0.png").read_bytes() == b"ground truth"
    assert not (data / "new").exists()
    model_dir = tmp_path / "m"
    model_dir.mkdir()
    shutil.copy(root / "model.ply", model_dir / "model.ply")
    rc = cli.main(["render", str(model_dir / "model.ply"), "--cameras",
                   str(data / "transforms_test.json"), "--out", str(model_dir)])
    assert rc == 2 and "holds the input" in capsys.readouterr().err


def test_an_out_under_a_file_exits_2_naming_it(setup, tmp_path, capsys):
    root, _ = setup
    (tmp_path / "afile").write_text("mine")
    for out in (tmp_path / "afile", tmp_path / "afile" / "sub"):
        rc = cli.main(["render", str(root / "model.ply"), "--cameras",
                       str(root / "data" / "transforms_test.json"), "--out", str(out)])
        assert rc == 2
        assert f"error: {out}: " in capsys.readouterr().err
    assert (tmp_path / "afile").read_text() == "mine"


def test_renders_never_mix_and_overwrite_removes_only_renders(setup, tmp_path, capsys):
    root, cams = setup
    out = tmp_path / "out"
    assert _render(root, out, "--aov", "depth") == 0
    assert (out / "r_1_depth.exr").stat().st_mode & 0o777 == 0o666 & ~_umask()
    (out / "notes.txt").write_text("mine")
    one = tmp_path / "one.json"  # another camera set: one view under another name
    one.write_text(json.dumps({"camera_angle_x": 0.8, "w": W, "h": H, "world_up": "+y",
                               "frames": [cams[0].to_frame_json("./test/other")]}))
    assert _render(root, out, cameras=one) == 2
    err = capsys.readouterr().err
    assert "its input cameras differs" in err and "Pass --overwrite to start over" in err
    assert _render(root, out, "--overwrite", cameras=one) == 0
    assert sorted(p.name for p in out.iterdir() if p.name[0] != ".") == \
        ["notes.txt", "other.exr", "other.png"]


def test_a_failed_render_leaves_no_folder(setup, tmp_path, monkeypatch):
    root, _ = setup
    from mi_shadowgs.core import render as surfel_render

    def broken(*args, **kwargs):
        raise RuntimeError("out of memory")

    monkeypatch.setattr(surfel_render, "render_surfels", broken)
    with pytest.raises(RuntimeError):
        _render(root, tmp_path / "a" / "out")
    assert not (tmp_path / "a").exists()


def _counted(monkeypatch, module, name: str) -> list:
    """Count the calls of ``module.name`` (one entry each)."""
    real, calls = getattr(module, name), []
    monkeypatch.setattr(module, name, lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


def test_interrupted_render_continues_with_the_missing_views(setup, tmp_path, capsys,
                                                             monkeypatch):
    from mi_shadowgs.core import render as surfel_render
    from mi_shadowgs.io import images

    root, cams = setup
    many = tmp_path / "many.json"
    views = [Camera.look_at((2.5 * np.cos(a), 0.6, 2.5 * np.sin(a)), (0, 0, 0), width=W,
                            height=H, fov_x=0.8) for a in np.linspace(0, 5, 5)]
    many.write_text(json.dumps({"camera_angle_x": 0.8, "w": W, "h": H, "world_up": "+y",
                                "frames": [c.to_frame_json(f"./v_{i}")
                                           for i, c in enumerate(views)]}))
    assert _render(root, tmp_path / "whole", "--aov", "depth", cameras=many) == 0
    out = tmp_path / "out"
    with monkeypatch.context() as mp:
        # Two PNGs per view: the 5th call is view 2's own PNG, after its EXR. Views 0 and 1
        # are whole; view 2 is cut between its files.
        signal_on_call(mp, images, "write_png", 5, signal.SIGINT)
        assert _render(root, out, "--aov", "depth", cameras=many) == 130
    assert "interrupted by SIGINT; run the same command again to continue" in \
        capsys.readouterr().err
    assert (out / "v_2.exr").is_file() and not (out / "v_2.png").exists()
    # The first call ran on cuda_ad_rgb (simulated: its record edited; no GPU here): the
    # views it left stay, and one warning line says the folder mixes two backends.
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    manifest["made_with"] = [{"variant": "cuda_ad_rgb", "device": "NVIDIA H200"}]
    (out / MANIFEST_NAME).write_text(json.dumps(manifest))
    rendered = _counted(monkeypatch, surfel_render, "render_surfels")
    assert _render(root, out, "--aov", "depth", cameras=many) == 0
    assert len(rendered) == 3  # views 2, 3 and 4
    captured = capsys.readouterr()
    assert "the other 2 were there from an earlier call" in captured.out
    assert f"{out}: continued on llvm_ad_rgb from work that cuda_ad_rgb made" in captured.err
    _same_views(out, tmp_path / "whole")
    # Finished: the same command renders nothing; other settings are refused by name.
    assert _render(root, out, "--aov", "depth", cameras=many) == 0
    assert len(rendered) == 3
    assert "already holds these 5 view(s)" in capsys.readouterr().out
    assert _render(root, out, "--aov", "normal", cameras=many) == 2
    err = capsys.readouterr().err
    assert 'aovs: ["depth"] there, ["normal"] now' in err and "--overwrite" in err
    # An --overwrite cut short continues without the flag (with it, it would start over).
    with monkeypatch.context() as mp:
        signal_on_call(mp, images, "write_png", 3, signal.SIGINT)  # view 1's own PNG
        assert _render(root, out, "--aov", "depth", "--overwrite", cameras=many) == 130
    assert "interrupted by SIGINT; run it again without --overwrite to continue" in \
        capsys.readouterr().err
    assert len(rendered) == 5 and not (out / "v_1.png").exists()
    assert _render(root, out, "--aov", "depth", cameras=many) == 0
    assert len(rendered) == 9  # views 1 to 4 again
    _same_views(out, tmp_path / "whole")


def _same_views(got, whole) -> None:
    """``got`` holds the files of ``whole`` (5 views, 4 files each), byte for byte."""
    names = sorted(p.name for p in whole.iterdir())
    assert sorted(p.name for p in got.iterdir()) == names and len(names) == 21
    for name in names:
        if name != ".mi_shadowgs_manifest.json":
            assert (got / name).read_bytes() == (whole / name).read_bytes(), name


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
