"""The viewer behind ``mi-shadowgs view`` (issue 20): its frames follow the light where the
shadows move, reuse the camera's G-buffer and each direction's shadow map, switch shadows
off and between modes, show a run without stage 4 as geometry and segments (saying why),
and the command exits 2 on a missing run, a run without a model and a busy port."""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest
import view_fixtures

from mi_shadowgs import cli
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import angles_from_direction, direction_from_angles
from mi_shadowgs.stages.relight import viewer


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return view_fixtures.make_run(tmp_path_factory.mktemp("view"))


@pytest.fixture(scope="module")
def session(runs):
    return viewer.ViewerSession(runs[0])


def _lights(az, el=35.0, e=3.0):
    return viewer.LightState((viewer.DirectionalLight(az, el, e),))


def test_pose_round_trip_and_frame_size():
    cam = Camera.look_at([2.0, 1.5, -3.0], [0.1, 0.2, 0.3], width=160, height=90,
                         fov_x=math.radians(50))
    pos, wxyz, fov_y = viewer.pose_of_camera(cam)
    back = viewer.camera_from_pose(pos, wxyz, fov_y, 160, 90)
    np.testing.assert_allclose(back.c2w, cam.c2w, atol=1e-12)
    assert back.fov_x == pytest.approx(cam.fov_x, rel=1e-12)
    # A camera looking straight down (the quaternion's other branch).
    down = Camera.look_at([0, 3, 0], [0, 0, 0], width=8, height=8, fov_x=0.7)
    np.testing.assert_allclose(viewer.camera_from_pose(*viewer.pose_of_camera(down), 8, 8)
                               .c2w, down.c2w, atol=1e-12)
    # About N^2 pixels at the window's shape.
    assert viewer.frame_size(128, 1.0) == (128, 128)
    w, h = viewer.frame_size(128, 16 / 9)
    assert abs(w * h - 128 * 128) < 200 and w / h == pytest.approx(16 / 9, rel=0.02)
    with pytest.raises(ValueError, match="aspect"):
        viewer.frame_size(128, float("nan"))
    az, el = angles_from_direction(direction_from_angles(250.0, 33.0))
    assert (az, el) == (pytest.approx(250.0), pytest.approx(33.0))


def test_light_change_moves_the_shadows_and_reuses_the_gbuffer(session):
    cam = session.default_camera(96, 96)
    g0, m0 = session.gbuffers.rendered, session.maps.rendered
    a = session.render(cam, _lights(40.0), visibility=True)
    b = session.render(cam, _lights(160.0), visibility=True)
    assert session.gbuffers.rendered == g0 + 1  # one G-buffer for both lights
    assert b.shadow_maps_rendered == 1 and session.maps.rendered == m0 + 2
    assert session.render(cam, _lights(40.0)).shadow_maps_rendered == 0  # seen before
    lum_a = a.image.astype(np.float64).mean(-1)
    lum_b = b.image.astype(np.float64).mean(-1)
    va, vb = a.visibility[..., 0], b.visibility[..., 0]
    covered = a.alpha > 0.99
    now_lit = covered & (va == 0) & (vb == 1)
    now_dark = covered & (va == 1) & (vb == 0)
    assert now_lit.sum() > 50 and now_dark.sum() > 50  # the box's shadow moved
    # Where the shadow left the image brightens, where it arrived it darkens.
    assert np.median(lum_b[now_lit] - lum_a[now_lit]) > 20
    assert np.median(lum_b[now_dark] - lum_a[now_dark]) < -20


def test_shadows_off_is_the_unshadowed_image(session):
    cam = session.default_camera(64, 64)
    on = session.render(cam, _lights(100.0), visibility=True)
    off = session.render(cam, _lights(100.0), shadows=False, visibility=True)
    assert off.shadow_maps_rendered == 0 and np.all(off.visibility == 1)
    lum_on, lum_off = (f.image.astype(np.float64).mean(-1) for f in (on, off))
    # Occluded (V = 0) and facing the light (lit once shadows are off).
    shadowed = (on.alpha > 0.99) & (on.visibility[..., 0] == 0) & (lum_off > 30)
    assert shadowed.sum() > 20
    assert np.all(lum_off >= lum_on - 1)  # no pixel darker without shadows (+-1: rounding)
    assert np.median(lum_off[shadowed] - lum_on[shadowed]) > 20


def test_modes(session):
    cam = session.default_camera(48, 48)
    assert session.modes == viewer.MODES
    albedo = [session.render(cam, _lights(az), "albedo").image for az in (10.0, 200.0)]
    np.testing.assert_array_equal(*albedo)  # albedo does not see the light
    irr = session.render(cam, _lights(10.0), "irradiance", shadows=False)
    relit = session.render(cam, _lights(10.0), "relit", shadows=False)
    assert irr.image.max() > 200 and not np.array_equal(irr.image, relit.image)
    seg = session.render(cam, _lights(10.0), "segments").image
    covered = session.render(cam, _lights(10.0), "normals").alpha > 0.99
    colors = {tuple(c) for c in seg[covered]}
    assert len(colors) > 2  # the box's and the plane's (and blends at their edges)
    assert session.render(cam, viewer.LightState(), "relit").image.max() == 0  # no light
    with pytest.raises(ValueError, match="view mode"):
        session.render(cam, _lights(10.0), "depth")


def test_envmap_lights_and_rotation(session, tmp_path):
    from mi_shadowgs.dataset.generate import SkyConfig, sky_envmap_image
    from mi_shadowgs.io.images import write_exr

    sky = tmp_path / "sky.exr"
    write_exr(sky, sky_envmap_image(SkyConfig(sun_azimuth_deg=30.0, sun_elevation_deg=40.0)))
    cam = session.default_camera(32, 32)
    a = session.render(cam, viewer.LightState(envmap=str(sky)))
    before = session.maps.rendered
    b = session.render(cam, viewer.LightState(envmap=str(sky), envmap_rotate_deg=120.0))
    # The grid directions' maps are shared by every rotation; only the weights move.
    assert session.maps.rendered == before
    assert a.image.max() > 0 and not np.array_equal(a.image, b.image)


def test_run_without_stage_4_shows_geometry_and_segments(runs):
    s = viewer.ViewerSession(runs[1])
    assert not s.can_relight and s.modes == ("segments", "normals")
    assert "material/full/model.ply is missing" in s.relight_off
    assert s.fitted_lights() == []
    cam = s.default_camera(32, 32)
    assert s.render(cam, viewer.LightState(), "normals").image.max() > 0
    with pytest.raises(ValueError, match="relighting is off"):
        s.render(cam, _lights(10.0), "relit")


def test_view_bad_input_exits_2(tmp_path, capsys, runs):
    assert cli.main(["view", str(tmp_path / "missing")]) == 2
    assert "run folder not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert cli.main(["view", str(tmp_path / "empty"), "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "no model to view" in err and "geometry/model.ply" in err
    assert cli.main(["view", str(runs[0]), "--resolution", "4"]) == 2
    assert "--resolution must be in [16, 2048]" in capsys.readouterr().err
    assert cli.main(["view", str(runs[0]), "--light", "10,0,3"]) == 2
    assert "field elevation must be in (0, 90]" in capsys.readouterr().err
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert cli.main(["view", str(runs[0]), "--port", str(port)]) == 2
        assert f"--port {port}: cannot listen on 127.0.0.1:{port}" in capsys.readouterr().err


def test_view_command_serves_the_page_until_interrupted(runs):
    with socket.socket() as s:  # a free port (released before the viewer binds it)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "mi_shadowgs.cli", "view", str(runs[0]),
                             "--port", str(port), "--resolution", "32"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        lines = []
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if f"at http://127.0.0.1:{port}" in line:
                break
        assert any(f"at http://127.0.0.1:{port}" in x for x in lines), "".join(lines)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_view_benchmark_measures_a_run(runs, monkeypatch):
    from benchmarks import bm_view

    monkeypatch.setattr(bm_view, "FRAMES", 2)
    monkeypatch.setattr(bm_view, "WARMUP", 1)
    monkeypatch.setattr(bm_view, "TARGETS", {32: 10.0})
    row = bm_view._measure(runs[0], 32, log=lambda _m: None)
    assert row["surfels"] == 4000 and row["shadow_map_resolution"] == 128
    assert row["new_maps_per_change"] == [1, 1]  # every change a new direction
    assert len(row["frame_s"]) == 2 and 0 < row["median_s"] < 10.0 and row["met"]


def test_previews_while_changes_come_then_one_full_frame():
    import threading

    from mi_shadowgs.stages.relight.viewer_server import _ClientWorker

    calls, done = [], threading.Event()

    class Owner:
        settle_s = 0.3

        def render_for(self, client, preview, changed_at=None):
            calls.append((preview, changed_at is not None))
            if not preview:
                done.set()

    class Client:
        client_id = 7

    worker = _ClientWorker(Owner(), Client())
    worker.start()
    try:
        for _ in range(5):  # a drag: changes 50 ms apart
            worker.request()
            time.sleep(0.05)
        assert done.wait(10)
        time.sleep(0.5)  # nothing more comes once the full frame is out
    finally:
        worker.close()
    assert calls[0] == (True, True) and calls[-1][0] is False
    assert [p for p, _ in calls].count(False) == 1
