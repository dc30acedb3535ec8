"""Guards at the door and on memory: refused surfel models (PLY files and user arrays), and
renders whose pair list would not fit the memory budget (bands of rows, or a clear error)."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import drjit as dr
import numpy as np
import pytest

from mi_shadowgs import cli
from mi_shadowgs.core import memory, raster, raster_common
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster import AOV_CHANNELS, RasterConfig, RasterMemoryError, rasterize
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.io import ply

N = 8


def _model(n=N, seed=0) -> ply.PlyModel:
    rng = np.random.default_rng(seed)
    return ply.PlyModel(position=rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
                        log_scale=np.log(rng.uniform(0.05, 0.2, (n, 2))).astype(np.float32),
                        rotation=rng.normal(size=(n, 4)).astype(np.float32),
                        opacity_logit=rng.normal(size=n).astype(np.float32),
                        channels={"sh": rng.normal(size=(n, 3)).astype(np.float32)})


def _set(m: ply.PlyModel, prop: str, rows, value) -> None:
    """Set a PLY property (as the file names it) of some vertices."""
    fields = {"x": ("position", 0), "y": ("position", 1), "z": ("position", 2),
              "opacity": ("opacity_logit", None), "f_dc_1": ("sh", 1)}
    fields |= {f"scale_{i}": ("log_scale", i) for i in range(2)}
    fields |= {f"rot_{i}": ("rotation", i) for i in range(4)}
    name, col = fields[prop]
    arr = m.channels[name] if name == "sh" else getattr(m, name)
    if col is None:
        arr[rows] = value
    else:
        arr[rows, col] = value


# (property set, vertices, value, expected message: field and first vertex, count)
REFUSED = [
    ("x", [3, 5], np.inf, r"'x' holds Inf at vertex 3 \(2 of 8 vertices\)"),
    ("z", [7], np.nan, r"'z' holds NaN at vertex 7 \(1 of 8 vertices\)"),
    ("opacity", [0], -np.inf, r"'opacity' holds Inf at vertex 0 \(1 of 8"),
    ("f_dc_1", [2, 3, 4], np.inf, r"'f_dc_1' holds Inf at vertex 2 \(3 of 8"),
    ("scale_1", [6], 89.0, r"'scale_1' holds a log-scale above 27.63 .* at vertex 6 \(1 of 8"),
    ("scale_0", [1, 2], 30.0, r"'scale_0' holds a log-scale above .* at vertex 1 \(2 of 8"),
    ("scale_0", [4], -100.0, r"'scale_0' holds a log-scale whose exp is zero .* at vertex 4"),
    ("rot_0", [], None, r"rot_0\.\.rot_3 hold a zero quaternion .* at vertex 4 \(2 of 8"),
]


@pytest.mark.parametrize("prop, rows, value, message", REFUSED)
def test_ply_refused_names_field_and_vertex(tmp_path, prop, rows, value, message):
    m = _model()
    if value is None:  # zero quaternions at vertices 4 (exactly) and 6 (|q| = 2e-13)
        m.rotation[4] = 0.0
        m.rotation[6] = [1e-13, 1e-13, -1e-13, 1e-13]
    else:
        _set(m, prop, rows, value)
    path = tmp_path / "bad.ply"
    ply.write_ply_model(path, m)
    with pytest.raises(ply.PlyError, match=re.escape(str(path)) + ".*" + message):
        ply.load_ply(path)


def test_ply_accepts_the_limits(tmp_path):
    # Just inside every bound: loads, and renders finite (not the identity, not culled).
    m = _model()
    m.log_scale[0] = 27.6  # 9.7e11, facing the camera
    m.rotation[0] = [1.0, 0.0, 0.0, 0.0]
    m.opacity_logit[0] = 2.0
    m.log_scale[2] = -87.3  # 1.2e-38 (culled by the rasterizer's scale_min)
    m.rotation[1] = [1e-11, 0.0, 0.0, 1e-11]  # |q| = 1.4e-11 > 1e-12: a 90 deg turn
    ply.write_ply_model(tmp_path / "ok.ply", m)
    s = ply.load_ply(tmp_path / "ok.ply")
    t_u = np.array(s.tangent_frame()[0], np.float64).reshape(3, N).T
    np.testing.assert_allclose(t_u[1], [0.0, 1.0, 0.0], atol=1e-6)  # normalised, not identity
    cam = Camera.look_at([0.3, 0.4, 2.0], [0, 0, 0], width=16, height=12, fov_x=0.8)
    out = rasterize(s, cam, {"sh": s.channels["sh"]}, aovs=tuple(AOV_CHANNELS))
    assert all(np.isfinite(v.numpy()).all() for v in out.values())
    assert out["alpha"].numpy().min() > 0.1  # the 1e12 surfel covers the whole image


def test_ply_refuses_an_empty_model(tmp_path):
    ply.write_ply_model(tmp_path / "empty.ply", _model(n=0))
    with pytest.raises(ply.PlyError, match=r"empty\.ply: no surfels \(0 vertices\)"):
        ply.load_ply(tmp_path / "empty.ply")


def _cameras_json(path: Path, res: int) -> Path:
    cam = Camera.look_at((0.3, 0.4, 2.5), (0.0, 0.0, 0.0), width=res, height=res, fov_x=0.8)
    path.write_text(json.dumps({"camera_angle_x": 0.8, "w": res, "h": res, "world_up": "+y",
                                "frames": [cam.to_frame_json("./test/r_0")]}))
    return path


def test_render_cli_refuses_inf_positions(tmp_path, capsys):
    # Used to render all black with exit status 0.
    m = _model()
    m.position[5, 1] = np.inf
    ply.write_ply_model(tmp_path / "inf.ply", m)
    rc = cli.main(["render", str(tmp_path / "inf.ply"), "--cameras",
                   str(_cameras_json(tmp_path / "t.json", 16)), "--out", str(tmp_path / "out")])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1, err
    assert "inf.ply" in err[0] and "'y' holds Inf at vertex 5" in err[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("field, change, message", [
    ("position", lambda a: a["position"].__setitem__((2, 0), np.nan), r"'position' holds NaN"
     r" at vertex 2"),
    ("scale", lambda a: a["scale"].__setitem__((3, 1), 0.0), r"'scale' must be > 0 .* at vertex 3"),
    ("scale", lambda a: a["scale"].__setitem__((1, 0), 1e13), r"'scale\[:, 0\] \(log\)' holds "
     r"a log-scale above .* at vertex 1"),
    ("scale", lambda a: a["scale"].__setitem__((5, 1), np.inf), r"'scale' holds Inf at vertex 5"),
    ("rotation", lambda a: a["rotation"].__setitem__(6, 0.0), r"rotation hold a zero "
     r"quaternion .* at vertex 6"),
    ("opacity", lambda a: a["opacity"].__setitem__(0, 1.5), r"'opacity' must lie in \[0, 1\] "
     r"at vertex 0"),
    ("channel", lambda a: a["channels"]["albedo"].__setitem__((7, 2), -np.inf),
     r"'channel albedo' holds Inf at vertex 7"),
    ("empty", lambda a: a.update({k: v[:0] for k, v in a.items() if k != "channels"},
                                 channels={}), r"no surfels"),
])
def test_from_numpy_refuses(field, change, message):
    rng = np.random.default_rng(1)
    a = {"position": rng.normal(size=(N, 3)), "scale": rng.uniform(0.1, 0.2, (N, 2)),
         "rotation": rng.normal(size=(N, 4)), "opacity": rng.uniform(0, 1, N),
         "channels": {"albedo": rng.uniform(size=(N, 3))}}
    Surfels.from_numpy(**a)  # valid as given
    change(a)
    with pytest.raises(ValueError, match=r"Surfels\.from_numpy: .*" + message):
        Surfels.from_numpy(**a)


# -- memory ------------------------------------------------------------------------------
def _scene(n=300, seed=0) -> Surfels:
    rng = np.random.default_rng(seed)
    return Surfels.from_numpy(rng.uniform(-0.5, 0.5, (n, 3)), rng.uniform(0.01, 0.4, (n, 2)),
                              rng.normal(size=(n, 4)), rng.uniform(0.05, 0.99, n),
                              {"c": rng.normal(size=(n, 3)).astype(np.float32)})


CAM = Camera.look_at([0.3, 0.4, 3.0], [0, 0, 0], width=40, height=30, fov_x=0.8)


def _bands(s: Surfels, config: RasterConfig, grad=False):
    g = raster_common.project(s, CAM, config).detach()
    return raster._plan_bands(g, CAM.width, CAM.height, config, grad)[0]


def test_bands_render_like_the_whole_image():
    s = _scene()
    box_pairs = raster.pair_counts(s, CAM)[0]
    # max_pairs forces bands as a tight budget would, without depending on this process's
    # resident memory.
    cfg = RasterConfig(max_pairs=box_pairs // 4)
    bands = _bands(s, cfg)
    assert len(bands) >= 4 and bands[0][0] == 0 and bands[-1][1] == CAM.height
    assert all(a[1] == b[0] for a, b in zip(bands, bands[1:], strict=False))
    aovs = tuple(AOV_CHANNELS)
    bg = {"c": [0.1, 0.2, 0.3]}
    whole = {k: v.numpy() for k, v in rasterize(s, CAM, s.channels, aovs=aovs,
                                                background=bg).items()}
    split = {k: v.numpy() for k, v in rasterize(s, CAM, s.channels, aovs=aovs, background=bg,
                                                config=cfg).items()}
    assert whole.keys() == split.keys()
    assert whole["alpha"].max() > 0.9 and (whole["alpha"] == 0).any()  # a real scene
    for k in whole:
        # Each pixel blends the same pairs in the same order; float32 scatter-adds run in
        # a thread-dependent order, which moves sums by an ulp or two (two renders of the
        # whole image differ the same way), and the Float64 transmittance scan restarts
        # per band. count and median_depth (one pair per pixel) are exact.
        tol = 0.0 if k in ("count", "median_depth") else 2e-6
        np.testing.assert_allclose(split[k], whole[k], rtol=tol, atol=tol, err_msg=k)
    # The per-view pair lists of the fixed-geometry stages, built in the same bands.
    ref = [np.asarray(x) for x in raster.splat_pairs(s, CAM)]
    got = [np.asarray(x) for x in raster.splat_pairs(s, CAM, cfg)]
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])
    np.testing.assert_allclose(got[2], ref[2], rtol=1e-6, atol=1e-7)  # Float64 scan restarts


def test_gradient_render_over_budget_is_refused():
    s = _scene()
    # The pair list's guard (the tiled path's: test_raster_tiles).
    cfg = RasterConfig(method="pairs", memory_budget_bytes=1 << 20)  # below any process
    for v in s.params().values():
        dr.enable_grad(v)
    with pytest.raises(RasterMemoryError, match=r"memory_budget_bytes=1048576.*gradients"):
        rasterize(s, CAM, s.channels, config=cfg)
    assert issubclass(RasterMemoryError, ValueError)  # the CLI: one line, exit 2
    with dr.suspend_grad(), pytest.raises(RasterMemoryError, match=r"one image row holds"):
        rasterize(s, CAM, s.channels, config=cfg)  # no gradient, but not one row fits
    # The default budget: a fraction of MemAvailable on top of what the process holds.
    assert len(_bands(s, RasterConfig(), grad=True)) == 1


def test_huge_surfel_box_is_clipped_to_the_image():
    # A surfel 1e6 times the scene covers the image many times over: H * W pairs, no more.
    s = Surfels.from_numpy([[0.0, 0.0, 0.0]], [[1e6, 1e6]], [[1.0, 0.2, 0.1, 0.0]], [0.5])
    assert raster.pair_counts(s, CAM) == (CAM.width * CAM.height,) * 2


def test_parse_bytes():
    assert memory.parse_bytes("2G", "b") == 2 << 30
    assert memory.parse_bytes("512MiB", "b") == 512 << 20
    assert memory.parse_bytes("1000", "b") == 1000
    for bad in ("lots", "0", "-5M", "inf"):
        with pytest.raises(ValueError, match="--x must be"):
            memory.parse_bytes(bad, "--x")


def test_render_of_1e6_scale_surfels_stays_under_the_budget(tmp_path):
    # The 2DGS-layout PLY of the issue: surfels 1e6 times the scene. 1000 of them at 128^2
    # make 16M pairs, ~0.8 GiB at the measured 51 B/pair; a 400 MiB budget must split the
    # render into bands and keep the process under it (it used to take 21.7 GB with 20k).
    n, res, budget = 1000, 128, 400 << 20
    assert n * res * res * RasterConfig().bytes_per_pair > 2 * budget  # bands are needed
    m = _model(n)
    m.log_scale[:] = math.log(1e6)
    m.opacity_logit[:] = -3.0  # alpha 0.05: every pair is kept
    ply.write_ply_model(tmp_path / "huge.ply", m)
    cams = _cameras_json(tmp_path / "t.json", res)
    code = ("import resource, subprocess, sys; "
            "r = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
            "print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); "
            "print(r.stderr[-2000:])")

    def render(budget_text, out):
        res_ = subprocess.run([sys.executable, "-c", code, sys.executable, "-m",
                               "mi_shadowgs.cli", "render",
                               str(tmp_path / "huge.ply"), "--cameras", str(cams),
                               "--out", str(tmp_path / out), "--memory-budget", budget_text],
                              capture_output=True, text=True, check=True, timeout=300)
        first, _, err = res_.stdout.partition("\n")
        rc, peak_kib = (int(v) for v in first.split())
        return rc, peak_kib * 1024, err

    rc, peak, err = render("400M", "out")
    assert rc == 0, err
    assert peak < budget, f"peak RSS {peak / 2**20:.0f} MiB over the 400 MiB budget"
    from mi_shadowgs.io.images import read_exr

    rgba = read_exr(tmp_path / "out" / "r_0.exr")
    assert np.isfinite(rgba).all() and rgba[..., 3].min() > 0.99  # covered everywhere
    # A budget below what one row needs: exit 2 with one line naming the setting.
    rc, _, err = render("100M", "out_small")
    lines = [ln for ln in err.splitlines() if ln.startswith("mi-shadowgs")]
    assert rc == 2 and len(lines) == 1 and "memory_budget_bytes" in lines[0], err


@pytest.mark.parametrize("setting, message", [
    ("refine_global=0", "refine_again_global needs the global pass"),
    ("no_such_field=1", "unknown material setting"),
])
def test_refit_lights_refuses_a_setting_before_any_work(tmp_path, capsys, setting, message):
    """``validation.refit_lights --set`` exits 2 naming what the stage-4 config refuses,
    before it reads the run (an empty folder here) or writes ``--out``."""
    from validation import refit_lights

    with pytest.raises(SystemExit) as e:
        refit_lights.main(["--run", str(tmp_path / "run"), "--data", str(tmp_path / "data"),
                           "--out", str(tmp_path / "out"), "--set", setting])
    assert e.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, message", [
    (["train", "{data}", "--out", "{out}", "--iterations", "-5"],
     "GeometryConfig.iterations must be >= 1, got -5"),
    (["train", "{data}", "--out", "{out}", "--iterations", "0"],
     "GeometryConfig.iterations must be >= 1, got 0"),
    # It reported albedo PSNR 143.7 dB, SSIM 1 for an albedo never fitted.
    (["run", "{data}", "--out", "{out}", "--material-iterations", "0"],
     "material.iterations must be >= 1 for a run, got 0"),
    (["segment", "{data}/m.ply", "--data", "{data}", "--out", "{out}", "--set",
      "iterations=0"], "SegmentationConfig.iterations must be >= 1, got 0"),
    (["segment", "{data}/m.ply", "--data", "{data}", "--out", "{out}", "--set", "log_every=0"],
     "SegmentationConfig.log_every must be >= 1, got 0"),
    (["segment", "{data}/m.ply", "--data", "{data}", "--out", "{out}", "--set",
      "iterations=abc"], "--set iterations='abc': segmentation setting 'iterations' takes int"),
    (["segment", "{data}/m.ply", "--data", "{data}", "--out", "{out}", "--set",
      "temperature=0"], "SegmentationConfig.temperature must be > 0"),
    (["segment", "{data}/m.ply", "--data", "{data}", "--out", "{out}", "--set", "nope=1"],
     "unknown segmentation setting 'nope'"),
])
def test_a_setting_out_of_range_exits_2_naming_it(tmp_path, capsys, argv, message):
    """Hard case: a count of 0 or below would write the untrained model as the stage's
    result (or divide by it), a word where a number goes would fail far from the flag. Each
    exits 2 with one line naming the setting, before anything is read or written."""
    data, out = tmp_path / "data", tmp_path / "out"
    argv = [a.format(data=data, out=out) for a in argv]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert not out.exists()


def test_parse_settings_reads_each_field_by_its_type():
    from mi_shadowgs.config import parse_settings
    from mi_shadowgs.stages.geometry.config import GeometryConfig

    got = parse_settings(GeometryConfig, ["iterations=7", "lambda_dist=3e3", "init=random",
                                          "hull_extent=none", "unmasked_opacity_reset=true"],
                         "geometry")
    assert got == {"iterations": 7, "lambda_dist": 3000.0, "init": "random",
                   "hull_extent": None, "unmasked_opacity_reset": True}
    assert type(got["lambda_dist"]) is float and type(got["iterations"]) is int
    for item, message in (("unmasked_opacity_reset=1", "takes bool"),
                          ("iterations=none", "takes int"), ("densify=3", "not set from"),
                          ("iterations", "expected KEY=VALUE")):
        with pytest.raises(ValueError, match=message):
            parse_settings(GeometryConfig, [item], "geometry")
