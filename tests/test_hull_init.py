"""Stage 1's visual hull (stages/geometry/train.py): the initialisation's cube every view
sees (``view_radius``) against a float64 reference, no hull point that no view sees, and the
prune after training (``prune_outside_masks``) against the sphere's exact silhouettes."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest

from mi_shadowgs import presets as run_presets
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.dataset.loader import View
from mi_shadowgs.stages.geometry import train

SPHERE_RADIUS = 0.5


def _ring_views(n: int = 8, distance: float = 5.0, size: int = 48, fov: float = 0.6,
                elevations_deg=(-60.0, -20.0, 20.0, 60.0)) -> list[View]:
    """Views on rings about the origin (``n`` per elevation), each masked to the silhouette
    of a sphere of ``SPHERE_RADIUS`` at the origin (a pixel is in when its ray passes
    within it)."""
    views = []
    for k in range(n * len(elevations_deg)):
        el = math.radians(elevations_deg[k // n])
        az = 2 * math.pi * (k % n + 0.5 * (k // n)) / n
        origin = distance * np.array([math.cos(el) * math.cos(az), math.sin(el),
                                      math.cos(el) * math.sin(az)])
        cam = Camera.look_at(origin, [0.0, 0.0, 0.0], width=size, height=size, fov_x=fov)
        far = cam.unproject(cam.pixel_grid(), np.ones(size * size))  # [H*W, 3] at depth 1
        d = far - cam.origin
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t = -(cam.origin[None] * d).sum(1)  # closest approach to the origin along each ray
        miss = np.linalg.norm(cam.origin[None] + t[:, None] * d, axis=1)
        mask = (miss < SPHERE_RADIUS).reshape(size, size)
        views.append(View(f"v{k}", cam, np.full((size, size, 3), 0.5, np.float32), mask))
    return views


def test_view_radius_is_the_half_width_at_the_centre():
    views = _ring_views(distance=5.0, fov=0.6)
    got = train.view_radius([v.camera for v in views], np.zeros(3))
    # Reference: distance * tan(fov / 2) for a square perspective view looking at the centre.
    assert abs(got - 5.0 * math.tan(0.3)) < 1e-9
    # A wider image's narrower side decides; one close-up among many does not.
    cam = dataclasses.replace(views[0].camera, height=24)
    assert abs(train.view_radius([cam], np.zeros(3)) - 0.5 * 5.0 * math.tan(0.3)) < 1e-9
    close = Camera.look_at([0.0, 0.0, 0.5], [0.0, 0.0, 0.0], width=48, height=48, fov_x=0.6)
    cams = [v.camera for v in views] + [close]
    assert abs(train.view_radius(cams, np.zeros(3)) - 5.0 * math.tan(0.3)) < 1e-9
    away = Camera.look_at([0.0, 0.0, 5.0], [0.0, 0.0, 10.0], width=48, height=48, fov_x=0.6)
    with pytest.raises(ValueError, match="hull_extent"):
        train.view_radius([away], np.zeros(3))


def test_hull_points_lie_on_the_object_and_in_some_view():
    views = _ring_views()
    centre, cam_radius = train.scene_bounds([v.camera for v in views])
    rng = np.random.default_rng(0)
    # The cameras' cube: cells seen by no view used to survive; none may now.
    pts = train.visual_hull_points(views, centre, cam_radius, 2000, 48, rng)
    seen = np.zeros(len(pts), bool)
    for v in views:
        seen |= v.camera.pixel_of(pts)[2]
    assert seen.all()
    # The cube every view sees: the hull is the sphere, up to a cell's slack and the cube's
    # corners that only a few views see.
    radius = 1.2 * train.view_radius([v.camera for v in views], centre)
    pts = train.visual_hull_points(views, centre, radius, 2000, 48, rng)
    r = np.linalg.norm(pts - centre, axis=1)
    cell = 2 * radius / 48
    assert np.mean(r < SPHERE_RADIUS + cell) > 0.95  # measured: 99% within the radius
    # The cameras' cube puts far fewer of its points there (why the preset uses the other).
    wide = train.visual_hull_points(views, centre, cam_radius, 2000, 48, rng)
    wide_share = np.mean(np.linalg.norm(wide - centre, axis=1) < SPHERE_RADIUS + cell)
    assert wide_share < 0.5  # measured: 0.015


@pytest.mark.parametrize("field, value, message", [
    ("hull_extent", 0.0, "GeometryConfig.hull_extent must be > 0 or None, got 0.0"),
    ("init", "hul", "GeometryConfig.init must be one of ('hull', 'random', 'points'), got 'hul'"),
    ("normal_depth_differences", "forward", "GeometryConfig.normal_depth_differences must be "
     "one of"),
])
def test_an_initialisation_setting_out_of_range_is_refused_when_made(field, value, message):
    """Refused when the config is made (a preset with ``--set``, a recorded config), not
    after stage 1 has loaded every view and started."""
    from mi_shadowgs.config import ConfigError

    with pytest.raises(ConfigError, match=re.escape(message)):
        dataclasses.replace(run_presets.geometry_config("cpu-small"), **{field: value})


def test_points_without_points_names_what_is_missing():
    views = _ring_views(n=4, elevations_deg=(30.0,))
    config = dataclasses.replace(run_presets.geometry_config("cpu-small"), init="points")
    with pytest.raises(ValueError, match="init 'points' needs the dataset's SfM points"):
        train.init_params(views, config)


# -- the prune after training ---------------------------------------------------------------
def _miss_distances(views, points: np.ndarray) -> np.ndarray:
    """[V, M] float64: the distance from the origin of the line from each view's camera
    through each point: the point is in the sphere's silhouette when it is < SPHERE_RADIUS."""
    out = []
    for v in views:
        d = points - v.camera.origin[None]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t = -(v.camera.origin[None] * d).sum(1)
        out.append(np.linalg.norm(v.camera.origin[None] + t[:, None] * d, axis=1))
    return np.array(out)


def _surfels_at(points: np.ndarray):
    from mi_shadowgs.core.surfels import Surfels

    n = len(points)
    rng = np.random.default_rng(3)
    return Surfels.from_numpy(points, np.full((n, 2), 0.01), rng.normal(size=(n, 4)),
                              np.full(n, 0.5), {"rgb": rng.random((n, 3))})


def test_outside_mask_votes_follow_the_silhouettes():
    """Each view's vote against the exact silhouette of the sphere: a point whose line of
    sight misses the sphere by more than 3 px (at the sphere's depth) must get the vote of
    the 1-px dilated mask, and one that passes within it by 1 px must not; the pixels in
    between are the rasterised edge's, where either answer is right."""
    views = _ring_views()
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1.2, 1.2, (3000, 3))
    px = 5.0 * 0.6 / 48  # a pixel's width at the sphere's distance (small-angle)
    miss = _miss_distances(views, pts)  # [V, M]
    seen = np.array([v.camera.pixel_of(pts)[2] for v in views])  # [V, M]
    must = (miss > SPHERE_RADIUS + 3 * px) & seen
    may = (miss > SPHERE_RADIUS - 1 * px) & seen
    got = train.outside_mask_votes(views, pts, dilate=1)
    assert np.all(got >= must.sum(0)) and np.all(got <= may.sum(0))
    assert np.mean(may & ~must) < 0.25  # most pairs are decided (measured: 0.18 are not)
    assert got.max() >= 20 and (got == 0).sum() > 100  # both kinds are in the draw
    # Without dilation a vote can only be added, and a view without a mask never votes.
    assert np.all(train.outside_mask_votes(views, pts, dilate=0) >= got)
    blind = [dataclasses.replace(v, mask=np.zeros_like(v.mask), has_mask=False) for v in views]
    assert not train.outside_mask_votes(blind, pts, dilate=1).any()


def test_prune_outside_masks_removes_floaters_and_keeps_the_object():
    views = _ring_views()
    rng = np.random.default_rng(2)
    inner = rng.normal(size=(200, 3))
    inner *= 0.4 / np.linalg.norm(inner, axis=1, keepdims=True)  # on a sphere inside
    floaters = np.array([[0.0, 0.0, 1.0], [0.9, 0.2, 0.0], [-0.6, -0.7, 0.3]])
    pts = np.concatenate([inner[:100], floaters, inner[100:]])
    surfels = _surfels_at(pts)
    config = dataclasses.replace(run_presets.geometry_config("cpu-small"), hull_prune_views=2)
    pruned, removed = train.prune_outside_masks(surfels, views, config)
    assert removed == 3 and pruned.count == 200
    got = pruned.to_numpy()
    want = surfels.to_numpy()
    keep = np.ones(len(pts), bool)
    keep[100:103] = False
    for key in ("position", "scale", "rotation", "opacity", "rgb"):
        np.testing.assert_allclose(got[key], want[key][keep], rtol=0, atol=1e-7)
    # Off (the paper): the very same set back.
    off, n = train.prune_outside_masks(surfels, views, run_presets.geometry_config("paper"))
    assert off is surfels and n == 0
    # One view whose mask lost its left half votes against the object's surfels there:
    # two views are needed to remove one, so they stay at 2 and go at 1.
    half = views[0].mask.copy()
    half[:, :24] = False
    clipped = [dataclasses.replace(views[0], mask=half)] + views[1:]
    assert train.prune_outside_masks(surfels, clipped, config)[1] == 3
    one = dataclasses.replace(config, hull_prune_views=1)
    xi, _, seen = views[0].camera.pixel_of(pts)
    left = seen & (xi < 24 - 1)  # the dilation gives the cut edge's column back
    left[100:103] = True
    assert 3 < left.sum() < len(pts) and \
        train.prune_outside_masks(surfels, clipped, one)[1] == int(left.sum())
    # Masks that nothing agrees with: refused, naming the setting.
    empty = [dataclasses.replace(v, mask=np.zeros_like(v.mask)) for v in views]
    with pytest.raises(ValueError, match="GeometryConfig.hull_prune_views 2: every surfel"):
        train.prune_outside_masks(surfels, empty, config)


def test_surfels_subset_keeps_the_rows_asked_for():
    pts = np.random.default_rng(4).normal(size=(7, 3))
    surfels = _surfels_at(pts)
    keep = np.array([1, 0, 0, 1, 1, 0, 1], bool)
    got, want = surfels.subset(keep).to_numpy(), surfels.to_numpy()
    for key, value in want.items():
        np.testing.assert_array_equal(got[key], value[keep])
    with pytest.raises(ValueError, match="keep has 6 entries for 7 surfels"):
        surfels.subset(keep[:6])


@pytest.mark.parametrize("field, value", [("hull_prune_views", -1), ("hull_prune_dilate", -1)])
def test_a_prune_setting_below_zero_is_refused(field, value):
    from mi_shadowgs.config import ConfigError

    with pytest.raises(ConfigError, match=f"GeometryConfig.{field} must be >= 0"):
        dataclasses.replace(run_presets.geometry_config("cpu-small"), **{field: value})
