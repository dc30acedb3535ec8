"""The frame mapping of ``validation.photos`` (ground-truth cameras and lights into an
import's frame) and the view subsets of ``validation.view_count``."""

from __future__ import annotations

import json
import math

import numpy as np

from mi_shadowgs.core.frames import matrix_to_quaternion, quaternion_to_matrix
from mi_shadowgs.dataset.world_frame import Similarity
from tests.synthetic_asset import box_on_plane_surfels, ring_cameras, write_cameras
from validation.photos import fit_frame, mapped_lights, mapped_split
from validation.view_count import spread_views, subset_copy

# A similarity like an import's: scale, a turn mostly about the up axis, a shift.
THETA = math.radians(130.0)
TILT = math.radians(3.0)


def _similarity() -> Similarity:
    ry = np.array([[math.cos(THETA), 0, math.sin(THETA)], [0, 1, 0],
                   [-math.sin(THETA), 0, math.cos(THETA)]])
    rx = np.array([[1, 0, 0], [0, math.cos(TILT), -math.sin(TILT)],
                   [0, math.sin(TILT), math.cos(TILT)]])
    return Similarity(scale=0.37, rotation=rx @ ry, translation=np.array([0.4, -1.2, 2.0]))


def test_the_fitted_frame_is_the_similarity_that_made_the_cameras():
    sim = _similarity()
    truth = {f"train_{i:03d}.jpg": c for i, c in enumerate(ring_cameras(12))}
    imported = {n: type(c)(**{**c.__dict__, "c2w": sim.c2w(c.c2w)}) for n, c in truth.items()}
    imported.pop("train_005.jpg")  # a photo SfM did not register is left out of the fit
    fitted, residual = fit_frame(imported, truth)
    assert residual["photos"] == 11
    assert math.isclose(fitted.scale, sim.scale, rel_tol=1e-9)
    assert np.allclose(fitted.rotation, sim.rotation, atol=1e-9)
    assert np.allclose(fitted.translation, sim.translation, atol=1e-9)
    assert residual["centre_rms_pct"] < 1e-7 and residual["rotation_max_deg"] < 1e-5


def test_a_model_moved_by_the_frame_renders_the_same_under_the_mapped_cameras():
    """What the photo run's evaluation relies on: its model lives in the import's frame, and
    the mapped ground-truth camera sees there what the true camera sees of the true scene
    (alpha equal, depth scaled by the similarity's scale)."""
    from mi_shadowgs.core.raster import rasterize
    from mi_shadowgs.core.surfels import Surfels
    from mi_shadowgs.dataset.loader import Dataset, View

    sim = _similarity()
    surf = box_on_plane_surfels(600, 1.0, 0.3, 0.5)
    raw = surf.to_numpy()
    moved = Surfels.from_numpy(
        sim.points(raw["position"]), raw["scale"] * sim.scale,
        matrix_to_quaternion(sim.rotation @ quaternion_to_matrix(raw["rotation"])),
        raw["opacity"])
    cams = ring_cameras(3, size=48)
    views = [View(name=f"r_{i}", camera=c, image=np.zeros((48, 48, 3)),
                  mask=np.ones((48, 48), bool)) for i, c in enumerate(cams)]
    lights = {"training": {"lights": [{"direction": [0.0, 1.0, 0.0]}]}, "relightings": []}
    mapped = mapped_split(Dataset(root=None, split="test", views=views), sim, lights)
    for cam, view in zip(cams, mapped.views, strict=True):
        a = rasterize(surf, cam, None, aovs=("alpha", "depth"))
        b = rasterize(moved, view.camera, None, aovs=("alpha", "depth"))
        alpha_a, alpha_b = np.asarray(a["alpha"]), np.asarray(b["alpha"])
        assert alpha_a.max() > 0.9  # the view sees the box
        # float32 positions moved and projected again: a few 1e-4 at the splats' edges
        assert np.abs(alpha_a - alpha_b).max() < 2e-3
        assert np.allclose(np.asarray(b["depth"]), sim.scale * np.asarray(a["depth"]),
                           atol=2e-3 * sim.scale * 5.0)
    assert mapped.lights is lights


def test_mapped_lights_turn_every_directional_light_and_leave_env_maps_out():
    sim = _similarity()
    d0, d1 = np.array([0.6, 0.8, 0.0]), np.array([0.0, 0.6, -0.8])
    lights = {"convention": "x", "training": {
        "lights": [{"name": "light0", "direction": d0.tolist(), "irradiance": [3.0] * 3}],
        "light_map": {"radiance": [[1.0] * 3]}},
        "relightings": [{"name": "sun", "type": "directional",
                         "lights": [{"direction": d1.tolist(), "irradiance": [1.0] * 3}]},
                        {"name": "env", "type": "envmap", "path": "envmaps/x.exr"}]}
    out = mapped_lights(lights, sim.rotation)
    assert np.allclose(out["training"]["lights"][0]["direction"], sim.rotation @ d0)
    assert out["training"]["lights"][0]["irradiance"] == [3.0] * 3
    assert "light_map" not in out["training"]  # a grid map would need resampling
    assert [e["name"] for e in out["relightings"]] == ["sun"]
    assert np.allclose(out["relightings"][0]["lights"][0]["direction"], sim.rotation @ d1)
    assert lights["training"]["lights"][0]["direction"] == d0.tolist()  # input untouched


def test_spread_views_covers_the_sphere_before_repeating_a_side(tmp_path):
    cams = ring_cameras(16)
    centres = np.array([c.origin for c in cams])
    picked = spread_views(centres, 4)
    assert picked[0] == 0 and len(set(picked)) == 4
    az = sorted(np.degrees(np.arctan2(centres[picked, 2], centres[picked, 0])) % 360)
    gaps = np.diff(az + [az[0] + 360])
    assert gaps.max() < 135  # four views spread around, not bunched on one side

    src = tmp_path / "data"
    (src / "train").mkdir(parents=True)
    (src / "test").mkdir()
    write_cameras(src / "transforms_train.json", cams, "train")
    write_cameras(src / "transforms_test.json", cams[:2], "test")
    for i in range(16):
        for suffix in (".exr", "_albedo.exr", "_irradiance_0.exr"):
            (src / "train" / f"r_{i:03d}{suffix}").write_text(str(i))
    (src / "lights.json").write_text("{}")
    dst = subset_copy(src, tmp_path / "sub", 4)
    frames = json.loads((dst / "transforms_train.json").read_text())["frames"]
    stems = sorted(f["file_path"].split("/")[-1] for f in frames)
    assert stems == sorted(f"r_{i:03d}" for i in picked)
    assert sorted(p.name for p in (dst / "train").iterdir()) == sorted(
        f"{s}{suffix}" for s in stems for suffix in (".exr", "_albedo.exr", "_irradiance_0.exr"))
    assert (dst / "lights.json").is_file() and (dst / "transforms_test.json").is_file()
    assert len(json.loads((src / "transforms_train.json").read_text())["frames"]) == 16


def test_the_light_sweep_spans_the_hemisphere_and_judges_lights_by_their_share():
    from validation.light_sweep import MAX_ERROR_DEG, markdown, sweep_pairs, sweep_row

    pairs = sweep_pairs()
    assert len(pairs) >= 8
    strong = {int(p["light0_azimuth"]) for p in pairs.values()}
    assert strong == set(range(0, 360, 45))  # all azimuths
    for p in pairs.values():
        els = [float(p[f"light{k}_elevation"]) for k in range(2)]
        assert all(15 <= e <= 75 for e in els)
        assert (int(p["light1_azimuth"]) - int(p["light0_azimuth"])) % 360 == 180
    assert {float(p["light0_elevation"]) for p in pairs.values()} >= {15.0, 75.0}

    def row(errors):
        return {"scene": "x", "lights": "s0", "light_pair": pairs["s0"], "variants": {"full": {
            "angular_error_deg": errors, "fitted_lights": 2, "light_cosine": 1.0,
            "spurious_irradiance_fraction": 0.0, "shadow_iou": 0.9}}}

    assert sweep_row(row([0.5, MAX_ERROR_DEG - 0.1]))["within"]
    # the weak light carries a third of the irradiance (>= 25 %): it must be found too
    assert not sweep_row(row([0.5, MAX_ERROR_DEG + 0.1]))["within"]
    assert not sweep_row(row([0.5, None]))["within"]  # a lost light
    # The decided figure stands beside the shadow IoU; a row evaluated before it says n/a,
    # and every line of the table has its header's cells.
    decided = row([0.5, 1.0])
    decided["variants"]["full"]["shadow_iou_decided"] = 0.93
    table = markdown([sweep_row(decided), sweep_row(row([0.5, 1.0]))])
    lines = [ln for ln in table.splitlines() if ln.startswith("|")]
    assert "shadow IoU (decided)" in lines[0]
    assert {ln.count("|") for ln in lines} == {lines[0].count("|")}
    assert "| 0.900 | 0.930 |" in lines[2] and "| 0.900 | n/a |" in lines[3]


def test_photos_albedo_detail_and_seed_are_checked_first_and_reach_the_runs(
        tmp_path, monkeypatch, capsys):
    """`validation.photos --albedo-detail W --seed N` runs both fits with `run
    --albedo-detail W --seed N`; a value `run` would refuse exits 2 before any data is
    made."""
    import pytest

    import mi_shadowgs.pipeline as pipeline
    from validation import photos

    with pytest.raises(SystemExit) as exc:
        photos.main(["--out", str(tmp_path / "p"), "--albedo-detail", "-1"])
    assert exc.value.code == 2 and "detail_prior >= 0" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        photos.main(["--out", str(tmp_path / "p"), "--seed", "-1"])
    assert exc.value.code == 2 and "seed must be >= 0" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()
    seen = []
    monkeypatch.setattr(pipeline, "run_pipeline", lambda data, out, config, **kw: seen.append(
        config) or {"total_seconds": 1.0})
    photos._timed_run(tmp_path, tmp_path / "run", "cpu-small", tmp_path / "t.json", 0.1)
    photos._timed_run(tmp_path, tmp_path / "run2", "cpu-small", tmp_path / "t.json", seed=3)
    assert [(c.material.detail_prior, c.geometry.seed, c.material.seed) for c in seen] == [
        (0.1, 0, 0), (0.0, 3, 3)]
    # A study folder whose runs were made with another W: exit 2 naming the setting.
    from mi_shadowgs.io.provenance import ProvenanceError

    def refuse(data, out, config, **kw):
        raise ProvenanceError(f"{out}: other settings (material.detail_prior: 0.0 there, "
                              "0.1 now)")

    monkeypatch.setattr(pipeline, "run_pipeline", refuse)
    with pytest.raises(SystemExit) as exc:
        photos._timed_run(tmp_path, tmp_path / "run", "cpu-small", tmp_path / "t.json", 0.1)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "detail_prior: 0.0 there, 0.1 now" in err
    assert "give another --out" in err


def test_a_resumed_run_adds_its_reused_stages_recorded_seconds_and_says_so(tmp_path,
                                                                         monkeypatch):
    """A study run interrupted in stage 5 and resumed: the call's own seconds (the last
    stage) would report a whole run as 2 s. Its time adds what the reused stages 1, 2 and 4
    recorded, the table marks it resumed, and a finished run reads both back."""
    import json

    import mi_shadowgs.pipeline as pipeline
    from validation import photos

    stages = ["Stage 1: geometry", "Stage 2: material segmentation",
              "Stages 3-5: visibility, decomposition, relighting"]
    fresh = {"total_seconds": 300.0, "reused_stages": [],
             "stages": [{"name": n, "seconds": 100.0} for n in stages]}
    resumed = {"total_seconds": 2.0,
               "reused_stages": ["geometry", "segmentation", "material (full)"],
               "stages": [{"name": n, "seconds": None} for n in stages]}
    monkeypatch.setattr(pipeline, "run_pipeline", lambda data, out, config, **kw: fresh)
    times = tmp_path / "t.json"
    assert photos._timed_run(tmp_path, tmp_path / "whole", "cpu-small", times) == (300.0, False)

    run = tmp_path / "cut"
    (run / "geometry").mkdir(parents=True)
    (run / "geometry" / "log.csv").write_text("iteration,loss,time\n25,0.2,1.5\n2500,0.06,198.5\n")
    (run / "segmentation").mkdir()
    (run / "segmentation" / "segmentation.json").write_text(json.dumps({"seconds_stage": 15.0}))
    (run / "material" / "full").mkdir(parents=True)
    (run / "material" / "full" / "metrics.json").write_text(json.dumps({"fit_s": 57.0}))
    monkeypatch.setattr(pipeline, "run_pipeline", lambda data, out, config, **kw: resumed)
    assert photos._timed_run(tmp_path, run, "cpu-small", times) == (272.5, True)
    (run / "summary.json").write_text("{}")  # finished: read back, not measured again
    assert photos._timed_run(tmp_path, run, "cpu-small", times) == (272.5, True)
    assert json.loads(times.read_text()) == {"whole": [300.0, False], "cut": [272.5, True]}

    scores = {"albedo_psnr": 30.0, "albedo_ssim": 0.9, "object_albedo_psnr": 31.0,
              "shadow_iou": 0.88, "shadow_iou_decided": 0.9, "relight_psnr": 20.0,
              "light_cosine": 0.99,
              "light_angular_errors_deg": [0.2, 0.5], "fitted_lights": 2}
    rec = {"gt": {"wall_s": 300.0, "resumed": False, "scores": scores},
           "photos": {"wall_s": 361.0, "resumed": True, "scores": scores},
           "differences": {"albedo_psnr": 0.0, "shadow_iou": 0.0, "shadow_iou_decided": 0.0,
                           "relight_psnr": 0.0},
           "within_bounds": True, "import_s": 89.0, "photos_imported": 64,
           "frame": {"photos": 64, "centre_rms_pct": 0.1, "rotation_rms_deg": 0.05}}
    md = photos.markdown(rec)
    assert "| 361 (resumed) |" in md and "| 300 |" in md and "interrupted and resumed" in md
