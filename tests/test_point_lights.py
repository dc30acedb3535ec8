"""Lamps in and out: ``relight --point``, Mitsuba ``point``/``spot``/sphere ``area`` emitters
read as lamps (against Mitsuba's own emitters), a relit view under a point lamp against
Mitsuba's direct lighting of the same scene, light sets mixing lamps and directional lights,
the bad inputs (exit 2, the field named), and the lamps of ``export``, the viewer, the report,
the generator's point relighting and its scoring.

Everything at <= 64^2 on GT surfels (``synthetic_asset.sphere_on_plane``)."""

from __future__ import annotations

import json
import math
import types

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.ndimage import binary_erosion
from synthetic_asset import CENTER, RADIUS, fake_run, sphere_on_plane

import mi_shadowgs
from mi_shadowgs.core import jit, shading
from mi_shadowgs.stages.relight import lamps
from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.visibility.shadow_maps import SceneBounds

S = 64
LAMP = (1.2, 2.6, 0.8)  # above the plane, outside the scene's bounding sphere
INTENSITY = 12.0  # W/sr
BOUNDS = SceneBounds((0.0, 0.3, 0.0), 1.7, 4.0)


def _v3(a, t=mi.Vector3f):
    return t(*(jit.array(np.asarray(a)[:, k].astype(np.float32)) for k in range(3)))


def _irradiance_factors(ls: shading.LightSet, pts: np.ndarray) -> np.ndarray:
    """[K, P] what light k gives points ``pts`` [P, 3] at normal incidence (weight times
    the falloff and cone), from our kernel."""
    out = []
    for k in range(ls.count):
        li = dr.full(mi.UInt32, k, len(pts))
        _, fac = shading.light_vectors(_v3(pts, mi.Point3f), li, ls.directions, ls.positions,
                                       ls.center, ls.cones)
        w = float(np.asarray(ls.weights[0])[k])
        out.append(w * (np.ones(len(pts)) if fac is None else np.asarray(fac, np.float64)))
    return np.array(out)


# -- the shading kernel: a spot's cone, against float64 -------------------------------------
def _reference(pts, nrm, albedo, lights):
    """sum over lights of a / pi (n . l)^+ E(x), float64: lamps (p, I, cone or None) with
    E = I f(angle) / |p - x|^2, f Mitsuba's spot profile; directional (d, E)."""
    out = np.zeros((len(pts), 3))
    for lt in lights:
        if lt[0] == "dir":
            _, d, e = lt
            l_dir, irr = np.broadcast_to(d, pts.shape), np.full(len(pts), e)
        else:
            _, p, inten, cone = lt
            to = p - pts
            r = np.linalg.norm(to, axis=1)
            l_dir = to / r[:, None]
            irr = inten / r**2
            if cone is not None:
                axis, cutoff, beam = np.asarray(cone[:3]), cone[3], cone[4]
                theta = np.arccos(np.clip(-(l_dir @ axis), -1, 1))
                f = np.where(theta <= beam, 1.0, (cutoff - theta) / (cutoff - beam))
                irr = irr * np.where(theta < cutoff, f, 0.0)
        out += albedo / np.pi * (np.maximum(np.sum(nrm * l_dir, 1), 0) * irr)[:, None]
    return out


def test_lamps_and_a_spots_cone_shade_as_a_float64_reference():
    rng = np.random.default_rng(4)
    n = 400
    pts = rng.uniform(-1.5, 1.5, (n, 3)) * [1, 0.2, 1]
    nrm = rng.normal(size=(n, 3)) * 0.3 + [0, 1, 0]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    geom = shading.PixelGeometry(dr.ones(mi.Float, n), None, None, _v3(nrm), _v3(nrm),
                                 _v3(pts, mi.Point3f), dr.zeros(mi.Float, n))
    axis = np.array([-0.3, -1.0, -0.2]) / np.linalg.norm([-0.3, -1.0, -0.2])
    cone = (*axis, math.radians(25.0), math.radians(15.0))  # its edge falls among the points
    spot = lamps.Lamp((1.0, 3.0, 0.5), (40.0,) * 3, cone=cone)
    point = lamps.Lamp((-2.0, 2.5, 1.0), (20.0,) * 3)
    sun = relight.directional_light_set([[0.3, 0.8, -0.2]], [1.5])
    ls = relight.combine_light_sets([lamps.lamp_light_set([spot, point], BOUNDS.center), sun])
    albedo = np.array([0.6, 0.5, 0.4])
    zero = dr.zeros(mi.Float, n)
    got = shading.direct(geom, mi.Color3f(*albedo.tolist()), zero, zero, ls, None, False)
    got = np.stack([np.asarray(got[c], np.float64) for c in range(3)], 1)
    ref = _reference(pts, nrm, albedo, [
        ("lamp", np.array(spot.position), 40.0, cone), ("lamp", np.array(point.position), 20.0,
                                                        None),
        ("dir", sun.directions[0], 1.5)])
    # float32 positions and angles: relative 1e-5 of the largest radiance
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=2e-5 * ref.max())
    theta = np.degrees(np.arccos((pts - spot.position) @ axis /
                                 np.linalg.norm(pts - spot.position, axis=1)))
    assert ((theta > 15) & (theta < 25)).sum() > 20  # the ramp is exercised


# -- Mitsuba's emitters as lamps ------------------------------------------------------------
_HELD = []  # the scenes of _emitters: an area emitter's shape lives in its scene


def _emitters(**extra):
    spot_tf = mi.ScalarTransform4f().look_at(origin=[1.0, 3.5, 0.5], target=[0.3, 0.0, 0.0],
                                             up=[0, 0, 1])
    desc = {"type": "scene",
            "p": {"type": "point", "position": list(LAMP),
                  "intensity": {"type": "rgb", "value": [12.0, 10.0, 8.0]}},
            "s": {"type": "spot", "to_world": spot_tf, "cutoff_angle": 20.0,
                  "beam_width": 12.0, "intensity": {"type": "rgb", "value": [30.0] * 3}},
            "ball": {"type": "sphere", "center": [-1.5, 2.5, -1.0], "radius": 0.3,
                     "emitter": {"type": "area",
                                 "radiance": {"type": "rgb", "value": [4.0, 3.0, 2.0]}}},
            **extra}
    _HELD.append(mi.load_dict(desc))
    return _HELD[-1].emitters()


def test_point_spot_and_sphere_emitters_give_mitsubas_irradiance():
    emitters = _emitters()
    by_class = {e.class_name(): e for e in emitters}
    ls = relight.emitter_light_set(emitters, where="t", bounds=BOUNDS)
    assert ls.count == 3 and np.all(ls.local)
    order = {lamps.mitsuba_lamp(e, "t").position: e.class_name() for e in emitters}
    pos = lamps.local_rows(ls)[0]
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-1.5, 1.5, 3000), np.zeros(3000), rng.uniform(-1.5, 1.5, 3000)]
    ours = _irradiance_factors(ls, pts)  # [K, P]
    it = dr.zeros(mi.Interaction3f, len(pts))
    it.p = _v3(pts, mi.Point3f)
    for k in range(3):
        e = by_class[order[tuple(pos[k])]]
        if e.class_name() == "AreaLight":
            # Mitsuba's irradiance at normal incidence toward the sphere's centre: the mean
            # of its sampled radiance / pdf times the cosine to that axis.
            to_c = pos[k] - pts
            axis = to_c / np.linalg.norm(to_c, axis=1, keepdims=True)
            g = (np.arange(16) + 0.5) / 16  # 16 x 16 stratified samples per point
            u = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
            many = dr.zeros(mi.Interaction3f, len(pts) * len(u))
            many.p = _v3(np.repeat(pts, len(u), 0), mi.Point3f)
            ds, spec = e.sample_direction(many, mi.Point2f(*np.tile(u, (len(pts), 1)).T
                                                           .astype(np.float32)))
            d = np.asarray(ds.d, np.float64).T
            cos = np.maximum(np.sum(d * np.repeat(axis, len(u), 0), 1), 0)
            ref = (np.asarray(spec[0], np.float64) * cos).reshape(len(pts), -1).mean(1)
            assert np.all(np.abs(ours[k] - ref) <= 0.01 * ref + 1e-6)  # the sphere: exact
            continue
        _, spec = e.sample_direction(it, mi.Point2f(0.5, 0.5))
        ref = np.asarray(spec[0], np.float64)  # red: I falloff / r^2
        # float32: our weight (I / |p - c|^2) times the falloff is a few roundings from
        # Mitsuba's I / r^2 (measured up to 2.3e-5); in the spot's ramp the two float32
        # angles differ by ~4e-7 rad (measured up to 3e-6 of the peak)
        np.testing.assert_allclose(ours[k], ref, rtol=1e-4, atol=1e-5 * ref.max())
        if e.class_name() == "SpotLight":  # the cone's edge and ramp are among the points
            cone = ref * np.sum((pos[k] - pts) ** 2, 1) / 30.0
            assert (cone == 0).sum() > 300 and ((cone > 0.01) & (cone < 0.99)).sum() > 100
    # the sphere's intensity is its radiance times pi R^2 toward every side
    (ball,) = [lp for lp in map(lambda e: lamps.mitsuba_lamp(e, "t"), emitters) if lp.radius]
    assert ball.radius == pytest.approx(0.3) and ball.intensity == pytest.approx(
        (4.0 * math.pi * 0.09, 3.0 * math.pi * 0.09, 2.0 * math.pi * 0.09))


@pytest.mark.parametrize("extra, named", [
    ({"s2": {"type": "spot", "cutoff_angle": 10.0, "intensity": {"type": "rgb", "value": 5.0},
             "to_world": mi.ScalarTransform4f().look_at(origin=[0, 4, 0], target=[9, 4, 0],
                                                        up=[0, 1, 0])}},
     "misses the scene"),
    ({"rect": {"type": "rectangle", "emitter": {"type": "area"},
               "to_world": mi.ScalarTransform4f().translate([0, 5, 0])}}, "Rectangle"),
    ({"low": {"type": "point", "position": [3.0, -0.5, 0.0]}}, "below the base plane"),
    ({"in": {"type": "point", "position": [0.2, 0.5, 0.1]}}, "inside the scene"),
    ({"egg": {"type": "sphere", "to_world": mi.ScalarTransform4f().translate([0, 4, 0])
              .scale([0.2, 0.4, 0.2]), "emitter": {"type": "area"}}}, "scaled unevenly"),
])
def test_lamps_the_model_cannot_take_are_refused(extra, named):
    with pytest.raises(ValueError, match=named):
        relight.emitter_light_set(_emitters(**extra), where="--scene x.xml", bounds=BOUNDS)


# -- light sets ------------------------------------------------------------------------------
def test_mixed_light_sets_combine_scale_and_weigh_the_centre():
    a = lamps.lamp_light_set([lamps.Lamp(LAMP, (INTENSITY,) * 3, 0.1)], (0.0, 0.0, 0.0))
    b = lamps.lamp_light_set([lamps.Lamp((-2.0, 3.0, 1.0), (5.0, 6.0, 7.0))], BOUNDS.center)
    sun = relight.directional_light_set([[0.0, 1.0, 0.0]], [2.0])
    both = relight.combine_light_sets([sun, a, b])
    assert both.count == 3 and list(both.local) == [False, True, True]
    np.testing.assert_allclose(both.center, [0.0, 0.0, 0.0])
    np.testing.assert_allclose(lamps.intensities(both)[1:], [[INTENSITY] * 3, [5, 6, 7]],
                               rtol=1e-6)
    np.testing.assert_allclose(lamps.local_rows(both)[1], [0.0, 0.1, 0.0])
    pts = np.array([[0.3, 0.0, 0.2], [-1.0, 0.5, 0.4]])
    sep = np.concatenate([_irradiance_factors(s, pts) for s in (sun, a, b)])
    np.testing.assert_allclose(_irradiance_factors(both, pts), sep, rtol=1e-5)
    half = relight.scale_light_set(both, 0.5)
    np.testing.assert_allclose(lamps.intensities(half)[1:], lamps.intensities(both)[1:] * 0.5,
                               rtol=1e-6)
    # E_up: the sun's 2 and each lamp's irradiance at the centre along its direction there
    d = np.asarray(LAMP) / np.linalg.norm(LAMP)
    e_b = np.mean([5, 6, 7]) / np.sum((np.array([-2.0, 3.0, 1.0])) ** 2)
    d_b = np.array([-2.0, 3.0, 1.0]) / np.linalg.norm([-2.0, 3.0, 1.0])
    expect = 2.0 + INTENSITY / np.sum(np.square(LAMP)) * d[1] + e_b * d_b[1]
    assert relight.upward_irradiance(both) == pytest.approx(expect, rel=1e-5)
    # a spot aimed away from the centre gives it nothing
    away = lamps.Lamp((0.0, 3.0, 0.0), (9.0,) * 3, cone=(0.0, 0.0, 1.0, 0.3, 0.2))
    assert relight.upward_irradiance(lamps.lamp_light_set([away], (0.0, 0.0, 0.0))) == 0.0


def test_point_light_set_and_lights_json_lamps():
    ls = relight.point_light_set([LAMP], [INTENSITY], BOUNDS.center, [0.2])
    assert float(np.asarray(ls.weights[0])[0]) == pytest.approx(
        INTENSITY / np.sum((np.array(LAMP) - BOUNDS.center) ** 2), rel=1e-6)
    entry = {"name": "lamp_moved", "type": "point",
             "lights": [{"position": list(LAMP), "intensity": [INTENSITY] * 3, "radius": 0.2}]}
    js = relight.lights_from_json(entry, BOUNDS.center)
    np.testing.assert_allclose(_irradiance_factors(js, np.zeros((1, 3))),
                               _irradiance_factors(ls, np.zeros((1, 3))), rtol=1e-6)
    for bad in ({"position": [1, 2]}, {"position": list(LAMP), "intensity": [-1]},
                {"position": list(LAMP), "intensity": [1], "radius": -1}):
        with pytest.raises(ValueError, match="relighting 'x' light 0"):
            relight.lights_from_json({"name": "x", "type": "point", "lights": [bad]}, (0, 0, 0))


# -- a relit view under a point lamp against Mitsuba ----------------------------------------
SENSOR = f"""<sensor type="perspective"><float name="fov" value="50"/>
  <transform name="to_world"><lookat origin="-2.2, 2.4, 2.6" target="0.1, 0.2, -0.1"
   up="0, 1, 0"/></transform>
  <sampler type="independent"><integer name="sample_count" value="64"/></sampler>
  <film type="hdrfilm"><integer name="width" value="{S}"/><integer name="height" value="{S}"/>
  <string name="pixel_format" value="rgba"/><rfilter type="box"/></film></sensor>"""
POINT_XML = (f'<emitter type="point"><point name="position" x="{LAMP[0]}" y="{LAMP[1]}" '
             f'z="{LAMP[2]}"/><rgb name="intensity" value="{INTENSITY}"/></emitter>')


@pytest.fixture(scope="module")
def lamp_scene(tmp_path_factory):
    """(our relit image through ``surfel_relight``, our visibility, Mitsuba's direct image,
    Mitsuba's ray-traced visibility, the pixels both cover) of GT surfels of a ball on a
    plane (albedo 0.5, diffuse) under a point lamp."""
    from mi_shadowgs.core import render as core_render
    from mi_shadowgs.io import ply

    mi_shadowgs.register_plugins()
    model = sphere_on_plane()
    n = len(model.position)
    model.channels.update(albedo=np.full((n, 3), 0.5, np.float32),
                          metallic=np.zeros((n, 1), np.float32))
    path = tmp_path_factory.mktemp("lamp") / "gt.ply"
    ply.write_ply_model(path, model)
    ours = mi.load_string(f"""<scene version="3.0.0"><integrator type="surfel_relight">
      <string name="filename" value="{path}"/><boolean name="specular" value="false"/>
      </integrator>{SENSOR}{POINT_XML}</scene>""")
    img = np.asarray(mi.render(ours))
    diffuse = '<bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>'
    ref_scene = mi.load_string(f"""<scene version="3.0.0"><integrator type="direct"/>
      {SENSOR}{POINT_XML}
      <shape type="sphere"><point name="center" x="{CENTER[0]}" y="{CENTER[1]}"
       z="{CENTER[2]}"/><float name="radius" value="{RADIUS}"/>{diffuse}</shape>
      <shape type="rectangle"><transform name="to_world"><scale value="1.2"/>
       <rotate x="1" angle="-90"/></transform>{diffuse}</shape></scene>""")
    ref = np.asarray(mi.render(ref_scene, seed=3))
    sensor = ref_scene.sensors()[0]
    ys, xs = np.mgrid[0:S, 0:S]
    film = mi.Point2f(((xs.ravel() + 0.5) / S).astype(np.float32),
                      ((ys.ravel() + 0.5) / S).astype(np.float32))
    rays, _ = sensor.sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
    si = ref_scene.ray_intersect(rays)
    hit = np.asarray(si.is_valid()).reshape(S, S)
    lit = hit & ~np.asarray(ref_scene.ray_test(si.spawn_ray_to(mi.Point3f(*LAMP)),
                                               si.is_valid())).reshape(S, S)
    # our visibility, as the plugin renders it (its bounds, the model's recorded maps)
    cam = core_render.sensor_camera(sensor)
    surf = ply.load_ply(path)
    bounds = SceneBounds.from_points(model.position.astype(np.float64), [cam])
    vis_cfg = relight.recorded_visibility(path) or relight.VisibilityConfig()
    rm = relight.RelightModel(surf, False, True, receiver_band=vis_cfg.receiver_band)
    ls = relight.point_light_set([LAMP], [INTENSITY], bounds.center)
    out = relight.relight_view(rm, cam, ls, relight.RelightCache().shadow_maps(
        rm, ls, bounds, vis_cfg), 0.0, buffers=True)
    both = binary_erosion(hit & (img[..., 3] > 0.99) & (out["alpha"] > 0.99), iterations=1)
    return img[..., :3], out["visibility"][..., 0] > 0.5, ref[..., :3], lit, both


def test_point_lamp_relit_view_matches_mitsuba_where_lit(lamp_scene):
    img, vis, ref, lit, both = lamp_scene
    unshadowed = binary_erosion(both & lit & vis, iterations=1)
    assert unshadowed.sum() > 300
    a, b = img[unshadowed], ref[unshadowed]
    psnr = 10 * np.log10(b.max() ** 2 / np.mean((a - b) ** 2))
    # Measured 34.1 dB, the sums within 0.7%: surfel normals and the pixel's footprint
    # (Mitsuba averages 64 samples over it, we shade its centre).
    assert psnr > 30.0, psnr
    assert a.sum() / b.sum() == pytest.approx(1.0, abs=0.02)


def _have_lamp_maps() -> bool:
    import mi_shadowgs.stages.visibility as vis

    return hasattr(vis, "lamp_arguments")


@pytest.mark.xfail(not _have_lamp_maps(), strict=True,
                   reason="lamp shadows take the orthographic map of the lamp's direction "
                          "until the shadow maps render from a lamp's position")
def test_point_lamp_shadow_matches_mitsubas_ray_traced_shadow(lamp_scene):
    _, vis, _, lit, both = lamp_scene
    ours, truth = both & ~vis, both & ~lit
    assert truth.sum() > 200
    # With perspective maps from the lamp, measured 0.964; with the map of its direction
    # from the centre, 0.549 (the shadow falls where a sun's would).
    assert (ours & truth).sum() / (ours | truth).sum() >= 0.9


# -- the command line: --point and its bad inputs -------------------------------------------
@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return fake_run(tmp_path_factory.mktemp("points"))[0]


def test_relight_point_renders_and_bad_lamps_exit_2(run, tmp_path, capsys):
    from mi_shadowgs import cli
    from mi_shadowgs.io.images import read_exr

    out = tmp_path / "relit"
    assert cli.main(["relight", str(run), "--out", str(out), "--point", "1.5,2.5,1,12",
                     "--point=-2,3,1,1,2,3,0.2", "--light", "30,45,0.5", "--orbit", "1",
                     "--no-progress"]) == 0, capsys.readouterr().err
    img = read_exr(out / "orbit_000.exr")
    assert img[..., :3].max() > 0.05
    assert json.loads((out / ".mi_shadowgs_manifest.json").read_text())["settings"]["points"] \
        == ["1.5,2.5,1,12", "-2,3,1,1,2,3,0.2"]
    capsys.readouterr()
    for point, named in (("0.1,0.4,0,5", "inside the scene"), ("2,-0.5,1,5", "base plane"),
                         ("2,3,1,5,-0.1", "field radius"), ("2,3,1,nan", "field intensity"),
                         ("2,3,1,0", "field intensity"), ("2,3,1,1,0,0,0,0", "got 8 field"),
                         ("2,3,x,5", "field z"), ("2,0.1,1,5,0.2", "base plane")):
        rc = cli.main(["relight", str(run), "--out", str(tmp_path / "bad"), "--point", point,
                       "--orbit", "1", "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 2 and named in err and "--point" in err, (point, err)
    assert not (tmp_path / "bad").exists()


def test_relight_scene_with_a_spot_that_misses_exits_2(run, tmp_path, capsys):
    from mi_shadowgs import cli
    from mi_shadowgs.io.images import read_exr

    lamps_xml = tmp_path / "lamps.xml"
    lamps_xml.write_text("""<scene version="3.0.0"><emitter type="spot" id="desk">
      <transform name="to_world"><lookat origin="2, 3, 1" target="0, 0.4, 0" up="0, 1, 0"/>
      </transform><rgb name="intensity" value="20"/></emitter>
      <shape type="sphere"><point name="center" x="-2" y="3" z="-1"/>
      <float name="radius" value="0.2"/><emitter type="area"><rgb name="radiance"
      value="30"/></emitter></shape></scene>""")
    assert cli.main(["relight", str(run), "--out", str(tmp_path / "lit"), "--scene",
                     str(lamps_xml), "--orbit", "1", "--no-progress"]) == 0
    assert read_exr(tmp_path / "lit" / "orbit_000.exr")[..., :3].max() > 0.05
    xml = tmp_path / "spot.xml"
    xml.write_text("""<scene version="3.0.0"><emitter type="spot" id="desk">
      <transform name="to_world"><lookat origin="3, 3, 0" target="9, 3, 0" up="0, 1, 0"/>
      </transform><float name="cutoff_angle" value="15"/></emitter></scene>""")
    assert cli.main(["relight", str(run), "--out", str(tmp_path / "o"), "--scene", str(xml),
                     "--orbit", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "emitter 'desk' (SpotLight)" in err and "misses the scene" in err


# -- export, viewer, report -----------------------------------------------------------------
def test_export_writes_lamps_that_mitsuba_reads_as_ours():
    from mi_shadowgs.stages.export.export import ExportConfig, fitted_lights, scene_xml

    c = np.array([0.0, 0.3, 0.0])
    lamps_at = np.array([[1.5, 2.5, 1.0], [-2.0, 3.0, 0.5]])
    dirs = np.array([[0.0, 1.0, 0.0], *((lamps_at - c) / np.linalg.norm(lamps_at - c, axis=1,
                                                                         keepdims=True))])
    light = {"radiance": [0.0] * 128, "active": [0, 0, 0], "directions": dirs.tolist(),
             "irradiance": [1.0, 2.0, 0.5], "positions": [None, *lamps_at.tolist()],
             "radii": [0.0, 0.0, 0.25], "center": c.tolist()}
    fitted = fitted_lights(light)
    scene = mi.load_string(scene_xml({}, fitted, [], ExportConfig(), "test"))
    emitters = {e.id() or e.get_shape().id(): e for e in scene.emitters()}
    assert sorted(e.class_name() for e in emitters.values()) == [
        "AreaLight", "DirectionalEmitter", "PointLight"]
    r2 = np.sum((lamps_at - c) ** 2, 1)  # light.json's weights are irradiance at c
    ours = relight.combine_light_sets([relight.directional_light_set(dirs[:1], [1.0]),
                                       relight.point_light_set(lamps_at, [2.0, 0.5] * r2, c,
                                                               [0.0, 0.25])])
    pts = np.array([[0.4, 0.0, -0.3], [-1.0, 0.0, 1.0]])
    ours_e = _irradiance_factors(relight.relocate(ours, c), pts)
    # what Mitsuba's point emitter gives these points is ours
    it = dr.zeros(mi.Interaction3f, len(pts))
    it.p = _v3(pts, mi.Point3f)
    _, spec = emitters["light_1"].sample_direction(it, mi.Point2f(0.5, 0.5))
    np.testing.assert_allclose(np.asarray(spec[0]), ours_e[1], rtol=1e-5)
    # the sphere reads back as the same lamp: position, radius, intensity
    ball = lamps.mitsuba_lamp([e for e in emitters.values()
                               if e.class_name() == "AreaLight"][0], "t")
    assert ball.radius == pytest.approx(0.25)
    np.testing.assert_allclose(ball.position, lamps_at[1], rtol=1e-6)
    np.testing.assert_allclose(ball.intensity, [0.5 * r2[1]] * 3, rtol=1e-5)


def test_viewer_lamp_and_fitted_lamps(tmp_path):
    import view_fixtures

    from mi_shadowgs.stages.viewer import viewer

    run, _ = view_fixtures.make_run(tmp_path, n=1500)
    session = viewer.ViewerSession(run)
    assert session.fitted_lamps() == []
    cam = session.default_camera(24, 24)
    lamp = viewer.LampLight(210.0, 40.0, 3.0, 3.0)
    a = session.render(cam, viewer.LightState(lamps=(lamp,)))
    b = session.render(cam, viewer.LightState(lamps=(viewer.LampLight(30.0, 40.0, 3.0, 3.0),)))
    assert a.image.max() > 0 and np.abs(a.image.astype(int) - b.image.astype(int)).max() > 20
    ls = session.light_set(viewer.LightState(lamps=(lamp,)))
    c, r = np.asarray(session.bounds.center), session.bounds.radius
    np.testing.assert_allclose(lamps.local_rows(ls)[0][0], lamp.position(c, r))
    assert lamps.intensities(ls)[0, 0] == pytest.approx(3.0 * (3.0 * r) ** 2, rel=1e-5)
    # a fit with a lamp shows it where it is
    light = run / "material" / "full" / "light.json"
    data = json.loads(light.read_text())
    pos = (c + 4 * r * np.asarray(data["directions"][0])).tolist()
    data.update(positions=[pos], radii=[0.1], center=c.tolist())
    light.write_text(json.dumps(data))
    again = viewer.ViewerSession(run)
    np.testing.assert_allclose(again.fitted_lamps()[0], pos)
    from mi_shadowgs.stages.viewer.server import ViewerServer

    server = ViewerServer(again, port=0, resolution=16).start()
    try:
        assert server.light_state().lamps == ()
        on, az, *_ = server.lamp
        on.value, az.value = True, 100.0
        server._draw_arrows()  # the lamp's ball and the fitted lamp's
        assert server.light_state().lamps[0].azimuth_deg == 100.0
        assert again.render(cam, server.light_state()).image.max() > 0
    finally:
        server.stop()


def test_report_table_gives_a_lamps_distance_and_position(tmp_path):
    from mi_shadowgs.summary import _fitted_lights_table

    path = tmp_path / "light.json"
    base = {"directions": [[0, 1, 0], [0.6, 0.8, 0.0]], "irradiance": [1.0, 3.0]}
    path.write_text(json.dumps(base))
    plain = _fitted_lights_table(path)
    assert len(plain["columns"]) == 5 and all(len(r) == 5 for r in plain["rows"])
    path.write_text(json.dumps({**base, "positions": [None, [3.0, 4.3, 0.0]],
                                "radii": [0.0, 0.15], "center": [0.0, 0.3, 0.0]}))
    tab = _fitted_lights_table(path)
    assert tab["columns"][5:] == ["distance", "position (x, y, z)", "radius"]
    lamp_row = tab["rows"][0]  # the strongest first
    assert lamp_row[5] == pytest.approx(5.0) and lamp_row[6] == "(3, 4.3, 0)"
    assert lamp_row[7] == 0.15 and tab["rows"][1][6] == "directional"


# -- the generator's point relighting and its scoring ---------------------------------------
def test_lamp_captures_get_a_point_relighting_and_plain_scenes_do_not():
    from mi_shadowgs.dataset.capture import RELIGHT_LAMP_NAME
    from mi_shadowgs.dataset.scene import SceneError, load_scene
    from mi_shadowgs.scenes import scene_path

    plain = load_scene(scene_path("default"))
    assert plain.lamp_relights == [] and "relight_lamp" not in plain.params
    lab = load_scene(scene_path("default"), {"lamp_distance": "6", "lamp_azimuth": "35"})
    (name, (lt,)), = lab.lamp_relights
    assert name == RELIGHT_LAMP_NAME and lab.params["relight_lamp"] == "185,35,6"
    assert lt.radius == 0 and lt.azimuth_deg == 185 and lt.distance == pytest.approx(
        6 * lab.object_radius)
    asked = load_scene(scene_path("default"), {"relight_lamp": "90,60,4"})
    assert asked.lamp_relights[0][1][0].elevation_deg == 60
    none = load_scene(scene_path("default"), {"lamp_distance": "6", "relight_lamp": "none"})
    assert none.lamp_relights == []
    for bad, named in (("90,60", "'relight_lamp'"), ("90,60,0.5", "inside the object"),
                       ("90,-40,6", "below the base")):
        with pytest.raises(SceneError, match=named):
            load_scene(scene_path("default"), {"relight_lamp": bad})


def test_a_point_relighting_is_scored_against_its_ground_truth(lamp_scene):
    """The evaluation's relit scores of a "point" relighting: the GT surfels under the lamp
    against Mitsuba's image of the true scene (with the model's recorded maps)."""
    from mi_shadowgs.core import render as core_render
    from mi_shadowgs.stages.evaluation import evaluate

    _, _, ref, _, both = lamp_scene
    scene = mi.load_string(f'<scene version="3.0.0">{SENSOR}</scene>')
    cam = core_render.sensor_camera(scene.sensors()[0])
    model = sphere_on_plane()
    n = len(model.position)
    model.channels.update(albedo=np.full((n, 3), 0.5, np.float32),
                          metallic=np.zeros((n, 1), np.float32))
    rm = relight.RelightModel(model.to_surfels(), False, True)
    entry = {"name": "lamp_moved", "type": "point",
             "lights": [{"position": list(LAMP), "intensity": [INTENSITY] * 3, "radius": 0}]}
    train = types.SimpleNamespace(lights={"relightings": [entry]}, root=None)
    test = types.SimpleNamespace(cameras=[cam], views=[types.SimpleNamespace(
        relit={"lamp_moved": ref})])
    bounds = SceneBounds.from_points(model.position.astype(np.float64), [cam])
    images = {}
    scores = evaluate._relit_scores(rm, train, test, bounds, relight.VisibilityConfig(),
                                    relight.RelightConfig(indirect="none"), None,
                                    both[None].astype(np.float32), images)
    got = scores["lamp_moved"]
    assert got["type"] == "point" and got["light_directions"] == 1
    assert got["psnr"] > 20.0, got  # shadows from the fallback maps included
    np.testing.assert_allclose(images["gt/relit/lamp_moved"][0], ref)


def test_generate_writes_the_point_relighting_the_evaluation_reads(tmp_path, capsys):
    from mi_shadowgs import cli
    from mi_shadowgs.dataset import layout
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.io.images import read_exr
    from mi_shadowgs.stages.evaluation.evaluate import check_evaluation_inputs, ground_truth

    out = tmp_path / "lamp"
    assert cli.main(["generate", "default", "--out", str(out), "-D", "lamp_distance=6",
                     "--width", "48", "--height", "48", "--n-train", "4", "--n-test", "1",
                     "--spp", "16", "--envmap", "none", "--no-progress"]) == 0
    capsys.readouterr()
    relit = json.loads((out / layout.LIGHTS_JSON).read_text())["relightings"]
    point = [e for e in relit if e["type"] == "point"]
    assert [e["name"] for e in point] == ["lamp_moved"]
    (lt,) = point[0]["lights"]
    centre = np.array(json.loads((out / layout.DATASET_JSON).read_text())["object"]["center"])
    assert np.linalg.norm(np.array(lt["position"]) - centre) == pytest.approx(lt["distance"])
    assert lt["intensity"] == pytest.approx([3.0 * lt["distance"] ** 2] * 3)
    img = read_exr(out / (layout.view_stem("test", 0) + layout.RELIT.format(name="lamp_moved")))
    assert img[..., :3].max() > 0.05
    train, test = load_dataset(out, "train"), load_dataset(out, "test")
    assert check_evaluation_inputs(train, test)["test relit images"] is None
    assert "lamp_moved" in test.views[0].relit and ground_truth(train, test)["relightings"] is None
    bad = json.loads((out / layout.LIGHTS_JSON).read_text())
    bad["relightings"][-1]["lights"][0]["intensity"] = [-1.0]
    train.lights = bad
    with pytest.raises(ValueError, match="relighting 'lamp_moved' light 0"):
        check_evaluation_inputs(train, test)
