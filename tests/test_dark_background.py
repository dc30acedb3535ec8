"""Stage 1's dark-alpha prior without masks acts on the background, not on cast shadows: the
SfM points' support (``stages/geometry/background.py``) against float64 references, on a
plane whose dark shadow patch has SfM points around it and a black backdrop that has none."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from mi_shadowgs import presets as run_presets
from mi_shadowgs.config import ConfigError
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.stages.geometry import background
from mi_shadowgs.stages.geometry import train as geometry_train

SIZE = 48
MAT = 1.5  # the mat's half-size; the object a box of half-size 0.5 and height 1 on it
SHADOW = (0.6, 1.3, -0.4, 0.4)  # x0, x1, z0, z1 of the cast shadow on the mat


def _points(rng, with_shadow_points: bool = False, strays: int = 0) -> np.ndarray:
    """SfM-like points: the mat (none in the shadow, as in a darkroom), the box's surface,
    and ``strays`` far out in the backdrop."""
    g = rng.uniform(-MAT, MAT, (3000, 2))
    x0, x1, z0, z1 = SHADOW
    in_shadow = (g[:, 0] > x0) & (g[:, 0] < x1) & (g[:, 1] > z0) & (g[:, 1] < z1)
    if not with_shadow_points:
        g = g[~in_shadow]
    mat = np.stack([g[:, 0], rng.normal(0, 0.003, len(g)), g[:, 1]], axis=-1)
    box = rng.uniform([-0.5, 0.0, -0.5], [0.5, 1.0, 0.5], (2000, 3))
    face = rng.integers(0, 3, len(box))  # snap each to a face: a surface, not a volume
    box[face == 0, 0] = np.sign(box[face == 0, 0]) * 0.5
    box[face == 1, 1] = 1.0
    box[face == 2, 2] = np.sign(box[face == 2, 2]) * 0.5
    far = rng.uniform(-6, 6, (strays, 3)) + np.array([0.0, 3.0, -8.0])
    return np.concatenate([mat, box, far])


def _camera(origin=(0.0, 2.5, 4.0)) -> Camera:
    return Camera.look_at(origin, (0.0, 0.3, 0.0), fov_x=1.0, width=SIZE, height=SIZE)


def _truth(camera: Camera):
    """(mat, shadow, box, backdrop) [H, W] bool of the scene, by a float64 ray trace of the
    box and the mat."""
    o, d = background._rays(camera)
    lo, hi = np.array([-0.5, 0.0, -0.5]), np.array([0.5, 1.0, 0.5])
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t_near = np.minimum(ta, tb).max(axis=1)
    t_far = np.maximum(ta, tb).min(axis=1)
    box = (t_near <= t_far) & (t_far > 0)
    t = -o[:, 1] / d[:, 1]
    p = o + t[:, None] * d
    on_mat = (t > 0) & (np.abs(p[:, 0]) <= MAT) & (np.abs(p[:, 2]) <= MAT) & ~box
    x0, x1, z0, z1 = SHADOW
    shadow = on_mat & (p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 2] > z0) & (p[:, 2] < z1)
    shape = (camera.height, camera.width)
    return (on_mat.reshape(shape), shadow.reshape(shape), box.reshape(shape),
            (~on_mat & ~box).reshape(shape))


def _image(camera: Camera) -> np.ndarray:
    """Lit mat and box at 0.4, the shadow and the backdrop black."""
    on_mat, shadow, box, _ = _truth(camera)
    img = np.zeros((SIZE, SIZE, 3), np.float32)
    img[(on_mat | box) & ~shadow] = 0.4
    return img


def test_rays_meet_hull_on_a_cube_against_hand_cases():
    """Hit, miss, a ray starting inside, one pointing away, one along a face outside."""
    cube = np.array([[1, 0, 0, -1], [-1, 0, 0, -1], [0, 1, 0, -1], [0, -1, 0, -1],
                     [0, 0, 1, -1], [0, 0, -1, -1]], np.float64)
    o = np.array([[0, 0, -5], [0, 3, -5], [0, 0, 0], [0, 0, -5], [0, 2, -5], [0, 0.9, -5]],
                 np.float64)
    d = np.array([[0, 0, 1], [0, 0, 1], [1, 0, 0], [0, 0, -1], [0, 0, 1], [0.1, 0.06, 1]],
                 np.float64)
    assert background.rays_meet_hull(o, d, cube).tolist() == [True, False, True, False,
                                                               False, False]


def test_ground_and_hull_tests_against_float64_references():
    """The ground: each ray's point on y = 0 in the Delaunay triangulation of the ground's
    points. A hull (the points above the ground and the object's cells): a linear programme
    per ray (a convex combination of the hull's vertices on the ray, t >= 0), exact; the
    half-space tests must agree on every ray."""
    from scipy.optimize import linprog
    from scipy.spatial import ConvexHull, Delaunay

    pts = _points(np.random.default_rng(0))
    ground, above = background.split_points(pts)
    cam = _camera()
    o, d = background._rays(cam)
    t = -o[:, 1] / d[:, 1]
    hit = o + t[:, None] * d
    ref = (t > 0) & (Delaunay(ground[:, [0, 2]]).find_simplex(hit[:, [0, 2]]) >= 0)
    got = background.rays_meet_ground(o, d, background._hull(ground[:, [0, 2]], 0.0))
    assert 0.1 < ref.mean() < 0.9
    assert np.mean(got != ref) <= 0.002  # rays through the outline's edge, in float64

    body = np.concatenate([above, background.object_cells(6)])
    verts = body[ConvexHull(body).vertices]
    near = Camera.look_at((0.0, 2.5, 4.0), (0.0, 1.0, 0.0), fov_x=0.6, width=16, height=16)
    o, d = background._rays(near)
    ref = []
    for oi, di in zip(o, d, strict=True):
        a_eq = np.zeros((4, len(verts) + 1))
        a_eq[:3, :-1], a_eq[:3, -1], a_eq[3, :-1] = verts.T, -di, 1.0
        res = linprog(np.zeros(len(verts) + 1), A_eq=a_eq, b_eq=np.r_[oi, 1.0],
                      bounds=(0, None), method="highs")
        ref.append(res.status == 0)
    ref = np.array(ref)
    assert 0.2 < ref.mean() < 0.8
    got = background.rays_meet_hull(o, d, background._hull(body, 0.0))
    np.testing.assert_array_equal(got, ref)
    # The projected outline (what supported_pixels uses before the camera) is the same
    # test, also for the hull grown by a margin; a camera inside the hull falls back.
    np.testing.assert_array_equal(background.hull_pixels(near, background._hull(body, 0.0)),
                                  ref)
    grown = background._hull(body, 0.1)
    for cam in (near, Camera.look_at((3.0, 0.5, -2.0), (0.0, 1.0, 0.0), fov_x=0.9,
                                     width=40, height=30)):
        o, d = background._rays(cam)
        np.testing.assert_array_equal(background.hull_pixels(cam, grown),
                                      background.rays_meet_hull(o, d, grown))
    inside = Camera.look_at((0.0, 1.0, 0.0), (1.0, 1.0, 0.0), fov_x=0.8, width=8, height=8)
    assert background.hull_pixels(inside, grown) is None
    assert background.supported_pixels(inside, background.Support(None, grown)).all()


def _clear_of_the_scene(camera: Camera, slack: float = 0.3) -> np.ndarray:
    """[H, W] bool: the rays that stay ``slack`` clear of the mat and of the object's bound
    (the frame's cylinder of radius 1 and height 2), sampled in float64."""
    o, d = background._rays(camera)
    t = np.linspace(0.0, 12.0, 600)
    p = o[:, None] + t[None, :, None] * d[:, None]  # [P, T, 3]
    in_cylinder = ((np.hypot(p[..., 0], p[..., 2]) <= 1.0 + slack)
                   & (p[..., 1] >= -slack) & (p[..., 1] <= 2.0 + slack))
    in_mat = ((np.abs(p[..., 0]) <= MAT + slack) & (np.abs(p[..., 2]) <= MAT + slack)
              & (np.abs(p[..., 1]) <= 0.05))
    return ~np.any(in_cylinder | in_mat, axis=1).reshape(camera.height, camera.width)


# Eight views round the scene, from 15 to 50 degrees above the mat.
ORBIT = [(4.5 * np.cos(np.radians(el)) * np.sin(np.radians(az)),
          4.5 * np.sin(np.radians(el)), 4.5 * np.cos(np.radians(el)) * np.cos(np.radians(az)))
         for az, el in zip(range(0, 360, 45), (15, 50, 25, 40, 15, 50, 25, 40), strict=True)]


def _dataset(pts):
    cams = [_camera(o) for o in ORBIT]
    views = [SimpleNamespace(camera=c, image=_image(c), mask=np.ones((SIZE, SIZE), bool),
                             has_mask=False) for c in cams]
    return SimpleNamespace(views=views, points="unused"), cams


def test_a_shadow_on_the_mat_keeps_its_surface_and_the_backdrop_gets_the_prior():
    """Every dark pixel of the shadow (no SfM points in it) is left to the photometric loss,
    and so is the box; every dark backdrop pixel whose ray passes clear of the mat and of the
    object's bound gets the prior, and most of the others. The rule of every dark pixel
    ("none") puts the prior on the shadow too."""
    from unittest import mock

    dataset, cams = _dataset(_points(np.random.default_rng(1), strays=5))
    cfg = dataclasses.replace(run_presets.geometry_config("cpu-small"),
                              lambda_dark_alpha=0.1)
    with mock.patch.object(background, "read_points",
                           return_value=_points(np.random.default_rng(1), strays=5)):
        priors = background.prior_pixels(dataset, cfg)
    none = background.prior_pixels(dataset, dataclasses.replace(cfg, dark_alpha_support="none"))
    shares = []
    for cam, prior, every in zip(cams, priors, none, strict=True):
        _, shadow, box, backdrop = _truth(cam)
        assert backdrop.sum() > 100
        assert not prior[shadow].any() and not prior[box].any()
        assert every[shadow].all() and every[backdrop].all()
        assert prior[_clear_of_the_scene(cam)].all()
        shares.append(prior[backdrop].mean())
    assert sum(_truth(c)[1].sum() for c in cams) > 100  # the shadow is in view
    assert np.mean(shares) > 0.85


def test_the_carve_keeps_the_box_and_empties_the_space_above_it():
    """The object's cells that half the views see as dark backdrop are carved: the space
    above the box (height 1) goes, every cell within the box stays, and a cell no view sees
    stays."""
    dataset, cams = _dataset(_points(np.random.default_rng(1)))
    ground, _ = background.split_points(_points(np.random.default_rng(1)))
    mat = background.Support(background._hull(ground[:, [0, 2]], 0.05), None)
    off = [background.dark_pixels(v.image, 1.0 / 255.0)
           & ~background.supported_pixels(v.camera, mat) for v in dataset.views]
    cells = background.object_cells()
    kept = background.carve(cells, cams, off)
    in_box = np.all(np.abs(cells - [0.0, 0.5, 0.0]) <= 0.5, axis=1)
    assert kept[in_box].all()
    assert not kept[cells[:, 1] > 1.4].any()
    hidden = np.array([[0.0, 50.0, 0.0]])  # behind every camera's image
    assert background.carve(hidden, cams, off).tolist() == [True]


def test_stray_points_are_dropped_and_a_scene_without_ground_has_a_body():
    rng = np.random.default_rng(2)
    pts = _points(rng, with_shadow_points=True, strays=6)
    keep = background.inliers(pts)
    assert not keep[-6:].any() and keep[:-6].mean() > 0.99
    blob = rng.normal(0, 1, (500, 3)) + np.array([0.0, 3.0, 0.0])
    ground, body = background.split_points(blob)
    assert ground is None and len(body) > 490
    s = background.support_of(blob, [], [], 0.05)
    assert s.ground is None and s.body is not None
    # No points: the object's bound, uncarved without views
    bound = background.support_of(np.zeros((0, 3)), [], [], 0.0)
    assert bound.ground is None
    hits = background.rays_meet_hull(np.array([[0.0, 1.9, 0.0], [0.0, 2.2, 0.0]]),
                                     np.array([[1.0, 0.0, 0.0]] * 2), bound.body)
    assert hits.tolist() == [True, False]


def test_views_with_masks_and_a_zero_weight_get_no_prior_and_no_points_fall_back():
    cam = _camera()
    masked = SimpleNamespace(camera=cam, image=_image(cam), has_mask=True)
    unmasked = SimpleNamespace(camera=cam, image=_image(cam), has_mask=False)
    cfg = dataclasses.replace(run_presets.geometry_config("cpu-small"),
                              lambda_dark_alpha=0.1)
    ds = SimpleNamespace(views=[masked, unmasked], points=None)
    priors = background.prior_pixels(ds, cfg)
    assert priors[0] is None
    np.testing.assert_array_equal(priors[1], background.dark_pixels(_image(cam), cfg.dark_max))
    off = dataclasses.replace(cfg, lambda_dark_alpha=0.0)
    assert background.prior_pixels(ds, off) == [None, None]


def test_the_view_data_takes_the_prior_pixels():
    """What stage 1's loss reads: the prior's pixels as given, a view with a mask none."""
    cam = _camera()
    prior = np.zeros((SIZE, SIZE), bool)
    prior[:5] = True
    view = SimpleNamespace(camera=cam, image=_image(cam), mask=np.ones((SIZE, SIZE), bool),
                           has_mask=False)
    vd = geometry_train._view_data(view, prior=prior)
    np.testing.assert_array_equal(np.asarray(vd.dark)[..., 0], prior.astype(np.float32))
    assert geometry_train._view_data(SimpleNamespace(**{**vars(view), "has_mask": True}),
                                     prior=prior).dark is None


def _lit_room(camera: Camera, room=(0.03, 0.035, 0.04)) -> np.ndarray:
    """``_image`` in a lit room: the backdrop at ``room``, the shadow half as bright."""
    on_mat, shadow, box, backdrop = _truth(camera)
    img = _image(camera)
    img[backdrop] = room
    img[shadow] = 0.5 * np.asarray(room)
    return img


def _lit_room_dataset():
    """(room colour, the views in that lit room, their cameras, stage 1's settings with
    the prior on)."""
    room = np.array([0.03, 0.035, 0.04])
    dataset, cams = _dataset(_points(np.random.default_rng(1)))
    for v in dataset.views:
        v.image = _lit_room(v.camera, room)
    cfg = dataclasses.replace(run_presets.geometry_config("cpu-small"),
                              lambda_dark_alpha=0.1)
    return room, dataset, cams, cfg


def test_a_lit_rooms_backdrop_is_estimated_and_the_prior_follows_it():
    """The backdrop's colour from the pixels that miss the ground and the object's bound;
    with it the prior acts on the (now grey) backdrop and still not on the shadow, which is
    darker. Black setting, masks or a black room: no backdrop."""
    from unittest import mock

    room, dataset, cams, cfg = _lit_room_dataset()
    with mock.patch.object(background, "read_points",
                           return_value=_points(np.random.default_rng(1))):
        got = background.estimate_backdrop(dataset, cfg)
        priors = background.prior_pixels(dataset, cfg, got)
        assert background.estimate_backdrop(
            dataset, dataclasses.replace(cfg, backdrop="black")) is None
        for v in dataset.views:
            v.image = _image(v.camera)
        assert background.estimate_backdrop(dataset, cfg) is None  # a black room
    np.testing.assert_allclose(got, room, rtol=1e-6)
    for cam, prior in zip(cams, priors, strict=True):
        _, shadow, box, backdrop = _truth(cam)
        assert not prior[shadow].any() and not prior[box].any()
        assert prior[_clear_of_the_scene(cam)].all()
    masked = SimpleNamespace(views=[SimpleNamespace(**{**vars(v), "has_mask": True})
                                    for v in dataset.views], points="unused")
    assert background.estimate_backdrop(masked, cfg) is None


def test_stage4_leaves_out_surfaces_past_the_ground_as_dark_as_the_room():
    """Stage 4's rule (``PastTheGround``): a dark surface outside the mat's outline and the
    body's hull is the room seen past the ground; a dark shadow on the mat, the dark top of
    the box, and a lit floor past the mat are not. Without a backdrop colour, SfM points or
    views without masks there is no rule."""
    from unittest import mock

    room, dataset, _, cfg = _lit_room_dataset()
    with mock.patch.object(background, "read_points",
                           return_value=_points(np.random.default_rng(1))):
        rule = background.PastTheGround.of(dataset, cfg, room)
    points = np.array([[1.0, 0.0, 0.0],    # in the cast shadow on the mat
                       [0.0, 1.0, 0.0],    # on the box's top
                       [0.0, 0.3, -2.5],   # past the mat's far edge, off the ground
                       [2.2, 0.0, 0.0],    # past the mat's side, on the ground's plane
                       [2.2, 0.0, 0.0]])   # the same, lit
    rgb = np.array([0.5 * room, 0.5 * room, room, 1.2 * room, [0.4] * 3])
    assert rule.pixels(points, rgb).tolist() == [False, False, True, True, False]
    # the same by surfels: their centres and stage 1's mean colour (the SH's DC band)
    from mi_shadowgs.core.surfels import SH_C0, Surfels

    n = len(points)
    surfels = Surfels.from_numpy(points, np.full((n, 2), 0.01), np.tile([1.0, 0, 0, 0], (n, 1)),
                                 np.full(n, 0.9), channels={"sh": (rgb - 0.5) / SH_C0})
    assert rule.surfels(surfels).tolist() == [False, False, True, True, False]
    assert background.PastTheGround.of(dataset, cfg, None) is None
    masked = SimpleNamespace(views=[SimpleNamespace(**{**vars(v), "has_mask": True})
                                    for v in dataset.views], points="unused")
    assert background.PastTheGround.of(masked, cfg, room) is None
    assert background.PastTheGround.of(SimpleNamespace(views=dataset.views, points=None),
                                       cfg, room) is None


def test_the_render_over_the_backdrop_and_its_gradients_against_numpy():
    """``over_backdrop``: rgb + (1 - alpha) * colour per channel; d/d colour = sum of
    (1 - alpha), d/d alpha = -colour summed over the channels."""
    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.core import jit

    rng = np.random.default_rng(3)
    rgb, alpha = rng.uniform(0, 1, (5, 4, 3)), rng.uniform(0, 1, (5, 4, 1))
    colour = np.array([0.2, 0.3, 0.5])
    t_rgb, t_a, t_c = (jit.tensor(x.astype(np.float32)) for x in (rgb, alpha, colour))
    dr.enable_grad(t_a, t_c)
    out = background.over_backdrop(t_rgb, t_a, t_c)
    np.testing.assert_allclose(out.numpy(), rgb + (1 - alpha) * colour, rtol=1e-6)
    dr.backward(dr.sum(out.array))
    np.testing.assert_allclose(dr.grad(t_c).numpy(), np.full(3, (1 - alpha).sum()),
                               rtol=1e-5)
    np.testing.assert_allclose(dr.grad(t_a).numpy()[..., 0], np.full((5, 4), -colour.sum()),
                               rtol=1e-6)
    render = {"rgb": rgb, "alpha": alpha[..., 0]}
    np.testing.assert_allclose(background.composite(render, colour),
                               rgb + (1 - alpha) * colour, rtol=1e-6)
    assert background.composite(render, None) is rgb
    assert isinstance(out, mi.TensorXf)


@pytest.mark.parametrize("field, value", [("dark_alpha_support", "sfm"), ("backdrop", "grey"),
                                          ("dark_alpha_margin", -0.1),
                                          ("dark_alpha_margin", float("nan"))])
def test_bad_settings_are_refused_by_name(field, value):
    with pytest.raises(ConfigError, match=field):
        dataclasses.replace(run_presets.geometry_config("cpu-small"), **{field: value})


def test_stage4_leaves_the_rules_pixels_out_unless_told_to_fit_them():
    """``prepare_view`` drops the supervision of the pixels the rule names (here the floor
    at x < -0.5), and ``setup_fit`` passes the rule on only with ``backdrop_surfels``
    "skip"."""
    from mi_shadowgs.presets import material_config
    from mi_shadowgs.stages.material.fit import setup_fit
    from mi_shadowgs.stages.material.views import prepare_view
    from tests.test_light_fit import _scene

    class Left:
        def pixels(self, points, rgb):
            return points[:, 0] < -0.5

    s, cams, bounds = _scene()
    img, mask = np.full((64, 64, 3), 0.2, np.float32), np.ones((64, 64), bool)
    cfg = dataclasses.replace(material_config("cpu-small"), warmup=0)
    plain = prepare_view(s, cams[0], img, mask, cfg)
    left = prepare_view(s, cams[0], img, mask, cfg, past=Left())
    x = plain.geom.points[0].numpy()
    w0, w1 = plain.weight.numpy() > 0, left.weight.numpy() > 0
    assert (w0 & (x < -0.5)).sum() > 100
    np.testing.assert_array_equal(w1, w0 & ~(x < -0.5))
    for mode, want in (("skip", w1), ("fit", w0)):
        fit, _ = setup_fit(s, cams[:1], [img], [mask],
                           dataclasses.replace(cfg, backdrop_surfels=mode), bounds,
                           progress=False, past=Left())
        np.testing.assert_array_equal(fit.views[0].weight.numpy() > 0, want)
