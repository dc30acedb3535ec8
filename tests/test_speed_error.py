"""``validation.speed_error`` on test-tiny runs: every point is run once into its own folder
and skipped when finished, the stage-4 points reuse the base run's stages 1-2 untouched, the
CSV marks what was reused, and the Pareto front is the set no other point beats."""

from __future__ import annotations

import csv
import json

import pytest
from tiny_cli import TINY, presets

import mi_shadowgs.api as msg
from mi_shadowgs.io.images import read_png
from validation import pipeline as vpipe
from validation import speed_error as se


def test_pareto_front_is_the_set_no_point_beats():
    rows = [{"point": "a", "wall_s": 10.0, "m": 1.0}, {"point": "b", "wall_s": 20.0, "m": 2.0},
            {"point": "c", "wall_s": 30.0, "m": 1.5},  # slower and worse than b
            {"point": "d", "wall_s": 20.0, "m": 2.0},  # ties b: neither beats the other
            {"point": "e", "wall_s": float("nan"), "m": 9.0}]  # unknown time: not on it
    assert se.pareto(rows, "m") == {"a", "b", "d"}
    # jointly over two metrics: c is worse than b on m but better on n, so it stays
    for r, n in zip(rows, (0.0, 1.0, 2.0, 0.5, 0.0), strict=True):
        r["n"] = n
    assert se.pareto(rows, ("m", "n")) == {"a", "b", "c"}  # d: as slow as b, worse on n


def test_stage1_schedule_scales_with_its_steps():
    base = se.scaled_geometry(1.0)
    half = se.scaled_geometry(0.5)
    assert half.iterations * 2 == base.iterations
    for field in ("normal_from", "dist_from", "sh_degree_interval"):
        assert getattr(half, field) * 2 == pytest.approx(getattr(base, field), abs=1)
    assert half.densify.stop * 2 == pytest.approx(base.densify.stop, abs=1)
    assert half.densify.stop < half.iterations  # the densification window stays inside


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("speed_error")
    base = root / "table"
    with pytest.MonkeyPatch.context() as mp:
        for table, config in presets():
            mp.setitem(table, TINY, config)
        mp.setattr(se, "PRESET", TINY)
        mp.setattr(se, "POINTS", {"res16": {"resolution": 16}, "s4_30": {"stage4": 30},
                                  "s1x0.5": {"stage1": 0.5}})
        # The base point, as validation.pipeline leaves it (row.json beside data and run).
        folder = base / "default-tuned"
        # default.xml's own lights are the tuned pair, which the res16 point's dataset sets
        assert vpipe.LIGHT_PAIRS["tuned"]["light0_elevation"] == "50"
        data = msg.generate_dataset(msg.scene_path("default"), folder / "data", preset=TINY)
        summary = msg.run(data, folder / "run", preset=TINY)
        full = json.loads((folder / "run" / "material" / "full" / "metrics.json").read_text())
        (folder / "row.json").write_text(json.dumps({
            "scene": "default", "lights": "tuned", "load_end": 1.0, "variants": {"full": full},
            "stage_s": {st["name"]: st.get("seconds") for st in summary["stages"]}}))
        rows = se.sweep(root / "out", base, ["default"], ["res16", "s4_30", "s1x0.5"],
                        root / "figures", "test", wait=False)
        mtimes = {p: p.stat().st_mtime_ns for p in (root / "out").rglob("point.json")}
        again = se.sweep(root / "out", base, ["default"], ["res16", "s4_30", "s1x0.5"],
                         None, "test", wait=False)
    return root, rows, again, mtimes


def test_sweep_runs_each_point_once_and_tabulates_it(sweep):
    root, rows, again, mtimes = sweep
    out = root / "out"
    assert [r["point"] for r in rows] == ["cpu-small", "res16", "s1x0.5", "s4_30"]
    by = {r["point"]: r for r in rows}
    assert by["res16"]["resolution"] == 16
    assert by["s4_30"]["stage4_iterations"] == 30
    assert by["s1x0.5"]["stage1_iterations"] * 2 == by["cpu-small"]["stage1_iterations"]
    assert all(r["wall_s"] > 0 and r["albedo_psnr"] is not None for r in rows)
    assert by["cpu-small"]["source"].startswith("reused: ") and \
        by["s4_30"]["source"].startswith("stages 1-2 reused from ")
    # the stage-4 point started from the base's stage 1, byte for byte, and its own fit
    # ran 30 steps (then the preset's normal phase)
    base_run = root / "table" / "default-tuned" / "run"
    s4_run = out / "default" / "s4_30" / "run"
    assert (s4_run / "geometry" / "model.ply").read_bytes() == \
        (base_run / "geometry" / "model.ply").read_bytes()
    hist = (s4_run / "material" / "full" / "history.csv").read_text().splitlines()
    normal_steps = next(c.material.normal_steps for _, c in presets() if hasattr(c, "material"))
    assert int(hist[-1].split(",")[0]) == 30 + normal_steps
    # the res16 point trained on its own 16-px dataset
    info = json.loads((out / "default" / "res16" / "data" / "dataset.json").read_text())
    assert (info["config"]["width"], info["config"]["height"]) == (16, 16)
    # a second call runs nothing
    assert {p: p.stat().st_mtime_ns for p in out.rglob("point.json")} == mtimes
    assert [r["point"] for r in again] == [r["point"] for r in rows]
    with open(out / "speed_error.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert [t["point"] for t in table] == [r["point"] for r in rows]
    assert any(t["pareto"] != "-" for t in table)
    for p in (out / "speed_error_default.png", root / "figures" / "speed_error_default.png"):
        assert read_png(p).shape[1] > 1000


def test_attached_plots_show_in_the_report(sweep):
    """--attach puts the plots into a run's speed_error/, lists them in its manifest, and its
    report shows them; `mi-shadowgs report` picks up plots added after the run."""
    from mi_shadowgs.cli import main as cli_main

    root = sweep[0]
    run = root / "table" / "default-tuned" / "run"
    page = run / "report.html"
    assert "src='speed_error/" not in page.read_text()  # none yet: the section's note says how
    assert "validation.speed_error --attach RUN" in page.read_text()
    se.attach(run, [root / "out" / "speed_error_default.png"], "the sweep's command")
    html = page.read_text()
    assert "src='speed_error/speed_error_default.png'" in html
    # the report says the plots are the sweep's, and which sweep
    assert "not a measurement of this run" in html and str((root / "out").resolve()) in html
    assert "the sweep&#x27;s command" in html
    assert (run / "speed_error" / "speed_error_default.png").is_file()
    manifest = json.loads((run / ".mi_shadowgs_manifest.json").read_text())
    assert "speed_error/speed_error_default.png" in manifest["files"]
    # a plot dropped in by hand: the report command refreshes the section
    (run / "speed_error" / "extra.png").write_bytes(
        (run / "speed_error" / "speed_error_default.png").read_bytes())
    assert cli_main(["report", str(run)]) == 0
    assert "src='speed_error/extra.png'" in page.read_text()
    # attaching again writes over its own plot, never over the one put there by hand
    se.attach(run, [root / "out" / "speed_error_default.png"])
    hand = (run / "speed_error" / "extra.png").read_bytes()
    other = root / "other_sweep" / "extra.png"  # a plot of the same name as the hand's
    other.parent.mkdir()
    other.write_bytes(b"not the hand's plot")
    with pytest.raises(SystemExit) as exc:
        se.attach(run, [root / "out" / "speed_error_default.png", other])
    assert exc.value.code == 2
    assert (run / "speed_error" / "extra.png").read_bytes() == hand
    assert "speed_error/extra.png" not in json.loads(
        (run / ".mi_shadowgs_manifest.json").read_text())["files"]
    with pytest.raises(SystemExit) as exc:  # nothing to attach
        se.attach(run, [])
    assert exc.value.code == 2
