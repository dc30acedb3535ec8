"""The browser page of ``mi-shadowgs view RUN``, drawn with viser (nerfstudio's viewer).

The page is viser's: an orbit camera, a GUI panel and a 3D scene in which the fitted and
the new lights are arrows, and lamps (fitted local lights, the lamp of the sliders) balls.
Each frame is rendered on the server by ``viewer.ViewerSession`` (our relighting: surfels,
shadow maps, Cook-Torrance) for the browser's camera and shown as the scene's background
image, composited with the arrows by depth.

Progressive: every change (camera, slider, toggle) renders a preview at once: half the
frame size and half the run's shadow-map resolution (a 512^2 map of a 30k-surfel model
takes most of a light change's time); when nothing has changed for ``settle_s`` the
full frame follows, with the run's shadow maps. One render
thread per browser tab; renders take turns (one lock: Dr.Jit and the caches are shared).
"""

from __future__ import annotations

import dataclasses
import errno
import math
import socket
import sys
import threading
import time
import traceback

import numpy as np

from mi_shadowgs.core.directions import angles_from_direction
from mi_shadowgs.stages.viewer import viewer

NO_ENVMAP = "none"
ARROW_FITTED = (255, 150, 30)  # orange: the lights stage 4 fitted
ARROW_NEW = (90, 170, 255)  # blue: the lights of the sliders
BACKGROUND_DEPTH = 150.0  # viser's depth images reach 167.77 units; "far" for the arrows
ELEVATION_MIN = 1.0  # the elevation slider's low end (a --light below it lowers it)
INTENSITY_MAX = 10.0  # the intensity slider's high end (a --light above it raises it)
# The lamp's distance slider, in scene radii (the bounds' radius): outside the scene (a lamp
# inside it is refused) out to where it lights almost as a directional light does.
LAMP_DISTANCE = (1.2, 12.0)


class AddressUnusable(OSError):
    """The viewer cannot serve on ``--host``/``--port``; the message names which."""


class PortInUse(AddressUnusable):
    pass


class UnknownHost(AddressUnusable):
    pass


def check_port(host: str, port: int) -> None:
    """PortInUse naming ``--port`` when something listens on (host, port) already (viser
    itself would quietly move to the next free port); UnknownHost naming ``--host`` when
    it does not resolve or is no address of this machine."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        # As the server will bind: a port left in TIME_WAIT is free, a listening one not.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except socket.gaierror as exc:
            raise UnknownHost(f"--host {host}: cannot resolve this address ({exc.strerror}); "
                              "give a name or IP address of this machine") from None
        except OSError as exc:
            if exc.errno == errno.EADDRNOTAVAIL:
                raise UnknownHost(f"--host {host}: not an address of this machine "
                                  f"({exc.strerror})") from None
            raise PortInUse(f"--port {port}: cannot listen on {host}:{port} "
                            f"({exc.strerror or exc}); is another viewer running? "
                            "choose another --port") from None


@dataclasses.dataclass
class Shown:
    """The last frame sent to a browser tab (for the status line and the tests)."""

    count: int  # frames sent to this tab so far
    camera: object  # core.camera.Camera
    lights: viewer.LightState
    mode: str
    shadows: bool
    preview: bool
    frame: viewer.Frame
    latency_s: float | None = None  # oldest change it shows -> sent (None: no change)


class ViewerServer:
    """A viser server showing ``session``; ``start`` binds it, ``stop`` ends it."""

    def __init__(self, session: viewer.ViewerSession, host: str = "127.0.0.1",
                 port: int = 8080, resolution: int = 256, preview_resolution: int | None = None,
                 settle_s: float = 0.4, initial_lights: list[viewer.DirectionalLight] = ()):
        if resolution < 8:
            raise ValueError(f"--resolution must be >= 8, got {resolution}")
        self.session = session
        self.host, self.port = host, port
        self.resolution = resolution
        self.preview_resolution = preview_resolution or max(8, resolution // 2)
        self.settle_s = settle_s
        self.initial_lights = list(initial_lights)
        self.shown: dict[int, Shown] = {}  # client id -> last frame
        self.errors: list[str] = []
        self._render_lock = threading.Lock()
        self._workers: dict[int, _ClientWorker] = {}
        self.server = None

    # -- lifetime ------------------------------------------------------------------------
    def start(self) -> ViewerServer:
        import viser

        check_port(self.host, self.port)
        self.server = viser.ViserServer(host=self.host, port=self.port, verbose=False,
                                        label=f"mi-shadowgs view {self.session.run.name}")
        if self.port and self.server.get_port() != self.port:  # lost a race for the port
            taken = self.server.get_port()
            self.server.stop()
            raise PortInUse(f"--port {self.port}: taken while starting (viser moved to "
                            f"{taken}); choose another --port")
        self.port = self.server.get_port()
        self.server.scene.set_up_direction("+y")
        # Every tab starts (and "Reset View" returns) at the run's first test view,
        # orbiting the object's centre.
        pos, _, fov_y = viewer.pose_of_camera(
            self.session.default_camera(self.resolution, self.resolution))
        init = self.server.initial_camera
        init.up = (0.0, 1.0, 0.0)
        init.fov = fov_y
        init.position = tuple(pos)
        init.look_at = tuple(self.session.bounds.center)
        self._build_gui()
        self._screen_browser_updates()
        self._draw_arrows()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        return self

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def stop(self) -> None:
        for w in list(self._workers.values()):
            w.close()
        if self.server is not None:
            self.server.stop()

    # -- the GUI -------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        s = self.session
        fitted = s.fitted_lights()
        lines = [f"**{s.run.name}**: {s.surfels.count} surfels"]
        if s.relight_off:
            lines.append(f"_{s.relight_off}_")
        if fitted:
            lines.append("fitted lights (orange): " + ", ".join(
                "az {:.0f} el {:.0f} E {:.2f}".format(*angles_from_direction(d), e)
                for d, e in fitted))
        if s.fitted_lamps():
            lines.append("fitted lamps (orange balls) at " + ", ".join(
                "({:.2f}, {:.2f}, {:.2f})".format(*p) for p in s.fitted_lamps()))
        gui.add_markdown("  \n".join(lines))
        self.status = gui.add_markdown("waiting for the browser's camera")
        modes = list(s.modes)
        self.mode = gui.add_dropdown("view", modes, initial_value=modes[0])
        self.shadows = gui.add_checkbox("shadows", True, hint="off: V = 1, the paper's "
                                        "'w/o visibility' ablation",
                                        disabled=not s.can_relight)
        self.exposure = gui.add_slider("exposure", 0.1, 4.0, 0.05, 1.0)
        self.show_fitted = gui.add_checkbox("fitted lights (arrows)", bool(fitted),
                                            disabled=not fitted)
        self.show_new = gui.add_checkbox("new lights (arrows)", s.can_relight,
                                         disabled=not s.can_relight)
        self.lights = []
        starts = list(self.initial_lights)
        for d, e in sorted(fitted, key=lambda f: -f[1])[len(starts):2]:
            # Fitted lights start the sliders rounded (the arrows show them exactly); the
            # --light values are kept as given, the sliders' range widened to hold them.
            az, el = angles_from_direction(d)
            starts.append(viewer.DirectionalLight(float(round(az)) % 360.0,
                                                  float(min(90, max(ELEVATION_MIN, round(el)))),
                                                  round(e, 2)))
        while len(starts) < 2:
            starts.append(viewer.DirectionalLight(30.0 + 180.0 * len(starts), 45.0, 3.0))
        for i, lt in enumerate(starts[:2]):
            with gui.add_folder(f"light {i + 1}"):
                on = gui.add_checkbox("on", i == 0 or len(self.initial_lights) > 1,
                                      disabled=not s.can_relight)
                az = gui.add_slider("azimuth", 0.0, 360.0, 1.0, float(lt.azimuth_deg),
                                    disabled=not s.can_relight)
                el = gui.add_slider("elevation", min(ELEVATION_MIN, lt.elevation_deg), 90.0,
                                    1.0, float(lt.elevation_deg), disabled=not s.can_relight)
                irr = gui.add_slider("intensity", 0.0, max(INTENSITY_MAX, lt.irradiance), 0.05,
                                     float(lt.irradiance), disabled=not s.can_relight)
            self.lights.append((on, az, el, irr))
        with gui.add_folder("lamp"):
            off = not s.can_relight
            self.lamp = (gui.add_checkbox("on", False, disabled=off),
                         gui.add_slider("azimuth", 0.0, 360.0, 1.0, 210.0, disabled=off),
                         gui.add_slider("elevation", ELEVATION_MIN, 90.0, 1.0, 40.0,
                                        disabled=off),
                         gui.add_slider("distance (scene radii)", *LAMP_DISTANCE, 0.1, 3.0,
                                        disabled=off),
                         gui.add_slider("irradiance at centre", 0.0, INTENSITY_MAX, 0.05, 3.0,
                                        hint="W/m^2 at the scene's centre; its intensity "
                                        "(W/sr) is this times the squared distance",
                                        disabled=off))
        envs = s.envmaps()
        self._envmaps = {k: str(v) for k, v in envs.items()}
        with gui.add_folder("env map"):
            self.envmap = gui.add_dropdown("env map", [NO_ENVMAP, *envs],
                                           initial_value=NO_ENVMAP,
                                           disabled=not (s.can_relight and envs))
            self.env_rotate = gui.add_slider("rotation", 0.0, 360.0, 1.0, 0.0,
                                             disabled=not s.can_relight)
            self.env_scale = gui.add_slider("env intensity", 0.05, 4.0, 0.05, 1.0,
                                            disabled=not s.can_relight)
        handles = [self.mode, self.shadows, self.exposure, self.envmap, self.env_rotate,
                   self.env_scale, *(h for group in self.lights for h in group), *self.lamp]
        for h in handles:
            h.on_update(lambda _event: self._changed())
        for h in (self.show_fitted, self.show_new):
            h.on_update(lambda _event: self._draw_arrows())
        self._inputs = {h._impl.uuid: h for h in (*handles, self.show_fitted, self.show_new)}

    # -- what the browser sends ----------------------------------------------------------
    def _screen_browser_updates(self) -> None:
        """Every GUI value a browser sends passes ``screen_value`` before viser applies it:
        the page's sliders keep to their ranges, but any websocket client can send a value
        (an elevation below the horizon, an intensity of 1e308 that fails every later frame,
        null, which viser's own cast raises on)."""
        from viser._messages import GuiUpdateMessage

        api = self.server.gui
        apply = api._handle_gui_updates

        async def screened(client_id, message) -> None:
            handle = self._inputs.get(message.uuid)
            if handle is not None and "value" in message.updates:
                value, why = screen_value(handle, message.updates["value"])
                if why:
                    sent = repr(message.updates["value"])
                    sent = sent if len(sent) <= 40 else sent[:37] + "..."
                    print(f"mi-shadowgs view: {handle.label} = {sent} from the browser: {why}",
                          file=sys.stderr, flush=True)
                if value is None:
                    return
                message.updates["value"] = value
            await apply(client_id, message)

        api._websock_interface.unregister_handler(GuiUpdateMessage, apply)
        api._websock_interface.register_handler(GuiUpdateMessage, screened)

    def light_state(self) -> viewer.LightState:
        """The lights the GUI says."""
        lights = tuple(viewer.DirectionalLight(float(az.value), float(el.value),
                                               float(irr.value))
                       for on, az, el, irr in self.lights if on.value)
        env = self._envmaps.get(self.envmap.value)
        on, az, el, dist, irr = self.lamp
        lamps = ((viewer.LampLight(float(az.value), float(el.value), float(dist.value),
                                   float(irr.value)),) if on.value else ())
        return viewer.LightState(lights, env, float(self.env_rotate.value) if env else 0.0,
                                 float(self.env_scale.value) if env else 1.0, lamps)

    def _draw_arrows(self) -> None:
        s = self.session
        c = np.asarray(s.bounds.center, np.float64)
        r = s.bounds.radius
        state = self.light_state()
        fitted = s.fitted_lights()
        local = s.fit.model.train_lights.local if s.fit is not None else []
        balls = (("/lamps/fitted", s.fitted_lamps(), ARROW_FITTED, self.show_fitted.value),
                 ("/lamps/new", [lt.position(c, r) for lt in state.lamps], ARROW_NEW,
                  self.show_new.value))
        for name, where, color, visible in balls:
            self.server.scene.remove_by_name(name)
            for k, p in enumerate(where if visible else []):
                self.server.scene.add_icosphere(f"{name}/{k}", 0.06 * r, color,
                                                position=tuple(np.asarray(p, float)))
        groups = (("/lights/fitted", [d for k, (d, _) in enumerate(fitted)
                                      if not (len(local) and local[k])], ARROW_FITTED,
                   self.show_fitted.value),
                  ("/lights/new", [lt.direction for lt in state.directional],
                   ARROW_NEW, self.show_new.value))
        for name, dirs, color, visible in groups:
            if not dirs or not visible:
                self.server.scene.remove_by_name(name)
                continue
            d = np.asarray(dirs, np.float64).reshape(-1, 3)
            # From far along l toward the object: the way the light travels.
            points = np.stack([c + 1.45 * r * d, c + 0.95 * r * d], 1)  # [K, 2, 3]
            self.server.scene.add_arrows(name, points, color, shaft_radius=0.012 * r,
                                         head_radius=0.04 * r, head_length=0.12 * r)

    def _changed(self) -> None:
        self._draw_arrows()
        for w in list(self._workers.values()):
            w.request()

    # -- clients -------------------------------------------------------------------------
    def _connect(self, client) -> None:
        worker = _ClientWorker(self, client)
        self._workers[client.client_id] = worker
        client.camera.on_update(lambda _cam: worker.request())
        worker.start()

    def _disconnect(self, client) -> None:
        w = self._workers.pop(client.client_id, None)
        if w is not None:
            w.close()

    def render_for(self, client, preview: bool, changed_at: float | None = None) -> Shown:
        """Render and send one frame for ``client``'s camera and the GUI's settings."""
        import viser  # noqa: F401  (the client handles come from it)

        cam_h = client.camera
        aspect = cam_h.aspect if cam_h.image_height > 0 else 1.0
        n = self.preview_resolution if preview else self.resolution
        w, h = viewer.frame_size(n, aspect)
        camera = viewer.camera_from_pose(cam_h.position, cam_h.wxyz, cam_h.fov, w, h)
        lights = self.light_state()
        mode = self.mode.value
        shadows = bool(self.shadows.value)
        full_maps = self.session.vis_config.resolution
        # An env map's ~100 grid directions keep the run's maps even in previews: they are
        # rendered once (seconds) and every later frame and rotation reuses them.
        maps_res = max(64, full_maps // 2) if preview and lights.envmap is None else full_maps
        prev = self.shown.get(client.client_id)
        if lights.envmap is not None and (prev is None or prev.lights.envmap != lights.envmap):
            self.status.content = ("integrating the env map and rendering a shadow map per "
                                   "grid direction (once per env map; seconds)")
        with self._render_lock:
            frame = self.session.render(camera, lights, mode, shadows,
                                        float(self.exposure.value),
                                        shadow_resolution=min(maps_res, full_maps))
        depth = np.where(frame.alpha > 0.5, frame.depth, BACKGROUND_DEPTH)
        client.scene.set_background_image(frame.image, format="jpeg", jpeg_quality=92,
                                          depth=depth)
        latency = None if changed_at is None else time.monotonic() - changed_at
        shown = Shown((prev.count if prev else 0) + 1, camera, lights, mode, shadows, preview,
                      frame, latency)
        self.shown[client.client_id] = shown
        sec = frame.seconds
        self.status.content = (
            f"{'preview' if preview else 'frame'} {w}x{h}: {1000 * sec['total']:.0f} ms "
            f"(G-buffer {1000 * sec['gbuffer']:.0f}, lights and shadows "
            f"{1000 * sec['lights']:.0f}, shading {1000 * sec['shading']:.0f}); "
            f"{frame.shadow_maps_rendered} new shadow map(s) of {min(maps_res, full_maps)}^2")
        return shown


def screen_value(handle, value) -> tuple[object, str]:
    """(the value to apply, or None to ignore it; why it was changed or ignored, or "") for
    ``value`` sent for the GUI input ``handle``: a slider's value a finite number (clamped
    to its range), a dropdown's one of its options, a checkbox's a boolean."""
    import viser

    if isinstance(handle, viser.GuiSliderHandle):
        if isinstance(value, bool) or not isinstance(value, int | float):
            return None, "not a number; ignored"
        if not math.isfinite(value):
            return None, "not finite; ignored"
        if not handle.min <= value <= handle.max:
            clamped = float(min(handle.max, max(handle.min, value)))
            return (clamped, f"outside the slider's [{handle.min:g}, {handle.max:g}]; "
                             f"using {clamped:g}")
        return value, ""
    if isinstance(handle, viser.GuiDropdownHandle):
        if not isinstance(value, str) or value not in handle.options:
            return None, f"not one of {', '.join(handle.options)}; ignored"
        return value, ""
    if isinstance(handle, viser.GuiCheckboxHandle) and not isinstance(value, bool):
        return None, "not true or false; ignored"
    return value, ""


class _ClientWorker:
    """Renders for one browser tab: a preview at once after each change, the full frame
    once changes stop for ``settle_s``."""

    def __init__(self, owner: ViewerServer, client):
        self.owner, self.client = owner, client
        self._cond = threading.Condition()
        self._version = 0  # changes seen
        self._last_change = 0.0
        self._pending_since: float | None = None  # the oldest change not yet rendered
        self._camera_known = False
        self._closed = False
        self._thread = threading.Thread(target=self._loop, daemon=True,
                                        name=f"view-render-{client.client_id}")

    def start(self) -> None:
        self._thread.start()

    def request(self) -> None:
        with self._cond:
            self._version += 1
            self._last_change = time.monotonic()
            if self._pending_since is None:
                self._pending_since = self._last_change
            self._camera_known = True  # the first request follows the browser's camera
            self._cond.notify()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()

    def _loop(self) -> None:
        done_version, full_done = 0, True
        settle = self.owner.settle_s
        while True:
            with self._cond:
                while not self._closed:
                    if self._camera_known and self._version != done_version:
                        break
                    if (self._camera_known and not full_done and
                            time.monotonic() - self._last_change >= settle):
                        break
                    self._cond.wait(settle if not full_done else None)
                if self._closed:
                    return
                version = self._version
                quiet = time.monotonic() - self._last_change >= settle
                changed_at, self._pending_since = self._pending_since, None
            # While changes come, previews; once quiet, the full frame.
            preview = not quiet
            try:
                self.owner.render_for(self.client, preview, changed_at)
            except Exception as exc:  # noqa: BLE001 -- a bad frame must not end the viewer
                msg = f"render failed: {type(exc).__name__}: {exc}"
                self.owner.errors.append(msg)
                traceback.print_exc(file=sys.stderr)
                try:
                    self.owner.status.content = msg
                except Exception:  # noqa: BLE001 -- the tab may be gone
                    pass
            done_version, full_done = version, not preview

