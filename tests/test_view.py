"""The viewer behind ``mi-shadowgs view``: its frames follow the light where the
shadows move, reuse the camera's G-buffer and each direction's shadow map, switch shadows
off and between modes, show a run without stage 4 as geometry and segments (saying why),
and the command exits 2 on a missing run, a run without a model and a busy port."""

from __future__ import annotations

import math
import os
import shutil
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
from mi_shadowgs.stages.viewer import viewer


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
    # Every camera move a new G-buffer (full frame and preview), a light change none.
    assert row["gbuffers_per_move"] == 1 and row["gbuffers_per_light_change"] == 0
    assert len(row["camera_move_s"]) == bm_view.MOVES == len(row["camera_move_preview_s"])
    assert row["camera_move_met"] is None  # no camera-move target at 32^2


def test_view_benchmark_makes_its_own_run_where_there_is_none(tmp_path):
    """Without a demo run the benchmark views the raster workload as a run folder the
    viewer opens (its manifests list the fit)."""
    from benchmarks import bm_view

    session = viewer.ViewerSession(bm_view._synthetic_run(tmp_path, 500))
    assert session.can_relight and session.surfels.count == 500


def test_previews_while_changes_come_then_one_full_frame():
    import threading

    from mi_shadowgs.stages.viewer.server import _ClientWorker

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


def test_run_without_stage_4_is_checked_for_stages_that_do_not_belong_together(runs, tmp_path,
                                                                                capsys):
    from mi_shadowgs.io.provenance import ProvenanceError

    run = tmp_path / "mixed"
    shutil.copytree(runs[1], run)
    view_fixtures.add_segmentation(run, "0" * 32)  # made from another geometry/model.ply
    with pytest.raises(ProvenanceError, match="segmentation was made from another geometry"):
        viewer.ViewerSession(run)
    assert cli.main(["view", str(run), "--port", "0"]) == 2
    assert "its stages do not belong together" in capsys.readouterr().err


def test_view_refuses_what_it_cannot_show_as_given(runs, capsys):
    assert cli.main(["view", str(runs[0]), "--fit", "typo"]) == 2
    err = capsys.readouterr().err
    assert "--fit 'typo'" in err and "material/typo/model.ply is missing" in err
    assert "the run's fits: full" in err
    assert cli.main(["view", str(runs[0]), "--light", "30,45,1,0,0"]) == 2
    assert "the viewer's lights are white" in capsys.readouterr().err
    report = runs[0] / "report.html"
    report.write_text("<html></html>")
    try:
        assert cli.main(["view", str(report)]) == 2
        assert f"{report} is a file; give the run folder" in capsys.readouterr().err
    finally:
        report.unlink()
    assert cli.main(["view", str(runs[0]), "--host", "no.such.host.invalid"]) == 2
    err = capsys.readouterr().err
    assert "--host no.such.host.invalid: cannot resolve" in err and "--port" not in err


def test_view_starts_with_the_lights_given_exactly(session):
    from mi_shadowgs.stages.viewer.server import ViewerServer

    given = [viewer.DirectionalLight(30.25, 0.5, 50.0), viewer.DirectionalLight(200.0, 45.5, 3.33)]
    server = ViewerServer(session, port=0, resolution=16, initial_lights=given).start()
    try:
        assert server.light_state().directional == tuple(given)
        (_, _, el, irr), (_, _, _, irr2) = server.lights
        assert el.min == 0.5 and irr.max == 50.0  # the sliders' ranges hold the values
        assert irr2.max == 10.0  # and are the usual ones where they do
    finally:
        server.stop()


def test_values_a_browser_sends_are_kept_to_the_sliders(session, capsys):
    import asyncio

    import msgspec
    import viser
    import websockets

    from mi_shadowgs.stages.viewer.server import ViewerServer

    server = ViewerServer(session, port=0, resolution=16).start()
    _, az, el, irr = server.lights[0]
    sent = [(el, -1e300), (irr, 1e308), (server.exposure, None), (server.exposure, "nan"),
            (irr, float("nan")), (server.mode, [1]), (server.shadows, "false"), (az, 200)]

    async def send():
        async with websockets.connect(f"ws://127.0.0.1:{server.port}", max_size=None,
                                      subprotocols=[f"viser-v{viser.__version__}"]) as ws:
            for handle, value in sent:
                await ws.send(msgspec.msgpack.encode({
                    "type": "GuiUpdateMessage", "uuid": handle._impl.uuid,
                    "updates": {"value": value}}))
            deadline = time.monotonic() + 20
            while az.value != 200 and time.monotonic() < deadline:
                await asyncio.sleep(0.05)

    try:
        asyncio.run(send())
        lights = server.light_state().directional[0]
        assert (lights.azimuth_deg, lights.elevation_deg, lights.irradiance) == (200, 1, 10)
        assert server.exposure.value == 1.0 and server.mode.value == "relit"
        assert server.shadows.value is True
    finally:
        server.stop()
    lines = capsys.readouterr().err.splitlines()
    assert lines[:2] == [
        "mi-shadowgs view: elevation = -1e+300 from the browser: outside the slider's "
        "[1, 90]; using 1",
        "mi-shadowgs view: intensity = 1e+308 from the browser: outside the slider's "
        "[0, 10]; using 10"]
    assert len(lines) == len(sent) - 1 and all("ignored" in x for x in lines[2:])
    # The clamped light renders.
    frame = session.render(session.default_camera(16, 16), server.light_state())
    assert frame.image.max() > 0


def test_a_signal_stops_view_without_a_resume_hint(runs, monkeypatch, capsys):
    from mi_shadowgs.io.interrupt import Interrupted

    def interrupted(*_args, **_kwargs):
        raise Interrupted(signal.SIGTERM)  # a SIGTERM while the model loads

    monkeypatch.setattr(viewer, "ViewerSession", interrupted)
    assert cli.main(["view", str(runs[0]), "--port", "0"]) == 0
    out, err = capsys.readouterr()
    assert out.strip() == "mi-shadowgs view: stopped" and err == ""
