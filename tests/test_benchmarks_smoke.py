"""Smoke tests of benchmarks/ (the benchmarks themselves are never tests): the shared
workload, one tiny configuration of each renderer, and the report writer."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from benchmarks import bm_raster
from benchmarks.workloads import SH_C0, WorkloadConfig, build_workload, split_by_area
from mi_shadowgs.core.frames import quaternion_to_matrix

TINY = {"n": 600, "res": 32, "warmup": 0, "iters": 1}


def test_workload_geometry():
    wl = build_workload(WorkloadConfig(n=1000, resolution=64))
    cfg = wl.config
    # N split by area: sphere pi * 1^2 / (pi + 4) of 1000 = 439.98 -> 440.
    assert (wl.n_sphere, wl.n_plane) == (440, 560) == split_by_area(cfg)
    spacing = math.sqrt((math.pi + 4.0) / 1000)
    assert wl.spacing == pytest.approx(spacing, rel=1e-12)
    np.testing.assert_allclose(wl.scale, 1.5 * spacing, rtol=1e-12)
    np.testing.assert_allclose(wl.ellipsoid_scales()[:, 2], 0.3 * 1.5 * spacing, rtol=1e-12)
    np.testing.assert_allclose(wl.opacity, 0.8)

    sph, pln = wl.position[:440], wl.position[440:]
    np.testing.assert_allclose(np.linalg.norm(sph - [0.0, 0.5, 0.0], axis=-1), 0.5, atol=1e-12)
    assert np.all(pln[:, 1] == 0.0) and np.all(np.abs(pln[:, [0, 2]]) <= 1.0)
    # Plane points fill the square evenly (low-discrepancy): each quadrant holds ~1/4.
    quadrant = (pln[:, 0] > 0).astype(int) * 2 + (pln[:, 2] > 0)
    assert np.bincount(quadrant, minlength=4).min() >= 0.22 * 560  # uniform: 0.25

    # The rotation's third column is the surface normal (outward on the sphere, +Y on the plane).
    normals = quaternion_to_matrix(wl.rotation)[:, :, 2]
    np.testing.assert_allclose(normals[:440], (sph - [0, 0.5, 0]) / 0.5, atol=1e-9)
    np.testing.assert_allclose(normals[440:], np.tile([0.0, 1.0, 0.0], (560, 1)), atol=1e-9)
    # Mitsuba's quaternions are xyzw; its degree-0 SH must give back the colours.
    np.testing.assert_array_equal(wl.quaternions_xyzw()[:, 3], wl.rotation[:, 0])
    np.testing.assert_allclose(SH_C0 * wl.sh_dc() + 0.5, wl.color, atol=1e-12)

    # Camera 2.5 from the sphere centre, 40-degree fov, the centre on the image centre.
    cam = wl.camera
    assert np.linalg.norm(cam.origin - [0.0, 0.5, 0.0]) == pytest.approx(2.5, rel=1e-12)
    assert math.degrees(cam.fov_x) == pytest.approx(40.0)
    uv, z = cam.project(np.array([[0.0, 0.5, 0.0]]))
    np.testing.assert_allclose(uv[0], [32.0, 32.0], atol=1e-9)
    assert z[0] == pytest.approx(2.5)


def test_fit_line():
    x = np.array([1.0, 2.0, 3.0, 5.0])
    slope, intercept, r2 = bm_raster.fit_line(x, 3.0 * x + 2.0)
    assert (slope, intercept, r2) == pytest.approx((3.0, 2.0, 1.0), abs=1e-9)  # exact line
    # y = (2, 1, 4, 4), by hand: Sxx = 8.75, Syy = 6.75, Sxy = 5.75; R^2 = Sxy^2 / (Sxx Syy),
    # slope = Sxy / Sxx. Float64 rounding only, hence 1e-12.
    slope, intercept, r2 = bm_raster.fit_line(x, x + np.array([1.0, -1.0, 1.0, -1.0]))
    assert r2 == pytest.approx(5.75**2 / (8.75 * 6.75), abs=1e-12)
    assert slope == pytest.approx(5.75 / 8.75, abs=1e-12)
    assert intercept == pytest.approx(2.75 - 2.75 * 5.75 / 8.75, abs=1e-12)


def _check_row(row, renderer):
    assert row["renderer"] == renderer and (row["n"], row["res"]) == (600, 32)
    for key in ("first_ms", "fwd_ms", "fwd_bwd_ms"):
        assert math.isfinite(row[key]) and row[key] > 0.0
    assert row["fwd_bwd_ms"] >= row["fwd_ms"]
    # Constant target 0.5 and colours in [0, 1]: the L1 loss lies in (0, 0.5].
    assert 0.05 < row["loss"] <= 0.5
    # A 1e-4 nudge against sigmas of ~0.05 moves the loss by far less than 1%.
    assert row["loss_drift"] < 1e-2
    assert 50.0 < row["peak_rss_mb"] < 4096.0
    # Gradients reach every parameter group (finite and not all zero).
    runner_cls = bm_raster.OursRunner if renderer == "ours" else bm_raster.MitsubaRunner
    assert tuple(row["grad_l1"]) == runner_cls.grad_names
    for name, value in row["grad_l1"].items():
        assert math.isfinite(value) and value > 0.0, name


def test_both_renderers_tiny(tmp_path):
    peer = bm_raster.run_case("mitsuba", **TINY, image_path=tmp_path / "mi.npy")
    _check_row(peer, "mitsuba")
    ours = bm_raster.run_case("ours", **TINY, image_path=tmp_path / "ours.npy")
    _check_row(ours, "ours")
    # ~600 splats of ~5 px radius, two thirds in view: thousands of pairs, far below 32^2 * 600.
    assert 1_000 < ours["pairs"] <= ours["box_pairs"] < 32 * 32 * 600
    assert 0 < ours["contributing"] <= ours["pairs"]

    img_mi, img_ours = np.load(tmp_path / "mi.npy"), np.load(tmp_path / "ours.npy")
    assert img_mi.shape == img_ours.shape == (32, 32, 3)
    assert np.isfinite(img_mi).all() and np.isfinite(img_ours).all()
    # Both must show the same scene from the same camera. They differ by design (3D
    # ellipsoids vs 2D surfels, Mitsuba's jittered spp=1 samples vs pixel centres, other
    # transmittance cut-offs); measured: mean 0.381 vs 0.359, coverage IoU 0.973 (32^2,
    # where the silhouette ring is a large share of the pixels). An upside-down image gives
    # IoU 0.53. (The scene is nearly mirror-symmetric, so a left-right mirror is not caught
    # here; tests of camera.py and the rasterizer's cross-check against Mitsuba cover that.)
    assert img_ours.mean() == pytest.approx(img_mi.mean(), rel=0.15)
    cov_mi, cov_ours = img_mi.sum(-1) > 0.05, img_ours.sum(-1) > 0.05
    assert (cov_mi & cov_ours).sum() / (cov_mi | cov_ours).sum() > 0.93


def test_report_from_rows(tmp_path):
    cfg = bm_raster.BenchConfig(resolutions=(128, 256), counts=(20_000,),
                                linearity_resolutions=(), image_case=(20_000, 128))
    assert bm_raster.sweep_cases(cfg) == [("ours", 20_000, 128), ("mitsuba", 20_000, 128),
                                          ("ours", 20_000, 256), ("mitsuba", 20_000, 256)]
    rows = []
    for res, pairs, t_ours, t_mi, rss in ((128, 1e6, 100.0, 500.0, 300.0),
                                          (256, 4e6, 400.0, 1000.0, 600.0)):
        base = {"n": 20_000, "res": res, "status": "ok", "first_ms": 1.0, "peak_rss_mb": rss}
        rows.append({**base, "renderer": "ours", "pairs": pairs, "fwd_ms": t_ours / 2,
                     "fwd_bwd_ms": t_ours, "fwd_bwd_cpu_ms": t_ours})
        rows.append({**base, "renderer": "mitsuba", "fwd_ms": t_mi / 2, "fwd_bwd_ms": t_mi,
                     "fwd_bwd_cpu_ms": 3 * t_mi})
    rows.append({"renderer": "ours", "n": 5_000, "res": 64, "status": "ok", "pairs": 2.5e5,
                 "fwd_ms": 12.5, "fwd_bwd_ms": 25.0, "fwd_bwd_cpu_ms": 25.0, "first_ms": 1.0,
                 "peak_rss_mb": 1.0})
    # A second, slower round of ours at 128^2 (another process on the cores): the faster
    # round's times are kept, the larger peak RSS too.
    rows.append({**rows[0], "round": 1, "fwd_bwd_ms": 300.0, "fwd_bwd_cpu_ms": 90.0,
                 "peak_rss_mb": 310.0, "first_ms": 3.0})
    best = {(r["renderer"], r["res"]): r for r in bm_raster.best_of_rounds(rows)}
    assert best[("ours", 128)]["fwd_bwd_ms"] == 100.0
    assert best[("ours", 128)]["fwd_bwd_cpu_ms"] == 90.0
    assert best[("ours", 128)]["peak_rss_mb"] == 310.0
    assert best[("ours", 128)]["first_ms"] == 2.0 and best[("ours", 128)]["rounds_ok"] == 2
    img = np.full((8, 8, 3), 0.25, dtype=np.float32)
    summary = bm_raster.write_report(tmp_path, rows, {"ours": img, "mitsuba": img}, cfg, "x")
    assert summary["goals"]["speedup_fwd_bwd_128_20k"] == pytest.approx(5.0)
    assert summary["goals"]["speedup_goal_128_met"] is False  # >= 10x
    assert summary["goals"]["speedup_fwd_bwd_256_20k"] == pytest.approx(2.5)
    assert summary["goals"]["speedup_goal_256_met"] is False
    assert summary["table"][0]["ratio_fwd_bwd_cpu"] == pytest.approx(1500.0 / 90.0)
    assert summary["goals"]["ours_peak_rss_mb_256_20k"] == pytest.approx(600.0)
    assert summary["goals"]["memory_goal_met"] is False
    # The three ours points lie on t = 1e-4 ms * pairs exactly.
    lin = summary["linearity"]["fwd_bwd_ms"]
    assert lin["r2"] == pytest.approx(1.0, abs=1e-12)
    assert lin["slope_ns_per_pair"] == pytest.approx(100.0)
    for name in ("raster.csv", "raster_runs.csv", "raster.json", "raster.md",
                 "raster_linearity.png", "raster_render_128_20000.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert "5.00x" in (tmp_path / "raster.md").read_text()


def test_scale_case_runs_in_its_own_process(tmp_path):
    from benchmarks import bm_raster_scale

    row = bm_raster_scale.run_case(32, 300, tmp_path, iters=1, warmup=0)
    assert row["rc"] == 0, row.get("error")
    assert row["method"] == "tiles" and row["fwd_bwd_ms"] > 0
    # The child's own peak: Python + Mitsuba alone take ~100 MB.
    assert 50 << 20 < row["peak_bytes"] < 2 << 30


def test_cuda_suite_says_it_was_skipped_without_a_gpu(tmp_path, monkeypatch):
    from benchmarks import bm_cuda
    from mi_shadowgs import backend

    monkeypatch.setattr(backend, "variant_available", lambda name: False)
    summary = bm_cuda.run_suite(tmp_path, preset="cpu-small", log=lambda msg: None)
    assert "needs an NVIDIA GPU" in summary["skipped"]
    assert "Skipped: cuda_ad_rgb needs an NVIDIA GPU" in summary["markdown"]
    assert json.loads((tmp_path / "cuda.json").read_text())["skipped"] == summary["skipped"]


def test_cuda_suite_report_ratios_and_failures():
    # The H100 figures of RESULTS.md for one case: llvm / cuda and Mitsuba /
    # ours are the ratios of the fwd+bwd medians; a failed case reads as failed, not as 0.
    from benchmarks import bm_cuda

    def case(renderer, variant, ms, status="ok"):
        return {"renderer": renderer, "variant": variant, "n": 20000, "res": 256,
                "status": status, "fwd_bwd_ms": ms}

    result = {"tests": {"summary": "2 passed, 18 deselected"},
              "raster": [case("ours", "cuda_ad_rgb", 4.75), case("ours", "llvm_ad_rgb", 21.13),
                         case("mitsuba", "cuda_ad_rgb", 50.80)],
              "runs": [{"variant": "cuda_ad_rgb", "status": "ok", "wall_s": 39.2,
                        "albedo_psnr": 34.52, "light_cosine": 0.9997, "shadow_iou": 0.891,
                        "relight_psnr": None},
                       {"variant": "llvm_ad_rgb", "status": "timeout", "wall_s": 1800.0}]}
    md = bm_cuda.markdown(result)
    assert "| 256^2, 20000 surfels | 4.75 | 21.13 | 50.80 | 4.4x | 10.7x |" in md
    assert "| cuda_ad_rgb | 39.2 | 34.52 | 0.9997 | 0.891 | n/a |" in md
    assert "| llvm_ad_rgb | timeout |" in md
    result["raster"][2]["status"] = "error"
    assert "| 4.75 | 21.13 | failed | 4.4x | - |" in bm_cuda.markdown(result)


def test_cuda_suite_raster_case_in_its_own_process(tmp_path, monkeypatch):
    # The suite's case runner on the backend every machine has: bm_raster in a subprocess
    # with the variant in its environment, its JSON row read back and labelled.
    from benchmarks import bm_cuda

    monkeypatch.setattr(bm_cuda, "RASTER_RUNS", (("ours", "llvm_ad_rgb"),))
    cfg = bm_cuda.CudaBenchConfig(raster_cases=((500, 32),), warmup=0, iters=1)
    rows = bm_cuda.raster_rows(cfg, tmp_path, log=lambda msg: None)
    assert len(rows) == 1 and rows[0]["status"] == "ok", rows
    assert rows[0]["variant"] == "llvm_ad_rgb" and rows[0]["n"] == 500 and rows[0]["res"] == 32
    assert rows[0]["fwd_bwd_ms"] > 0


def test_run_all_never_replaces_a_folder_it_did_not_write(someone_elses_folder, capsys):
    """--out continues an earlier benchmark run (its mark, or machine.json from before the
    mark), never someone else's folder: that is refused before any suite runs, with exit 2,
    and left as it was."""
    from conftest import untouched

    from benchmarks import run_all

    with pytest.raises(SystemExit) as e:
        run_all.main(["--out", str(someone_elses_folder), "--only", "view"])
    assert e.value.code == 2 and "did not write" in capsys.readouterr().err
    assert untouched(someone_elses_folder)
