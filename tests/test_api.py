"""The public face end to end on a tiny dataset: generate, run (the pipeline runner), load
the model, render it — what the README's example does."""

from __future__ import annotations

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
    from mi_shadowgs.stages.relight.render import recorded_visibility
    from mi_shadowgs.stages.visibility.shadow_maps import get_config

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
    ({"material_iterations": "10"}, ValueError, "'material_iterations' takes a number"),
    ({"segmnets": 3}, ValueError, r"unknown run setting\(s\) \['segmnets'\]"),
    ({"preview_envmaps": "sky.exr"}, TypeError, "preview_envmaps takes a list"),
    ({"preview_envmaps": ["missing.exr"]}, FileNotFoundError,
     "preview_envmaps: missing.exr: not found"),  # was left out without a word
])
def test_run_settings_are_checked_by_name_before_any_work(tmp_path, settings, error, match):
    with pytest.raises(error, match=match):
        msg.run(tmp_path / "no-data", tmp_path / "run", **settings)
    assert not (tmp_path / "run").exists()

