"""The public face end to end on a tiny dataset: generate, run (the pipeline runner), load
the model, render it — what the README's example does."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tiny_cli import TINY, presets

import mi_shadowgs.api as msg


@pytest.fixture
def tiny_presets(monkeypatch):
    for table, config in presets():
        monkeypatch.setitem(table, TINY, config)


def test_script_the_method(tiny_presets, tmp_path):
    data = msg.generate_dataset(msg.scene_path("default"), tmp_path / "data", preset=TINY)
    truth = msg.dataset_scene(data)  # the scene as rendered, for ray-traced ground truth
    assert len(truth.lights) == 2 and truth.inputs == {"scene": msg.scene_path("default")}
    summary = msg.run(data, tmp_path / "run", preset=TINY)
    assert summary["tables"][0]["rows"][0][0] == "full"
    assert (tmp_path / "run" / "report.html").is_file()
    model = msg.load_model(tmp_path / "run" / "material" / "full" / "model.ply")
    assert "albedo" in model.channels
    # The model records the maps and receivers it was fitted with, for readers of the bare
    # PLY.
    from mi_shadowgs.presets import visibility_config as get_config
    from mi_shadowgs.stages.relight.render import recorded_visibility

    assert recorded_visibility(tmp_path / "run" / "material" / "full" / "model.ply") == \
        get_config(TINY)
    camera = msg.load_dataset(data, "test").cameras[0]
    images = msg.render(model, camera, aovs=("depth",))
    alpha = images["alpha"].numpy()
    assert alpha.shape[:2] == (camera.height, camera.width) and alpha.max() > 0.5
    assert np.isfinite(images["depth"].numpy()).all()
    msg.export_ply(tmp_path / "copy.ply", model)
    assert msg.load_model(tmp_path / "copy.ply").count == model.count


@pytest.mark.parametrize("settings, error, match", [
    ({"ablations": "false"}, ValueError, "'ablations' takes True or False"),  # was True
    ({"material": {"iterations": "10"}}, ValueError, "'iterations' takes a number"),
    ({"segmnets": 3}, ValueError, r"unknown run setting\(s\) \['segmnets'\]"),
    ({"material": {"iterationz": 3}}, ValueError, r"unknown material setting"),
    ({"preview_envmaps": "sky.exr"}, TypeError, "preview_envmaps takes a list"),
    ({"preview_envmaps": ["missing.exr"]}, FileNotFoundError,
     "preview_envmaps: missing.exr: not found"),  # was left out without a word
])
def test_run_settings_are_checked_by_name_before_any_work(tmp_path, settings, error, match):
    with pytest.raises(error, match=match):
        msg.run(tmp_path / "no-data", tmp_path / "run", **settings)
    assert not (tmp_path / "run").exists()


def test_render_and_relight_name_an_argument_of_the_wrong_kind(tmp_path):
    """A string of AOVs was read letter by letter ("unknown AOV 'd'"); a list of cameras,
    a path, None bounds or a list of light tuples raised an AttributeError or TypeError
    from deep inside."""
    from mi_shadowgs.core.surfels import Surfels

    rng = np.random.default_rng(0)
    model = Surfels.from_numpy(rng.uniform(-0.5, 0.5, (30, 3)), np.full((30, 2), 0.1),
                               rng.normal(size=(30, 4)), np.full(30, 0.8),
                               {"sh": rng.uniform(0, 1, (30, 3)),
                                "albedo": rng.uniform(0, 1, (30, 3)),
                                "roughness": np.full((30, 1), 0.5),
                                "metallic": np.zeros((30, 1))})
    camera = msg.Camera.look_at(np.array([0.0, 1.0, 3.0]), np.zeros(3), fov_x=0.8, width=16,
                                height=12)
    with pytest.raises(TypeError, match=r"aovs must be a sequence of names, e.g. \('depth',\)"):
        msg.render(model, camera, aovs="depth")
    with pytest.raises(TypeError, match="'camera' must be one Camera"):
        msg.render(model, [camera])
    with pytest.raises(TypeError, match="export_ply: 'surfels' must be a surfel model"):
        msg.export_ply(tmp_path / "list.ply", [model])  # an AttributeError in the writer
    assert not (tmp_path / "list.ply").exists()
    msg.export_ply(tmp_path / "model.ply", model)
    by_path = msg.render(tmp_path / "model.ply", camera, aovs=("depth",))
    assert by_path["depth"].shape == (12, 16, 1)
    # The colour channel, as the CLI's --color-channel and the plugin's property take it.
    albedo = msg.render(model, camera, aovs=("albedo",), color_channel="albedo")
    np.testing.assert_array_equal(albedo["rgb"].numpy(), albedo["albedo"].numpy())
    with pytest.raises(ValueError, match="colour channel 'nope' is not in the model"):
        msg.render(model, camera, color_channel="nope")
    with pytest.raises(TypeError, match="'color_channel' must be a channel's name"):
        msg.render(model, camera, color_channel=["albedo"])
    lights = msg.directional_light_set([[0.3, 0.9, 0.2]], [3.0])
    with pytest.raises(TypeError, match="'cameras' must be a list of Camera"):
        msg.relight(model, camera, lights)
    with pytest.raises(TypeError, match="'lights' must be a LightSet"):
        msg.relight(model, [camera], [(30, 45, 3)])
    with pytest.raises(TypeError, match="'surfels' must be a surfel model"):
        msg.relight(None, [camera], lights)
    views, _ = msg.relight(str(tmp_path / "model.ply"), [camera], lights)  # bounds: default
    assert views[0]["rgb"].shape == (12, 16, 3) and views[0]["rgb"].max() > 0


def test_relight_of_a_ply_uses_the_shadow_maps_it_records(tmp_path):
    """Given stage 4's PLY by path, relight shades with the maps and receivers the model
    records (as the surfel_relight plugin and `mi-shadowgs relight` do), not cpu-small's."""
    from mi_shadowgs.core.surfels import Surfels
    from mi_shadowgs.io.ply import save_ply
    from mi_shadowgs.presets import visibility_config as get_config
    from mi_shadowgs.stages.material.outputs import model_metadata
    from mi_shadowgs.stages.relight.render import relight_views
    from mi_shadowgs.stages.visibility.shadow_maps import SceneBounds

    rng = np.random.default_rng(1)
    n = 400
    pos = np.concatenate([rng.uniform(-1, 1, (n, 3)) * [1, 0, 1],  # a floor
                          rng.uniform(-0.3, 0.3, (n, 3)) + [0, 0.5, 0]])  # a block above it
    model = Surfels.from_numpy(pos, np.full((2 * n, 2), 0.08),
                               np.tile([0.7071, 0.7071, 0, 0], (2 * n, 1)), np.full(2 * n, 0.9),
                               {"albedo": np.full((2 * n, 3), 0.6),
                                "roughness": np.full((2 * n, 1), 0.5),
                                "metallic": np.zeros((2 * n, 1))})
    fitted = dataclasses.replace(get_config("cpu-small"), resolution=48, receiver_band=0.0)
    save_ply(tmp_path / "model.ply", model, metadata=model_metadata(fitted, True))
    camera = msg.Camera.look_at(np.array([0.0, 2.5, 2.5]), np.zeros(3), fov_x=0.9, width=24,
                                height=24)
    lights = msg.directional_light_set([[0.5, 0.8, 0.2]], [3.0])
    views, _ = msg.relight(tmp_path / "model.ply", [camera], lights)
    loaded = msg.load_model(tmp_path / "model.ply")
    bounds = SceneBounds.from_points(np.asarray(loaded.to_numpy()["position"]), [camera])
    expect, _ = relight_views(msg.stages.relight.RelightModel(loaded, True, True),
                              [camera], lights, bounds, vis_config=fitted)
    np.testing.assert_array_equal(views[0]["rgb"], expect[0]["rgb"])
    preset, _ = msg.relight(loaded, [camera], lights)  # a Surfels: cpu-small's maps
    assert np.abs(preset[0]["rgb"] - expect[0]["rgb"]).max() > 1e-3
