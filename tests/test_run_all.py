"""``make validate`` (validation.run_all): the table's --scene/--lights subset reaches the
pipeline validation and runs alone, a second call resumes in place instead of starting over,
and a folder that is not ours is refused. The runs themselves are stood in for (hours)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from validation import pipeline as vpipe
from validation import run_all


def _fake_row(name: str, lights: str) -> dict:
    full = {k: 0.5 for k in vpipe.TABLE_KEYS}
    return {"scene": name, "lights": lights, "wall_s": 60.0, "segments": 3,
            "geometry": {"psnr": 30.0, "normal_error_median_deg": 2.0, "mask_iou": 0.99},
            "segmentation": {"ari": 0.9, "miou": 0.8}, "variants": {"full": full}}


@pytest.fixture
def fake_runs(monkeypatch):
    calls = []

    def run_scene(name, mesh, out, lights="tuned", ablations=True, envmaps=vpipe.ENVMAPS,
                  preset="cpu-small", seed=0):
        call = (name, lights) if preset == "cpu-small" else (name, lights, preset)
        calls.append(call + ((seed,) if seed else ()))
        folder = Path(out) / vpipe.row_name(name, lights, seed)
        folder.mkdir(parents=True, exist_ok=True)
        row = {**_fake_row(name, lights), "preset": preset, "seed": seed}
        (folder / "row.json").write_text(json.dumps(row))
        return row

    monkeypatch.setattr(vpipe, "run_scene", run_scene)
    monkeypatch.setattr(vpipe, "available_scenes",
                        lambda: {"default": None, "bunny": Path("bunny.ply")})
    return calls


def test_a_scene_and_light_subset_runs_alone(fake_runs, tmp_path):
    out = tmp_path / "validate"
    assert run_all.main(["--out", str(out), "--only", "pipeline", "--scene", "bunny",
                         "--lights", "low"]) == 0
    assert fake_runs == [("bunny", "low")]
    md = (out / "pipeline" / "pipeline.md").read_text()
    assert "| bunny | low |" in md and "| default |" not in md
    info = json.loads((out / "run.json").read_text())
    assert info["failed"] == [] and "--scene bunny --lights low" in info["command"]
    # Without a subset, every scene under both pairs: the pairs reach the pipeline.
    fake_runs.clear()
    assert run_all.main(["--out", str(out), "--only", "pipeline"]) == 0
    assert sorted(fake_runs) == sorted((s, p) for s in ("default", "bunny")
                                       for p in vpipe.LIGHT_PAIRS)


def test_a_second_call_resumes_in_place(fake_runs, tmp_path):
    out = tmp_path / "validate"
    assert run_all.main(["--out", str(out), "--only", "pipeline", "--scene", "default",
                         "--lights", "tuned"]) == 0
    marker = out / "pipeline" / "default-tuned" / "row.json"
    before = marker.stat().st_mtime_ns
    # a second subset adds its rows beside the first; the first folder is kept, not redone
    assert run_all.main(["--out", str(out), "--only", "pipeline", "--scene", "bunny",
                         "--lights", "tuned"]) == 0
    assert marker.stat().st_mtime_ns == before
    md = (out / "pipeline" / "pipeline.md").read_text()
    assert "| default | tuned |" in md and "| bunny | tuned |" in md


def test_a_folder_that_is_not_ours_is_refused(fake_runs, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    with pytest.raises(SystemExit) as e:
        run_all.main(["--out", str(out), "--only", "pipeline"])
    assert e.value.code == 2 and "notes.txt" in capsys.readouterr().err
    assert fake_runs == [] and sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_report_pages_follow_the_pipeline():
    names = list(run_all.VALIDATIONS)
    assert names.index("pipeline") < names.index("report_pages")


def test_one_preset_per_table_folder(fake_runs, tmp_path, capsys):
    # A cpu-medium table in a folder holding a cpu-small row would mix the two presets in
    # one table (and the row's dataset would be reused at the wrong size): refused, by name.
    out = tmp_path / "table"
    assert vpipe.main(["--out", str(out), "--scene", "default", "--lights", "tuned"]) == 0
    assert fake_runs == [("default", "tuned")]
    assert "; cpu-small;" in (out / "pipeline.md").read_text()
    fake_runs.clear()
    with pytest.raises(SystemExit) as e:
        vpipe.main(["--out", str(out), "--scene", "bunny", "--lights", "tuned",
                    "--preset", "cpu-medium"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "default-tuned" in err and "row.json" in err
    assert "'cpu-small'" in err and "'cpu-medium'" in err
    assert fake_runs == []
    # In a folder of its own the preset reaches every row and the table names it.
    other = tmp_path / "medium"
    assert vpipe.main(["--out", str(other), "--scene", "bunny", "--lights", "low",
                       "--preset", "cpu-medium"]) == 0
    assert fake_runs == [("bunny", "low", "cpu-medium")]
    assert "; cpu-medium;" in (other / "pipeline.md").read_text()
    # gpu-large (512^2, for a GPU) is a table preset too.
    fake_runs.clear()
    assert vpipe.main(["--out", str(tmp_path / "large"), "--scene", "bunny", "--lights",
                       "tuned", "--preset", "gpu-large"]) == 0
    assert fake_runs == [("bunny", "tuned", "gpu-large")]


def test_a_dataset_of_another_preset_is_not_reused(tmp_path):
    # A half-made row (its dataset written, no row.json) of another preset: refused before
    # its 128^2 images could feed a 256^2 run.
    folder = tmp_path / "default-tuned"
    (folder / "data").mkdir(parents=True)
    (folder / "data" / "dataset.json").write_text(json.dumps({"preset": "cpu-small"}))
    with pytest.raises(vpipe.PresetMismatch, match="dataset.json: made at preset 'cpu-small'"):
        vpipe.make_dataset("default", None, folder, preset="cpu-medium")
    with pytest.raises(vpipe.PresetMismatch, match="dataset.json"):
        vpipe.check_preset(tmp_path, "cpu-medium")
    # The same preset: kept only with this row's fingerprint (this dataset.json has none).
    with pytest.raises(vpipe.DatasetMismatch, match=r"data: holds a dataset made from other"):
        vpipe.make_dataset("default", None, folder)


def test_seeds_run_each_row_again_beside_seed_0(fake_runs, tmp_path):
    # --seed 0 --seed 2: every row at both seeds, seed 2 in a folder of its own; the table
    # names each seed's row and adds the spread over seeds.
    out = tmp_path / "table"
    assert vpipe.main(["--out", str(out), "--scene", "default", "--lights", "tuned",
                       "--seed", "2", "--seed", "0"]) == 0
    assert fake_runs == [("default", "tuned"), ("default", "tuned", 2)]
    assert (out / "default-tuned-seed2" / "row.json").is_file()
    md = (out / "pipeline.md").read_text()
    assert "| default | tuned, seed 2 |" in md and "| default | tuned |" in md
    assert "Spread over seeds" in md and "| default | tuned | 0,2 |" in md
    with pytest.raises(SystemExit) as e:
        vpipe.main(["--out", str(out), "--seed", "-1"])
    assert e.value.code == 2


def test_seed_spread_weights_each_row_once():
    # hotdog-low at seeds 0 and 1 (shadow IoU 0.4, 0.6), default-tuned at 0 and 1 (0.9, 0.8)
    # and bunny-tuned at seed 0 alone (0.7): each row's mean over its seeds, the table's mean
    # at the one seed every row has, and the mean of the rows' means.
    def row(scene, lights, seed, iou):
        full = {**dict.fromkeys(vpipe.TABLE_KEYS, 0.5), "shadow_iou": iou}
        return {"scene": scene, "lights": lights, "seed": seed, "variants": {"full": full}}

    lines = vpipe.seed_spread([row("hotdog", "low", 0, 0.4), row("hotdog", "low", 1, 0.6),
                               row("default", "tuned", 0, 0.9), row("default", "tuned", 1, 0.8),
                               row("bunny", "tuned", 0, 0.7)])
    col = 4 + vpipe.SPREAD_KEYS.index("shadow_iou")
    cells = {line.split("|")[1].strip(): line.split("|")[col].strip()
             for line in lines if line.startswith("| ")}
    assert cells["hotdog"] == "0.5 [0.4, 0.6]" and cells["default"] == "0.85 [0.8, 0.9]"
    assert cells["bunny"] == "0.7 [0.7, 0.7]"
    assert cells["**mean all, seed 0** (3)"] == "0.6667"
    assert "**mean all, seed 1** (3)" not in cells  # bunny has no seed 1
    assert cells["**mean all of the seed means** (3)"] == "0.6833"
    assert vpipe.seed_spread([row("hotdog", "low", 0, 0.4)]) == []


def test_every_seed_of_a_row_runs_on_its_seed_0_dataset(monkeypatch, tmp_path):
    # The seeds measure the method's chance alone: a seed's row must not make (or read) a
    # dataset of its own.
    made = []

    def make_dataset(name, mesh, folder, *args, **kwargs):
        made.append(folder)
        raise RuntimeError("stop after the dataset")

    monkeypatch.setattr(vpipe, "make_dataset", make_dataset)
    with pytest.raises(RuntimeError, match="stop after"):
        vpipe.run_scene("default", None, tmp_path, "low", seed=3)
    assert made == [tmp_path / "default-low"]


def test_visibility_runs_scores_the_table_models_at_their_rows_preset(tmp_path, monkeypatch):
    # The stage-1 item was measured with the paper's maps at first; the
    # table's models are scored here with the maps their runs use: the rows' preset.
    from validation import visibility

    out = tmp_path / "validate"
    assert run_all._visibility_runs(out / "visibility_runs", False)["markdown"].startswith(
        "## visibility_runs")  # no table yet: a note, no work
    calls = []
    monkeypatch.setattr(visibility, "run", lambda *a, **k: calls.append((a, k)) or {})
    for row, preset in (("default-tuned", "cpu-medium"), ("bunny-low", "cpu-medium")):
        model = out / "pipeline" / row / "run" / "geometry" / "model.ply"
        model.parent.mkdir(parents=True)
        model.write_bytes(b"")
        (out / "pipeline" / row / "row.json").write_text(json.dumps({"preset": preset}))
    run_all._visibility_runs(out / "visibility_runs", False)
    (args, kwargs), = calls
    assert kwargs["preset"] == "cpu-medium" and kwargs["models_only"] and kwargs["factors"]
    assert [m.parts[-4] for m in kwargs["model"]] == ["bunny-low", "default-tuned"]
    assert kwargs["data"] == [out / "pipeline" / r / "data" for r in ("bunny-low",
                                                                     "default-tuned")]
    run_all._visibility(out / "visibility", False)  # Table 2: the paper's maps, no preset
    assert "preset" not in calls[-1][1] and not calls[-1][1].get("factors")
    names = list(run_all.VALIDATIONS)
    assert names.index("pipeline") < names.index("visibility_runs")


def test_a_study_that_exits_2_does_not_stop_the_others(fake_runs, tmp_path, monkeypatch,
                                                      capsys):
    """A study refusing its folder (``validation.fail``: exit 2, e.g. a unit made with other
    settings) is reported as failed; the validations after it still run."""
    from validation import fail

    def refuses(out_dir, quick, opts):
        fail(f"{out_dir}/units/x: other settings (size: 128 there, 256 now)")

    monkeypatch.setitem(run_all.VALIDATIONS, "lowpass_drift", refuses)
    ran = []
    monkeypatch.setitem(run_all.VALIDATIONS, "report_pages",
                        lambda out_dir, quick, opts: ran.append(1) or {"markdown": "## ok"})
    out = tmp_path / "validate"
    assert run_all.main(["--out", str(out), "--only", "lowpass_drift", "--only",
                         "report_pages"]) == 1
    assert ran == [1]
    assert json.loads((out / "run.json").read_text())["failed"] == ["lowpass_drift"]
    err = capsys.readouterr().err
    assert "size: 128 there, 256 now" in err and "lowpass_drift FAILED: exit 2" in err


def test_overwrite_reaches_the_studies_with_units(fake_runs, tmp_path, monkeypatch):
    """``make validate VALIDATE_ARGS=--overwrite``: the studies that keep units make them
    again; without it they are asked to reuse them (and refuse units made otherwise)."""
    from validation import lowpass_drift, metric_floor, visibility

    seen = []

    def study(name):
        def run(*args, **kwargs):
            seen.append((name, kwargs["overwrite"]))
            return {"markdown": f"## {name}"}
        return run

    monkeypatch.setattr(visibility, "run", study("visibility"))
    monkeypatch.setattr(metric_floor, "run", study("metric_floor"))
    monkeypatch.setattr(lowpass_drift, "run", study("lowpass_drift"))
    out = tmp_path / "validate"
    assert run_all.main(["--out", str(out), "--only", "pipeline", "--scene", "default",
                         "--lights", "tuned"]) == 0
    model = out / "pipeline" / "default-tuned" / "run" / "geometry" / "model.ply"
    model.parent.mkdir(parents=True)
    model.write_bytes(b"")
    studies = ["--only", "visibility", "--only", "visibility_runs", "--only", "metric_floor",
               "--only", "lowpass_drift"]
    assert run_all.main(["--out", str(out), *studies]) == 0
    assert run_all.main(["--out", str(out), *studies, "--overwrite"]) == 0
    names = ["visibility", "visibility", "metric_floor", "lowpass_drift"]
    assert seen == [(n, False) for n in names] + [(n, True) for n in names]
