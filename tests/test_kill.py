"""Kill at any moment: ``generate``, ``train`` and ``run`` are SIGKILLed at
random (seeded) moments in a subprocess, rerun to completion, and must leave the files of an
unkilled run.

Dr.Jit's LLVM backend adds float atomics (the rasterizer's gradient scatters) in an order
that depends on thread scheduling: two unkilled runs on 2 threads differ in the last bits
(stage 2 features by ~1e-6, measured on this dataset) and stage 4's pruning turns that into
a different number of lights. On one thread every command is bit-deterministic across
processes, so the commands here run with ``--threads 1`` and every file must be
byte-identical, except wall-clock figures: ``log.csv``'s time column, JSON fields holding
seconds or the date, the elapsed time inside checkpoints, ``summary.json``'s stages that an
earlier call made, and ``report.html`` (which shows those; ``summary.json`` behind it is
compared).
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mi_shadowgs.io.checkpoint import CHECKPOINT_NAME, load_checkpoint

pytestmark = pytest.mark.kill
ROOT = Path(__file__).resolve().parents[1]
KILLS = {"generate": 3, "train": 3, "run": 4}  # 10 in all, chained per command
GENERATE = ["--preset", "test-tiny", "--width", "48", "--height", "48", "--spp", "256",
            "--n-train", "16", "--n-test", "4"]  # ~2.5 s: long enough to be cut in the middle


def _cli(*argv) -> list[str]:
    return [sys.executable, "-m", "tests.tiny_cli", "--threads", "1", *argv, "--no-progress"]


def _run(argv: list[str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return time.perf_counter() - t0


def _kill_at(argv: list[str], seconds: float) -> float | None:
    """Start ``argv``, SIGKILL it after ``seconds``: None, or the seconds it took when it
    finished before."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        proc.wait(timeout=seconds)
        return time.perf_counter() - t0
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        return None


# -- comparing output folders ---------------------------------------------------------------
def _timeless(obj):
    """A JSON value without its wall-clock fields (seconds, dates, elapsed times) and the
    stages a call found made by an earlier one (a rerun after a kill reuses those)."""
    if isinstance(obj, dict):
        if "columns" in obj and all(isinstance(r, list) for r in obj.get("rows", [{}])):
            # a table of summary.json: without its time columns
            keep = [i for i, c in enumerate(obj["columns"]) if not str(c).endswith("(s)")]
            obj = {**obj, "columns": [obj["columns"][i] for i in keep],
                   "rows": [[r[i] for i in keep] for r in obj["rows"]]}
        return {k: _timeless(v) for k, v in obj.items()
                if not (k in ("time", "date", "seconds", "total_seconds", "elapsed", "timings",
                              "reused_stages")
                        or k.endswith("_s") or k.startswith("seconds_"))}
    if isinstance(obj, list):
        return [_timeless(v) for v in obj]
    return obj


def _content(path: Path):
    """What must match between a killed-and-rerun output and an unkilled one."""
    if path.name == "report.html":
        return None
    if path.suffix == ".json":
        return _timeless(json.loads(path.read_text()))
    if path.name == "log.csv":
        rows = list(csv.DictReader(io.StringIO(path.read_text())))
        return [{k: v for k, v in r.items() if k != "time"} for r in rows]
    if path.name == CHECKPOINT_NAME:
        arrays, meta = load_checkpoint(path.parent)
        if "scalars" in arrays:  # stage 1: [step, t, extent, elapsed, log count]
            arrays["scalars"] = np.delete(arrays["scalars"], 3)
        return {k: (a.dtype.str, a.shape, a.tobytes()) for k, a in arrays.items()}, \
            _timeless(meta)
    return path.read_bytes()


def _compare(got: Path, ref: Path) -> None:
    files = sorted(p.relative_to(ref).as_posix() for p in ref.rglob("*") if p.is_file())
    assert sorted(p.relative_to(got).as_posix() for p in got.rglob("*") if p.is_file()) \
        == files
    differ = [f for f in files if _content(got / f) != _content(ref / f)]
    assert differ == []


def _siblings(out: Path) -> list[Path]:
    """``out`` and whatever a killed write left beside it."""
    return list(out.parent.glob(f"*{out.name}*"))


def _save_siblings(out: Path, snapshot: Path) -> None:
    shutil.rmtree(snapshot, ignore_errors=True)
    snapshot.mkdir()
    for p in _siblings(out):
        _copy(p, snapshot / p.name)


def _restore_siblings(snapshot: Path, out: Path) -> None:
    for p in _siblings(out):
        if p.is_dir():
            shutil.rmtree(p)
        else:
            p.unlink()
    for p in snapshot.iterdir():
        _copy(p, out.parent / p.name)


def _copy(src: Path, dst: Path) -> None:
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        shutil.copy2(src, dst)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    root = tmp_path_factory.mktemp("kill")
    _run(_cli("generate", "default", "--out", str(root / "data"), "--preset", "test-tiny"))
    return root


@pytest.mark.parametrize("command", list(KILLS))
def test_a_killed_command_rerun_ends_as_an_unkilled_one(command, work):
    """The kills come one after another on the same output: each run after the first
    continues what the kills before left (a checkpoint, a partial file, a stage without
    its successor), so the one comparison at the end checks every kill's recovery, and
    recoveries from recoveries. The kills are drawn as moments of the unkilled run; each
    rerun is killed after the time a rerun takes to start plus the gap to the next moment,
    so it lands at or before that moment (less the work redone since its checkpoint). A run
    that finishes before its kill is put back as it was and cut at three quarters of the
    time it took, so the count of kills does not hang on the machine's load."""
    data, out, ref = work / "data", work / command / "out", work / command / "ref"
    argv = {"generate": _cli("generate", "default", "--out", str(out), *GENERATE),
            "train": _cli("train", str(data), "--out", str(out), "--preset", "test-tiny"),
            "run": _cli("run", str(data), "--out", str(out), "--preset", "test-tiny")}[command]
    again = argv + (["--resume"] if command == "train" else [])
    out.parent.mkdir()
    # The same folder for the reference and the killed runs: the outputs hold its path.
    seconds = _run(argv)
    startup = _run(again)  # a finished command's rerun: the time a rerun takes to start
    out.rename(ref)
    rng = np.random.default_rng(sorted(KILLS).index(command))
    work_seconds = max(seconds - startup, seconds / 2)  # the part past the start
    moments = np.sort(rng.uniform(0.1, 0.95, KILLS[command])) * work_seconds
    snapshot = out.parent / "before-this-kill"
    killed = 0
    for gap in np.diff(moments, prepend=0.0):
        _save_siblings(out, snapshot)
        wait = startup + gap
        while (took := _kill_at(again if killed else argv, wait)) is not None:
            # A run quicker than the timings above (a busy machine's startup, measured
            # once, can overstate a rerun's): back to where it started, and cut it sooner.
            _restore_siblings(snapshot, out)
            wait = 0.75 * min(wait, took)
        killed += 1
    _run(again)
    _compare(out, ref)
