"""`mi-shadowgs export`: the splat PLYs under the loading rules of 3DGS/2DGS and
of splat viewers, the mesh + Mitsuba scene rendered by plain Mitsuba in a subprocess, and
bad input refused (exit 2, one line naming what is wrong) without writing anything."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from mi_shadowgs import cli
from mi_shadowgs import presets as run_presets
from mi_shadowgs.io.ply import SH_C0, read_ply_model
from mi_shadowgs.io.provenance import MANIFEST_NAME, file_digest
from tests import synthetic_asset as syn

# What splat viewers demand (SuperSplat/PlayCanvas splat-transform and three.js viewers
# read these without checking; 3DGS's load_ply reads them too).
VIEWER_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0",
                   "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def srgb(x):
    x = np.clip(np.asarray(x, np.float64), 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def gs_load_ply(path, max_sh_degree=3, scales=3):
    """The loading rules of 3DGS's / 2DGS's ``GaussianModel.load_ply`` (the public code),
    restated with plyfile: the first element's properties by name; ``f_rest_*`` sorted by
    their number and asserted to be 3 * (degree + 1)^2 - 3, then read channel-major;
    ``scale_*`` and ``rot*`` gathered by prefix, sorted."""
    from plyfile import PlyData

    el = PlyData.read(str(path)).elements[0]
    names = [p.name for p in el.properties]
    xyz = np.stack([el["x"], el["y"], el["z"]], 1)
    opacity = np.asarray(el["opacity"])
    dc = np.stack([el[f"f_dc_{i}"] for i in range(3)], 1)
    extra = sorted([n for n in names if n.startswith("f_rest_")],
                   key=lambda n: int(n.split("_")[-1]))
    assert len(extra) == 3 * (max_sh_degree + 1) ** 2 - 3
    rest = np.stack([el[n] for n in extra], 1).reshape(len(xyz), 3, -1)  # [N, 3, 15]
    scale_names = sorted([n for n in names if n.startswith("scale_")],
                         key=lambda n: int(n.split("_")[-1]))
    assert len(scale_names) == scales
    rot_names = sorted([n for n in names if n.startswith("rot")],
                       key=lambda n: int(n.split("_")[-1]))
    assert len(rot_names) == 4
    return {"xyz": xyz, "opacity": opacity, "dc": dc, "rest": rest,
            "scale": np.stack([el[n] for n in scale_names], 1),
            "rot": np.stack([el[n] for n in rot_names], 1), "names": names}


@pytest.fixture(scope="module", autouse=True)
def small_mesh_grid():
    """A coarser object grid (96 voxels) for speed: the tests here check files, scenes and
    refusals; tests/test_tsdf.py measures the mesh's accuracy."""
    import dataclasses

    from tiny_cli import set_sections

    cfg = run_presets.export_config("cpu-small")
    with pytest.MonkeyPatch.context() as mp:
        set_sections(mp, "cpu-small", export=dataclasses.replace(
            cfg, mesh=dataclasses.replace(cfg.mesh, resolution=96)))
        yield


@pytest.fixture(scope="module")
def run_data(tmp_path_factory):
    return syn.fake_run(tmp_path_factory.mktemp("export"))


def export(*args) -> int:
    return cli.main(["export", *map(str, args), "--no-progress"])


def test_3dgs_ply_loads_by_3dgs_rules_and_in_viewers(run_data, tmp_path):
    run, _ = run_data
    from mi_shadowgs.io.ply import read_ply_metadata, to_frame

    ours = read_ply_model(run / "material" / "full" / "model.ply")
    # In the splat tools' frame by default (Y down: upright in SuperSplat), recorded
    assert export(run, "--format", "3dgs-ply", "--out", tmp_path / "sh") == 0
    assert read_ply_metadata(tmp_path / "sh" / "point_cloud.ply") == \
        {"sh_space": "srgb", "world_frame": "opencv"}
    model = to_frame(ours, "opencv")
    np.testing.assert_array_equal(model.position, ours.position * [1, -1, -1])
    back = read_ply_model(tmp_path / "sh" / "point_cloud.ply")  # turned back into ours
    np.testing.assert_array_equal(back.position, ours.position)
    np.testing.assert_array_equal(back.rotation, ours.rotation)
    assert export(run, "--format", "3dgs-ply", "--out", tmp_path / "yup", "--frame",
                  "y-up") == 0
    np.testing.assert_array_equal(gs_load_ply(tmp_path / "yup" / "point_cloud.ply")["xyz"],
                                  ours.position)
    g = gs_load_ply(tmp_path / "sh" / "point_cloud.ply")
    assert all(n in g["names"] for n in VIEWER_REQUIRED)
    np.testing.assert_array_equal(g["xyz"], model.position)
    np.testing.assert_array_equal(g["opacity"], model.opacity_logit)
    np.testing.assert_array_equal(g["rot"], model.rotation)
    np.testing.assert_array_equal(g["scale"][:, :2], model.log_scale)
    assert (g["scale"][:, 2] < g["scale"][:, :2].min(1) - 2.0).all()  # thin along the normal
    # Colour: the 3DGS DC colour is the sRGB of the model's view-mean linear colour; the
    # degree-1 bands scaled, bands 2-3 zero-padded.
    sh = model.channels["sh"].reshape(model.count, 4, 3)
    np.testing.assert_allclose(SH_C0 * g["dc"] + 0.5, srgb(SH_C0 * sh[:, 0] + 0.5), atol=2e-6)
    assert np.all(g["rest"][:, :, 3:] == 0) and np.any(g["rest"][:, :, :3] != 0)
    assert np.all(np.sign(g["rest"][:, :, :3]) == np.sign(sh[:, 1:].transpose(0, 2, 1)))

    assert export(run, "--format", "3dgs-ply", "--out", tmp_path / "alb", "--color",
                  "albedo") == 0
    a = gs_load_ply(tmp_path / "alb" / "point_cloud.ply")
    np.testing.assert_allclose(SH_C0 * a["dc"] + 0.5, srgb(model.channels["albedo"]), atol=2e-6)
    assert np.all(a["rest"] == 0)


def test_2dgs_ply_keeps_our_channels(run_data, tmp_path):
    run, _ = run_data
    model = read_ply_model(run / "material" / "full" / "model.ply")
    assert export(run, "--format", "2dgs-ply", "--out", tmp_path) == 0
    g = gs_load_ply(tmp_path / "point_cloud.ply", scales=2)
    np.testing.assert_array_equal(g["scale"], model.log_scale)
    back = read_ply_model(tmp_path / "point_cloud.ply")
    assert back.channels["sh"].shape == (model.count, 48)
    for name in ("albedo", "roughness", "metallic", "segment"):
        np.testing.assert_array_equal(back.channels[name], model.channels[name])
    # The display SH (sRGB, for viewers) carry `sh_space srgb`, so our reader gives back
    # the model's linear SH (where the view-mean colour is inside [0, 1]) and renders the
    # run's colours; read as linear they rendered washed out.
    k = model.channels["sh"].shape[1]
    inside = np.all(np.abs(SH_C0 * model.channels["sh"][:, :3]) < 0.5, axis=1)
    assert inside.mean() > 0.9
    np.testing.assert_allclose(back.channels["sh"][inside, :k], model.channels["sh"][inside],
                               rtol=1e-4, atol=1e-5)
    assert np.all(back.channels["sh"][:, k:] == 0)
    from mi_shadowgs import api
    from mi_shadowgs.dataset.loader import load_cameras

    camera = load_cameras(run_data[1] / "transforms_test.json")[0][1]
    ours = api.render(run / "material" / "full" / "model.ply", camera)["rgb"].numpy()
    exported = api.render(tmp_path / "point_cloud.ply", camera)["rgb"].numpy()
    assert ours.max() > 0.05
    np.testing.assert_allclose(exported, ours, atol=2e-3)
    albedo = api.render(tmp_path / "point_cloud.ply", camera, color_channel="albedo")["rgb"]
    np.testing.assert_allclose(albedo.numpy(), api.render(run / "material" / "full" / "model.ply",
                               camera, color_channel="albedo")["rgb"].numpy(), atol=1e-6)


def _render_plain_mitsuba(scene: str, out_npy: str, size: int = 32) -> None:
    """Render sensor 0 of ``scene`` in a fresh Python that imports only mitsuba."""
    code = (
        "import sys, numpy as np, mitsuba as mi\n"
        "mi.set_variant('llvm_ad_rgb')\n"
        f"s = mi.load_file(sys.argv[1], resx={size}, resy={size}, spp=16)\n"
        "img = np.asarray(mi.render(s, sensor=0, seed=1))\n"
        "assert not any(m.startswith('mi_shadowgs') for m in sys.modules)\n"
        "np.save(sys.argv[2], img)\n"
        "print('RESULT', len(s.sensors()), len(s.emitters()),\n"
        "      sorted(sh.id() for sh in s.shapes()))\n")
    # The LLVM library that `import mi_shadowgs` found for this process (README: Set-up);
    # a user's plain Mitsuba needs a working one too.
    env = dict(os.environ)
    res = subprocess.run([sys.executable, "-c", code, scene, out_npy], env=env,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    return res.stdout[res.stdout.index("RESULT ") + len("RESULT "):]


def test_mesh_scene_renders_with_plain_mitsuba(run_data, tmp_path):
    run, data = run_data
    out = tmp_path / "asset"
    assert export(run, "--format", "mesh", "--out", out) == 0
    files = json.loads((out / MANIFEST_NAME).read_text())["files"]
    assert sorted(files) == sorted(["object.ply", "object.obj", "base.ply", "base.obj",
                                    "asset.glb", "scene.xml", "export.json"])
    stdout = _render_plain_mitsuba(str(out / "scene.xml"), str(tmp_path / "img.npy"))
    assert stdout.split()[:2] == ["3", "2"]  # 3 test cameras, the 2 fitted lights
    img = np.load(tmp_path / "img.npy")
    assert img.shape == (32, 32, 4) and np.isfinite(img).all()
    # The same view from the ground truth's point of view: the sphere covers the centre,
    # the base fills most of the rest; coverage matches the analytic silhouette.
    from mi_shadowgs.dataset.loader import load_cameras

    cam = load_cameras(data / "transforms_test.json")[0][1]
    uv = cam.pixel_grid()
    o = cam.origin
    dirs = cam.unproject(uv, np.ones(len(uv))) - o
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    oc = o - syn.CENTER
    b = np.einsum("ij,j->i", dirs, oc)
    hit_sphere = (b * b - (oc @ oc - syn.RADIUS ** 2)) > 0
    t = -o[1] / dirs[:, 1]
    x, z = o[0] + t * dirs[:, 0], o[2] + t * dirs[:, 2]
    hit_plane = (t > 0) & (np.abs(x) < 1.2) & (np.abs(z) < 1.2)
    alpha = img[..., 3].ravel()
    assert hit_sphere.mean() > 0.05
    # Pixel coverage of the analytic sphere + square: box filter at 32^2, the mesh's edges
    # within a voxel or two of the surfels' (measured: 0.5 % of the pixels differ).
    assert abs(alpha.mean() - (hit_sphere | hit_plane).mean()) < 0.03
    assert (alpha[hit_sphere] > 0.99).mean() > 0.8  # all but silhouette pixels
    sphere_px = img[..., :3].reshape(-1, 3)[hit_sphere & (uv[:, 1] < 14)]  # upper half
    # Upper hemisphere: albedo (0.8, 0.2, 0.1), lit from above: clearly red.
    assert (sphere_px[:, 0] > 2 * sphere_px[:, 2]).mean() > 0.8
    # Round trip of the materials through Mitsuba's PLY loader.
    import mitsuba as mi

    shape = mi.load_dict({"type": "ply", "filename": str(out / "object.ply")})
    for attr in ("vertex_albedo_color", "vertex_roughness", "vertex_metallic"):
        assert shape.has_attribute(attr)
    params = mi.traverse(shape)
    alb = np.asarray(params["vertex_albedo_color"]).reshape(-1, 3)
    assert np.all((alb >= 0) & (alb <= 1)) and alb[:, 0].max() > 0.7
    np.testing.assert_allclose(np.asarray(params["vertex_roughness"]), 0.4, atol=0.02)
    # No slivers (a ray hitting one got NaN barycentrics in Mitsuba): in both meshes every
    # triangle has three distinct corners and an area, every vertex a unit normal.
    import trimesh

    for part in ("object", "base"):
        m = trimesh.load(out / f"{part}.ply", process=False)
        f = np.asarray(m.faces)
        assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
        assert m.area_faces.min() > 1e-10, part
        pts = np.asarray(m.vertices)[f]
        assert np.linalg.norm(pts[:, 0] - pts[:, 1], axis=1).min() > 1e-6, part
        np.testing.assert_allclose(np.linalg.norm(m.vertex_normals, axis=1), 1.0, atol=1e-4)
    _check_mesh_tools_read_it(out)


def _check_mesh_tools_read_it(out):
    """What mesh tools (trimesh, MeshLab, Blender, three.js) read: the PLYs' standard uchar
    colours are sRGB(albedo) within 1/255 beside the float materials; the object is
    watertight or export.json says why not; no sliver components; the glTF loads."""
    import trimesh
    from plyfile import PlyData

    info = json.loads((out / "export.json").read_text())
    for part in ("object", "base"):
        m = trimesh.load(out / f"{part}.ply")
        assert m.visual.kind == "vertex", part
        el = PlyData.read(str(out / f"{part}.ply"))["vertex"]
        assert [el[c].dtype.name for c in ("red", "green", "blue")] == ["uint8"] * 3
        albedo = np.stack([el[f"albedo_{c}"] for c in "rgb"], 1)
        colours = np.stack([el[c] for c in ("red", "green", "blue")], 1) / 255.0
        assert np.abs(colours - srgb(albedo)).max() <= 1 / 255 + 1e-9, part
        # trimesh's own read of the colours (it may merge vertices: compare by position)
        raw = trimesh.load(out / f"{part}.ply", process=False)
        np.testing.assert_array_equal(raw.visual.vertex_colors[:, :3],
                                      np.round(colours * 255).astype(np.uint8))
        split = raw.split(only_watertight=False)
        areas = sorted(c.area for c in split)
        assert areas[0] >= 0.02 * areas[-1], (part, areas)  # no sliver components
    obj = trimesh.load(out / "object.ply", process=False)
    assert obj.is_watertight == info["watertight"]
    assert info["watertight"] or info["not_watertight_because"], info
    glb = trimesh.load(out / "asset.glb")
    assert isinstance(glb, trimesh.Scene) and sorted(glb.geometry) == ["base", "object"]
    g = glb.geometry["object"]
    assert g.visual.kind == "vertex" and len(g.faces) == len(obj.faces)


def test_rerun_reuses_and_other_settings_are_refused(run_data, tmp_path, capsys):
    run, _ = run_data
    out = tmp_path / "p"
    assert export(run, "--format", "3dgs-ply", "--out", out) == 0
    stamp = (out / "point_cloud.ply").stat().st_mtime_ns
    assert export(run, "--format", "3dgs-ply", "--out", out) == 0
    assert "reused" in capsys.readouterr().out
    assert (out / "point_cloud.ply").stat().st_mtime_ns == stamp
    assert export(run, "--format", "3dgs-ply", "--out", out, "--color", "albedo") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "color" in err
    assert export(run, "--format", "3dgs-ply", "--out", out, "--color", "albedo",
                  "--overwrite") == 0
    # An export made before the splat PLYs carried their header records (no `layout` in
    # its settings) is not reused as if it were this one: it lacks `sh_space`.
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    del manifest["settings"]["layout"]
    (out / MANIFEST_NAME).write_text(json.dumps(manifest))
    capsys.readouterr()
    assert export(run, "--format", "3dgs-ply", "--out", out, "--color", "albedo") == 2
    assert "layout: null there, 2 now" in capsys.readouterr().err


def _run_digests(run):
    return {p: file_digest(p) for p in sorted(run.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("case", ["no-stage-4", "unknown-format", "unknown-color",
                                  "out-is-run", "out-in-stage", "foreign-folder", "no-run",
                                  "moved-dataset", "not-a-run", "out-names-a-file",
                                  "data-for-a-splat"])
def test_bad_input_exits_2_naming_it(tmp_path, capsys, case):
    run, data = syn.fake_run(tmp_path / "r", stage4=case != "no-stage-4")
    original = run
    before = _run_digests(original)
    out = tmp_path / "out"
    fmt, extra = "mesh", []
    if case == "unknown-format":
        fmt = "gltf"
    elif case == "unknown-color":
        fmt, extra = "3dgs-ply", ["--color", "rainbow"]
    elif case == "out-is-run":
        out = run
    elif case == "out-in-stage":
        out = run / "material" / "full" / "export"
    elif case == "foreign-folder":
        out.mkdir()
        (out / "notes.txt").write_text("mine")
    elif case == "no-run":
        run = tmp_path / "nothing"
    elif case == "moved-dataset":
        data.rename(tmp_path / "elsewhere")
    elif case == "not-a-run":
        run = data
    elif case == "out-names-a-file":
        out = tmp_path / "model.ply"
    elif case == "data-for-a-splat":  # it was ignored without a word
        fmt, extra = "2dgs-ply", ["--data", data]
    code = export(run, "--format", fmt, "--out", out, *extra)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1
    expect = {"no-stage-4": "material/full/model.ply", "unknown-format": "'gltf'",
              "unknown-color": "'rainbow'", "out-is-run": "is the run folder",
              "out-in-stage": "material", "foreign-folder": "notes.txt",
              "no-run": "run folder not found", "moved-dataset": "--data",
              "not-a-run": "not a run folder",
              "out-names-a-file": "names a .ply file, but --out is a folder",
              "data-for-a-splat": "--data is read by --format mesh only"}[case]
    assert expect in err
    assert _run_digests(original) == before  # nothing in the run changed
    if case == "foreign-folder":
        assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    elif case not in ("out-is-run", "out-in-stage"):
        assert not out.exists()


@pytest.mark.parametrize("roughness,metallic", [(0.5, 0.0), (0.25, 0.3), (0.8, 1.0)])
def test_model_bsdf_renders_our_cook_torrance(tmp_path, roughness, metallic):
    """scene.xml's "model" BSDF (diffuse + roughconductor in blendbsdfs) on a lit square,
    path-traced by plain Mitsuba (direct light only), against the float64 Cook-Torrance
    reference of test_brdf. The one directional light is sampled exactly, so each pixel is
    the BRDF at its view direction; the box filter averages it over the pixel (the view
    direction changes < 0.1 deg across one). Light and camera on the same side, low: the
    half vector is near the view, so Schlick's and Mitsuba's exact Fresnel (eta 1.5) agree,
    and the metal's Fresnel of 1 equals Schlick's F0 there (measured error 0.0 %; with the
    light opposite at grazing, Schlick is up to 15 % under the exact Fresnel in the
    specular peak, a difference of the Fresnel models, not of the export). Tolerance 1 % of
    the largest value. "principled" (Disney's diffuse, retro-reflective toward grazing
    light and view) is 10-22 % brighter here: the check can fail."""
    import mitsuba as mi

    from mi_shadowgs.core.camera import Camera
    from mi_shadowgs.stages.export import export as ex
    from mi_shadowgs.stages.export.mesh import MeshPart
    from tests.test_brdf import ref_cook_torrance

    verts = 3.0 * np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], np.float32)
    faces = np.array([[0, 2, 1], [0, 3, 2]], np.int32)
    albedo = np.array([0.7, 0.45, 0.2])
    part = MeshPart(verts, faces, np.tile([0.0, 1.0, 0.0], (4, 1)).astype(np.float32),
                    np.tile(albedo, (4, 1)).astype(np.float32), np.full(4, roughness),
                    np.full(4, metallic))
    (tmp_path / "quad.ply").write_bytes(ex._mesh_ply_bytes(part))
    # a low light behind a low camera: where Disney's diffuse parts from Lambert's
    light_dir = np.array([0.3, 0.35, -0.9]) / np.linalg.norm([0.3, 0.35, -0.9])  # toward it
    irradiance = np.array([2.0, 2.0, 2.0])
    cam = Camera.look_at([0.0, 0.7, -2.6], [0.0, 0.0, 0.0], width=24, height=24,
                         fov_x=np.radians(40.0))
    results = {}
    for kind in ("model", "principled"):
        cfg = ex.ExportConfig(bsdf=kind)
        xml = ex.scene_xml({"quad": "quad.ply"}, [(light_dir, irradiance)], [("c", cam)], cfg,
                           "test")
        path = tmp_path / f"{kind}.xml"
        path.write_text(xml)
        scene = mi.load_file(str(path), spp=16, max_depth=2)
        results[kind] = np.asarray(mi.render(scene))[..., :3].astype(np.float64)
    # The reference at each pixel centre's view ray hitting the plane.
    uv = cam.pixel_grid()
    d = cam.unproject(uv, np.ones(len(uv))) - cam.origin
    t = -cam.origin[1] / d[:, 1]
    p = cam.origin + t[:, None] * d
    v = cam.origin - p
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    inside = (np.abs(p[:, 0]) < 0.9) & (np.abs(p[:, 2]) < 0.9)
    n_px = len(v)
    ref = ref_cook_torrance(np.tile([0.0, 1.0, 0.0], (n_px, 1)), np.tile(light_dir, (n_px, 1)),
                            v, np.tile(albedo, (n_px, 1)), np.full(n_px, roughness),
                            np.full(n_px, metallic)) * irradiance
    assert inside.sum() > 100
    scale = ref[inside].max()
    err = {k: np.abs(img.reshape(-1, 3)[inside] - ref[inside]).max() / scale
           for k, img in results.items()}
    assert err["model"] < 0.01, err
    if metallic == 0.0 and roughness >= 0.5:  # Disney's retro-reflection grows with both
        assert err["principled"] > 0.05, err


def test_the_export_takes_the_runs_settings_by_default(tmp_path):
    """Without --preset the export's settings are those the run recorded (RUN/config.json:
    the mesh grid of a `paper` run is `paper`'s), as relight takes them; --preset names
    another preset's."""
    import json

    from mi_shadowgs.io.provenance import MANIFEST_NAME
    from mi_shadowgs.presets import CONFIG_NAME

    run, _ = syn.fake_run(tmp_path / "r")
    paper, small = run_presets.get_config("paper"), run_presets.get_config("cpu-small")
    assert paper.export.mesh.resolution != small.export.mesh.resolution
    (run / CONFIG_NAME).write_text(json.dumps(paper.to_dict()))
    assert export(run, "--format", "2dgs-ply", "--out", tmp_path / "a") == 0
    made = json.loads((tmp_path / "a" / MANIFEST_NAME).read_text())
    assert made["settings"]["mesh"]["resolution"] == paper.export.mesh.resolution
    assert export(run, "--format", "2dgs-ply", "--out", tmp_path / "b", "--preset",
                  "cpu-small") == 0
    made = json.loads((tmp_path / "b" / MANIFEST_NAME).read_text())
    assert made["settings"]["mesh"]["resolution"] == small.export.mesh.resolution


def test_2dgs_ply_keeps_the_fits_header_records(tmp_path):
    """The 2DGS PLY carries albedo/roughness/metallic for relighting; the stage-4 model's
    header records (receiver band, shadow maps, whether the GGX lobe was fitted) must come
    along, or a relight of it (api.relight, surfel_relight) takes another tool's defaults:
    the specular lobe on for a cpu-* model fitted without it (the export dropped them)."""
    from mi_shadowgs.io.ply import read_ply_metadata, write_ply_model
    from mi_shadowgs.stages.relight.render import recorded_specular

    run, _ = syn.fake_run(tmp_path / "r", model=syn.sphere_on_plane(300, 300))
    model_path = run / "material" / "full" / "model.ply"
    meta = {"receiver_band": "0.5", "specular": "false"}
    write_ply_model(model_path, read_ply_model(model_path), meta)
    assert export(run, "--format", "2dgs-ply", "--out", tmp_path / "e") == 0
    out = tmp_path / "e" / "point_cloud.ply"
    # + its SH's colour space and its frame
    assert read_ply_metadata(out) == {**meta, "sh_space": "srgb", "world_frame": "opencv"}
    assert recorded_specular(out) is False


def test_splat_colours_above_white_are_said_clipped_in_the_header(tmp_path, capsys):
    """Display SH hold sRGB values, which end at white: a linear colour above 1 comes back
    as 1 (95 of 4,096 pixels of a 64^2 view up to 0.88 darker). The export says so on stderr
    and in the header (``display_clipped_splats``); a model inside [0, 1] gets no record."""
    import dataclasses

    from mi_shadowgs.io.ply import CLIPPED_KEY, read_ply_metadata

    model = syn.sphere_on_plane(300, 300)
    sh = model.channels["sh"].copy()
    bright = np.arange(0, model.count, 7)
    sh[bright, :3] = (1.6 - 0.5) / SH_C0  # a view-mean colour of 1.6
    run, _ = syn.fake_run(tmp_path / "r", model=dataclasses.replace(
        model, channels={**model.channels, "sh": sh}))
    for fmt in ("3dgs-ply", "2dgs-ply"):
        capsys.readouterr()
        assert export(run, "--format", fmt, "--out", tmp_path / fmt) == 0
        err = capsys.readouterr().err
        assert f"{len(bright)} of {model.count} splats have colours outside [0, 1]" in err, err
        meta = read_ply_metadata(tmp_path / fmt / "point_cloud.ply")
        assert meta[CLIPPED_KEY] == str(len(bright)) and meta["sh_space"] == "srgb"
    plain, _ = syn.fake_run(tmp_path / "p", model=model)
    assert export(plain, "--format", "3dgs-ply", "--out", tmp_path / "plain") == 0
    assert CLIPPED_KEY not in read_ply_metadata(tmp_path / "plain" / "point_cloud.ply")
    assert "outside [0, 1]" not in capsys.readouterr().err


def test_close_mesh_caps_the_foot_and_small_holes_and_says_what_stays_open():
    """A star-footed prism open at y = 0 (a non-convex foot) with a small hole and a large
    one in its walls: the foot is capped inside the footprint, facing down; the small hole
    is capped; the large one stays open and the info says why."""
    import trimesh

    from mi_shadowgs.stages.export.close import close_mesh, ear_clip

    k = 24
    ang = np.linspace(0, 2 * np.pi, k, endpoint=False)
    r = np.where(np.arange(k) % 2 == 0, 1.0, 0.45)
    ring = np.stack([r * np.cos(ang), r * np.sin(ang)], 1)
    tri = ear_clip(ring)
    assert len(tri) == k - 2
    a = ring[tri]
    areas = 0.5 * ((a[:, 1, 0] - a[:, 0, 0]) * (a[:, 2, 1] - a[:, 0, 1])
                   - (a[:, 1, 1] - a[:, 0, 1]) * (a[:, 2, 0] - a[:, 0, 0]))
    poly = 0.5 * np.sum(ring[:, 0] * np.roll(ring[:, 1], -1) - np.roll(ring[:, 0], -1) * ring[:, 1])
    assert np.all(areas > 0) and np.isclose(areas.sum(), poly)  # no fold, no overlap
    # A closed prism (star cross-section in x, z; y from 0.01 to 1), its bottom removed.
    bottom = np.c_[ring[:, 0], np.full(k, 0.01), ring[:, 1]]
    top = np.c_[ring[:, 0], np.ones(k), ring[:, 1]]
    v = np.concatenate([bottom, top])
    i = np.arange(k)
    j = (i + 1) % k
    walls = np.concatenate([np.c_[i, j, k + j], np.c_[i, k + j, k + i]])
    top_faces = k + tri[:, ::-1]
    full = trimesh.Trimesh(v, np.concatenate([walls, top_faces, tri]), process=False)
    full.fix_normals()
    assert full.is_watertight and full.volume > 0
    bottom_cap = set(map(tuple, np.sort(tri, 1)))
    faces = np.array([f for f in full.faces if tuple(sorted(f)) not in bottom_cap])
    verts, closed, info = close_mesh(v.astype(np.float32), faces, 0.05, 8)
    m = trimesh.Trimesh(verts, closed, process=False)
    assert info == {"watertight": True, "capped_base_loops": 1, "capped_holes": 0}
    assert m.is_watertight and m.is_winding_consistent and np.isclose(m.volume, full.volume,
                                                                        rtol=0.02)
    cap = m.faces[len(faces):]
    assert np.all(verts[cap][..., 1] == 0) and np.all(m.face_normals[len(faces):, 1] < -0.99)
    # A hole of one top triangle (3 edges) is capped; with hole_edges 2 it stays open.
    holed = np.delete(faces, len(walls), axis=0)
    _, _, info = close_mesh(v.astype(np.float32), holed, 0.05, 8)
    assert info["watertight"] and info["capped_holes"] == 1
    _, _, info = close_mesh(v.astype(np.float32), holed, 0.05, 2)
    assert not info["watertight"] and "1 open loop(s) off the base" in \
        info["not_watertight_because"]
