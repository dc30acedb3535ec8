"""``validation.lab``: the truth's lamp mapped into an import's frame, the acceptance table,
the gains' errors, the control's light against the lab's lamp, and the study's steps (each
case's control shared, the lab run with lamps, bad options and other settings refused)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mi_shadowgs.dataset.world_frame import Similarity
from validation import lab
from validation.photos import mapped_lights


def _similarity() -> Similarity:
    a, b = math.radians(130.0), math.radians(3.0)
    ry = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    return Similarity(scale=0.37, rotation=rx @ ry, translation=np.array([0.4, -1.2, 2.0]))


def _lamp_lights(centre, direction, distance) -> dict:
    position = centre + distance * direction
    return {"training": {"lights": [{
        "name": "lamp", "type": "lamp", "direction": direction.tolist(),
        "irradiance": [3.0, 3.0, 3.0], "position": position.tolist(), "distance": distance,
        "radius": 0.15, "intensity": [3.0 * distance**2] * 3}],
        "light_map": {"radiance": [[1.0] * 3]}, "room": {"radiance": [0.03] * 3}},
        "relightings": [{"name": "sun", "type": "directional", "lights": [
            {"direction": [0.0, 1.0, 0.0], "irradiance": [1.0] * 3}]},
            {"name": "lamp_moved", "type": "point", "lights": [
                {"position": (centre + [3.0, 4.0, 0.0]).tolist(), "intensity": [75.0] * 3,
                 "radius": 0.0, "direction": [0.6, 0.8, 0.0]}]},
            {"name": "env", "type": "envmap", "path": "envmaps/x.exr"}]}


def test_a_lamp_is_moved_by_the_whole_similarity():
    """p' = s R p + t against the homogeneous matrix in float64; the distance and radius
    scale by s, the intensity by s^2, the irradiance at the centre stays; the lamp's
    position error as a share of its distance is the same in both frames."""
    from mi_shadowgs.stages.evaluation.metrics import lamp_errors

    sim = _similarity()
    rng = np.random.default_rng(3)
    centre = np.array([0.1, 1.0, -0.2])
    direction = np.array([0.5, 0.7, 0.3]) / np.linalg.norm([0.5, 0.7, 0.3])
    lights = _lamp_lights(centre, direction, 6.0)
    out = mapped_lights(lights, sim)
    lamp, true = out["training"]["lights"][0], lights["training"]["lights"][0]
    m = np.zeros((4, 4))
    m[:3, :3] = sim.scale * sim.rotation
    m[:3, 3], m[3, 3] = sim.translation, 1.0
    ref = (m @ np.append(np.asarray(true["position"], np.float64), 1.0))[:3]
    assert np.allclose(lamp["position"], ref, rtol=0, atol=1e-12)
    assert np.allclose(lamp["direction"], sim.rotation @ direction, atol=1e-12)
    assert math.isclose(lamp["distance"], 6.0 * 0.37, rel_tol=1e-12)
    assert math.isclose(lamp["radius"], 0.15 * 0.37, rel_tol=1e-12)
    assert np.allclose(lamp["intensity"], np.array(true["intensity"]) * 0.37**2, rtol=1e-12)
    assert lamp["irradiance"] == [3.0, 3.0, 3.0]
    # the lamp still sits at its distance along its direction from the mapped centre
    mapped_centre = (m @ np.append(centre, 1.0))[:3]
    assert np.allclose(np.asarray(lamp["position"]) - lamp["distance"] *
                       np.asarray(lamp["direction"]), mapped_centre, atol=1e-12)
    assert "light_map" not in out["training"] and out["training"]["room"]["radiance"]
    # the new point lamp of the relit test set moves alike; env maps are left out
    assert [e["name"] for e in out["relightings"]] == ["sun", "lamp_moved"]
    moved = out["relightings"][1]["lights"][0]
    src = lights["relightings"][1]["lights"][0]
    assert np.allclose(moved["position"], (m @ np.append(src["position"], 1.0))[:3],
                       atol=1e-12)
    assert np.allclose(moved["intensity"], np.array(src["intensity"]) * 0.37**2, rtol=1e-12)
    assert moved["radius"] == 0.0
    assert lights["training"]["lights"][0]["position"] == true["position"]  # input untouched
    fitted = np.asarray(true["position"]) + rng.normal(0, 0.2, 3)
    here = lamp_errors([direction], [1.0], [fitted], lights["training"]["lights"])
    there = lamp_errors([sim.rotation @ direction], [1.0], [sim.points(fitted[None])[0]],
                        out["training"]["lights"])
    assert math.isclose(here["lamp_position_error"][0], there["lamp_position_error"][0],
                        rel_tol=1e-9)
    # a rotation alone (as validation.photos passes for its own frame) moves no lamp
    same = mapped_lights(lights, np.eye(3))["training"]["lights"][0]
    assert np.allclose(same["position"], true["position"], atol=1e-15)


def _scores(**kw) -> dict:
    base = {"light_angular_errors_deg": [0.5], "strongest_light_share": 0.95,
            "fitted_lights": 1, "fitted_lamps": 1, "shadow_iou": 0.80, "albedo_psnr": 18.0,
            "relight_psnr": 20.0, "lamp_position_error": [0.03],
            "relighting": {"lamp_moved": {"psnr": 21.5, "ssim": 0.9}}}
    return {**base, **kw}


def _kind(scores, gain=0.01, error=None) -> dict:
    out = {"scores": scores, "registered": 48, "photos": 48,
           "gains": None if gain is None else {"global": {"max": gain, "mean": gain / 2}},
           "times": {"photoset_s": 400.0, "gt_s": 100.0, "import_s": 90.0, "run_s": 3000.0,
                     "stage1_s": 2000.0, "stage2_s": 300.0, "stage4_s": 700.0,
                     "score_s": 60.0}}
    return out if error is None else {**out, "error": error, "where": "x.py:1"}


def _case(lab_scores, lab_gain=0.01, error=None, control_lamps=0) -> dict:
    control = _kind(_scores(lamp_position_error=None, light_angular_errors_deg=[0.3],
                            shadow_iou=0.82, albedo_psnr=18.8, fitted_lamps=control_lamps,
                            relighting={}), gain=0.002)
    labk = _kind(lab_scores, lab_gain, error)
    rows = lab.acceptance(labk, control)
    return {"scene": "default", "distance": 6.0, "control": control, "lab": labk,
            "acceptance": rows, "passed": lab.passed(rows)}


def _record(cases) -> dict:
    return {"command": "python -m validation.lab --out X", "date": "2026-12-06",
            "commit": "abc", "settings": {"preset": "cpu-small", "photo_size": [640, 480],
                                          "views": 48, "max_size": 128, "sets": [],
                                          "seed": 0},
            "cases": cases}


def test_the_acceptance_table_marks_each_bound(tmp_path):
    ok = _case(_scores())
    marks = {r["figure"].split(" (")[0]: r["status"] for r in ok["acceptance"]}
    assert ok["passed"] is True and set(marks.values()) == {"pass", "info"}
    assert len([m for m in marks.values() if m == "pass"]) == 7
    cases = [
        (_scores(lamp_position_error=[0.06]), "lamp position error"),
        (_scores(lamp_position_error=[None]), "lamp position error"),  # fitted directional
        (_scores(light_angular_errors_deg=[2.5]), "light direction error"),
        (_scores(strongest_light_share=0.85), "strongest light's share of the irradiance"),
        (_scores(shadow_iou=0.76), "shadow IoU"),  # 0.06 below the control's 0.82
        (_scores(albedo_psnr=17.7), "albedo PSNR"),  # 1.1 dB below
    ]
    for scores, figure in cases:
        case = _case(scores)
        failed = [r["figure"].split(" (")[0] for r in case["acceptance"]
                  if r["status"] == "fail"]
        assert failed == [figure], (scores, failed)
        assert case["passed"] is False
    lamped = _case(_scores(), control_lamps=1)  # the directional capture fitted a lamp
    assert lamped["passed"] is False and [r["figure"] for r in lamped["acceptance"]
                                          if r["status"] == "fail"] == [
        "of them lamps (the control's must stay directional)"]
    above = _case(_scores(shadow_iou=0.9, albedo_psnr=25.0))  # better than the control
    assert above["passed"] is True
    assert _case(_scores(), lab_gain=0.04)["passed"] is False
    no_gains = _case(_scores(), lab_gain=None)
    assert no_gains["passed"] is None  # not wholly measured
    assert [r["status"] for r in no_gains["acceptance"] if "gain" in r["figure"]] == ["n/a"]
    assert _case(_scores(lamp_position_error=[None]))["acceptance"][0]["lab"] == \
        "fitted as directional"
    crashed = _case({}, error="TypeError: boom")
    assert crashed["passed"] is False
    assert {r["status"] for r in crashed["acceptance"]} == {"fail", "info"}

    record = _record([ok, crashed, no_gains])
    md = lab.markdown(record)
    tables = [ln for ln in md.splitlines() if ln.startswith("|")]
    assert all(ln.count("|") in (4, 6) for ln in tables)
    assert "| lamp position error (share of its distance) | n/a | 0.03 | <= 0.05 | **pass** |" \
        in md
    assert "| shadow IoU | 0.82 | 0.8 | >= control - 0.05 | **pass** |" in md
    assert "run failed: `TypeError: boom`" in md and "not wholly measured" in md
    assert "| run, lab / control | | 1.00x |" in md
    assert "| relight PSNR (dB) under a new point lamp | n/a | 21.50 |  |  |" in md
    from scripts.results import lab_result

    doc = lab_result(record, "CPU, 2 cores")
    assert [r[0] for r in doc["tables"][0]["rows"]] == ["default, 6 radii"] * 3
    assert doc["tables"][0]["rows"][0][-1] == "pass"
    assert doc["tables"][0]["rows"][1][-1] == "fail"
    assert doc["tables"][0]["rows"][0][5] == "0.820 / 0.800"
    from scripts.results import render, write_result

    write_result(tmp_path / "lab.json", doc)
    assert "Lab captures: a lamp in a room" in render(tmp_path)


def test_the_gains_are_scored_after_one_global_scale(tmp_path):
    rng = np.random.default_rng(7)
    truth = np.exp2(rng.uniform(-0.35, 0.35, (12, 1))) * (1 + rng.uniform(-0.04, 0.04, (12, 3)))
    errs = lab.gain_errors(truth / 1.7, truth)  # one scale: exact
    assert errs["global"]["max"] < 1e-12 and math.isclose(errs["global"]["scale"][0], 1.7)
    tint = np.array([1.02, 1.0, 0.98])  # a white balance the albedo took: per channel only
    errs = lab.gain_errors(truth * tint, truth)
    s = math.exp(-np.log(tint).mean())  # the float64 reference of the global scale
    assert math.isclose(errs["global"]["max"], np.abs(tint * s - 1).max(), rel_tol=1e-9)
    assert errs["per_channel"]["max"] < 1e-12
    with pytest.raises(ValueError, match="fitted gains"):
        lab.gain_errors(truth[:3], truth)

    run, photoset = tmp_path / "run", tmp_path / "photoset"
    assert lab.gain_scores(run, photoset) is None  # a run without fitted gains
    (run / "geometry").mkdir(parents=True)
    (photoset / "photos").mkdir(parents=True)
    names = [f"train_{i:03d}.jpg" for i in range(12)]
    (run / lab.GAINS_FILE).write_text(json.dumps({"views": [
        {"name": f"r_{i}", "photo": n, "gain": (truth[i] * 0.5).tolist()}
        for i, n in enumerate(names)]}))
    control = lab.gain_scores(run, photoset)  # no gains.json: a photo set without jitter
    assert control["truth"] == "1 (no jitter)" and control["views"] == 12
    assert control["global"]["max"] > 0.1
    (photoset / "photos" / "gains.json").write_text(json.dumps(
        {"photos": {n: {"gain": truth[i].tolist()} for i, n in enumerate(names)}}))
    scored = lab.gain_scores(run, photoset)
    assert scored["global"]["max"] < 1e-9 and scored["views"] == 12


def test_the_control_light_is_the_lamp_seen_from_the_centre():
    """The control's one directional light has the lab lamp's direction and irradiance at
    the object's centre; the scene's second light is off."""
    from mi_shadowgs.dataset.scene import load_scene
    from mi_shadowgs.scenes import scene_path

    lab_setup = load_scene(scene_path("default"), {**lab.scene_lights("lab", 6.0),
                                                   "base_texture": "mat"})
    control = load_scene(scene_path("default"), {**lab.scene_lights("control", 6.0),
                                                  "base_texture": "mat"})
    (lamp,) = lab_setup.lights
    on = [lt for lt in control.lights if max(lt.irradiance) > 0]
    assert len(on) == 1 and len(control.lights) == 2
    assert np.allclose(on[0].direction, lamp.direction, atol=1e-9)
    assert np.allclose(on[0].irradiance, lamp.irradiance)
    assert lamp.radius > 0 and math.isclose(
        lamp.distance, 6.0 * lab_setup.object_radius, rel_tol=1e-9)
    assert lab.scene_lights("lab", 12.0)["lamp_distance"] == "12"


def test_bad_options_and_other_settings_exit_2(tmp_path, capsys):
    def refused(argv, text):
        with pytest.raises(SystemExit) as exc:
            lab.main(["--out", str(tmp_path / "o"), *argv])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and text in err, err

    refused(["--distance", "1.1"], "--distance 1.1")
    refused(["--photo-size", "640y"], "--photo-size")
    refused(["--scene", "nowhere"], "--scene nowhere")
    refused(["--set", "material.nothing=1"], "unknown material setting 'nothing'")
    refused(["--set", "material.lamps=sometimes"], "lamps")
    assert not (tmp_path / "o").exists()  # checked before any folder is made
    settings = {"preset": "cpu-small", "photo_size": [640, 480], "views": 48,
                "max_size": 128, "sets": [], "seed": 0}
    lab.check_settings(tmp_path, settings)
    lab.check_settings(tmp_path, settings)  # the same: taken
    with pytest.raises(SystemExit) as exc:
        lab.check_settings(tmp_path, {**settings, "views": 24})
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "views = 48" in err and "24" in err


def test_cases_share_their_control_and_the_lab_fits_lamps(tmp_path, monkeypatch, capsys):
    """Two distances of one scene: one control run (the preset's ``material.lamps``), two
    lab runs (``material.lamps=auto``), ``--set`` in all; a lab run that raises is
    recorded and the study exits 1."""
    import validation.photos as photos
    from mi_shadowgs.presets import get_config

    made, ran = [], []

    def fake_make(out, scene, mesh, kind, distance, settings, times):
        folder = lab.kind_dir(out, scene, kind, distance)
        made.append(folder.relative_to(out).as_posix())
        (folder / "import").mkdir(parents=True, exist_ok=True)
        (folder / "import" / "import.json").write_text(json.dumps(
            {"registered": ["a", "b", "c"], "rejected": ["d"]}))
        return {"photoset": folder / "photoset" / "data", "gt": folder / "gt" / "data",
                "import": folder / "import", "run": folder / "run",
                "times": {"photoset_s": 1.0, "gt_s": 1.0, "import_s": 1.0}}

    def fake_run(data, out, config, times, key=None, study=None):
        ran.append((key, config.material.lamps, config.material.iterations))
        if "lamp12" in key:
            raise TypeError("no lamp maps")
        out.mkdir(parents=True, exist_ok=True)
        (out / "summary.json").write_text(json.dumps({"stages": [
            {"name": "Stage 1: geometry", "seconds": 5.0}]}))
        return 7.0, False

    def fake_score(paths, settings):
        return {"registered": 3, "photos": 4, "scores": _scores(), "gains": None,
                "score_s": 0.5}

    monkeypatch.setattr(lab, "make_kind", fake_make)
    monkeypatch.setattr(photos, "timed_run", fake_run)
    monkeypatch.setattr(lab, "score_kind", fake_score)
    out = tmp_path / "study"
    argv = ["--out", str(out), "--distance", "6,12", "--set", "material.iterations=50"]
    assert lab.main(argv) == 1
    assert "runs that failed: default at 12 (lab)" in capsys.readouterr().err
    assert made == ["default/control", "default/lamp6", "default/control", "default/lamp12"]
    preset = get_config("cpu-small").material.lamps  # the control runs as the preset does
    assert [r[1:] for r in ran] == [(preset, 50), ("auto", 50), (preset, 50), ("auto", 50)]
    rec = json.loads((out / "lab.json").read_text())
    assert [c["distance"] for c in rec["cases"]] == [6.0, 12.0]
    assert rec["cases"][1]["lab"]["error"] == "TypeError: no lamp maps"
    assert rec["cases"][0]["lab"]["times"]["stage1_s"] == 5.0
    assert (out / "lab.md").is_file() and json.loads(
        (out / lab.SETTINGS_FILE).read_text())["sets"] == ["material.iterations=50"]
    with pytest.raises(SystemExit) as exc:  # the same OUT with other settings
        lab.main([*argv, "--views", "24"])
    assert exc.value.code == 2 and "views = 48" in capsys.readouterr().err
