"""``mi-shadowgs batch`` on a local Ray runtime of 2 CPUs (one for the module).

- Three tiny captures (two datasets, one of photos: import, then run) finish with their
  figures in batch.csv; run again, they are reused.
- A capture of unreadable photos fails alone, with its error.
- A worker killed in the middle of an item is tried again; its run continues from its
  checkpoint and ends with the figures of an uninterrupted run.
- An item that asks for a GPU where there is none fails at once, saying so.
- Without Ray the command exits 2, naming the extra.
- The validation table's rows through Ray are those of a serial call.

Every command runs on one Dr.Jit thread (one CPU per item), so that runs are byte-identical
and figures compare exactly."""

from __future__ import annotations

import csv
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from mi_shadowgs import cli
from mi_shadowgs.batch import runner, spec
from mi_shadowgs.io.checkpoint import load_checkpoint
from tests import tiny_cli

ROOT = Path(__file__).resolve().parents[1]
TINY = tiny_cli.TINY
# The workers start each step through tests.tiny_cli, which knows the test-tiny preset.
LAUNCHER = tiny_cli.launcher()
TIMERS = ("relight time (s)",)  # wall-clock figures: the only ones two runs may differ in


@pytest.fixture(scope="module")
def tiny():
    """The test-tiny preset in this process (the specs are checked here) and its launcher
    for the workers."""
    with pytest.MonkeyPatch.context() as mp:
        for table, config in tiny_cli.presets():
            mp.setitem(table, TINY, config)
        mp.setattr(runner, "DEFAULT_LAUNCHER", LAUNCHER)
        yield mp


@pytest.fixture(scope="module")
def ray_local(tiny):
    ray = pytest.importorskip("ray", reason="Ray is the cluster extra (pip install .[cluster])")
    ray.init(address="local", num_cpus=2, include_dashboard=False,
             object_store_memory=runner.LOCAL_OBJECT_STORE_BYTES, logging_level=logging.ERROR,
             log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A tiny dataset, with its views also as photos (``photos/``)."""
    data = tmp_path_factory.mktemp("tiny") / "data"
    subprocess.run([sys.executable, "-m", "tests.tiny_cli", "--threads", "1", "generate",
                    "default", "--out", str(data), "--preset", TINY, "--photos",
                    "--no-progress"], cwd=ROOT, check=True, capture_output=True)
    return data


def _captures(folder: Path, dataset: Path, names) -> Path:
    for name in names:
        shutil.copytree(dataset, folder / name)
    return folder


def _photo_capture(folder: Path, dataset: Path) -> None:
    """``dataset``'s photos with their cameras as a nerfstudio capture (photos/ and
    transforms.json): imported without SfM, no ground truth."""
    from mi_shadowgs.dataset.loader import load_cameras

    frames = []
    (folder / "photos").mkdir(parents=True)
    for split in ("train", "test"):
        for i, (_, cam) in enumerate(load_cameras(dataset / f"transforms_{split}.json")):
            name = f"{split}_{i:03d}.jpg"
            shutil.copy(dataset / "photos" / name, folder / "photos" / name)
            frames.append({"file_path": f"photos/{name}", "transform_matrix": cam.c2w.tolist()})
    (fx, fy), (cx, cy) = cam.focal_xy, cam.principal_point
    (folder / "transforms.json").write_text(json.dumps(
        {"w": cam.width, "h": cam.height, "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
         "camera_model": "OPENCV", "frames": frames}))


def _table(out: Path) -> dict[str, dict]:
    with open(out / "batch.csv", newline="") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


def _figures(row: dict) -> dict:
    keys = list(row)
    return {k: row[k] for k in keys[keys.index("log") + 1:] if k not in TIMERS}


def _batch(*argv) -> tuple[int, float]:
    t0 = time.perf_counter()
    code = cli.main(["batch", *map(str, argv), "--preset", TINY, "--no-progress"])
    return code, time.perf_counter() - t0


@pytest.fixture(scope="module")
def first(ray_local, dataset, tmp_path_factory):
    """Three tiny captures through ``mi-shadowgs batch``, two datasets and one of photos:
    (spec, out, batch.csv, seconds)."""
    base = tmp_path_factory.mktemp("batch")
    captures = _captures(base / "captures", dataset, "ab")
    _photo_capture(captures / "c", dataset)
    code, seconds = _batch(captures, "--out", base / "out")
    assert code == 0, (base / "out" / "a" / "batch.log").read_text()
    return captures, base / "out", _table(base / "out"), seconds


def test_three_captures_finish_with_their_figures(first):
    _, out, table, seconds = first
    print(f"three tiny captures on 2 workers: {seconds:.1f} s")
    assert sorted(table) == ["a", "b", "c"]
    for name, row in table.items():
        assert row["status"] == "finished" and row["attempts"] == "1" and not row["error"]
        assert 50 < float(row["peak MiB"]) < 4096, row  # a whole run: Python, Mitsuba, data
        assert float(row["geometry PSNR"]) > 10, row
        assert row["report"] == f"{name}/run/report.html" and (out / row["report"]).is_file()
    # one dataset twice, on one thread each: the same figures
    assert float(table["a"]["albedo PSNR"]) > 10 and _figures(table["a"]) == _figures(table["b"])
    # the photos were imported first; without ground truth, the decomposition has no figures
    assert (out / "c" / "data" / "import.json").is_file() and table["c"]["albedo PSNR"] == ""
    page = (out / "batch.html").read_text()
    assert '<a href="a/run/report.html">a</a>' in page and "3 finished" in page


def test_run_again_reuses_them_and_a_capture_of_unreadable_photos_fails_alone(first):
    captures, out, table, seconds = first
    bad = captures / "bad"
    bad.mkdir()
    for i in range(3):
        (bad / f"p{i}.jpg").write_bytes(b"not a photo")
    try:
        code, again = _batch(captures, "--out", out)
    finally:
        shutil.rmtree(bad)
    print(f"run again (three reused, one failing): {again:.1f} s, first call {seconds:.1f} s")
    assert code == 1
    rows = _table(out)
    assert rows["bad"]["status"] == "failed" and not rows["bad"]["report"]
    assert "p0.jpg: unreadable image" in rows["bad"]["error"], rows["bad"]
    assert rows["bad"]["error"].startswith("import: ")
    for name in "abc":
        assert rows[name]["status"] == "reused", rows[name]
        assert _figures(rows[name]) == _figures(table[name])
        assert float(rows[name]["seconds"]) < float(table[name]["seconds"])


def _children_running(run: Path) -> list[int]:
    """PIDs of the processes whose command line names ``run``."""
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                if str(run) in (proc / "cmdline").read_bytes().decode(errors="replace"):
                    pids.append(int(proc.name))
            except OSError:
                continue
    return pids


def _parent(pid: int) -> int:
    return int((Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[1])


def test_a_killed_worker_is_tried_again_and_its_run_continues(first, dataset, tmp_path):
    _, _, table, _ = first
    out = tmp_path / "out"
    items = spec.read_spec(_captures(tmp_path / "captures", dataset, ["d"]), out,
                           {"preset": TINY})
    rows = []
    thread = threading.Thread(target=lambda: rows.extend(
        runner.run_batch(items, out, progress=False)))
    thread.start()
    run = out / "d" / "run"
    ckpt = run / "geometry" / "checkpoint"
    end = time.monotonic() + 120
    # stage 1 has saved a checkpoint past its first log row
    while not (ckpt / "checkpoint.npz").is_file() or load_checkpoint(ckpt)[1]["step"] < 10:
        assert time.monotonic() < end and thread.is_alive(), "no checkpoint was written"
        time.sleep(0.02)
    (child,) = _children_running(run)
    worker = _parent(child)
    assert "ray" in (Path("/proc") / str(worker) / "cmdline").read_text().lower()
    os.kill(worker, signal.SIGKILL)
    while _children_running(run):  # the step dies with its worker
        assert time.monotonic() < end, "the step outlived its worker"
        time.sleep(0.02)
    assert not (run / "geometry" / "model.ply").exists(), "killed after stage 1"
    step = load_checkpoint(ckpt)[1]["step"]
    before = [r for r in (run / "geometry" / "log.csv").read_text().splitlines()[1:]
              if int(r.split(",")[0]) <= step]
    thread.join(timeout=300)
    assert not thread.is_alive()
    (row,) = rows
    assert row["status"] == "finished" and row["attempts"] == 2, row
    # continued, not started over: the log's rows up to the checkpoint (with their times)
    # are the first attempt's
    log = (run / "geometry" / "log.csv").read_text().splitlines()[1:]
    assert before and log[:len(before)] == before
    assert _figures(_table(out)["d"]) == _figures(table["a"])


def test_an_item_asking_for_a_gpu_where_there_is_none_fails_at_once(ray_local, dataset,
                                                                     tmp_path, capsys):
    if ray_local.cluster_resources().get("GPU"):
        pytest.skip("this machine has a GPU: the request can be met")
    captures = _captures(tmp_path / "captures", dataset, ["g"])
    t0 = time.perf_counter()
    assert cli.main(["--variant", "cuda_ad_rgb", "batch", str(captures), "--out",
                     str(tmp_path / "out"), "--preset", TINY, "--no-progress"]) == 1
    assert time.perf_counter() - t0 < 10
    row = _table(tmp_path / "out")["g"]
    assert row["status"] == "failed" and "asks for a GPU (variant cuda_ad_rgb)" in row["error"]
    assert "has none" in row["error"] and "llvm_ad_rgb" in row["error"]
    assert "g: asks for a GPU" in capsys.readouterr().out


def test_resources_of_an_item(tmp_path, tiny, dataset):
    """A cuda_ad_rgb item asks Ray for a GPU and passes the variant on; its CPUs are its
    commands' Dr.Jit threads; a node too small for it is named."""
    (item,) = spec.read_spec(_captures(tmp_path / "c", dataset, ["x"]), tmp_path / "out",
                             {"preset": TINY, "variant": "cuda_ad_rgb", "cpus": 4})
    assert (item.gpus, item.cpus) == (1, 4)
    assert item.steps[-1].args[:4] == ("--threads", "4", "--variant", "cuda_ad_rgb")
    where = "the Ray cluster at HOST"
    assert "has none" in runner.unschedulable(item, {"CPU": 16, "GPU": 0}, where)
    assert runner.unschedulable(item, {"CPU": 16, "GPU": 1}, where) is None
    assert "largest node of the Ray cluster at HOST has 2" in runner.unschedulable(
        item, {"CPU": 2, "GPU": 8}, where)


def test_without_ray_batch_exits_2_naming_the_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails as when not installed
    (tmp_path / "captures" / "x").mkdir(parents=True)
    assert cli.main(["batch", str(tmp_path / "captures"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "not installed" in err and "pip install 'mi_shadowgs[cluster]'" in err
    assert not (tmp_path / "out").exists()


def test_a_spec_file_is_checked_before_anything_runs(tmp_path, tiny, dataset):
    captures = _captures(tmp_path / "c", dataset, ["x"])
    (tmp_path / "c" / "photos").mkdir()
    for i in range(3):
        (tmp_path / "c" / "photos" / f"p{i}.png").write_bytes(b"")
    good = tmp_path / "good.toml"
    good.write_text('preset = "test-tiny"\nset = ["material.iterations=30"]\n'
                    '[[items]]\nsource = "c/x"\nseed = 2\nset = ["material.iterations=40"]\n'
                    '[[items]]\nname = "p"\nsource = "c/photos"\ncpus = 2\n')
    x, p = spec.read_spec(good, tmp_path / "out")
    assert x.name == "x" and [s.name for s in x.steps] == ["run"]
    assert x.steps[0].args[-6:] == ("--set", "material.iterations=30", "--set",
                                    "material.iterations=40", "--seed", "2")
    assert [s.name for s in p.steps] == ["import", "run"] and p.cpus == 2
    assert p.steps[0].creates == "data"
    assert p.steps[0].inputs == (str((captures / "photos").resolve()),)
    assert p.steps[1].args[3] == str((tmp_path / "out" / "p" / "data").resolve())
    bad = tmp_path / "bad.json"
    for text, message in (
            ({"items": [{"source": "c/x", "set": ["material.iterationz=3"]}]},
             "item x: --set material.iterationz: unknown material setting"),
            ({"items": [{"source": "c/x"}, {"source": "c/x"}]}, "two items are named 'x'"),
            ({"items": [{"source": "c/x", "colour": 1}]}, "unknown key(s) ['colour']"),
            ({"items": [{"source": "c/nothing"}]}, "c/nothing: not found"),
            ({"preset": "cpu-huge", "items": [{"source": "c/x"}]}, "unknown preset"),
            ({"items": []}, "non-empty list 'items'")):
        bad.write_text(json.dumps(text))
        with pytest.raises(spec.SpecError, match=re.escape(message)):
            spec.read_spec(bad, tmp_path / "out")


def test_a_changed_photo_folder_is_not_reused(tmp_path):
    """An import's dataset stands only for the photos it was made from."""
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "p0.jpg").write_bytes(b"one")
    step = spec.Step("import", "mi_shadowgs.cli", ("--threads", "1", "import", str(photos)),
                     creates="data", inputs=(str(photos),))
    folder = tmp_path / "item"
    folder.mkdir()
    assert not runner._made_before(step, folder)  # new: it runs (and its key is recorded)
    (folder / "data").mkdir()
    assert runner._made_before(step, folder)  # made from the same photos: skipped
    moved = spec.Step("import", "mi_shadowgs.cli", ("--threads", "4", "import", str(photos)),
                      creates="data", inputs=(str(photos),))
    assert runner._made_before(moved, folder)  # another thread count makes the same
    (photos / "p0.jpg").write_bytes(b"two")
    with pytest.raises(ValueError, match="made from other inputs or arguments"):
        runner._made_before(step, folder)


def test_an_address_where_nothing_answers_exits_2_at_once(tmp_path, tiny, dataset, capsys):
    pytest.importorskip("ray", reason="Ray is the cluster extra (pip install .[cluster])")
    import socket

    with socket.socket() as s:  # a port of this machine that no one listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    captures = _captures(tmp_path / "c", dataset, ["x"])
    t0 = time.perf_counter()
    assert cli.main(["batch", str(captures), "--out", str(tmp_path / "out"), "--address",
                     f"127.0.0.1:{port}", "--preset", TINY]) == 2
    assert time.perf_counter() - t0 < 10
    err = capsys.readouterr().err
    assert f"--address 127.0.0.1:{port}: nothing answers there" in err and "ray start" in err


def test_a_folder_that_is_not_a_batch_is_refused(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(runner.BatchError, match="holds files that no batch wrote"):
        runner.claim_batch_folder(tmp_path / "mine", "spec", [])


def _rows_without_timers(path: Path) -> list[dict]:
    def strip(value):
        if isinstance(value, dict):
            return {k: strip(v) for k, v in value.items()
                    if not k.endswith("_s") and k not in ("report", "load_end")}
        return value

    return [strip(r) for r in json.loads(path.read_text())]


@pytest.mark.filterwarnings("ignore:Mean of empty slice", "ignore:All-NaN slice")
def test_validation_rows_through_ray_are_those_of_a_serial_call(ray_local, tmp_path,
                                                                monkeypatch):
    from validation import claim_out
    from validation import pipeline as vpipe

    args = ["--scene", "default", "--lights", "low", "--preset", TINY, "--threads", "1"]
    serial = subprocess.Popen([sys.executable, "-m", "tests.tiny_cli", "--threads", "1", "-m",
                               "validation.pipeline", "--out", str(tmp_path / "serial"),
                               *args], cwd=ROOT, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
    monkeypatch.setattr(vpipe, "TABLE_PRESETS", (*vpipe.TABLE_PRESETS, TINY))
    claim_out(tmp_path / "ray", "validation.pipeline")  # as main does
    res = vpipe.run(tmp_path / "ray", scenes=["default"], lights=["low"], preset=TINY,
                    address="local", threads=1)
    assert res["failed"] == [] and len(res["rows"]) == 1
    assert serial.wait(timeout=300) == 0, serial.stderr.read()
    assert (_rows_without_timers(tmp_path / "ray" / "pipeline.json")
            == _rows_without_timers(tmp_path / "serial" / "pipeline.json"))
    assert _table(tmp_path / "ray")["default-low"]["status"] == "finished"
    # run again: the finished row stands as recorded, without a task
    again = vpipe.run(tmp_path / "ray", scenes=["default"], lights=["low"], preset=TINY,
                      address="local", threads=1)
    assert again["rows"] == res["rows"]
    assert _table(tmp_path / "ray")["default-low"]["status"] == "reused"


def test_validation_rows_as_items(tmp_path, monkeypatch):
    """Each row is one item of --threads CPUs (a GPU under cuda_ad_rgb), done once its
    row.json is there; a later seed's row waits for the row that makes its dataset."""
    from validation import pipeline as vpipe

    monkeypatch.setenv("MI_SHADOWGS_VARIANT", "cuda_ad_rgb")  # after the import: the rows'
    items = vpipe.batch_items(tmp_path, [("default", "tuned"), ("bunny", "low")], [0, 2],
                              "cpu-small", "sky", True, 2)
    assert [i.name for i in items] == ["default-tuned", "bunny-low", "default-tuned-seed2",
                                       "bunny-low-seed2"]
    assert [i.after for i in items] == [(), (), ("default-tuned",), ("bunny-low",)]
    first, last = items[0], items[-1]
    assert (first.cpus, first.gpus, first.done) == (2, 1, "default-tuned/row.json")
    assert ("MI_SHADOWGS_VARIANT", "cuda_ad_rgb") in first.env
    (step,) = last.steps
    assert step.module == "validation.pipeline" and "--rows-only" in step.args
    assert step.args[step.args.index("--seed") + 1] == "2"
    assert step.args[step.args.index("--out") + 1] == str(tmp_path.resolve())


def test_the_error_line_of_a_failed_command():
    text = "warning: few views\nTraceback ...\nmi-shadowgs run: error: DATA: not found\n"
    assert runner.error_line(text, "run", 2) == "run: mi-shadowgs run: error: DATA: not found"
    crash = runner.error_line("step 1\rstep 2\nSegmentation fault\n", "run", -11)
    assert crash == "run: Segmentation fault"
    assert runner.error_line("", "import", 1) == "import: exit status 1, no message"
