"""``python -m validation.refit_lights`` keeps its stage-4 fit as a unit
(``validation.units``): a killed call, run again, continues the fit from its checkpoint; the
same --out with other settings exits 2 naming the setting; --out inside the run it reads is
refused."""

from __future__ import annotations

import json
import math

import pytest
from conftest import untouched


def test_a_killed_refit_continues_from_its_checkpoint(tiny_run, tiny_presets, tmp_path, capsys,
                                                      monkeypatch, someone_elses_folder):
    from mi_shadowgs.stages.evaluation import evaluate
    from mi_shadowgs.stages.material import runner
    from validation import refit_lights

    run, data, out = tiny_run / "run", tiny_run / "data", tmp_path / "refit"
    argv = ["--run", str(run), "--data", str(data), "--out", str(out), "--quiet"]
    fits = []
    decompose, score = runner.decompose, evaluate.evaluate_decomposition

    def counted_fit(*args, **kwargs):
        fits.append(kwargs.get("state") is not None)
        return decompose(*args, **kwargs)

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # as a kill after the fit's last checkpoint

    monkeypatch.setattr(runner, "decompose", counted_fit)
    monkeypatch.setattr(evaluate, "evaluate_decomposition", killed)
    with pytest.raises(KeyboardInterrupt):
        refit_lights.main(argv)
    assert fits == [False] and not (out / "refit.json").exists()
    assert (out / "units" / "refit" / "checkpoint" / "checkpoint.npz").is_file()
    monkeypatch.setattr(evaluate, "evaluate_decomposition", score)
    assert refit_lights.main(argv) == 0
    assert fits == [False, True]  # continued, not fitted afresh
    res = json.loads((out / "refit.json").read_text())
    assert math.isfinite(res["after"]["shadow_iou"]) and res["before"]["shadow_iou"] is not None
    assert refit_lights.main(argv) == 0 and len(fits) == 2  # finished: only gathered
    capsys.readouterr()
    for extra, named in ((["--set", "iterations=3"], "overrides.iterations"),
                         (["--other-data"], "other_data")):
        with pytest.raises(SystemExit) as exc:
            refit_lights.main([*argv, *extra])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and named in err, err
    with pytest.raises(SystemExit) as exc:
        refit_lights.main(["--run", str(run), "--data", str(data), "--out",
                           str(run / "refit")])
    assert exc.value.code == 2 and "only reads" in capsys.readouterr().err
    assert not (run / "refit").exists()
    with pytest.raises(SystemExit) as exc:
        refit_lights.main(["--run", str(run), "--data", str(data), "--out",
                           str(someone_elses_folder)])
    assert exc.value.code == 2 and "did not write" in capsys.readouterr().err
    assert untouched(someone_elses_folder)


def test_a_refit_takes_the_settings_its_runs_segments_were_fitted_with(tmp_path):
    """A run whose segments came from chromaticity was fitted with stage 4's chromaticity_*
    settings in place of normal_steps and refine_score; its refit takes them too (a --set
    still wins), and a run of material-id segments keeps the preset's."""
    from mi_shadowgs.presets import material_config as get_config
    from validation.refit_lights import with_label_source

    preset = get_config("cpu-small")
    run = tmp_path / "run"
    (run / "segmentation").mkdir(parents=True)
    record = run / "segmentation" / "segmentation.json"
    record.write_text(json.dumps({"masks": "chromaticity"}))
    assert with_label_source(run, "cpu-small", {"iterations": 5}) == {
        "iterations": 5, "normal_steps": preset.chromaticity_normal_steps,
        "refine_score": preset.chromaticity_refine_score}
    assert with_label_source(run, "cpu-small", {"normal_steps": 7})["normal_steps"] == 7
    record.write_text(json.dumps({"masks": "material"}))
    assert with_label_source(run, "cpu-small", {"iterations": 5}) == {"iterations": 5}
    record.write_text(json.dumps({"masks": "auto"}))  # a record no run writes: named
    with pytest.raises(ValueError, match="segmentation.json: field 'masks'"):
        with_label_source(run, "cpu-small", {})
