"""Lab capture conditions in the generator (``dataset/capture.py``, ``dataset/photos.py``):
the lamp's ground truth against Mitsuba's own rendering of the same lamp and against a
float64 reference, the photos' recorded gains, and the bad inputs.

Small images and few views keep the file to seconds on 2 cores.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.ndimage import maximum_filter, minimum_filter

from mi_shadowgs.cli import main as cli_main
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.generate import ViewRenderer, camera_rays, trace_ground_truth
from mi_shadowgs.dataset.scene import dataset_scene, load_scene
from mi_shadowgs.scenes import scene_path

SIZE = 64
# A sphere lamp near the sphere_plane scene's ball (object radius 0.866: the bounding
# sphere of its bounding box): a penumbra ~5 pixels wide on the plane.
SOFT_LAMP = {"lamp_azimuth": "30", "lamp_elevation": "50", "lamp_distance": "4",
             "lamp_radius": "0.5", "lamp_irradiance": "3"}


def _shadow_camera(setup) -> Camera:
    lamp = setup.lights[0]
    c = np.array([0.0, 1.0, 0.0])
    to_c = c - np.array(lamp.position)
    shadow_c = c + c[1] / -to_c[1] * to_c  # where the ball's centre falls on y = 0
    return Camera.look_at(shadow_c + np.array([0.8, 3.5, 1.5]), shadow_c, fov_x=0.9,
                          width=SIZE, height=SIZE)


def _direct(setup, cam, spp: int) -> np.ndarray:
    """Mitsuba's direct light only (paths of one bounce), linear RGB [H, W, 3]."""
    renderer = ViewRenderer(cam, spp=spp, max_depth=2, sampler="independent")
    return renderer.render(setup.path_traced, cam, seed=5)[..., :3]


@pytest.mark.parametrize("radius", ["0", "0.5"])
def test_lamp_visibility_matches_mitsuba_rendering_of_the_lamp(radius):
    """On the plane under the ball, Mitsuba's direct light from the true lamp (a ``point``
    emitter, or the ``sphere`` area emitter) divided by the unshadowed radiance
    albedo / pi * I cos / r^2 is the lamp's visible share: it matches the ground truth's
    visibility (hard for the point, soft for the sphere)."""
    setup = load_scene(scene_path("sphere_plane"), {**SOFT_LAMP, "lamp_radius": radius})
    cam = _shadow_camera(setup)
    gt = trace_ground_truth(setup, [cam])
    img = _direct(setup, cam, spp=256)
    base = gt["material"][0] == setup.base_id
    # unshadowed irradiance at each base pixel from float64 geometry
    o, d, _ = camera_rays([cam])
    p = o + (-o[:, 1] / d[:, 1])[:, None] * d
    to = np.array(setup.lights[0].position) - p
    r2 = np.sum(to * to, -1)
    free = (3.0 * setup.lights[0].distance**2 * to[:, 1] / np.sqrt(r2) / r2).reshape(SIZE, SIZE)
    share = img[..., 0] / (0.5 / np.pi * free)  # base albedo 0.5
    hard, soft = gt["visibility"][0][..., 0], gt["visibility_soft"][0][..., 0]
    # away from the ball's silhouette (the pixel footprint straddles it)
    keep = base & (minimum_filter(base, 3) > 0)
    shadow_gt, shadow_mi = keep & (hard < 0.5), keep & (share < 0.5)
    iou = np.sum(shadow_gt & shadow_mi) / np.sum(shadow_gt | shadow_mi)
    print(f"lamp radius {radius}: shadow IoU {iou:.3f}")
    assert shadow_gt.sum() > 200
    if radius == "0":
        assert np.all(soft == hard)
        # the point's edge: only pixels whose footprint straddles it differ
        assert iou >= 0.95
        inner = keep & (minimum_filter(hard, 3) == maximum_filter(hard, 3))
        assert np.abs(share[inner] - hard[inner]).max() < 0.01
        return
    assert not np.array_equal(soft, hard)
    penumbra = keep & (soft > 0.05) & (soft < 0.95)
    assert penumbra.sum() > 60  # a band a few pixels wide around the shadow
    err = np.abs(share - soft)
    print(f"penumbra pixels {penumbra.sum()}: mean |share - soft| {err[penumbra].mean():.4f}, "
          f"|share - hard| {np.abs(share - hard)[penumbra].mean():.4f}; all base "
          f"{err[keep].mean():.4f}")
    # 16 points on the lamp's disc quantise the share to 1/16; Mitsuba's 256 samples have a
    # std of <= 0.03 in the penumbra; pixel footprints add ~0.05 across its ~5 pixels.
    assert err[penumbra].mean() < 0.06
    assert err[keep].mean() < 0.01
    # the hard test of the centre would be off by a third of the lamp across the penumbra
    assert np.abs(share - hard)[penumbra].mean() > 0.15
    assert iou >= 0.9


def test_lamp_irradiance_falls_off_as_inverse_square_on_the_base():
    """The ground truth's irradiance on the flat base against a float64 reference
    E_c D^2 max(0, n . l) / r^2, l and r from each pixel to the lamp's centre."""
    setup = load_scene(scene_path("default"),
                       {"lamp_distance": "6", "lamp_elevation": "35", "lamp_azimuth": "80",
                        "lamp_irradiance": "2, 3, 4"})
    lamp = setup.lights[0]
    assert lamp.distance == pytest.approx(6.0 * setup.object_radius)
    cam = Camera.look_at((0.01, 7.0, 0.02), (0.0, 0.0, 0.0), fov_x=0.55, width=SIZE,
                         height=SIZE)
    gt = trace_ground_truth(setup, [cam])
    ok = ((gt["material"][0] == setup.base_id) & (gt["visibility"][0][..., 0] > 0.5)).ravel()
    assert ok.sum() > 1500  # the base around the object and its shadow
    o, d, _ = camera_rays([cam])
    p = o + (-o[:, 1] / d[:, 1])[:, None] * d  # [M, 3] on y = 0
    to = np.array(lamp.position) - p
    r2 = np.sum(to * to, -1)
    cos = to[:, 1] / np.sqrt(r2)
    ref = np.array([2.0, 3.0, 4.0]) * (lamp.distance**2 * cos / r2)[:, None]  # [M, 3]
    got = gt["irradiance"][0][..., 0, :].reshape(-1, 3).astype(np.float64)
    rel = np.abs(got[ok] - ref[ok]) / ref[ok]
    print(f"irradiance on the base: max relative error {rel.max():.2e} over {ok.sum()} px")
    assert rel.max() < 1e-4
    # across the base the lamp's irradiance changes by far more than that: the same
    # cosine without the fall-off (a directional light of the lamp's direction at p) misses
    no_falloff = np.array([2.0, 3.0, 4.0]) * cos[:, None]
    assert (np.abs(no_falloff[ok] - ref[ok]) / ref[ok]).max() > 0.3


def _run(argv, capsys):
    rc = cli_main(["generate", *argv])
    return rc, capsys.readouterr()


TINY = ["--width", "48", "--height", "48", "--n-train", "4", "--n-test", "1", "--spp", "16",
        "--envmap", "none", "--no-progress"]


def test_lab_photos_record_and_apply_their_gains(tmp_path, capsys):
    """A lab capture's photo divided by its recorded gains is the view's render (with the
    room light behind it) within the noise and the JPEG's loss."""
    from mi_shadowgs.io.images import read_exr, read_png, srgb_to_linear

    out = tmp_path / "lab"
    rc, cap = _run(["default", "--out", str(out), "-D", "capture=lab", "--photos", *TINY],
                   capsys)
    assert rc == 0, cap.err
    gains = json.loads((out / layout.PHOTOS / layout.PHOTO_GAINS).read_text())
    assert gains["jpeg_quality"] == 90 and gains["photo_ev"] == 0.35
    room = np.array(gains["room_radiance"])
    assert room == pytest.approx([0.03] * 3)
    ratios, spread = [], []
    for split, n in (("train", 4), ("test", 1)):
        for i in range(n):
            name = layout.photo_name(split, i)
            g = gains["photos"][name]
            assert abs(g["ev"]) <= 0.35 and np.all(np.abs(np.array(g["white_balance"]) - 1)
                                                   <= 0.04)
            assert g["gain"] == pytest.approx(2.0 ** g["ev"] * np.array(g["white_balance"]))
            photo = srgb_to_linear(read_png(out / layout.PHOTOS / name)[..., :3] / 255.0)
            rgba = read_exr(out / (layout.view_stem(split, i) + layout.IMAGE_EXR))
            ref = rgba[..., :3] + (1 - rgba[..., 3:]) * room
            use = (read_png(out / layout.PHOTOS / name)[..., :3].max(-1) < 250) & \
                (ref.min(-1) > 0.02)
            assert use.sum() > 1000
            dev = photo[use] / np.array(g["gain"])
            ratios.append(dev.sum(0) / ref[use].sum(0))  # per channel
            spread.append(photo[use].sum(0) / ref[use].sum(0))
            # per pixel: noise ~1-3% and JPEG quantisation at quality 90
            assert np.median(np.abs(dev - ref[use]) / ref[use]) < 0.05
    ratios, spread = np.array(ratios), np.array(spread)
    assert np.abs(ratios - 1).max() < 0.02
    # the photos themselves differ by their gains, far beyond that
    assert spread.max() / spread.min() > 1.15
    # the ground truth: the lamp in lights.json, its soft visibility, the room light
    lights = json.loads((out / layout.LIGHTS_JSON).read_text())["training"]
    (lamp,) = lights["lights"]
    assert lamp["type"] == "lamp" and lamp["radius"] == pytest.approx(0.15)
    assert lamp["distance"] == pytest.approx(6.0)
    assert lamp["intensity"] == pytest.approx([3.0 * 36.0] * 3)
    centre = np.array(json.loads((out / layout.DATASET_JSON).read_text())["object"]["center"])
    assert np.linalg.norm(np.array(lamp["position"]) - centre) == pytest.approx(6.0)
    assert lights["room"]["radiance"] == pytest.approx([0.03] * 3)
    assert (out / (layout.view_stem("train", 0) + layout.VISIBILITY_SOFT)).is_file()
    # the dataset's scene reloads with its lamp, for the validations that trace it
    again = dataset_scene(out)
    assert again.lights[0].position == pytest.approx(tuple(lamp["position"]))


def test_plain_scenes_record_no_capture():
    setup = load_scene(scene_path("default"))
    assert not any(k.startswith(("lamp_", "room_", "photo_", "capture")) for k in setup.params)
    assert setup.render_scene is None and not setup.capture.jitters_photos
    assert [lt.is_lamp for lt in setup.lights] == [False, False]
    assert "type" not in setup.lights[0].to_json()


@pytest.mark.parametrize("define, named", [
    ("lamp_distance=0.9", "inside the object"),
    ("lamp_distance=nan", "'lamp_distance'"),
    ("capture=studio", "'capture'"),
    ("lamp_radius=0.2", "need 'lamp_distance'"),
])
def test_bad_capture_parameters_exit_2(tmp_path, capsys, define, named):
    rc, cap = _run(["default", "--out", str(tmp_path / "out"), "-D", define, *TINY], capsys)
    lines = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and named in lines[0], cap.err
    assert not any(tmp_path.iterdir())  # nothing written


@pytest.mark.parametrize("defines, named", [
    ({"lamp_elevation": "-20"}, "below the base"),
    ({"lamp_elevation": "-5", "lamp_distance": "12"}, "below the base"),
    ({"lamp_radius": "-0.1"}, "'lamp_radius'"),
    ({"lamp_radius": "5.5"}, "inside the object"),
    ({"lamp_irradiance": "0"}, "'lamp_irradiance'"),
    ({"lamp_irradiance": "1, 2"}, "'lamp_irradiance'"),
    ({"room_radiance": "-0.1"}, "'room_radiance'"),
    ({"photo_ev": "-1"}, "'photo_ev'"),
    ({"photo_wb": "0.9"}, "'photo_wb'"),
    ({"photo_noise": "x"}, "'photo_noise'"),
    ({"photo_jpeg": "0"}, "'photo_jpeg'"),
    ({"photo_jpeg": "80.5"}, "'photo_jpeg'"),
])
def test_bad_lamp_and_photo_parameters_are_named(defines, named):
    from mi_shadowgs.dataset.scene import SceneError

    with pytest.raises(SceneError, match=named):
        load_scene(scene_path("default"), {"lamp_distance": "6", **defines})


def test_a_lamp_whose_sphere_dips_below_the_base_is_refused():
    """Its centre above y = 0, its sphere not."""
    from mi_shadowgs.dataset.scene import SceneError

    centre_y = load_scene(scene_path("default")).object_center[1]
    el = np.degrees(np.arcsin((0.1 - centre_y) / 6.0))  # centre at y = 0.1 < radius 0.2
    with pytest.raises(SceneError, match="below the base"):
        load_scene(scene_path("default"), {"lamp_distance": "6", "lamp_radius": "0.2",
                                           "lamp_elevation": f"{el:.6f}"})
    load_scene(scene_path("default"), {"lamp_distance": "6", "lamp_radius": "0.05",
                                       "lamp_elevation": f"{el:.6f}"})
