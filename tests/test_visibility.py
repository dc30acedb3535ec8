"""Shadow-map visibility (paper Eq. 6-7): a float64 NumPy reference of the lookup, and
checks against Mitsuba ray tracing on hard cases."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import direction_from_angles
from mi_shadowgs.core.sampling import surfels_on_surface
from mi_shadowgs.stages.visibility.shadow_maps import (
    SceneBounds,
    VisibilityConfig,
    render_shadow_maps,
    view_visibility,
)

RES = 48  # view resolution for the ray-traced comparisons
HORIZON_COS = 1e-4  # n . l below this is "at or below the horizon" (float32 normals)


def _rect(center, half, rot=None, name="rect"):
    """A Mitsuba rectangle dict: centre [3], half sizes (x, y), optional rotation (axis, deg)."""
    t = mi.ScalarTransform4f().translate(center)
    if rot is not None:
        t = t @ mi.ScalarTransform4f().rotate(rot[0], rot[1])
    t = t @ mi.ScalarTransform4f().scale([half[0], half[1], 1.0])
    return {"type": "rectangle", "to_world": t,
            "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}}


def _ground(half=2.0):
    return _rect([0, 0, 0], (half, half), rot=([1, 0, 0], -90.0))


def primary_hits(scene, camera: Camera):
    """Mitsuba's primary hit of each pixel centre's ray: (interaction, valid, normal facing
    the camera, z-depth (0 where it misses))."""
    pix = camera.pixel_grid()
    far = camera.unproject(pix, np.ones(len(pix)))
    o = np.broadcast_to(camera.origin, far.shape)
    d = far - o
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    ray = mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
    forward = mi.Vector3f(*(float(c) for c in camera.forward))
    depth = dr.select(valid, si.t * dr.dot(ray.d, forward), 0.0)
    return si, valid, n, depth


def _ray_traced(scene, camera: Camera, directions):
    """Independent ground truth: primary hits and shadow rays, straight from Mitsuba.

    A point whose camera-facing normal turns away from the light gets no direct light (an
    attached shadow) even where its shadow ray escapes, e.g. the lit-from-behind face of a
    zero-thickness wall: that counts as shadow, as it does for the shadow-map method.
    Returns (depth [H, W, 1], normal [H, W, 3] facing the camera, mask [H, W], V [H, W, L]).
    """
    si, valid, n, depth = primary_hits(scene, camera)
    vis = []
    for l_dir in directions:
        lv = mi.Vector3f(*(float(c) for c in l_dir))
        occluded = scene.ray_test(si.spawn_ray(lv), valid)
        lit = valid & ~occluded & (dr.dot(n, lv) > HORIZON_COS)
        vis.append(np.asarray(dr.select(lit, 1.0, 0.0)))
    h, w = camera.height, camera.width
    return (np.asarray(depth).reshape(h, w, 1), np.asarray(n).T.reshape(h, w, 3),
            np.asarray(valid).reshape(h, w), np.stack(vis, -1).reshape(h, w, -1))


def _compare(scene_dict, occluder_keys, directions, camera, config=None,
             count=12000, use_normals=True):
    """Shadow IoU per direction of shadow-map visibility (from surfels sampled on the
    occluders) against ray tracing, at the ray-traced surface points."""
    config = config or VisibilityConfig()
    scene = mi.load_dict(scene_dict, optimize=False)
    by_id = {s.id(): s for s in scene.shapes()}
    occluders = [by_id[k] for k in occluder_keys]
    surfels = surfels_on_surface(occluders, count, seed=1, sigma_factor=0.7)
    pts = surfels.to_numpy()["position"]
    bounds = SceneBounds.from_points(pts, [camera])
    maps = render_shadow_maps(surfels, np.asarray(directions), bounds, config)
    depth, normal, mask, v_gt = _ray_traced(scene, camera, directions)
    v = np.asarray(view_visibility(mi.TensorXf(depth), camera, maps,
                                   mi.TensorXf(normal) if use_normals else None,
                                   rendered=False))
    ious = []
    for k in range(len(directions)):
        a = (v[..., k] < 0.5) & mask
        b = (v_gt[..., k] < 0.5) & mask
        union = (a | b).sum()
        ious.append(1.0 if union == 0 else (a & b).sum() / union)
    return np.array(ious), v, v_gt, mask


def _view(origin, target=(0, 0.3, 0), fov=0.8, res=RES):
    return Camera.look_at(origin, target, width=res, height=res, fov_x=fov)


# -- the lookup against a float64 reference -----------------------------------------------
def _reference_lookup(maps, points, normals, cfg):
    """Eq. 6-7 in float64 NumPy, nearest texel, from the maps' cameras and depth arrays."""
    r = maps.resolution
    out = np.ones((len(points), maps.count))
    for k, cam in enumerate(maps.cameras):
        uv, z = cam.project(points)
        ix, iy = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (ix >= 0) & (ix < r) & (iy >= 0) & (iy < r)
        dg = np.full(len(points), np.inf)
        dg[inside] = maps.depth_image(k)[iy[inside], ix[inside]]
        if cfg.bias_texels is None:
            v = ((z - dg) / (z + cfg.eps) <= cfg.tau).astype(float)
        else:  # the absolute threshold, in texels at the scene centre
            v = (z - dg <= cfg.bias_texels * maps.texel).astype(float)
        if normals is not None:
            v[normals @ maps.directions[k] <= 0] = 0.0
        out[:, k] = v
    return out


@pytest.mark.parametrize("projection,bias_texels", [("perspective", None),
                                                    ("orthographic", None),
                                                    ("perspective", 2.0)])
def test_lookup_matches_float64_reference(projection, bias_texels):
    rng = np.random.default_rng(3)
    scene = mi.load_dict({"type": "scene", "ground": _ground(),
                          "ball": {"type": "sphere", "center": [0, 0.6, 0], "radius": 0.3}})
    ball = [s for s in scene.shapes() if s.id() == "ball"]
    surfels = surfels_on_surface(ball, 3000, seed=0)
    cfg = VisibilityConfig(resolution=96, projection=projection, bias_texels=bias_texels)
    dirs = np.stack([direction_from_angles(a, e) for a, e in ((0, 60), (130, 35), (250, 15))])
    bounds = SceneBounds((0.0, 0.6, 0.0), 0.35, 3.0)
    maps = render_shadow_maps(surfels, dirs, bounds, cfg)
    pts = np.concatenate([rng.uniform([-1, 0, -1], [1, 0, 1], (3000, 3)),
                          rng.uniform(-0.4, 0.4, (1000, 3)) + [0, 0.6, 0]])
    nrm = rng.normal(size=pts.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    got = np.asarray(maps.evaluate(mi.Point3f(*pts.T.astype(np.float32)),
                                   mi.Vector3f(*nrm.T.astype(np.float32)))).reshape(-1, 3)
    want = _reference_lookup(maps, pts.astype(np.float32).astype(np.float64),
                             nrm.astype(np.float32).astype(np.float64), cfg)
    # Float32 vs float64 projection can move a point across a texel edge or the threshold;
    # those are rare (a few per thousand) and are the only allowed disagreements.
    assert np.mean(got != want) < 5e-3
    assert 0.05 < np.mean(want == 0) < 0.95  # the case is not trivial


# -- against ray tracing ------------------------------------------------------------------
def test_sphere_over_plane_matches_ray_tracing():
    scene = {"type": "scene", "ground": _ground(),
             "ball": {"type": "sphere", "center": [0, 0.6, 0], "radius": 0.3}}
    dirs = [direction_from_angles(a, e) for a, e in ((20, 70), (200, 40), (100, 25))]
    ious, *_ = _compare(scene, ["ball"], dirs, _view([1.8, 2.2, 1.6]))
    # Surfels are a discrete, slightly blurred copy of the sphere (sigma 0.7 spacing) and a
    # 48 px view has few shadow pixels: one pixel of edge disagreement costs ~1-3% IoU.
    assert ious.min() >= 0.9, ious


def test_light_at_and_below_the_horizon():
    """V = 0 where the light is below a surface's horizon; no acne at grazing light."""
    scene = {"type": "scene", "ground": _ground(1.0)}
    cam = _view([1.5, 1.8, 1.2], target=(0, 0, 0))
    for elevation, expect in ((4.0, 1.0), (0.0, 0.0), (-5.0, 0.0)):
        d = [direction_from_angles(30.0, elevation)]
        _, v, v_gt, mask = _compare(scene, ["ground"], d, cam, count=8000)
        assert mask.sum() > 0.5 * mask.size
        # Exact: at grazing light (4 degrees) every base pixel is lit (no shadow acne);
        # at and below the horizon every base pixel is in shadow.
        assert np.all(v[mask, 0] == expect), (elevation, np.mean(v[mask, 0] == expect))
        assert np.all(v_gt[mask, 0] == expect)


def test_grazing_light_without_normals_has_no_acne():
    """Without normals only the depth test decides: the flat base must not shadow itself."""
    scene = {"type": "scene", "ground": _ground(1.0)}
    cam = _view([1.5, 1.8, 1.2], target=(0, 0, 0))
    for elevation in (20.0, 12.0):
        d = [direction_from_angles(30.0, elevation)]
        _, v, _, mask = _compare(scene, ["ground"], d, cam, count=8000, use_normals=False)
        # The paper's relative threshold (tau d ~ 0.06 here) covers the base's depth error
        # over a texel (up to ~1 px of low-pass footprint at the centre depth, times the
        # slope 1/tan(elevation)) down to ~12 degrees; below that the normal offset (with
        # normals, test above) is the remedy.
        assert np.mean(v[mask, 0] < 0.5) == 0.0, elevation


def test_thin_leaf_casts_a_shadow():
    leaf = _rect([0.0, 0.5, 0.0], (0.35, 0.12), rot=([1, 0, 0], -70.0))
    scene = {"type": "scene", "ground": _ground(), "leaf": leaf}
    dirs = [direction_from_angles(a, e) for a, e in ((90, 60), (270, 45))]
    ious, _, v_gt, mask = _compare(scene, ["leaf"], dirs, _view([0.2, 2.4, 1.5], (0, 0.2, 0)),
                                   count=4000)
    assert (v_gt[mask] < 0.5).sum() > 40  # the leaf's shadow is really there
    # A 2 cm-thin structure: surfels at both faces of a zero-thickness rectangle; the
    # shadow outline is blurred by one surfel sigma (~0.01) = well under a pixel here.
    assert ious.min() >= 0.85, ious


def test_concave_self_shadowing():
    """An open box: its walls shadow its own floor."""
    walls = {
        "floor": _rect([0, 0.01, 0], (0.5, 0.5), rot=([1, 0, 0], -90.0)),
        "wall_n": _rect([0, 0.3, -0.5], (0.5, 0.3)),
        "wall_s": _rect([0, 0.3, 0.5], (0.5, 0.3)),
        "wall_e": _rect([0.5, 0.3, 0], (0.5, 0.3), rot=([0, 1, 0], 90.0)),
        "wall_w": _rect([-0.5, 0.3, 0], (0.5, 0.3), rot=([0, 1, 0], 90.0)),
    }
    scene = {"type": "scene", **walls}
    dirs = [direction_from_angles(a, e) for a, e in ((45, 50), (200, 35))]
    ious, _, v_gt, mask = _compare(scene, list(walls), dirs,
                                   _view([0.6, 2.0, 1.3], (0, 0.1, 0)), count=12000)
    assert (v_gt[mask] < 0.5).sum() > 100
    assert ious.min() >= 0.9, ious


@pytest.mark.parametrize("factor", [30.0, 300.0])
def test_far_perspective_camera_keeps_float32_depth_precision(factor):
    """30x (paper) and 300x camera distance: float32 depths stay precise enough, the
    result agrees with the orthographic (infinitely far) map.

    tau is relative, so it is scaled by 30 / factor to keep the same absolute depth margin
    (tau * d ~ 0.07): this isolates float32 precision from the threshold's own effect."""
    scene = {"type": "scene", "ground": _ground(),
             "ball": {"type": "sphere", "center": [0, 0.6, 0], "radius": 0.3}}
    dirs = [direction_from_angles(a, e) for a, e in ((20, 70), (200, 40))]
    cam = _view([1.8, 2.2, 1.6])
    persp, *_ = _compare(scene, ["ball"], dirs, cam,
                         VisibilityConfig(distance_factor=factor, tau=0.0008 * 30.0 / factor))
    ortho, *_ = _compare(scene, ["ball"], dirs, cam,
                         VisibilityConfig(projection="orthographic"))
    assert np.all(persp >= 0.9) and np.all(np.abs(persp - ortho) <= 0.03), (persp, ortho)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="projection"):
        VisibilityConfig(projection="fisheye")
    with pytest.raises(ValueError, match="need points"):
        SceneBounds.from_points(np.zeros((0, 3)), [])
    assert math.isfinite(VisibilityConfig().tau)


def test_receiver_offset_removes_acne_of_a_thick_fitted_surface():
    """A fitted surface is a few pixel-sized surfels thick. Here a floor of two faint surfel
    layers 1.5 view-pixel footprints apart, seen at 128^2: the view's median depth often
    lands on the lower layer, while a grazing light's map sees the upper one, so without
    the receiver offset a quarter of the unoccluded floor is in its own shadow (acne; tau
    and the normal offset absorb ~1.3 footprints here); with 0.5 footprints (the default)
    it is lit. The lift itself is exactly ``amount * footprint`` along n."""
    from mi_shadowgs.core.depth import pixel_footprint
    from mi_shadowgs.core.frames import frame_to_quaternion
    from mi_shadowgs.core.raster import rasterize
    from mi_shadowgs.core.surfels import Surfels
    from mi_shadowgs.stages.visibility.shadow_maps import lift_receivers

    cam = Camera.look_at(np.array([0.0, 2.0, 3.0]), np.zeros(3), width=128, height=128,
                         fov_x=0.7)
    footprint = float(np.linalg.norm(cam.origin)) / cam.focal  # at the floor's centre
    n = 90
    u = (np.arange(n) + 0.5) / n * 3.0 - 1.5
    uu, vv = np.meshgrid(u, u)
    rng = np.random.default_rng(0)
    layers = []
    for y in (0.0, -1.5 * footprint):
        jitter = rng.uniform(-0.3, 0.3, (2, n * n)) * (3.0 / n)  # no aligned rows
        layers.append(np.stack([uu.ravel() + jitter[0], np.full(n * n, y),
                                vv.ravel() + jitter[1]], -1))
    pos = np.concatenate(layers)
    sigma = 0.7 * 3.0 / n
    up = np.tile([0.0, 1.0, 0.0], (len(pos), 1))
    floor = Surfels.from_numpy(pos, np.full((len(pos), 2), sigma), frame_to_quaternion(up),
                               np.full(len(pos), 0.25))
    out = rasterize(floor, cam, None, aovs=("alpha", "median_depth", "normal"))
    mask = out["alpha"].numpy().reshape(128, 128) > 0.5
    dirs = np.stack([direction_from_angles(a, 12.0) for a in (30.0, 150.0, 270.0)])
    bounds = SceneBounds((0.0, 0.0, 0.0), 1.5, float(np.linalg.norm(cam.origin)))
    lit = {}
    for amount in (0.0, 0.5):
        cfg = VisibilityConfig(projection="orthographic", receiver_offset=amount)
        maps = render_shadow_maps(floor, dirs, bounds, cfg)
        v = view_visibility(out["median_depth"], cam, maps, out["normal"]).numpy()
        lit[amount] = float(np.mean(v[mask] >= 0.5))
    # Nothing occludes the floor: every receiver should be lit.
    # Measured: 0.754 without, 0.9998 with.
    assert lit[0.5] > 0.99 and lit[0.0] < 0.9, lit
    # The lift: amount * footprint along the normal, and none without footprints.
    p = mi.Point3f(0.0, 0.0, 0.0)
    nrm = mi.Vector3f(0.0, 1.0, 0.0)
    assert np.allclose(np.asarray(lift_receivers(p, nrm, mi.Float(0.02), 0.5)).ravel(),
                       [0.0, 0.01, 0.0])
    assert lift_receivers(p, nrm, None, 0.5) is p
    fp = pixel_footprint(mi.TensorXf(np.full((2, 2, 1), 4.0, np.float32)), cam).numpy()
    assert np.allclose(fp, 4.0 / cam.focal)


def test_fractional_maps_let_a_semi_transparent_layer_through():
    """A layer of half-transparent surfels over the floor (``fractional``): the visibility
    under it is its transmittance along the light, checked against a float64 NumPy product
    of (1 - alpha_i) over the surfels the light ray crosses; the binary maps make it 0."""
    from mi_shadowgs.core.frames import frame_to_quaternion
    from mi_shadowgs.core.surfels import Surfels

    n, half, height, opacity = 12, 0.4, 0.5, 0.2
    u = ((np.arange(n) + 0.5) / n * 2 - 1) * half
    uu, vv = np.meshgrid(u, u)
    pos = np.stack([uu.ravel(), np.full(n * n, height), vv.ravel()], -1)
    sigma = 1.2 * 2 * half / n  # overlapping: the transmittance varies smoothly
    surfels = Surfels.from_numpy(pos, np.full((n * n, 2), sigma),
                                 frame_to_quaternion(np.tile([0.0, 1.0, 0.0], (n * n, 1))),
                                 np.full(n * n, opacity))
    light = direction_from_angles(30.0, 60.0)
    bounds = SceneBounds((0.0, 0.3, 0.0), 1.0, 3.0)
    rng = np.random.default_rng(0)
    # Floor points whose light ray crosses the layer's interior (1 sigma inside its edge).
    hit = rng.uniform(-half + sigma, half - sigma, (400, 2))
    t = height / light[1]
    pts = np.stack([hit[:, 0] - t * light[0], np.zeros(400), hit[:, 1] - t * light[2]], -1)
    # Reference: the ray crosses the plane y = height at `hit`.
    d2 = ((hit[:, None, 0] - pos[None, :, 0]) ** 2 + (hit[:, None, 1] - pos[None, :, 2]) ** 2)
    alpha = np.minimum(0.99, opacity * np.exp(-0.5 * d2 / sigma ** 2))
    want = np.prod(1.0 - alpha, axis=1)
    assert 0.05 < want.min() and want.max() < 0.9  # semi-transparent throughout
    p = mi.Point3f(*pts.T.astype(np.float32))
    nrm = mi.Vector3f(0.0, 1.0, 0.0)
    frac = render_shadow_maps(surfels, light[None], bounds,
                              VisibilityConfig(resolution=256, projection="orthographic",
                                               fractional=True))
    got = np.asarray(frac.evaluate(p, dr.repeat(nrm, 1) + dr.zeros(mi.Vector3f, 400)))
    # The map holds the transmittance at texel centres (0.0047 scene units apart here,
    # sigma 0.08: the Gaussians change < 2% across a texel) and the rasterizer drops
    # splat weights below 1/255: measured max error 0.0095 (transmittance 0.15-0.23).
    assert np.max(np.abs(got - want)) < 0.03, np.max(np.abs(got - want))
    binary = render_shadow_maps(surfels, light[None], bounds,
                                VisibilityConfig(resolution=256, projection="orthographic"))
    got_b = np.asarray(binary.evaluate(p, dr.zeros(mi.Vector3f, 400) + nrm))
    assert set(np.unique(got_b)) <= {0.0, 1.0}
    assert np.mean(np.abs(got_b - want)) > 3 * np.mean(np.abs(got - want))


def test_texel_bias_keeps_contact_shadows():
    """A slab 4 cm over the ground, lit from 60 deg: the occluder is 4.6 cm in front of the
    ground under it along the light. The paper's relative tau (8e-4 of the light camera's
    depth, ~0.07 units at 30x the camera distance) lets it through and the contact shadow
    vanishes; an absolute threshold of 2 texels (~0.02 units) keeps it, and leaves the lit
    ground and the slab's top without acne. Analytic truth: a ground point is shadowed iff
    its ray toward the light crosses the slab."""
    from mi_shadowgs.stages.visibility.shadow_maps import point_visibility

    gap, half = 0.04, 0.5
    scene = mi.load_dict({"type": "scene", "ground": _ground(),
                          "slab": _rect([0, gap, 0], (half, half), rot=([1, 0, 0], -90.0))},
                         optimize=False)
    surfels = surfels_on_surface(list(scene.shapes()), 30000, seed=2, sigma_factor=0.7)
    l_dir = np.asarray(direction_from_angles(30.0, 60.0), np.float64)
    camera = _view([0.0, 2.0, 2.0], (0, 0, 0))
    bounds = SceneBounds.from_points(surfels.to_numpy()["position"], [camera])
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-1.2, 1.2, 4000), np.zeros(4000), rng.uniform(-1.2, 1.2, 4000)]
    hit = ground + (gap / l_dir[1]) * l_dir  # where each ground point's light ray meets y = gap
    shadowed = (np.abs(hit[:, 0]) < half - 0.03) & (np.abs(hit[:, 2]) < half - 0.03)
    lit = (np.abs(hit[:, 0]) > half + 0.03) | (np.abs(hit[:, 2]) > half + 0.03)
    top = np.c_[rng.uniform(-0.45, 0.45, 1000), np.full(1000, gap), rng.uniform(-0.45, 0.45, 1000)]
    pts = np.concatenate([ground, top]).astype(np.float32)
    up = np.tile(np.float32([0.0, 1.0, 0.0]), (len(pts), 1))
    result = {}
    for name, cfg in (("tau", VisibilityConfig()), ("texels", VisibilityConfig(bias_texels=2.0))):
        maps = render_shadow_maps(surfels, l_dir[None], bounds, cfg)
        assert 2.0 * maps.texel < 0.75 * gap  # the threshold is well under the gap
        v = np.asarray(point_visibility(mi.Point3f(*pts.T), maps, mi.Vector3f(*up.T)))
        result[name] = (v[:4000][shadowed].mean(), v[:4000][lit].mean(), v[4000:].mean())
    assert shadowed.sum() > 500 and lit.sum() > 1500
    assert result["tau"][0] > 0.9, result  # the failure the option fixes (the test can fail)
    v_shadowed, v_lit, v_top = result["texels"]
    assert v_shadowed < 0.02 and v_lit > 0.98 and v_top > 0.98, result


# -- the occluder layer's slack (VisibilityConfig.layer_bias) -----------------------------
def _layered_ground_scene(thickness: float, opacity: float, gap: float = 0.04,
                          half: float = 0.5):
    """A ground fitted as a layer ``thickness`` deep (surfels of ``opacity`` spread
    uniformly in y below 0, as a stage-1 fit is a few surfels thick) under a one-layer
    slab ``gap`` over it."""
    from mi_shadowgs.core.surfels import Surfels

    scene = mi.load_dict({"type": "scene", "ground": _ground(),
                          "slab": _rect([0, gap, 0], (half, half), rot=([1, 0, 0], -90.0))},
                         optimize=False)
    shapes = list(scene.shapes())
    ground = surfels_on_surface([s for s in shapes if s.id() == "ground"], 60000, seed=2,
                                sigma_factor=0.7, opacity=opacity).to_numpy()
    slab = surfels_on_surface([s for s in shapes if s.id() != "ground"], 6000, seed=3,
                              sigma_factor=0.7).to_numpy()
    rng = np.random.default_rng(5)
    ground["position"][:, 1] -= rng.uniform(0.0, thickness, len(ground["position"]))
    keys = ("position", "scale", "rotation", "opacity")
    surfels = Surfels.from_numpy(**{k: np.concatenate([ground[k], slab[k]]) for k in keys},
                                 channels={"albedo": np.concatenate([ground["albedo"],
                                                                     slab["albedo"]])})
    return surfels, slab["position"]


def _ground_hit_slab(points: np.ndarray, l_dir: np.ndarray, gap: float, half: float
                     ) -> np.ndarray:
    """How far inside (< 0) or outside (> 0) the slab's square the light ray from each
    ground point's true position (y = 0) crosses the slab's height."""
    hit = points * [1, 0, 1] + (gap / l_dir[1]) * l_dir
    return np.maximum(np.abs(hit[:, 0]), np.abs(hit[:, 2])) - half


@pytest.mark.parametrize("window", [0, 1])
def test_layer_slack_matches_float64_reference(window):
    """The folded map depth is median d + min(max(k |E[d] - median d|, the step to the
    deepest occupied texel within ``window``), cap texel), from the light's own median and
    expected depth (rasterized again here and combined in float64), and the lookup compares
    against it."""
    from mi_shadowgs.core.raster import rasterize

    surfels, slab_points = _layered_ground_scene(0.01, 0.5)
    l_dir = np.asarray(direction_from_angles(30.0, 60.0), np.float64)
    camera = _view([0.0, 2.0, 2.0], (0, 0, 0))
    bounds = SceneBounds.from_points(slab_points, [camera])
    cfg = VisibilityConfig(resolution=128, projection="orthographic", bias_texels=1.0,
                           layer_bias=1.0, layer_cap_texels=3.0, layer_window=window)
    maps = render_shadow_maps(surfels, l_dir[None], bounds, cfg)
    out = rasterize(surfels, maps.cameras[0], None, aovs=("alpha", "depth", "median_depth"))
    alpha = np.asarray(out["alpha"].array, np.float64)
    med = np.asarray(out["median_depth"].array, np.float64)
    expected = np.asarray(out["depth"].array, np.float64)
    empty = (alpha < cfg.empty_alpha) | (med <= 0)
    slack = np.abs(expected - med)
    if window:
        padded = np.pad(np.where(empty, -np.inf, med).reshape(128, 128), window,
                        mode="edge")
        deepest = np.max([padded[window + dy:window + dy + 128, window + dx:window + dx + 128]
                          for dy in range(-window, window + 1)
                          for dx in range(-window, window + 1)], axis=0).reshape(-1)
        slack = np.maximum(slack, deepest - med)
    want = med + np.minimum(slack, 3.0 * maps.texel)
    want[empty] = np.inf
    got = maps.depth_image(0).reshape(-1)
    finite = np.isfinite(want)
    assert np.array_equal(finite, np.isfinite(got))
    # float32 sums of the same terms: the error is a few ulps of the depth (~5 units here)
    np.testing.assert_allclose(got[finite], want[finite], rtol=0, atol=2e-6 * want.max())
    slack = want[finite] - med[finite]
    assert (slack > 0.1 * maps.texel).mean() > 0.2  # the slack is not trivially 0 ...
    assert slack.max() <= 3.0 * maps.texel * (1 + 1e-6)  # ... and the cap holds
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-1, 1, 3000), rng.uniform(-0.02, 0.06, 3000),
                rng.uniform(-1, 1, 3000)].astype(np.float32)
    v = np.asarray(maps.evaluate(mi.Point3f(*pts.T))).reshape(-1)
    uv, z = maps.cameras[0].project(pts.astype(np.float64))
    ix, iy = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    inside = (ix >= 0) & (ix < 128) & (iy >= 0) & (iy < 128)
    dg = np.full(len(pts), np.inf)
    dg[inside] = want.reshape(128, 128)[iy[inside], ix[inside]]
    ref = (z - dg <= cfg.bias_texels * maps.texel).astype(float)
    assert np.mean(v != ref) < 5e-3  # texel-edge and threshold ties in float32 only
    assert 0.05 < ref.mean() < 0.95


def test_layer_slack_removes_acne_and_keeps_contact_shadows():
    """Hard case: receivers are the view's median depth of a ground fitted ~3.6 texels
    thick, with a one-layer slab 4 cm over it. A fixed 1-texel threshold shadows part of the
    lit ground (the receivers sit deeper in the layer than the light's median); tau hides
    the slab's contact shadow. The layer slack grows only where the map's layer is thick:
    the acne falls to under half and the contact shadow stays."""
    from mi_shadowgs.core.depth import unproject_depth
    from mi_shadowgs.core.raster import rasterize
    from mi_shadowgs.stages.visibility.shadow_maps import point_visibility

    gap, half = 0.04, 0.5
    surfels, slab_points = _layered_ground_scene(0.01, 0.5, gap, half)
    l_dir = np.asarray(direction_from_angles(30.0, 60.0), np.float64)
    camera = _view([0.0, 2.0, 2.0], (0, 0, 0), fov=1.2, res=128)
    bounds = SceneBounds.from_points(slab_points, [camera])
    out = rasterize(surfels, camera, None, aovs=("alpha", "median_depth"))
    p = unproject_depth(out["median_depth"], camera)
    pts = np.stack([np.asarray(p[k]) for k in range(3)], -1)
    alpha = np.asarray(out["alpha"].array)
    pts = pts[(alpha > 0.5) & (pts[:, 1] < gap / 2) & (np.abs(pts[:, 0]) < 1.2)
              & (np.abs(pts[:, 2]) < 1.2)]
    lit = _ground_hit_slab(pts, l_dir, gap, half) > 0.03  # clear of the slab's shadow
    # Under the slab (hidden from the view): ground points anywhere in the layer's depth.
    rng = np.random.default_rng(0)
    under = np.c_[rng.uniform(-1.2, 1.2, 20000), -rng.uniform(0.0, 0.01, 20000),
                  rng.uniform(-1.2, 1.2, 20000)]
    under = under[_ground_hit_slab(under, l_dir, gap, half) < -0.03]
    assert len(under) > 1000 and lit.sum() > 3000
    pts = np.concatenate([pts[lit], under]).astype(np.float32)
    up = np.tile(np.float32([0.0, 1.0, 0.0]), (len(pts), 1))
    n_lit = int(lit.sum())
    result = {}
    for name, cfg in (("tau", VisibilityConfig()),
                      ("texel", VisibilityConfig(bias_texels=1.0)),
                      ("layer", VisibilityConfig(bias_texels=1.0, layer_bias=1.0))):
        maps = render_shadow_maps(surfels, l_dir[None], bounds, cfg)
        v = np.asarray(point_visibility(mi.Point3f(*pts.T), maps, mi.Vector3f(*up.T)))
        result[name] = (v[n_lit:].mean(), 1.0 - v[:n_lit].mean())  # (leak, acne)
    assert 0.01 / maps.texel > 3  # the layer is several texels thick
    assert result["tau"][0] > 0.9, result  # tau: no contact shadow
    assert result["texel"][1] > 0.01, result  # the acne the slack is for (can fail)
    assert result["layer"][0] < 0.02, result  # the contact shadow kept
    assert result["layer"][1] < 0.5 * result["texel"][1], result


def test_layer_window_removes_grazing_acne():
    """Hard case: a plane lit at 20 deg elevation, receivers up to 2 texels under it (a view's
    depth is known to about a pixel) with normals bent up to 20 deg (fitted normals). At
    grazing light the map depth changes by ~2.7 texels per texel, so a receiver looked up one
    texel off lands behind its own surface; the normal offset computed from a bent normal
    does not cover it, and a single-layer plane has no layer slack. The window's deepest
    neighbour does."""
    from mi_shadowgs.stages.visibility.shadow_maps import point_visibility

    scene = mi.load_dict({"type": "scene", "ground": _ground(1.0)}, optimize=False)
    surfels = surfels_on_surface(list(scene.shapes()), 40000, seed=2, sigma_factor=0.7)
    l_dir = np.asarray(direction_from_angles(30.0, 20.0), np.float64)
    bounds = SceneBounds.from_points(surfels.to_numpy()["position"],
                                     [_view([0.0, 2.0, 2.0], (0, 0, 0))])
    acne = {}
    for name, cfg in (("texel", VisibilityConfig(bias_texels=1.0)),
                      ("layer", VisibilityConfig(bias_texels=1.0, layer_bias=1.0)),
                      ("window", VisibilityConfig(bias_texels=1.0, layer_bias=1.0,
                                                  layer_window=1))):
        maps = render_shadow_maps(surfels, l_dir[None], bounds, cfg)
        rng = np.random.default_rng(0)
        n = 20000
        pts = np.c_[rng.uniform(-0.8, 0.8, n), -rng.uniform(0.0, 2.0 * maps.texel, n),
                    rng.uniform(-0.8, 0.8, n)].astype(np.float32)
        tilt, phi = np.radians(rng.uniform(0.0, 20.0, n)), rng.uniform(0.0, 2 * np.pi, n)
        nrm = np.c_[np.sin(tilt) * np.cos(phi), np.cos(tilt),
                    np.sin(tilt) * np.sin(phi)].astype(np.float32)
        v = np.asarray(point_visibility(mi.Point3f(*pts.T), maps, mi.Vector3f(*nrm.T)))
        facing = nrm @ l_dir > 1e-4
        acne[name] = 1.0 - v[facing].mean()
    assert acne["texel"] > 0.05 and acne["layer"] > 0.05, acne  # the failure (can fail)
    assert acne["window"] < 0.005, acne


def test_map_cache_reuses_maps_that_equal_fresh_ones():
    """MapCache: a held map is bit-identical to a fresh render, only new directions are
    rendered, sets come back in the order asked (repeats too), fractional maps keep their
    alpha, and past its byte budget the oldest maps go while the current set stays whole."""
    from mi_shadowgs.core.frames import frame_to_quaternion
    from mi_shadowgs.core.surfels import Surfels
    from mi_shadowgs.stages.visibility.shadow_maps import MapCache

    rng = np.random.default_rng(4)
    n = 60
    surfels = Surfels.from_numpy(rng.uniform(-0.5, 0.5, (n, 3)) + [0.0, 0.5, 0.0],
                                 np.full((n, 2), 0.08),
                                 frame_to_quaternion(rng.normal(size=(n, 3))),
                                 rng.uniform(0.3, 0.99, n))
    bounds = SceneBounds((0.0, 0.5, 0.0), 1.0, 3.0)
    dirs = np.array([direction_from_angles(az, el) for az, el in
                     ((10, 40), (100, 60), (200, 30), (300, 75))])
    for cfg in (VisibilityConfig(resolution=64, projection="orthographic"),
                VisibilityConfig(resolution=64, fractional=True)):
        cache = MapCache(surfels, bounds)
        fresh = render_shadow_maps(surfels, dirs, bounds, cfg)
        got = cache.maps(dirs[[2, 0]], cfg)
        assert cache.rendered == 2
        got = cache.maps(dirs[[3, 0, 2, 1, 3]], cfg)  # two new ones, a repeat
        assert cache.rendered == 4
        r2 = 64 * 64
        depth = np.asarray(got.depth).reshape(5, r2)
        want = np.asarray(fresh.depth).reshape(4, r2)
        np.testing.assert_array_equal(depth, want[[3, 0, 2, 1, 3]])
        assert np.isfinite(depth).any() and np.isinf(depth).any()  # occluders and empty
        np.testing.assert_array_equal(got.directions, dirs[[3, 0, 2, 1, 3]])
        assert [c.origin.tolist() for c in got.cameras] == \
            [fresh.cameras[i].origin.tolist() for i in (3, 0, 2, 1, 3)]
        if cfg.fractional:
            np.testing.assert_array_equal(np.asarray(got.alpha).reshape(5, r2),
                                          np.asarray(fresh.alpha).reshape(4, r2)[[3, 0, 2, 1, 3]])
        else:
            assert got.alpha is None
        # Room for two maps: asking for three keeps those three, then drops the oldest.
        small = MapCache(surfels, bounds, max_bytes=2 * 4 * r2 * (2 if cfg.fractional else 1))
        trio = small.maps(dirs[:3], cfg)
        np.testing.assert_array_equal(np.asarray(trio.depth).reshape(3, r2), want[:3])
        assert len(small._maps) == 3  # the set asked for stays whole
        small.maps(dirs[3], cfg)
        assert len(small._maps) == 2 and small.rendered == 4
        again = small.maps(dirs[0], cfg)  # dropped: rendered again, the same map
        assert small.rendered == 5
        np.testing.assert_array_equal(np.asarray(again.depth), want[0])


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_a_maps_texel_does_not_depend_on_its_light(projection):
    """A map's texel (its bias, slack and normal offset scale with it) is the map's design,
    one value for every light direction: a set of maps gathered from renders of other
    batches (the relight cache) has the texel of a fresh render of the set, to the bit. The
    light cameras' origins differ in their last bits from direction to direction, so a
    texel read off the set's first camera did not. The design's texel is the cameras' own
    to rounding."""
    from mi_shadowgs.core.frames import frame_to_quaternion
    from mi_shadowgs.core.surfels import Surfels
    from mi_shadowgs.stages.visibility.shadow_maps import map_texel, shadow_camera

    surfels = Surfels.from_numpy(np.array([[0.0, 0.5, 0.0]]), np.full((1, 2), 0.1),
                                 frame_to_quaternion(np.array([[0.0, 1.0, 0.0]])), [0.9])
    bounds = SceneBounds((0.1, 0.5, -0.2), 1.3, 3.7)
    cfg = VisibilityConfig(resolution=64, projection=projection)
    rng = np.random.default_rng(5)
    dirs = [direction_from_angles(az, el)
            for az, el in zip(rng.uniform(0, 360, 24), rng.uniform(5, 89, 24), strict=True)]
    texels = {render_shadow_maps(surfels, np.array([d]), bounds, cfg).texel for d in dirs}
    assert texels == {map_texel(bounds, cfg)}
    for d in dirs:
        cam = shadow_camera(d, np.array(bounds.center), bounds.radius,
                            bounds.mean_camera_distance, cfg)
        own = cam.ortho_width / 64 if cam.is_ortho else \
            2.0 * math.tan(0.5 * cam.fov_x) * np.linalg.norm(cam.origin - bounds.center) / 64
        assert own == pytest.approx(map_texel(bounds, cfg), rel=1e-12)
