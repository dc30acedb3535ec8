"""A killed validation study loses only the unit in progress (``validation.units``): stage 1
of ``validation.geometry``, the stages of ``validation.segmentation``, each filter strength
of ``validation.lowpass_drift`` and the parts of ``validation.asset``. Each study is
interrupted in its second piece of work (after a checkpoint where it has one); the rerun
does nothing the first call finished, continues the piece in progress, and ends with the
tables of an uninterrupted call; other settings exit 2 naming the setting.

The comparisons with an uninterrupted call run Dr.Jit on one thread: on more, float atomics
add in a varying order and two calls differ in the last bits (see tests/test_kill.py).
"""

from __future__ import annotations

import dataclasses
import json

import pytest
from conftest import exits_2
from tiny_cli import TINY, set_sections

from mi_shadowgs import presets as run_presets
from mi_shadowgs.stages.geometry import train as geometry_train


def _stopped_after_step(step: int):
    """An ``on_step`` that stops the loop after ``step`` (its checkpoint written), as a kill."""
    def on_step(done: int) -> None:
        if done == step:
            raise KeyboardInterrupt
    return on_step


def test_geometry_continues_its_stage_and_times_it_from_the_log(
        tiny_presets, tiny_run, monkeypatch, tmp_path, capsys, one_thread):
    """Killed at step 50 of 80 (checkpoints every 25): the rerun continues from step 50, not
    from 0, scores as an uninterrupted call, and the time item is the log's training time
    across both calls; a third call reuses the stage; other settings exit 2 naming the
    setting and the folder."""
    import csv

    from validation import geometry

    out = tmp_path / "geometry"
    argv = ["--data", str(tiny_run / "data"), "--out", str(out), "--preset", TINY,
            "--no-progress"]
    starts = []
    train = geometry_train.train_geometry

    def counted(dataset, config, *, state=None, callbacks=None, **kw):
        starts.append(0 if state is None else state.step)
        if len(starts) == 1:
            callbacks = dataclasses.replace(callbacks, on_step=_stopped_after_step(50))
        return train(dataset, config, state=state, callbacks=callbacks, **kw)

    monkeypatch.setattr(geometry_train, "train_geometry", counted)
    with pytest.raises(KeyboardInterrupt):
        geometry.main(argv)
    assert not (out / "geometry.json").exists()
    geometry.main(argv)
    assert starts == [0, 50]
    m = json.loads((out / "geometry.json").read_text())
    with open(out / "stage" / "log.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["iteration"]) for r in rows] == list(range(10, 81, 10))
    assert m["stage"] == "resumed" and m["train_s"] == float(rows[-1]["time"])
    assert m["accept"]["wall_s"] == (m["train_s"] <= geometry.ACCEPT["wall_s"])
    assert {p.name for p in (out / "previews").iterdir()} == {"r_000.png", "r_001.png"}
    geometry.main([*argv[:3], str(tmp_path / "whole"), *argv[4:]])
    once = json.loads((tmp_path / "whole" / "geometry.json").read_text())
    timeless = ("model", "train_s", "wall_s", "stage", "loadavg_start", "loadavg_end")
    assert {k: v for k, v in m.items() if k not in timeless} == \
        {k: v for k, v in once.items() if k not in timeless}
    geometry.main(argv)
    assert starts == [0, 50, 0]  # reused
    again = json.loads((out / "geometry.json").read_text())
    assert again["stage"] == "reused" and again["train_s"] == m["train_s"]
    err = exits_2(geometry.main, [*argv, "--iterations", "60"], capsys)
    assert "iterations: 80 there, 60 now" in err and str(out / "stage") in err, err
    assert starts == [0, 50, 0]


def test_segmentation_reuses_its_dataset_and_stages_and_continues_the_one_in_progress(
        tiny_presets, monkeypatch, tmp_path, capsys, one_thread):
    """Two stages (material and chromaticity masks); killed after the second one's first
    checkpoint. The rerun keeps the dataset, reuses the first stage, continues the second
    from its checkpoint and writes the rows of an uninterrupted call; other settings exit 2
    naming the setting."""
    from mi_shadowgs.stages.segmentation import features
    from validation import segmentation

    # The default scene only, its dataset and stages at the tiny preset.
    monkeypatch.setattr(segmentation, "HOTDOG", tmp_path / "no_hotdog.ply")
    monkeypatch.setitem(run_presets.GENERATE, "cpu-small", run_presets.GENERATE[TINY])
    set_sections(monkeypatch, "cpu-small", segmentation=run_presets.PRESETS[TINY].segmentation)
    root, out = tmp_path / "data", tmp_path / "seg"
    argv = ["--out", str(out), "--data-root", str(root), "--quick"]
    starts = []
    segment = features.segment_surfels

    def counted(*args, state=None, on_checkpoint=None, **kw):
        starts.append(state is not None)
        if len(starts) == 2:
            def on_checkpoint_then_killed(s, save=on_checkpoint):
                save(s)
                raise KeyboardInterrupt
            on_checkpoint = on_checkpoint_then_killed
        return segment(*args, state=state, on_checkpoint=on_checkpoint, **kw)

    monkeypatch.setattr(features, "segment_surfels", counted)
    with pytest.raises(KeyboardInterrupt):
        segmentation.main(argv)
    dataset_json = root / "seg_val_default" / "dataset.json"
    made = dataset_json.stat()
    assert not (out / "segmentation.json").exists()
    assert segmentation.main(argv) == 0
    assert starts == [False, False, True]  # the first stage reused, the second continued
    assert (dataset_json.stat().st_ino, dataset_json.stat().st_mtime_ns) == \
        (made.st_ino, made.st_mtime_ns)  # not generated again
    rows = json.loads((out / "segmentation.json").read_text())
    assert [(r["scene"], r["masks"]) for r in rows] == [("default", "material"),
                                                       ("default", "chromaticity")]
    whole = tmp_path / "whole"
    assert segmentation.main(["--out", str(whole), "--data-root", str(root), "--quick"]) == 0

    def timeless(table):
        return [{k: v for k, v in r.items() if not k.startswith("seconds")} for r in table]

    assert timeless(rows) == timeless(json.loads((whole / "segmentation.json").read_text()))
    set_sections(monkeypatch, "cpu-small", segmentation=dataclasses.replace(
        run_presets.PRESETS[TINY].segmentation, n_samples=128))
    err = exits_2(segmentation.main, argv, capsys)
    assert "config.n_samples: 256 there, 128 now" in err and str(out / "default_material") \
        in err, err


def test_lowpass_drift_keeps_each_finished_k_and_continues_the_one_in_progress(
        tiny_presets, tiny_run, monkeypatch, tmp_path, capsys, one_thread):
    """Two filter strengths; killed in the second's training after a checkpoint. The rerun
    trains only the rest of the second and writes an uninterrupted call's tables; other
    settings exit 2 naming the setting."""
    from validation import lowpass_drift

    quick = lowpass_drift.DriftConfig(ks=(2.0, 12.0), steps=20, object_surfels=600,
                                      base_surfels=300, test_views=2)
    monkeypatch.setattr(lowpass_drift, "QUICK", quick)
    set_sections(monkeypatch, "cpu-small", geometry=dataclasses.replace(
        run_presets.geometry_config("cpu-small"), checkpoint_every=5))
    out, data = tmp_path / "drift", str(tiny_run / "data")
    argv = ["--out", str(out), "--data", data, "--quick"]
    starts = []
    train = geometry_train.train_geometry

    def counted(dataset, config, *, state=None, callbacks=None, **kw):
        starts.append(state.step)
        if len(starts) == 2:
            callbacks = dataclasses.replace(callbacks or geometry_train.Callbacks(),
                                            on_step=_stopped_after_step(1210))
        return train(dataset, config, state=state, callbacks=callbacks, **kw)

    monkeypatch.setattr(geometry_train, "train_geometry", counted)
    with pytest.raises(KeyboardInterrupt):
        lowpass_drift.main(argv)
    assert starts == [1200, 1200] and not (out / "lowpass_drift.json").exists()
    assert lowpass_drift.main(argv) == 0
    assert starts == [1200, 1200, 1210]  # k = 2 reused, k = 12 continued from step 1210
    whole = tmp_path / "whole"
    assert lowpass_drift.main(["--out", str(whole), "--data", data, "--quick"]) == 0
    for name in ("lowpass_drift.json", "lowpass_drift.md"):
        assert (out / name).read_text() == (whole / name).read_text()
    assert [r["k"] for r in json.loads((out / "lowpass_drift.json").read_text())["rows"]] == \
        [2.0, 12.0]
    monkeypatch.setattr(lowpass_drift, "QUICK", dataclasses.replace(quick, steps=25))
    err = exits_2(lowpass_drift.main, argv, capsys)
    assert "drift.steps: 20 there, 25 now" in err and str(out / "units" / "quick-k_2") in err


def test_asset_keeps_its_finished_parts_and_continues_a_path_trace_from_its_last_view(
        tiny_presets, tiny_run, monkeypatch, tmp_path, capsys, one_thread):
    """Killed after the first test view's path-trace: the rerun exports, samples and scales
    nothing again, traces only the other view, and writes an uninterrupted call's numbers
    and figure; another --spp exits 2 naming it."""
    import mitsuba as mi

    from validation import asset

    cfg = run_presets.export_config("cpu-small")  # a coarse grid for speed, as tests/test_export.py
    set_sections(monkeypatch, "cpu-small", export=dataclasses.replace(
        cfg, mesh=dataclasses.replace(cfg.mesh, resolution=48)))
    calls = {"truth": 0, "mesh": 0, "scale": 0, "trace": 0}

    def counted(name, fn, **fewer):
        def call(*args, **kw):
            calls[name] += 1
            return fn(*args, **{**kw, **fewer})
        return call

    monkeypatch.setattr(asset, "ground_truth_points", counted(
        "truth", asset.ground_truth_points, n=20_000))
    monkeypatch.setattr(asset, "mesh_points", counted("mesh", asset.mesh_points, n=20_000))
    monkeypatch.setattr(asset, "surfel_albedo_scale", counted("scale", asset.surfel_albedo_scale))
    render = mi.render

    def killed_on_the_second_view(*args, **kw):
        calls["trace"] += 1
        if calls["trace"] == 2:
            raise KeyboardInterrupt
        return render(*args, **kw)

    out = tmp_path / "asset"
    argv = ["--run", str(tiny_run / "run"), "--data", str(tiny_run / "data"), "--out",
            str(out), "--spp", "4", "--no-progress"]
    monkeypatch.setattr(mi, "render", killed_on_the_second_view)
    with pytest.raises(KeyboardInterrupt):
        asset.main(argv)
    assert calls == {"truth": 1, "mesh": 1, "scale": 1, "trace": 2}
    assert not (out / "asset.json").exists()
    exported = (out / "export" / "export.json").stat().st_mtime_ns
    asset.main(argv)
    assert calls == {"truth": 1, "mesh": 1, "scale": 1, "trace": 3}
    assert (out / "export" / "export.json").stat().st_mtime_ns == exported  # reused
    result = json.loads((out / "asset.json").read_text())
    (name,) = result["relighting"]
    assert result["relighting"][name]["views_traced"] == 1
    monkeypatch.setattr(mi, "render", render)
    whole = tmp_path / "whole"
    asset.main([*argv[:4], "--out", str(whole), "--spp", "4", "--no-progress"])
    once = json.loads((whole / "asset.json").read_text())
    assert once["relighting"][name]["views_traced"] == 2

    def scores(r):
        return ({k: v for k, v in r["relighting"][name].items()
                 if k not in ("render_s", "views_traced")}, r["chamfer"], r["albedo_scale"])

    assert scores(result) == scores(once)
    assert (out / "asset.png").read_bytes() == (whole / "asset.png").read_bytes()
    err = exits_2(asset.main, [*argv[:6], "--spp", "8", "--no-progress"], capsys)
    assert "spp: 4 there, 8 now" in err and str(out / "units" / f"relight_{name}") in err
