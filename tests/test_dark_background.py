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


def test_support_against_float64_references():
    """The ground: each ray's point on y = 0 in the Delaunay triangulation of the ground's
    points. The body: a linear programme per ray (a convex combination of the hull's vertices
    on the ray, t >= 0), exact; the support's half-space tests must agree on every ray."""
    from scipy.optimize import linprog
    from scipy.spatial import ConvexHull, Delaunay

    rng = np.random.default_rng(0)
    pts = _points(rng)
    support = background.support_from_points(pts, 0.0)
    assert support.ground is not None and support.body is not None
    keep = pts[background.inliers(pts)]
    on_ground = np.abs(keep[:, 1]) <= background.GROUND_HEIGHT
    cam = _camera()
    o, d = background._rays(cam)
    t = -o[:, 1] / d[:, 1]
    hit = o + t[:, None] * d
    ref = (t > 0) & (Delaunay(keep[on_ground][:, [0, 2]]).find_simplex(hit[:, [0, 2]]) >= 0)
    got = background.rays_meet_ground(o, d, support.ground)
    assert 0.1 < ref.mean() < 0.9
    assert np.mean(got != ref) <= 0.002  # rays through the outline's edge, in float64

    body = keep[~on_ground]
    verts = body[ConvexHull(body).vertices]
    near = Camera.look_at((0.0, 2.5, 4.0), (0.0, 0.5, 0.0), fov_x=0.45, width=16, height=16)
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
    np.testing.assert_array_equal(background.rays_meet_hull(o, d, support.body), ref)


def test_a_shadow_on_the_mat_keeps_its_surface_and_the_backdrop_gets_the_prior():
    """Every dark pixel of the shadow (no SfM points in it) is left to the photometric loss;
    every dark backdrop pixel but those within the margin's reach of the mat gets the prior.
    The rule of every dark pixel ("none") puts the prior on both."""
    rng = np.random.default_rng(1)
    pts = _points(rng, strays=5)
    cams = [_camera(o) for o in ((0.0, 2.5, 4.0), (3.0, 1.5, 3.0), (2.5, 3.0, -3.0),
                                (4.0, 1.2, 0.5))]
    views = [SimpleNamespace(camera=c, image=_image(c), mask=np.ones((SIZE, SIZE), bool),
                             has_mask=False) for c in cams]
    dataset = SimpleNamespace(views=views, points="unused")
    cfg = dataclasses.replace(run_presets.geometry_config("cpu-small"),
                              lambda_dark_alpha=0.1)
    from unittest import mock

    with mock.patch.object(background, "read_points", return_value=pts):
        priors = background.prior_pixels(dataset, cfg)
        none = background.prior_pixels(
            dataset, dataclasses.replace(cfg, dark_alpha_support="none"))
    for cam, prior, every in zip(cams, priors, none, strict=True):
        _, shadow, _, backdrop = _truth(cam)
        assert shadow.sum() > 20 and backdrop.sum() > 100
        assert not prior[shadow].any()
        assert every[shadow].all() and every[backdrop].all()
        assert prior[backdrop].mean() > 0.9


def test_stray_points_are_dropped_and_a_scene_without_ground_has_a_body_only():
    rng = np.random.default_rng(2)
    pts = _points(rng, with_shadow_points=True, strays=6)
    keep = background.inliers(pts)
    assert not keep[-6:].any() and keep[:-6].mean() > 0.99
    blob = rng.normal(0, 1, (500, 3)) + np.array([0.0, 3.0, 0.0])
    s = background.support_from_points(blob, 0.05)
    assert s.ground is None and s.body is not None
    flat = background.support_from_points(np.zeros((50, 3)), 0.05)  # no volume, no area
    assert flat.ground is None and flat.body is None
    assert not background.supported_pixels(_camera(), flat).any()


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


@pytest.mark.parametrize("field, value", [("dark_alpha_support", "sfm"),
                                          ("dark_alpha_margin", -0.1),
                                          ("dark_alpha_margin", float("nan"))])
def test_bad_settings_are_refused_by_name(field, value):
    with pytest.raises(ConfigError, match=field):
        dataclasses.replace(run_presets.geometry_config("cpu-small"), **{field: value})
