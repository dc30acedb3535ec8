"""One writer per output folder; the output path's OS faults and the backend's environment
named in one line (docs/robustness.md, "Output folders and the machine")."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mi_shadowgs import cli
from mi_shadowgs.io import outlock

ROOT = Path(__file__).resolve().parents[1]


def _cli(*argv) -> list[str]:
    return [sys.executable, "-m", "tests.tiny_cli", "--threads", "1", *argv, "--no-progress"]


def _wait_for(path: Path, seconds: float = 120.0) -> None:
    end = time.monotonic() + seconds
    while not path.exists():
        assert time.monotonic() < end, f"{path} never appeared"
        time.sleep(0.05)


@pytest.fixture(scope="module")
def holder(tmp_path_factory):
    """(folder, pid): another process holding the lock of ``folder`` until the module ends."""
    folder = tmp_path_factory.mktemp("locked") / "out"
    code = ("import sys, time\n"
            "from mi_shadowgs.io.outlock import output_lock\n"
            "with output_lock(sys.argv[1], 'train'):\n"
            "    print('held', flush=True)\n"
            "    time.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(folder)], cwd=ROOT,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    yield folder, proc.pid
    proc.kill()
    proc.wait()


# Each command's arguments with its output folder as OUT; the inputs need not exist: the
# lock is taken before anything is read.
COMMANDS = {
    "train": ["train", "nodata", "--out", "OUT", "--resume"],
    "run": ["run", "nodata", "--out", "OUT"],
    "relight": ["relight", "norun", "--out", "OUT", "--light", "0,45,3"],
    "render": ["render", "nomodel.ply", "--cameras", "nocams.json", "--out", "OUT"],
    "export": ["export", "norun", "--format", "3dgs-ply", "--out", "OUT"],
    "import": ["import", "nophotos", "--out", "OUT"],
    "generate": ["generate", "--out", "OUT", "--preset", "cpu-small"],
    "segment": ["segment", "norun", "--data", "nodata", "--out", "OUT"],
    "report": ["report", "OUT"],
    "batch": ["batch", "nocaptures", "--out", "OUT"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_second_writer_into_a_locked_folder_exits_2_naming_the_holder(command, holder,
                                                                        capsys):
    folder, pid = holder
    argv = [str(folder) if a == "OUT" else a for a in COMMANDS[command]]
    start = time.monotonic()
    assert cli.main(argv) == 2
    assert time.monotonic() - start < 1.0
    err = capsys.readouterr().err
    assert f"{folder}: process {pid} (mi-shadowgs train) is writing there now" in err, err
    assert "Traceback" not in err
    assert outlock.lock_file(folder).exists()  # the holder's lock is left alone


def test_a_killed_commands_lock_is_taken_over_and_removed_after(tmp_path, capsys):
    folder = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()  # a pid that has ended
    lock = outlock.lock_file(folder)
    lock.write_text(f"{proc.pid} train\n")
    with outlock.output_lock(folder, "train", note=print):
        assert lock.read_text().split()[0] == str(os.getpid())
    assert f"took over the lock of process {proc.pid}" in capsys.readouterr().out
    assert not lock.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing left beside the folder


def test_two_names_of_one_folder_share_its_lock(tmp_path):
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    with outlock.output_lock(tmp_path / "real", "run"):
        with pytest.raises(outlock.FolderBusyError, match=f"process {os.getpid()}"):
            with outlock.output_lock(tmp_path / "link", "run"):
                pass


def _startup() -> float:
    """Seconds that ``train --help`` takes: starting Python, Mitsuba and the CLI."""
    start = time.monotonic()
    subprocess.run(_cli("train", "--help"), cwd=ROOT, check=True, capture_output=True)
    return time.monotonic() - start


def test_train_then_resume_while_it_runs(tmp_path):
    """The acceptance case: the second (``--resume``) exits 2 within a second of starting
    its work, naming the first's PID; the first finishes its model unharmed."""
    data, run = tmp_path / "data", tmp_path / "run"
    subprocess.run(_cli("generate", "default", "--out", str(data), "--preset", "test-tiny"),
                   cwd=ROOT, check=True, capture_output=True)
    train = ["train", str(data), "--out", str(run), "--preset", "test-tiny", "--iterations",
             "400"]
    first = subprocess.Popen(_cli(*train), cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    _wait_for(outlock.lock_file(run))
    before = _startup()
    start = time.monotonic()
    second = subprocess.run(_cli(*train, "--resume"), cwd=ROOT, capture_output=True, text=True)
    elapsed = time.monotonic() - start
    assert first.poll() is None, "the first train ended before the second started"
    # starting Python and Mitsuba on this load, the slower of just before and just after
    startup = max(before, _startup())
    assert second.returncode == 2, second.stderr
    assert f"process {first.pid} (mi-shadowgs train) is writing there now" in second.stderr
    assert elapsed < startup + 1.0, (elapsed, startup)
    out, err = first.communicate(timeout=600)
    assert first.returncode == 0, err
    assert (run / "geometry" / "model.ply").is_file()
    steps = [int(line.split(",")[0]) for line in
             (run / "geometry" / "log.csv").read_text().splitlines()[1:]]
    assert steps == sorted(steps) and len(steps) == len(set(steps))
    assert not outlock.lock_file(run).exists()


# -- the output path's OS faults ---------------------------------------------------------------
def test_a_read_only_output_exits_2_before_any_work(tmp_path, monkeypatch, capsys):
    real_access = os.access

    class ReadOnly:
        f_flag = os.ST_RDONLY

    monkeypatch.setattr(os, "access", lambda p, mode: False if str(p).startswith(
        str(tmp_path)) else real_access(p, mode))
    monkeypatch.setattr(os, "statvfs", lambda p: ReadOnly())
    assert cli.main(["render", "nomodel.ply", "--cameras", "c.json", "--out",
                     str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'out'}: cannot be written (a read-only file system)" in err, err
    assert list(tmp_path.iterdir()) == []


def test_a_nearly_full_disk_and_a_long_name_exit_2_before_any_work(tmp_path, monkeypatch,
                                                                   capsys):
    long_name = tmp_path / ("x" * 300)
    assert cli.main(["render", "m.ply", "--cameras", "c.json", "--out", str(long_name)]) == 2
    assert "the name is too long (300 bytes; this file system allows 255)" in \
        capsys.readouterr().err
    monkeypatch.setattr(outlock.shutil, "disk_usage",
                        lambda p: type("U", (), {"free": 10 * 2**20})())
    assert cli.main(["render", "m.ply", "--cameras", "c.json", "--out",
                     str(tmp_path / "out")]) == 2
    assert "only 10 MiB free on its file system; at least 64 MiB" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_disk_filling_up_mid_train_is_named_and_resumable(tmp_path, tiny_presets,
                                                            monkeypatch, capsys):
    from mi_shadowgs.io import checkpoint
    from mi_shadowgs.scenes import scene_path

    data, run = tmp_path / "data", tmp_path / "run"
    assert cli.main(["generate", str(scene_path("default")), "--out", str(data), "--preset",
                     "test-tiny", "--no-progress"]) == 0
    real, calls = checkpoint.save_checkpoint, []

    def full(directory, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(directory, *args, **kwargs)

    monkeypatch.setattr(checkpoint, "save_checkpoint", full)
    train = ["train", str(data), "--out", str(run), "--preset", "test-tiny", "--no-eval",
             "--no-progress"]
    capsys.readouterr()
    assert cli.main(train) == 2
    err = capsys.readouterr().err
    assert f"error: {run}: No space left on device; the work so far is kept: free some " \
        "space and run it again with --resume to continue" in err, err
    monkeypatch.setattr(checkpoint, "save_checkpoint", real)
    assert cli.main([*train, "--resume"]) == 0
    assert (run / "geometry" / "model.ply").is_file()


def test_describe_os_error_names_the_file_or_the_folder():
    exc = OSError(errno.EROFS, "Read-only file system", "/x/run/log.csv")
    assert outlock.describe_os_error(exc, "/x/run", "again") == \
        "/x/run/log.csv: Read-only file system"
    assert outlock.describe_os_error(OSError(errno.ENAMETOOLONG, "File name too long"),
                                     "/x/run", "again") == "/x/run: File name too long"
    assert outlock.describe_os_error(OSError(errno.ECONNRESET, "reset"), "/x", "again") is None


# -- the backend's environment -----------------------------------------------------------------
@pytest.mark.parametrize("value", ["bogus", "scalar_rgb", "cuda_ad_rgb"])
def test_a_bad_variant_in_the_environment_is_named_and_overridden(value, tmp_path):
    from conftest import CUDA_AVAILABLE

    if value == "cuda_ad_rgb" and CUDA_AVAILABLE:
        pytest.skip("cuda_ad_rgb runs on this machine")
    env = {**os.environ, "MI_SHADOWGS_VARIANT": value}
    help_ = subprocess.run([sys.executable, "-m", "mi_shadowgs.cli", "--help"], cwd=ROOT,
                           env=env, capture_output=True, text=True)
    assert help_.returncode == 0 and "usage: mi-shadowgs" in help_.stdout, help_.stderr
    argv = ["render", "nomodel.ply", "--cameras", "c.json", "--out", str(tmp_path / "o")]
    bad = subprocess.run([sys.executable, "-m", "mi_shadowgs.cli", *argv], cwd=ROOT, env=env,
                         capture_output=True, text=True)
    assert bad.returncode == 2, bad.stderr
    assert f"MI_SHADOWGS_VARIANT={value}: " in bad.stderr
    assert "Traceback" not in bad.stderr
    over = subprocess.run([sys.executable, "-m", "mi_shadowgs.cli", "--variant", "llvm_ad_rgb",
                           *argv], cwd=ROOT, env=env, capture_output=True, text=True)
    assert over.returncode == 2 and "model file not found: nomodel.ply" in over.stderr, \
        over.stderr
