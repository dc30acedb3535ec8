"""Checkpoints and signals: every training loop resumes from a checkpoint
to the bit-identical result of an uninterrupted run, from any step; SIGINT/SIGTERM write a
checkpoint and end the command with one line and exit 130/143.

Run on one Dr.Jit thread: with more, float atomics make even two uninterrupted runs differ
in the last bits (tests/test_kill.py says more).
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal

import drjit as dr
import numpy as np
import pytest
import tiny_cli
from segmentation_fixtures import standin_surfels
from test_stage_material import _plane_scene, _render_truth

from mi_shadowgs import cli
from mi_shadowgs import presets as run_presets
from mi_shadowgs.core.directions import direction_from_angles
from mi_shadowgs.dataset.loader import load_dataset
from mi_shadowgs.io import interrupt
from mi_shadowgs.io.checkpoint import load_checkpoint, save_checkpoint
from mi_shadowgs.presets import material_config as get_config
from mi_shadowgs.scenes import scene_path
from mi_shadowgs.stages import common as stage_common
from mi_shadowgs.stages.geometry import train as geometry_train
from mi_shadowgs.stages.material import fit as material_fit
from mi_shadowgs.stages.material.fit import fit_material
from mi_shadowgs.stages.material.state import MaterialState
from mi_shadowgs.stages.segmentation import features as seg
from mi_shadowgs.stages.segmentation.masks import material_masks
from mi_shadowgs.stages.visibility.shadow_maps import VisibilityConfig
from tests.conftest import signal_on_call, without_few_views_warning

TINY = tiny_cli.TINY


@pytest.fixture(scope="module", autouse=True)
def one_thread_tiny_presets():
    threads = dr.thread_count()
    dr.set_thread_count(1)
    with pytest.MonkeyPatch.context() as mp:
        for table, config in tiny_cli.presets():
            mp.setitem(table, TINY, config)
        yield
    dr.set_thread_count(threads)


@pytest.fixture(scope="module")
def data(tmp_path_factory, one_thread_tiny_presets):
    out = tmp_path_factory.mktemp("resume") / "data"
    assert cli.main(["generate", str(scene_path("default")), "--out", str(out), "--preset",
                     TINY, "--no-progress"]) == 0
    return out


class Stop(Exception):
    pass


def _stopping_at(stop: int, folder):
    """on_checkpoint: save like the CLI does; stop the run after the checkpoint at ``stop``."""
    def on_checkpoint(state):
        save_checkpoint(folder, *state.to_checkpoint())
        if state.step == stop:
            raise Stop
    return on_checkpoint


def test_checkpoint_clock(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(interrupt.time, "monotonic", lambda: now[0])
    clock = interrupt.CheckpointClock(every=10, seconds=60.0)
    assert clock.due(10) and not clock.due(11)  # by count
    due = []
    for _ in range(100):  # steps of 1 s
        now[0] += 1.0
        due.append(clock.due())
    # In time for a kill to lose at most 60 s: the next step could end at 160 s.
    assert due.index(True) == 58
    clock.saved()
    now[0] += 20.0  # a long step: the next ones may be as long
    assert not clock.due()
    now[0] += 20.0
    assert clock.due()
    assert interrupt.CheckpointClock(every=0, seconds=1.0).due(0) is False  # by time only
    with pytest.raises(ValueError, match="seconds > 0"):
        interrupt.CheckpointClock(10, 0.0)


def test_signals_are_deferred_in_a_loop_and_immediate_outside():
    # the handler before: SIG_DFL, or one that an earlier test's library put there (Ray's)
    before = signal.getsignal(signal.SIGTERM)
    with interrupt.handle_signals():
        with pytest.raises(interrupt.Interrupted) as exc:
            os.kill(os.getpid(), signal.SIGINT)
        assert exc.value.exit_code == 130
        clock = interrupt.CheckpointClock(5, 60.0)
        with clock.running():
            os.kill(os.getpid(), signal.SIGTERM)
            assert clock.due(3)  # the loop checkpoints now...
            with pytest.raises(interrupt.Interrupted, match="SIGTERM .step 3.") as exc:
                interrupt.raise_pending("step 3")  # ... and then stops
            assert exc.value.exit_code == 143
            os.kill(os.getpid(), signal.SIGTERM)
            with pytest.raises(interrupt.Interrupted):  # a second signal stops at once
                os.kill(os.getpid(), signal.SIGINT)
        interrupt.raise_pending("nothing pending")  # the state was reset
    assert signal.getsignal(signal.SIGTERM) is before  # put back


def test_stage1_resumes_bit_identically(data, tmp_path):
    train = load_dataset(data, "train")
    config = dataclasses.replace(run_presets.geometry_config(TINY), checkpoint_every=7,
                                 checkpoint_seconds=1e9)
    logs = []
    straight = geometry_train.train_geometry(
        train, config, callbacks=geometry_train.Callbacks(on_log=logs.append), progress=False
    )
    for stop in (14, 35, 77):  # between log rows (every 10), around densification (20-60)

        def on_checkpoint(state, stop=stop):
            save_checkpoint(tmp_path, state.to_numpy(), {})
            if state.step == stop:
                raise Stop

        with pytest.raises(Stop):
            geometry_train.train_geometry(
                train,
                config,
                callbacks=geometry_train.Callbacks(on_checkpoint=on_checkpoint),
                progress=False,
            )
        state = geometry_train.TrainState.from_numpy(load_checkpoint(tmp_path)[0], config)
        resumed_logs = []
        resumed = geometry_train.train_geometry(
            train,
            config,
            state=state,
            progress=False,
            callbacks=geometry_train.Callbacks(on_log=resumed_logs.append),
        )
        for key, a in straight.to_numpy().items():
            np.testing.assert_array_equal(resumed.to_numpy()[key], a, err_msg=key)
        # The log rows after the checkpoint, the first one included, are the same.
        assert [{k: v for k, v in r.items() if k != "time"} for r in resumed_logs] == [
            {k: v for k, v in r.items() if k != "time"} for r in logs if r["iteration"] > stop
        ], stop


def test_stage2_resumes_bit_identically(data, tmp_path):
    train = load_dataset(data, "train")
    surfels, _ = standin_surfels(800)
    labels = seg.prepare_labels(material_masks(train), train.cameras)
    config = dataclasses.replace(run_presets.segmentation_config(TINY), checkpoint_every=1)
    straight = seg.train_features(surfels, train.cameras, labels, config, progress=False)
    for stop in (5, 16, 35):  # inside a round of the 8 views; in the prototype quarter
        with pytest.raises(Stop):
            seg.train_features(
                surfels,
                train.cameras,
                labels,
                config,
                progress=False,
                on_checkpoint=_stopping_at(stop, tmp_path),
            )
        state = seg.FeatureState.from_checkpoint(*load_checkpoint(tmp_path))
        assert state.step == stop
        resumed = seg.train_features(
            surfels, train.cameras, labels, config, progress=False, state=state
        )
        for key in ("features", "coverage", "prototypes"):
            np.testing.assert_array_equal(getattr(resumed, key), getattr(straight, key))
        assert resumed.history == straight.history


def _where(state) -> tuple:
    """(finished steps, finished units of the refinement in progress or None)."""
    return state.step, None if state.refine is None else state.refine.done


@pytest.mark.parametrize("specular", ["auto", "on"])
def test_stage4_resumes_bit_identically(specular, tmp_path):
    s, cams, bounds = _plane_scene()
    vcfg = VisibilityConfig(resolution=64)
    # Two lights between grid directions: each unit of the refinements moves one of the
    # lights, and the others' shadows enter its score.
    imgs, masks = _render_truth(
        s,
        cams,
        bounds,
        [direction_from_angles(47.0, 52.0), direction_from_angles(200.0, 35.0)],
        [2.0, 1.5],
        vcfg,
    )
    # The warm-up ends at 20, pruning every 10 after it, the second refinement at step 40;
    # a checkpoint after every step and every refinement unit.
    config = dataclasses.replace(
        get_config(TINY),
        checkpoint_every=1,
        checkpoint_seconds=1e-9,
        specular=specular,
        refine_score="segment",  # "albedo" needs the lobe off
        refine_passes=((4.0, 2.0), (2.0, 1.0)),
        refine_again_passes=((2.0, 1.0),),
        refine_again_global=specular == "auto",
        # "on" fits the albedo detail too, from the second refinement (step 40) on: a fit
        # resumed after it makes the same gates from the lights it joined with.
        detail_prior=0.3 if specular == "on" else 0.0,
    )

    def fit(**kw):
        return fit_material(
            s, cams, imgs, masks, config, bounds, vcfg, progress=False, **kw
        )

    # The first refinement: per light the global pass then the two local ones (6 units;
    # (20, 4) resumes after light 2's global pass). The second: with refine_again_global
    # ("auto") the same 6 units, (40, 1) resuming after light 1's global pass; without
    # ("on") its own pass only (2 units; (40, 1) resumes between its lights). Either way
    # the checkpoint must say which passes.
    # (75, None): inside the normal phase (steps 60-90).
    stops = [(20, None), (20, 4), (21, None), (31, None), (40, 1), (60, None), (75, None)]
    # (45, None): the detail phase, resumed ("on")
    resume_at = stops if specular == "auto" else stops[1:5:3] + [(45, None)] + stops[-1:]
    seen = []

    def on_checkpoint(state):
        """Each stop's checkpoint, saved as the CLI saves it when it is stopped there."""
        where = _where(state)
        if where in resume_at and where not in seen:
            save_checkpoint(tmp_path / f"{where[0]}_{where[1]}", *state.to_checkpoint())
        seen.append(where)

    straight = fit(on_checkpoint=on_checkpoint)
    assert straight.specular == (specular == "on")  # "auto" drops the lobe: a diffuse scene
    assert all(stop in seen for stop in stops)
    for stop in resume_at:
        folder = tmp_path / f"{stop[0]}_{stop[1]}"
        resumed = fit(state=MaterialState.from_checkpoint(*load_checkpoint(folder)))
        for key in ("albedo", "roughness", "metallic", "indirect_sh", "shading_normal"):
            np.testing.assert_array_equal(
                resumed.surfels.channels[key].numpy(),
                straight.surfels.channels[key].numpy(),
                err_msg=key,
            )
        np.testing.assert_array_equal(resumed.light.directions, straight.light.directions)
        np.testing.assert_array_equal(resumed.light.weights, straight.light.weights)
        assert resumed.history == straight.history
        assert resumed.light_log == straight.light_log


def _files(folder):
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*.ply")) + sorted(folder.rglob("*.png"))
    }


def test_sigterm_checkpoints_and_resume_continues(data, tmp_path, capsys, monkeypatch):
    argv = ["train", str(data), "--preset", TINY, "--no-progress"]
    assert cli.main([*argv, "--out", str(tmp_path / "ref")]) == 0
    run = tmp_path / "run"
    with monkeypatch.context() as mp:
        signal_on_call(mp, geometry_train, "geometry_loss", 33, signal.SIGTERM)
        assert cli.main([*argv, "--out", str(run)]) == 143
    err = without_few_views_warning(capsys.readouterr().err).strip().splitlines()
    assert (
        len(err) == 1
        and "SIGTERM" in err[0]
        and "step 33 of 80, checkpoint written" in err[0]
        and "--resume" in err[0]
    ), err
    assert load_checkpoint(run / "geometry" / "checkpoint")[1]["step"] == 33
    assert cli.main([*argv, "--out", str(run), "--resume"]) == 0
    assert _files(run) == _files(tmp_path / "ref")


def test_resume_before_the_first_checkpoint_starts_afresh(data, tmp_path, capsys, monkeypatch):
    """A kill before the first checkpoint used to leave --resume with "no checkpoint"."""
    argv = ["train", str(data), "--preset", TINY, "--no-progress", "--no-eval"]
    run = tmp_path / "run"
    with monkeypatch.context() as mp:
        mp.setattr(
            geometry_train, "geometry_loss", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt)
        )
        with pytest.raises(KeyboardInterrupt):  # as a kill -9 would, before any checkpoint
            cli.main([*argv, "--out", str(run)])
    assert not (run / "geometry" / "checkpoint").exists()
    assert cli.main([*argv, "--out", str(run), "--resume"]) == 0
    assert "no checkpoint yet; starting from step 0" in capsys.readouterr().err
    assert (run / "geometry" / "model.ply").is_file()


def test_signal_outside_a_loop_stops_at_once(data, tmp_path, capsys, monkeypatch):
    def load(*a):
        os.kill(os.getpid(), signal.SIGINT)
        raise AssertionError("the signal did not stop the command")

    monkeypatch.setattr(stage_common, "load_training_views", load)
    assert (
        cli.main(
            ["run", str(data), "--out", str(tmp_path / "run"), "--preset", TINY, "--no-progress"]
        )
        == 130
    )
    err = without_few_views_warning(capsys.readouterr().err).strip().splitlines()
    assert err == ["mi-shadowgs run: interrupted by SIGINT; run the same command again to continue"]


def test_interrupted_segment_and_run_continue(data, tmp_path, capsys, monkeypatch):
    """SIGTERM in stage 2 (``segment``) and in stage 4 (``run``): the rerun continues from the
    checkpoint to the files of an uninterrupted run."""
    run, ref = tmp_path / "run", tmp_path / "ref"
    argv = ["run", str(data), "--preset", TINY, "--no-progress"]
    assert cli.main([*argv, "--out", str(ref)]) == 0
    with monkeypatch.context() as mp:
        signal_on_call(mp, material_fit, "view_loss", 27, signal.SIGTERM)
        assert cli.main([*argv, "--out", str(run)]) == 143
    assert "stage 4 stopped at step 27 of 90" in capsys.readouterr().err  # 60 + 30 normal steps
    assert cli.main([*argv, "--out", str(run)]) == 0
    assert _files(run) == _files(ref)

    seg_argv = [
        "segment",
        str(ref),
        "--data",
        str(data),
        "--preset",
        TINY,
        "--quiet",
        "--out",
        str(tmp_path / "seg"),
    ]
    with monkeypatch.context() as mp:
        signal_on_call(mp, seg, "segmentation_loss", 9, signal.SIGTERM)
        assert cli.main(seg_argv) == 143
    assert "run it again with --resume" in capsys.readouterr().err
    # The killed call's training is counted in the stage's time as in the training's: made
    # long here (1000 s) so that the continuing call's own time cannot stand in for it.
    ckpt = tmp_path / "seg" / "checkpoint"
    arrays, meta = load_checkpoint(ckpt)
    save_checkpoint(ckpt, arrays, {**meta, "elapsed": meta["elapsed"] + 1000.0})
    assert cli.main(seg_argv) == 2
    assert "pass --resume to continue it" in capsys.readouterr().err
    assert cli.main([*seg_argv, "--resume"]) == 0
    assert _files(tmp_path / "seg") == _files(ref / "segmentation")
    report = json.loads((tmp_path / "seg" / "segmentation.json").read_text())
    assert report["seconds_train"] > 1000.0
    assert report["seconds_stage"] > report["seconds_train"] + report["seconds_masks"]
    capsys.readouterr()
    assert cli.main([*seg_argv, "--resume"]) == 0  # finished: says so (it printed nothing)
    assert "is finished, with the same dataset, model and settings" in capsys.readouterr().out
    assert cli.main([*seg_argv, "--resume", "--overwrite"]) == 2  # as train refuses the pair
    assert "pass one of them" in capsys.readouterr().err


def test_a_log_row_cut_short_is_dropped_on_resume(tmp_path):
    """Hard case: a crash while stage 1 appended a log row leaves it cut short; the resume
    keeps the whole rows up to its checkpoint and drops that one (before, it kept it with
    empty fields, or failed on int('') where the cut fell in the first field)."""
    from types import SimpleNamespace

    from mi_shadowgs.stages.geometry.runner import LOG_FIELDS, GeometryWriter

    log = tmp_path / "log.csv"
    whole = [",".join([str(i), "0.5"] + ["1"] * (len(LOG_FIELDS) - 2)) for i in (25, 50, 75)]
    log.write_text(",".join(LOG_FIELDS) + "\n" + "\n".join(whole) + "\n100,0.4")
    writer = GeometryWriter(SimpleNamespace(path=lambda name: tmp_path / name), {})
    writer.start_log(100)
    rows = log.read_text().splitlines()
    assert rows[0] == ",".join(LOG_FIELDS) and [r.split(",")[0] for r in rows[1:]] == \
        ["25", "50", "75"]
    writer.start_log(50)  # an earlier checkpoint: the rows after it go too
    assert [r.split(",")[0] for r in log.read_text().splitlines()[1:]] == ["25", "50"]
