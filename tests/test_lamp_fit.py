"""Stage 4's lamps (``stages.material.lamps``): a light tested as a lamp against a
directional light on views the model itself renders (true albedo, no indirect), the lamp's
position searched, and a directional light kept directional."""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_shadowgs  # noqa: F401
from mi_shadowgs.core import shading
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import direction_from_angles
from mi_shadowgs.core.frames import frame_to_quaternion
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.presets import material_config as get_config
from mi_shadowgs.stages.material.lamps import (
    LampSearch,
    candidate_set,
    lamp_share,
    localize_lights,
)
from mi_shadowgs.stages.visibility.shadow_maps import SceneBounds, render_shadow_maps
from tests.test_light_fit import VCFG, _grid, _scene, rendered_views

TRUE_DIR = direction_from_angles(35.0, 50.0)


@pytest.fixture(scope="module")
def scene():
    threads = dr.thread_count()
    dr.set_thread_count(1)
    yield _scene()
    dr.set_thread_count(threads)


def _search(scene, lights, **over):
    s, cams, bounds = scene
    views, ch = rendered_views(s, cams, lights)
    cfg = dataclasses.replace(get_config("cpu-small"), lamps="auto", **over)
    center = np.asarray(bounds.center)
    return LampSearch(views, ch, lambda *a, **k: None, cfg, False, center, bounds.radius)


def test_a_lamp_is_found_and_placed(scene):
    _, _, bounds = scene
    center = np.asarray(bounds.center)
    true_pos = center + TRUE_DIR * 5.0  # 2.6 bound radii
    lamp = shading.local_lights(true_pos[None], mi.Color3f(2.0), center)
    search = _search(scene, lamp)
    start = direction_from_angles(38.0, 47.0)  # a directional fit's few degrees off
    dirs, pos, irr, log = localize_lights(search, start[None], None, np.array([1.5]),
                                          np.array([0]))
    assert log[0]["kept"] == "lamp"
    assert log[0]["error_lamp"] < 0.5 * log[0]["error_directional"]
    dist = np.linalg.norm(pos[0] - center)
    assert abs(dist - 5.0) / 5.0 < 0.05
    d = (pos[0] - center) / dist
    assert math.degrees(math.acos(np.clip(d @ TRUE_DIR, -1, 1))) < 2.0
    np.testing.assert_allclose(dirs[0], d, atol=1e-9)
    assert irr[0] == pytest.approx(2.0, rel=0.05)
    assert lamp_share(irr, pos) == 1.0


def test_a_directional_light_stays_directional(scene):
    sun = shading.directional_lights(TRUE_DIR[None], mi.Color3f(2.0))
    search = _search(scene, sun)
    dirs, pos, irr, log = localize_lights(search, TRUE_DIR[None], None, np.array([2.0]),
                                          np.array([0]))
    assert log[0]["kept"] == "directional"
    assert not np.isfinite(pos).any()
    np.testing.assert_array_equal(dirs[0], TRUE_DIR)
    assert irr[0] == pytest.approx(2.0, rel=1e-3)
    assert lamp_share(irr, pos) == 0.0


def test_candidate_set_rows():
    c = np.array([0.0, 1.0, 0.0])
    cand = candidate_set(c, np.array([[0, 2.0, 0], [0, 0, 1.0]]), np.array([math.inf, 3.0]))
    assert not np.isfinite(cand.positions[0]).any()
    np.testing.assert_allclose(cand.positions[1], [0, 1, 3])
    np.testing.assert_array_equal(cand.local, [False, True])


def test_lamp_settings_are_checked():
    base = get_config("cpu-small")
    for bad in ({"lamps": "on"}, {"lamp_distances": (0.5,)}, {"lamp_distances": ()},
                {"lamp_min_gain": 1.0}, {"lamp_passes": ((50.0, 0.1),)},
                {"lamp_score": "pixel"}, {"lamp_scan_directions": -1},
                {"lamp_scan_distances": ()}, {"lamp_scan_distances": (1.0,)},
                {"lamp_position_score": "edges"}, {"lamp_lit_ratio": 0.0},
                {"lamp_lit_ratio": 1.0}):
        with pytest.raises(ValueError, match="lamp"):
            dataclasses.replace(base, **bad)


def test_lamp_errors_against_the_truth():
    from mi_shadowgs.stages.evaluation.metrics import lamp_errors

    true = {"direction": TRUE_DIR.tolist(), "position": (TRUE_DIR * 6.0).tolist(),
            "distance": 6.0, "irradiance": [3, 3, 3]}
    est_pos = np.array([TRUE_DIR * 6.3, [np.nan] * 3])
    sun = direction_from_angles(200.0, 30.0)
    out = lamp_errors(np.array([TRUE_DIR, sun]), np.array([3.0, 1.0]), est_pos, [true])
    assert out["lamp_position_error"] == [pytest.approx(0.05)]
    assert out["strongest_light_share"] == pytest.approx(0.75)
    # matched to a directional light: no position error
    out = lamp_errors(np.array([TRUE_DIR]), np.array([3.0]), None, [true])
    assert out["lamp_position_error"] == [None]
    assert "lamp_position_error" not in lamp_errors(np.array([TRUE_DIR]), np.array([1.0]),
                                                    None, [{"direction": [0, 1, 0]}])


def test_a_lamp_is_placed_under_a_held_albedo_that_is_off_per_segment(scene):
    """The albedo fitted under the directional light is off by a scale per segment (floor
    0.8x, tile 1.25x): with ``lamp_score`` "auto" (no lobe: "albedo") each segment's albedo
    is fitted again per candidate, and the lamp is still placed within 5% of its
    distance."""
    s, _, bounds = scene
    center = np.asarray(bounds.center)
    true_pos = center + TRUE_DIR * 5.0
    lamp = shading.local_lights(true_pos[None], mi.Color3f(2.0), center)
    search = _search(scene, lamp)
    assert search.scoring == "albedo" and search.config.lamp_score == "auto"
    with_lobe = _search(scene, lamp, specular="auto", refine_score="segment")
    assert with_lobe.scoring == "segment"
    seg = s.channels["segment"].numpy()[:, 0]
    scale = np.where(seg == 0, 0.8, 1.25)[:, None].astype(np.float32)
    held = mi.TensorXf(search.channels["albedo"].numpy() * scale)
    start = direction_from_angles(38.0, 47.0)
    errors = {}
    for score in ("albedo", "irradiance"):
        search = _search(scene, lamp, lamp_score=score)
        search.channels = {**search.channels, "albedo": held}
        _, pos, _, log = localize_lights(search, start[None], None, np.array([1.5]),
                                         np.array([0]))
        assert log[0]["kept"] == "lamp"
        errors[score] = abs(np.linalg.norm(pos[0] - center) - 5.0) / 5.0
    assert errors["albedo"] < 0.05
    assert errors["irradiance"] > 0.2  # the held albedo's error moves the lamp


@pytest.mark.parametrize("scan", [True, False])
def test_a_lamp_started_far_off_is_found_by_the_scan(scene, scan):
    """A directional fit of a near lamp can start its search far off (a grazing light at
    the wrong azimuth): the global scan (``lamp_scan_directions``) moves it into the true
    lamp's basin, where the pattern search places it; without the scan it stays off. The
    views have the lamp's shadows, and the search its maps."""
    s, cams, bounds = scene
    center = np.asarray(bounds.center)
    true_pos = center + TRUE_DIR * 5.0
    lamp = shading.local_lights(true_pos[None], mi.Color3f(2.0), center)

    def render(dirs, resolution=None, positions=None):
        return render_shadow_maps(s, dirs, bounds, VCFG, resolution or 128, positions)

    views, ch = rendered_views(s, cams, lamp, render(TRUE_DIR[None], None, true_pos[None]))
    cfg = dataclasses.replace(get_config("cpu-small"), lamps="auto",
                              lamp_scan_directions=32 if scan else 0)
    search = LampSearch(views, ch, render, cfg, False, center, bounds.radius)
    start = direction_from_angles(85.0, 12.0)  # 50 degrees of azimuth, 38 of elevation off
    dirs, pos, irr, log = localize_lights(search, start[None], None, np.array([1.5]),
                                          np.array([0]))
    assert log[0]["kept"] == "lamp"
    d = (pos[0] - center) / np.linalg.norm(pos[0] - center)
    angle = math.degrees(math.acos(np.clip(d @ TRUE_DIR, -1, 1)))
    if scan:
        assert log[0]["scan"]["moved"] and log[0]["scan"]["kept"] == "scan"
        assert log[0]["scan"]["candidates"] == 1 + 32 * 5
        assert angle < 2.0
        assert abs(np.linalg.norm(pos[0] - center) - 5.0) / 5.0 < 0.05
    else:
        assert "scan" not in log[0]
        assert angle > 10.0



def _posts_scene():
    """A printed floor (its albedo x1.4 to x0.6 along +x) and four tiles held over it at
    (+-0.6, 0.5, +-0.6): a near lamp's shadows of the four diverge, and scale with its
    distance; 4 views at 128^2."""
    floor = _grid([0, 0, 0], 1.5, 90)
    tiles = [_grid([x, 0.5, z], 0.15, 8) for x in (-0.6, 0.6) for z in (-0.6, 0.6)]
    pos = np.concatenate([floor[0], *(t[0] for t in tiles)])
    size = np.concatenate([floor[1], *(t[1] for t in tiles)])
    seg = np.concatenate([np.zeros(len(floor[0])), np.ones(len(pos) - len(floor[0]))])
    base = np.where(seg[:, None] == 0, [[0.6, 0.5, 0.3]], [[0.2, 0.4, 0.7]])
    printed = base * np.where(seg == 0, 1.0 + 0.4 * pos[:, 0] / 1.5, 1.0)[:, None]
    s = Surfels.from_numpy(pos, size, frame_to_quaternion(np.tile([0.0, 1.0, 0.0],
                                                                  (len(pos), 1))),
                           np.full(len(pos), 0.99),
                           channels={"segment": seg[:, None].astype(np.float32),
                                     "albedo_gt": printed.astype(np.float32)})
    cams = [Camera.look_at(np.array([2.6 * math.cos(a), 2.8, 2.6 * math.sin(a)]),
                           np.zeros(3), fov_x=1.0, width=128, height=128)
            for a in np.linspace(0.3, 2 * math.pi + 0.3, 4, endpoint=False)]
    return s, cams, SceneBounds((0.0, 0.25, 0.0), 2.2, 4.0), base


@pytest.mark.parametrize("placed_by", ["shadows", "photometric"])
def test_shadows_place_a_lamp_that_a_print_moves(placed_by):
    """A print that brightens toward the lamp looks like a nearer lamp's falloff when each
    segment's albedo is one value: the photometric score places the lamp off; where its
    shadows fall (``lamp_position_score`` "shadows") places it within 5% of its distance."""
    s, cams, bounds, base = _posts_scene()
    center = np.asarray(bounds.center)
    true_dir = direction_from_angles(0.0, 50.0)  # azimuth 0: toward +x
    true_pos = center + true_dir * 5.0

    def render(dirs, resolution=None, positions=None):
        return render_shadow_maps(s, dirs, bounds, VCFG, resolution or 256, positions)

    lamp = shading.local_lights(true_pos[None], mi.Color3f(2.0), center)
    views, ch = rendered_views(s, cams, lamp, render(true_dir[None], None, true_pos[None]))
    ch = {**ch, "albedo": mi.TensorXf(base.astype(np.float32))}  # each segment's one value
    cfg = dataclasses.replace(get_config("cpu-small"), lamps="auto", lamp_scan_directions=0,
                              lamp_position_score=placed_by)
    search = LampSearch(views, ch, render, cfg, False, center, bounds.radius)
    start = direction_from_angles(3.0, 47.0)
    _, pos, _, log = localize_lights(search, start[None], None, np.array([1.5]),
                                     np.array([0]))
    assert log[0]["kept"] == "lamp"
    err = np.linalg.norm(pos[0] - true_pos) / 5.0
    assert (err < 0.05) == (placed_by == "shadows")


def test_a_lamps_direction_is_scored_from_the_true_centre():
    """A fitted lamp at the true position, fitted about a centre 0.5 off the object's, is
    0 degrees off as the truth gives its direction (from the object's centre), although
    its stored direction, from the fit's centre, is not; directional lights as stored."""
    from mi_shadowgs.stages.evaluation.metrics import light_angular_errors, seen_from

    centre = np.array([0.2, 0.5, -0.1])
    true = {"direction": TRUE_DIR.tolist(), "position": (centre + TRUE_DIR * 6.0).tolist(),
            "distance": 6.0, "irradiance": [3, 3, 3]}
    fit_centre = centre + np.array([0.5, 0.0, 0.0])
    stored = (np.asarray(true["position"]) - fit_centre)
    stored /= np.linalg.norm(stored)
    sun = direction_from_angles(200.0, 30.0)
    dirs = np.array([stored, sun])
    pos = np.array([true["position"], [np.nan] * 3])
    seen = seen_from(dirs, pos, [true])
    np.testing.assert_allclose(seen[0], TRUE_DIR, atol=1e-12)
    np.testing.assert_array_equal(seen[1], sun)
    assert light_angular_errors(dirs, np.array([3.0, 0.1]), TRUE_DIR[None])[
        "angular_error_deg"][0] > 4.0
    assert light_angular_errors(seen, np.array([3.0, 0.1]), TRUE_DIR[None])[
        "angular_error_deg"][0] < 1e-4
    np.testing.assert_array_equal(seen_from(dirs, None, [true]), dirs)
    np.testing.assert_array_equal(seen_from(dirs, pos, [{"direction": [0, 1, 0]}]), dirs)
