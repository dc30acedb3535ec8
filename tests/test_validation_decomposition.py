"""``python -m validation.decomposition`` (stage 4-5 on the ground-truth stand-in) end to end
on a tiny generated dataset: it reloads the dataset's scene, fits and scores every column.

Each variant is a unit of its own (``validation.units``): a killed call continues the variant
in progress from stage 4's checkpoint and reuses the finished ones.

It refused every generated dataset from the time the scene loader refused derived parameters
(``object_to_world``, the lights' directions) until ``dataset_scene`` reloaded scenes for it.
"""

from __future__ import annotations

import json
import math

import pytest
from conftest import untouched


def test_the_validation_runs_on_a_generated_dataset(tmp_path, capsys, someone_elses_folder):
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
        with pytest.raises(SystemExit) as exc:  # a folder it did not write: refused, as it was
            decomposition.main([str(tmp_path / "data"), "--out", str(someone_elses_folder),
                                "--preset", TINY, "--no-ablations"])
        assert exc.value.code == 2 and "did not write" in capsys.readouterr().err
        assert untouched(someone_elses_folder)
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


def test_a_killed_call_reuses_finished_variants_and_continues_the_one_in_progress(
        tmp_path, capsys):
    """Killed while scoring the second variant (its fit done, its final checkpoint written):
    the rerun fits nothing it has, continues the second from its checkpoint, and ends with
    every variant; the same folder with other settings exits 2 naming the setting."""
    import tiny_cli
    from tiny_cli import TINY

    from mi_shadowgs import cli
    from mi_shadowgs.scenes import scene_path
    from mi_shadowgs.stages import evaluation
    from validation import decomposition

    data, out = tmp_path / "data", tmp_path / "out"
    argv = [str(data), "--out", str(out), "--preset", TINY]
    fits, scored = [], []
    decompose, evaluate = decomposition.material.decompose, evaluation.evaluate_decomposition

    def counted_fit(*args, **kwargs):
        fits.append(kwargs.get("state") is not None)
        return decompose(*args, **kwargs)

    def killed_on_the_second(*args, **kwargs):
        scored.append(1)
        if len(scored) == 2:
            raise KeyboardInterrupt  # as a kill after the fit's last checkpoint
        return evaluate(*args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        for table, config in tiny_cli.presets():
            mp.setitem(table, TINY, config)
        assert cli.main(["generate", str(scene_path("default")), "--out", str(data),
                         "--preset", TINY, "--no-progress"]) == 0
        mp.setattr(decomposition.material, "decompose", counted_fit)
        mp.setattr(evaluation, "evaluate_decomposition", killed_on_the_second)
        with pytest.raises(KeyboardInterrupt):
            decomposition.main(argv)
        assert fits == [False, False] and not (out / "summary.json").exists()
        first = json.loads((out / "units" / "full" / "result.json").read_text())
        fits.clear()
        assert decomposition.main(argv) == 0
        # the finished variant is reused; the second resumes; the third starts afresh
        assert fits == [True, False]
        summary = json.loads((out / "summary.json").read_text())
        assert list(summary["variants"]) == list(decomposition.VARIANTS)
        assert summary["variants"]["full"] == first
        assert [summary["variants"][v]["resumed"] for v in decomposition.VARIANTS] == \
            [False, True, False]
        assert (out / "no_visibility_albedo.png").is_file()
        capsys.readouterr()
        with pytest.raises(SystemExit) as exc:
            decomposition.main([*argv, "--iterations", "3"])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and "overrides.iterations" in err, err
