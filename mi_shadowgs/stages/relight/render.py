"""Stage 5: relight a decomposed surfel model under new lights (directional, lamps, env map).

A model is surfels with "albedo", "roughness", "metallic" and "indirect_sh" channels
(``stage_material``). New lights become a ``LightSet`` (directions with RGB weights):
directional lights as they are (their exact directions, irradiance E), lamps as local lights
(``lamps``: a position, its intensity as the irradiance at the scene's centre, 1/r^2
falloff, a spot's cone), an environment map integrated over the 128 grid directions (mean
radiance over each direction's cell times dw = 2 pi / 128). Visibility is recomputed for
the new lights with new shadow maps of the surfels (rendered once per light, shared by
every view).

Indirect light under new lights: the fitted L_ind is what the *training* light bounced
around; reusing it as is would keep the old lighting's glow, dropping it would darken the
shadows that interreflection fills in. We keep its spatial pattern and scale it by the ratio
of the new to the training lights' irradiance on an unoccluded upward-facing surface,
E_up = sum_k E_k max(0, l_k . y) (mode "scaled", the default; "none" drops it, "keep" reuses
it unchanged); a lamp counts with its irradiance at the lights' reference point (the scene's
centre), along its direction from there, a spot's cone included. This is a first-order
guess, exact only when the new light illuminates the scene the way the old one did; it is
documented as such.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Sequence
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit, shading
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import light_grid, nearest_grid_index, solid_angle
from mi_shadowgs.core.raster import RasterConfig, rasterize
from mi_shadowgs.core.surfels import Surfels, eval_sh
from mi_shadowgs.stages.material.outputs import (
    BAND_METADATA_KEY,
    SPECULAR_METADATA_KEY,
    VISIBILITY_METADATA_KEY,
)
from mi_shadowgs.stages.relight import lamps as lamp_mod
from mi_shadowgs.stages.visibility.lamp_maps import lamp_arguments
from mi_shadowgs.stages.visibility.shadow_maps import (
    MapCache,
    SceneBounds,
    VisibilityConfig,
    render_shadow_maps,
)

INDIRECT_MODES = ("scaled", "none", "keep")
DEFAULT_RASTER = RasterConfig()
DEFAULT_VISIBILITY = VisibilityConfig()


@dataclasses.dataclass(frozen=True)
class RelightConfig:
    indirect: str = "scaled"  # see the module docstring
    n_directions: int = 128  # grid of the environment-map integration
    # Env-map samples per grid direction (a regular polar grid over the hemisphere): 2048
    # gives 256 x 1024 samples, 0.35 degrees apart, well inside a generated sky's pixels
    # (1.4 degrees) and its sun disc (4 degrees radius).
    env_samples: int = 2048

    def __post_init__(self):
        if self.indirect not in INDIRECT_MODES:
            raise ValueError(f"RelightConfig.indirect must be one of {INDIRECT_MODES}, got "
                             f"{self.indirect!r}")


DEFAULT_RELIGHT = RelightConfig()


@dataclasses.dataclass
class RelightModel:
    """What relighting needs from stage 4."""

    surfels: Surfels  # with albedo/roughness/metallic/indirect_sh channels
    specular: bool  # the GGX lobe is modelled
    use_visibility: bool  # False: V = 1 (the "w/o visibility" ablation)
    train_lights: shading.LightSet | None = None  # for the indirect scaling
    # The receivers it was fitted with (``VisibilityConfig.receiver_band``; 0: blended).
    receiver_band: float = 0.0


def recorded_specular(path) -> bool | None:
    """Whether a stage-4 PLY was fitted with the specular lobe: its header's record; else
    the ``specular`` field of the ``light.json`` beside it when the run's manifest there lists
    both (models saved before the record); None for a model with neither (another tool's).
    A malformed record is an error naming the file."""
    import json

    from mi_shadowgs.io.ply import PlyError, read_ply_metadata
    from mi_shadowgs.io.provenance import read_manifest

    path = Path(path)
    text = read_ply_metadata(path).get(SPECULAR_METADATA_KEY)
    if text is not None:
        if text not in ("true", "false"):
            raise PlyError(f"{path}: header comment {SPECULAR_METADATA_KEY} {text!r} is not "
                           "true or false")
        return text == "true"
    manifest = read_manifest(path.parent)
    light = path.parent / "light.json"
    if not (manifest and path.name in manifest["files"] and "light.json" in manifest["files"]
            and light.is_file()):
        return None
    try:
        value = json.loads(light.read_text())["specular"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{light}: missing or malformed field 'specular' ({exc})") from None
    if not isinstance(value, bool):
        raise ValueError(f"{light}: field 'specular' must be true or false, got {value!r}")
    return value


def recorded_visibility(path) -> VisibilityConfig | None:
    """The shadow-map and receiver settings a stage-4 PLY was fitted with: its header's
    record; else the visibility settings of the run's manifest beside it that lists it, read
    as relighting reads them (``config.recorded_config``: fields it predates keep their
    defaults), with the header's band where the model has only that; else the paper's maps
    with the header's band; None for a model with none of these (another tool's). A
    malformed record is an error naming the file."""
    import json

    from mi_shadowgs.config import ConfigError, recorded_config
    from mi_shadowgs.io.ply import PlyError, read_ply_metadata
    from mi_shadowgs.io.provenance import MANIFEST_NAME, read_manifest

    path = Path(path)
    header = read_ply_metadata(path)
    if VISIBILITY_METADATA_KEY in header:
        text = header[VISIBILITY_METADATA_KEY]
        try:
            saved = json.loads(text)
            return recorded_config(VisibilityConfig, saved, lambda: None,
                                   f"{path}: header comment {VISIBILITY_METADATA_KEY}")
        except json.JSONDecodeError as err:
            raise PlyError(f"{path}: header comment {VISIBILITY_METADATA_KEY} is not JSON "
                           f"({err})") from err
        except ConfigError as err:
            raise PlyError(str(err)) from err
    band = header.get(BAND_METADATA_KEY)
    if band is not None:
        try:
            band = float(band)
        except ValueError:
            band = float("nan")
        if not band >= 0:
            raise PlyError(f"{path}: header comment {BAND_METADATA_KEY} "
                           f"{header[BAND_METADATA_KEY]!r} is not a number >= 0")
    manifest = read_manifest(path.parent)
    config = None
    if manifest and path.name in manifest["files"]:
        config = recorded_config(VisibilityConfig, (manifest.get("settings") or {})
                                 .get("visibility"), lambda: None,
                                 f"{path.parent / MANIFEST_NAME}: settings.visibility")
    if band is None:
        return config
    return dataclasses.replace(config or VisibilityConfig(), receiver_band=band)


def directional_light_set(directions, irradiance) -> shading.LightSet:
    """Directional lights: unit directions toward the lights [K, 3], irradiance [K] or [K, 3]."""
    d = np.atleast_2d(np.asarray(directions, np.float64))
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    e = np.asarray(irradiance, np.float64).reshape(len(d), -1)
    if e.shape[1] == 1:
        e = np.repeat(e, 3, axis=1)
    if e.shape[1] != 3 or not np.all(np.isfinite(e)) or not np.all(np.isfinite(d)):
        raise ValueError(f"directional lights: bad directions {d.shape} or irradiance {e.shape}")
    e = e.astype(np.float32)
    return shading.LightSet(d, mi.Color3f(*(jit.array(e[:, k]) for k in range(3))))


def point_light_set(positions, intensity, center, radii=None) -> shading.LightSet:
    """Lamps at ``positions`` [K, 3] (world) of radiant intensity ``intensity`` [K] or
    [K, 3] (W/sr) and ``radii`` [K] (world units; default 0: points), weighted by their
    irradiance at ``center`` [3] (the scene's centre, e.g. ``SceneBounds.center``)."""
    pos = np.atleast_2d(np.asarray(positions, np.float64))
    inten = np.asarray(intensity, np.float64).reshape(len(pos), -1)
    inten = np.repeat(inten, 3, axis=1) if inten.shape[1] == 1 else inten
    radii = np.zeros(len(pos)) if radii is None else np.asarray(radii, np.float64).reshape(-1)
    if pos.shape[1] != 3 or inten.shape[1] != 3 or len(radii) != len(pos):
        raise ValueError(f"point lights: bad positions {pos.shape}, intensity {inten.shape} "
                         f"or radii {radii.shape}")
    lamps = [lamp_mod.Lamp(tuple(map(float, p)), tuple(map(float, i)), float(r),
                           source=f"point light {k}")
             for k, (p, i, r) in enumerate(zip(pos, inten, radii, strict=True))]
    for lamp in lamps:
        lamp_mod.check_lamp_values(lamp)
    return lamp_mod.lamp_light_set(lamps, center)


def lights_from_json(entry: dict, center=None) -> shading.LightSet:
    """A ``lights.json`` relighting entry of type "directional", or "point" (lamps: each
    light's ``position``, ``intensity`` in W/sr and ``radius``; their weights are their
    irradiance at ``center`` [3], the scene's centre)."""
    if entry.get("type") == "point":
        if center is None:
            raise ValueError(f"lights.json: relighting {entry.get('name')!r} has lamps; "
                             "their weights need the scene's centre")
        return lamp_mod.lamp_light_set(lamp_mod.lamps_from_json(entry, "lights.json"), center)
    if entry.get("type") != "directional":
        raise ValueError(f"lights.json: relighting {entry.get('name')!r} has type "
                         f"{entry.get('type')!r}; use envmap_light_set for env maps")
    lts = entry.get("lights") or []
    if not lts:
        raise ValueError(f"lights.json: relighting {entry.get('name')!r} has no lights")
    return directional_light_set([lt["direction"] for lt in lts], [lt["irradiance"] for lt in lts])


def grid_light_set(radiance: np.ndarray, n: int | None = None) -> shading.LightSet:
    """A radiance map over the grid ([n] white or [n, 3]) as a LightSet (L dw per direction);
    directions with zero radiance are left out (no shadow map, no shading work)."""
    rad = np.asarray(radiance, np.float64)
    rad = rad[:, None].repeat(3, 1) if rad.ndim == 1 else rad
    n = len(rad) if n is None else n
    keep = np.flatnonzero(np.any(rad > 0, axis=1))
    w = (rad[keep] * solid_angle(n)).astype(np.float32)
    weights = mi.Color3f(*(jit.array(w[:, k]) for k in range(3)))
    return shading.LightSet(light_grid(n)[keep], weights)


def envmap_grid_radiance(emitter, config: RelightConfig = DEFAULT_RELIGHT) -> np.ndarray:
    """Radiance [n, 3] of an infinite Mitsuba emitter over each grid direction's cell, such
    that radiance x ``solid_angle(n)`` is the emitter's integral over the cell.

    A midpoint rule on a regular (polar angle, azimuth) grid over the upper hemisphere,
    each sample weighted by its solid angle sin(theta) dtheta dphi and given to its nearest
    grid direction (the grid's Voronoi cells). A regular polar grid resolves a small sun
    near the zenith as well as anywhere else (equal-area rows there are ~3.6 degrees apart).
    The lower hemisphere is left out: the base occludes it for everything above it.
    """
    n = config.n_directions
    rows = max(8, int(np.sqrt(n * config.env_samples / 4)))  # polar angle over 90 degrees
    d, weight, cell = _hemisphere_samples(rows, n)
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    # Infinite emitters look up -wi: wi is the propagation direction (from the env inward).
    si.wi = mi.Vector3f(*(jit.host(-d[:, k].astype(np.float32)) for k in range(3)))
    with dr.suspend_grad():
        val = emitter.eval(si)
    rgb = np.stack([np.asarray(val[k], np.float64) for k in range(3)], -1)
    acc = np.zeros((n, 3))
    np.add.at(acc, cell, rgb * weight[:, None])
    return acc / solid_angle(n)


@functools.lru_cache(maxsize=4)
def _hemisphere_samples(rows: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The integration grid of ``envmap_grid_radiance``: sample directions [m, 3], their
    solid angles [m] and their grid cells [m]. Kept: the nearest-cell search is most of an
    integration's time, and a turned env map (the viewer's rotation slider) reuses it."""
    cols = 4 * rows  # azimuth over 360 degrees: square samples at the horizon
    theta = (np.arange(rows) + 0.5) * (0.5 * np.pi / rows)
    phi = (np.arange(cols) + 0.5) * (2 * np.pi / cols)
    th, ph = (a.ravel() for a in np.meshgrid(theta, phi, indexing="ij"))
    d = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1)  # [m, 3]
    weight = np.sin(th) * (0.5 * np.pi / rows) * (2 * np.pi / cols)  # [m] solid angle
    cell = nearest_grid_index(d, light_grid(n))
    for a in (d, weight, cell):
        a.setflags(write=False)  # shared between calls
    return d, weight, cell


def envmap_light_set(emitter, config: RelightConfig = DEFAULT_RELIGHT) -> shading.LightSet:
    """The 128-direction light set of an infinite emitter (``envmap``, ``constant``); the
    evaluation scores the env-map relightings of ``lights.json`` with it."""
    return grid_light_set(envmap_grid_radiance(emitter, config), config.n_directions)


def upward_irradiance(lights: shading.LightSet) -> float:
    """Mean-RGB irradiance the lights give an unoccluded surface facing +Y."""
    w = np.stack([np.asarray(lights.weights[k], np.float64) for k in range(3)], -1)
    up = w.mean(1) * np.maximum(np.asarray(lights.directions)[:, 1], 0.0)
    if lights.cones is not None:  # a spot lights the centre only inside its cone
        up = up * lamp_mod.cone_at(lights, lights.center)
    return float(np.sum(up))


def indirect_factor(model: RelightModel, lights: shading.LightSet, config: RelightConfig) -> float:
    if config.indirect == "none":
        return 0.0
    if config.indirect == "keep" or model.train_lights is None:
        return 1.0
    e_train = upward_irradiance(model.train_lights)
    return upward_irradiance(lights) / e_train if e_train > 0 else 0.0


def _check_model(surfels: Surfels) -> None:
    missing = [c for c in shading.MATERIAL_CHANNELS if c not in surfels.channels]
    if missing:
        raise ValueError(f"relight: the model lacks channel(s) {missing} (run stage 4)")


@dataclasses.dataclass
class ViewBuffers:
    """One rasterization of a view: what no light changes (``view_buffers``)."""

    geom: shading.PixelGeometry
    albedo: mi.Color3f | None = None  # [P] the material channels (None: not asked for)
    roughness: mi.Float | None = None
    metallic: mi.Float | None = None
    indirect: mi.Color3f | None = None  # [P] the fitted indirect irradiance (unscaled)
    colors: dict = dataclasses.field(default_factory=dict)  # name -> Color3f [P] (extra)


def view_buffers(surfels: Surfels, camera: Camera, raster: RasterConfig = DEFAULT_RASTER,
                 material: bool = True, extra: dict | None = None,
                 receiver_band: float = 0.0) -> ViewBuffers:
    """One rasterization of a view: geometry (its receivers per ``receiver_band``, see
    ``VisibilityConfig``), with ``material`` the albedo, roughness, metallic and indirect
    channels, and the ``extra`` per-surfel colour channels (name -> TensorXf [N, 3])."""
    chans = {}
    if material:
        _check_model(surfels)
        chans = {k: surfels.channels[k] for k in shading.MATERIAL_CHANNELS}
        if shading.INDIRECT_CHANNEL in surfels.channels:  # per surfel, as stage 4 fits it
            chans[shading.INDIRECT_CHANNEL] = eval_sh(
                surfels.channels[shading.INDIRECT_CHANNEL],
                shading.facing_normals(surfels, camera), offset=0.0)
    chans.update(extra or {})
    geometry_chans, aovs = shading.geometry_request(surfels, camera, receiver_band)
    chans.update(geometry_chans)

    def color(name: str) -> mi.Color3f:
        a = out[name].array
        return mi.Color3f(*(shading.channel(a, 3, c) for c in range(3)))

    with dr.suspend_grad():
        out = rasterize(surfels, camera, chans or None, aovs=aovs, config=raster)
        shading.with_surface_aovs(out, surfels, camera, raster, receiver_band)
        buf = ViewBuffers(shading.geometry_from_aovs(out, camera),
                          colors={name: color(name) for name in extra or {}})
        if material:  # as stage 4 fits them (fit.view_maps): the albedo blended, the
            # roughness, metallic and indirect irradiance the covering surface's own
            cover = out["alpha"].array
            buf.albedo = color("albedo")
            buf.roughness = shading.per_surface(out["roughness"].array, cover)
            buf.metallic = shading.per_surface(out["metallic"].array, cover)
            if shading.INDIRECT_CHANNEL in out:
                ind = shading.per_surface(out[shading.INDIRECT_CHANNEL].array, cover)
                buf.indirect = mi.Color3f(*(shading.channel(ind, 3, c) for c in range(3)))
    return buf


def shadow_maps_for(model: RelightModel, lights: shading.LightSet, bounds: SceneBounds,
                    vis_config: VisibilityConfig = DEFAULT_VISIBILITY):
    if not model.use_visibility or lights.count == 0:
        return None
    return render_shadow_maps(model.surfels, lights.directions, bounds, vis_config,
                              **lamp_arguments(lights))


def relight_view(model: RelightModel, camera: Camera, lights: shading.LightSet, maps,
                 factor: float, raster: RasterConfig = DEFAULT_RASTER,
                 buffers: bool = False, only_rgb: bool = False,
                 view: ViewBuffers | None = None) -> dict:
    """Relit image and buffers of one view: "rgb" [H, W, 3], "albedo" [H, W, 3] (diffuse,
    (1 - m) a), "direct_irradiance" [H, W] (white sum_k E_k (n . l_k)^+ V_k, mean RGB),
    "alpha" [H, W] as numpy. With ``buffers`` also "roughness" [H, W], "metallic" [H, W],
    "normal" [H, W, 3] (world, 0 on background) and "visibility" [H, W, K] (1 where light k
    is unoccluded; all 1 without shadow maps). ``only_rgb``: "rgb" and "alpha" alone (the
    relight command's frames: no irradiance pass). ``view``: the view's buffers when the
    caller has them (``RelightCache.view_buffers``), else rasterized here."""
    h, w = camera.height, camera.width
    if view is None:
        view = view_buffers(model.surfels, camera, raster, receiver_band=model.receiver_band)
    geom, albedo, rough, metal, ind = (view.geom, view.albedo, view.roughness, view.metallic,
                                       view.indirect)
    with dr.suspend_grad():
        vis = (None if maps is None else
               maps.evaluate(geom.points, geom.normal, geom.footprint))
        indirect = ind * factor if ind is not None and factor > 0 else None
        rgb = shading.shade(geom, albedo, rough, metal, lights, vis, indirect, model.specular)
        out = {"rgb": color_image(rgb, h, w), "alpha": geom.alpha.numpy().reshape(h, w)}
        if only_rgb:
            return out
        ones = mi.Color3f(1.0)
        irr = shading.direct(geom, ones * dr.pi, dr.zeros(mi.Float, dr.width(geom.alpha)),
                       dr.zeros(mi.Float, dr.width(geom.alpha)), lights, vis, False)
        diff_albedo = albedo * (1.0 - metal)
    out.update({"albedo": color_image(diff_albedo, h, w),
                "direct_irradiance": color_image(irr, h, w).mean(-1)})
    if buffers:
        covered = out["alpha"][..., None] > 0
        out["roughness"] = rough.numpy().reshape(h, w)
        out["metallic"] = metal.numpy().reshape(h, w)
        out["normal"] = np.where(covered, color_image(mi.Color3f(geom.normal), h, w), 0.0)
        k = lights.count
        out["visibility"] = (  # pixel-major [P * K]
            np.ones((h, w, k), np.float32) if vis is None else
            np.asarray(vis.numpy(), np.float32).reshape(h, w, k))
    return out


def color_image(c: mi.Color3f, h: int, w: int) -> np.ndarray:
    """A Color3f [H * W] as a numpy image [H, W, 3]."""
    return np.stack([np.asarray(c[k], np.float32) for k in range(3)], -1).reshape(h, w, 3)


def relight_views(model: RelightModel, cameras: Sequence[Camera], lights: shading.LightSet,
                  bounds: SceneBounds, config: RelightConfig = DEFAULT_RELIGHT,
                  vis_config: VisibilityConfig = DEFAULT_VISIBILITY,
                  raster: RasterConfig = DEFAULT_RASTER, progress: bool = False,
                  cache: RelightCache | None = None,
                  only_rgb: bool = False) -> tuple[list[dict], float]:
    """Relight every camera's view; returns the per-view dicts and the time (s) to
    rasterize and shade them, shadow maps included. With ``cache``, the shadow maps and
    each view's rasterization (``RelightCache.view_buffers``) are made once and shared
    with later calls; the time still counts the rasterizations it reused, at what they
    took to make, so that it is what a relighting of these views costs. ``only_rgb``: each
    view's "rgb" and "alpha" alone (``relight_view``), without the second shading pass
    over every light that the irradiance buffer takes."""
    from tqdm import tqdm

    dr.sync_thread()
    t0 = time.perf_counter()
    maps = (shadow_maps_for(model, lights, bounds, vis_config) if cache is None else
            cache.shadow_maps(model, lights, bounds, vis_config))
    factor = indirect_factor(model, lights, config)
    out, reused = [], 0.0
    for cam in tqdm(cameras, desc="relight", disable=not progress):
        view = None
        if cache is not None:
            view, made_s, hit = cache.view_buffers(model, cam, raster)
            reused += made_s if hit else 0.0
        out.append(relight_view(model, cam, lights, maps, factor, raster, only_rgb=only_rgb,
                                view=view))
    dr.sync_thread()
    return out, time.perf_counter() - t0 + reused


# -- light sources of the relight command and the plugin ---------------------------------
def standard_turntable(count: int = 8, elevation_deg: float = 45.0,
                       irradiance: float = 1.0) -> list[tuple[str, shading.LightSet]]:
    """One directional light per azimuth 0, 360/count, ... at ``elevation_deg``: the light
    turntable of the report's previews."""
    from mi_shadowgs.core.directions import direction_from_angles

    out = []
    for i in range(count):
        az = 360.0 * i / count
        d = np.asarray(direction_from_angles(az, elevation_deg), np.float64).reshape(1, 3)
        out.append((f"az{az:03.0f}_el{elevation_deg:02.0f}",
                    directional_light_set(d, [irradiance])))
    return out


def combine_light_sets(sets: Sequence[shading.LightSet]) -> shading.LightSet:
    """One LightSet holding every light of ``sets`` (e.g. a sun, a sky and a lamp); the
    lamps' weights are taken to the first reference point among them (``relocate``)."""
    if all(s.positions is None for s in sets):
        dirs = np.concatenate([np.asarray(s.directions, np.float64).reshape(-1, 3)
                               for s in sets])
        return directional_light_set(dirs, np.concatenate([light_weights(s) for s in sets]))
    center = next(np.asarray(s.center, np.float64) for s in sets if s.positions is not None)
    sets = [relocate(s, center) for s in sets]
    rows = [lamp_mod.local_rows(s) for s in sets]
    pos, radii, cones = (np.concatenate([r[i] for r in rows]) for i in range(3))
    dirs = np.concatenate([np.asarray(s.directions, np.float64).reshape(-1, 3) for s in sets])
    wf = np.concatenate([light_weights(s) for s in sets]).astype(np.float32)
    return shading.LightSet(dirs, mi.Color3f(*(jit.array(wf[:, k]) for k in range(3))),
                            pos, radii, center,
                            None if np.all(np.isnan(cones)) else cones)


def relocate(lights: shading.LightSet, center) -> shading.LightSet:
    """``lights`` with the reference point ``center`` [3]: each lamp's weight becomes its
    irradiance there (intensity / |p - c|^2) and its direction points from there."""
    c = np.asarray(center, np.float64).reshape(3)
    if lights.positions is None or (lights.center is not None and
                                    np.array_equal(np.asarray(lights.center, np.float64), c)):
        return lights
    pos, _, _ = lamp_mod.local_rows(lights)
    loc = lights.local
    w = light_weights(lights)
    w[loc] = lamp_mod.intensities(lights)[loc] / np.sum((pos[loc] - c) ** 2, axis=1)[:, None]
    dirs = np.array(lights.directions, np.float64).reshape(-1, 3)
    dirs[loc] = (pos[loc] - c) / np.linalg.norm(pos[loc] - c, axis=1, keepdims=True)
    wf = w.astype(np.float32)
    return dataclasses.replace(lights, directions=dirs, center=c, weights=mi.Color3f(
        *(jit.array(wf[:, k]) for k in range(3))))


def light_weights(lights: shading.LightSet) -> np.ndarray:
    """The RGB irradiance of each light as numpy [K, 3]."""
    return (np.stack([np.asarray(lights.weights[k], np.float64) for k in range(3)], -1)
            .reshape(-1, 3))


def scale_light_set(lights: shading.LightSet, factor: float) -> shading.LightSet:
    """``lights`` with every weight (and so every lamp's intensity) times ``factor``."""
    if lights.positions is None:
        return directional_light_set(lights.directions, light_weights(lights) * factor)
    w = (light_weights(lights) * factor).astype(np.float32)
    return dataclasses.replace(lights, weights=mi.Color3f(*(jit.array(w[:, k])
                                                             for k in range(3))))


def emitter_light_set(emitters, config: RelightConfig = DEFAULT_RELIGHT,
                      cache: RelightCache | None = None, where: str = "scene",
                      bounds: SceneBounds | None = None) -> shading.LightSet:
    """The lights of Mitsuba emitters: each ``directional`` emitter as it is, each infinite
    one (``envmap``, ``constant``) over the grid (``envmap_grid_radiance``, cached by its
    contents in ``cache``), each ``point``, ``spot`` and ``area`` emitter on a ``sphere`` as
    a lamp (``lamps.mitsuba_lamp``; checked against ``bounds``, the model's
    ``SceneBounds``, whose centre is the lamps' reference point). Any other emitter type,
    a lamp outside the model's reach (``lamps.check_lamps``), or no emitter at all, is a
    ValueError naming ``where``."""
    sets, lamps = [], []
    for e in emitters:
        lamp = lamp_mod.mitsuba_lamp(e, where)
        if lamp is not None:
            lamps.append(lamp)
            continue
        name = e.class_name()
        if "Directional" in name:
            p = mi.traverse(e)
            to_world = mi.ScalarTransform4f(np.asarray(p["to_world"].matrix, np.float64)
                                            .reshape(4, 4))
            prop = np.asarray(to_world @ mi.ScalarVector3f(0, 0, 1), np.float64)
            sets.append(directional_light_set(
                -prop / np.linalg.norm(prop),
                np.asarray(p["irradiance.value"], np.float64).reshape(-1)[:3]))
        elif mi.has_flag(e.flags(), mi.EmitterFlags.Infinite):
            rad = (cache.envmap_radiance(e, config) if cache is not None else
                   envmap_grid_radiance(e, config))
            ls = grid_light_set(rad, config.n_directions)
            if ls.count:
                sets.append(ls)
        else:
            raise ValueError(f"{where}: emitter {e.id()!r} ({name}) is not supported; use "
                             "directional, point, spot, area (on a sphere) or infinite "
                             "(envmap, constant) emitters")
    if lamps:
        if bounds is None:
            raise ValueError(f"{where}: lamps need the model's scene bounds")
        lamp_mod.check_lamps(lamps, bounds)
        sets.append(lamp_mod.lamp_light_set(lamps, bounds.center))
    if not sets:
        raise ValueError(f"{where}: no emitter to relight with")
    return combine_light_sets(sets)


GEOMETRY_FIELDS = ("position", "log_scale", "rotation", "opacity_logit")


def _nbytes(x) -> int:
    """Bytes of the Dr.Jit arrays in ``x`` (a dataclass, dict, tuple or array; others 0)."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return sum(_nbytes(getattr(x, f.name)) for f in dataclasses.fields(x))
    if isinstance(x, dict):
        return sum(_nbytes(v) for v in x.values())
    if isinstance(x, tuple | list):
        return sum(_nbytes(v) for v in x)
    if not dr.is_array_v(x):
        return 0
    components = 1 if dr.is_tensor_v(x) or dr.depth_v(x) == 1 else dr.size_v(x)
    return dr.width(x) * components * dr.itemsize_v(x)


class RelightCache:
    """Shadow maps, views' rasterizations and env-map grid radiance kept between renders
    of one model.

    A shadow map depends on the surfels, its light direction, the scene bounds and the
    visibility settings, never on the view: ``shadow_maps`` keeps a ``MapCache`` per
    geometry and bounds, which renders only the directions it has not seen and reuses the
    rest. ``envmap_radiance`` keys an infinite emitter's grid radiance on a digest of its
    parameters (image, scale, to_world), so an edited env map is integrated again. It holds
    at most ``max_map_bytes`` of maps per geometry, ``max_sets`` assembled sets and
    ``max_envmaps`` emitters (oldest dropped first). ``view_buffers`` keeps each view's
    rasterization, which no light changes, up to ``max_view_bytes``.
    """

    def __init__(self, max_map_bytes: int = 1 << 30, max_envmaps: int = 8,
                 max_sets: int = 16, max_view_bytes: int = 1 << 30):
        self.max_map_bytes = max_map_bytes
        self.max_envmaps = max_envmaps
        self.max_sets = max_sets
        self.max_view_bytes = max_view_bytes
        # (model ids, camera id, raster, band) -> (ViewBuffers, seconds, bytes, held objects)
        self._views: dict[tuple, tuple] = {}
        self._caches: dict[tuple, MapCache] = {}  # (geometry ids, bounds) -> its maps
        self._sets: dict[tuple, object] = {}  # all keys of a light set -> its ShadowMaps
        self._models: dict[tuple, tuple] = {}
        self._env: dict[str, np.ndarray] = {}

    @property
    def rendered(self) -> int:
        """Shadow maps rendered (not reused), for tests and benchmarks."""
        return sum(c.rendered for c in self._caches.values())

    def shadow_maps(self, model: RelightModel, lights: shading.LightSet, bounds: SceneBounds,
                    vis_config: VisibilityConfig = DEFAULT_VISIBILITY):
        """``shadow_maps_for``, reusing every map of a direction seen before."""
        if not model.use_visibility or lights.count == 0:
            return None
        # Shadow maps see only the geometry: a model with other material channels (e.g.
        # the evaluation's rescaled albedo) shares the maps of its geometry.
        geometry = tuple(getattr(model.surfels, k) for k in GEOMETRY_FIELDS)
        base = (tuple(id(g) for g in geometry), bounds)
        self._models[base[0]] = geometry  # held: the ids stay unique
        dirs = np.asarray(lights.directions, np.float64).reshape(-1, 3)
        lamps = lamp_arguments(lights)
        key = (*base, vis_config, dirs.round(12).tobytes(),
               *(np.asarray(v, np.float64).round(12).tobytes() for v in lamps.values()))
        if key in self._sets:  # the same lights again: the assembled maps as they are
            return self._sets[key]
        if base not in self._caches:
            self._caches[base] = MapCache(model.surfels, bounds, self.max_map_bytes)
        maps = self._caches[base].maps(dirs, vis_config, **lamps)
        self._sets[key] = maps
        while len(self._sets) > self.max_sets:  # oldest first
            self._sets.pop(next(iter(self._sets)))
        return maps

    def view_buffers(self, model: RelightModel, camera: Camera,
                     raster: RasterConfig = DEFAULT_RASTER) -> tuple[ViewBuffers, float, bool]:
        """(``view_buffers`` of ``model`` seen by ``camera``, the seconds they took to make,
        whether they were reused). A view's rasterization depends on the surfels (their
        geometry and every channel), the camera, the raster settings and the receiver band,
        never on the lights: each is made once, keyed on the identity of those objects
        (held, so that the identities stay unique), and kept up to ``max_view_bytes``
        (oldest dropped first)."""
        surfels = model.surfels
        held = (*(getattr(surfels, k) for k in GEOMETRY_FIELDS), *surfels.channels.values(),
                camera)
        key = (tuple(id(x) for x in held), tuple(surfels.channels), raster,
               model.receiver_band)
        if key in self._views:
            return self._views[key][0], self._views[key][1], True
        dr.sync_thread()
        t0 = time.perf_counter()
        view = view_buffers(surfels, camera, raster, receiver_band=model.receiver_band)
        dr.sync_thread()
        seconds = time.perf_counter() - t0
        size = _nbytes(view)
        self._views[key] = (view, seconds, size, held)
        while (len(self._views) > 1 and
               sum(v[2] for v in self._views.values()) > self.max_view_bytes):
            self._views.pop(next(iter(self._views)))
        return view, seconds, False

    def envmap_radiance(self, emitter, config: RelightConfig = DEFAULT_RELIGHT) -> np.ndarray:
        import hashlib

        h = hashlib.blake2b(digest_size=16)
        h.update(repr((emitter.class_name(), config)).encode())
        params = mi.traverse(emitter)
        for key in sorted(params.keys()):
            v = params[key]
            h.update(key.encode())
            h.update(np.asarray(v.matrix if hasattr(v, "matrix") else v).tobytes())
        key = h.hexdigest()
        if key not in self._env:
            self._env[key] = envmap_grid_radiance(emitter, config)
            while len(self._env) > self.max_envmaps:
                self._env.pop(next(iter(self._env)))
        return self._env[key]
