"""``python -m validation.decomposition`` (stage 4-5 on the ground-truth stand-in) end to end
on a tiny generated dataset: it reloads the dataset's scene, fits and scores every column.

It refused every generated dataset from the time the scene loader refused derived parameters
(``object_to_world``, the lights' directions) until ``dataset_scene`` reloaded scenes for it.
"""

from __future__ import annotations

import json
import math

import pytest


def test_the_validation_runs_on_a_generated_dataset(tmp_path, capsys):
    import tiny_cli
    from tiny_cli import TINY

    from mi_shadowgs import cli
    from mi_shadowgs.scenes import scene_path
    from validation import decomposition

    out = tmp_path / "decomposition"
    with pytest.MonkeyPatch.context() as mp:
        for table, config in tiny_cli.presets():
            mp.setitem(table, TINY, config)
        assert cli.main(["generate", str(scene_path("default")), "--out",
                         str(tmp_path / "data"), "--preset", TINY, "--no-progress"]) == 0
        assert decomposition.main([str(tmp_path / "data"), "--out", str(out), "--preset", TINY,
                                   "--no-ablations"]) == 0
        _bad_input_exits_2(decomposition, tmp_path, capsys, TINY)
    summary = json.loads((out / "summary.json").read_text())
    full = summary["variants"]["full"]
    for key in ("albedo_psnr", "light_cosine", "shadow_iou", "relight_psnr"):
        assert math.isfinite(full[key]), (key, full[key])
    assert 0.0 <= full["shadow_iou"] <= 1.0 and -1.0 <= full["light_cosine"] <= 1.0
    assert {"full_albedo.png", "full_irradiance.png", "full_light_map.png"} <= {
        p.name for p in out.iterdir()}


def _bad_input_exits_2(decomposition, tmp_path, capsys, preset):
    """A folder that is not a generated dataset (its images and cameras alone), one with an
    image missing, an unknown preset: one line naming the file or preset, exit 2, nothing
    written."""
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(tmp_path / "data", bare)
    (bare / "dataset.json").unlink()
    broken = tmp_path / "broken"
    shutil.copytree(tmp_path / "data", broken)
    for image in (broken / "test").glob("r_001.*"):  # the PNG and the EXR of the view
        image.unlink()
    for data, opt, named in ((bare, preset, "dataset.json"), (broken, preset, "r_001"),
                             (tmp_path / "data", "cpu-tiny", "'cpu-tiny'")):
        capsys.readouterr()
        with pytest.raises(SystemExit) as exc:
            decomposition.main([str(data), "--out", str(tmp_path / "none"), "--preset", opt])
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(err) == 1 and named in err[0], err
        assert not (tmp_path / "none").exists()
