"""The state behind ``mi-shadowgs view RUN``: a finished run loaded once, rendered again for
every camera, light and display mode the viewer asks for.

Where the time goes when only the light moves: the camera's G-buffer (points, normals,
albedo, roughness, metallic, indirect SH irradiance, segment colours) does not change, so
it is rasterized once per camera pose and size and kept (``GBufferCache``); a new light
direction costs one shadow map (``render.RelightCache``, keyed by direction, the cache of
the ``relight`` command), the visibility lookup and the Cook-Torrance shading of the
G-buffer. Nothing here knows about the browser: ``viewer_server`` draws the page.

A run without stage 4 (no ``material/<fit>/model.ply``) still loads: its geometry (stage 1)
and segments (stage 2, when there) are shown, and ``relight_off`` says why relighting is off.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import shading
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import direction_from_angles
from mi_shadowgs.core.raster import RasterConfig
from mi_shadowgs.io.images import to_uint8
from mi_shadowgs.stages.relight import lamps as lamp_mod
from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.visibility import shadow_maps

MODES = ("relit", "albedo", "irradiance", "segments", "normals")
RELIGHT_MODES = ("relit", "albedo", "irradiance")  # need stage 4
SEGMENT_CHANNEL = "segment"
SEGMENT_COLOR = "segment_color"


@dataclasses.dataclass(frozen=True)
class DirectionalLight:
    """One slider-driven light: degrees as in docs/conventions.md, irradiance in W/m^2."""

    azimuth_deg: float
    elevation_deg: float
    irradiance: float = 3.0

    @property
    def direction(self) -> np.ndarray:  # [3] unit, toward the light
        return np.asarray(direction_from_angles(self.azimuth_deg, self.elevation_deg),
                          np.float64).reshape(3)


@dataclasses.dataclass(frozen=True)
class LampLight:
    """One slider-driven point lamp about the scene's centre: its direction from there
    (degrees, as a directional light's), its distance in scene radii (the bounds' radius)
    and the irradiance it gives the centre (W/m^2; its intensity is that times the squared
    distance in world units)."""

    azimuth_deg: float
    elevation_deg: float
    distance: float = 3.0
    irradiance: float = 3.0

    def position(self, center, radius: float) -> np.ndarray:  # [3] world
        d = np.asarray(direction_from_angles(self.azimuth_deg, self.elevation_deg),
                       np.float64).reshape(3)
        return np.asarray(center, np.float64) + self.distance * radius * d


@dataclasses.dataclass(frozen=True)
class LightState:
    """The viewer's lights: directional lights, lamps and/or one env map turned about +Y."""

    directional: tuple[DirectionalLight, ...] = ()
    envmap: str | None = None  # path of a lat-long EXR
    envmap_rotate_deg: float = 0.0
    envmap_scale: float = 1.0
    lamps: tuple[LampLight, ...] = ()


@dataclasses.dataclass
class Frame:
    """One rendered frame and what it cost."""

    image: np.ndarray  # [H, W, 3] uint8 sRGB, ready to display
    alpha: np.ndarray  # [H, W] coverage
    depth: np.ndarray  # [H, W] z-depth, 0 on the background
    mode: str
    shadows: bool
    seconds: dict  # "gbuffer", "lights", "shading", "total" (wall, Dr.Jit synced)
    shadow_maps_rendered: int  # new shadow maps this frame needed
    visibility: np.ndarray | None = None  # [H, W, K] with ``render(..., visibility=True)``


class GBufferCache:
    """G-buffers by camera pose and size, least recently used dropped first."""

    def __init__(self, capacity: int = 8):
        self.capacity = capacity
        self._items: collections.OrderedDict = collections.OrderedDict()
        self.rendered = 0  # G-buffers rasterized (not reused), for tests and benchmarks

    @staticmethod
    def key(camera: Camera) -> tuple:
        return (np.round(camera.c2w, 9).tobytes(), camera.width, camera.height,
                camera.fov_x, camera.focal_y, camera.cx, camera.cy)

    def get(self, camera: Camera, build):
        k = self.key(camera)
        if k in self._items:
            self._items.move_to_end(k)
            return self._items[k]
        value = build(camera)
        self.rendered += 1
        self._items[k] = value
        while len(self._items) > self.capacity:
            self._items.popitem(last=False)
        return value


def frame_size(pixels: int, aspect: float) -> tuple[int, int]:
    """(width, height) of about ``pixels``^2 pixels at ``aspect`` = width / height: the
    cost of a frame follows its pixel count, whatever the browser window's shape."""
    if pixels < 1 or not (math.isfinite(aspect) and aspect > 0):
        raise ValueError(f"frame size: need pixels >= 1 and aspect > 0, got {pixels}, {aspect}")
    s = math.sqrt(aspect)
    return max(1, round(pixels * s)), max(1, round(pixels / s))


def camera_from_pose(position, wxyz, fov_y: float, width: int, height: int) -> Camera:
    """Our camera from a viewer pose: ``wxyz`` rotates the OpenCV camera frame (+Z forward,
    +Y down) to the world, ``fov_y`` is the vertical field of view (radians)."""
    w, x, y, z = (float(v) for v in np.asarray(wxyz, np.float64).reshape(4))
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    r_cv = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    c2w = np.eye(4)
    c2w[:3, :3] = r_cv @ np.diag([1.0, -1.0, -1.0])  # OpenCV -> OpenGL camera axes
    c2w[:3, 3] = np.asarray(position, np.float64).reshape(3)
    fov_x = 2.0 * math.atan(math.tan(0.5 * fov_y) * width / height)
    return Camera(c2w=c2w, width=width, height=height, fov_x=fov_x)


def pose_of_camera(camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(position [3], wxyz [4] of the OpenCV frame, vertical fov) of ``camera``: the
    inverse of ``camera_from_pose``."""
    r = camera.c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    t = np.trace(r)
    # Shepperd's method: the branch with the largest diagonal term is stable.
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1e-300, 1.0 + r[i, i] - r[j, j] - r[k, k]))
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    fov_y = 2.0 * math.atan(0.5 * camera.height / camera.focal_xy[1])
    return camera.origin, np.asarray(q, np.float64), fov_y


class ViewerSession:
    """A run loaded for viewing, with its G-buffer and shadow-map caches."""

    def __init__(self, run: str | Path, fit: str = "full", *, max_shadow_maps: int = 192):
        from mi_shadowgs.io.ply import load_ply
        from mi_shadowgs.stages.common import check_run_stages
        from mi_shadowgs.stages.relight import runner

        self.run = Path(run)
        if not self.run.is_dir():
            raise FileNotFoundError(f"run folder not found: {self.run}")
        material = self.run / "material" / fit
        self.fit = None  # runner.RunFit when stage 4 is there
        self.relight_off: str | None = None  # why relighting is off, when it is
        self.segments_off: str | None = None
        if (material / "model.ply").is_file():
            # Where the dataset is gone, an orbit camera stands in for the training
            # cameras in the shadow maps' bounds (as --orbit does for `relight`).
            fallback = [] if self._training_cameras() else [self._orbit_template(
                load_ply(material / "model.ply").to_numpy()["position"])]
            self.fit = runner.load_run(self.run, fit, fallback)
            self.surfels = self.fit.model.surfels
            self.bounds = self.fit.bounds
        else:
            # load_run checks this for a run with stage 4; without it a segmentation made
            # from another geometry would be shown as this run's.
            check_run_stages(self.run)
            self.relight_off = (f"relighting is off: {material / 'model.ply'} is missing (the "
                                "run has no stage-4 model); showing geometry and segments")
            model = next((p for p in (self.run / "segmentation" / "model.ply",
                                      self.run / "geometry" / "model.ply") if p.is_file()),
                         None)
            if model is None:
                raise FileNotFoundError(
                    f"{self.run}: no model to view (neither material/{fit}/model.ply, "
                    "segmentation/model.ply nor geometry/model.ply); is it a "
                    "`mi-shadowgs run` folder?")
            self.surfels = load_ply(model)
            pos = self.surfels.to_numpy()["position"]
            self.bounds = shadow_maps.SceneBounds.from_points(
                pos, self._training_cameras() or [self._orbit_template(pos)],
                runner.DEFAULT_QUANTILE)
        if SEGMENT_CHANNEL in self.surfels.channels:
            self._segment_colors = self._segment_color_channel()
        else:
            self._segment_colors = None
            self.segments_off = "the model has no segments (stage 2 did not run)"
        # The settings stage 4 ran with (its manifest); without a fit, the defaults (the
        # geometry and segments are shown unlit).
        self.vis_config = self.fit.vis_config if self.fit else shadow_maps.VisibilityConfig()
        self.relight_config = (self.fit.relight_config if self.fit
                               else relight.RelightConfig())
        self.raster = RasterConfig()
        self.maps = relight.RelightCache(
            max_map_bytes=max_shadow_maps * 4 * self.vis_config.resolution ** 2, max_sets=4)
        self.gbuffers = GBufferCache()
        self._light_sets: dict = {}

    # -- what the run offers ------------------------------------------------------------
    @property
    def can_relight(self) -> bool:
        return self.fit is not None

    @property
    def modes(self) -> tuple[str, ...]:
        return tuple(m for m in MODES if (m not in RELIGHT_MODES or self.can_relight)
                     and (m != "segments" or self._segment_colors is not None))

    def fitted_lights(self) -> list[tuple[np.ndarray, float]]:
        """Stage 4's lights: (direction [3] toward the light, irradiance W/m^2); a lamp's
        from the fit's centre and there."""
        if self.fit is None:
            return []
        ls = self.fit.model.train_lights
        w = relight.light_weights(ls).mean(1)
        return [(np.asarray(d, np.float64), float(e))
                for d, e in zip(np.asarray(ls.directions).reshape(-1, 3), w, strict=True)]

    def fitted_lamps(self) -> list[np.ndarray]:
        """The positions [3] of stage 4's lamps (its local lights)."""
        if self.fit is None or self.fit.model.train_lights.positions is None:
            return []
        ls = self.fit.model.train_lights
        pos = np.asarray(ls.positions, np.float64).reshape(-1, 3)
        return [pos[k] for k in np.flatnonzero(ls.local)]

    def envmaps(self) -> dict[str, Path]:
        """Env maps to light with: the shipped ones and those copied into the run's
        dataset (``envmaps/*.exr``), by name."""
        from mi_shadowgs.dataset.assets import ENVMAP_SUFFIXES, shipped_envmaps

        found = {p.stem: p for p in shipped_envmaps()}
        data = self.fit.dataset if self.fit else None
        if data is not None and (data / "envmaps").is_dir():
            for p in sorted((data / "envmaps").iterdir()):
                if p.suffix.lower() in ENVMAP_SUFFIXES:
                    found.setdefault(p.stem, p)
        return found

    def default_camera(self, width: int, height: int) -> Camera:
        """The run's first test view (else an orbit camera) at ``width`` x ``height``."""
        from mi_shadowgs.stages.relight import runner

        data = self._dataset()
        cams = ((runner.dataset_cameras(data, "test") or runner.dataset_cameras(data, "train"))
                if data is not None else [])
        template = (cams[0] if cams else
                    self._orbit_template(self.surfels.to_numpy()["position"]))
        return camera_from_pose(*pose_of_camera(template), width, height)

    # -- rendering -----------------------------------------------------------------------
    def light_set(self, state: LightState) -> shading.LightSet | None:
        """The LightSet of ``state`` (None: no light); env maps integrated once per
        (file, rotation, scale)."""
        from mi_shadowgs.stages.relight import runner

        key = state
        if key in self._light_sets:
            return self._light_sets[key]
        sets = [relight.directional_light_set(lt.direction[None], [lt.irradiance])
                for lt in state.directional if lt.irradiance > 0]
        c, r = self.bounds.center, self.bounds.radius
        lamps = [lamp_mod.Lamp(tuple(lt.position(c, r)), (lt.irradiance * (lt.distance * r)
                               ** 2,) * 3, source="the viewer's lamp")
                 for lt in state.lamps if lt.irradiance > 0]
        if lamps:
            lamp_mod.check_lamps(lamps, self.bounds)
            sets.append(lamp_mod.lamp_light_set(lamps, c))
        if state.envmap is not None:
            em = runner.envmap_emitter(state.envmap, state.envmap_rotate_deg, state.envmap_scale)
            ls = relight.grid_light_set(self.maps.envmap_radiance(em, self.relight_config),
                                        self.relight_config.n_directions)
            if ls.count:
                sets.append(ls)
        out = relight.combine_light_sets(sets) if sets else None
        if len(self._light_sets) > 64:  # slider drags make many; keep the recent ones
            self._light_sets.pop(next(iter(self._light_sets)))
        self._light_sets[key] = out
        return out

    def gbuffer(self, camera: Camera) -> relight.ViewBuffers:
        return self.gbuffers.get(camera, self._build_gbuffer)

    def render(self, camera: Camera, lights: LightState, mode: str = "relit",
               shadows: bool = True, exposure: float = 1.0, visibility: bool = False,
               shadow_resolution: int | None = None) -> Frame:
        """One frame of ``camera`` under ``lights`` in ``mode`` (``MODES``); ``shadows``
        False is the "w/o visibility" ablation (V = 1). ``visibility``: also return the
        per-light visibility [H, W, K] (for checks). ``shadow_resolution``: shadow maps of
        this size instead of the run's (the viewer's previews while a slider moves)."""
        if mode not in MODES:
            raise ValueError(f"view mode must be one of {MODES}, got {mode!r}")
        if mode not in self.modes:
            why = self.relight_off if mode in RELIGHT_MODES else self.segments_off
            raise ValueError(f"view mode {mode!r} is not available: {why}")
        h, w = camera.height, camera.width
        dr.sync_thread()
        t0 = time.perf_counter()
        g = self.gbuffer(camera)
        dr.sync_thread()
        t1 = time.perf_counter()
        before = self.maps.rendered
        vis_np = None
        with dr.suspend_grad():
            if mode in ("normals", "segments"):
                t2 = t1
                if mode == "normals":
                    n = relight.color_image(g.geom.normal, h, w)
                    image = to_uint8(0.5 * (n + 1.0), srgb=False)
                else:
                    image = to_uint8(relight.color_image(g.colors[SEGMENT_COLOR], h, w),
                                     srgb=False)
            else:
                ls = self.light_set(lights)
                maps = None
                if ls is not None and shadows and mode != "albedo":
                    cfg = (self.vis_config if shadow_resolution is None else
                           dataclasses.replace(self.vis_config, resolution=shadow_resolution))
                    maps = self.maps.shadow_maps(self.fit.model, ls, self.bounds, cfg)
                vis = (None if maps is None else
                       maps.evaluate(g.geom.points, g.geom.normal, g.geom.footprint))
                if vis is not None:
                    dr.eval(vis)
                dr.sync_thread()
                t2 = time.perf_counter()
                image = self._shade(g, ls, vis, mode, exposure, h, w)
                if visibility and ls is not None:
                    vis_np = (np.ones((h, w, ls.count), np.float32) if vis is None else
                              np.asarray(vis.numpy(), np.float32).reshape(h, w, ls.count))
        alpha = g.geom.alpha.numpy().reshape(h, w)
        depth = np.asarray(g.geom.depth.numpy(), np.float32).reshape(h, w)
        t3 = time.perf_counter()  # numpy read-back: synced
        return Frame(image, alpha, depth, mode, shadows,
                     {"gbuffer": t1 - t0, "lights": t2 - t1, "shading": t3 - t2,
                      "total": t3 - t0}, self.maps.rendered - before, vis_np)

    # -- internals -----------------------------------------------------------------------
    def _shade(self, g: relight.ViewBuffers, ls, vis, mode: str, exposure: float, h: int, w: int
               ) -> np.ndarray:
        if mode == "albedo":
            return to_uint8(relight.color_image(g.albedo * (1.0 - g.metallic), h, w))
        if ls is None:  # no light: black, as a real scene would be
            return np.zeros((h, w, 3), np.uint8)
        if mode == "irradiance":
            # White direct irradiance over the lights' total: 1 = facing every light, lit.
            total = float(relight.light_weights(ls).mean(1).sum())
            irr = shading.direct(g.geom, mi.Color3f(dr.pi), dr.zeros(mi.Float, h * w),
                                 dr.zeros(mi.Float, h * w), ls, vis, False)
            return to_uint8(relight.color_image(irr, h, w) * (exposure / max(total, 1e-12)))
        factor = relight.indirect_factor(self.fit.model, ls, self.relight_config)
        indirect = g.indirect * factor if g.indirect is not None and factor > 0 else None
        rgb = shading.shade(g.geom, g.albedo, g.roughness, g.metallic, ls, vis, indirect,
                            self.fit.model.specular)
        return to_uint8(relight.color_image(rgb, h, w) * exposure)

    def _build_gbuffer(self, camera: Camera) -> relight.ViewBuffers:
        extra = None if self._segment_colors is None else {SEGMENT_COLOR: self._segment_colors}
        g = relight.view_buffers(self.surfels, camera, self.raster,
                                 material=self.fit is not None, extra=extra,
                                 receiver_band=self.vis_config.receiver_band)
        dr.eval(g.albedo, g.roughness, g.metallic, g.indirect, *g.colors.values())
        return g

    def _segment_color_channel(self) -> mi.TensorXf:
        from mi_shadowgs.stages.segmentation.maps import segment_colors

        seg = np.asarray(self.surfels.channels[SEGMENT_CHANNEL].numpy()).reshape(-1)
        seg = np.round(seg).astype(np.int64)
        k = int(seg.max()) + 1 if seg.size else 1
        colors = segment_colors(k)[1:].astype(np.float32) / 255.0  # [k, 3] sRGB
        return mi.TensorXf(colors[np.clip(seg, 0, k - 1)])  # [N, 3]

    def _dataset(self) -> Path | None:
        """The run's dataset folder, where it still is."""
        from mi_shadowgs.io.provenance import read_manifest

        path = ((read_manifest(self.run) or {}).get("dataset") or {}).get("path")
        return Path(path) if path and Path(path).is_dir() else None

    def _training_cameras(self) -> list[Camera]:
        from mi_shadowgs.stages.relight import runner

        data = self._dataset()
        return runner.dataset_cameras(data, "train") if data is not None else []

    def _orbit_template(self, pos: np.ndarray) -> Camera:
        """A camera at 2.8 bounding radii from the surfels, 25 degrees up, 40 degree fov:
        the view when the run's dataset is gone."""
        c = pos.mean(0)
        r = float(np.quantile(np.linalg.norm(pos - c, axis=1), 0.98)) if len(pos) else 1.0
        eye = c + 2.8 * max(r, 1e-3) * np.asarray(direction_from_angles(-60.0, 25.0))
        return Camera.look_at(eye, c, width=256, height=256, fov_x=math.radians(40.0))

