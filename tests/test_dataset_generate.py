"""Dataset generator acceptance tests: (a) camera convention, (b) analytic shadow,
(c) buffers agree with the path-traced image, (d) material ids, (e) bad input; determinism.

Small images and few views keep the whole file to seconds on 2 cores.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import map_coordinates, maximum_filter, minimum_filter

from mi_shadowgs.cli import main as cli_main
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import direction_from_angles
from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.cameras import train_cameras
from mi_shadowgs.dataset.generate import ViewRenderer, camera_rays, trace_ground_truth
from mi_shadowgs.dataset.scene import SceneError, load_scene
from mi_shadowgs.io.provenance import MANIFEST_NAME
from mi_shadowgs.presets import GENERATE as PRESETS
from mi_shadowgs.presets import generate_config as get_config
from mi_shadowgs.scenes import scene_path

SIZE = 64


@pytest.fixture(scope="module")
def default_setup():
    return load_scene(scene_path("default"))


@pytest.fixture(scope="module")
def two_views(default_setup):
    cams = train_cameras(2, np.random.default_rng(3), default_setup.object_center, 4.0,
                         layout.NERF_CAMERA_ANGLE_X, SIZE, SIZE, 20.0, 70.0)
    return cams, trace_ground_truth(default_setup, cams)


def _rays(o, d):
    import mitsuba as mi

    return mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))


def test_presets():
    assert (PRESETS["cpu-small"].width, PRESETS["cpu-small"].n_train,
            PRESETS["cpu-small"].n_test) == (128, 64, 32)
    assert (PRESETS["paper"].width, PRESETS["paper"].n_train, PRESETS["paper"].n_test) == \
        (800, 100, 200)
    medium = PRESETS["cpu-medium"]
    assert (medium.width, medium.height) == (256, 256) and 64 <= medium.n_train <= 100
    large = PRESETS["gpu-large"]
    assert (large.width, large.height, large.n_train) == (512, 512, 96)


def test_gpu_large_differs_from_cpu_medium_only_where_the_size_asks():
    # 512^2 views: no screen-space prune (it removed the flat surfaces' surfels at 400^2 and
    # 800^2), a larger surfel cap, and maps of twice the texels; every other setting is
    # cpu-medium's, so a gpu-large row differs from a cpu-medium one by the size alone.
    import dataclasses

    from mi_shadowgs.presets import GEOMETRY, MATERIAL, VISIBILITY

    large, medium = GEOMETRY["gpu-large"], GEOMETRY["cpu-medium"]
    assert large.densify.screen_size_threshold is None
    assert large.densify.max_surfels > medium.densify.max_surfels
    assert dataclasses.replace(large, densify=medium.densify) == medium
    assert VISIBILITY["gpu-large"] == dataclasses.replace(VISIBILITY["cpu-medium"],
                                                          resolution=1024)
    assert MATERIAL["gpu-large"] == MATERIAL["cpu-medium"]


def test_every_table_has_every_preset_and_only_one_module_defines_them():
    # A run with --preset P reads P from every table; a missing one would fail mid-run.
    import re
    from pathlib import Path

    from mi_shadowgs import presets
    from mi_shadowgs.config import PRESET_NAMES

    for table in (presets.PRESETS, presets.GEOMETRY, presets.SEGMENTATION,
                  presets.CHROMATICITY, presets.VISIBILITY, presets.MATERIAL, presets.RELIGHT,
                  presets.EXPORT, presets.GENERATE, presets.IMPORT, presets.GAUSSIAN_TRACE,
                  presets.VOXEL):
        assert set(PRESET_NAMES) <= set(table), sorted(table)
    package = Path(presets.__file__).parent
    others = [p for p in package.rglob("*.py") if p.name != "presets.py"
              and re.search(r"^\w*PRESETS\s*=\s*[{d]", p.read_text(), re.M)]
    assert not others, f"preset tables outside mi_shadowgs/presets.py: {others}"


def test_default_scene_normalised(default_setup):
    s = default_setup
    assert [p.material_id for p in s.parts] == [1, 2, 3, 4]
    assert s.base_id == 5
    assert s.object_radius == pytest.approx(1.0, abs=1e-9)
    assert s.object_center[[0, 2]] == pytest.approx([0.0, 0.0], abs=1e-9)
    lo = min(float(sh.bbox().min[1]) for sh in s.scene.shapes() if sh.id().startswith("object_"))
    # float32 bbox of the transformed shapes: the object stands on y = 0
    assert abs(lo) < 1e-5
    # two opposing lights, 180 degrees apart in azimuth, both above the horizon
    assert abs((s.lights[1].azimuth_deg - s.lights[0].azimuth_deg) % 360 - 180) < 1e-9
    assert min(lt.direction[1] for lt in s.lights) > 0


def test_a_depth_reprojects_between_views(default_setup, two_views):
    """(a) unproject view A's depth, project into B: z agrees within 1e-3 relative."""
    (cam_a, cam_b), gt = two_views
    d_a, d_b = gt["depth"]
    hit = d_a > 0
    x = cam_a.unproject(cam_a.pixel_grid()[hit.ravel()], d_a[hit])
    uv, z = cam_b.project(x)
    # Seen by B: an unoccluded segment from the point to B's centre (Mitsuba ray_test).
    to_b = cam_b.origin - x
    dist = np.linalg.norm(to_b, axis=1)
    to_b /= dist[:, None]
    ray = _rays(x + 1e-4 * to_b, to_b)
    import mitsuba as mi

    ray.maxt = mi.Float((dist * (1 - 1e-4)).astype(np.float32))
    seen = ~np.asarray(default_setup.scene.ray_test(ray))
    px, py = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    inside = (px >= 0) & (px <= SIZE - 1) & (py >= 0) & (py <= SIZE - 1)
    x0 = np.clip(np.floor(px).astype(int), 0, SIZE - 2)
    y0 = np.clip(np.floor(py).astype(int), 0, SIZE - 2)
    corners = [(y0, x0), (y0, x0 + 1), (y0 + 1, x0), (y0 + 1, x0 + 1)]
    # B's depth is sampled at pixel centres; interpolating 1/z bilinearly is exact on a
    # plane, so only compare where B's 4 neighbours lie on one flat face (same part, same
    # normal): across creases and silhouettes interpolation error is not a convention error.
    mat_b, n_b = gt["material"][1], gt["normal"][1]
    same = np.all([mat_b[c] == mat_b[corners[0]] for c in corners], axis=0)
    flat = np.all([np.sum(n_b[c] * n_b[corners[0]], -1) > 0.995 for c in corners], axis=0)
    filled = np.all([d_b[c] > 0 for c in corners], axis=0)
    both = inside & seen & same & flat & filled
    inv = map_coordinates(1.0 / np.where(d_b > 0, d_b, 1.0), [py, px], order=1,
                          mode="nearest")
    rel = np.abs(1.0 / inv - z) / z
    assert both.sum() > 800  # enough shared pixels for the percentage to mean something
    assert np.mean(rel[both] < 1e-3) >= 0.99


def test_b_sphere_shadow_matches_analytic_ellipse():
    """(b) a sphere over a plane: visibility == the analytic shadow, IoU >= 0.98 at 128^2."""
    az, el, r, c = 30.0, 50.0, 0.5, np.array([0.0, 1.0, 0.0])
    setup = load_scene(scene_path("sphere_plane"),
                       {"light0_azimuth": str(az), "light0_elevation": str(el),
                        "sphere_radius": str(r), "sphere_center": "0, 1, 0"})
    l_dir = direction_from_angles(az, el)
    shadow_c = c - c[1] / l_dir[1] * l_dir  # where the centre's shadow falls on y = 0
    cam = Camera.look_at(shadow_c + np.array([0.8, 3.5, 1.5]), shadow_c, fov_x=0.9,
                         width=128, height=128)
    gt = trace_ground_truth(setup, [cam])
    on_base = (gt["material"][0] == setup.base_id).ravel()
    # Analytic: intersect each pixel ray with y = 0, then test the ray toward the light
    # against the sphere (closest approach < r, ahead of the point).
    o, d, _ = camera_rays([cam])
    p = o + (-o[:, 1] / d[:, 1])[:, None] * d
    q = c - p
    along = q @ l_dir
    perp2 = np.sum(q * q, -1) - along**2
    analytic = (along > 0) & (perp2 < r * r) & on_base
    traced = (gt["visibility"][0][..., 0].ravel() < 0.5) & on_base
    iou = np.sum(analytic & traced) / np.sum(analytic | traced)
    assert analytic.sum() > 500  # the ellipse covers many pixels
    assert iou >= 0.98


def test_c_image_equals_direct_plus_nonnegative_indirect(default_setup, two_views):
    """(c) diffuse, unshadowed pixels: image = albedo/pi * sum(E n.l V) + indirect >= 0."""
    cams, gt = two_views
    spp = 512
    # independent samples: the noise figures below were measured with them
    renderer = ViewRenderer(cams[0], spp=spp, max_depth=5, sampler="independent")
    diffuse = [p.material_id for p in default_setup.parts if p.bsdf == "diffuse"]
    diffuse.append(default_setup.base_id)
    rels = []
    for i, cam in enumerate(cams):
        img = renderer.render(default_setup.scene, cam, seed=100 + i)[..., :3]
        mat, vis = gt["material"][i], gt["visibility"][i].min(-1)
        direct = gt["albedo"][i] / math.pi * gt["irradiance"][i].sum(-2)
        # Interior of unshadowed diffuse regions: the image integrates the pixel's footprint
        # while the buffers hold the pixel centre, so pixels next to an edge are left out.
        interior = (minimum_filter(mat, 3) == maximum_filter(mat, 3)) & \
            (minimum_filter(vis, 3) > 0.5)
        ok = np.isin(mat, diffuse) & interior & (direct.min(-1) > 0.02)
        rels.append((img[ok] - direct[ok]) / direct[ok])
    rel = np.concatenate(rels)
    assert len(rel) > 2000
    # Mean: indirect light is non-negative. The per-pixel noise (measured ~2%, mostly
    # Mitsuba choosing one of the two lights per sample) averages over > 2000 x 3 values to
    # a standard error of ~0.05%, so -0.5% is > 5 standard errors; the upper bound 0.1
    # catches a lost 1/pi or cos factor (indirect light is ~1-2% in this open scene).
    assert -0.005 <= rel.mean() <= 0.1
    # Per pixel: 99% within -8% (4x the measured per-pixel noise at 512 spp).
    assert np.mean(rel >= -0.08) >= 0.99


def test_two_multijittered_passes_closer_than_256_independent_spp(default_setup, two_views):
    """The presets' samples: two multi-jittered passes of 64 per pixel are closer to a
    4096-spp reference than 256 independent samples (the earlier sampler), so
    that half the paths lower the images' noise floor."""
    cams, _ = two_views

    def psnr(cam, ref, spp, **kw):
        img = ViewRenderer(cam, spp, 4, **kw).render(default_setup.scene, cam, 1)[..., :3]
        return 10 * math.log10(float(ref.max()) ** 2 / np.mean((img - ref) ** 2))

    for cam in cams:
        ref_renderer = ViewRenderer(cam, 1024, 4, sampler="independent")
        ref = np.mean([ref_renderer.render(default_setup.scene, cam, 100 + s)[..., :3]
                       for s in range(4)], axis=0)  # its own noise: ~12 dB below 256 spp
        two_passes = psnr(cam, ref, 128, pass_spp=64)
        # Measured +1.8 dB on average over six 128^2 views of this scene, every view
        # ahead; 0.5 dB of margin for these 64^2 views' edges.
        assert two_passes >= psnr(cam, ref, 256, sampler="independent") + 0.5
        # one pass of 64: its noise is that of one stratified set (the passes average)
        assert two_passes >= psnr(cam, ref, 64) + 2.0


def test_d_material_ids_cover_each_part(default_setup, two_views):
    """(d) material id k <=> the pixel's ray hits part k first (ray-traced per part alone)."""
    import mitsuba as mi

    cams, gt = two_views
    o, d, f = camera_rays(cams)
    depth = gt["depth"].ravel()
    t_full = depth / np.sum(d * f, -1)
    ids = default_setup.shape_material_ids()
    shapes = {s.id(): s for s in default_setup.scene.shapes()}
    for sid, mid in ids.items():
        alone = mi.load_dict({"type": "scene", sid: shapes[sid]}, optimize=False)
        si = alone.ray_intersect(_rays(o, d))
        t = np.asarray(si.t)
        # the part alone is hit at the full scene's first-hit distance (float32: 1e-5 rel)
        first = np.asarray(si.is_valid()) & (depth > 0) & (np.abs(t - t_full) <= 1e-5 * t_full)
        labelled = gt["material"].ravel() == mid
        assert labelled.sum() > 50, sid
        assert int(np.sum(labelled != first)) == 0, sid
    assert set(np.unique(gt["material"])) == {0, *ids.values()}


# -- the command, atomicity and errors --------------------------------------------------
# the sky pinned: the cpu-small preset's "auto" would add the shipped env maps where
# ../shared/data exists, and the file counts below would depend on the machine
TINY = ["--width", "32", "--height", "32", "--n-train", "2", "--n-test", "1", "--spp", "4",
        "--envmap", "sky", "--no-progress"]


def _run(argv, capsys):
    rc = cli_main(["generate", *argv])
    return rc, capsys.readouterr()


def _listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def test_generate_deterministic_and_recognised(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    assert _run([str(scene_path("default")), "--out", str(a), "--seed", "7", *TINY],
                capsys)[0] == 0
    assert _run(["default", "--out", str(b), "--seed", "7", *TINY], capsys)[0] == 0
    la, lb = _listing(a), _listing(b)
    # 2 + 1 views x 10 files, 4 relit test images (3 directional, the procedural sky), 2
    # transforms (and the val split's, the test one for NeRF tools), lights.json,
    # dataset.json, the sky's env map, the manifest
    assert len(la) == 3 * 10 + 4 + 7
    assert json.loads(la[MANIFEST_NAME])["files"] == sorted(set(la) - {MANIFEST_NAME})
    assert la.keys() == lb.keys()
    differ = [k for k in la if la[k] != lb[k]]
    assert differ == []  # bit-identical for the same seed
    info = json.loads((a / "dataset.json").read_text())
    assert len(info["fingerprint"]) == 64 and info["seed"] == 7
    lights = json.loads((a / "lights.json").read_text())
    assert len(lights["training"]["lights"]) == 2
    assert len(lights["relightings"]) >= 3
    assert np.array(lights["training"]["light_map"]["radiance"]).shape == (128, 3)
    # same inputs again: recognised, nothing rewritten
    mtime = (a / "dataset.json").stat().st_mtime_ns
    rc, cap = _run(["default", "--out", str(a), "--seed", "7", *TINY], capsys)
    assert rc == 0 and "nothing to do" in cap.out
    assert (a / "dataset.json").stat().st_mtime_ns == mtime


def _assert_error(argv, capsys, tmp_path, must_name, out=None):
    before = sorted(p.name for p in tmp_path.iterdir())
    rc, cap = _run(argv, capsys)
    lines = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert rc == 2
    assert len(lines) == 1, cap.err  # one clear line
    assert must_name in lines[0]
    after = sorted(p.name for p in tmp_path.iterdir())
    assert after == before  # nothing written, no partial folder left behind
    return lines[0]


def test_e_bad_input(tmp_path, capsys):
    out = tmp_path / "out"
    # a missing mesh
    _assert_error([str(scene_path("mesh")), "--out", str(out), "-D", "mesh=/nonexistent.ply",
                   *TINY], capsys, tmp_path, "/nonexistent.ply")
    # malformed XML
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type='sphere' id='object_a'></scene>")
    _assert_error([str(bad), "--out", str(out), *TINY], capsys, tmp_path, "bad.xml")
    # an unknown preset
    _assert_error(["default", "--out", str(out), "--preset", "huge", *TINY], capsys,
                  tmp_path, "'huge'")
    # an unknown scene parameter
    _assert_error(["default", "--out", str(out), "-D", "no_such=1", *TINY], capsys,
                  tmp_path, "'no_such'")
    # a pass count the sampler would round (multijitter: 32 -> 35), and an spp that is not
    # a whole number of passes
    _assert_error(["default", "--out", str(out), *TINY, "--spp", "32"], capsys, tmp_path,
                  "not 32")
    _assert_error(["default", "--out", str(out), *TINY, "--spp", "72"], capsys, tmp_path,
                  "spp=72")
    _assert_error(["default", "--out", str(out), *TINY, "--sampler", "bogus"], capsys,
                  tmp_path, "'bogus'")
    assert not out.exists()
    # an output folder holding a different dataset: untouched unless --overwrite
    assert _run(["default", "--out", str(out), "--seed", "1", *TINY], capsys)[0] == 0
    before = _listing(out)
    msg = _assert_error(["default", "--out", str(out), "--seed", "2", *TINY], capsys,
                        tmp_path, str(out))
    assert "different dataset" in msg
    assert _listing(out) == before
    assert _run(["default", "--out", str(out), "--seed", "2", "--overwrite", *TINY],
                capsys)[0] == 0
    assert json.loads((out / "dataset.json").read_text())["seed"] == 2


def test_killed_generate_resumes_from_its_views(tmp_path, capsys, monkeypatch):
    """A run stopped after some renders leaves its partial folder; the same command again
    renders only the missing views and writes the bytes of an uninterrupted run."""
    from mi_shadowgs.dataset import generate

    ref, out = tmp_path / "ref", tmp_path / "out"
    argv = ["default", "--seed", "3", *TINY]
    assert _run([*argv, "--out", str(ref)], capsys)[0] == 0
    render = generate.ViewRenderer.render
    calls = []

    def dying_render(self, *a, **kw):
        calls.append(1)
        if len(calls) == 5:  # the test view's second relit image: 2 train views are finished
            raise KeyboardInterrupt
        return render(self, *a, **kw)

    monkeypatch.setattr(generate.ViewRenderer, "render", dying_render)
    with pytest.raises(KeyboardInterrupt):
        cli_main(["generate", *argv, "--out", str(out)])
    (partial,) = [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]
    assert partial.name.endswith(".partial") and not out.exists()
    assert (partial / "train" / "r_001.exr").is_file()
    relit = sorted(p.name for p in (partial / "test").glob("*relit*"))
    assert relit == ["r_000_relit_sun_high.exr"] and not (partial / "test" / "r_000.exr").exists()
    (partial / "train" / ".r_001.exr.abcdefgh.tmp.exr").write_bytes(b"cut short")
    # A stale partial folder of other settings goes; the one of these settings is reused.
    stale = tmp_path / ".out.0123456789abcdef.partial"
    stale.mkdir()
    calls.clear()
    monkeypatch.setattr(generate.ViewRenderer, "render", lambda self, *a, **kw:
                        (calls.append(1), render(self, *a, **kw))[1])
    assert _run([*argv, "--out", str(out)], capsys)[0] == 0
    # The test view and 3 of its 4 relit images (3 directional, the sky): nothing else.
    assert len(calls) == 1 + 3
    assert _listing(out) == _listing(ref)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "ref"]


def test_overwrite_removes_only_what_generate_wrote(tmp_path, capsys):
    out = tmp_path / "out"
    assert _run(["default", "--out", str(out), "--seed", "1", *TINY], capsys)[0] == 0
    (out / "train" / "notes.txt").write_text("mine")
    msg = _assert_error(["default", "--out", str(out), "--seed", "2", "--overwrite", *TINY],
                        capsys, tmp_path, "notes.txt")
    assert "not written by mi-shadowgs generate" in msg
    # Without --overwrite the same: it used to say "pass --overwrite", which then refused.
    msg = _assert_error(["default", "--out", str(out), "--seed", "2", *TINY], capsys,
                        tmp_path, "notes.txt")
    assert "not written by mi-shadowgs generate" in msg and "pass --overwrite" not in msg
    assert json.loads((out / "dataset.json").read_text())["seed"] == 1
    (out / "train" / "notes.txt").unlink()
    (out / "extra").mkdir()  # a folder of someone else's, even empty, is not ours either
    _assert_error(["default", "--out", str(out), "--seed", "2", "--overwrite", *TINY], capsys,
                  tmp_path, "extra")
    (out / "extra").rmdir()
    # A dataset without a manifest (an older version wrote it) is not replaced either.
    (out / MANIFEST_NAME).rename(tmp_path / "manifest")
    _assert_error(["default", "--out", str(out), "--seed", "2", "--overwrite", *TINY], capsys,
                  tmp_path, "dataset.json")
    (tmp_path / "manifest").rename(out / MANIFEST_NAME)
    assert _run(["default", "--out", str(out), "--seed", "2", "--overwrite", *TINY],
                capsys)[0] == 0
    assert json.loads((out / "dataset.json").read_text())["seed"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    _assert_error(["default", "--out", str(out / "nested"), *TINY], capsys, tmp_path,
                  "inside the dataset folder")


def test_a_swap_cut_short_is_completed(tmp_path, capsys):
    """A kill between the two renames of an --overwrite leaves ``.out.old`` and no ``out``:
    the next run puts the previous dataset back; after both renames it removes it."""
    out, old = tmp_path / "out", tmp_path / ".out.old"
    argv = ["default", "--out", str(out), "--seed", "1", *TINY]
    assert _run(argv, capsys)[0] == 0
    before = _listing(out)
    out.rename(old)
    rc, cap = _run(argv, capsys)
    assert rc == 0 and "nothing to do" in cap.out
    assert _listing(out) == before and not old.exists()
    import shutil

    shutil.copytree(out, old)
    (old / "left.txt").write_text("not ours")  # the removal follows the manifest
    assert _run(argv, capsys)[0] == 0
    assert sorted(p.name for p in old.iterdir()) == ["left.txt"]


def test_unknown_preset_is_config_error():
    from mi_shadowgs.config import ConfigError

    with pytest.raises(ConfigError, match="'nope'"):
        get_config("nope")


def test_computed_parameters_are_refused(tmp_path, capsys):
    # The loader computes these and used to drop a -D of them without a word.
    out = tmp_path / "out"
    for define, instead in (("light0_direction=0,-1,0", ("light0_azimuth", "light0_elevation")),
                            ("light1_direction=1,0,0", ("light1_azimuth", "light1_elevation")),
                            ("object_to_world=2 0 0 0 0 2 0 0 0 0 2 0 0 0 0 1",
                             ("normalize",))):
        line = _assert_error(["default", "--out", str(out), "-D", define, *TINY], capsys,
                             tmp_path, repr(define.partition("=")[0]))
        assert "computed" in line and all(repr(p) in line for p in instead), line
    assert not out.exists()
    with pytest.raises(SceneError, match="'mesh_type' is computed.*'mesh'"):
        load_scene(scene_path("mesh"), {"mesh": "x.ply", "mesh_type": "obj"})


SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "meshes"


@pytest.mark.skipif(not (SHARED / "toy_train" / "toy_train_parts.json").is_file(),
                    reason="../shared/data (optional assets) is absent on this machine")
def test_mesh_scene_with_parts_json():
    setup = load_scene(scene_path("mesh"), {"mesh": str(SHARED / "toy_train" /
                                                        "toy_train.ply")})
    assert [p.name for p in setup.parts] == ["yellow", "green", "blue", "red", "wood"]
    assert setup.object_radius == pytest.approx(1.0, abs=1e-9)
    cam = Camera.look_at([0.0, 2.5, 3.0], setup.object_center, fov_x=0.7, width=48, height=48)
    gt = trace_ground_truth(setup, [cam])
    seen = set(np.unique(gt["material"][0]).tolist())
    assert {1, 2, 3, 4, 5, setup.base_id} <= seen
