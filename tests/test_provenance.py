"""Output manifests, dataset fingerprints, atomic writes and image read errors: the library
under every command's "runs never mix, outputs never destroy" guarantees."""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from mi_shadowgs.dataset import fingerprint
from mi_shadowgs.io import atomic, provenance
from mi_shadowgs.io.images import ImageReadError, read_exr, read_png, write_exr, write_png


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    try:
        yield
    finally:
        os.umask(old)


def test_outputs_honour_the_umask(tmp_path, umask_027):
    atomic.write_text(tmp_path / "a.txt", "x")
    with atomic.atomic_dir(tmp_path / "d") as d:
        (d / "f").write_text("y")
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o640
    assert (tmp_path / "d").stat().st_mode & 0o777 == 0o750
    os.umask(0o002)
    atomic.write_text(tmp_path / "b.txt", "x")
    assert (tmp_path / "b.txt").stat().st_mode & 0o777 == 0o664


def test_next_write_removes_stale_temporaries_of_the_same_output_only(tmp_path):
    stale = [tmp_path / ".out.json.k1lled_0.tmp.json", tmp_path / ".data.abcd1234.partial"]
    kept = [tmp_path / ".out.json.short.tmp.json",  # not tempfile's 8 characters
            tmp_path / ".other.json.k1lled_0.tmp.json",  # another output's
            tmp_path / ".data.x.abcd1234.partial"]  # output "data.x"'s
    for p in stale[:1] + kept[:2]:
        p.write_text("half")
    for p in stale[1:] + kept[2:]:
        p.mkdir()
    atomic.write_json(tmp_path / "out.json", {"a": 1})
    with atomic.atomic_dir(tmp_path / "data") as d:
        (d / "f").write_text("y")
    assert not any(p.exists() for p in stale)
    assert all(p.exists() for p in kept)
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == \
        ["data", "out.json"]


def _ended_pid() -> int:
    """The pid of a process that has ended (and been reaped)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_a_temporary_is_stale_only_once_its_writer_has_ended(tmp_path, monkeypatch):
    """Processes that share an output folder (the pipeline's rows, each writing the table)
    must not remove each other's writes in flight; a killed writer's are removed."""
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        ended = _ended_pid()
        stale = [tmp_path / f".out.json.{ended}-abcd1234.tmp.json",  # its writer ended
                 tmp_path / f".out.json.{os.getpid()}-abcd1234.tmp.json",  # ours, not in flight
                 tmp_path / f".data.{ended}-abcd1234.partial"]
        kept = [tmp_path / f".out.json.{live.pid}-abcd1234.tmp.json",  # a live writer's
                tmp_path / f".data.{live.pid}-abcd1234.partial"]
        for p in stale + kept:
            p.mkdir() if p.suffix == ".partial" else p.write_text("half")
        with atomic.atomic_path(tmp_path / "out.json") as tmp:
            # this write's own temporary is named by this process and survives a scan
            assert tmp.name.startswith(f".out.json.{os.getpid()}-")
            atomic.remove_stale(tmp_path / "out.json")
            monkeypatch.chdir(tmp_path)
            atomic.remove_stale("out.json")  # the same output, named relatively
            tmp.write_text("{}")
        with atomic.atomic_dir(tmp_path / "data") as d:
            (d / "f").write_text("y")
        assert not any(p.exists() for p in stale)
        assert all(p.exists() for p in kept)
    finally:
        live.kill()
        live.wait()
    atomic.write_json(tmp_path / "out.json", {"a": 2})  # its writer gone, the rest is stale
    assert not any(p.exists() for p in kept[:1])


def _write_many(path: str, n: int) -> None:
    for i in range(n):
        atomic.write_json(path, {"i": i, "pid": os.getpid()})


def test_concurrent_writers_of_one_output_do_not_fail(tmp_path):
    """A table's rows sharing one folder, each writing pipeline.json at its end: none may
    fail because another's write removed its temporary as stale."""
    target = str(tmp_path / "table.json")
    ctx = multiprocessing.get_context("spawn")
    workers = [ctx.Process(target=_write_many, args=(target, 300)) for _ in range(3)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(120)
    assert [w.exitcode for w in workers] == [0, 0, 0]
    assert json.loads((tmp_path / "table.json").read_text())["i"] == 299
    assert [p.name for p in tmp_path.iterdir()] == ["table.json"]


def test_atomic_dir_puts_back_a_folder_a_kill_left_aside(tmp_path):
    # Killed between "move the old folder aside" and "move the new one in".
    old = tmp_path / ".data.old"
    old.mkdir()
    (old / "f").write_text("old")
    with pytest.raises(RuntimeError), atomic.atomic_dir(tmp_path / "data", overwrite=True):
        raise RuntimeError("fails before the swap")
    assert (tmp_path / "data" / "f").read_text() == "old" and not old.exists()


def _corrupt_files(tmp_path):
    write_png(tmp_path / "ok.png", np.full((8, 8, 3), 0.5))
    write_exr(tmp_path / "ok.exr", np.full((8, 8, 3), 0.5))
    png, exr = (tmp_path / "ok.png").read_bytes(), (tmp_path / "ok.exr").read_bytes()
    (tmp_path / "cut.png").write_bytes(png[:len(png) // 2])
    (tmp_path / "text.png").write_bytes(b"not an image at all")
    (tmp_path / "cut.exr").write_bytes(exr[:len(exr) // 2])
    (tmp_path / "text.exr").write_bytes(b"not an image at all")


@pytest.mark.parametrize("name", ["cut.png", "text.png", "cut.exr", "text.exr"])
def test_a_corrupt_image_gives_one_line_naming_the_file(tmp_path, capfd, name):
    _corrupt_files(tmp_path)
    read = read_png if name.endswith(".png") else read_exr
    with pytest.raises(ImageReadError) as info:
        read(tmp_path / name)
    msg = str(info.value)
    assert msg.startswith(f"{tmp_path / name}: ") and "\n" not in msg
    assert "pip install" not in msg and "plugin" not in msg
    out, err = capfd.readouterr()
    assert out == "" and err == ""  # OpenEXR's own diagnostics do not reach the terminal
    assert read(tmp_path / ("ok" + name[-4:])).shape == (8, 8, 3)  # and reading still works


def _dataset(root):
    (root / "train").mkdir(parents=True)
    (root / "transforms_train.json").write_text(json.dumps({"frames": []}))
    for i in range(3):
        (root / "train" / f"r_{i}.png").write_bytes(bytes([i]) * 1000)
    return root


def test_dataset_fingerprint_follows_contents_not_times_or_hidden_files(tmp_path):
    a = _dataset(tmp_path / "a")
    fp = fingerprint.dataset_fingerprint(a)
    b = tmp_path / "b"
    shutil.copytree(a, b)  # another path, other times, same contents
    assert fingerprint.dataset_fingerprint(b) == fp
    os.utime(b / "train" / "r_0.png", (1, 1))
    (b / ".mi_shadowgs_manifest.json").write_text("{}")
    (b / "notes.txt").write_text("not a dataset file")
    (b / "manifest.json").write_text("{}")  # a writer's list of files, not the loader's
    assert fingerprint.dataset_fingerprint(b) == fp
    (b / "train" / "r_1.png").write_bytes(bytes([1]) * 999 + b"\x07")  # one byte, same size
    assert fingerprint.dataset_fingerprint(b) != fp
    (b / "train" / "r_1.png").write_bytes(bytes([1]) * 1000)
    assert fingerprint.dataset_fingerprint(b) == fp
    (b / "train" / "r_1.png").rename(b / "train" / "r_9.png")
    assert fingerprint.dataset_fingerprint(b) != fp
    (b / "train" / "r_9.png").rename(b / "train" / "r_1.png")
    (b / "transforms_train.json").write_text(json.dumps({"frames": [None]}))
    assert fingerprint.dataset_fingerprint(b) != fp


def test_dataset_fingerprint_reads_each_file_once_per_process(tmp_path, monkeypatch):
    a = _dataset(tmp_path / "a")
    fingerprint.dataset_fingerprint(a)
    reads = []
    monkeypatch.setattr(provenance, "file_digest", lambda p: reads.append(p) or "x")
    fingerprint.dataset_fingerprint(a)
    assert reads == []
    (a / "train" / "r_2.png").write_bytes(b"changed")
    fingerprint.dataset_fingerprint(a)
    assert reads == [a / "train" / "r_2.png"]  # only the file whose stat changed


POSE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]


def _frames_dataset(root, images="train", file_path="./train/r_{i}"):
    """A dataset whose two frames name ``file_path`` (formatted with the index), their images
    (with an object mask and a training light's irradiance each) in the folder ``images``,
    and a ``lights.json`` with an env-map relighting ``sky.exr``. The loader reads only
    whether the files are there: bytes stand in for the images."""
    root.mkdir(parents=True, exist_ok=True)
    frames = [{"file_path": file_path.format(i=i), "transform_matrix": POSE} for i in range(2)]
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.69,
                                                            "frames": frames}))
    (root / "lights.json").write_text(json.dumps({
        "training": {"lights": [{"name": "l0"}]},
        "relightings": [{"name": "env", "type": "envmap", "path": "sky.exr"}]}))
    (root / "sky.exr").write_bytes(b"sky" * 50)
    folder = root / images
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(2):
        (folder / f"r_{i}.png").write_bytes(bytes([i]) * 300)
        (folder / f"r_{i}_mask.png").write_bytes(bytes([i + 7]) * 30)
        (folder / f"r_{i}_irradiance_0.exr").write_bytes(bytes([i + 9]) * 30)
    return root


def test_an_ordinary_dataset_keeps_the_fingerprint_its_runs_recorded(tmp_path):
    """Every file under the folder, no links: the walk alone, as before ``files_read``."""
    assert fingerprint.dataset_fingerprint(_frames_dataset(tmp_path / "a")) == \
        "2ad3fd796babac0a73fed4158a0cfaa3"


def _changes_fingerprint(root, path, data=b"changed") -> bool:
    before = fingerprint.dataset_fingerprint(root)
    path.write_bytes(data)
    return fingerprint.dataset_fingerprint(root) != before


def test_dataset_fingerprint_covers_the_sfm_points(tmp_path):
    """Stage 1 starts from ``points3d.ply`` in a dataset without masks."""
    a = _frames_dataset(tmp_path / "a")
    assert _changes_fingerprint(a, a / "points3d.ply", b"ply points")
    assert _changes_fingerprint(a, a / "points3d.ply", b"ply other points")


def test_dataset_fingerprint_covers_images_outside_the_folder(tmp_path):
    """A frame's ``file_path`` may leave the dataset folder: its image and the view's
    buffers are read from there."""
    a = _frames_dataset(tmp_path / "a", images="../imgs_train", file_path="../imgs_train/r_{i}")
    outside = tmp_path / "imgs_train"
    for name in ("r_1.png", "r_0_mask.png", "r_1_irradiance_0.exr"):
        assert _changes_fingerprint(a, outside / name), name
    (outside / "r_0.png").unlink()
    (outside / "notes.png").write_bytes(b"not read by the loader")
    before = fingerprint.dataset_fingerprint(a)
    (outside / "notes.png").write_bytes(b"still not read")
    assert fingerprint.dataset_fingerprint(a) == before


def test_dataset_fingerprint_follows_linked_split_folders(tmp_path):
    """A linked split folder's images count as if the folder were there: a copy of the
    dataset with the folder itself has the same fingerprint."""
    a = _frames_dataset(tmp_path / "a", images="../elsewhere/train")
    (a / "train").symlink_to(tmp_path / "elsewhere" / "train", target_is_directory=True)
    copy = tmp_path / "copy"
    shutil.copytree(a, copy, symlinks=False)
    assert fingerprint.dataset_fingerprint(a) == fingerprint.dataset_fingerprint(copy)
    for name in ("r_0.png", "r_1_mask.png", "r_0_irradiance_0.exr"):
        assert _changes_fingerprint(a, tmp_path / "elsewhere" / "train" / name), name


def test_dataset_fingerprint_covers_an_env_map_given_by_absolute_path(tmp_path):
    a = _frames_dataset(tmp_path / "a")
    sky = tmp_path / "maps" / "sky.exr"
    sky.parent.mkdir()
    sky.write_bytes(b"sky" * 50)
    lights = json.loads((a / "lights.json").read_text())
    lights["relightings"][0]["path"] = str(sky)
    (a / "lights.json").write_text(json.dumps(lights))
    assert _changes_fingerprint(a, sky)


def test_dataset_fingerprint_follows_linked_tensoir_folders(tmp_path):
    a = tmp_path / "a"
    a.mkdir()
    view = tmp_path / "elsewhere" / "train_000"
    view.mkdir(parents=True)
    for name in ("metadata.json", "rgba.png", "normal.png", "rgba_sunset.png"):
        (view / name).write_bytes(name.encode())
    (a / "train_000").symlink_to(view, target_is_directory=True)
    for name in ("metadata.json", "rgba.png", "normal.png", "rgba_sunset.png"):
        assert _changes_fingerprint(a, view / name), name


def test_a_malformed_dataset_still_has_a_fingerprint(tmp_path):
    """Loading names the fault; the fingerprint covers what it can (the file's bytes)."""
    a = _frames_dataset(tmp_path / "a")
    for text in ("{not json", '{"frames": 3}', '{"frames": [3, {"file_path": 4}]}'):
        assert _changes_fingerprint(a, a / "transforms_train.json", text.encode())
    for text in ('{"relightings": 3}', '{"relightings": [{"type": "envmap", "path": 5}]}',
                 '{"training": []}'):
        assert _changes_fingerprint(a, a / "lights.json", text.encode())


def _prov(ds, **settings):
    return provenance.Provenance(dataset=fingerprint.dataset_ref(ds),
                                 settings={"iterations": 100, **settings})


def test_output_claims_a_folder_lazily_and_lists_every_file(tmp_path):
    ds = _dataset(tmp_path / "ds")
    folder = tmp_path / "run" / "stage"
    out = provenance.Output.open(folder, "train", _prov(ds))
    assert not (tmp_path / "run").exists()  # nothing until the first file
    out.path("model.ply").write_text("m")
    out.claim("previews/a.png")
    out.finish()
    m = provenance.read_manifest(folder)
    assert m["command"] == "train" and m["complete"] and m["settings"] == {"iterations": 100}
    assert m["files"] == ["model.ply", "previews/a.png"]
    assert m["dataset"]["fingerprint"] == fingerprint.dataset_fingerprint(ds)


def test_a_manifest_records_its_backend_which_no_reuse_compares(tmp_path):
    """Each manifest records the backend that made it (``made_with``: variant, device,
    threads, commit); a folder continued on another backend records both, one from before
    the record stays without one, and neither is ever a reason to refuse a reuse (the two
    backends' results differ at round-off level, as two thread counts do)."""
    import drjit as dr

    ds = _dataset(tmp_path / "ds")
    out = provenance.Output.open(tmp_path / "o", "train", _prov(ds))
    out.path("a").write_text("a")
    made = provenance.read_manifest(tmp_path / "o")["made_with"]
    assert made == [provenance.made_with()]
    assert made[0]["variant"] == "llvm_ad_rgb" and made[0]["threads"] == dr.thread_count()
    assert made[0]["device"] == provenance.device_name("llvm_ad_rgb")
    assert made[0]["mi_shadowgs"] == provenance.git_commit()
    assert provenance.read_manifest(tmp_path / "o")["settings"] == _prov(ds).settings
    path = tmp_path / "o" / provenance.MANIFEST_NAME
    cuda = {"variant": "cuda_ad_rgb", "device": "NVIDIA H200", "mi_shadowgs": "abc"}
    for record, after in (([cuda], [cuda, provenance.made_with()]), (None, None)):
        manifest = json.loads(path.read_text())
        manifest.pop("made_with")
        if record is not None:  # made on a GPU ...
            manifest["made_with"] = record
        path.write_text(json.dumps(manifest))  # ... or before the record
        assert provenance.differences(manifest, _prov(ds)) == []
        again = provenance.Output.open(tmp_path / "o", "train", _prov(ds), reuse=True)
        assert again.reused and again.made_before == (record or [])
        again.path("b").write_text("b")  # continued here
        assert provenance.read_manifest(tmp_path / "o").get("made_with") == after
    assert provenance.recorded_variants({"made_with": [cuda, made[0], cuda]}) == [
        "cuda_ad_rgb", "llvm_ad_rgb"]
    assert provenance.recorded_variants({"made_with": "junk"}) == []


def test_an_output_folder_that_is_or_lies_under_a_file_is_refused(tmp_path):
    """It could never be made: refused by name before any work (it was a NotADirectoryError
    at the first file written)."""
    ds = _dataset(tmp_path / "ds")
    (tmp_path / "afile").write_text("mine")
    for out in (tmp_path / "afile", tmp_path / "afile" / "sub" / "stage"):
        with pytest.raises(provenance.ProvenanceError, match=f"^{out}: .*a file, not a folder"):
            provenance.Output.open(out, "train", _prov(ds))
        with pytest.raises(provenance.ProvenanceError, match=f"under {tmp_path / 'afile'}, "
                           if out != tmp_path / "afile" else "is a file"):
            provenance.check_output_location(out, writes_dataset=True)
    assert (tmp_path / "afile").read_text() == "mine"


@pytest.mark.parametrize("error", [PermissionError(13, "Permission denied", "/x/out"),
                                   NotADirectoryError(20, "Not a directory", "/x/afile/out"),
                                   IsADirectoryError(21, "Is a directory", "/x/folder")])
def test_an_os_error_on_a_path_exits_2_naming_it(error, monkeypatch, capsys):
    from mi_shadowgs import cli
    from mi_shadowgs.cli import report

    def fail(args):
        raise error

    monkeypatch.setattr(report, "run", fail)
    assert cli.main(["report", "RUN"]) == 2
    assert capsys.readouterr().err == \
        f"mi-shadowgs report: error: {error.filename}: {error.strerror}\n"


def test_an_os_error_without_a_path_is_not_taken_for_a_user_error(monkeypatch):
    from mi_shadowgs import cli
    from mi_shadowgs.cli import report

    def fail(args):
        raise PermissionError("no path: a fault of the code, shown with its traceback")

    monkeypatch.setattr(report, "run", fail)
    with pytest.raises(PermissionError):
        cli.main(["report", "RUN"])


def test_a_failed_command_leaves_no_folder(tmp_path):
    ds = _dataset(tmp_path / "ds")
    with (
        pytest.raises(RuntimeError),
        provenance.Output.open(tmp_path / "a" / "b", "x", _prov(ds)) as out,
    ):
        out.claim("f.txt")  # listed, then the command fails before writing it
        raise RuntimeError
    assert not (tmp_path / "a").exists()
    (tmp_path / "kept").mkdir()  # a folder the command did not create stays
    with (
        pytest.raises(RuntimeError),
        provenance.Output.open(tmp_path / "kept", "x", _prov(ds)) as out,
    ):
        out.claim("f.txt")
        raise RuntimeError
    assert (tmp_path / "kept").is_dir() and not any((tmp_path / "kept").iterdir())
    with pytest.raises(RuntimeError), provenance.Output.open(tmp_path / "c", "x", _prov(ds)) as out:
        out.path("f.txt").write_text("partial work stays for --resume / --overwrite")
        raise RuntimeError
    assert (tmp_path / "c" / "f.txt").is_file()


def test_output_refuses_dataset_folders_inputs_and_foreign_folders(tmp_path):
    ds = _dataset(tmp_path / "ds")
    for where in (ds, ds / "train", ds / "new" / "deep"):
        with pytest.raises(provenance.ProvenanceError, match="outputs never go into a dataset"):
            provenance.Output.open(where, "render", provenance.Provenance())
    for sub in ("tensoir/train_0", "notes/my_notes"):  # TensoIR's views; a user's folder
        (tmp_path / sub).mkdir(parents=True)
        (tmp_path / sub / "metadata.json").write_text("{}")
    with pytest.raises(provenance.ProvenanceError, match="outputs never go into a dataset"):
        provenance.Output.open(tmp_path / "tensoir" / "out", "render", provenance.Provenance())
    provenance.Output.open(tmp_path / "notes" / "out", "render", provenance.Provenance())
    model = tmp_path / "geo" / "model.ply"
    model.parent.mkdir()
    model.write_text("m")
    with pytest.raises(provenance.ProvenanceError, match="holds the input .*model.ply"):
        provenance.Output.open(tmp_path / "geo", "segment", provenance.Provenance(), inputs=[model])
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("precious")
    with pytest.raises(provenance.ProvenanceError, match="did not write.*thesis.tex"):
        provenance.Output.open(tmp_path / "mine", "render", provenance.Provenance(), overwrite=True)
    assert (tmp_path / "mine" / "thesis.tex").read_text() == "precious"


def test_overwrite_removes_only_listed_files_of_the_same_command(tmp_path):
    ds = _dataset(tmp_path / "ds")
    folder = tmp_path / "out"
    out = provenance.Output.open(folder, "render", _prov(ds))
    out.path("r_0.exr").write_text("old")
    out.path("sub/r_1.exr").write_text("old")
    (folder / ".r_0.exr.abcdefgh.tmp.exr").write_text("killed write")
    out.finish()
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(provenance.ProvenanceError, match="already holds an output.*--overwrite"):
        provenance.Output.open(folder, "render", _prov(ds))
    with pytest.raises(
        provenance.ProvenanceError,
        match="output of `mi-shadowgs render`, not of `mi-shadowgs segment`",
    ):
        provenance.Output.open(folder, "segment", _prov(ds), overwrite=True)
    new = provenance.Output.open(folder, "render", _prov(ds, iterations=5), overwrite=True)
    assert sorted(p.name for p in folder.iterdir()) == [provenance.MANIFEST_NAME, "notes.txt"]
    assert provenance.read_manifest(folder)["files"] == []  # emptied: still render's folder
    assert not new.reused and new.files == []


def test_reuse_only_with_the_same_dataset_inputs_and_settings(tmp_path):
    ds, other = _dataset(tmp_path / "ds"), _dataset(tmp_path / "other")
    (other / "train" / "r_0.png").write_bytes(b"another image")
    model = tmp_path / "model.ply"
    model.write_text("geometry A")
    prov = provenance.Provenance(
        dataset=fingerprint.dataset_ref(ds),
        inputs={"model": provenance.input_ref(model)},
        settings={"iterations": 60, "densify": {"start": 5}, "k": (1, 2)},
    )
    out = provenance.Output.open(tmp_path / "o", "segment", prov)
    out.path("a").write_text("a")
    out.finish()
    again = provenance.Output.open(tmp_path / "o", "segment", prov, reuse=True)
    assert again.reused and again.complete and again.files == ["a"]

    def err(p, **kw):
        with pytest.raises(provenance.ProvenanceError) as info:
            provenance.Output.open(tmp_path / "o", "segment", p, reuse=True, **kw)
        assert "--overwrite" in str(info.value)
        return str(info.value)

    msg = err(
        provenance.Provenance(
            dataset=fingerprint.dataset_ref(other), inputs=prov.inputs, settings=prov.settings
        )
    )
    assert f"made from dataset {ds}" in msg and str(other) in msg
    msg = err(
        dataclasses_replace(
            prov, settings={"iterations": 2500, "densify": {"start": 9}, "k": [1, 2]}
        )
    )
    assert "iterations: 60 there, 2500 now" in msg and "densify.start: 5 there, 9 now" in msg
    assert "k:" not in msg  # a tuple equals the list it reads back as
    # When to checkpoint is no part of what was made (a resume is bit-identical).
    assert provenance.Output.open(
        tmp_path / "o",
        "segment",
        dataclasses_replace(
            prov,
            settings={
                **prov.settings,
                "checkpoint_seconds": 5.0,
                "densify": {"start": 5, "checkpoint_every": 3},
            },
        ),
        reuse=True,
    ).reused
    model.write_text("geometry B")
    msg = err(dataclasses_replace(prov, inputs={"model": provenance.input_ref(model)}))
    assert "input model differs" in msg
    (ds / "train" / "r_1.png").write_bytes(b"edited")
    msg = err(dataclasses_replace(prov, dataset=fingerprint.dataset_ref(ds)))
    assert f"the dataset {ds} changed since" in msg
    # The run folder compares only the dataset; its stages compare the rest.
    provenance.Output.open(
        tmp_path / "o",
        "segment",
        dataclasses_replace(prov, settings={}),
        reuse=True,
        compare=("dataset",),
    )


def dataclasses_replace(obj, **kw):
    import dataclasses

    return dataclasses.replace(obj, **kw)


def test_overwrite_clears_parts_and_a_run_may_adopt_stage_folders(tmp_path):
    ds = _dataset(tmp_path / "ds")
    run = tmp_path / "run"
    geo = provenance.Output.open(run / "geometry", "train", _prov(ds))  # `train --out RUN` first
    geo.path("model.ply").write_text("m")
    geo.finish()
    top = provenance.Output.open(run, "run", _prov(ds), reuse=True, parts=("geometry", "material"))
    top.add_part("geometry")
    top.path("summary.json").write_text("{}")
    (run / "geometry" / "mine.txt").write_text("mine")
    top = provenance.Output.open(run, "run", _prov(ds), overwrite=True, parts=("geometry",))
    # The user's file stays, and with it an emptied manifest in each folder that keeps one:
    # the stage is made again there (`run --overwrite` exited 2 after removing the run: the
    # stage's folder held a file and no manifest, so it was taken for someone else's).
    assert sorted(p.relative_to(run).as_posix() for p in run.rglob("*")) == [
        provenance.MANIFEST_NAME,
        "geometry",
        f"geometry/{provenance.MANIFEST_NAME}",
        "geometry/mine.txt",
    ]
    assert provenance.read_manifest(run / "geometry")["files"] == []
    top.add_part("geometry")
    with provenance.Output.open(run / "geometry", "train", _prov(ds, iterations=7),
                                reuse=True) as geo:  # no earlier settings to differ from
        assert not geo.reused
        geo.path("model.ply").write_text("m2")
        geo.finish()
    assert (run / "geometry" / "mine.txt").read_text() == "mine"


def test_a_staged_sub_folder_replaces_only_its_own_files(tmp_path):
    """A run's `report/` and a fit's `figures/` were replaced whole on every call, taking a
    user's notes there with them: now each file made replaces ours of its name, ours not made
    again go, and someone else's stay; one of someone else's with a name made is refused."""
    ds = _dataset(tmp_path / "ds")
    run = tmp_path / "run"
    out = provenance.Output.open(run, "run", _prov(ds))
    with out.staged("report") as tmp:
        (tmp / "a.png").write_text("1")
        (tmp / "b.png").write_text("1")
    (run / "report" / "notes.txt").write_text("mine")
    with out.staged("report") as tmp:
        (tmp / "a.png").write_text("2")
    assert sorted(p.name for p in (run / "report").iterdir()) == ["a.png", "notes.txt"]
    assert (run / "report" / "a.png").read_text() == "2"
    assert "report/a.png" in out.files and "report/notes.txt" not in out.files
    (run / "report" / "c.png").write_text("mine too")
    with pytest.raises(provenance.ProvenanceError, match=r"c.png: exists and mi-shadowgs did "
                                                         "not write it"):
        with out.staged("report") as tmp:
            (tmp / "a.png").write_text("3")
            (tmp / "c.png").write_text("ours")
    assert (run / "report" / "c.png").read_text() == "mine too"
    assert (run / "report" / "a.png").read_text() == "2"  # refused before anything moved
    assert not [p for p in run.iterdir() if p.name.startswith(".report.")]  # no temporaries


def test_an_output_never_goes_inside_another_outputs_folders(tmp_path):
    """`run --out RUN/material/full` was taken as a run (stage 4's manifest names `run`
    too): it rewrote stage 4's manifest and nested a run there. An output inside a folder
    that an enclosing output lists as its own is refused; a run's stages, written as its
    parts (or by `train`/`segment`), and new folders beside its files are not."""
    ds = _dataset(tmp_path / "ds")
    run = tmp_path / "run"
    top = provenance.Output.open(run, "run", _prov(ds), parts=("geometry", "material"))
    top.add_part("geometry")
    top.add_part("material/full")
    top.path("report/a.png").write_text("a")
    provenance.Output.open(run / "geometry", "train", _prov(ds)).path("model.ply").write_text("m")
    provenance.Output.open(run / "material" / "full", "run", _prov(ds), part_of=run).path(
        "model.ply").write_text("m")
    for folder, command in ((run / "material" / "full", "run"),
                            (run / "material" / "x", "render"),
                            (run / "material" / "full" / "relit", "relight"),
                            (run / "report" / "x", "render"),
                            (run / "geometry" / "x", "train")):
        with pytest.raises(provenance.ProvenanceError, match="lies inside .* which `mi-shadowgs "
                                                             "run` wrote"):
            provenance.Output.open(folder, command, provenance.Provenance())
    with pytest.raises(provenance.ProvenanceError, match="lies inside"):
        provenance.check_output_location(run / "material" / "data", command="generate",
                                         writes_dataset=True)
    assert provenance.read_manifest(run / "material" / "full")["files"] == ["model.ply"]
    provenance.Output.open(run / "relit", "relight", provenance.Provenance())  # beside: free


def test_a_dataset_writer_may_rewrite_its_own_dataset_but_not_nest_one(tmp_path):
    ds = _dataset(tmp_path / "ds")
    with pytest.raises(provenance.ProvenanceError, match="did not write"):  # no manifest: not ours
        provenance.Output.open(
            ds, "generate", provenance.Provenance(), overwrite=True, writes_dataset=True
        )
    out = provenance.Output.open(
        tmp_path / "gen", "generate", provenance.Provenance(), writes_dataset=True
    )
    out.path("transforms_train.json").write_text("{}")
    out.finish()
    again = provenance.Output.open(
        tmp_path / "gen", "generate", provenance.Provenance(), overwrite=True, writes_dataset=True
    )
    assert not (tmp_path / "gen" / "transforms_train.json").exists() and not again.reused
    with pytest.raises(provenance.ProvenanceError, match="outputs never go into a dataset"):
        provenance.Output.open(
            ds / "inner", "generate", provenance.Provenance(), writes_dataset=True
        )


def test_settings_added_later_keep_older_outputs_when_they_change_nothing():
    """An output made before a setting existed is still the same output when the new value
    does what the older code did (ADDED_SETTINGS), or when the setting only acts through
    compared ones (RESULT_NEUTRAL_SETTINGS); otherwise the difference is named."""
    old = {"settings": {"config": {"iterations": 300, "lambda_dist": 3e4}}}

    def diff(**new_config):
        new = provenance.Provenance(settings={"config": {"iterations": 300,
                                                         "lambda_dist": 3e4, **new_config}})
        return provenance.differences(old, new, ("settings",))

    # stage 2 before k_select: K from the labels; silhouette_samples unused then
    assert diff(k_select="labels", silhouette_samples=2000) == []
    # stage 1 before the unmasked settings: they act through lambda_dist (compared)
    assert diff(unmasked_lambda_dist=0.0, unmasked_lambda_normal=0.0,
                unmasked_opacity_reset=False, unmasked_lambda_dark_alpha=0.1) == []
    assert diff(unmasked_lambda_dist=None, unmasked_lambda_normal=None) == []
    assert diff(unmasked_max_surfels=40000) == []  # ... and densify.max_surfels
    # stage 4 before its chromaticity settings: they act through normal_steps and
    # refine_score (compared)
    assert diff(chromaticity_normal_steps=0, chromaticity_refine_score="segment") == []
    # ... and before the dark-alpha term: off (it acts on views without masks only)
    assert diff(lambda_dark_alpha=0.0, dark_max=1.0 / 255.0) == []
    assert "lambda_dark_alpha" in diff(lambda_dark_alpha=0.1)[0]
    # ... and before the prune outside the masks: none; its dilation unused then
    assert diff(hull_prune_views=0, hull_prune_dilate=1) == []
    assert "hull_prune_views" in diff(hull_prune_views=2, hull_prune_dilate=1)[0]
    # ... and before the choice of depth-normal differences: 2DGS's central ones
    assert diff(normal_depth_differences="central") == []
    assert "normal_depth_differences" in diff(normal_depth_differences="same_plane")[0]
    # ... and before stage 4's normal phase: none; its own settings unused then
    assert diff(normal_steps=0, lr_normal=0.5, lambda_normal_prior=9.0,
                normal_hold_planar=False) == []
    d = diff(normal_steps=1500, lr_normal=0.03, lambda_normal_prior=0.3,
             normal_hold_planar=True)
    assert len(d) == 1 and all(k in d[0] for k in ("normal_steps", "lr_normal",
                                                     "lambda_normal_prior")), d
    # ... and before the shares of stage 1's consistent cells and stage 2's prototypes
    # were settings: the 5% and the last quarter, written in the code
    assert diff(init_consistent_top=0.05, prototype_share=0.25, outline_weld=0.25,
                sliver_area=1e-3, min_points=10) == []
    assert "init_consistent_top" in diff(init_consistent_top=0.1)[0]
    assert "prototype_share" in diff(prototype_share=0.5)[0]
    # a value the older code did not use is a difference, and so is one it did use
    d = diff(k_select="silhouette", silhouette_samples=2000)
    assert len(d) == 1 and "k_select" in d[0] and "silhouette_samples" in d[0]
    assert "lambda_dist" in provenance.differences(
        old, provenance.Provenance(settings={"config": {"iterations": 300,
                                                        "lambda_dist": 0.0}}), ("settings",))[0]


def test_uncommitted_changes_are_told_apart(tmp_path):
    """``uncommitted_digest``: None on a clean checkout (and outside one); two different
    edits of a tracked file give two digests, which "+changes" alone does not."""
    import subprocess

    from mi_shadowgs.io.provenance import git_commit, uncommitted_digest

    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    assert uncommitted_digest(tmp_path) is None  # not a checkout
    git("init", "-q")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("add", "code.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "one")
    assert uncommitted_digest(tmp_path) is None
    (tmp_path / "code.py").write_text("x = 2\n")
    first = uncommitted_digest(tmp_path)
    (tmp_path / "code.py").write_text("x = 3\n")
    assert first is not None and uncommitted_digest(tmp_path) not in (None, first)
    assert git_commit(tmp_path).endswith(" +changes")
