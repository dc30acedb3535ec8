"""`run`, `train`, `segment` and `report` on tiny datasets: the pipeline end to end, stages
reused only for the same dataset, model and settings, no output over an input, and every
input checked before the first training step."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from mi_shadowgs import cli
from mi_shadowgs import presets as run_presets
from mi_shadowgs.dataset.writer import write_dataset
from mi_shadowgs.io import ply
from mi_shadowgs.io.provenance import MANIFEST_NAME
from mi_shadowgs.presets import generate_config as gen_config
from mi_shadowgs.scenes import scene_path
from mi_shadowgs.stages.geometry import train as geometry_train
from tests.conftest import without_few_views_warning


# Every stage cut to seconds: the checks here are about which files are written, kept or
# refused, not about the fits' quality (tests/test_stage_*.py measure that).
def _tiny_tree():
    small = run_presets.get_config("cpu-small")
    return dataclasses.replace(
        small,
        geometry=dataclasses.replace(
            small.geometry, iterations=20, sh_degree=0, init_points=500, hull_resolution=16,
            log_every=10, preview_every=10, checkpoint_every=10,
            densify=dataclasses.replace(small.geometry.densify, start=5, stop=15, interval=5,
                                        opacity_reset_interval=0, max_surfels=2000)),
        segmentation=dataclasses.replace(small.segmentation, iterations=20, n_samples=256),
        material=dataclasses.replace(
            small.material, iterations=10, warmup=5, refine_passes=(), refine_views=2,
            refine_global=0, refine_again_global=False, lamps="off", normal_steps=30,
            log_every=10,
            detail_edge_px=0),  # at 32^2 nearly every pixel is near a shadow's edge
        visibility=dataclasses.replace(small.visibility, resolution=64))


@pytest.fixture(scope="module", autouse=True)
def tiny_presets():
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(run_presets.PRESETS, "cpu-small", _tiny_tree())
        yield


def _dataset(root, seed):
    cfg = dataclasses.replace(
        gen_config("cpu-small"), width=32, height=32, n_train=8, n_test=2, spp=4,
        envmaps="sky",
    )
    write_dataset(scene_path("default"), root, cfg, "cpu-small", seed=seed, progress=False)
    return root


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    base = tmp_path_factory.mktemp("data")
    return _dataset(base / "A", 1), _dataset(base / "B", 2)


@pytest.fixture(scope="module")
def finished(data, tmp_path_factory):
    """A finished run of dataset A (about 10 s)."""
    run = tmp_path_factory.mktemp("runs") / "A"
    assert cli.main(["run", str(data[0]), "--out", str(run), "--no-progress"]) == 0
    return run


def _copy(run, tmp_path):
    shutil.copytree(run, tmp_path / "run")
    return tmp_path / "run"


def _snapshot(folder):
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_run_writes_every_stage_and_a_rerun_reuses_them(finished, data, capsys):
    names = {p.relative_to(finished).as_posix() for p in finished.rglob("*") if p.is_file()}
    for name in (
        "summary.json",
        "report.html",
        "geometry/model.ply",
        "geometry/config.json",
        "geometry/metrics.json",
        "geometry/log.csv",
        "geometry/previews/iter_000020.png",
        "geometry/checkpoint/checkpoint.npz",
        "segmentation/model.ply",
        "segmentation/segmentation.json",
        "segmentation/segments/r_000_overlay.png",
        "material/full/model.ply",
        "material/full/light.json",
        "material/full/metrics.json",
        "material/full/grid.json",
        "material/full/figures/light_map.png",
    ):
        assert name in names
    manifests = sorted(n for n in names if n.endswith(MANIFEST_NAME))
    assert manifests == [
        f"{d}{MANIFEST_NAME}" for d in ("", "geometry/", "material/full/", "segmentation/")
    ]
    for m in manifests:  # every file of the run is listed in its folder's manifest
        listed = json.loads((finished / m).read_text())
        assert listed["complete"]
        folder = m[: -len(MANIFEST_NAME)]
        own = {
            n
            for n in names
            if n.startswith(folder)
            and not n.endswith(MANIFEST_NAME)
            and not any(n.startswith(f"{folder}{p}/") for p in listed["parts"])
        }
        assert own == {folder + f for f in listed["files"]}
    before = _snapshot(finished / "material")
    capsys.readouterr()
    assert cli.main(["run", str(data[0]), "--out", str(finished), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "geometry:" not in out and "segmented" not in out  # nothing ran again
    # ... and its seconds are this call's, so the report says which stages it did not make
    reused = ["geometry", "segmentation", "material (full)"]
    assert f"made by an earlier call: {', '.join(reused)})" in out
    assert json.loads((finished / "summary.json").read_text())["reused_stages"] == reused
    assert "stages made by an earlier call" in (finished / "report.html").read_text()
    assert _snapshot(finished / "material") == before
    assert cli.main(["report", str(finished)]) == 0


def test_a_run_of_another_dataset_does_not_relabel_a_finished_run(finished, data, tmp_path, capsys):
    run = _copy(finished, tmp_path)
    before = _snapshot(run)
    assert cli.main(["run", str(data[1]), "--out", str(run), "--no-progress"]) == 2
    err = without_few_views_warning(capsys.readouterr().err).strip()
    assert f"made from dataset {data[0]}" in err and str(data[1]) in err
    assert "--overwrite" in err and "\n" not in err
    assert _snapshot(run) == before


def test_run_does_not_take_a_stage_1_of_other_settings(data, tmp_path, capsys):
    run = tmp_path / "run"
    assert (
        cli.main(
            [
                "train",
                str(data[0]),
                "--out",
                str(run),
                "--iterations",
                "5",
                "--no-eval",
                "--no-progress",
            ]
        )
        == 0
    )
    before = _snapshot(run)
    capsys.readouterr()
    assert cli.main(["run", str(data[0]), "--out", str(run), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "geometry" in err and "iterations: 5 there, 20 now" in err and "--overwrite" in err
    assert _snapshot(run) == before  # and no run manifest or empty folder left behind


def test_a_seed_reaches_every_stage_and_a_run_of_another_seed_is_not_reused(
    finished, data, tmp_path, capsys
):
    # A run at seed 1 into seed 0's folder would mix two runs' stages: refused, naming the
    # seed, and nothing there changes.
    run = _copy(finished, tmp_path)
    before = _snapshot(run)
    capsys.readouterr()
    assert cli.main(["run", str(data[0]), "--out", str(run), "--seed", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "geometry" in err and "seed: 0 there, 1 now" in err and "--overwrite" in err
    assert _snapshot(run) == before
    # In a folder of its own, every stage records the seed and draws from it: stage 1 starts
    # from other points, so its model differs from seed 0's.
    other = tmp_path / "seed1"
    assert cli.main(["run", str(data[0]), "--out", str(other), "--seed", "1", "--no-progress"]) == 0
    settings = {
        stage: json.loads((other / stage / MANIFEST_NAME).read_text())["settings"]
        for stage in ("geometry", "segmentation", "material/full")
    }
    assert settings["geometry"]["seed"] == 1
    assert settings["segmentation"]["config"]["seed"] == 1
    assert settings["material/full"]["material"]["seed"] == 1
    seed0 = ply.read_ply_model(finished / "geometry" / "model.ply")
    seed1 = ply.read_ply_model(other / "geometry" / "model.ply")
    assert seed0.position.shape != seed1.position.shape or (seed0.position != seed1.position).any()
    assert cli.main(["run", str(data[0]), "--out", str(other), "--seed", "-1"]) == 2
    assert "seed must be >= 0" in capsys.readouterr().err


def test_albedo_detail_reaches_stage_4_and_a_run_without_it_is_not_reused(
    finished, data, tmp_path, capsys
):
    """`run --albedo-detail W` sets stage 4's detail_prior (the albedo then varies within a
    segment); into a run fitted without it, stage 4 is refused naming the setting, and
    nothing there changes. Stages 1-2 do not depend on it and are reused."""
    run = _copy(finished, tmp_path)
    before = _snapshot(run)
    capsys.readouterr()
    argv = ["run", str(data[0]), "--no-progress", "--albedo-detail"]
    assert cli.main([*argv, "0.3", "--out", str(run)]) == 2
    err = capsys.readouterr().err
    assert "material" in err and "detail_prior: 0.0 there, 0.3 now" in err, err
    assert _snapshot(run) == before
    other = tmp_path / "detail"
    shutil.copytree(finished / "geometry", other / "geometry")
    shutil.copytree(finished / "segmentation", other / "segmentation")
    assert cli.main([*argv, "0.3", "--out", str(other)]) == 0
    assert "geometry:" not in capsys.readouterr().out  # stage 1 reused
    settings = json.loads((other / "material" / "full" / MANIFEST_NAME).read_text())["settings"]
    assert settings["material"]["detail_prior"] == 0.3
    fitted = ply.read_ply_model(other / "material" / "full" / "model.ply")
    albedo, seg = fitted.channels["albedo"], fitted.channels["segment"][:, 0]
    assert max(np.ptp(albedo[seg == k], axis=0).max() for k in np.unique(seg)) > 0
    plain = ply.read_ply_model(finished / "material" / "full" / "model.ply")
    assert max(np.ptp(plain.channels["albedo"][seg == k], axis=0).max()
               for k in np.unique(seg)) == 0
    for bad in ("-1", "inf", "nan"):
        assert cli.main([*argv, bad, "--out", str(tmp_path / "bad")]) == 2
        assert "MaterialConfig: detail_prior >= 0" in \
            capsys.readouterr().err
        assert not (tmp_path / "bad").exists()


def test_chromaticity_segments_get_stage_4s_chromaticity_settings(finished, data, tmp_path,
                                                                  capsys):
    """Stage 4's normal phase and "albedo" refinement score read each segment's albedo as
    right; on segments from chromaticity (which can mix materials) its chromaticity_*
    settings take their place, recorded as the values that ran and said once. With
    material ids the preset's run. A run fitted before on chromaticity segments is
    refused naming the setting."""
    preset = run_presets.material_config("cpu-small")
    # else the test would not tell the two apart
    assert preset.normal_steps != preset.chromaticity_normal_steps
    assert preset.refine_score != preset.chromaticity_refine_score
    recorded = json.loads((finished / "material" / "full" / MANIFEST_NAME).read_text())
    assert recorded["settings"]["material"]["normal_steps"] == preset.normal_steps
    assert recorded["settings"]["material"]["refine_score"] == preset.refine_score
    other = tmp_path / "chroma"
    shutil.copytree(finished / "geometry", other / "geometry")
    capsys.readouterr()
    argv = ["run", str(data[0]), "--no-progress", "--masks", "chromaticity", "--out"]
    assert cli.main([*argv, str(other)]) == 0
    out = capsys.readouterr().out
    assert "geometry:" not in out  # stage 1 reused
    assert (f"stage 4 on segments from chromaticity: normal_steps "
            f"{preset.chromaticity_normal_steps}, refine_score "
            f"{preset.chromaticity_refine_score}") in out, out
    manifest = other / "material" / "full" / MANIFEST_NAME
    settings = json.loads(manifest.read_text())["settings"]["material"]
    assert settings["normal_steps"] == preset.chromaticity_normal_steps
    assert settings["refine_score"] == preset.chromaticity_refine_score
    # A stage 4 fitted on chromaticity segments with the preset's own settings (before
    # these existed) is not taken as one made with them.
    old = json.loads(manifest.read_text())
    for key in ("chromaticity_normal_steps", "chromaticity_refine_score"):
        del old["settings"]["material"][key]
    old["settings"]["material"].update(normal_steps=preset.normal_steps,
                                       refine_score=preset.refine_score)
    manifest.write_text(json.dumps(old))
    before = _snapshot(other)
    assert cli.main([*argv, str(other)]) == 2
    err = capsys.readouterr().err
    assert f"normal_steps: {preset.normal_steps} there, " \
        f"{preset.chromaticity_normal_steps} now" in err, err
    assert _snapshot(other) == before
    with pytest.raises(ValueError, match="chromaticity_refine_score must be one of"):
        dataclasses.replace(preset, chromaticity_refine_score="lucky")


def test_a_changed_stage_1_model_is_not_segmented_as_the_old_one(finished, data, tmp_path, capsys):
    run = _copy(finished, tmp_path)
    model = ply.read_ply_model(run / "geometry" / "model.ply")
    model.position[0] += 0.01
    ply.write_ply_model(run / "geometry" / "model.ply", model)
    assert cli.main(["run", str(data[0]), "--out", str(run), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "segmentation" in err and "input model differs" in err


def test_a_stage_made_again_in_a_finished_run_is_not_read_with_the_later_ones(
        finished, data, tmp_path, capsys):
    """`train --overwrite` (or `segment --overwrite`) into a finished run makes one stage
    again and leaves the later stages, the summary and the report made from the old one:
    report, relight, view and export refuse the mix, naming the stage, instead of using it;
    `run --overwrite` makes the run whole again."""
    from mi_shadowgs.stages.relight.runner import load_run

    run = _copy(finished, tmp_path)
    readers = (["report", str(run)],
               ["relight", str(run), "--out", str(tmp_path / "relit"), "--light", "30,45,3",
                "--no-progress"],
               ["export", str(run), "--format", "2dgs-ply", "--out", str(tmp_path / "ply")])
    for argv in readers:  # the finished run reads
        assert cli.main(argv) == 0, argv
    assert cli.main(["train", str(data[0]), "--out", str(run), "--iterations", "10",
                     "--overwrite", "--no-progress"]) == 0
    for argv in readers:
        assert cli.main([*argv, "--overwrite"] if argv[0] != "report" else argv) == 2, argv
        err = capsys.readouterr().err
        assert "segmentation was made from another geometry/model.ply" in err, err
    with pytest.raises(ValueError, match="segmentation was made from another geometry"):
        load_run(run)  # the viewer's reader
    assert cli.main(["run", str(data[0]), "--out", str(run), "--overwrite",
                     "--no-progress"]) == 0
    assert cli.main(readers[0]) == 0
    # Stage 2 made again: stage 4 is the stale one.
    assert cli.main(["segment", str(run), "--data", str(data[0]), "--out",
                     str(run / "segmentation"), "--segments", "2", "--overwrite",
                     "--quiet"]) == 0
    assert cli.main(readers[0]) == 2
    assert "material/full was made from another segmentation/model.ply" in \
        capsys.readouterr().err


STAGES = ("geometry", "segmentation", "material/full")


def _edit_manifest(folder, **changes):
    """Set (or, with None, remove) top-level keys of ``folder``'s manifest."""
    path = folder / MANIFEST_NAME
    manifest = json.loads(path.read_text())
    for key, value in changes.items():
        manifest.pop(key, None) if value is None else manifest.update({key: value})
    path.write_text(json.dumps(manifest))


def _report_provenance(run):
    return {p["name"]: p["value"]
            for p in json.loads((run / "summary.json").read_text())["provenance"]}


def test_a_run_from_before_the_backend_record_is_reused_as_it_was(finished, data, tmp_path,
                                                                   capsys):
    """Every manifest of a run records the backend that made it (``made_with``); a run made
    before the record (its manifests without it) is reused as it was: exit 0, no warning,
    nothing made again, no record added, and the report's provenance reads as before."""
    import drjit as dr

    from mi_shadowgs.io.provenance import device_name

    for stage in ("", *STAGES):
        made = json.loads((finished / stage / MANIFEST_NAME).read_text())["made_with"]
        assert [e["variant"] for e in made] == ["llvm_ad_rgb"], stage
    run = _copy(finished, tmp_path)
    for stage in ("", *STAGES):
        _edit_manifest(run / stage, made_with=None)
    before = _snapshot(run / "material")
    capsys.readouterr()
    assert cli.main(["run", str(data[0]), "--out", str(run), "--no-progress"]) == 0
    err = without_few_views_warning(capsys.readouterr().err)
    assert "warning" not in err, err
    assert _snapshot(run / "material") == before
    for stage in ("", *STAGES):
        assert "made_with" not in json.loads((run / stage / MANIFEST_NAME).read_text())
    prov = _report_provenance(run)
    assert prov["variant"] == "llvm_ad_rgb" and prov["Dr.Jit threads"] == dr.thread_count()
    assert prov["device"] == device_name("llvm_ad_rgb")


def test_a_stage_resumed_or_made_on_another_backend_warns_and_the_report_names_each(
        finished, data, tmp_path, capsys):
    """A run whose stage 1 was made on cuda_ad_rgb and whose stage 2 was begun there
    (simulated: their records edited; no GPU here) goes on on llvm_ad_rgb: one warning line
    naming both variants and the folder, stage 2's record keeps both backends, and the
    report names each stage's backend instead of showing the last call's as everyone's."""
    from mi_shadowgs.io.provenance import device_name, made_with

    run = _copy(finished, tmp_path)
    gpu = {"variant": "cuda_ad_rgb", "device": "NVIDIA H200", "mi_shadowgs": "abc"}
    _edit_manifest(run / "geometry", made_with=[gpu])
    _edit_manifest(run / "segmentation", made_with=[gpu], complete=False)  # killed there
    shutil.rmtree(run / "material" / "full")  # not made yet
    capsys.readouterr()
    assert cli.main(["run", str(data[0]), "--out", str(run), "--no-progress"]) == 0
    err = without_few_views_warning(capsys.readouterr().err)
    warnings = [ln for ln in err.splitlines() if "warning" in ln]
    assert len(warnings) == 1, err
    assert f"{run / 'segmentation'}: continued on llvm_ad_rgb from work that cuda_ad_rgb " \
        "made" in warnings[0]
    assert f"made on llvm_ad_rgb from {run / 'geometry' / 'model.ply'}, which cuda_ad_rgb " \
        "made" in warnings[0]
    made = {stage: json.loads((run / stage / MANIFEST_NAME).read_text())["made_with"]
            for stage in STAGES}
    assert [e["variant"] for e in made["segmentation"]] == ["cuda_ad_rgb", "llvm_ad_rgb"]
    assert [e["variant"] for e in made["material/full"]] == ["llvm_ad_rgb"]
    prov = _report_provenance(run)
    assert prov["variant"] == ("cuda_ad_rgb (geometry, segmentation), "
                               "llvm_ad_rgb (segmentation, material/full)")
    assert prov["device"] == ("NVIDIA H200 (geometry, segmentation), "
                              f"{device_name('llvm_ad_rgb')} (segmentation, material/full)")
    # ... and the commit that made each (the report showed this call's as everyone's)
    assert prov["commit"] == (f"abc (geometry, segmentation), {made_with()['mi_shadowgs']} "
                              "(segmentation, material/full)")
    # summary.json's "variant" stays this call's, a name other tools can read
    assert json.loads((run / "summary.json").read_text())["variant"] == "llvm_ad_rgb"
    assert cli.main(["report", str(run)]) == 0
    assert "cuda_ad_rgb (geometry, segmentation)" in (run / "report.html").read_text()


def test_train_resumed_on_another_backend_warns_and_records_both(data, tmp_path, capsys):
    """`train --resume` of a stage 1 begun on cuda_ad_rgb (simulated), here on llvm_ad_rgb:
    it goes on from the checkpoint with one warning line naming both variants and the
    folder, and the manifest records both backends."""
    run = tmp_path / "run"
    argv = ["train", str(data[0]), "--out", str(run), "--no-eval", "--no-progress"]
    assert cli.main(argv) == 0
    gpu = {"variant": "cuda_ad_rgb", "device": "NVIDIA H200", "mi_shadowgs": "abc"}
    _edit_manifest(run / "geometry", made_with=[gpu], complete=False)
    capsys.readouterr()
    assert cli.main([*argv, "--resume"]) == 0
    err = without_few_views_warning(capsys.readouterr().err)
    warnings = [ln for ln in err.splitlines() if "warning" in ln]
    assert warnings == [f"mi-shadowgs: warning: {run / 'geometry'}: continued on llvm_ad_rgb "
                        "from work that cuda_ad_rgb made (its checkpoint and files so far); its "
                        "manifest records both (results of the two backends differ at "
                        "round-off level)"], err
    made = json.loads((run / "geometry" / MANIFEST_NAME).read_text())["made_with"]
    assert [e["variant"] for e in made] == ["cuda_ad_rgb", "llvm_ad_rgb"]


def test_a_stage_1_trained_without_its_evaluation_is_evaluated_by_run(data, tmp_path):
    """`train --no-eval` then `run` into the same folder: stage 1 is reused and evaluated
    then, so the run's summary and report have stage 1."""
    run = tmp_path / "run"
    assert cli.main(["train", str(data[0]), "--out", str(run), "--no-eval",
                     "--no-progress"]) == 0
    assert not (run / "geometry" / "metrics.json").exists()
    model = (run / "geometry" / "model.ply").read_bytes()
    assert cli.main(["run", str(data[0]), "--out", str(run), "--no-progress"]) == 0
    assert (run / "geometry" / "model.ply").read_bytes() == model  # reused, not trained
    metrics = json.loads((run / "geometry" / "metrics.json").read_text())
    assert metrics["psnr"] > 0 and metrics["surfels"] > 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["stages"][0]["name"] == "Stage 1: geometry"
    assert summary["stages"][0]["metrics"]["psnr"] == metrics["psnr"]
    manifest = json.loads((run / "geometry" / MANIFEST_NAME).read_text())
    assert manifest["complete"] and "metrics.json" in manifest["files"]


def test_train_resume_against_another_dataset_changes_nothing(data, tmp_path, capsys):
    run = tmp_path / "run"
    assert cli.main(["train", str(data[0]), "--out", str(run), "--no-eval", "--no-progress"]) == 0
    before = _snapshot(run)
    assert (
        cli.main(
            ["train", str(data[1]), "--out", str(run), "--resume", "--no-eval", "--no-progress"]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert f"made from dataset {data[0]}" in err and "--overwrite" in err
    assert (
        cli.main(
            [
                "train",
                str(data[0]),
                "--out",
                str(run),
                "--resume",
                "--iterations",
                "30",
                "--no-eval",
                "--no-progress",
            ]
        )
        == 2
    )
    assert "iterations: 20 there, 30 now" in capsys.readouterr().err
    assert (
        cli.main(
            ["train", str(data[0]), "--out", str(run), "--resume", "--overwrite", "--no-progress"]
        )
        == 2
    )
    assert "pass one of them" in capsys.readouterr().err
    assert _snapshot(run) == before  # config.json, log and checkpoint untouched
    assert (
        cli.main(
            ["train", str(data[1]), "--out", str(run), "--overwrite", "--no-eval", "--no-progress"]
        )
        == 0
    )
    cfg = json.loads((run / "geometry" / "config.json").read_text())
    assert cfg["data"] == str(data[1])


def test_sfm_points_added_to_a_dataset_without_masks_are_a_dataset_change(
        data, tmp_path, capsys):
    """Stage 1 of a dataset without masks starts from its ``points3d.ply`` when it has one:
    a stage 1 made before the file was added is not the one the file gives."""
    from validation.without_masks import unmasked_copy

    nomask = unmasked_copy(data[0], tmp_path / "nomask")
    run = tmp_path / "run"
    argv = ["train", str(nomask), "--out", str(run), "--no-eval", "--no-progress"]
    assert cli.main(argv) == 0
    before = _snapshot(run)
    (nomask / "points3d.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    assert cli.main([*argv, "--resume"]) == 2
    assert f"the dataset {nomask} changed since" in capsys.readouterr().err
    assert _snapshot(run) == before


@pytest.mark.parametrize("command", ["train", "run"])
def test_an_out_under_a_file_exits_2_naming_it(data, tmp_path, capsys, command):
    (tmp_path / "afile").write_text("mine")
    for out in (tmp_path / "afile", tmp_path / "afile" / "sub"):
        assert cli.main([command, str(data[0]), "--out", str(out), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert f"{tmp_path / 'afile'}" in err and "a file, not a folder" in err, err
    assert (tmp_path / "afile").read_text() == "mine"


def test_segment_never_writes_over_its_input_or_an_earlier_segmentation(
    finished, data, tmp_path, capsys
):
    run = _copy(finished, tmp_path)
    model = run / "geometry" / "model.ply"
    before = model.read_bytes()
    rc = cli.main(
        ["segment", str(run), "--data", str(data[0]), "--out", str(run / "geometry"), "--quiet"]
    )
    assert rc == 2 and "holds the input" in capsys.readouterr().err
    assert model.read_bytes() == before
    rc = cli.main(
        ["segment", str(run), "--data", str(data[0]), "--out", str(run / "segmentation"), "--quiet"]
    )
    assert rc == 2 and "or --overwrite to replace it" in capsys.readouterr().err
    assert (
        cli.main(
            [
                "segment",
                str(run),
                "--data",
                str(data[0]),
                "--out",
                str(data[0] / "segments"),
                "--quiet",
            ]
        )
        == 2
    )
    assert "outputs never go into a dataset" in capsys.readouterr().err
    assert not (data[0] / "segments").exists()


# A user's files in a run's folders (notes beside the figures, a PLY of their own).
USER_FILES = ("notes.txt", "report/notes.txt", "geometry/notes.ply",
              "geometry/checkpoint/notes.txt", "segmentation/notes.txt", "material/notes.txt",
              "material/full/extra.exr", "material/full/figures/mine.png")


def test_a_users_files_in_a_run_stay_and_are_never_read_as_the_runs(
        finished, data, tmp_path, capsys, monkeypatch):
    """A resume replaced `report/` whole (the user's notes in it went too), and the report
    showed a PNG put into `geometry/previews/` or `segmentation/segments/` as the run's own
    and plotted a `material/NAME/history.csv` as a fit; `run --overwrite` removed the run's
    files, then exited 2 because a stage folder held a file but no manifest. Now a call
    touches only the files its manifests list, reads only those, and `--overwrite` makes
    the run again beside the user's files."""
    from mi_shadowgs.io import plots

    run = _copy(finished, tmp_path)
    for name in USER_FILES:
        (run / name).write_text("mine")
    shutil.copy(run / "geometry" / "previews" / "iter_000020.png",
                run / "geometry" / "previews" / "zzz_mine.png")
    shutil.copy(run / "segmentation" / "segments" / "r_000_overlay.png",
                run / "segmentation" / "segments" / "zzz_overlay.png")
    (run / "material" / "mine").mkdir()
    (run / "material" / "mine" / "history.csv").write_text("step,loss\n0,1\n10,0.5\n")
    plotted = []
    real = plots.curves_png
    monkeypatch.setattr(plots, "curves_png", lambda path, panels, **kw: (
        plotted.extend(ln.get("label") for p in panels for ln in p["lines"]),
        real(path, panels, **kw))[1])
    for extra in ([], ["--overwrite"]):
        plotted.clear()
        rc = cli.main(["run", str(data[0]), "--out", str(run), "--no-progress", *extra])
        assert rc == 0, capsys.readouterr().err
        for name in USER_FILES:
            assert (run / name).read_text() == "mine", (extra, name)
        assert (run / "material" / "mine" / "history.csv").is_file()
        page = (run / "summary.json").read_text() + (run / "report.html").read_text()
        assert "zzz" not in page and "material/mine" not in page, extra
        assert "full" in plotted and "mine" not in plotted, plotted
        assert cli.main(["report", str(run)]) == 0
    assert (run / "geometry" / "previews" / "zzz_mine.png").is_file()
    assert (run / "segmentation" / "segments" / "zzz_overlay.png").is_file()


def test_no_output_goes_inside_a_runs_folders(finished, data, tmp_path, capsys):
    """`run --out RUN/material/full` was taken as a run (stage 4's manifest names `run`
    too): it rewrote stage 4's manifest and nested a run there, and RUN's next call exited 2
    on stage 4's "other settings"; other commands wrote into new folders under
    `RUN/material/` or `RUN/report/`, which the run's report then listed. Every command
    refuses an output inside a folder that a run wrote, as `export` did; a folder beside
    them is free."""
    run = _copy(finished, tmp_path)
    before = _snapshot(run)
    model = run / "material" / "full" / "model.ply"
    cams = data[0] / "transforms_test.json"
    for argv in (["run", str(data[0]), "--out", str(run / "material" / "full"), "--no-progress"],
                 ["train", str(data[0]), "--out", str(run / "material" / "full"),
                  "--no-progress"],
                 ["render", str(model), "--cameras", str(cams), "--out",
                  str(run / "material" / "renders")],
                 ["relight", str(run), "--out", str(run / "report" / "relit"), "--light",
                  "30,45,3", "--no-progress"]):
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "which `mi-shadowgs run` wrote" in err, err
    assert _snapshot(run) == before
    assert cli.main(["render", str(model), "--cameras", str(cams), "--out",
                     str(run / "renders")]) == 0
    assert cli.main(["run", str(data[0]), "--out", str(run), "--no-progress"]) == 0


def test_report_writes_only_into_a_run_folder(tmp_path, capsys):
    (tmp_path / "summary.json").write_text(json.dumps({"stages": []}))
    assert cli.main(["report", str(tmp_path)]) == 2
    assert "not a run folder" in capsys.readouterr().err
    assert not (tmp_path / "report.html").exists()


# -- inputs checked before work -------------------------------------------------------------
def _broken_copy(src, tmp_path, name="data"):
    dst = tmp_path / name
    shutil.copytree(src, dst)
    return dst


@pytest.mark.parametrize("command", ["train", "run"])
def test_a_corrupt_test_image_stops_the_command_before_training(data, tmp_path, capsys, command):
    bad = _broken_copy(data[0], tmp_path)
    exr = bad / "test" / "r_001_albedo.exr" if command == "run" else bad / "test" / "r_001.exr"
    exr.write_bytes(exr.read_bytes()[:200])
    rc = cli.main([command, str(bad), "--out", str(tmp_path / "out" / "run"), "--no-progress"])
    err = without_few_views_warning(capsys.readouterr().err).strip()
    assert rc == 2 and str(exr) in err and "\n" not in err and "plugin" not in err
    assert not (tmp_path / "out").exists()  # no training, no folder left behind


def test_segment_refuses_a_run_model_with_another_dataset(finished, data, tmp_path, capsys):
    """A run's stage-1 model segmented with another dataset's views: exit 2 naming both,
    nothing written; a PLY from elsewhere (no manifest lists it) is taken as it is."""
    out = tmp_path / "seg"
    argv = ["segment", str(finished), "--data", str(data[1]), "--out", str(out), "--quiet"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert f"{finished / 'geometry' / 'model.ply'}: was fitted to the dataset" in err
    assert f"not to --data {data[1]}" in err and not out.exists()
    loose = tmp_path / "model.ply"
    shutil.copy(finished / "geometry" / "model.ply", loose)
    assert cli.main(["segment", str(loose), *argv[2:]]) == 0


def test_preview_env_maps_are_recorded_by_content(data, tmp_path, capsys, monkeypatch):
    """The report's preview env maps (--preview-envmap, $MI_SHADOWGS_ENVMAPS) are inputs of
    stage 4 by content: one edited after the run makes the rerun exit 2 naming it (its
    previews were reused as they were); a missing one names where it was given."""
    import numpy as np

    from mi_shadowgs.io.images import write_exr

    envmap = tmp_path / "pe.exr"
    write_exr(envmap, np.full((8, 16, 3), 0.5, np.float32))
    run = tmp_path / "run"
    argv = ["run", str(data[0]), "--out", str(run), "--preview-envmap", str(envmap),
            "--no-progress"]
    assert cli.main(argv) == 0
    assert cli.main(argv) == 0  # the same env map: reused
    write_exr(envmap, np.full((8, 16, 3), 0.9, np.float32))
    assert cli.main(argv) == 2
    assert "preview_envmap_0" in capsys.readouterr().err
    monkeypatch.setenv("MI_SHADOWGS_ENVMAPS", str(tmp_path / "gone.exr"))
    assert cli.main(["run", str(data[0]), "--out", str(tmp_path / "other")]) == 2
    assert f"$MI_SHADOWGS_ENVMAPS: {tmp_path / 'gone.exr'}: not found" in \
        capsys.readouterr().err
    # an 8-bit map: used (its run not made here), with a warning of its clipped highlights
    import imageio.v3 as iio

    import mi_shadowgs.pipeline

    png = tmp_path / "pano.png"
    iio.imwrite(png, np.full((8, 16, 3), 200, np.uint8))
    monkeypatch.setenv("MI_SHADOWGS_ENVMAPS", str(png))
    monkeypatch.setattr(mi_shadowgs.pipeline, "run_pipeline",
                        lambda *a, **k: (_ for _ in ()).throw(FileNotFoundError("stub")))
    assert cli.main(["run", str(data[0]), "--out", str(tmp_path / "other")]) == 2
    assert f"$MI_SHADOWGS_ENVMAPS {png} stores integers" in capsys.readouterr().err


def test_run_with_material_masks_checks_them_before_stage_1(data, tmp_path, capsys,
                                                            monkeypatch):
    """`run --masks material` on a dataset without material ids stops before stage 1 trains,
    naming the view, not after it."""
    bad = _broken_copy(data[0], tmp_path)
    for png in (bad / "train").glob("*_material.png"):
        png.unlink()
    monkeypatch.setattr(geometry_train, "train_geometry",
                        lambda *a, **k: pytest.fail("stage 1 trained"))
    assert cli.main(["run", str(bad), "--out", str(tmp_path / "run"), "--masks", "material",
                     "--no-progress"]) == 2
    assert "has no material-id map (*_material.png)" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_run_checks_the_ground_truth_it_evaluates_against_first(data, tmp_path, capsys):
    # Absent ground truth only skips its metrics (tests/test_no_ground_truth.py); present
    # but malformed ground truth stops the run before stage 1.
    bad = _broken_copy(data[0], tmp_path)
    lights = json.loads((bad / "lights.json").read_text())
    lights["training"]["lights"][0]["direction"] = "up"
    (bad / "lights.json").write_text(json.dumps(lights))
    assert cli.main(["run", str(bad), "--out", str(tmp_path / "run"), "--no-progress"]) == 2
    assert "lights.json: missing or malformed field 'training.lights'" in \
        capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_one_training_view_warns(data, tmp_path, capsys):
    one = _broken_copy(data[0], tmp_path)
    meta = json.loads((one / "transforms_train.json").read_text())
    meta["frames"] = meta["frames"][:1]
    (one / "transforms_train.json").write_text(json.dumps(meta))
    assert (
        cli.main(
            [
                "train",
                str(one),
                "--out",
                str(tmp_path / "run"),
                "--iterations",
                "2",
                "--no-eval",
                "--no-progress",
            ]
        )
        == 0
    )
    warnings = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert len(warnings) == 1
    assert "1 training view(s)" in warnings[0] and "at least 16" in warnings[0]


def test_a_gpu_preset_on_the_cpu_warns_before_anything_runs(data, tmp_path, capsys):
    # gpu-large and paper take minutes on a GPU and hours on the CPU backend: said at once,
    # before the inputs are read (here they are broken, so the run stops right after).
    from mi_shadowgs.config import slow_preset_warning

    bad = _broken_copy(data[0], tmp_path)
    lights = json.loads((bad / "lights.json").read_text())
    lights["training"]["lights"][0]["direction"] = "up"
    (bad / "lights.json").write_text(json.dumps(lights))
    for preset, warned in (("gpu-large", True), ("paper", True), ("cpu-medium", False)):
        assert cli.main(["run", str(bad), "--out", str(tmp_path / "run"), "--preset", preset,
                         "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert (f"preset '{preset}' is sized for a GPU (--variant cuda_ad_rgb); on "
                "llvm_ad_rgb its run takes hours" in err) == warned, (preset, err)
        assert "lights.json" in err and not (tmp_path / "run").exists()
    assert slow_preset_warning("gpu-large", "cuda_ad_rgb") is None


@pytest.mark.parametrize("flag, want", [([], True), (["--no-ablations"], False),
                                        (["--ablations"], True)])
def test_the_paper_presets_ablations_can_be_turned_off(data, tmp_path, monkeypatch, flag,
                                                       want):
    """`run --preset paper` fits the two ablations (hours more on a CPU); `--no-ablations`
    turns them off (before, only `--ablations` existed, which could only turn them on)."""
    from mi_shadowgs import pipeline

    seen = []
    monkeypatch.setattr(pipeline, "run_pipeline", lambda data, out, config, **kw: seen.append(
        config) or {"tables": [{"rows": [], "columns": []}], "total_seconds": 0.0})
    assert cli.main(["run", str(data[0]), "--out", str(tmp_path / "run"), "--preset",
                     "paper", *flag]) == 0
    assert seen[0].preset == "paper" and seen[0].ablations is want
