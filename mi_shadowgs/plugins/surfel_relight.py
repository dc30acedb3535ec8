"""## `surfel_relight` (integrator)

Relights a decomposed surfel model (stage 4's PLY: `albedo`, `roughness`, `metallic`
channels, optional `indirect_sh`) under the emitters of the Mitsuba scene it is loaded in,
with shadows recomputed from shadow maps of the surfels
(`mi_shadowgs.stages.relight.render`). Source: `mi_shadowgs/plugins/surfel_relight.py`.

- `filename` | string | (required) | | PLY model in the 2DGS layout with the material
  channels; resolved like any Mitsuba file. A model without `albedo`/`roughness`/`metallic`
  is refused with an error naming the missing channels.
- `specular` | boolean | the model's | | Model the Cook-Torrance GGX lobe (`false`:
  diffuse `(1 - m) a / pi` only, no GGX work). By default as the model was fitted (the
  PLY's header, or the run's `light.json` beside it; a `cpu-*` model fits without the lobe,
  so its roughness and metallic were never fitted); `true` for another tool's PLY. A
  `<boolean>`; any other type is an error.
- `visibility` | boolean | `true` | | Shadows from shadow maps (`false`: V = 1, the paper's
  "w/o visibility" ablation). A `<boolean>`; any other type is an error.
- `indirect` | string | `"none"` | | `"none"` or `"keep"` (add the fitted `indirect_sh`
  unchanged). The training light is not known to the plugin, so the library's default
  `"scaled"` mode is not offered.
- `shadow_resolution` | integer | the model's | | Shadow-map width = height (texels); the map
  covers the surfels' bounding sphere. By default the resolution the model was fitted with
  (below); `512` for another tool's PLY. An `<integer>`; any other type is an error.
- `env_samples` | integer | `64` | | Samples per grid direction when integrating an
  infinite emitter over the 128-direction grid. An `<integer>`, as `shadow_resolution`.
- `receiver_band` | float | the model's | | Which surface of a pixel is shaded: `0` the
  alpha-blended depth and normal (the paper's), > 0 the pixel's median surface, the splats
  within this many pixel footprints of its median depth. By default the value the model
  was fitted with (below); `0` for another tool's PLY. A value given here is used as given.

**The model's shadow maps.** Stage 4 records the shadow-map and receiver settings it fitted
with (`VisibilityConfig`: projection, depth bias, occluder layer, receivers) in the PLY's
header (`comment mi_shadowgs visibility {...}`), and the plugin renders its maps with them,
as `mi-shadowgs relight` does for the run: a `cpu-*` model gets its orthographic maps with a
one-texel bias, a `paper` one the paper's perspective maps and depth threshold. A model
saved before that record takes them from the run's manifest beside it, or, with only its
`receiver_band` record, the paper's maps with that band. Another tool's PLY gets the
paper's maps. A malformed record is an error naming the file, even where a property above
is given.

**Emitters:** every `directional` emitter (direction from its `to_world`, `irradiance`),
every infinite emitter (`envmap`, `constant`: mean radiance over each of the 128 equal-area
grid cells of the upper hemisphere, times `2 pi / 128`) and every lamp: a `point` emitter
(`position`, `intensity` in W/sr), a `spot` (position and axis from its `to_world`,
`intensity`, and Mitsuba's cone: full between the axis and `beam_width`, falling linearly
in angle to 0 at `cutoff_angle`) and an `area` emitter on a `sphere` shape (its centre and
radius R from the shape, its `radiance` L shining as a lamp of intensity L pi R^2). A lamp
must stand above the base plane y = 0 and outside the surfels' bounding sphere, and a
spot's cone must reach that sphere; a textured spot or radiance, an area light on another
shape, any other emitter type and a scene without emitters are errors. One shadow map per
light is rendered the first time the light is seen and kept with the integrator: a later
`mi.render` of the same emitters (any sensor at the same distance) reuses the maps and the
env map's grid radiance (re-integrated only when the env map's parameters change).

**Not used:** sampler, spp and seeds (deterministic); the sensor's `near_clip` and
`far_clip`; not differentiable (`render_forward` and `render_backward` are not
implemented), and `mi.traverse` exposes none of its surfels' parameters: the model is the
file's, checked as it is read. The film gets `R, G, B` (and `A` = coverage). Sensors as for
`surfel_raster`: `perspective` or `orthographic`, without a principal-point offset or crop
window.

```xml
<scene version="3.0.0">
    <integrator type="surfel_relight">
        <string name="filename" value="material.ply"/>
        <boolean name="specular" value="false"/>
    </integrator>
    <emitter type="directional">
        <vector name="direction" value="-0.5, -0.8, 0.3"/>
        <rgb name="irradiance" value="3"/>
    </emitter>
    <sensor type="perspective"> ... <film type="hdrfilm"/> </sensor>
</scene>
```
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import render as core_render
from mi_shadowgs.core import shading
from mi_shadowgs.io import ply
from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.visibility.shadow_maps import SceneBounds, VisibilityConfig


def _bool(props, name, default):
    # A <string name="specular" value="false"/> was bool("false"), i.e. True.
    value = props.get(name, default)
    if not isinstance(value, bool):
        raise ValueError(f"surfel_relight: {name!r} must be a boolean (<boolean name="
                         f"\"{name}\" value=\"false\"/>), got {value!r}")
    return value


def _int(props, name, default):
    # A <float name="shadow_resolution" value="64.9"/> was cut to 64 without a word.
    value = props.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"surfel_relight: {name!r} must be an integer (<integer name="
                         f"\"{name}\" .../>), got {value!r}")
    return value


class SurfelRelightIntegrator(mi.SamplingIntegrator):
    def __init__(self, props: mi.Properties):
        super().__init__(props)
        if "filename" not in props:
            raise ValueError("surfel_relight: the 'filename' property (a PLY model) is required")
        self.filename = str(mi.file_resolver().resolve(str(props.get("filename"))))
        self.surfels = ply.load_ply(self.filename)
        missing = [c for c in shading.MATERIAL_CHANNELS if c not in self.surfels.channels]
        if missing:
            raise ValueError(f"surfel_relight ({self.filename}): the model lacks channel(s) "
                             f"{missing}; it needs albedo, roughness and metallic (stage 4)")
        recorded = relight.recorded_specular(self.filename)
        self.specular = _bool(props, "specular", True if recorded is None else recorded)
        self.visibility = _bool(props, "visibility", True)
        self.indirect = str(props.get("indirect", "none"))
        if self.indirect not in ("none", "keep"):
            raise ValueError(f"surfel_relight: 'indirect' must be 'none' or 'keep', got "
                             f"{self.indirect!r}")
        fitted = relight.recorded_visibility(self.filename) or VisibilityConfig()
        res = _int(props, "shadow_resolution", fitted.resolution)
        env = _int(props, "env_samples", 64)
        if res < 1 or env < 1:
            raise ValueError("surfel_relight: 'shadow_resolution' and 'env_samples' must be >= 1")
        self.receiver_band = float(props.get("receiver_band", fitted.receiver_band))
        if not 0 <= self.receiver_band < float("inf"):
            raise ValueError(f"surfel_relight: 'receiver_band' must be finite and >= 0, got "
                             f"{self.receiver_band}")
        self.vis_config = dataclasses.replace(fitted, resolution=res,
                                              receiver_band=self.receiver_band)
        self.relight_config = relight.RelightConfig(indirect=self.indirect, env_samples=env)
        # Shadow maps per light direction and env-map grid radiance, kept between renders.
        self.cache = relight.RelightCache()

    def bounds(self, camera) -> SceneBounds:
        """The surfels' bounding sphere: what the shadow maps cover, and where a lamp may
        not stand."""
        pos = np.stack([np.asarray(self.surfels.position[k]) for k in range(3)], -1)
        return SceneBounds.from_points(pos, [camera])

    def light_set(self, scene, bounds: SceneBounds | None = None) -> shading.LightSet:
        """The scene's emitters as lights (lamps checked against ``bounds``, by default those
        seen from the scene's first sensor)."""
        if bounds is None:
            bounds = self.bounds(core_render.sensor_camera(scene.sensors()[0]))
        return relight.emitter_light_set(scene.emitters(), self.relight_config, self.cache,
                                         where="surfel_relight", bounds=bounds)

    def _image(self, scene, sensor) -> mi.TensorXf:
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        camera = core_render.sensor_camera(sensor)
        bounds = self.bounds(camera)
        lights = self.light_set(scene, bounds)
        model = relight.RelightModel(self.surfels, self.specular, self.visibility,
                                     receiver_band=self.receiver_band)
        maps = self.cache.shadow_maps(model, lights, bounds, self.vis_config)
        factor = relight.indirect_factor(model, lights, self.relight_config)
        out = relight.relight_view(model, camera, lights, maps, factor)
        film = sensor.film()
        has_alpha = mi.has_flag(film.flags(), mi.FilmFlags.Alpha)
        layout = core_render.FilmLayout(has_alpha=has_alpha, aovs=())
        images = {"rgb": mi.TensorXf(out["rgb"]), "alpha": mi.TensorXf(out["alpha"][..., None])}
        return core_render.develop_film(film, layout, [], images, "surfel_relight")

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not develop:
            raise ValueError("surfel_relight: only develop=True is supported")
        with dr.suspend_grad():
            image = self._image(scene, sensor)
            if evaluate:
                dr.eval(image)
        return image

    def to_string(self):
        return (f"SurfelRelightIntegrator[filename={self.filename!r}, "
                f"surfels={self.surfels.count}, specular={self.specular}, "
                f"visibility={self.visibility}, receiver_band={self.receiver_band}]")


mi.register_integrator("surfel_relight", lambda props: SurfelRelightIntegrator(props))
