"""Real-camera intrinsics (fx != fy, principal point off the centre) in the camera, the
rasterizer and the Mitsuba sensor, against an independent float64 pinhole written here."""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster import RasterConfig, rasterize
from mi_shadowgs.core.surfels import Surfels

W, H = 64, 48
FX, FY, CX, CY = 70.0, 77.0, 36.3, 20.1
# A plane through the origin tilted about X and Y, seen from +Z (the plane's pose is chosen
# so that depth varies across the image: a wrong principal point shifts depth too).
PLANE_N = np.array([0.25, 0.35, 1.0]) / np.linalg.norm([0.25, 0.35, 1.0])
HALF = (0.8, 0.6)  # half extents of the rectangle in its tangent axes


def _camera(**kw) -> Camera:
    c2w = np.eye(4)
    c2w[:3, 3] = [0.1, -0.05, 3.0]  # OpenGL: looks down -Z towards the plane
    return Camera.from_intrinsics(c2w, W, H, FX, FY, CX, CY, **kw)


def _tangents():
    t_u = np.cross([0.0, 1.0, 0.0], PLANE_N)
    t_u /= np.linalg.norm(t_u)
    return t_u, np.cross(PLANE_N, t_u)


def _plane_surfels(spacing=0.02) -> Surfels:
    t_u, t_v = _tangents()
    a = np.arange(-HALF[0] + spacing / 2, HALF[0], spacing)
    b = np.arange(-HALF[1] + spacing / 2, HALF[1], spacing)
    aa, bb = np.meshgrid(a, b)
    pos = aa.reshape(-1, 1) * t_u + bb.reshape(-1, 1) * t_v  # [N, 3]
    rot = np.column_stack([t_u, t_v, PLANE_N])
    # rotation matrix -> quaternion (w, x, y, z); trace is positive for this pose
    w = 0.5 * math.sqrt(1.0 + np.trace(rot))
    q = [w, (rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w),
         (rot[1, 0] - rot[0, 1]) / (4 * w)]
    n = len(pos)
    return Surfels.from_numpy(pos, np.full((n, 2), 0.6 * spacing), np.tile(q, (n, 1)),
                              np.full(n, 0.99))


def _reference(fx, fy, cx, cy):
    """Float64 pinhole written from the maths: per pixel centre, the ray's hit on the plane
    (z-depth of the unbounded plane [H, W], and whether it hits the rectangle [H, W])."""
    origin = np.array([0.1, -0.05, 3.0])
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    # CV camera frame (+Y down, +Z forward) -> world for a camera looking down world -Z
    d = np.stack([(xs - cx) / fx, -(ys - cy) / fy, -np.ones_like(xs)], -1)  # [H, W, 3]
    t = -(origin @ PLANE_N) / (d @ PLANE_N)  # ray parameter = z-depth (d has unit z)
    hit = origin + t[..., None] * d
    t_u, t_v = _tangents()
    inside = (np.abs(hit @ t_u) < HALF[0]) & (np.abs(hit @ t_v) < HALF[1])
    return t, inside


def _centroid(weights):
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    return np.array([(weights * xs).sum(), (weights * ys).sum()]) / weights.sum()


def test_plane_depth_lands_within_half_a_pixel():
    cam = _camera()
    out = rasterize(_plane_surfels(), cam, None, aovs=("alpha", "depth"),
                    config=RasterConfig())
    alpha = np.array(out["alpha"], np.float64)[..., 0]
    depth = np.array(out["depth"], np.float64)[..., 0]
    ref_depth, inside = _reference(FX, FY, CX, CY)
    # Where the plane is solid (away from the soft Gaussian rim) the expected z-depth is the
    # plane's; an error in depth over the plane's depth gradient is a shift in pixels.
    solid = alpha > 0.95
    assert solid.sum() > 0.5 * inside.sum()
    gy, gx = np.gradient(ref_depth)
    px_err = np.abs(depth[solid] - ref_depth[solid]) / np.hypot(gx, gy)[solid]
    assert np.all(inside[solid])
    # Median, not max: a surfel grid's depth ripples by a fraction of its spacing.
    assert np.median(px_err) < 0.5, np.median(px_err)
    # The silhouette: the alpha-weighted centroid against the reference coverage's centroid.
    # The splats' soft rim is symmetric to first order, so 0.5 px is a shift, not blur.
    err = np.abs(_centroid(alpha) - _centroid(inside.astype(float)))
    assert np.all(err < 0.5), err
    # The check can fail: the same camera with the principal point at the centre (what
    # the rasterizer did before) lands more than a pixel away.
    centred = Camera.from_intrinsics(cam.c2w, W, H, FX, FY, W / 2, H / 2)
    alpha_c = np.array(rasterize(_plane_surfels(), centred, None, aovs=("alpha",))["alpha"],
                       np.float64)[..., 0]
    assert np.abs(_centroid(alpha_c) - _centroid(inside.astype(float))).max() > 1.0


def test_project_unproject_use_the_intrinsics():
    cam = _camera()
    rng = np.random.default_rng(0)
    pix = rng.uniform(0, [W, H], size=(50, 2))
    z = rng.uniform(1, 4, size=50)
    world = cam.unproject(pix, z)
    back, zz = cam.project(world)
    np.testing.assert_allclose(back, pix, atol=1e-9)
    np.testing.assert_allclose(zz, z, atol=1e-12)
    # independent: a point on the optical axis lands on (cx, cy)
    uv, _ = cam.project(np.array([[0.1, -0.05, 0.0]]))
    np.testing.assert_allclose(uv[0], [CX, CY], atol=1e-12)


def test_lookup_reads_the_pixel_each_point_falls_in():
    """``Camera.lookup`` against the pinhole written out here: a point at pixel (x + fx_, y +
    fy_) (fractions in [0, 1)) reads image[y, x]; points behind the camera or off the image
    read zero and are not inside."""
    cam = _camera()
    origin = np.array([0.1, -0.05, 3.0])
    rng = np.random.default_rng(1)
    image = rng.uniform(0.1, 1.0, size=(H, W, 3))  # [H, W, 3], no zero in it
    xs, ys = rng.integers(0, W, 40), rng.integers(0, H, 40)
    frac = rng.uniform(0.05, 0.95, size=(40, 2))  # away from the pixels' edges
    u, v = xs + frac[:, 0], ys + frac[:, 1]
    depth = rng.uniform(0.5, 5.0, 40)
    # CV pixel -> world for a camera at ``origin`` looking down world -Z (as _reference)
    on_image = origin + depth[:, None] * np.stack([(u - CX) / FX, -(v - CY) / FY,
                                                   -np.ones(40)], -1)
    behind = origin + np.array([[0.0, 0.0, 1.0], [0.2, 0.1, 2.0]])
    off_image = origin + 2.0 * np.array([[(W + 3 - CX) / FX, 0.0, -1.0],
                                         [0.0, -(-4 - CY) / FY, -1.0]])
    pts = np.concatenate([on_image, behind, off_image])  # [44, 3]
    values, inside = cam.lookup(image, pts)
    assert values.shape == (44, 3) and values.dtype == image.dtype
    np.testing.assert_array_equal(inside, [True] * 40 + [False] * 4)
    np.testing.assert_array_equal(values[:40], image[ys, xs])
    assert not values[40:].any()
    mask = image[..., 0] > 0.5  # [H, W] bool: a bool mask reads as bool
    hit, inside = cam.lookup(mask, pts)
    assert hit.dtype == bool
    np.testing.assert_array_equal(hit[:40], mask[ys, xs])
    assert not hit[40:].any()


def test_with_size_scales_intrinsics_and_refusals():
    cam = _camera().with_size(2 * W, 2 * H)
    assert cam.focal_xy == pytest.approx((2 * FX, 2 * FY))
    assert cam.principal_point == pytest.approx((2 * CX, 2 * CY))
    with pytest.raises(ValueError, match="focal_y"):
        _camera().to_mitsuba_dict()
    with pytest.raises(ValueError, match="focal_y"):
        Camera(c2w=np.eye(4), width=4, height=4, ortho_width=1.0, focal_y=3.0)
    with pytest.raises(ValueError, match="cx"):
        Camera(c2w=np.eye(4), width=4, height=4, fov_x=1.0, cx=float("nan"))


def test_mitsuba_sensor_offset_matches_projection():
    """The principal-point offset given to Mitsuba puts a ray-traced rectangle where the
    camera's own projection says (sign and units of Mitsuba's offsets)."""
    c2w = np.eye(4)
    c2w[:3, 3] = [0.1, -0.05, 3.0]
    cam = Camera.from_intrinsics(c2w, W, H, FX, FX, CX, CY)
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "aov", "aovs": "dd:depth"},
        "sensor": cam.to_mitsuba_dict(spp=16),
        "plane": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().scale([0.3, 0.2, 1.0])},
    })
    img = np.array(mi.render(scene), np.float64)
    cover = img[..., -1] > 0
    ref_depth, inside = _reference_flat(cam)
    err = np.abs(_centroid(cover.astype(float)) - _centroid(inside.astype(float)))
    assert np.all(err < 0.5), err


def _reference_flat(cam):
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    fx, _ = cam.focal_xy
    x = (xs - CX) / fx * 3.0 + 0.1  # world point on z = 0 (camera at z = 3, looking down -Z)
    y = -(ys - CY) / fx * 3.0 - 0.05
    inside = (np.abs(x) < 0.3) & (np.abs(y) < 0.2)
    return np.where(inside, 3.0, 0.0), inside


# -- nerfstudio transforms: intrinsics and k1 distortion through the loader ----------------
K1 = -0.9  # strong barrel: the raw photo's edges sit 0.8 px off the pinhole's (0.13 undistorted)


def _distorted_photo(ss=4):
    """RGBA [H, W, 4] uint8 of the plane seen through the distorted lens, alpha = coverage
    from ``ss`` x ``ss`` samples per pixel: each sample's ray is found by inverting the
    radial model by fixed-point iteration (the project's code only distorts forward)."""
    ys, xs = (np.mgrid[0:H * ss, 0:W * ss] + 0.5) / ss
    xd, yd = (xs - CX) / FX, (ys - CY) / FY
    x, y = xd.copy(), yd.copy()
    for _ in range(50):
        d = 1.0 + K1 * (x * x + y * y)
        x, y = xd / d, yd / d
    origin = np.array([0.1, -0.05, 3.0])
    ray = np.stack([x, -y, -np.ones_like(x)], -1)
    t = -(origin @ PLANE_N) / (ray @ PLANE_N)
    hit = origin + t[..., None] * ray
    t_u, t_v = _tangents()
    inside = (np.abs(hit @ t_u) < HALF[0]) & (np.abs(hit @ t_v) < HALF[1])
    img = np.zeros((H, W, 4), np.uint8)
    img[..., :3] = 200
    img[..., 3] = np.round(255 * inside.reshape(H, ss, W, ss).mean(axis=(1, 3)))
    return img


def _pinhole_coverage(ss=4):
    """[H, W] bool: pixels more than half covered by the plane in the pinhole view."""
    ys, xs = (np.mgrid[0:H * ss, 0:W * ss] + 0.5) / ss
    origin = np.array([0.1, -0.05, 3.0])
    ray = np.stack([(xs - CX) / FX, -(ys - CY) / FY, -np.ones_like(xs)], -1)
    hit = origin + (-(origin @ PLANE_N) / (ray @ PLANE_N))[..., None] * ray
    t_u, t_v = _tangents()
    inside = (np.abs(hit @ t_u) < HALF[0]) & (np.abs(hit @ t_v) < HALF[1])
    return inside.reshape(H, ss, W, ss).mean(axis=(1, 3)) > 0.5


def _edge_error(mask, ref):
    """Mean boundary displacement in pixels: symmetric difference area over perimeter."""
    perimeter = np.count_nonzero(ref ^ np.roll(ref, 1, 0)) + np.count_nonzero(
        ref ^ np.roll(ref, 1, 1))
    return np.count_nonzero(mask ^ ref) / perimeter


def _nerfstudio_folder(root, **extra):
    from mi_shadowgs.io.images import write_png

    (root / "train").mkdir(parents=True, exist_ok=True)
    write_png(root / "train" / "r_0.png", _distorted_photo())
    c2w = np.eye(4)
    c2w[:3, 3] = [0.1, -0.05, 3.0]
    meta = {"w": W, "h": H, "fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "k1": K1,
            "camera_model": "OPENCV", "world_up": "+y",
            "frames": [{"file_path": "train/r_0.png", "transform_matrix": c2w.tolist()}]}
    meta.update(extra)
    import json

    (root / "transforms_train.json").write_text(json.dumps(meta))


def test_nerfstudio_intrinsics_and_k1_render_the_plane_in_place(tmp_path):
    from mi_shadowgs.dataset.loader import load_dataset

    _nerfstudio_folder(tmp_path)
    view = load_dataset(tmp_path, "train").views[0]
    cam = view.camera
    assert cam.focal_xy == pytest.approx((FX, FY)) and cam.principal_point == \
        pytest.approx((CX, CY))
    ref = _pinhole_coverage()  # the pinhole view of the plane
    # The undistorted photo's mask sits where the pinhole says ...
    assert _edge_error(view.mask, ref) < 0.5
    # ... and the raw photo did not (the check can fail).
    assert _edge_error(_distorted_photo()[..., 3] > 127, ref) > 0.5
    # The rasterized plane, seen by the loaded camera, lands on the undistorted mask.
    alpha = np.array(rasterize(_plane_surfels(), cam, None, aovs=("alpha",))["alpha"],
                     np.float64)[..., 0]
    assert _edge_error(alpha > 0.5, view.mask) < 0.5
    assert _edge_error(alpha > 0.5, ref) < 0.5


@pytest.mark.parametrize("extra, field", [
    ({"cx": 70.0}, "'cx'"),
    ({"fl_y": -3.0}, "'fl_y'"),
    ({"camera_model": "OPENCV_FISHEYE"}, "'camera_model'"),
    ({"world_up": "up"}, "'world_up'"),
    ({"k2": "big"}, "'k2'"),
])
def test_nerfstudio_bad_intrinsics_name_the_field(tmp_path, extra, field):
    from mi_shadowgs.dataset.loader import DatasetError, load_dataset

    _nerfstudio_folder(tmp_path, **extra)
    with pytest.raises(DatasetError, match=field):
        load_dataset(tmp_path, "train")
