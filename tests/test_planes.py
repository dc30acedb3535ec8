"""Planar segments (stages/segmentation/planes.py): the plane fit against a float64 SVD
reference, the shading normals of a planar segment beside a curved one and off-plane
outliers, the shading's use of them (core/shading.py), and the split of colour segments
at the support's plane."""

from __future__ import annotations

import numpy as np
import pytest

from mi_shadowgs.core.frames import frame_to_quaternion, quaternion_to_matrix
from mi_shadowgs.core.shading import SHADING_NORMAL_CHANNEL
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.stages.segmentation.planes import (
    PlaneConfig,
    fit_plane,
    planar_shading_normals,
    support_split,
    support_split_applies,
)

ON = PlaneConfig(enabled=True)


def _tilted(normals: np.ndarray, max_deg: float, rng) -> np.ndarray:
    """``normals`` [m, 3] each tilted by up to ``max_deg`` in a random direction."""
    t = rng.normal(size=normals.shape)
    t -= (t * normals).sum(1, keepdims=True) * normals
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    a = np.radians(rng.uniform(0, max_deg, len(normals)))[:, None]
    return np.cos(a) * normals + np.sin(a) * t


def _scene(rng):
    """Segment 0: a tilted plane of 600 surfels (centres 0.2 std-dev off it, normals up to
    30 deg off) with 60 off-plane outliers (an object's side touching it: normals in the
    plane, centres up to 0.5 above); segment 1: a sphere of 400 surfels."""
    up = np.array([0.1, 1.0, -0.2])
    up /= np.linalg.norm(up)
    t1 = np.cross(up, [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(up, t1)
    sigma = 0.03
    uv = rng.uniform(-1, 1, (600, 2))
    plane_p = uv[:, :1] * t1 + uv[:, 1:] * t2 + 0.2 * sigma * rng.normal(size=(600, 1)) * up
    plane_n = _tilted(np.tile(up, (600, 1)), 30.0, rng)
    out_p = rng.uniform(-0.3, 0.3, (60, 1)) * t1 + rng.uniform(0.05, 0.5, (60, 1)) * up
    out_n = np.tile(t2, (60, 1))
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sphere_p = np.array([3.0, 0.5, 0.0]) + 0.5 * d
    pos = np.concatenate([plane_p, out_p, sphere_p])
    nrm = np.concatenate([plane_n, out_n, d])
    n = len(pos)
    opacity = rng.uniform(0.2, 0.95, n)
    surfels = Surfels.from_numpy(pos, np.full((n, 2), sigma), frame_to_quaternion(nrm),
                                 opacity, {"albedo": rng.uniform(0, 1, (n, 3))})
    segments = np.array([0] * 660 + [1] * 400)
    return surfels, segments, up


def test_fit_plane_matches_a_float64_svd():
    rng = np.random.default_rng(1)
    surfels, _, up = _scene(rng)
    a = surfels.to_numpy()
    p, w = a["position"][:600], a["opacity"][:600]
    n = quaternion_to_matrix(a["rotation"][:600])[:, :, 2]
    fit = fit_plane(p, n, w, distance=1.0, max_angle_deg=90.0, iterations=1)
    # Reference: the weighted centroid and the least singular vector of the weighted
    # deviations (float64 SVD).
    c = (w[:, None] * p).sum(0) / w.sum()
    ref = np.linalg.svd(np.sqrt(w)[:, None] * (p - c))[2][-1]
    np.testing.assert_allclose(fit.point, c, rtol=0, atol=1e-12)
    assert abs(abs(fit.normal @ ref) - 1.0) < 1e-12
    assert abs(abs(fit.normal @ up) - 1.0) < 1e-3  # noise of 0.2 sigma over a 2x2 plane
    assert fit.inliers.all() and fit.inlier_share == pytest.approx(1.0)


def test_planar_segment_gets_the_plane_normal_and_the_rest_is_kept():
    rng = np.random.default_rng(2)
    surfels, segments, up = _scene(rng)
    out, reports = planar_shading_normals(surfels, segments, ON)
    by_segment = {r["segment"]: r for r in reports}
    assert by_segment[0]["planar"] and not by_segment[1]["planar"]
    assert by_segment[1]["inlier_share"] < 0.2 and by_segment[1]["flattened"] == 0
    plane_n = np.asarray(by_segment[0]["normal"])
    assert abs(abs(plane_n @ up) - 1.0) < 1e-3
    before = surfels.to_numpy()
    n_b = quaternion_to_matrix(before["rotation"])[:, :, 2]
    shading_n = np.array(out.channels[SHADING_NORMAL_CHANNEL], np.float64)
    changed = np.flatnonzero(np.any(np.abs(shading_n - n_b) > 1e-6, axis=1))
    # Every plane surfel is an inlier (0.2 sigma off, <= 30 deg tilt); no outlier is.
    np.testing.assert_array_equal(changed, np.arange(600))
    assert by_segment[0]["flattened"] == 600
    # The plane's normal on each one's own side; the others keep their own (float32).
    np.testing.assert_allclose(shading_n[:600], np.sign(n_b[:600] @ plane_n)[:, None] *
                               plane_n, atol=1e-6)
    np.testing.assert_allclose(shading_n[600:], n_b[600:], atol=1e-6)
    # The geometry and every other channel, bit for bit.
    for name in ("position", "log_scale", "rotation", "opacity_logit"):
        np.testing.assert_array_equal(np.array(getattr(out, name)),
                                      np.array(getattr(surfels, name)))
    np.testing.assert_array_equal(np.array(out.channels["albedo"]),
                                  np.array(surfels.channels["albedo"]))


def test_shading_uses_the_shading_normals():
    """pixel_geometry and facing_normals read SHADING_NORMAL_CHANNEL when the model has
    it: the surfels' own normals in it give the rasterized normals (the same blend), other
    normals change only the normals, not alpha, depth or points."""
    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.core import shading
    from mi_shadowgs.core.camera import Camera

    rng = np.random.default_rng(5)
    surfels, _, up = _scene(rng)
    cam = Camera.look_at([0.3, 2.5, 2.0], [0.0, 0.0, 0.0], width=48, height=40, fov_x=0.9)
    plain = shading.pixel_geometry(surfels, cam)
    a = surfels.to_numpy()
    own = quaternion_to_matrix(a["rotation"])[:, :, 2]
    ch = dict(surfels.channels)
    ch[SHADING_NORMAL_CHANNEL] = mi.TensorXf(own.astype(np.float32))
    same = shading.pixel_geometry(type(surfels)(surfels.position, surfels.log_scale,
                                                surfels.rotation, surfels.opacity_logit, ch),
                                  cam)
    for k in range(3):
        np.testing.assert_allclose(np.array(same.normal[k]), np.array(plain.normal[k]),
                                   atol=2e-6)
    ch[SHADING_NORMAL_CHANNEL] = mi.TensorXf(np.tile(up, (surfels.count, 1)).astype(np.float32))
    flat_model = type(surfels)(surfels.position, surfels.log_scale, surfels.rotation,
                               surfels.opacity_logit, ch)
    flat = shading.pixel_geometry(flat_model, cam)
    covered = np.array(flat.alpha) > 0.5
    assert covered.sum() > 200
    n = np.stack([np.array(flat.normal[k]) for k in range(3)], -1)[covered]
    facing = np.where((n @ up)[:, None] >= 0, up, -up)
    np.testing.assert_allclose(n, facing, atol=1e-5)  # every surfel's shading normal +-up
    np.testing.assert_array_equal(np.array(flat.alpha), np.array(plain.alpha))
    np.testing.assert_array_equal(np.array(flat.depth), np.array(plain.depth))
    fn = shading.facing_normals(flat_model, cam)
    assert np.allclose(np.abs(np.stack([np.array(fn[k]) for k in range(3)], -1) @ up), 1.0,
                       atol=1e-6)
    assert dr.width(fn) == surfels.count


def test_off_small_and_bad_settings():
    rng = np.random.default_rng(3)
    surfels, segments, _ = _scene(rng)
    same, reports = planar_shading_normals(surfels, segments, PlaneConfig())
    assert same is surfels and reports == []  # off: the paper's stage 2
    few, reports = planar_shading_normals(
        surfels, segments, PlaneConfig(enabled=True, min_surfels=1000))
    assert few is surfels and reports == []
    with pytest.raises(ValueError, match="segment ids for"):
        planar_shading_normals(surfels, segments[:10], ON)
    for bad in ({"distance_scales": 0.0}, {"max_angle_deg": 0.0}, {"min_inlier_share": 1.5},
                {"iterations": 0}):
        with pytest.raises(ValueError, match="PlaneConfig"):
            PlaneConfig(enabled=True, **bad)


def test_segments_split_at_the_support_plane_and_only_there():
    # One colour segment for a grey object standing on a grey mat (the tilted plane of
    # ``_scene``, its off-plane outliers and the sphere all labelled 0), a second on the mat
    # alone: the object's surfels leave both; the plane found is the mat's.
    rng = np.random.default_rng(7)
    surfels, _, up = _scene(rng)
    pos = surfels.to_numpy()["position"]
    seg = np.zeros(len(pos), int)
    seg[:300] = 1  # half the mat
    split, report = support_split(pos, seg)
    assert report["segments_before"] == 2 and report["segments_after"] == 3
    assert abs(abs(np.dot(report["normal"], up)) - 1) < 1e-3
    assert report["share"] == pytest.approx(600 / len(pos), abs=0.02)
    mat, obj = np.arange(len(pos)) < 600, np.arange(len(pos)) >= 660
    assert len(np.unique(split[mat & (seg == 1)])) == 1  # each mat part one segment ...
    assert len(np.unique(split[mat & (seg == 0)])) == 1
    assert set(split[obj]).isdisjoint(split[mat])  # ... and the sphere none of them
    # without a dominant plane (the sphere alone) nothing is split
    sphere = pos[660:]
    same, none = support_split(sphere, np.zeros(len(sphere), int))
    assert none is None and np.array_equal(same, np.zeros(len(sphere), int))


@pytest.mark.parametrize("mode, segments, split", [
    ("auto", 1, True), ("auto", 2, False), ("on", 1, True), ("on", 3, True),
    ("off", 1, False), ("off", 2, False)])
def test_support_split_applies_where_colour_found_one_segment(mode, segments, split):
    # "auto": a grey object on a grey mat is one colour segment, split at the mat's plane;
    # where colour told the objects apart it is trusted (docs/decisions.md)
    assert support_split_applies(mode, segments) is split
    # a count the user set (``n_segments``, ``run --segments``) is kept as asked under "auto"
    assert support_split_applies(mode, segments, forced=True) is (mode == "on")


def test_support_split_setting_is_checked():
    from mi_shadowgs.config import ConfigError
    from mi_shadowgs.stages.segmentation.features import SegmentationConfig

    assert SegmentationConfig().support_split == "auto"
    with pytest.raises((ConfigError, ValueError), match="support_split"):
        SegmentationConfig(support_split="yes")
    with pytest.raises(ValueError, match="support_split"):
        support_split_applies("true", 1)


def test_a_run_recorded_with_the_old_switch_reads_as_on_or_off():
    from mi_shadowgs.config import recorded_config
    from mi_shadowgs.stages.segmentation.features import SegmentationConfig

    for old, now in ((False, "off"), (True, "on")):
        cfg = recorded_config(SegmentationConfig, {"support_split": old}, None)
        assert cfg.support_split == now
