"""`mi-shadowgs relight` and the shadow-map cache: light arguments checked
with the field named, shadow maps rendered once per direction and reused (the cached maps
equal fresh ones), the env map integrated once per content, the plugin's second render
reusing its maps, and the command's views, files and video on a tiny run."""

from __future__ import annotations

import dataclasses
import json
import os
import signal

import imageio.v3 as iio
import mitsuba as mi
import numpy as np
import pytest
import synthetic_asset
import tiny_cli

from mi_shadowgs import cli
from mi_shadowgs import presets as run_presets
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import direction_from_angles, light_grid
from mi_shadowgs.core.envmap import two_threads
from mi_shadowgs.dataset.generate import SkyConfig, sky_envmap_image
from mi_shadowgs.io.images import read_exr, write_exr
from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.relight import runner
from mi_shadowgs.stages.visibility.shadow_maps import (
    SceneBounds,
    VisibilityConfig,
    render_shadow_maps,
)

TINY = tiny_cli.TINY


@pytest.mark.parametrize("text, field", [
    ("a,45,3", "field azimuth must be a number"),
    ("30,95,3", "field elevation must be in (0, 90]"),
    # Below the horizon, refused as generate and view refuse it (it was rendered).
    ("0,-10,3", "field elevation must be in (0, 90] degrees, got -10"),
    ("0,0,3", "field elevation must be in (0, 90]"),
    ("30,45,-1", "field irradiance must be >= 0"),
    ("30,45,nan", "field irradiance must be finite"),
    ("30,45", "expected AZ,EL,IRRADIANCE"),
    ("30,45,1,x,1", "field irradiance G must be a number"),
])
def test_bad_light_exits_2_naming_the_field(tmp_path, capsys, text, field):
    # Checked before the run is read: the run folder need not exist.
    assert cli.main(["relight", str(tmp_path / "none"), "--out", str(tmp_path / "o"),
                     f"--light={text}"]) == 2
    err = capsys.readouterr().err
    assert "--light" in err and field in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv, message", [
    (["--envmap", "missing.exr"], "--envmap missing.exr: file not found"),
    (["--light", "0,45,1", "--rotate", "30"], "give --envmap too"),
    (["--envmap", "ENV", "--envmap-scale", "0"], "--envmap-scale must be > 0"),
    (["--envmap", "ENV", "--rotate", "inf"], "--rotate must be finite"),
    (["--scene", "missing.xml"], "--scene missing.xml: file not found"),
    ([], "no light"),
    (["--light", "0,45,1", "--orbit", "4", "--orbit-elevation", "nan"],
     "--orbit-elevation must be a finite angle in (-90, 90) degrees, got nan"),
    (["--light", "0,45,1", "--orbit-elevation", "30"], "give --orbit N with it"),
])
def test_bad_envmap_or_scene_arguments_exit_2(tmp_path, capsys, argv, message):
    env = tmp_path / "sky.exr"
    write_exr(env, np.ones((8, 16, 3), np.float32))
    argv = [str(env) if a == "ENV" else a for a in argv]
    assert cli.main(["relight", str(tmp_path / "none"), "--out", str(tmp_path / "o"),
                     *argv]) == 2
    assert message in capsys.readouterr().err


def test_parse_light_values():
    az, el, rgb = runner.parse_light("30, 45, 3")
    assert (az, el) == (30.0, 45.0) and rgb.tolist() == [3.0, 3.0, 3.0]
    assert runner.parse_light("0,90,1,2,3")[2].tolist() == [1.0, 2.0, 3.0]


def _plane_model(n=1500):
    surf = synthetic_asset.box_on_plane_surfels(n, 1.0, 0.25, roughness=0.5)
    return relight.RelightModel(surf, False, True)


def test_cache_renders_each_direction_once_and_equals_fresh_maps():
    model = _plane_model()
    pos = model.surfels.to_numpy()["position"]
    cam = Camera.look_at([1.5, 1.5, 1.5], [0, 0.1, 0], fov_x=0.8, width=24, height=24)
    bounds = SceneBounds.from_points(pos, [cam])
    cfg = VisibilityConfig(resolution=64)
    a, b, c = (direction_from_angles(az, 40.0) for az in (10.0, 130.0, 250.0))
    cache = relight.RelightCache()
    ab = relight.directional_light_set(np.stack([a, b]), [1.0, 1.0])
    bc = relight.directional_light_set(np.stack([b, c]), [1.0, 1.0])
    m1 = cache.shadow_maps(model, ab, bounds, cfg)
    assert cache.rendered == 2
    assert cache.shadow_maps(model, ab, bounds, cfg) is m1 and cache.rendered == 2
    m2 = cache.shadow_maps(model, bc, bounds, cfg)
    assert cache.rendered == 3  # only c is new
    fresh = render_shadow_maps(model.surfels, np.stack([b, c]), bounds, cfg)
    # Each map is rendered on its own: the cached map of b is bit-identical to a fresh one.
    np.testing.assert_array_equal(np.asarray(m2.depth), np.asarray(fresh.depth))
    assert m2.texel == fresh.texel
    # Other bounds or settings are other maps.
    cache.shadow_maps(model, ab, bounds, VisibilityConfig(resolution=32))
    assert cache.rendered == 5


def test_cache_rasterizes_each_view_once_and_counts_it_in_every_relighting(monkeypatch):
    """Relightings of the same views share each view's rasterization: the images equal
    uncached ones, each view is rasterized once per model, and every relighting's time
    still counts the rasterizations it reused. Another model (other channels) or camera
    is rasterized anew; the cache drops its oldest views past ``max_view_bytes``."""
    model = _plane_model()
    pos = model.surfels.to_numpy()["position"]
    cams = [Camera.look_at([1.5, 1.5, z], [0, 0.1, 0], fov_x=0.8, width=20, height=16)
            for z in (1.5, -1.5)]
    bounds = SceneBounds.from_points(pos, cams)
    cfg = VisibilityConfig(resolution=64)
    calls = []
    real = relight.view_buffers
    monkeypatch.setattr(relight, "view_buffers",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    cache = relight.RelightCache()
    lights = [relight.directional_light_set(direction_from_angles(az, 40.0)[None], [1.0])
              for az in (10.0, 200.0)]
    runs = [relight.relight_views(model, cams, ls, bounds, vis_config=cfg, cache=cache)
            for ls in lights]
    assert len(calls) == 2  # two views, rasterized once for both relightings
    made = sum(v[1] for v in cache._views.values())
    assert runs[1][1] >= made  # the second relighting's time counts the reused views
    for ls, (views, _) in zip(lights, runs, strict=True):
        fresh, _ = relight.relight_views(model, cams, ls, bounds, vis_config=cfg)
        for a, b in zip(views, fresh, strict=True):
            for key in ("rgb", "albedo", "direct_irradiance", "alpha"):
                np.testing.assert_array_equal(a[key], b[key])
    other = relight.RelightModel(model.surfels.with_channels(
        {"albedo": mi.TensorXf(np.full((model.surfels.count, 3), 0.3, np.float32))}),
        False, True)
    cache.view_buffers(other, cams[0])
    assert cache.view_buffers(other, cams[0])[2] and len(cache._views) == 3
    small = relight.RelightCache(max_view_bytes=1)
    for cam in cams:
        small.view_buffers(model, cam)
    assert len(small._views) == 1 and not small.view_buffers(model, cams[0])[2]


def _sky_file(tmp_path, **kw):
    path = tmp_path / "sky.exr"
    write_exr(path, sky_envmap_image(SkyConfig(**kw)))
    return path


def test_a_scene_file_with_an_exr_env_map_loads_on_one_thread(tmp_path):
    """Mitsuba's EXR reads never return on a one-thread Dr.Jit (``--threads 1``): the scene
    file of ``relight --scene`` is loaded on two (in a child, so that a hang fails here)."""
    import subprocess
    import sys

    scene = tmp_path / "scene.xml"
    scene.write_text("<scene version='3.0.0'><emitter type='envmap'><string name='filename' "
                     f"value='{_sky_file(tmp_path)}'/></emitter></scene>")
    code = ("import drjit as dr, mi_shadowgs, sys\n"
            "from mi_shadowgs import backend\n"
            "backend.set_variant('llvm_ad_rgb')\n"
            "dr.set_thread_count(1)\n"
            "from mi_shadowgs.stages.relight.runner import load_scene_file\n"
            "scene = load_scene_file(sys.argv[1])\n"
            "print(len(scene.emitters()), dr.thread_count())\n")
    out = subprocess.run([sys.executable, "-c", code, str(scene)], capture_output=True,
                         text=True, timeout=120, check=True).stdout
    assert out.split() == ["1", "1"]  # loaded, and the count put back


def test_envmap_radiance_is_cached_by_content_and_rotates_with_azimuth(tmp_path, monkeypatch):
    path = _sky_file(tmp_path, sun_azimuth_deg=30.0, sun_elevation_deg=40.0)
    calls = []
    real = relight.envmap_grid_radiance
    monkeypatch.setattr(relight, "envmap_grid_radiance",
                        lambda e, c=relight.DEFAULT_RELIGHT: calls.append(1) or real(e, c))
    cache = relight.RelightCache()
    cfg = relight.RelightConfig(env_samples=64)
    em = runner.envmap_emitter(path)
    r1 = cache.envmap_radiance(em, cfg)
    assert np.array_equal(cache.envmap_radiance(runner.envmap_emitter(path), cfg), r1)
    assert len(calls) == 1
    r2 = cache.envmap_radiance(runner.envmap_emitter(path, scale=2.0), cfg)
    assert len(calls) == 2
    np.testing.assert_allclose(r2, 2 * r1, rtol=1e-5)
    # --rotate 90 moves the sun 90 degrees in azimuth (from +X toward -Z, as azimuth turns).
    grid = light_grid(128)
    rot = cache.envmap_radiance(runner.envmap_emitter(path, rotate_deg=90.0), cfg)
    assert np.argmax(rot.mean(1)) == np.argmax(grid @ direction_from_angles(120.0, 40.0))
    assert np.argmax(r1.mean(1)) == np.argmax(grid @ direction_from_angles(30.0, 40.0))


def test_plugin_second_render_reuses_its_maps(plugins, tmp_path):
    from mi_shadowgs.io.ply import save_ply

    model = _plane_model()
    path = tmp_path / "model.ply"
    save_ply(path, model.surfels)
    cam = Camera.look_at([1.5, 1.5, 1.5], [0, 0.1, 0], fov_x=0.8, width=16, height=16)
    with two_threads():  # the env map's EXR (core.envmap)
        scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "surfel_relight", "filename": str(path),
                           "shadow_resolution": 64, "env_samples": 16},
            "sky": {"type": "envmap", "filename": str(_sky_file(tmp_path))},
            "sensor": cam.to_mitsuba_dict(spp=1)})
    first = np.asarray(mi.render(scene))
    integ = scene.integrator()
    rendered = integ.cache.rendered
    assert rendered > 10  # the sky's grid directions
    second = np.asarray(mi.render(scene))
    assert integ.cache.rendered == rendered
    np.testing.assert_array_equal(first, second)
    # A changed env map is integrated again (its parameters are part of the key).
    params = mi.traverse(scene.emitters()[0])
    params["scale"] = 2.0
    params.update()
    third = np.asarray(mi.render(scene))
    lit = first[..., :3] > 1e-3
    np.testing.assert_allclose(third[..., :3][lit], 2 * first[..., :3][lit], rtol=1e-3)


def test_relight_command_orbit_video_and_test_views(tiny_run, tiny_presets, tmp_path, capsys):
    run = tiny_run / "run"
    out = tmp_path / "orbit"
    assert cli.main(["relight", str(run), "--out", str(out), "--light", "30,45,3",
                     "--light", "200,30,1", "--orbit", "4", "--video", "--no-progress"]) == 0
    info = json.loads((out / "relight.json").read_text())
    assert info["views"] == [f"orbit_{i:03d}" for i in range(4)]
    assert info["light_directions"] == 2 and info["shadow_maps_rendered"] == 2
    for i in range(4):
        rgba = read_exr(out / f"orbit_{i:03d}.exr")
        assert rgba.shape == (24, 24, 4) and rgba[..., :3].max() > 0
        assert (out / f"orbit_{i:03d}.png").is_file()
    video = out / info["video"]
    assert video.is_file() and video.stat().st_size > 0
    text = capsys.readouterr().out
    assert "shadow maps included" in text and "GIF" not in text
    # imageio-ffmpeg is a dependency: a fresh install writes H.264, as ffmpeg reads it
    import imageio_ffmpeg

    assert video.suffix == ".mp4", info.get("video_note")
    reader = imageio_ffmpeg.read_frames(str(video))
    meta = next(reader)
    assert meta["codec"] == "h264" and meta["size"] == (24, 24)
    assert sum(1 for _ in reader) == 4
    # Default views: the run's test views.
    assert cli.main(["relight", str(run), "--out", str(tmp_path / "test"), "--light",
                     "30,45,3", "--no-progress"]) == 0
    info = json.loads((tmp_path / "test" / "relight.json").read_text())
    assert info["views"] == ["test_000", "test_001"]
    # Another relight into the same folder needs --overwrite.
    assert cli.main(["relight", str(run), "--out", str(out), "--light", "30,45,3"]) == 2


def test_a_fit_the_run_did_not_make_is_not_relit(tiny_run, tiny_presets, tmp_path, capsys):
    """A folder put under RUN/material/ by hand (a copy of a fit, another tool's model) is
    not one of the run's fits: `relight --fit` names the fits the run lists instead of
    relighting it as the run's."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_run / "run", run)
    shutil.copytree(run / "material" / "full", run / "material" / "mine")
    capsys.readouterr()
    assert cli.main(["relight", str(run), "--out", str(tmp_path / "r"), "--fit", "mine",
                     "--light", "30,45,3", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "material/mine: not a stage-4 fit of the run" in err and "lists" in err
    assert "full" in err.split("lists", 1)[1]
    assert not (tmp_path / "r").exists()
    assert cli.main(["view", str(run), "--fit", "mine", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "material/mine/model.ply is not one of the run's fits; the run's fits: " in err


def test_interrupted_relight_continues_with_the_missing_views(tiny_run, tiny_presets, one_thread,
                                                              tmp_path, capsys, monkeypatch):
    from mi_shadowgs.io import images

    run = tiny_run / "run"

    def relight_to(out, *extra):
        return cli.main(["relight", str(run), "--out", str(out), "--light", "30,45,3",
                         "--orbit", "5", "--video", "--no-progress", *extra])

    assert relight_to(tmp_path / "whole") == 0
    out = tmp_path / "out"
    real_png, pngs = images.write_png, []

    def ctrl_c_at_the_third_png(*args, **kwargs):  # view 2's PNG, after its EXR
        pngs.append(1)
        if len(pngs) == 3:
            os.kill(os.getpid(), signal.SIGINT)
        return real_png(*args, **kwargs)

    with monkeypatch.context() as mp:
        mp.setattr(images, "write_png", ctrl_c_at_the_third_png)
        assert relight_to(out) == 130
    assert "interrupted by SIGINT; run the same command again to continue" in \
        capsys.readouterr().err
    assert (out / "orbit_002.exr").is_file() and not (out / "orbit_002.png").exists()
    # The first call ran on cuda_ad_rgb (simulated: its record edited; no GPU here): its
    # views stay, and one warning line says the folder mixes two backends.
    from mi_shadowgs.io.provenance import MANIFEST_NAME

    manifest = json.loads((out / MANIFEST_NAME).read_text())
    manifest["made_with"] = [{"variant": "cuda_ad_rgb", "device": "NVIDIA H200"}]
    (out / MANIFEST_NAME).write_text(json.dumps(manifest))
    real_view, frames = relight.relight_view, []
    monkeypatch.setattr(relight, "relight_view",
                        lambda *a, **k: frames.append(1) or real_view(*a, **k))
    assert relight_to(out) == 0
    assert len(frames) == 3  # views 2, 3 and 4
    captured = capsys.readouterr()
    assert "the other 2 were there from an earlier call" in captured.out
    assert f"{out}: continued on llvm_ad_rgb from work that cuda_ad_rgb made" in captured.err
    info = json.loads((out / "relight.json").read_text())
    assert info["rendered_views"] == ["orbit_002", "orbit_003", "orbit_004"]
    assert len(info["frame_seconds"]) == 3 and info["video"] == \
        json.loads((tmp_path / "whole" / "relight.json").read_text())["video"]
    # Every view and the video (made from the views' files) as an uninterrupted relight's.
    names = sorted(p.name for p in (tmp_path / "whole").iterdir())
    assert sorted(p.name for p in out.iterdir()) == names and info["video"] in names
    for name in names:
        if name not in (".mi_shadowgs_manifest.json", "relight.json"):
            assert (out / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name
    # Finished: the same command renders nothing; other settings are refused by name.
    assert relight_to(out) == 0
    assert len(frames) == 3 and "already holds these 5 relit view(s)" in \
        capsys.readouterr().out
    assert relight_to(out, "--fps", "6") == 2
    err = capsys.readouterr().err
    assert "fps: 12.0 there, 6.0 now" in err and "--overwrite" in err
    # Shadow maps over other bounds (the run's dataset moved or changed) are other views.
    from mi_shadowgs.stages.material import runner as material_runner

    real_bounds = material_runner.occluder_bounds

    def wider_bounds(*args):
        bounds = real_bounds(*args)
        return dataclasses.replace(bounds, radius=1.01 * bounds.radius)

    monkeypatch.setattr(material_runner, "occluder_bounds", wider_bounds)
    assert relight_to(out) == 2
    assert "shadow_bounds.radius" in capsys.readouterr().err and len(frames) == 3


def test_scene_emitter_equals_the_same_light_given_as_angles(tiny_run, tiny_presets, tmp_path,
                                                             capsys):
    run = tiny_run / "run"
    d = direction_from_angles(30.0, 45.0)
    xml = tmp_path / "lights.xml"
    xml.write_text(f"""<scene version="3.0.0"><emitter type="directional">
        <vector name="direction" value="{-d[0]:.17g}, {-d[1]:.17g}, {-d[2]:.17g}"/>
        <rgb name="irradiance" value="3"/></emitter></scene>""")
    assert cli.main(["relight", str(run), "--out", str(tmp_path / "a"), "--scene", str(xml),
                     "--no-progress"]) == 0
    assert cli.main(["relight", str(run), "--out", str(tmp_path / "b"), "--light", "30,45,3",
                     "--no-progress"]) == 0
    a = read_exr(tmp_path / "a" / "test_000.exr")
    b = read_exr(tmp_path / "b" / "test_000.exr")
    # The XML's float32 direction differs from the float64 one in the last bits.
    np.testing.assert_allclose(a, b, atol=1e-4)
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr")
    with pytest.raises(ValueError, match="--envmap .*bad.exr: not a readable env map"):
        runner.build_lights(envmap=str(bad))
    # An 8-bit map is used (Mitsuba takes sRGB to linear), with a warning of its clipping.
    png = tmp_path / "pano.png"
    iio.imwrite(png, np.full((8, 16, 3), 200, np.uint8))
    runner.build_lights(envmap=str(png))
    assert f"--envmap {png} stores integers" in capsys.readouterr().err


def test_previews_turntable_and_env_maps_reuse_the_callers_maps(tmp_path, monkeypatch):
    from mi_shadowgs.presets import visibility_config as vis_get_config
    from mi_shadowgs.stages.material.state import LightModel, MaterialResult
    from mi_shadowgs.stages.relight.previews import write_previews

    for table, config in tiny_cli.presets():  # 64^2 shadow maps
        monkeypatch.setitem(table, TINY, config)
    model = _plane_model()
    grid = light_grid(128)
    light = LightModel(np.zeros(128), np.array([5]), grid[[5]], np.array([2.0]))
    result = MaterialResult(model.surfels, light, False, True, [], {})
    cam = Camera.look_at([1.5, 1.5, 1.5], [0, 0.1, 0], fov_x=0.8, width=16, height=16)
    bounds = SceneBounds.from_points(model.surfels.to_numpy()["position"], [cam])
    sky = _sky_file(tmp_path)
    cache = relight.RelightCache()
    rcfg = run_presets.relight_config(TINY)
    # What the evaluation's sky relighting leaves in the cache (another model object with
    # the same geometry, as the evaluation's rescaled albedo is).
    sky_lights = relight.grid_light_set(
        cache.envmap_radiance(runner.envmap_emitter(sky), rcfg), rcfg.n_directions)
    other = relight.RelightModel(dataclasses.replace(model.surfels, channels={}), False, True)
    cache.shadow_maps(other, sky_lights, bounds, vis_get_config(TINY))
    before = cache.rendered
    out = write_previews(tmp_path, result, [cam], bounds, vis_get_config(TINY), rcfg,
                         [("sky", sky, 1.0)], cache)
    assert cache.rendered == before + 8  # only the turntable's 8 directions are new
    assert [s["file"] for s in out["strips"]] == ["preview_0_turntable.png",
                                                  "preview_0_envmap.png"]
    frames = sorted(tmp_path.glob("preview_0_turntable_az*_el45.png"))
    assert [f.name[len("preview_0_turntable_"):-4] for f in frames] == \
        [f"az{a:03d}_el45" for a in range(0, 360, 45)]
    assert (tmp_path / "preview_0_envmap_sky.png").is_file()


def test_the_plugin_and_api_relight_take_the_lobe_the_model_was_fitted_with(plugins, tiny_run,
                                                                           tiny_presets,
                                                                           tmp_path):
    """A `cpu-*` model is fitted without the GGX lobe, so its roughness and metallic were
    never fitted; the `surfel_relight` plugin and `api.relight` turned the lobe on for it
    unless told (their default was true). Stage 4's PLY now records the lobe; a model saved
    before that takes it from the run's light.json beside it; another tool's keeps it on."""
    import shutil

    import mi_shadowgs.api as msg
    from mi_shadowgs.io.ply import PlyError, load_ply, read_ply_metadata, save_ply

    full = tiny_run / "run" / "material" / "full"
    fitted = json.loads((full / "light.json").read_text())["specular"]
    key = relight.SPECULAR_METADATA_KEY
    assert read_ply_metadata(full / "model.ply")[key] == ("true" if fitted else "false")

    def lobe(path, **props):
        scene = mi.load_dict({"type": "scene", "integrator": {
            "type": "surfel_relight", "filename": str(path), **props}})
        return scene.integrator().specular

    assert lobe(full / "model.ply") is fitted
    assert lobe(full / "model.ply", specular=not fitted) is (not fitted)
    model = load_ply(full / "model.ply")
    header = read_ply_metadata(full / "model.ply")
    diffuse = tmp_path / "diffuse.ply"
    save_ply(diffuse, model, {**header, key: "false"})
    assert lobe(diffuse) is False
    # api.relight of the path: the lobe it records (the same views as the lobe given)
    from mi_shadowgs.dataset.loader import load_dataset

    camera = load_dataset(tiny_run / "data", "test").cameras[0]
    lights = msg.directional_light_set([[0.3, 0.8, 0.5]], [2.0])
    (got,), _ = msg.relight(diffuse, [camera], lights)
    (off,), _ = msg.relight(diffuse, [camera], lights, specular=False)
    (on,), _ = msg.relight(diffuse, [camera], lights, specular=True)
    np.testing.assert_array_equal(got["rgb"], off["rgb"])
    assert np.abs(on["rgb"] - off["rgb"]).max() > 1e-4  # else the case proves nothing
    # saved before the record: the run's light.json beside it, which the manifest lists
    old = tmp_path / "full"
    shutil.copytree(full, old)
    save_ply(old / "model.ply", model, {k: v for k, v in header.items() if k != key})
    assert relight.recorded_specular(old / "model.ply") is fitted
    other = tmp_path / "other.ply"  # another tool's: the lobe on, as before
    save_ply(other, model)
    assert relight.recorded_specular(other) is None and lobe(other) is True
    bad = tmp_path / "bad.ply"
    save_ply(bad, model, {key: "maybe"})
    with pytest.raises(PlyError, match=f"{bad}: header comment specular 'maybe'"):
        relight.recorded_specular(bad)


def test_video_is_h264_and_a_gif_only_without_the_encoder(tmp_path, monkeypatch):
    import importlib.util

    import imageio_ffmpeg

    from mi_shadowgs.stages.relight.runner import write_video

    frames = [np.full((16, 20, 3), 40 * i, np.uint8) for i in range(5)]
    path, why = write_video(tmp_path / "v", frames, 10.0)
    assert path.suffix == ".mp4" and why is None
    meta = next(imageio_ffmpeg.read_frames(str(path)))
    assert meta["codec"] == "h264" and meta["size"] == (20, 16)
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "imageio_ffmpeg" else real(name, *a))
    path, why = write_video(tmp_path / "g", frames, 10.0)
    assert path.suffix == ".gif" and "imageio-ffmpeg" in why and "wrote a GIF instead" in why
    assert iio.imread(path).shape[0] == 5
