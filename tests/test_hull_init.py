"""Stage 1's visual-hull initialisation (stages/geometry/train.py): the cube every view
sees (``view_radius``) against a float64 reference, and no hull point that no view sees."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest

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
        dataclasses.replace(train.get_config("cpu-small"), **{field: value})


def test_points_without_points_names_what_is_missing():
    views = _ring_views(n=4, elevations_deg=(30.0,))
    config = dataclasses.replace(train.get_config("cpu-small"), init="points")
    with pytest.raises(ValueError, match="init 'points' needs the dataset's SfM points"):
        train.init_params(views, config)
