"""Receivers on each pixel's median surface (``VisibilityConfig.receiver_band``,
``shading.surface_aovs``) against the float64 reference, the hard case they exist for (a
base pixel beside an object), and their path through stage 4, relighting and the runs."""

from __future__ import annotations

import dataclasses

import mitsuba as mi
import numpy as np
import pytest
from raster_reference import random_scene, reference, to_surfels

from mi_shadowgs import presets as run_presets
from mi_shadowgs.config import ConfigError
from mi_shadowgs.core import shading
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster import RasterConfig
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.stages.visibility import shadow_maps

CFG = RasterConfig()


def _unit(n):  # [..., 3]
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)


def _image(t, h, w, c):
    return np.array(t, dtype=np.float64).reshape(h, w, c)


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
@pytest.mark.parametrize("band", [0.5, 3.0])
@pytest.mark.parametrize("seed", [1, 2])
def test_surface_receivers_match_the_float64_reference(kind, band, seed):
    if kind == "perspective":
        cam = Camera.look_at([0.4, 0.9, 2.6], [0.0, 0.0, 0.0], width=24, height=20, fov_x=0.8)
    else:
        cam = Camera.look_at([-2.5, 1.2, 1.0], [0.0, 0.0, 0.0], width=24, height=20,
                             ortho_width=1.9)
    raw = random_scene(40, seed)
    _, got = shading.surface_aovs(to_surfels(raw), cam, band, CFG)
    ref = reference(cam, raw, CFG, surface_band=band)
    ok = ~(ref["unsure"] | ref["surface_unsure"]) & (ref["alpha"] > 0)
    # float32 may take the other branch near a threshold: those pixels must stay rare.
    assert ok.sum() > 0.8 * (ref["alpha"] > 0).sum() > 200
    # The cases the surface exists for occur: pixels whose pairs lie in another order along
    # the ray than in compositing order (tilted splats), and surfaces the band leaves out.
    assert (ref["reordered"] & ok).sum() > 20
    blended = _unit(ref["normal"])
    surface = _unit(ref["surface_normal"])
    assert (np.abs(ref["surface_depth"] - ref["depth"])[ok] > 0.01).sum() > 20
    assert (np.sum(blended * surface, -1)[ok] < 0.99).sum() > 20
    depth = _image(got["depth"], 20, 24, 1)[..., 0]
    normal = _image(got["normal"], 20, 24, 3)
    # 1e-4 relative on depth, 1e-4 absolute on the (unnormalised) normal sums: float32 sums
    # of O(10) weights (~1e-6) plus the intersection's rounding, as the rasterizer's test.
    np.testing.assert_allclose(depth[ok], ref["surface_depth"][ok], rtol=1e-4, atol=0)
    np.testing.assert_allclose(normal[ok], ref["surface_normal"][ok], rtol=0, atol=1e-4)
    assert np.all(depth[ref["alpha"] == 0] == 0) and np.all(normal[ref["alpha"] == 0] == 0)


def _quat_to(normal):
    """wxyz quaternion turning +z onto ``normal``."""
    from scipy.spatial.transform import Rotation

    z = np.array([0.0, 0.0, 1.0])
    n = _unit(np.asarray(normal, np.float64))
    axis = np.cross(z, n)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0]) if n[2] > 0 else np.array([0.0, 1.0, 0.0, 0.0])
    q = Rotation.from_rotvec(axis / s * np.arctan2(s, n @ z)).as_quat()  # xyzw
    return np.array([q[3], q[0], q[1], q[2]])


def _surfels(centres, normals, scales, opacity) -> Surfels:
    c = np.asarray(centres, np.float32)
    q = np.array([_quat_to(n) for n in normals], np.float32)
    ls = np.log(np.asarray(scales, np.float32))
    op = np.full(len(c), np.log(opacity / (1 - opacity)), np.float32)
    return Surfels(mi.Point3f(*(c[:, k] for k in range(3))),
                   mi.Point2f(*(ls[:, k] for k in range(2))),
                   mi.Vector4f(*(q[:, k] for k in range(4))), mi.Float(op), {})


def test_a_base_pixel_beside_an_object_keeps_the_base_normal():
    """The hard case: a low wall stands on a base, seen from above and in front. Over the
    wall's top edge the pixels see the base behind it, and the wall's splats reach into them
    with under half the weight: the blended normal bends toward the wall's and the blended
    point floats between the two. The median surface's stays on the base, with its normal,
    to float32 rounding (and where the wall carries the pixel, on the wall)."""
    up = np.array([0.0, 1.0, 0.0])
    xs = np.linspace(-0.6, 0.6, 13)
    base = [(x, 0.0, z) for x in xs for z in np.linspace(-1.2, 0.6, 19)]  # y = 0
    wall = [(x, y, -0.25) for x in xs for y in (0.05, 0.12, 0.19)]  # faces +z, top ~0.2
    normals = [up] * len(base) + [(0.0, 0.0, 1.0)] * len(wall)
    surfels = _surfels(base + wall, normals, [(0.07, 0.07)] * len(base) +
                       [(0.07, 0.035)] * len(wall), 0.95)
    cam = Camera.look_at([0.0, 0.9, 1.4], [0.0, 0.0, -0.3], width=40, height=32, fov_x=0.9)
    plain = shading.pixel_geometry(surfels, cam)
    surf = shading.pixel_geometry(surfels, cam, surface_band=0.5)

    def rows(v):
        return np.stack([np.array(v[k]) for k in range(3)], -1)

    n0, n1, p0, p1 = rows(plain.normal), rows(surf.normal), rows(plain.points), \
        rows(surf.points)
    covered = np.array(surf.alpha) > 0.9
    # Base pixels (by the median surface) whose blended normal the wall bends > 10 degrees.
    bent = covered & (n1 @ up > 0.999) & (n0 @ up < np.cos(np.radians(10.0)))
    assert bent.sum() >= 10, bent.sum()
    np.testing.assert_allclose(n1[bent], np.tile(up, (bent.sum(), 1)), atol=1e-5)
    np.testing.assert_allclose(p1[bent, 1], 0.0, atol=1e-4)  # on the base plane
    assert np.median(p0[bent, 1]) > 0.02  # the blend's point floats above it
    on_wall = covered & (n1[:, 2] > 0.999)
    assert on_wall.sum() >= 10  # the wall's own pixels keep the wall
    # Alpha (which pixels are supervised) is the blend's.
    np.testing.assert_array_equal(np.array(surf.alpha), np.array(plain.alpha))


def _wall_on_base_model() -> Surfels:
    """The wall-on-base scene with stage 4's material channels."""
    xs = np.linspace(-0.6, 0.6, 13)
    base = [(x, 0.0, z) for x in xs for z in np.linspace(-1.2, 0.6, 19)]
    wall = [(x, y, -0.25) for x in xs for y in (0.05, 0.12, 0.19)]
    s = _surfels(base + wall, [(0.0, 1.0, 0.0)] * len(base) + [(0.0, 0.0, 1.0)] * len(wall),
                 [(0.07, 0.07)] * len(base) + [(0.07, 0.035)] * len(wall), 0.95)
    n = s.count
    return dataclasses.replace(s, channels={
        "albedo": mi.TensorXf(np.full((n, 3), 0.6, np.float32)),
        "roughness": mi.TensorXf(np.full((n, 1), 0.5, np.float32)),
        "metallic": mi.TensorXf(np.zeros((n, 1), np.float32))})


def test_the_plugin_shades_the_receivers_and_maps_its_model_was_fitted_with(plugins, tmp_path):
    """Stage 4 records its shadow-map and receiver settings in the model's PLY; the
    ``surfel_relight`` plugin, which sees only the file, relights with them, as ``relight``
    does with the run's."""
    from mi_shadowgs.io.ply import PlyError, save_ply
    from mi_shadowgs.stages.material import outputs
    from mi_shadowgs.stages.relight import render as relight

    s = _wall_on_base_model()
    paper = shadow_maps.VisibilityConfig(resolution=128, receiver_band=0.5)
    cpu = dataclasses.replace(run_presets.visibility_config("cpu-small"), resolution=128)
    assert cpu.projection != paper.projection  # else the cpu case below would prove nothing
    fitted, plain, ortho = tmp_path / "fitted.ply", tmp_path / "plain.ply", tmp_path / "o.ply"
    save_ply(fitted, s, outputs.model_metadata(paper, False))
    save_ply(plain, s)  # as before the record, or from another tool: the paper's blend
    save_ply(ortho, s, outputs.model_metadata(cpu, False))
    # A model saved with the band alone (an older format): the paper's maps, its band.
    banded = tmp_path / "banded.ply"
    save_ply(banded, s, {outputs.BAND_METADATA_KEY: "0.5"})
    bad, bad_json = tmp_path / "bad.ply", tmp_path / "bad_json.ply"
    save_ply(bad, s, {outputs.BAND_METADATA_KEY: "wide"})
    save_ply(bad_json, s, {outputs.VISIBILITY_METADATA_KEY: '{"projection":"fisheye"}'})
    # 80 x 64: at 40 x 32 no pixel centre lands where the two maps' depth tests differ
    cam = Camera.look_at([0.0, 0.9, 1.4], [0.0, 0.0, -0.3], width=80, height=64, fov_x=0.9)
    light = {"type": "directional", "direction": [0.3, -0.8, 0.5], "irradiance": 2.0}

    def plugin(path, **props):
        return mi.load_dict({"type": "scene", "light": light, "sensor":
                             cam.to_mitsuba_dict(spp=1), "integrator":
                             {"type": "surfel_relight", "filename": str(path),
                              "shadow_resolution": 128, "specular": False, **props}})

    def library(config):
        model = relight.RelightModel(s, False, True, receiver_band=config.receiver_band)
        sc = plugin(plain)
        lights = sc.integrator().light_set(sc)
        pos = np.stack([np.asarray(s.position[k]) for k in range(3)], -1)
        bounds = shadow_maps.SceneBounds.from_points(pos, [cam])
        maps = relight.shadow_maps_for(model, lights, bounds, config)
        return relight.relight_view(model, cam, lights, maps, 0.0)["rgb"]

    blended = dataclasses.replace(paper, receiver_band=0.0)
    ref = {"paper": library(paper), "blended": library(blended), "cpu": library(cpu)}
    # the band and the maps each change the image here (the base's pixels over the wall's
    # edge; the shadow's outline), else the comparisons below would prove nothing
    assert np.abs(ref["paper"] - ref["blended"]).max() > 0.05
    assert np.abs(ref["cpu"] - ref["paper"]).max() > 0.05
    for path, props, config, key in ((fitted, {}, paper, "paper"),
                                     (banded, {}, paper, "paper"),
                                     (plain, {}, blended, "blended"),
                                     (fitted, {"receiver_band": 0.0}, blended, "blended"),
                                     (ortho, {}, cpu, "cpu")):  # given: used as given
        sc = plugin(path, **props)
        assert sc.integrator().vis_config == config
        np.testing.assert_allclose(np.asarray(mi.render(sc))[..., :3], ref[key],
                                   rtol=2e-4, atol=1e-6)
    with pytest.raises(PlyError, match="receiver_band 'wide' is not a number"):
        relight.recorded_visibility(bad)
    for path, props in ((bad, {}), (bad, {"receiver_band": 0.0})):
        with pytest.raises(Exception, match=f"{path}: header comment receiver_band 'wide'"):
            plugin(path, **props)  # Mitsuba passes the message on in its own exception
    with pytest.raises(PlyError, match=f"{bad_json}: header comment visibility.*projection"):
        relight.recorded_visibility(bad_json)


@pytest.mark.parametrize("settings, lists, band", [
    ({"visibility": {"receiver_band": 0.5, "layer_bias": 1.0}}, True, 0.5),
    ({"visibility": {"layer_bias": 1.0}}, True, 0.0),  # a run from before the band: blended
    ({"visibility": {"receiver_band": 0.5}}, False, None),  # the manifest is not its
    ({"material": {}}, True, None)])  # no visibility settings (a stage-1 folder)
def test_a_model_saved_before_the_record_takes_its_settings_from_its_manifest(
        tmp_path, settings, lists, band):
    """Models fitted before the PLY recorded their maps and receivers are relit with them
    too: the stage-4 folder's manifest records the settings it ran with."""
    import json

    from mi_shadowgs.io.ply import save_ply
    from mi_shadowgs.io.provenance import FORMAT_VERSION, MANIFEST_NAME
    from mi_shadowgs.stages.relight.render import recorded_visibility

    save_ply(tmp_path / "model.ply", _wall_on_base_model())
    assert recorded_visibility(tmp_path / "model.ply") is None  # no manifest: another tool's
    (tmp_path / MANIFEST_NAME).write_text(json.dumps(
        {"format": FORMAT_VERSION, "command": "run", "complete": True, "settings": settings,
         "files": ["model.ply", "light.json"] if lists else ["light.json"]}))
    config = recorded_visibility(tmp_path / "model.ply")
    if band is None:
        assert config is None
    else:
        assert config.receiver_band == band and config.layer_bias == 1.0


def test_one_surface_gives_the_blended_receivers():
    """Where a pixel sees one surface (a flat, opaque base seen from above), the median
    surface is all of it: the same depth and normal as the blend."""
    xs = np.linspace(-0.6, 0.6, 13)
    surfels = _surfels([(x, 0.0, z) for x in xs for z in xs], [(0.0, 1.0, 0.0)] * 169,
                       [(0.07, 0.07)] * 169, 0.95)
    cam = Camera.look_at([0.05, 2.0, 0.3], [0.0, 0.0, 0.0], width=24, height=24, fov_x=0.5)
    plain = shading.pixel_geometry(surfels, cam)
    surf = shading.pixel_geometry(surfels, cam, surface_band=0.5)
    ok = np.array(plain.alpha) > 0.5
    assert ok.sum() > 300
    np.testing.assert_allclose(np.array(surf.depth).ravel()[ok],
                               np.array(plain.depth).ravel()[ok], rtol=1e-5)
    for k in range(3):
        np.testing.assert_allclose(np.array(surf.normal[k])[ok], np.array(plain.normal[k])[ok],
                                   atol=1e-5)


def test_stage_4_and_relighting_shade_the_same_receivers():
    """Stage 4's views (``prepare_view``) and relighting's buffers (``view_buffers``) take
    the receivers from the same setting, so a model is relit as it was fitted."""
    from mi_shadowgs.stages.material.config import MaterialConfig
    from mi_shadowgs.stages.material.normals import with_surfel_normals
    from mi_shadowgs.stages.material.views import prepare_view
    from mi_shadowgs.stages.relight import render as relight

    raw = random_scene(40, 3)
    s = to_surfels(raw)
    ch = dict(s.channels)
    n = s.count
    ch.update({"albedo": mi.TensorXf(np.full((n, 3), 0.5, np.float32)),
               "roughness": mi.TensorXf(np.full((n, 1), 0.5, np.float32)),
               "metallic": mi.TensorXf(np.zeros((n, 1), np.float32))})
    s = dataclasses.replace(s, channels=ch)
    cam = Camera.look_at([0.4, 0.9, 2.6], [0.0, 0.0, 0.0], width=24, height=20, fov_x=0.8)
    cfg = MaterialConfig()
    for band in (0.0, 0.5):
        view = prepare_view(s, cam, np.zeros((20, 24, 3)), np.ones((20, 24)),
                            cfg, receiver_band=band)
        buf = relight.view_buffers(s, cam, receiver_band=band)
        for k in range(3):
            np.testing.assert_array_equal(np.array(view.geom.normal[k]),
                                          np.array(buf.geom.normal[k]))
            np.testing.assert_array_equal(np.array(view.geom.points[k]),
                                          np.array(buf.geom.points[k]))
        # The normal phase blends its trainable normals over the same pairs: from the
        # surfels' own normals it gives back the receivers' normals.
        pn = with_surfel_normals(view, shading.shading_normals(s),
                                 s.position).geom.normal
        for k in range(3):
            np.testing.assert_allclose(np.array(pn[k]), np.array(view.geom.normal[k]),
                                       atol=2e-6)
    # and the setting changes them (else the comparison above proves nothing)
    a = shading.pixel_geometry(s, cam)
    b = shading.pixel_geometry(s, cam, surface_band=0.5)
    assert not np.array_equal(np.array(a.normal[0]), np.array(b.normal[0]))


def test_a_run_is_relit_with_the_receivers_it_was_fitted_with():
    """``recorded_config`` reads the visibility settings a run's manifest recorded: a run
    fitted on the median surface is relit on it; a run recorded before the setting existed
    gets the blend it was fitted with, not the preset's new default."""
    from mi_shadowgs.stages.relight.runner import recorded_config

    preset = dataclasses.replace(run_presets.visibility_config("cpu-small"), receiver_band=0.5)
    saved = dataclasses.asdict(preset)
    assert recorded_config(shadow_maps.VisibilityConfig, saved,
                           lambda: None).receiver_band == 0.5
    old = {k: v for k, v in saved.items() if k != "receiver_band"}
    got = recorded_config(shadow_maps.VisibilityConfig, old, lambda: None)
    assert got.receiver_band == 0.0 and got.layer_bias == preset.layer_bias
    assert recorded_config(shadow_maps.VisibilityConfig, None, lambda: preset) is preset
    # A record that is there but does not read is refused by name, never swapped for the
    # preset's settings (a relight would use maps and receivers the fit did not).
    for broken, field in (({**saved, "receiver_band": "0.5"}, "receiver_band"),
                          ({**saved, "resolution": -3}, "resolution"), ([1, 2], "not a dict")):
        with pytest.raises(ConfigError, match=f"run/manifest.*{field}"):
            recorded_config(shadow_maps.VisibilityConfig, broken, lambda: preset,
                            "run/manifest")


def test_a_view_with_nothing_in_it_has_empty_receivers():
    """Hard case: no splat in view (a camera looking away): no pairs to sort, every pixel
    empty, as the blend's."""
    s = to_surfels(random_scene(40, 1))
    cam = Camera.look_at([0.0, 0.0, 5.0], [0.0, 0.0, 10.0], width=16, height=12, fov_x=0.8)
    g = shading.pixel_geometry(s, cam, surface_band=0.5)
    assert np.array(g.alpha).max() == 0
    assert np.array(g.depth).max() == 0 and np.abs(np.array(g.normal[0])).max() == 0
    assert len(np.array(g.surface_pairs.weight)) == 0


def test_receiver_band_is_checked():
    with pytest.raises(ValueError, match="visibility"):
        shadow_maps.VisibilityConfig(receiver_band=-1.0)


def test_surface_receivers_render_in_row_bands_alike():
    """A pair list too large for the memory budget is built in bands of rows: the receivers
    are the same (each pixel's pairs lie in one band)."""
    raw = random_scene(40, 1)
    s = to_surfels(raw)
    cam = Camera.look_at([0.4, 0.9, 2.6], [0.0, 0.0, 0.0], width=24, height=20, fov_x=0.8)
    from mi_shadowgs.core.raster import pair_counts, splat_pairs

    _, whole = shading.surface_aovs(s, cam, 0.5, CFG)
    small = dataclasses.replace(CFG, max_pairs=pair_counts(s, cam)[0] // 3)
    assert len(splat_pairs(s, cam, small)[0]) == len(splat_pairs(s, cam, CFG)[0])
    _, banded = shading.surface_aovs(s, cam, 0.5, small)
    for k in ("depth", "normal"):
        np.testing.assert_array_equal(np.array(whole[k]), np.array(banded[k]))
