"""The factor split of ``validation.shadow_factors`` (pure parts; the tool itself needs a
finished run and the shared assets)."""

from __future__ import annotations

import itertools
import math
import shutil

import numpy as np
import pytest

from validation.shadow_factors import FACTORS, irradiance, shapley


def test_shapley_is_exact_for_additive_gains_and_sums_to_the_total():
    gains = {"lights": 0.2, "receivers": 0.05, "occluders": 0.01}
    scores = {k: 0.6 + sum(g for g, on in zip(gains.values(), k, strict=True) if on)
              for k in itertools.product((False, True), repeat=3)}
    sh = shapley(scores)
    assert all(math.isclose(sh[f], gains[f]) for f in FACTORS), sh
    rng = np.random.default_rng(0)
    scores = {k: float(rng.random()) for k in itertools.product((False, True), repeat=3)}
    sh = shapley(scores)
    total = scores[(True, True, True)] - scores[(False, False, False)]
    assert math.isclose(sum(sh.values()), total, abs_tol=1e-12)
    # An interaction (a gain only when two factors are both swapped) is split evenly.
    scores = {k: float(k[0] and k[1]) for k in itertools.product((False, True), repeat=3)}
    sh = shapley(scores)
    assert math.isclose(sh["lights"], 0.5) and math.isclose(sh["receivers"], 0.5)
    assert sh["occluders"] == 0.0


def test_irradiance_matches_the_definition():
    class Rec:
        normals_np = [np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])]

    dirs = np.array([[0.0, 1.0, 0.0], [0.6, 0.8, 0.0]])
    vis = [np.array([[1.0, 0.0], [1.0, 1.0]])]
    out = irradiance(Rec(), vis, dirs, np.array([2.0, 1.0]), (1, 2))
    # pixel 0: 2 * 1 * 1 + 1 * 0.8 * 0; pixel 1: 2 * 0 + 1 * 0.6 * 1
    assert np.allclose(out, [[[2.0, 0.6]]])


def test_the_tool_on_a_finished_run_reports_every_factor_and_the_exact_geometry(tmp_path,
                                                                                  capsys):
    """End to end on a tiny run of the default scene: every score is an IoU, the run's own
    is the recorded one (the same receivers, maps and lights as stage 5), and the table
    carries the method's IoU on exact geometry. The run's lights are kept directional
    (``lamps=off``): a run with a lamp is refused, naming its light.json."""
    import json

    import tiny_cli
    from tiny_cli import TINY

    from mi_shadowgs import cli
    from mi_shadowgs.scenes import scene_path
    from validation import shadow_factors

    with pytest.MonkeyPatch.context() as mp:
        for table, config in tiny_cli.presets():
            mp.setitem(table, TINY, config)
        assert cli.main(["generate", str(scene_path("default")), "--out",
                         str(tmp_path / "data"), "--preset", TINY, "--no-progress"]) == 0
        assert cli.main(["run", str(tmp_path / "data"), "--out", str(tmp_path / "run"),
                         "--preset", TINY, "--no-progress", "--set",
                         "material.lamps=off"]) == 0
    out = tmp_path / "factors"
    assert shadow_factors.main(["--run", str(tmp_path / "run"), "--data",
                                str(tmp_path / "data"), "--out", str(out), "--quiet"]) == 0
    res = json.loads((out / "shadow_factors.json").read_text())
    ious = [*res["scores"].values(), res["exact_geometry_iou"], res["shadow_iou"]]
    assert all(0.0 <= v <= 1.0 for v in ious), res
    assert res["scores"]["---"] == res["shadow_iou"]
    assert res["shadow_iou"] == pytest.approx(res["recorded_shadow_iou"], abs=1e-6)
    lamp_run = tmp_path / "lamp_run"
    shutil.copytree(tmp_path / "run", lamp_run)
    light_file = lamp_run / "material" / "full" / "light.json"
    light = json.loads(light_file.read_text())
    light["positions"] = [[0.0, 5.0, 0.0]] + [None] * (len(light["directions"]) - 1)
    light_file.write_text(json.dumps(light))
    with pytest.raises(SystemExit) as exc:
        shadow_factors.main(["--run", str(lamp_run), "--data", str(tmp_path / "data"),
                             "--out", str(tmp_path / "f2"), "--quiet"])
    assert exc.value.code == 2
    assert "light 0 is a lamp" in capsys.readouterr().err
    md = (out / "shadow_factors.md").read_text()
    assert "exact geometry" in md and f"{res['exact_geometry_iou']:.3f}" in md
    # the visibility validation's 20000 for 128^2 views, scaled to the test views' size
    from mi_shadowgs.dataset.loader import load_cameras

    cam = load_cameras(tmp_path / "data" / "transforms_test.json")[0][1]
    assert res["exact_surfels_128"] == 20000
    assert res["exact_surfels"] == round(20000 * cam.width * cam.height / 128 ** 2)
    assert res["base_surfels"] == round(4000 * cam.width * cam.height / 128 ** 2)
    with pytest.raises(SystemExit) as e:
        shadow_factors.main(["--run", str(tmp_path / "run"), "--data", str(tmp_path / "data"),
                             "--out", str(tmp_path / "none"), "--exact-surfels", "0"])
    assert e.value.code == 2 and not (tmp_path / "none").exists()
