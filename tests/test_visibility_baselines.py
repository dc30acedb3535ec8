"""Table 2 baselines (Gaussian-based ray tracing, voxel grid): float64 NumPy references,
an analytic disk-over-plane shadow, grazing and below-horizon lights, interface checks."""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mi_shadowgs.config import ConfigError
from mi_shadowgs.core.frames import frame_to_quaternion
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.stages.visibility import baselines
from mi_shadowgs.stages.visibility.shadow_maps import SceneBounds, render_shadow_maps

SPACING = 0.03
DISK_R, DISK_H = 0.5, 1.0
BOUNDS = SceneBounds((0.0, 1.0, 0.0), 0.75, 4.0)  # around the disk (the occluder)


def _grid_surfels(half: float, height: float, spacing: float, radius: float | None = None,
                  sigma_factor: float = 0.7) -> dict:
    g = np.arange(-half, half + 1e-9, spacing)
    x, z = np.meshgrid(g, g)
    keep = np.ones(x.shape, bool) if radius is None else x ** 2 + z ** 2 <= radius ** 2
    pos = np.stack([x[keep], np.full(keep.sum(), height), z[keep]], 1)
    n = len(pos)
    return {"position": pos, "scale": np.full((n, 2), sigma_factor * spacing),
            "rotation": frame_to_quaternion(np.tile([0.0, 1.0, 0.0], (n, 1))),
            "opacity": np.full(n, 0.99)}


def _surfels(*parts: dict) -> Surfels:
    return Surfels.from_numpy(**{k: np.concatenate([p[k] for p in parts]) for k in parts[0]})


def _disk() -> Surfels:
    return _surfels(_grid_surfels(DISK_R, DISK_H, SPACING, radius=DISK_R))


def _plane_points(half: float = 2.0, n: int = 160):
    xs = np.linspace(-half, half, n)
    px, pz = np.meshgrid(xs, xs)
    p = np.stack([px.ravel(), np.zeros(px.size), pz.ravel()], 1)
    pts = mi.Point3f(*p.T.astype(np.float32))
    nrm = dr.zeros(mi.Vector3f, len(p)) + mi.Vector3f(0.0, 1.0, 0.0)
    return p, pts, nrm


def _analytic_shadow(p: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Points [M, 3] on y = 0 whose ray toward ``light`` crosses the disk (float64)."""
    q = p + (DISK_H / light[1]) * light
    return q[:, 0] ** 2 + q[:, 2] ** 2 < DISK_R ** 2


def _iou(a, b):
    return np.count_nonzero(a & b) / np.count_nonzero(a | b)


BUILDERS = {
    "gaussian": lambda s, d, b: baselines.trace_surfels(s, d, b, baselines.GaussianTraceConfig()),
    "voxel": lambda s, d, b: baselines.voxelize_surfels(s, d, b, baselines.VoxelConfig()),
}


# -- float64 references -------------------------------------------------------------------
def _reference_arrays(surfels: Surfels) -> dict[str, np.ndarray]:
    """Float64 surfel values with each frame from SciPy: t_u, t_v, n are the columns of the
    rotation of the (w, x, y, z) quaternion (docs/conventions.md)."""
    s = surfels.to_numpy()
    rot = Rotation.from_quat(s["rotation"][:, [1, 2, 3, 0]]).as_matrix()  # [N, 3, 3]
    return {"position": s["position"], "scale": s["scale"], "opacity": s["opacity"],
            "t_u": rot[:, :, 0], "t_v": rot[:, :, 1], "n": rot[:, :, 2]}


def _reference_occupancy(arr: dict, lower: np.ndarray, voxel: float, g: int,
                         splat_sigma: float) -> np.ndarray:
    """Occupancy [G, G, G] as VoxelConfig documents it, written out surfel by surfel: each
    covers opacity * 2 pi s_u s_v / h^2 of a voxel's cross-section, a fifth at its centre and
    at +-splat_sigma sigma along t_u and t_v each; a voxel holds at most 1."""
    grid = np.zeros((g, g, g))
    for i in range(len(arr["position"])):
        su, sv = arr["scale"][i]
        cover = arr["opacity"][i] * 2.0 * math.pi * su * sv / voxel ** 2 / 5.0
        for off in (0.0 * arr["t_u"][i], splat_sigma * su * arr["t_u"][i],
                    -splat_sigma * su * arr["t_u"][i], splat_sigma * sv * arr["t_v"][i],
                    -splat_sigma * sv * arr["t_v"][i]):
            cell = np.floor((arr["position"][i] + off - lower) / voxel).astype(int)
            if np.all((cell >= 0) & (cell < g)):
                grid[tuple(cell)] += cover
    return np.minimum(grid, 1.0)


def test_gaussian_transmittance_matches_float64_reference():
    rng = np.random.default_rng(3)
    n = 40
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    surf = Surfels.from_numpy(rng.uniform(-0.3, 0.3, (n, 3)), rng.uniform(0.05, 0.15, (n, 2)),
                              frame_to_quaternion(normals), rng.uniform(0.2, 0.95, n))
    # No stagger: the traced planes pass through the surfels' own centres.
    cfg = baselines.GaussianTraceConfig(soft=True, max_hits=64, t_min=0.0, offset=0.0,
                                        stagger=0.0)
    tracer = baselines.trace_surfels(surf, [[0.0, 1.0, 0.0]], SceneBounds((0, 0, 0), 0.6, 4.0), cfg)
    arr = _reference_arrays(surf)
    centre = arr["position"]
    o = rng.uniform(-0.4, 0.4, (300, 3))
    o[:, 1] = -1.0
    d = rng.normal(size=(300, 3)) * 0.3 + [0.0, 1.0, 0.0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = np.asarray(tracer.transmittance(mi.Point3f(*o.T.astype(np.float32)),
                                          mi.Vector3f(*d.T.astype(np.float32)), mi.Bool(True)))
    # Reference: every plane crossing (t > 0) inside the quad of half-size extent sigma.
    nrm = arr["n"]
    t = np.einsum("sk,sk->s", centre, nrm)[None] - o @ nrm.T  # [R, S] numerator
    t = t / (d @ nrm.T)
    q = o[:, None] + t[..., None] * d[:, None]  # [R, S, 3]
    u = np.einsum("rsk,sk->rs", q - centre, arr["t_u"]) / arr["scale"][:, 0]
    v = np.einsum("rsk,sk->rs", q - centre, arr["t_v"]) / arr["scale"][:, 1]
    inside = (t > 0) & (np.abs(u) <= cfg.extent) & (np.abs(v) <= cfg.extent)
    alpha = np.minimum(arr["opacity"], cfg.alpha_max) * np.exp(-0.5 * (u * u + v * v))
    ref = np.prod(np.where(inside, 1.0 - alpha, 1.0), axis=1)
    # float32 hit points; rays grazing a quad's border by < 1e-6 may fall either side, and
    # there alpha < 1.2e-2 * opacity: one such ray may differ by that much.
    err = np.abs(got - ref)
    assert np.quantile(err, 0.99) < 1e-4, np.quantile(err, 0.99)
    assert err.max() < 1.5e-2
    assert np.count_nonzero(ref < 0.9) > 50  # the rays do cross surfels


def test_voxel_occupancy_and_march_match_float64_reference():
    surf = _disk()
    cfg = baselines.VoxelConfig(resolution=16, soft=True, tau_stop=1e9, start_offset=0.0)
    vox = baselines.voxelize_surfels(surf, [[0.0, 1.0, 0.0]], BOUNDS, cfg)
    # The grid: the voxel frame from the bounds (a cube of half-size radius * margin about
    # the centre), then the surfels' coverage, against the reference splat.
    half = BOUNDS.radius * cfg.margin
    lower, voxel = np.asarray(BOUNDS.center) - half, 2.0 * half / cfg.resolution
    np.testing.assert_allclose(vox.lower, lower, rtol=0, atol=1e-12)
    assert vox.voxel == pytest.approx(voxel, rel=1e-12)
    grid = _reference_occupancy(_reference_arrays(surf), lower, voxel, cfg.resolution,
                                cfg.splat_sigma)
    assert (grid == 1.0).any() and ((grid > 0) & (grid < 1)).any()  # clipped and partial
    np.testing.assert_allclose(vox.grid_np, grid, rtol=0, atol=1e-9)  # float64 both sides
    # Coverage is conserved where no voxel saturates (small surfels): the grid sums to
    # sum opacity * 2 pi s_u s_v / h^2, all five splat points landing inside the grid.
    small = _surfels(_grid_surfels(DISK_R, DISK_H, SPACING, DISK_R, 0.1))
    cfg64 = baselines.VoxelConfig(resolution=64)
    h64 = 2.0 * half / 64
    unclipped = baselines.voxelize_surfels(small, [[0.0, 1.0, 0.0]], BOUNDS, cfg64).grid_np
    arr = small.to_numpy()
    raw = arr["opacity"] * 2 * math.pi * arr["scale"].prod(1) / h64 ** 2
    assert 0.0 < unclipped.max() < 1.0
    np.testing.assert_allclose(unclipped.sum(), raw.sum(), rtol=1e-9)  # float64 both sides
    # March: trilinear occupancy at the same sample points, in float64.
    rng = np.random.default_rng(1)
    o = np.column_stack([rng.uniform(-0.4, 0.4, 64), np.full(64, 0.5), rng.uniform(-0.4, 0.4,
                                                                                      64)])
    d = np.column_stack([rng.normal(0, 0.3, 64), np.ones(64), rng.normal(0, 0.3, 64)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = np.asarray(vox.optical_depth(mi.Point3f(*o.T.astype(np.float32)),
                                       mi.Vector3f(*d.T.astype(np.float32)), mi.Bool(True)))
    g, h, lo = cfg.resolution, voxel, lower
    hi = lo + g * h
    ref = np.zeros(64)
    step = cfg.step * h
    for r in range(64):
        t0, t1 = (lo - o[r]) / d[r], (hi - o[r]) / d[r]  # d has no zero component
        t_exit = np.maximum(t0, t1).min()
        t = max(np.minimum(t0, t1).max(), 0.0) + 0.5 * step
        while t < t_exit:
            gp = (o[r] + t * d[r] - lo) / h - 0.5
            i0 = np.floor(gp).astype(int)
            f = gp - i0
            occ = 0.0
            for c in np.ndindex(2, 2, 2):
                i = i0 + c
                if np.all((i >= 0) & (i < g)):
                    w = np.prod(np.where(np.array(c) == 1, f, 1 - f))
                    occ += w * grid[tuple(i)]
            ref[r] += cfg.density / h * step * occ
            t += step
    assert ref.max() > 1.0  # the rays cross the disk
    # float32 positions and step accumulation over ~50 steps; optical depths are O(1-10).
    np.testing.assert_allclose(got, ref, rtol=2e-3, atol=2e-3)


# -- analytic shadow, grazing and below-horizon lights ------------------------------------
# Thresholds: the surfel disk's edge is soft (rim surfels reach ~sigma past the radius), so
# even exact tracing of it differs from the analytic disk in a ~1-sigma band (IoU ~0.94
# measured for both the tracer and the shadow maps); the grid blurs the edge by about one
# voxel (1.5 / 64 scene units) on top (measured 0.91).
@pytest.mark.parametrize("name,threshold", [("gaussian", 0.90), ("voxel", 0.85)])
def test_disk_shadow_on_plane_matches_analytic(name, threshold):
    light = np.array([0.5, 1.0, 0.2])
    light /= np.linalg.norm(light)
    p, pts, nrm = _plane_points()
    method = BUILDERS[name](_disk(), light[None], BOUNDS)
    vis = np.asarray(method.evaluate(pts, nrm))
    assert vis.shape == (len(p),)
    assert _iou(vis < 0.5, _analytic_shadow(p, light)) > threshold


@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_point_major_order_over_lights(name):
    lights = np.array([[0.5, 1.0, 0.2], [-0.3, 1.0, -0.6]])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    p, pts, nrm = _plane_points(n=60)
    method = BUILDERS[name](_disk(), lights, BOUNDS)
    assert method.count == 2
    vis = np.asarray(method.evaluate(pts, nrm)).reshape(len(p), 2)
    for k in range(2):
        assert _iou(vis[:, k] < 0.5, _analytic_shadow(p, lights[k])) > 0.8


@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_grazing_light_no_acne_and_below_horizon(name):
    # Receiver plane of surfels around the disk's foot; at 3 degrees the disk's shadow falls
    # ~19 units away, so every plane point must be lit: any shadow here is acne.
    surf = _surfels(_grid_surfels(DISK_R, DISK_H, SPACING, radius=DISK_R),
                    _grid_surfels(0.7, 0.0, 0.05))
    p, pts, nrm = _plane_points(half=0.6, n=50)
    for elevation, expect in ((3.0, 1.0), (0.0, 0.0), (-10.0, 0.0)):
        el = math.radians(elevation)
        light = np.array([[math.cos(el), math.sin(el), 0.0]])
        method = BUILDERS[name](surf, light, BOUNDS)
        vis = np.asarray(method.evaluate(pts, nrm))
        assert np.all(np.isfinite(vis))
        assert np.mean(vis == expect) >= (0.99 if expect else 1.0), (elevation, vis.mean())
        free = np.asarray(method.evaluate(pts, None))  # no normals: no horizon test, finite
        assert np.all(np.isfinite(free)) and np.all((free >= 0) & (free <= 1))


def test_soft_gaussian_visibility_in_unit_interval():
    light = np.array([[0.0, 1.0, 0.0]])
    _, pts, nrm = _plane_points(half=0.8, n=40)
    soft = baselines.trace_surfels(_disk(), light, BOUNDS, baselines.GaussianTraceConfig(soft=True))
    v = np.asarray(soft.evaluate(pts, nrm))
    assert np.all((v >= 0) & (v <= 1)) and np.any((v > 0.05) & (v < 0.95))  # soft rim


def test_configs_and_presets():
    from mi_shadowgs.presets import baseline_configs

    assert baseline_configs("paper")[0] == baselines.GaussianTraceConfig()
    assert baseline_configs("cpu-small")[1].resolution < baselines.VoxelConfig().resolution
    with pytest.raises(ConfigError, match="Gaussian-based"):
        baseline_configs("nope")
    with pytest.raises(ValueError):
        baselines.VoxelConfig(resolution=1)
    with pytest.raises(ValueError):
        baselines.GaussianTraceConfig(max_hits=0)
    with pytest.raises(ValueError, match="directions"):
        baselines.trace_surfels(_disk(), np.zeros((1, 3)), BOUNDS)


# -- validation scoring (validation/visibility.py) ----------------------------------------
def test_validation_score_counts_shadowed_pixels_in_mask():
    from validation.run_all import VALIDATIONS
    from validation.visibility import Case, score

    assert "visibility" in VALIDATIONS
    mask = np.zeros((1, 2, 3), bool)
    mask[0, :, :2] = True  # 4 pixels count; column 2 is background
    gt = np.zeros((1, 2, 3, 1), bool)
    gt[0, 0, :, 0] = True  # shadowed: (0,0), (0,1) in the mask, (0,2) outside
    pred = np.ones((2, 3, 1), np.float32)
    pred[0, 0, 0] = pred[1, 0, 0] = pred[0, 2, 0] = 0.0  # hits (0,0), false (1,0), bg (0,2)
    case = Case("t", None, None, np.zeros((1, 3)), [None], [], [], mask, gt)
    s = score([pred], case)
    # shadow: |{(0,0)}| / |{(0,0),(0,1),(1,0)}|; visible: {(1,1)} / {(0,1),(1,0),(1,1)}
    assert s["shadow_iou"] == pytest.approx(1 / 3)
    assert s["visible_iou"] == pytest.approx(1 / 3)
    assert s["accuracy"] == pytest.approx(2 / 4)


def test_make_validate_gives_the_pipeline_models_to_the_visibility_table(tmp_path, monkeypatch):
    """run_all runs the pipeline before the visibility validation and hands it each scene's
    stage-1 model with that scene's dataset; unpaired --model/--data fail before any work."""
    import validation.visibility as vv
    from validation import run_all

    names = list(run_all.VALIDATIONS)
    assert names.index("pipeline") < names.index("visibility")
    for scene in ("bunny", "default"):
        (tmp_path / "pipeline" / scene / "run" / "geometry").mkdir(parents=True)
        (tmp_path / "pipeline" / scene / "run" / "geometry" / "model.ply").write_text("")
    seen = {}
    monkeypatch.setattr(vv, "run", lambda out, quick, model, data, **kw: seen.update(
        model=model, data=data, **kw) or {"markdown": ""})
    run_all._visibility(tmp_path / "visibility", True)
    assert [m.parts[-4] for m in seen["model"]] == ["bunny", "default"]
    # the split comes with the runs' maps (visibility_runs; tests/test_run_all.py)
    assert not seen.get("factors") and "preset" not in seen
    assert seen["data"] == [tmp_path / "pipeline" / s / "data" for s in ("bunny", "default")]
    monkeypatch.undo()
    with pytest.raises(ValueError, match="every --model needs its --data"):
        vv.run(tmp_path / "out", quick=True, model=["a.ply", "b.ply"], data=["d"])


def test_two_stage1_models_of_one_dataset_are_told_apart_by_their_run(tmp_path):
    """Two models fitted to one dataset (say, two stage-1 settings) are compared in one
    validation: each case also names its run folder, and the folders above it where those
    are alike (the same scene's datasets at two sizes). One model given twice would mix the
    results (keyed by name); that is refused before any work, with exit 2."""
    import validation.visibility as vv

    data = tmp_path / "ficus-low" / "data"
    a = tmp_path / "ld3000" / "geometry" / "model.ply"
    b = tmp_path / "ld300" / "geometry" / "model.ply"
    assert vv.model_case_names([a, b], [data, data]) == [
        "stage-1 ficus-low (ld3000)", "stage-1 ficus-low (ld300)"]
    assert vv.model_case_names([a], [data]) == ["stage-1 ficus-low"]
    other = tmp_path / "again" / "ld3000" / "geometry" / "model.ply"
    assert vv.model_case_names([a, other], [data, data]) == [
        f"stage-1 ficus-low ({tmp_path.name}/ld3000)", "stage-1 ficus-low (again/ld3000)"]
    small, medium = (tmp_path / t / "ficus-low" for t in ("t20", "t23m"))
    assert vv.model_case_names(
        [small / "run" / "geometry" / "model.ply", medium / "run" / "geometry" / "model.ply"],
        [small / "data", medium / "data"]) == [
        "stage-1 ficus-low (t20/ficus-low/run)", "stage-1 ficus-low (t23m/ficus-low/run)"]
    with pytest.raises(ValueError, match="given twice"):
        vv.model_case_names([a, a], [data, data])
    with pytest.raises(SystemExit) as e:  # before any scene is loaded or traced
        vv.main(["--out", str(tmp_path / "out"), "--model", str(a), "--data", str(data),
                 "--model", str(a), "--data", str(data), "--quiet"])
    assert e.value.code == 2 and not (tmp_path / "out").exists()


def test_a_model_is_named_by_the_stage_that_wrote_it(tmp_path):
    """A run's PLYs of stages 1, 2 and 4 (its layout) are named by their stage; two of one
    run are told apart by it alone, and a PLY outside a run's layout is a "model"."""
    import validation.visibility as vv

    data = tmp_path / "ficus-low" / "data"
    run = tmp_path / "ficus-low" / "run"
    plys = [run / "geometry" / "model.ply", run / "segmentation" / "model.ply",
            run / "material" / "full" / "model.ply", run / "material" / "no_vis" / "model.ply",
            tmp_path / "mine.ply"]
    assert vv.model_case_names(plys, [data] * len(plys)) == [
        "stage-1 ficus-low", "stage-2 ficus-low", "stage-4 ficus-low",
        "stage-4 no_vis ficus-low", "model ficus-low"]
    other = tmp_path / "again" / "material" / "full" / "model.ply"
    assert vv.model_case_names([plys[2], other], [data, data]) == [
        "stage-4 ficus-low (run)", "stage-4 ficus-low (again)"]


@pytest.fixture(scope="module")
def exact_model(tmp_path_factory):
    """A tiny default-scene dataset (40 px: enough shadow pixels per view to score) and a
    "stage-1 model" that is the exact surfels themselves: (data, model PLY, config)."""
    import dataclasses

    from tiny_cli import TINY, presets

    import mi_shadowgs.api as msg
    import validation.visibility as vv
    from mi_shadowgs import presets as run_presets
    from mi_shadowgs.dataset.scene import dataset_scene
    from mi_shadowgs.io.ply import save_ply

    root = tmp_path_factory.mktemp("factors")
    with pytest.MonkeyPatch.context() as mp:
        for table, config in presets():
            if table is run_presets.GENERATE:
                config = dataclasses.replace(config, width=40, height=40)
            mp.setitem(table, TINY, config)
        data = msg.generate_dataset(msg.scene_path("default"), root / "data", preset=TINY)
    # the counts are for the dataset's 40 px views (exact_surfel_config scales from there)
    cfg = dataclasses.replace(vv.ValidationConfig(), n_views=2, object_surfels=3000,
                              base_surfels=800, resolution=40)
    model = root / "exact" / "geometry" / "model.ply"
    model.parent.mkdir(parents=True)
    save_ply(model, vv.scene_surfels(dataset_scene(data), cfg))
    return data, model, cfg


def test_factor_split_of_a_model_that_is_the_exact_geometry(exact_model, tmp_path):
    """``--factors`` wiring: a "stage-1 model" that is the exact surfels themselves scores
    the same as the exact-occluder and exact-geometry swaps, and the true receivers score
    the same over either occluders; with one point per pixel the pixel-area truth is the
    point truth (IoU 1), with more it blends at the shadows' edges (below 1)."""
    import validation.visibility as vv
    from mi_shadowgs.stages.visibility.shadow_maps import VisibilityConfig

    data, model, cfg = exact_model
    case = vv.model_case(model, data, cfg)
    base = VisibilityConfig()
    one = vv.model_factors(case, cfg, base, samples=1)
    assert set(one) == {k for k, _ in vv.FACTORS}
    assert one["exact_occluders"] == one["run"] and one["exact_geometry"] == one["run"]
    assert one["true_receivers_exact_occluders"] == one["true_receivers"]
    assert one["pixel_ceiling"] == 1.0
    assert 0.3 < one["run"] < 1.0 and all(0.0 <= v <= 1.0 for v in one.values())
    sparse = vv.model_factors(case, cfg, base, samples=1, exact_surfels=600)
    assert all(sparse[k] == one[k] for k in ("run", "true_points", "true_receivers"))
    assert sparse["exact_geometry"] != one["exact_geometry"]  # the exact surfels' count
    # The horizon columns' cast shadows are the run's without its horizon test: with the
    # model's own test they give the run back.
    cast_cfg = dataclasses.replace(base, horizon_cos=-math.inf)
    cast_maps = render_shadow_maps(case.surfels, case.directions, case.bounds, cast_cfg)
    h, w = case.mask.shape[1:]
    own = []
    for v in range(len(case.cameras)):
        n = np.stack([np.asarray(case.normals[v][k]) for k in range(3)], -1)  # [H*W, 3]
        cast = np.asarray(cast_maps.evaluate(case.points[v], case.normals[v],
                                             case.footprints[v])).reshape(h, w, -1)
        own.append(cast * ((n @ case.directions.T) > base.horizon_cos).reshape(h, w, -1))
    assert vv.score(own, case)["shadow_iou"] == pytest.approx(one["run"], abs=1e-12)
    assert one["true_horizon"] != one["run"]  # the model's normals are not the truth's
    # One point per pixel: the pixel-area horizon test is the pixel centre's.
    assert one["pixel_horizon"] == one["true_horizon"]
    four = vv.model_factors(case, cfg, base, samples=4)
    assert 0.5 < four["pixel_ceiling"] < 1.0
    boxed = ("pixel_ceiling", "pixel_horizon")  # the keys that read the pixel's area
    assert {k: v for k, v in four.items() if k not in boxed} == \
        {k: v for k, v in one.items() if k not in boxed}
    assert four["pixel_horizon"] != one["pixel_horizon"]
    table = vv.factors_markdown({case.name: one})
    assert table.count("\n") == 2 and "pixel-area truth" in table
    for flag in ("--factors", "--models-only"):  # both need a model; refused before any work
        with pytest.raises(SystemExit) as e:
            vv.main(["--out", str(tmp_path / "out"), flag, "--quiet"])
        assert e.value.code == 2 and not (tmp_path / "out").exists()


def test_models_only_factor_table_from_the_command_line(exact_model, tmp_path, monkeypatch):
    """``--models-only --factors``: the model's Table 2 row and its factor split, without
    the ground-truth scenes, the sweep or the timing (seconds instead of minutes)."""
    import json

    import validation.visibility as vv

    data, model, cfg = exact_model
    monkeypatch.setattr(vv, "QUICK", cfg)
    out = tmp_path / "vis"
    assert vv.main(["--out", str(out), "--quick", "--models-only", "--factors",
                    "--factor-samples", "2", "--model", str(model), "--data", str(data),
                    "--quiet"]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [".mi_shadowgs_study.json", "README.md", "factors.md", "summary.json",
                     "table2.csv", "table2.md", "units"]
    summary = json.loads((out / "summary.json").read_text())
    name = vv.model_case_names([model], [data])[0]
    assert list(summary["factors"]) == [name]
    row = summary["factors"][name]
    pixel = summary["results"]["Pixel-based (ours)"][name]["shadow_iou"]
    assert row["run"] == pytest.approx(pixel)  # the split's own run is the table's
    readme = (out / "README.md").read_text()
    assert "Where each model's IoU is lost" in readme and "Threshold tau" not in readme
    assert "2^2 points per pixel" in readme
    # no ground-truth scenes: the header names the models' views, not the spiral's
    assert "test-spiral" not in readme and "Stage-1 models: the first" in readme


def _models_only(exact_model, out, *options) -> dict:
    """``--quick --models-only`` on the exact model (at its small config); the summary."""
    import json

    import validation.visibility as vv

    data, model, cfg = exact_model
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(vv, "QUICK", cfg)
        assert vv.main(["--out", str(out), "--quick", "--models-only", "--model", str(model),
                        "--data", str(data), "--quiet", *options]) == 0
    return json.loads((out / "summary.json").read_text())


def test_receiver_band_scores_the_median_surface_receivers(exact_model, tmp_path, capsys):
    """``--receiver-band``: a model's receivers rendered as stages 4-5 of the cpu presets
    render them (``shading.pixel_geometry`` on the median surface), in the Table 2 row and
    in the factor split's exact geometry; recorded in the summary and the README."""

    import validation.visibility as vv
    from mi_shadowgs.core import shading
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.stages.visibility.shadow_maps import VisibilityConfig

    data, model, cfg = exact_model
    blend = vv.model_case(model, data, cfg)
    surface = vv.model_case(model, data, cfg, receiver_band=0.5)
    cam = surface.cameras[0]
    ref = shading.pixel_geometry(load_ply(model), cam, surface_band=0.5)
    for k in range(3):
        np.testing.assert_array_equal(np.asarray(surface.points[0][k]),
                                      np.asarray(ref.points[k]))
        np.testing.assert_array_equal(np.asarray(surface.normals[0][k]),
                                      np.asarray(ref.normal[k]))
    # the band changes receivers here (the object's edges over the base), else the
    # comparison above would not tell the two apart
    n0 = np.stack([np.asarray(blend.normals[0][k]) for k in range(3)], -1)
    n1 = np.stack([np.asarray(surface.normals[0][k]) for k in range(3)], -1)
    assert (np.sum(n0 * n1, -1)[blend.mask[0].ravel()] < 0.99).sum() >= 3
    # the split renders the exact surfels' receivers with the same band: a model that is
    # the exact surfels scores as its exact geometry
    split = vv.model_factors(surface, cfg, VisibilityConfig(), samples=1,
                             receiver_band=0.5)
    assert split["exact_geometry"] == split["run"]
    for bad, msg in ((["--receiver-band", "-1", "--model", str(model), "--data", str(data)],
                      "must be >= 0"), (["--receiver-band", "0.5"], "give --model")):
        with pytest.raises(SystemExit) as e:
            vv.main(["--out", str(tmp_path / "bad"), "--quiet", *bad])
        assert e.value.code == 2 and not (tmp_path / "bad").exists()
        assert msg in capsys.readouterr().err
    out = tmp_path / "vis"
    summary = _models_only(exact_model, out, "--receiver-band", "0.5")
    assert summary["receiver_band"] == 0.5
    assert "median surface (receiver band 0.5)" in (out / "README.md").read_text()


def test_preset_gives_the_pixel_method_a_runs_maps_and_receivers(exact_model, tmp_path,
                                                                  capsys):
    """``--preset P``: the pixel method's maps at P's visibility settings and the models'
    receivers at P's band, as a run at P has them (the paper's maps by default); recorded in
    the summary and the README; an unknown preset exits 2 naming it."""

    import validation.visibility as vv
    from mi_shadowgs.presets import visibility_config as get_config
    from mi_shadowgs.stages.visibility.shadow_maps import render_shadow_maps

    data, model, cfg = exact_model
    preset = get_config("cpu-small")
    assert preset.receiver_band == 0.5 and preset.projection == "orthographic"
    case = vv.model_case(model, data, cfg, receiver_band=preset.receiver_band)
    expected = vv.run_method(
        lambda: render_shadow_maps(case.surfels, case.directions, case.bounds, preset),
        case)["shadow_iou"]
    out = tmp_path / "vis"
    summary = _models_only(exact_model, out, "--preset", "cpu-small")
    assert summary["visibility_preset"] == "cpu-small" and summary["receiver_band"] == 0.5
    assert summary["visibility"]["projection"] == "orthographic"
    name = vv.model_case_names([model], [data])[0]
    assert summary["results"]["Pixel-based (ours)"][name]["shadow_iou"] == expected
    # the preset's maps are orthographic already: no second, identical row
    assert sorted(summary["results"]) == ["Gaussian-based", "Pixel-based (ours)", "Voxel-based"]
    assert "the visibility settings of preset 'cpu-small'" in (out / "README.md").read_text()
    # --receiver-band given: used as given, over the preset's
    summary = _models_only(exact_model, out, "--preset", "cpu-small", "--receiver-band", "0",
                           "--overwrite")
    assert summary["receiver_band"] == 0.0
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        vv.main(["--out", str(tmp_path / "bad"), "--models-only", "--model", str(model),
                 "--data", str(data), "--preset", "cpu-tiny", "--quiet"])
    assert e.value.code == 2 and not (tmp_path / "bad").exists()
    assert "'cpu-tiny'" in capsys.readouterr().err


def test_never_replaces_a_folder_it_did_not_write(someone_elses_folder, capsys):
    """--out is replaced when it holds an earlier output of this validation (its
    summary.json), never someone else's folder: refused before any work, with exit 2."""
    from conftest import untouched

    import validation.visibility as vv

    with pytest.raises(SystemExit) as e:
        vv.main(["--out", str(someone_elses_folder), "--quick", "--quiet"])
    assert e.value.code == 2 and "did not write" in capsys.readouterr().err
    assert untouched(someone_elses_folder)


def test_exact_surfels_scale_with_the_views_pixel_count():
    """The exact geometry keeps its surfels per pixel at every view size: counts given for
    ``cfg.resolution``^2 views grow with the pixel count (a fixed 80k on the object was too
    sparse at 512^2); at that size they are as given."""
    import dataclasses

    import validation.visibility as vv
    from mi_shadowgs.core.camera import Camera

    def cam(w, h):
        return Camera.look_at(np.array([0.0, 1.0, 4.0]), np.zeros(3), fov_x=0.7, width=w,
                              height=h)

    cfg = vv.ValidationConfig()  # 20000 / 4000 for 128^2 views
    same = vv.exact_surfel_config(cfg, cam(128, 128))
    assert (same.object_surfels, same.base_surfels) == (20000, 4000)
    big = vv.exact_surfel_config(cfg, cam(512, 256), object_surfels=40000)
    assert (big.object_surfels, big.base_surfels) == (320000, 32000)
    small = vv.exact_surfel_config(dataclasses.replace(cfg, resolution=40), cam(20, 20))
    assert (small.object_surfels, small.base_surfels) == (5000, 1000)


def test_a_full_run_after_a_smoke_run_in_the_same_folder(exact_model, tmp_path, monkeypatch):
    """``make validate`` after ``make validate --quick`` into the same folder: the smoke
    run's units are its own (``quick-``), so the full run makes its own instead of being
    refused for their other settings."""
    import validation.visibility as vv

    data, model, cfg = exact_model
    monkeypatch.setattr(vv, "QUICK", cfg)
    monkeypatch.setattr(vv, "ValidationConfig", lambda: cfg)  # the full run, at test size
    out = tmp_path / "vis"
    argv = ["--out", str(out), "--models-only", "--model", str(model), "--data", str(data),
            "--quiet"]
    assert vv.main([*argv, "--quick"]) == 0
    assert vv.main(argv) == 0
    units = sorted(p.name for p in (out / "units").iterdir())
    quick = [n for n in units if n.startswith("quick-")]
    assert len(quick) == 4 and len(units) == 8  # one row per method, each run its own


def test_lights_of_ones_own_replace_the_eight_and_key_the_results(tmp_path, capsys):
    """``--lights AZ,EL ...`` scores a model at chosen directions (a fitted light's own);
    the lights are a case setting, so units made under other lights are not reused; a
    malformed or sub-horizon pair exits 2 naming --lights before any work."""
    import validation.visibility as vv

    assert vv.checked_lights(["35,50", (215, 35.5)]) == ((35.0, 50.0), (215.0, 35.5))
    assert "lights" in vv.CASE_FIELDS
    cfg = vv.ValidationConfig()
    assert vv.case_settings(cfg) != vv.case_settings(
        dataclasses.replace(cfg, lights=vv.checked_lights(["35,50"])))
    data = tmp_path / "d"
    model = tmp_path / "run" / "geometry" / "model.ply"
    for bad, said in ((["35"], "expected AZ,EL"), (["35,0"], "elevation must be in (0, 90]"),
                      (["x,40"], "field azimuth must be a number"),
                      (["35,91"], "elevation must be in (0, 90]"),
                      (["35,inf"], "field elevation must be finite")):
        with pytest.raises(SystemExit) as e:
            vv.main(["--out", str(tmp_path / "out"), "--model", str(model), "--data",
                     str(data), "--models-only", "--lights", *bad, "--quiet"])
        err = capsys.readouterr().err
        assert e.value.code == 2 and "--lights" in err and said in err, err
        assert not (tmp_path / "out").exists()
