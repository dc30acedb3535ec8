"""The box-filtered ground truth (dataset.generate.box_filtered_ground_truth) and the metric
floor it gives (validation.metric_floor)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tiny_cli import TINY, presets

import mi_shadowgs.api as msg
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.dataset.generate import (
    box_filtered_ground_truth,
    camera_rays,
    trace_ground_truth,
)
from mi_shadowgs.dataset.scene import load_scene
from mi_shadowgs.scenes import scene_path
from validation import metric_floor


@pytest.fixture(scope="module")
def setup():
    return load_scene(scene_path("default"))


def test_camera_rays_pass_through_the_asked_point_of_each_pixel():
    cam = Camera.look_at((0.3, 2.0, 4.0), (0.0, 0.5, 0.0), fov_x=0.8, width=6, height=4)
    for offset in ((0.5, 0.5), (0.0, 0.0), (0.9, 0.2)):
        o, d, _ = camera_rays([cam], offset)
        pix = cam.pixel_grid() - 0.5 + np.asarray(offset)
        want = cam.unproject(pix, np.ones(len(pix))) - cam.origin
        np.testing.assert_allclose(d, want / np.linalg.norm(want, axis=1, keepdims=True),
                                   atol=1e-12)


def test_one_sample_is_the_point_truth_and_four_blend_only_at_edges(setup):
    cam = Camera.look_at((2.5, 2.5, 3.0), setup.object_center, fov_x=0.7, width=40, height=40)
    point = trace_ground_truth(setup, [cam])
    one = box_filtered_ground_truth(setup, [cam], samples=1)
    np.testing.assert_array_equal(one["coverage"], point["mask"].astype(np.float64))
    np.testing.assert_allclose(one["albedo"], point["albedo"], atol=0)
    np.testing.assert_allclose(one["irradiance"], point["irradiance"], atol=0)
    # Lit: the light's shadow ray unoccluded and n . l > 0 (validation.visibility's truth).
    dirs = np.array([lt.direction for lt in setup.lights])
    facing = np.einsum("nhwk,lk->nhwl", point["normal"].astype(np.float64), dirs) > 0
    np.testing.assert_array_equal(one["lit"], (point["visibility"] > 0.5) & facing)
    assert 0 < one["lit"].mean() < 1  # some of each, so the check above can fail
    # Facing: the horizon test alone, occluded or not.
    np.testing.assert_array_equal(one["facing"], facing & point["mask"][..., None])
    assert np.count_nonzero(one["facing"] > one["lit"]) > 10  # cast shadows: facing, unlit
    box = box_filtered_ground_truth(setup, [cam], samples=4)
    cov = box["coverage"]
    assert cov.min() >= 0 and cov.max() <= 1
    lit = box["lit"]  # a share of the points: partial at the shadows' edges
    assert lit.min() >= 0 and lit.max() <= 1 and np.count_nonzero((lit > 0) & (lit < 1)) > 10
    # Every lit point faces its light; the curved parts' edges face it in part.
    facing_share = box["facing"]
    assert np.all(facing_share >= lit) and facing_share.max() <= 1
    assert np.count_nonzero((facing_share > 0) & (facing_share < 1)) > 10
    # The object's silhouette against the background: pixels partly covered.
    assert np.count_nonzero((cov > 0) & (cov < 1)) > 10
    # Inside one material, away from every edge, the albedo is the point truth's: the
    # default scene's parts have constant albedo.
    mat = point["material"][0]
    same = np.ones_like(mat, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            same &= np.roll(np.roll(mat, dy, 0), dx, 1) == mat
    inner = same & (cov[0] == 1) & point["mask"][0].astype(bool)
    inner[[0, -1], :] = inner[:, [0, -1]] = False
    assert inner.sum() > 200
    np.testing.assert_allclose(box["albedo"][0][inner], point["albedo"][0][inner], atol=1e-6)
    # Where materials meet, the box filter blends them; the point truth cannot.
    edge = ~same & (cov[0] == 1)
    assert np.abs(box["albedo"][0][edge] - point["albedo"][0][edge]).max() > 0.05
    with pytest.raises(ValueError, match="samples"):
        box_filtered_ground_truth(setup, [cam], samples=0)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:
        for table, config in presets():
            mp.setitem(table, TINY, config)
        return msg.generate_dataset(msg.scene_path("default"),
                                    tmp_path_factory.mktemp("floor") / "data", preset=TINY)


def test_metric_floor_cli(tiny_data, tmp_path, capsys):
    out = tmp_path / "floor"
    assert metric_floor.main(["--data", str(tiny_data), "--out", str(out), "--sizes", "24",
                              "48", "--samples", "1", "--quiet"]) == 0
    rows = json.loads((out / "metric_floor.json").read_text())["rows"]
    assert [r["size"] for r in rows] == [24, 48]
    # One sample per pixel is the point truth itself: a perfect score.
    assert all(r["shadow_iou"] == 1.0 and r["albedo_psnr"] > 100 for r in rows)
    assert metric_floor.main(["--data", str(tiny_data), "--out", str(out), "--samples", "3",
                              "--quiet", "--overwrite"]) == 0
    (row,) = json.loads((out / "metric_floor.json").read_text())["rows"]
    assert row["size"] == 24 and row["partly_covered_share"] > 0
    assert row["shadow_iou"] < 1.0 and row["albedo_psnr"] < 100
    # The method on exact geometry beside it: a denser sampling changes it, the floor not.
    for surfels in ("1500", "6000"):
        assert metric_floor.main(["--data", str(tiny_data), "--out", str(out), "--samples",
                                  "3", "--exact", "cpu-small", "--exact-surfels", surfels,
                                  "--quiet", "--overwrite"]) == 0
        (ex,) = json.loads((out / "metric_floor.json").read_text())["rows"]
        assert ex["shadow_iou"] == row["shadow_iou"] and ex["exact_surfels_128"] == int(surfels)
        assert 0.2 < ex["exact_geometry_iou"] <= 1.0 and ex["exact_preset"] == "cpu-small"
        assert f"{ex['exact_geometry_iou']:.3f} |" in capsys.readouterr().out
        if surfels == "1500":
            sparse = ex["exact_geometry_iou"]
    assert ex["exact_geometry_iou"] != sparse
    # Exits 2 naming what is wrong; never replaces a folder it did not write.
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    for argv, what in ((["--data", str(tmp_path), "--out", str(tmp_path / "o")], "dataset"),
                       (["--data", str(tiny_data), "--out", str(other)], "did not write"),
                       (["--data", str(tiny_data), "--out", str(out), "--samples", "0"],
                        "--samples"),
                       (["--data", str(tiny_data), "--out", str(out), "--exact", "nope"],
                        "--exact")):
        with pytest.raises(SystemExit) as e:
            metric_floor.main(argv)
        assert e.value.code == 2 and what in capsys.readouterr().err
    assert (other / "keep.txt").read_text() == "x"


def test_make_validate_scores_the_pipelines_datasets(tiny_data, tmp_path):
    import shutil

    from validation import run_all

    assert "metric_floor" in run_all.VALIDATIONS
    shutil.copytree(tiny_data, tmp_path / "pipeline" / "default-tuned" / "data")
    summary = run_all._metric_floor(tmp_path / "metric_floor", True, {})
    (row,) = summary["rows"]
    assert row["dataset"] == "default-tuned" and row["size"] == 24
    assert row["exact_preset"] == "cpu-small" and 0.0 <= row["exact_geometry_iou"] <= 1.0
    assert "| default-tuned | 24 |" in summary["markdown"]
    assert "method on exact geometry" in summary["markdown"]
    assert (tmp_path / "metric_floor" / "metric_floor.json").is_file()
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("x")
    with pytest.raises(SystemExit) as e:
        metric_floor.run(foreign, [tiny_data])
    assert e.value.code == 2 and [p.name for p in foreign.iterdir()] == ["keep.txt"]
