"""Validation studies never write into someone else's folder (``validation.claim_out``): a
study takes --out when it is new or empty and marks it; a rerun finds its mark (or, for a
folder from before the mark, one of its own files) and goes on; any other folder is refused
with exit 2 before any work, and left as it was."""

from __future__ import annotations

import importlib
import json

import pytest
from conftest import untouched

import validation
from validation import STUDY_MARK, claim_out

# module -> its arguments besides --out (enough to get past argument parsing)
STUDIES = {
    "light_sweep": [],
    "view_count": ["--data", "nowhere"],
    "speed_error": [],
    "photos": [],
    "import_sfm": [],
    "geometry": ["--data", "nowhere"],
    "segmentation": [],
    "asset": ["--run", "nowhere", "--data", "nowhere"],
    "lowpass_drift": [],
    "report_page": ["nowhere"],
    "pipeline": [],
}


@pytest.mark.parametrize("name", sorted(STUDIES))
def test_a_study_refuses_a_folder_it_did_not_write(name, someone_elses_folder, capsys):
    module = importlib.import_module(f"validation.{name}")
    with pytest.raises(SystemExit) as e:
        module.main([*STUDIES[name], "--out", str(someone_elses_folder)])
    assert e.value.code == 2
    assert "did not write" in capsys.readouterr().err
    assert untouched(someone_elses_folder)


def test_claim_marks_a_new_folder_and_takes_only_its_own(tmp_path, capsys):
    out = claim_out(tmp_path / "sweep", "validation.light_sweep")
    assert json.loads((out / STUDY_MARK).read_text()) == {"study": "validation.light_sweep"}
    (out / "light_sweep.json").write_text("[]")
    assert claim_out(out, "validation.light_sweep") == out  # a rerun resumes in place
    with pytest.raises(SystemExit) as e:  # another study's folder
        claim_out(out, "validation.view_count")
    assert e.value.code == 2 and "holds the output of validation.light_sweep" in \
        capsys.readouterr().err
    older = tmp_path / "older"  # written before the mark: known by the study's own file
    older.mkdir()
    (older / "view_count.json").write_text("[]")
    claim_out(older, "validation.view_count", ("view_count.json",))
    assert (older / STUDY_MARK).is_file()
    empty = tmp_path / "empty"
    empty.mkdir()
    claim_out(empty, "validation.geometry")
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(SystemExit):
        claim_out(a_file, "validation.geometry")
    assert validation.STUDY_MARK.startswith(".")  # hidden beside the study's own files


def test_a_unit_is_reused_only_with_its_own_provenance(tmp_path, capsys):
    """``validation.units.run_unit``: a finished unit is reused (its work not run again),
    one cut short is run again, one of other settings exits 2 naming the setting, and
    ``overwrite`` runs it again; files the unit's work wrote are its own."""
    from mi_shadowgs.io.provenance import Provenance
    from validation.units import run_unit, settings_of

    calls = []

    def work(unit, fail_now=False):
        calls.append(unit.reused)
        unit.path("figure.txt").write_text("x")
        if fail_now:
            raise KeyboardInterrupt
        return {"value": len(calls)}

    same = Provenance(settings=settings_of(size=128, views=(0, 1)))
    with pytest.raises(KeyboardInterrupt):
        run_unit(tmp_path, "a", "validation.t", same, lambda u: work(u, True))
    assert run_unit(tmp_path, "a", "validation.t", same, work) == {"value": 2}
    assert calls == [False, True]  # cut short: run again, in its own folder
    assert run_unit(tmp_path, "a", "validation.t", same, work) == {"value": 2}
    assert len(calls) == 2
    with pytest.raises(SystemExit) as e:
        run_unit(tmp_path, "a", "validation.t", Provenance(settings=settings_of(size=256)),
                 work)
    assert e.value.code == 2 and "size: 128 there, 256 now" in capsys.readouterr().err
    assert run_unit(tmp_path, "a", "validation.t", same, work, overwrite=True) == {"value": 3}


def test_a_study_never_writes_into_a_dataset_or_over_what_it_reads(tmp_path, capsys):
    """``claim_out``: an --out inside a dataset folder, or one that holds a file the study
    reads, exits 2 before anything is written there."""
    data = tmp_path / "data"
    data.mkdir()
    (data / "dataset.json").write_text("{}")
    with pytest.raises(SystemExit) as e:
        claim_out(data / "study", "validation.metric_floor")
    assert e.value.code == 2 and "dataset folder" in capsys.readouterr().err
    assert not (data / "study").exists()
    model = tmp_path / "runs" / "model.ply"
    model.parent.mkdir()
    model.write_text("ply")
    with pytest.raises(SystemExit) as e:
        claim_out(tmp_path / "runs", "validation.visibility", inputs=[model])
    assert e.value.code == 2 and "holds the input" in capsys.readouterr().err
    assert not (tmp_path / "runs" / STUDY_MARK).exists()
