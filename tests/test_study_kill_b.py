"""A killed study loses only the unit in progress (``validation.units``): each model's row of
each method and its factor split in ``validation.visibility``, the four parts of
``validation.shadow_factors``, each (dataset, view size) of ``validation.metric_floor`` and
each suite of ``benchmarks.run_all``. Each is interrupted in its second unit; the rerun
does nothing the first call finished and ends with the tables of an uninterrupted call; a
third call only gathers; other settings exit 2 naming the setting.

The comparisons with an uninterrupted call run Dr.Jit on one thread: on more, float atomics
add in a varying order and two calls differ in the last bits (see tests/test_kill.py).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import exits_2

ROOT = Path(__file__).resolve().parents[1]


def _counted(monkeypatch, module, name: str, stop_at: int | None = None) -> list:
    """Replace ``module.name`` by a wrapper that records each call's (args, kwargs) and
    raises KeyboardInterrupt in call number ``stop_at`` (from 1), as a kill would stop it."""
    calls = []
    real = getattr(module, name)

    def counted(*args, **kwargs):
        calls.append((args, kwargs))
        if len(calls) == stop_at:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, counted)
    return calls


def _same(a, b) -> bool:
    """Equal as JSON (NaN, an empty IoU's mean, equals NaN there)."""
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _with_out(argv: list[str], out: Path) -> list[str]:
    i = argv.index("--out")
    return [*argv[:i + 1], str(out), *argv[i + 2:]]


def test_metric_floor_reuses_each_finished_view_size(tiny_run, monkeypatch, tmp_path, capsys):
    from validation import metric_floor

    out = tmp_path / "floor"
    argv = ["--data", str(tiny_run / "data"), "--out", str(out), "--sizes", "24", "32",
            "--samples", "2", "--quiet"]
    calls = _counted(monkeypatch, metric_floor, "size_row", stop_at=2)
    with pytest.raises(KeyboardInterrupt):
        metric_floor.main(argv)
    assert not (out / "metric_floor.json").exists()
    metric_floor.main(argv)
    assert [args[1] for args, _ in calls] == [24, 32, 32]  # 24 px made once
    rows = json.loads((out / "metric_floor.json").read_text())["rows"]
    metric_floor.main(_with_out(argv, tmp_path / "whole"))
    once = json.loads((tmp_path / "whole" / "metric_floor.json").read_text())["rows"]
    assert [r["size"] for r in rows] == [24, 32]
    assert _same([{k: v for k, v in r.items() if k != "wall_s"} for r in rows],
                 [{k: v for k, v in r.items() if k != "wall_s"} for r in once])
    assert (out / "metric_floor.md").read_text() == \
        (tmp_path / "whole" / "metric_floor.md").read_text()
    metric_floor.main(argv)  # only gathers
    assert len(calls) == 5 and json.loads((out / "metric_floor.json").read_text())["rows"] == rows
    err = exits_2(metric_floor.main, [*argv[:-2], "3", "--quiet"], capsys)
    assert "samples: 2 there, 3 now" in err and str(out / "units") in err, err
    assert len(calls) == 5
    metric_floor.main([*argv[:-2], "3", "--quiet", "--overwrite"])
    assert len(calls) == 7
    assert {r["samples"] for r in json.loads((out / "metric_floor.json").read_text())["rows"]} \
        == {3}


def test_metric_floor_tells_apart_datasets_of_one_name(tmp_path):
    from validation.metric_floor import unit_labels
    from validation.units import unit_name

    a, b, c = tmp_path / "t1" / "ficus" / "data", tmp_path / "t2" / "ficus" / "data", \
        tmp_path / "hotdog"
    labels = unit_labels([a, b, c, a])
    assert labels[2] == "hotdog" and labels[0] == labels[3]
    assert len(set(labels)) == 3 and all(x.startswith("ficus-") for x in labels[:2])
    assert unit_name("table2", "stage-1 ficus (t1/run)", "Pixel-based (ours)") == \
        "table2-stage-1_ficus_t1_run-Pixel-based_ours"


def test_visibility_reuses_each_models_rows_and_split(tiny_run, tiny_presets, monkeypatch,
                                                      tmp_path, capsys, one_thread):
    """--models-only --factors: four Table 2 rows (one per method) and the factor split,
    each a unit; stopped in the second row."""
    import validation.visibility as vv

    out = tmp_path / "vis"
    argv = ["--out", str(out), "--quick", "--models-only", "--factors", "--factor-samples",
            "1", "--model", str(tiny_run / "run" / "geometry" / "model.ply"), "--data",
            str(tiny_run / "data"), "--quiet"]
    rows = _counted(monkeypatch, vv, "table2_result", stop_at=2)
    splits = _counted(monkeypatch, vv, "model_factors")
    with pytest.raises(KeyboardInterrupt):
        vv.main(argv)
    assert not (out / "summary.json").exists()
    vv.main(argv)
    assert [type(kw["config"]).__name__ for _, kw in rows] == [
        "VoxelConfig", "GaussianTraceConfig", "GaussianTraceConfig", "VisibilityConfig",
        "VisibilityConfig"]  # the voxel row made once
    assert len(splits) == 1
    summary = json.loads((out / "summary.json").read_text())
    vv.main(_with_out(argv, tmp_path / "whole"))
    once = json.loads((tmp_path / "whole" / "summary.json").read_text())
    scores = ("shadow_iou", "visible_iou", "accuracy", "pairs")  # not the times
    assert _same({m: {c: {k: r[k] for k in scores} for c, r in per.items()}
                  for m, per in summary["results"].items()},
                 {m: {c: {k: r[k] for k in scores} for c, r in per.items()}
                  for m, per in once["results"].items()})
    assert len(summary["results"]) == 4 and _same(summary["factors"], once["factors"])
    assert (out / "factors.md").read_text() == (tmp_path / "whole" / "factors.md").read_text()
    vv.main(argv)  # only gathers (the uninterrupted call made 4 rows and a split)
    assert len(rows) == 5 + 4 and len(splits) == 1 + 1
    assert json.loads((out / "summary.json").read_text())["results"] == summary["results"]
    err = exits_2(vv.main, [*argv, "--receiver-band", "0.5"], capsys)
    assert "receiver_band: 0.0 there, 0.5 now" in err and str(out / "units") in err, err
    # rows hold timings: on another device they are not reused
    real = vv.device_name
    monkeypatch.setattr(vv, "device_name", lambda variant: "another CPU (64 cores)")
    err = exits_2(vv.main, argv, capsys)
    assert 'device: "' in err and '"another CPU (64 cores)" now' in err, err
    monkeypatch.setattr(vv, "device_name", real)
    assert len(rows) == 9
    # --overwrite makes the call's units again; a call without --factors drops factors.md
    vv.main([*argv[:4], *argv[7:], "--receiver-band", "0.5", "--overwrite"])
    assert len(rows) == 13 and len(splits) == 2
    assert json.loads((out / "summary.json").read_text())["receiver_band"] == 0.5
    assert not (out / "factors.md").exists()


def test_shadow_factors_reuses_its_finished_parts(tiny_run, tiny_presets, monkeypatch,
                                                  tmp_path, capsys, one_thread):
    """The 2^3 factors, the exact geometry, the bias sweep and the receivers' split, each a
    unit; stopped in the exact geometry."""
    from validation import shadow_factors as sf

    out = tmp_path / "factors"
    argv = ["--run", str(tiny_run / "run"), "--data", str(tiny_run / "data"), "--out",
            str(out), "--quiet"]
    calls = {name: _counted(monkeypatch, sf, name, stop_at=1 if name == "exact_geometry"
                            else None)
             for name in ("factor_scores", "exact_geometry", "bias_sweep", "receiver_split")}
    with pytest.raises(KeyboardInterrupt):
        sf.main(argv)
    assert not (out / "shadow_factors.json").exists()
    sf.main(argv)
    assert {name: len(c) for name, c in calls.items()} == {
        "factor_scores": 1, "exact_geometry": 2, "bias_sweep": 1, "receiver_split": 1}
    res = json.loads((out / "shadow_factors.json").read_text())
    sf.main(_with_out(argv, tmp_path / "whole"))
    once = json.loads((tmp_path / "whole" / "shadow_factors.json").read_text())
    timeless = ("wall_s", "loadavg")
    assert _same({k: v for k, v in res.items() if k not in timeless},
                 {k: v for k, v in once.items() if k not in timeless})
    assert (out / "shadow_factors.md").read_text() == \
        (tmp_path / "whole" / "shadow_factors.md").read_text()
    sf.main(argv)  # only gathers
    assert sum(len(c) for c in calls.values()) == 5 + 4
    err = exits_2(sf.main, [*argv, "--exact-surfels", "600"], capsys)
    assert "exact_surfels: 20000 there, 600 now" in err and str(out / "units") in err, err


# Two fake benchmark suites; "second" SIGKILLs its process half-way when KILL_IN names it.
FAKE_SUITES = '''
import os
import signal
from pathlib import Path
from types import SimpleNamespace

RAN = []


def fake_suite(name):
    def run_suite(out, preset="paper", log=print):
        RAN.append(name)
        (Path(out) / f"{name}_raw").mkdir()
        (Path(out) / f"{name}_raw" / "case.json").write_text(f"{name} at {preset}")
        if os.environ.get("KILL_IN") == name:
            os.kill(os.getpid(), signal.SIGKILL)
        (Path(out) / f"{name}.md").write_text(f"{name} figures")
        return {"markdown": f"## {name}\\n{preset}"}
    return SimpleNamespace(run_suite=run_suite)


SUITES = {"first": fake_suite("first"), "second": fake_suite("second")}
'''


def _fake_suites(monkeypatch) -> list[str]:
    """``benchmarks.run_all`` finds the two fake suites; the names of those run."""
    from benchmarks import run_all

    fake = {}
    exec(FAKE_SUITES, fake)
    monkeypatch.setattr(run_all, "discover_suites", lambda: fake["SUITES"])
    return fake["RAN"]


def _tree(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): p.read_text() for p in folder.rglob("*")
            if p.is_file()}


def test_benchmarks_killed_in_a_suite_run_only_the_unfinished_ones(monkeypatch, tmp_path,
                                                                    capsys):
    """A SIGKILL in the second suite: the rerun reuses the first, runs the second again (its
    half-written folder gone) and writes the files of an uninterrupted run; other code exits
    2 naming the commit before any suite runs; --overwrite runs them again."""
    from benchmarks import run_all

    out = tmp_path / "bench"
    script = (FAKE_SUITES + "\nimport sys\nfrom mi_shadowgs import backend\n"
              "backend.set_variant('llvm_ad_rgb')  # the tests' (a unit records it)\n"
              "from benchmarks import run_all\nrun_all.discover_suites = lambda: SUITES\n"
              f"sys.exit(run_all.main(['--out', {str(out)!r}, '--quick']))\n")
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True,
                          text=True, timeout=300, env={**os.environ, "KILL_IN": "second"})
    assert proc.returncode == -9, proc.stderr
    assert not (out / "README.md").exists() and not (out / "machine.json").exists()
    assert any(p.name.endswith(".partial") for p in (out / "units" / "second").iterdir())
    ran = _fake_suites(monkeypatch)
    assert run_all.main(["--out", str(out), "--quick"]) == 0
    assert ran == ["second"]
    files = _tree(out)
    assert not [name for name in files if ".partial" in name]
    assert run_all.main(["--out", str(tmp_path / "whole"), "--quick"]) == 0
    assert ran == ["second", "first", "second"]
    whole = _tree(tmp_path / "whole")
    top = {name: text for name, text in files.items() if not name.startswith("units/")}
    assert set(top) == {name for name in whole if not name.startswith("units/")} == {
        ".mi_shadowgs_study.json", "README.md", "machine.json", "first.md", "second.md",
        "first_raw/case.json", "second_raw/case.json"}
    assert all(top[name] == whole[name] for name in ("first.md", "second_raw/case.json"))
    assert "## first\ncpu-small" in top["README.md"] and "## second" in top["README.md"]
    machine = json.loads(top["machine.json"])
    assert set(machine["suites"]) == {"first", "second"} and machine["preset"] == "cpu-small"
    # Only the first suite: the report and the top level hold it alone.
    assert run_all.main(["--out", str(out), "--quick", "--only", "first"]) == 0
    assert ran == ["second", "first", "second"]
    assert not (out / "second.md").exists() and (out / "first.md").is_file()
    assert "## second" not in (out / "README.md").read_text()
    # Other code (or another machine, or preset): exit 2 naming it, before any suite runs;
    # uncommitted edits count as other code, which "+changes" alone would not tell apart.
    real = run_all.uncommitted_digest
    monkeypatch.setattr(run_all, "uncommitted_digest", lambda: "ab12")
    err = exits_2(run_all.main, ["--out", str(out), "--quick"], capsys)
    assert "changes: " in err and '"ab12" now' in err, err
    monkeypatch.setattr(run_all, "uncommitted_digest", real)
    monkeypatch.setattr(run_all, "git_commit", lambda: "0123abc")
    err = exits_2(run_all.main, ["--out", str(out), "--quick"], capsys)
    assert 'commit: "' in err and '"0123abc" now' in err and str(out / "units") in err, err
    err = exits_2(run_all.main, ["--out", str(out)], capsys)
    assert 'preset: "cpu-small" there, "paper" now' in err, err
    assert ran == ["second", "first", "second"]
    assert run_all.main(["--out", str(out), "--quick", "--overwrite"]) == 0
    assert ran == ["second", "first", "second", "first", "second"]
    assert json.loads((out / "machine.json").read_text())["commit"] == "0123abc"


def test_benchmarks_refuse_a_folder_they_did_not_write(someone_elses_folder, monkeypatch,
                                                       capsys):
    from conftest import untouched

    from benchmarks import run_all

    ran = _fake_suites(monkeypatch)
    err = exits_2(run_all.main, ["--out", str(someone_elses_folder), "--quick"], capsys)
    assert "did not write" in err and not ran and untouched(someone_elses_folder)
