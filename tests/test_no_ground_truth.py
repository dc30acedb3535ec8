"""`run` on data without ground truth: NeRF-synthetic and TensoIR
copies of a tiny generated dataset (images, masks and cameras only) run to exit 0, write the
models and the decomposition, and the summary names each skipped metric with its reason; a
run that fails in evaluation keeps its fitted model and a rerun evaluates it without
fitting again."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tiny_cli

from mi_shadowgs import cli, pipeline
from mi_shadowgs.dataset.export import export_without_ground_truth
from mi_shadowgs.dataset.loader import load_dataset
from mi_shadowgs.scenes import scene_path

TINY = tiny_cli.TINY


@pytest.fixture(scope="module", autouse=True)
def tiny_presets():
    with pytest.MonkeyPatch.context() as mp:
        for table, config in tiny_cli.presets():
            mp.setitem(table, TINY, config)
        yield


@pytest.fixture(scope="module")
def data(tmp_path_factory, tiny_presets):
    base = tmp_path_factory.mktemp("nogt")
    full = base / "full"
    assert cli.main(["generate", str(scene_path("default")), "--out", str(full), "--preset",
                     TINY, "--no-progress"]) == 0
    return {"full": full,
            "nerf": export_without_ground_truth(full, base / "nerf", "nerf"),
            "tensoir": export_without_ground_truth(full, base / "tensoir", "tensoir")}


def _run(data, out, *extra: str) -> int:
    return cli.main(["run", str(data), "--out", str(out), "--preset", TINY, "--no-progress",
                     *extra])


@pytest.fixture(scope="module")
def runs(data, tmp_path_factory):
    base = tmp_path_factory.mktemp("nogt_runs")
    out = {}
    for kind in ("nerf", "tensoir"):
        # the TensoIR copy's K is forced (`run --segments`); the NeRF copy's is chosen
        assert _run(data[kind], base / kind, *(["--segments", "3"] if kind == "tensoir"
                                               else [])) == 0
        out[kind] = base / kind
    return out


def test_exports_hold_images_and_cameras_only(data):
    full = load_dataset(data["full"], "test")
    for kind in ("nerf", "tensoir"):
        copy = load_dataset(data[kind], "test")
        assert copy.layout == kind and copy.lights is None and copy.info is None
        for a, b in zip(full.views, copy.views, strict=True):
            # Both copies' cameras go through Blender's Z-up frame and back.
            np.testing.assert_allclose(b.camera.c2w, a.camera.c2w, atol=1e-9)
            assert np.array_equal(b.mask, a.mask)
            # 8-bit sRGB: at most half a step (1/510) in sRGB, ~0.2% of a linear value.
            assert np.abs(b.image - np.clip(a.image, 0, 1)).max() < 0.01
            for field in ("albedo", "normal", "depth", "material", "visibility",
                          "irradiance"):
                assert getattr(b, field) is None, (kind, field)
            assert not b.relit


@pytest.mark.parametrize("kind", ["nerf", "tensoir"])
def test_run_without_ground_truth_writes_models_decomposition_and_skips(runs, kind, capsys):
    run = runs[kind]
    for name in ("geometry/model.ply", "segmentation/model.ply", "material/full/model.ply",
                 "material/full/light.json", "material/full/fit.json", "report.html",
                 "report/light_map.png"):
        assert (run / name).is_file(), name
    summary = json.loads((run / "summary.json").read_text())
    skipped = {s["metric"]: s for s in summary["skipped_metrics"]}
    for metric in ("albedo PSNR/SSIM/LPIPS", "light cosine and angular errors",
                   "shadow IoU", "relighting PSNR/SSIM/LPIPS", "geometry normal error",
                   "segmentation ARI/mIoU"):
        assert metric in skipped, metric
        assert skipped[metric]["why"]
    assert "test albedo" in skipped["albedo PSNR/SSIM/LPIPS"]["needs"]
    table = summary["tables"][0]
    row = dict(zip(table["columns"], table["rows"][0], strict=True))
    assert row["albedo PSNR"] is None and row["shadow IoU"] is None
    # The decomposition needs no ground truth: every column is there, without GT columns.
    cols = summary["grid"]["columns"]
    for col in ("input", "albedo", "roughness", "metallic", "normal", "irradiance",
                "segments"):
        assert col in cols, col
    assert any(c.startswith("visibility az") for c in cols)
    assert not any("(GT)" in c or "error" in c for c in cols)
    for r in summary["grid"]["rows"]:
        for cell in r["cells"]:
            assert (run / cell).is_file(), cell
    # Relit previews: the 8-light turntable, and the fitted lights with azimuth/elevation.
    stage = next(s for s in summary["stages"] if s["name"].startswith("Stages 3-5"))
    strips = [f for f in stage["figures"] if "turntable" in f["title"]]
    assert len(strips) == 1 and (run / strips[0]["path"]).is_file()
    assert len(list((run / "material/full/figures").glob("preview_0_turntable_az*.png"))) == 8
    lights = next(t for t in summary["tables"] if t["title"].startswith("Fitted lights"))
    assert lights["columns"][1:3] == ["azimuth (deg)", "elevation (deg)"] and lights["rows"]
    page = (run / "report.html").read_text()
    assert "Metrics not computed" in page and "missing:" not in page
    seg = json.loads((run / "segmentation" / "segmentation.json").read_text())
    if kind == "tensoir":
        assert seg["k"] == 3


def test_labelled_dataset_skips_nothing_of_stage_5(data, tmp_path):
    assert _run(data["full"], tmp_path / "run") == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert not summary.get("skipped_metrics")
    cols = summary["grid"]["columns"]
    assert "albedo (GT)" in cols and "irradiance (GT)" in cols


def test_failed_evaluation_keeps_the_fit_and_a_rerun_does_not_fit_again(data, tmp_path,
                                                                          monkeypatch):
    run = tmp_path / "run"

    def broken(*args, **kwargs):
        raise ValueError("evaluation broke")

    monkeypatch.setattr(pipeline, "evaluate_variant", broken)
    assert _run(data["nerf"], run) == 2
    fit = run / "material" / "full"
    kept = {n: (fit / n).read_bytes() for n in ("model.ply", "light.json", "fit.json")}
    monkeypatch.undo()
    for table, config in tiny_cli.presets():  # undo() dropped the module's presets too
        monkeypatch.setitem(table, TINY, config)

    def no_fit(*args, **kwargs):
        raise AssertionError("the rerun fitted stage 4 again")

    from mi_shadowgs.stages.material import runner as material_runner

    monkeypatch.setattr(material_runner, "decompose", no_fit)
    assert _run(data["nerf"], run) == 0
    assert {n: (fit / n).read_bytes() for n in kept} == kept
    assert json.loads((fit / "metrics.json").read_text())["fit_s"] == \
        json.loads(kept["fit.json"])["fit_s"]
