"""## `surfel_raster` (integrator)

Rasterizes a 2D Gaussian surfel model (`mi_shadowgs.core.raster.rasterize`) through a
standard Mitsuba `perspective` or `orthographic` sensor with an `hdrfilm`. Source:
`mi_shadowgs/plugins/surfel_raster.py`.

- `filename` | string | (required) | | PLY model in the 2DGS layout (`mi_shadowgs.io.ply`);
  resolved like any Mitsuba file (relative to the scene file).
- `aovs` | string | `""` | | Comma-separated extra film channels, in order: `alpha`,
  `depth` (z-depth, 0 on background), `median_depth`, `normal` (world space, facing the
  camera, weighted by coverage), `distortion` (2DGS depth distortion), `count`
  (contributing splats), or the name of any per-surfel channel (`albedo`, `roughness`,
  `feature`, ...), composited like colour.
- `color_channel` | string | `"sh"` | | Channel giving RGB: `sh` is evaluated from the
  sensor position (for an orthographic sensor, along its axis); any other channel with 1 or
  3 columns is used as is.
- `sh_space` | string | the file's | | What the file's SH colours are: `linear` (our
  models) or `srgb` (display values: 3DGS/2DGS and splat viewers, which train on sRGB
  photos; `mi-shadowgs export` writes them). `srgb` SH are turned linear on loading
  (`mi_shadowgs.io.ply.sh_from_srgb`). By default the PLY's `sh_space` header record, else
  `linear`: give `srgb` for another tool's PLY, or it renders washed out.
- `background` | rgb | none | | Composited under the colour:
  `rgb + background * (1 - alpha)`. Without it the colour is premultiplied over black. The
  film's `A` channel stays coverage.
- `alpha_min`, `alpha_max`, `transmittance_min`, `cutoff_sigma`, `lowpass_inv_var`, `near` |
  float | `RasterConfig` defaults (1/255, 0.99, 1e-4, 3, 12, 0.2) | | Rasterizer settings
  (`mi_shadowgs.core.raster.RasterConfig`); each must be positive, `alpha_max` below 1 and
  `alpha_min` below `alpha_max`.
- `position` | Point3f [N] | from file | differentiable | Surfel centres (world space).
- `log_scale` | Point2f [N] | from file | differentiable | Log of the two tangent standard
  deviations.
- `rotation` | Vector4f [N] | from file | differentiable | Quaternion (w, x, y, z),
  unnormalised, not zero.
- `opacity_logit` | Float [N] | from file | differentiable | Logit of the opacity.
- `channels.<name>` | TensorXf [N, C] | from file | differentiable | Each per-surfel channel
  of the model (`channels.sh` [N, 3(d+1)^2] coefficient-major, `channels.albedo`, ...).

The last five rows are not XML properties: they are the parameters that `mi.traverse`
exposes (prefixed by the integrator's `id`, e.g. `surf.position`, when traversing the
scene), and `mi.render(scene, params)` differentiates through them (`render_forward` and
`render_backward` re-run the differentiable rasterizer). After changing their number
(`N`), set all of them before `params.update()`. `params.update()` refuses a NaN or Inf in
any parameter it is given and a zero quaternion (`|q| < 1e-12`), as the PLY reader does: a
`ValueError` naming the parameter and its first bad row (`surfel_raster: params.update():
field 'position' holds NaN at vertex 7 (1 of 40 vertices)`), and puts back the values of
the last accepted update (or the file's), so the integrator goes on drawing those. It also
refuses a log-scale whose exp is zero or above 1e12 in float32, as the reader does.
Unchecked, the rasterizer drew most such surfels as nothing, a NaN or zero quaternion as
the identity, and a +Inf SH coefficient or a non-finite AOV channel as NaN pixels, without
a word. The check reads only the changed parameters, outside the AD graph, and waits for
one value from the device per update.

**Film channels.** `mi.render` returns `[H, W, C]`: the film's base channels (`R, G, B` and
`A` with `pixel_format="rgba"`, or `Y`/`Y, A` for luminance formats), then the AOVs named
as Mitsuba's `aov` integrator does: `depth.T`, `median_depth.T`, `distortion.T`,
`count.T`, `alpha.T`, `normal.X/Y/Z`, a 3-column channel `albedo.R/G/B`, a 1-column one
`roughness.T`, wider ones `feature.0..15`. `film.bitmap()` carries the same names.

**Not used:** the sampler, samples per pixel and seeds (the render is deterministic), the
film's reconstruction filter (each pixel is evaluated at its centre), and the sensor's
`near_clip` and `far_clip` (the `near` property culls splats nearer than it; none is culled
for being far). Sensors with a principal-point offset or a crop window, and other sensor
types (`thinlens`, ...), are refused with an error. A colour channel of another width
(`color_channel`, or after `params.update()`) and a model of 0 surfels are refused by name.

### Example

```xml
<scene version="3.0.0">
    <integrator type="surfel_raster" id="surf">
        <string name="filename" value="model.ply"/>
        <string name="aovs" value="depth,normal"/>
        <rgb name="background" value="1, 1, 1"/>
    </integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world">
            <lookat origin="0, 1, 4" target="0, 0.5, 0" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm">
            <integer name="width" value="256"/>
            <integer name="height" value="256"/>
            <string name="pixel_format" value="rgba"/>
        </film>
    </sensor>
</scene>
```

```python
import drjit as dr
import mitsuba as mi
import mi_shadowgs

mi_shadowgs.register_plugins()  # surfel_raster and surfel_relight, for the variant

scene = mi.load_file("scene.xml")
img = mi.render(scene)                        # [256, 256, 4 + 1 + 3]
target = mi.TensorXf(mi.Bitmap("photo.exr"))  # the RGBA image to fit, [256, 256, 4]
params = mi.traverse(scene)
opt = mi.ad.Adam(lr=0.01)
opt["surf.channels.sh"] = params["surf.channels.sh"]
params.update(opt)
for it in range(100):
    img = mi.render(scene, params, seed=it)
    loss = dr.mean(dr.square(img[:, :, :4] - target), axis=None)
    dr.backward(loss)
    opt.step()
    params.update(opt)
```

Command line: `mi-shadowgs render MODEL.ply --cameras transforms.json --out DIR
[--aov NAME]... [--background R,G,B] [--color-channel NAME]` (`--aov` once per AOV)
renders the same images from dataset cameras (`NAME.exr` linear RGBA, `NAME.png`,
`NAME_<aov>.exr/.png`).
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
        sh_space = props.get("sh_space", None)
        if sh_space is not None and (not isinstance(sh_space, str)
                                     or sh_space not in ply.SH_SPACES):
            raise ValueError(f"surfel_raster ({self.filename}): property 'sh_space' must be "
                             f"one of {', '.join(ply.SH_SPACES)}, got {sh_space!r}")
        self.surfels = ply.load_ply(self.filename, sh_space)
        self._accept_params()
        self.color_channel = str(props.get("color_channel", core_render.DEFAULT_COLOR_CHANNEL))
        aovs = str(props.get("aovs", ""))
        self.aovs = tuple(a.strip() for a in aovs.split(",") if a.strip())
        bg = props.get("background", None)
        try:
            if bg is not None and not isinstance(bg, int | float | str):
                bg = list(bg)  # an rgb property (ScalarColor3d)
            self.background = core_render.parse_background(bg, "'background'")
            core_render.aov_layout(self.aovs, self.surfels)
            core_render.check_color_channel(self.surfels, self.color_channel)
            known = {f.name for f in dataclasses.fields(RasterConfig)}
            overrides = {k: float(props.get(k)) for k in _CONFIG_PROPS
                         if k in known and k in props}
            for k, v in overrides.items():
                if not 0.0 < v < float("inf") or (k == "alpha_max" and v >= 1.0):
                    raise core_render.RenderError(f"property {k!r} must be a positive finite number"
                                         f"{' below 1' if k == 'alpha_max' else ''}, got {v}")
            self.config = with_overrides(RasterConfig(), overrides, "surfel_raster")
            # Every splat's alpha is clamped to alpha_max, then dropped below alpha_min: an
            # alpha_min at or above alpha_max rendered an empty image.
            if not self.config.alpha_min < self.config.alpha_max:
                raise core_render.RenderError(
                    f"property 'alpha_min' ({self.config.alpha_min}) must be below "
                    f"'alpha_max' ({self.config.alpha_max})")
        except (core_render.RenderError, ConfigError) as exc:
            raise ValueError(f"surfel_raster ({self.filename}): {exc}") from None

    # -- parameters -----------------------------------------------------------------------
    def traverse(self, callback):
        for key, value in self.surfels.params().items():
            callback.put(key, value, mi.ParamFlags.Differentiable)

    def _accept_params(self) -> None:
        """Keep references to the parameters as they are now, the values a refused update
        goes back to. No copy: an update replaces the arrays' variables, it does not write
        into them."""
        self._accepted = {k: type(v)(v) for k, v in self.surfels.params().items()}

    def parameters_changed(self, keys):
        try:
            self._check_params(keys)
        except ValueError:
            # Mitsuba has already written the new values into the parameters: put the
            # accepted ones back, so that the integrator draws what it drew before.
            current = self.surfels.params()
            for key, value in self._accepted.items():
                mi.set_property(current[key], value)
            raise
        self._accept_params()

    def _check_params(self, keys) -> None:
        n = self.surfels.count
        if n == 0:  # the rasterizer has nothing to draw and fails without a name
            raise ValueError("surfel_raster: parameter 'position' has 0 entries; a model needs "
                             "at least one surfel")
        for key, value in self.surfels.params().items():
            rows = value.shape[0] if isinstance(value, mi.TensorXf) else dr.width(value)
            if rows != n:
                raise ValueError(f"surfel_raster: parameter {key!r} has {rows} entries, "
                                 f"position has {n}")
        # NaN/Inf (a diverged optimiser step) and zero quaternions were drawn silently: a
        # NaN surfel as nothing, a zero quaternion as the identity. Only the changed keys
        # are read (all when Mitsuba names none). Mitsuba names a key by its last part
        # when the integrator is traversed inside a scene ('sh' for 'surf.channels.sh').
        changed = [k for k in self.surfels.params() if k in keys or k.rsplit(".", 1)[-1] in keys]
        self.surfels.check_params("surfel_raster: params.update()", changed if keys else None)
        try:
            core_render.check_color_channel(self.surfels, self.color_channel)
        except core_render.RenderError as exc:
            raise ValueError(f"surfel_raster: parameter 'channels.{self.color_channel}': "
                             f"{exc}") from None

    def aov_names(self):
        return [c for _, names in core_render.aov_layout(self.aovs, self.surfels) for c in names]

    def to_string(self):
        return (f"SurfelRasterIntegrator[filename={self.filename!r}, "
                f"surfels={self.surfels.count}, aovs={list(self.aovs)}, "
                f"color_channel={self.color_channel!r}]")

    # -- rendering ------------------------------------------------------------------------
    def _image(self, scene, sensor, config=None) -> mi.TensorXf:
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
                                   config=config or self.config)
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
        # Forward-mode AD runs on the pair list: the tiled renderer's hand-written
        # derivative is reverse mode only (the same images either way).
        with dr.resume_grad():
            image = self._image(scene, sensor, dataclasses.replace(self.config, method="pairs"))
            dr.forward_to(image)
            return dr.grad(image)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        with dr.resume_grad():
            image = self._image(scene, sensor)
            dr.set_grad(image, grad_in)
            dr.enqueue(dr.ADMode.Backward, image)
            dr.traverse(dr.ADMode.Backward)


mi.register_integrator("surfel_raster", lambda props: SurfelRasterIntegrator(props))
