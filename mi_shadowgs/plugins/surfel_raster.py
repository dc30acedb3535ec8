"""``surfel_raster``: a Mitsuba integrator that rasterizes a 2D Gaussian surfel model (PLY).

Properties (see docs/plugins.md for the table):

- ``filename`` (string, required): the PLY model (2DGS layout, ``mi_shadowgs.io.ply``),
  resolved with Mitsuba's file resolver (relative to the scene file).
- ``aovs`` (string, default ""): comma-separated extra film channels: ``alpha``, ``depth``
  (z-depth), ``median_depth``, ``normal`` (world space, facing the camera), ``distortion``,
  ``count``, or any per-surfel channel of the model (``albedo``, ``feature``, ...).
- ``color_channel`` (string, default "sh"): the channel that gives RGB; "sh" is evaluated
  from the sensor position.
- ``background`` (rgb, default none): composited under the colour (RGB only; the film's
  alpha stays coverage). Without it colour is premultiplied over black.
- ``alpha_min``, ``alpha_max``, ``transmittance_min``, ``cutoff_sigma``, ``lowpass_inv_var``,
  ``near`` (float): rasterizer settings (``mi_shadowgs.core.raster.RasterConfig``).

``mi.traverse`` exposes the differentiable surfel parameters ``position``, ``log_scale``,
``rotation``, ``opacity_logit`` and ``channels.<name>``; ``mi.render(scene, params)``
differentiates through the rasterizer. Sensors: ``perspective`` or ``orthographic`` with an
``hdrfilm`` (any pixel format); samples per pixel and seeds are ignored (the render is
deterministic).
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi

from mi_shadowgs.config import ConfigError, with_overrides
from mi_shadowgs.core import render as core_render
from mi_shadowgs.io import ply

_CONFIG_PROPS = ("alpha_min", "alpha_max", "transmittance_min", "cutoff_sigma",
                 "lowpass_inv_var", "near")


class SurfelRasterIntegrator(mi.SamplingIntegrator):
    def __init__(self, props: mi.Properties):
        super().__init__(props)
        from mi_shadowgs.core.raster import RasterConfig

        if "filename" not in props:
            raise ValueError("surfel_raster: the 'filename' property (a PLY model) is required")
        name = str(props.get("filename"))
        path = mi.file_resolver().resolve(name)
        self.filename = str(path)
        self.surfels = ply.load_ply(self.filename)
        self.color_channel = str(props.get("color_channel", core_render.DEFAULT_COLOR_CHANNEL))
        aovs = str(props.get("aovs", ""))
        self.aovs = tuple(a.strip() for a in aovs.split(",") if a.strip())
        bg = props.get("background", None)
        try:
            if bg is not None and not isinstance(bg, int | float | str):
                bg = list(bg)  # an rgb property (ScalarColor3d)
            self.background = core_render.parse_background(bg, "'background'")
            core_render.aov_layout(self.aovs, self.surfels)
            if self.color_channel not in self.surfels.channels:
                raise core_render.RenderError(f"colour channel {self.color_channel!r} is not in "
                                     f"{self.filename} (channels: "
                                     f"{sorted(self.surfels.channels)})")
            known = {f.name for f in dataclasses.fields(RasterConfig)}
            overrides = {k: float(props.get(k)) for k in _CONFIG_PROPS
                         if k in known and k in props}
            for k, v in overrides.items():
                if not 0.0 < v < float("inf") or (k == "alpha_max" and v >= 1.0):
                    raise core_render.RenderError(f"property {k!r} must be a positive finite number"
                                         f"{' below 1' if k == 'alpha_max' else ''}, got {v}")
            self.config = with_overrides(RasterConfig(), overrides, "surfel_raster")
        except (core_render.RenderError, ConfigError) as exc:
            raise ValueError(f"surfel_raster ({self.filename}): {exc}") from None

    # -- parameters -----------------------------------------------------------------------
    def traverse(self, callback):
        for key, value in self.surfels.params().items():
            callback.put(key, value, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        n = self.surfels.count
        for key, value in self.surfels.params().items():
            rows = value.shape[0] if isinstance(value, mi.TensorXf) else dr.width(value)
            if rows != n:
                raise ValueError(f"surfel_raster: parameter {key!r} has {rows} entries, "
                                 f"position has {n}")

    def aov_names(self):
        return [c for _, names in core_render.aov_layout(self.aovs, self.surfels) for c in names]

    def to_string(self):
        return (f"SurfelRasterIntegrator[filename={self.filename!r}, "
                f"surfels={self.surfels.count}, aovs={list(self.aovs)}, "
                f"color_channel={self.color_channel!r}]")

    # -- rendering ------------------------------------------------------------------------
    def _image(self, scene, sensor) -> mi.TensorXf:
        """The developed film tensor [H, W, C]; attached when AD is enabled."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        camera = core_render.sensor_camera(sensor)
        film = sensor.film()
        layout = core_render.FilmLayout(
            has_alpha=mi.has_flag(film.flags(), mi.FilmFlags.Alpha),
            aovs=tuple((n, tuple(c)) for n, c in core_render.aov_layout(self.aovs, self.surfels)))
        images = core_render.render_surfels(self.surfels, camera, color_channel=self.color_channel,
                                   aovs=self.aovs, background=self.background,
                                   config=self.config)
        return core_render.develop_film(film, layout, self.aov_names(), images, "surfel_raster")

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not develop:
            raise ValueError("surfel_raster: only develop=True is supported")
        with dr.suspend_grad():
            image = self._image(scene, sensor)
            if evaluate:
                dr.eval(image)
            return image

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        with dr.resume_grad():
            image = self._image(scene, sensor)
            dr.forward_to(image)
            return dr.grad(image)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        with dr.resume_grad():
            image = self._image(scene, sensor)
            dr.set_grad(image, grad_in)
            dr.enqueue(dr.ADMode.Backward, image)
            dr.traverse(dr.ADMode.Backward)


mi.register_integrator("surfel_raster", lambda props: SurfelRasterIntegrator(props))
