"""Shadow maps from a lamp (``lamp_maps``): a float64 NumPy reference of the lamp camera's
projection and lookup, the analytic hard shadow of a point lamp and penumbra of a disc lamp,
mixed directional and local sets, the map cache, bad inputs, and Mitsuba ray tracing."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowgs.core import shading
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.sampling import surfels_on_surface
from mi_shadowgs.stages.relight.render import RelightCache, RelightModel, shadow_maps_for
from mi_shadowgs.stages.visibility.lamp_maps import MAX_LAMP_FOV_DEG, lamp_arguments
from mi_shadowgs.stages.visibility.shadow_maps import (
    MapCache,
    SceneBounds,
    VisibilityConfig,
    render_shadow_maps,
    view_visibility,
)
from tests.test_visibility import primary_hits

NAN3 = [math.nan] * 3


def _square(y: float, half: float):
    """A horizontal two-sided square at height ``y``, |x|, |z| <= half."""
    t = (mi.ScalarTransform4f().translate([0.0, y, 0.0])
         @ mi.ScalarTransform4f().rotate([1, 0, 0], -90.0)
         @ mi.ScalarTransform4f().scale([half, half, 1.0]))
    return {"type": "rectangle", "to_world": t,
            "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}}


def _square_surfels(y=1.0, half=0.5, count=6000):
    scene = mi.load_dict({"type": "scene", "sq": _square(y, half)})
    return surfels_on_surface(list(scene.shapes()), count, seed=2, sigma_factor=0.7)


def _points(p: np.ndarray) -> mi.Point3f:
    return mi.Point3f(*np.asarray(p, np.float32).T)


def _vectors(n: np.ndarray) -> mi.Vector3f:
    return mi.Vector3f(*np.asarray(n, np.float32).T)


def _evaluate(maps, pts, nrm=None) -> np.ndarray:
    v = maps.evaluate(_points(pts), None if nrm is None else _vectors(nrm))
    return np.asarray(v, np.float64).reshape(len(pts), maps.count)


# -- the lookup against a float64 reference -----------------------------------------------
def _reference(maps, pts: np.ndarray, nrm: np.ndarray, cfg: VisibilityConfig) -> np.ndarray:
    """Every map of a set with lamps in float64 NumPy: the lamp's map is a perspective
    camera at the lamp point; its texel at z-depth z is z / focal; the normal offset moves
    a point along n by normal_offset * texel * sin(n, l) with l toward that map's lamp
    point; V of a light is the mean of its maps' hard tests; 0 below the horizon of the
    direction to the lamp's centre."""
    r = maps.resolution
    light = (np.arange(len(maps.cameras)) if maps.map_light is None else maps.map_light)
    out = np.zeros((len(pts), maps.count))
    for m, cam in enumerate(maps.cameras):
        k = light[m]
        local = np.isfinite(maps.positions[k]).all()
        l_m = cam.origin - pts if local else np.broadcast_to(maps.directions[k], pts.shape)
        l_m = l_m / np.linalg.norm(l_m, axis=1, keepdims=True)
        _, z0 = cam.project(pts)
        texel = z0 / cam.focal if local else maps.texel
        cos = np.clip(np.sum(nrm * l_m, 1), -1, 1)
        moved = pts + nrm * (cfg.normal_offset * texel * np.sqrt(1 - cos**2))[:, None]
        uv, z = cam.project(moved)
        ix, iy = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (ix >= 0) & (ix < r) & (iy >= 0) & (iy < r) & (z > 0)
        dg = np.full(len(pts), np.inf)
        dg[inside] = maps.depth_image(m)[iy[inside], ix[inside]]
        bias = cfg.bias_texels * (z / cam.focal if local else maps.texel)
        out[:, k] += (z - dg <= bias) / np.count_nonzero(light == k)
    for k in range(maps.count):
        c = maps.positions[k]
        l_c = c - pts if np.isfinite(c).all() else np.broadcast_to(maps.directions[k],
                                                                   pts.shape)
        out[np.sum(nrm * l_c, 1) <= cfg.horizon_cos, k] = 0.0
    return out


def test_lamp_lookup_matches_float64_reference():
    rng = np.random.default_rng(4)
    surfels = _square_surfels()
    cfg = VisibilityConfig(resolution=64, bias_texels=1.0, lamp_samples=4)
    bounds = SceneBounds((0.0, 1.0, 0.0), 0.75, 3.0)
    lamps = np.array([[0.4, 3.0, 0.3], [-1.5, 2.5, 0.5]])
    dirs = lamps - bounds.center
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    maps = render_shadow_maps(surfels, dirs, bounds, cfg, positions=lamps,
                              radii=np.array([0.0, 0.2]))
    assert len(maps.cameras) == 5 and list(maps.map_light) == [0, 1, 1, 1, 1]
    pts = np.concatenate([rng.uniform([-1.5, 0, -1.5], [1.5, 0, 1.5], (3000, 3)),
                          rng.uniform([-0.6, 0.9, -0.6], [0.6, 1.1, 0.6], (500, 3))])
    nrm = rng.normal(size=pts.shape) * 0.3 + [0, 1, 0]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    got = _evaluate(maps, pts, nrm)
    f32 = lambda a: a.astype(np.float32).astype(np.float64)  # noqa: E731
    want = _reference(maps, f32(pts), f32(nrm), cfg)
    # float32 against float64 projection moves a point across a texel edge or the bias
    # now and then: a few per thousand of the (point, map) tests
    assert np.mean(np.abs(got - want) > 1e-6) < 5e-3
    assert 0.05 < np.mean(want[:, 0] == 0) < 0.95  # the case is not trivial


@pytest.mark.parametrize("scale", [1.0, 0.05])
def test_point_lamp_casts_the_central_projection_of_a_square(scale):
    """A square of half size a at height h over the plane y = 0, lit by a point lamp at P:
    the shadow is the square's central projection from P onto the plane. At scale 0.05 the
    lamp stands nearer the square than the rasterizer's default near plane (0.2 units)."""
    h, a = scale, 0.5 * scale
    lamp = np.array([0.7, 3.2, -0.4]) * scale
    surfels = _square_surfels(h, a, 8000)
    bounds = SceneBounds((0.0, h, 0.0), a * math.sqrt(2.0), 3.0 * scale)
    cfg = VisibilityConfig(resolution=256, bias_texels=1.0)
    d = (lamp - bounds.center) / np.linalg.norm(lamp - bounds.center)
    maps = render_shadow_maps(surfels, d[None], bounds, cfg, positions=lamp[None])
    g = np.linspace(-1.5, 1.5, 121) * scale
    pts = np.stack(np.meshgrid(g, [0.0], g, indexing="ij"), -1).reshape(-1, 3)
    nrm = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
    vis = _evaluate(maps, pts, nrm)[:, 0]
    q = pts + (h / lamp[1]) * (lamp - pts)  # where the ray to the lamp crosses y = h
    shadow = (np.abs(q[:, 0]) <= a) & (np.abs(q[:, 2]) <= a)
    ours = vis < 0.5
    iou = np.count_nonzero(ours & shadow) / np.count_nonzero(ours | shadow)
    assert iou >= 0.95, iou
    # a directional light of the centre's direction casts a shadow of another size
    par = q_dir = pts + (h / d[1]) * d
    par = (np.abs(q_dir[:, 0]) <= a) & (np.abs(q_dir[:, 2]) <= a)
    assert np.count_nonzero(par & shadow) / np.count_nonzero(par | shadow) < 0.9


def _visible_share(s: np.ndarray) -> np.ndarray:
    """The share of a unit disc on the side x > s of the line x = s."""
    t = np.clip(s, -1.0, 1.0)
    return (np.arccos(t) - t * np.sqrt(1.0 - t * t)) / math.pi


def test_disc_lamp_penumbra_matches_the_analytic_share():
    """A disc lamp of radius R at height H right above a square's centre (its disc then
    horizontal): a receiver at (X, 0, 0) beyond the square's edge x = a sees the lamp's
    points with x > s, s = H a / h - X (H / h - 1): visible share = the disc's part beyond
    the line x = s. The surfels' coverage reaches a little past the square's edge (about
    one std-dev, ~0.008 here), so the edge a is fitted; the penumbra's shape is tested."""
    h, a, big_h, rad = 1.0, 0.5, 3.5, 0.3
    surfels = _square_surfels(h, a, 8000)
    bounds = SceneBounds((0.0, h, 0.0), a * math.sqrt(2.0), 3.0)
    lamp = np.array([[0.0, big_h, 0.0]])
    x = np.linspace(0.45, 0.95, 201)
    pts = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1)
    nrm = np.tile([0.0, 1.0, 0.0], (len(x), 1))
    edges = np.linspace(a - 0.02, a + 0.03, 51)
    want = [_visible_share((big_h * e / h - x * (big_h / h - 1.0)) / rad) for e in edges]
    penumbra = [(w > 0.02) & (w < 0.98) for w in want]
    err = {}
    for n in (0, 64):
        cfg = VisibilityConfig(resolution=256, bias_texels=1.0, lamp_samples=n)
        maps = render_shadow_maps(surfels, np.array([[0.0, 1.0, 0.0]]), bounds, cfg,
                                  positions=lamp, radii=np.array([rad]))
        v = _evaluate(maps, pts, nrm)[:, 0]
        err[n] = min((np.abs(v - w)[p].mean(), e, np.abs(v - w).max())
                     for w, p, e in zip(want, penumbra, edges, strict=True))
    mae, edge, worst = err[64]
    assert mae < 0.02 and worst < 0.06, err[64]
    assert abs(edge - a) < 0.015, edge
    assert err[0][0] > 5 * mae  # a hard shadow from the centre has no penumbra


# -- mixed sets, the cache and the relighting's entry points -------------------------------
def _mixed_case():
    surfels = _square_surfels()
    bounds = SceneBounds((0.0, 1.0, 0.0), 0.75, 3.0)
    lamps = np.array([NAN3, [0.4, 3.0, 0.3], NAN3, [-1.5, 2.5, 0.5]])
    dirs = np.array([[0.3, 0.9, 0.1], [0.0, 0.0, 0.0], [-0.5, 0.8, 0.2], [0.0, 0.0, 0.0]])
    for k in (1, 3):
        dirs[k] = lamps[k] - bounds.center
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rng = np.random.default_rng(1)
    pts = rng.uniform([-1.5, 0, -1.5], [1.5, 0, 1.5], (2000, 3))
    nrm = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
    return surfels, bounds, dirs, lamps, np.array([0.0, 0.0, 0.0, 0.2]), pts, nrm


@pytest.mark.parametrize("projection", ["orthographic", "perspective"])
def test_mixed_set_equals_its_directional_and_local_parts(projection):
    surfels, bounds, dirs, lamps, radii, pts, nrm = _mixed_case()
    cfg = VisibilityConfig(resolution=64, projection=projection, bias_texels=1.0,
                           lamp_samples=3)
    mixed = render_shadow_maps(surfels, dirs, bounds, cfg, positions=lamps, radii=radii)
    assert mixed.count == 4 and len(mixed.cameras) == 1 + 1 + 1 + 3
    v = _evaluate(mixed, pts, nrm)
    directional = render_shadow_maps(surfels, dirs[[0, 2]], bounds, cfg)
    assert directional.positions is None  # the directional path, unchanged
    np.testing.assert_array_equal(v[:, [0, 2]], _evaluate(directional, pts, nrm))
    local = render_shadow_maps(surfels, dirs[[1, 3]], bounds, cfg, positions=lamps[[1, 3]],
                               radii=radii[[1, 3]])
    np.testing.assert_array_equal(v[:, [1, 3]], _evaluate(local, pts, nrm))
    assert 0.0 < v[:, 3].mean() < 1.0 and np.any((v[:, 3] > 0) & (v[:, 3] < 1))  # soft
    sub = mixed.subset(np.array([False, True, True, True]))
    np.testing.assert_array_equal(_evaluate(sub, pts, nrm), v[:, 1:])
    sub = mixed.subset(np.array([True, False, True, False]))
    assert sub.positions is None
    np.testing.assert_array_equal(_evaluate(sub, pts, nrm), v[:, [0, 2]])


def test_map_cache_keys_lamps_by_position_and_radius():
    surfels, bounds, dirs, lamps, radii, pts, nrm = _mixed_case()
    cfg = VisibilityConfig(resolution=48, bias_texels=1.0, lamp_samples=3)
    cache = MapCache(surfels, bounds)
    maps = cache.maps(dirs, cfg, positions=lamps, radii=radii)
    assert cache.rendered == 6
    fresh = render_shadow_maps(surfels, dirs, bounds, cfg, positions=lamps, radii=radii)
    np.testing.assert_array_equal(np.asarray(maps.depth), np.asarray(fresh.depth))
    np.testing.assert_array_equal(_evaluate(maps, pts, nrm), _evaluate(fresh, pts, nrm))
    # again, reordered: nothing rendered
    order = [3, 0, 1]
    again = cache.maps(dirs[order], cfg, positions=lamps[order], radii=radii[order])
    assert cache.rendered == 6
    np.testing.assert_array_equal(_evaluate(again, pts, nrm),
                                  _evaluate(fresh, pts, nrm)[:, order])
    # another radius or position is another light; a lamp's direction alone is not a lamp
    cache.maps(dirs[[3]], cfg, positions=lamps[[3]], radii=np.array([0.1]))
    assert cache.rendered == 9
    cache.maps(dirs[[1]], cfg, positions=lamps[[1]] + 0.01)
    assert cache.rendered == 10
    cache.maps(dirs[[1]], cfg)
    assert cache.rendered == 11
    cache.maps(dirs[[0, 2]], cfg)  # directional lights held from the mixed set
    assert cache.rendered == 11


def test_relighting_renders_a_light_sets_lamps():
    surfels, bounds, dirs, lamps, radii, pts, nrm = _mixed_case()
    cfg = VisibilityConfig(resolution=48, bias_texels=1.0, lamp_samples=2)
    lights = shading.local_lights(lamps[[1, 3]], mi.Color3f(1.0), bounds.center, radii[[1, 3]])
    assert set(lamp_arguments(lights)) == {"positions", "radii"}
    assert lamp_arguments(shading.directional_lights(dirs[[0]], mi.Color3f(1.0))) == {}
    model = RelightModel(surfels, specular=False, use_visibility=True)
    direct = shadow_maps_for(model, lights, bounds, cfg)
    cache = RelightCache()
    cached = cache.shadow_maps(model, lights, bounds, cfg)
    want = _evaluate(render_shadow_maps(surfels, dirs[[1, 3]], bounds, cfg,
                                        positions=lamps[[1, 3]], radii=radii[[1, 3]]), pts, nrm)
    np.testing.assert_array_equal(_evaluate(direct, pts, nrm), want)
    np.testing.assert_array_equal(_evaluate(cached, pts, nrm), want)
    assert cache.rendered == 1 + 2
    moved = shading.local_lights(lamps[[1, 3]] + [0.0, 0.1, 0.0], mi.Color3f(1.0),
                                 bounds.center, radii[[1, 3]])
    cache.shadow_maps(model, moved, bounds, cfg)
    assert cache.rendered == 6  # the set's key holds the positions


# -- bad inputs --------------------------------------------------------------------------
def test_bad_lamps_are_refused_naming_the_lamp():
    surfels = _square_surfels(count=500)
    bounds = SceneBounds((0.0, 1.0, 0.0), 0.75, 3.0)
    cfg = VisibilityConfig(resolution=16)
    up = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    far = [0.0, 4.0, 0.0]
    with pytest.raises(ValueError, match=r"lamp 1 .*inside or too near"):
        render_shadow_maps(surfels, up, bounds, cfg, positions=np.array([far, [0, 1.3, 0]]))
    near = 0.75 * cfg.margin / math.sin(math.radians(MAX_LAMP_FOV_DEG / 2)) * 0.99
    with pytest.raises(ValueError, match=r"lamp 0 "):
        render_shadow_maps(surfels, up[:1], bounds, cfg, positions=np.array([[0, 1 + near, 0]]))
    with pytest.raises(ValueError, match=r"lamp 0 radius must be >= 0"):
        render_shadow_maps(surfels, up, bounds, cfg, positions=np.array([far, NAN3]),
                           radii=np.array([-0.1, 0.0]))
    with pytest.raises(ValueError, match=r"lamp 1 position"):
        render_shadow_maps(surfels, up, bounds, cfg,
                           positions=np.array([far, [0.0, math.nan, 1.0]]))
    with pytest.raises(ValueError, match=r"positions must be \[2, 3\]"):
        render_shadow_maps(surfels, up, bounds, cfg, positions=np.array([far]))
    with pytest.raises(ValueError, match="radii given without lamp positions"):
        MapCache(surfels, bounds).maps(up, cfg, radii=np.array([0.1, 0.0]))
    with pytest.raises(ValueError, match="invalid visibility settings"):
        VisibilityConfig(lamp_samples=-1)


# -- against Mitsuba ray tracing ----------------------------------------------------------
def _traced_to_lamp(scene, camera: Camera, lamp: np.ndarray):
    """Exact receivers of a view (z-depth, camera-facing normals, mask) and the hard
    visibility of the lamp point: a shadow ray to it, and n . l > 0."""
    si, valid, n, depth = primary_hits(scene, camera)
    target = mi.Point3f(*(float(c) for c in lamp))
    lit = (valid & ~scene.ray_test(si.spawn_ray_to(target), valid)
           & (dr.dot(n, dr.normalize(target - si.p)) > 1e-4))
    h, w = camera.height, camera.width
    return (np.asarray(depth).reshape(h, w, 1), np.asarray(n).T.reshape(h, w, 3),
            np.asarray(valid).reshape(h, w), np.asarray(lit).reshape(h, w))


@pytest.mark.parametrize("lamp", [[-1.2, 1.8, 0.4], [0.5, 1.5, -1.4]])
def test_sphere_over_plane_matches_ray_traced_lamp(lamp):
    ground = _square(0.0, 2.0)
    scene = mi.load_dict({"type": "scene", "ground": ground,
                          "ball": {"type": "sphere", "center": [0, 0.6, 0], "radius": 0.3}},
                         optimize=False)
    ball = [s for s in scene.shapes() if s.id() == "ball"]
    surfels = surfels_on_surface(ball, 12000, seed=1, sigma_factor=0.7)
    camera = Camera.look_at([1.6, 2.4, 1.9], [0, 0.2, 0], width=64, height=64, fov_x=0.9)
    bounds = SceneBounds.from_points(surfels.to_numpy()["position"], [camera])
    lamp = np.asarray(lamp, np.float64)
    d = (lamp - bounds.center) / np.linalg.norm(lamp - bounds.center)
    cfg = VisibilityConfig(resolution=256, bias_texels=1.0, lamp_samples=0)
    maps = render_shadow_maps(surfels, d[None], bounds, cfg, positions=lamp[None])
    depth, normal, mask, lit = _traced_to_lamp(scene, camera, lamp)
    v = np.asarray(view_visibility(mi.TensorXf(depth), camera, maps, mi.TensorXf(normal),
                                   rendered=False))[..., 0]
    ours, truth = (v < 0.5) & mask, ~lit & mask
    assert truth.sum() > 100
    iou = np.count_nonzero(ours & truth) / np.count_nonzero(ours | truth)
    assert iou >= 0.95, iou


# -- the validation command ---------------------------------------------------------------
def test_lamp_validation_smoke(tmp_path, monkeypatch, capsys):
    """``validation.visibility --lamp`` on a tiny case: its rows, its RESULTS section, and
    an unknown preset refused with exit 2 before any work."""
    from scripts import results
    from validation import lamp_visibility

    tiny = lamp_visibility.LampValidationConfig(
        n_views=1, resolution=32, object_surfels=1500, base_surfels=300, distances=(6.0,),
        radii=(0.15,), directions=((35.0, 50.0),), samples=(16,), truth_samples=8)
    monkeypatch.setattr(lamp_visibility, "QUICK", tiny)
    from validation import visibility

    argv = ["--lamp", "--out", str(tmp_path / "out"), "--quick", "--quiet",
            "--preset", "cpu-small", "--results", str(tmp_path / "res"),
            "--bunny", str(tmp_path / "no-bunny.ply")]
    assert visibility.main(argv) == 0
    assert "Visibility from a lamp" in capsys.readouterr().out
    summary = (tmp_path / "out" / "summary.json").read_text()
    assert '"hard_iou"' in summary and "bunny skipped" in summary
    doc = results.load(tmp_path / "res")[0]
    assert doc["title"].startswith("Shadow maps from a lamp")
    assert doc["command"].startswith("python -m validation.visibility --lamp --out OUT")
    assert len(doc["tables"][0]["rows"]) == 1 and len(doc["tables"][1]["rows"]) == 2
    assert "| cpu-small | 0.15 | default | 6 | 1 | " in results.render(tmp_path / "res")
    with pytest.raises(SystemExit) as e:
        visibility.main(["--lamp", "--out", str(tmp_path / "o2"), "--preset", "nope"])
    assert e.value.code == 2
    assert not (tmp_path / "o2").exists()
