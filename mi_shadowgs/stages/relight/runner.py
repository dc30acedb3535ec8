"""Stage 5's relight runner (``mi-shadowgs relight RUN --out DIR``): a finished run's fitted
model rendered under new lights, from new views, with shadows recomputed from the surfels.

Light sources: directional lights given as azimuth, elevation and irradiance
(``parse_light``), lamps given as a position, an intensity and a radius
(``lamps.parse_point``), an env map (optionally turned about +Y), the emitters of a Mitsuba
scene (directional, infinite, point, spot and sphere area emitters).
Views: a ``transforms.json``, an orbit of N cameras around the object, or the run's test
views. Every shadow map is rendered once per light direction and reused by every frame
(``render.RelightCache``); the env map's grid radiance is integrated once.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

from mi_shadowgs.config import ConfigError, recorded_config
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import direction_from_angles, parse_angle_fields
from mi_shadowgs.stages.common import warn, warn_other_backend
from mi_shadowgs.stages.material.outputs import fit_from_files
from mi_shadowgs.stages.relight import lamps as lamp_mod
from mi_shadowgs.stages.relight import render as relight
from mi_shadowgs.stages.visibility import shadow_maps

DEFAULT_QUANTILE = 0.98  # the run's bounds_quantile when its manifest does not say
NO_LIGHT = ("no light: give --light AZ,EL,IRRADIANCE, --point X,Y,Z,INTENSITY, --envmap FILE "
            "or --scene XML")


# Elevations a directional light may have, as `generate` and `view` take them: above the
# horizon. From below, a light reaches only the ground's underside, which no view saw and the
# model does not hold (it drew a lit object over a ground that cast no shadow).
LIGHT_ELEVATION = (0.0, 90.0, False)


def parse_light(text: str, option: str = "--light",
                elevation: tuple[float, float, bool] = LIGHT_ELEVATION
                ) -> tuple[float, float, np.ndarray]:
    """``AZ,EL,E`` or ``AZ,EL,R,G,B`` (degrees, W/m^2) -> (azimuth, elevation, RGB [3]);
    ValueError naming the option and the field at fault. ``elevation`` is
    ``parse_angle_fields``' range: above the horizon (``LIGHT_ELEVATION``)."""
    az, el, *irr = parse_angle_fields(
        str(text), option, "AZ,EL,IRRADIANCE or AZ,EL,R,G,B (degrees, W/m^2)",
        {3: ("azimuth", "elevation", "irradiance"),
         5: ("azimuth", "elevation", "irradiance R", "irradiance G", "irradiance B")},
        elevation)
    if any(e < 0 for e in irr):
        raise ValueError(f"{option} {text!r}: field irradiance must be >= 0, got "
                         f"{','.join(f'{e:g}' for e in irr)}")
    rgb = np.asarray(irr * 3 if len(irr) == 1 else irr, np.float64)
    return az, el, rgb


def check_light_args(lights=(), envmap: str | None = None, rotate_deg: float = 0.0,
                     envmap_scale: float = 1.0, scene: str | None = None,
                     points=()) -> None:
    """The light arguments checked before anything is loaded (errors name the option and
    field): ``parse_light`` on each light, ``lamps.parse_point`` on each lamp, the env
    map's and scene's files and numbers. Where the lamps stand is checked once the run's
    bounds are known (``build_lights``)."""
    for text in lights:
        parse_light(text)
    for text in points:
        lamp_mod.parse_point(text)
    for name, v in (("--rotate", rotate_deg), ("--envmap-scale", envmap_scale)):
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v!r}")
    if envmap_scale <= 0:
        raise ValueError(f"--envmap-scale must be > 0, got {envmap_scale:g}")
    if envmap is None and (rotate_deg or envmap_scale != 1.0):
        raise ValueError("--rotate and --envmap-scale change an env map: give --envmap too")
    if envmap is not None and not Path(envmap).is_file():
        raise FileNotFoundError(f"--envmap {envmap}: file not found")
    if scene is not None and not Path(scene).is_file():
        raise FileNotFoundError(f"--scene {scene}: file not found")


def envmap_emitter(path: str | Path, rotate_deg: float = 0.0, scale: float = 1.0):
    """Mitsuba's ``envmap`` of a lat-long image (Y-up), turned by ``rotate_deg`` about +Y
    (positive: from +X toward -Z, the way azimuth turns); errors name the option."""
    import mitsuba as mi

    from mi_shadowgs.core.envmap import EnvmapError, load_envmap, low_dynamic_range_warning

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--envmap {path}: file not found")
    for name, v in (("--rotate", rotate_deg), ("--envmap-scale", scale)):
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v!r}")
    if scale <= 0:
        raise ValueError(f"--envmap-scale must be > 0, got {scale:g}")
    try:
        emitter = load_envmap(str(path), scale)
    except EnvmapError as exc:  # names the file, and the texels that are no radiance
        raise ValueError(f"--envmap {exc}") from None
    except RuntimeError as exc:  # Mitsuba's message names the file; keep its first line
        raise ValueError(f"--envmap {path}: not a readable env map: "
                         f"{str(exc).splitlines()[0] if str(exc) else exc}") from None
    if (note := low_dynamic_range_warning(path, "--envmap")) is not None:
        warn(note)
    if rotate_deg:
        params = mi.traverse(emitter)
        params["to_world"] = mi.Transform4f().rotate([0, 1, 0], float(rotate_deg))
        params.update()
    return emitter


def load_scene_file(path: str | Path):
    """A Mitsuba scene file, for its emitters (its sensors and integrator unused; its shapes
    only where an area emitter lies on one: hold the scene while its emitters are read)."""
    import mitsuba as mi

    from mi_shadowgs.core.envmap import two_threads

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--scene {path}: file not found")
    try:
        with two_threads():  # an env map's EXR in it: see core.envmap
            scene = mi.load_file(str(path))
    except RuntimeError as exc:
        raise ValueError(f"--scene {path}: Mitsuba could not load it: "
                         f"{str(exc).splitlines()[0] if str(exc) else exc}") from None
    return scene


def build_lights(lights=(), envmap: str | None = None, rotate_deg: float = 0.0,
                 envmap_scale: float = 1.0, scene: str | None = None,
                 config: relight.RelightConfig = relight.DEFAULT_RELIGHT,
                 cache: relight.RelightCache | None = None, points=(),
                 bounds: shadow_maps.SceneBounds | None = None):
    """One LightSet from every source given: ``lights`` (``parse_light`` strings),
    ``points`` (``lamps.parse_point`` strings), an env map, a scene's emitters. The lamps
    are checked against ``bounds``, the run's ``SceneBounds`` (``lamps.check_lamps``), and
    weighted at its centre. ValueError when there is no light."""
    sets = []
    for text in lights:
        az, el, rgb = parse_light(text)
        sets.append(relight.directional_light_set(direction_from_angles(az, el)[None],
                                                  rgb[None]))
    if points:
        lamps = [lamp_mod.parse_point(text) for text in points]
        if bounds is None:
            raise ValueError("--point: lamps need the run's scene bounds")
        lamp_mod.check_lamps(lamps, bounds)
        sets.append(lamp_mod.lamp_light_set(lamps, bounds.center))
    if envmap is not None:
        rad = (cache.envmap_radiance(envmap_emitter(envmap, rotate_deg, envmap_scale), config)
               if cache is not None else relight.envmap_grid_radiance(
                   envmap_emitter(envmap, rotate_deg, envmap_scale), config))
        ls = relight.grid_light_set(rad, config.n_directions)
        if ls.count == 0:
            raise ValueError(f"--envmap {envmap}: the env map is black above the horizon")
        sets.append(ls)
    if scene is not None:
        loaded = load_scene_file(scene)
        sets.append(relight.emitter_light_set(loaded.emitters(), config, cache,
                                              where=f"--scene {scene}", bounds=bounds))
    if not sets:
        raise ValueError(NO_LIGHT)
    return relight.combine_light_sets(sets)


@dataclasses.dataclass
class RunFit:
    """What relighting takes from a finished run."""

    result: object  # fit.MaterialResult
    model: relight.RelightModel
    bounds: shadow_maps.SceneBounds
    dataset: Path | None  # the run's dataset, where it still is
    relight_config: relight.RelightConfig = relight.DEFAULT_RELIGHT  # the run's relighting
    # What stage 4 ran with (its receivers too).
    vis_config: shadow_maps.VisibilityConfig = shadow_maps.VisibilityConfig()


def _unrecorded(source: str):
    """The fallback of a setting a run must record: a ConfigError naming where."""
    def fail():
        raise ConfigError(f"{source}: not recorded (the fit was made by an older mi_shadowgs, "
                          "or by hand); run its stage 4 again with `mi-shadowgs run`")
    return fail


def run_fits(run: str | Path) -> list[str]:
    """The names of the run's stage-4 fits, sorted: the ``material/<name>`` parts its
    manifest lists (a folder put there by hand is none) that hold a model."""
    from mi_shadowgs.io.provenance import read_manifest

    run = Path(run)
    parts = (read_manifest(run) or {}).get("parts") or []
    return sorted(p.split("/", 1)[1] for p in parts
                  if p.startswith("material/") and (run / p / "model.ply").is_file())


def load_run(run: str | Path, variant: str = "full", fallback_cameras=()) -> RunFit:
    """The fitted model of ``RUN/material/<variant>``, with the shadow-map bounds the run
    used (its training cameras and ``bounds_quantile``; ``fallback_cameras`` where the
    dataset is no longer there)."""
    from mi_shadowgs.io.provenance import MANIFEST_NAME, read_manifest
    from mi_shadowgs.stages.common import check_run_stages
    from mi_shadowgs.stages.material.runner import occluder_bounds

    run = Path(run)
    folder = run / "material" / variant
    if not (folder / "model.ply").is_file():
        raise FileNotFoundError(f"{folder / 'model.ply'}: no stage-4 model (is {run} a "
                                "finished `mi-shadowgs run`?)")
    fits = run_fits(run)
    if variant not in fits:  # a folder put under material/ by hand is no fit of the run
        raise FileNotFoundError(f"{folder}: not a stage-4 fit of the run ({run / MANIFEST_NAME}"
                                f" lists {', '.join(fits) or 'none'})")
    check_run_stages(run)
    manifest = read_manifest(folder) or {}
    settings = manifest.get("settings") or {}
    result = fit_from_files(folder / "model.ply", folder / "light.json",
                            folder / "history.csv",
                            use_visibility=settings.get("material", {})
                            .get("use_visibility", True))
    data = (manifest.get("dataset") or {}).get("path")
    data = Path(data) if data and Path(data).is_dir() else None
    cams = dataset_cameras(data, "train") if data is not None else []
    pos = result.surfels.to_numpy()["position"]
    if cams:
        bounds = occluder_bounds(result.surfels, cams,
                                 settings.get("bounds_quantile", DEFAULT_QUANTILE))
    elif fallback_cameras:  # the dataset moved: the views to render stand in for its cameras
        bounds = shadow_maps.SceneBounds.from_points(
            pos, fallback_cameras, settings.get("bounds_quantile", DEFAULT_QUANTILE))
    else:
        gone = (manifest.get("dataset") or {}).get("path")
        raise FileNotFoundError(f"{run}: the run's dataset ({gone}) is gone; give the views "
                                "with --cameras or --orbit")
    vis_config = recorded_config(shadow_maps.VisibilityConfig, settings.get("visibility"),
                                 _unrecorded(f"{folder / MANIFEST_NAME}: settings.visibility"),
                                 f"{folder / MANIFEST_NAME}: settings.visibility")
    # (every preset relights alike: a fit that predates the record takes the defaults)
    relight_config = recorded_config(relight.RelightConfig, settings.get("relight"),
                                     relight.RelightConfig,
                                     f"{folder / MANIFEST_NAME}: settings.relight")
    model = relight.RelightModel(result.surfels, result.specular, result.use_visibility,
                                 result.light.light_set(), vis_config.receiver_band)
    return RunFit(result, model, bounds, data, relight_config, vis_config)


def dataset_cameras(root: Path, split: str) -> list[Camera]:
    """The cameras of a dataset's split (our layout, NeRF-synthetic or TensoIR)."""
    from mi_shadowgs.dataset.loader import load_cameras, load_dataset

    t = root / f"transforms_{split}.json"
    if t.is_file():
        return [c for _, c in load_cameras(t)]
    if any(root.glob(f"{split}_*/metadata.json")):
        return load_dataset(root, split, require_mask=False).cameras
    return []


def orbit_cameras(n: int, template: Camera, center, elevation_deg: float | None = None
                  ) -> list[Camera]:
    """``n`` cameras on a circle about +Y through ``center``, at the template camera's
    distance, field of view and size (and its elevation unless given)."""
    if n < 1:
        raise ValueError(f"--orbit must be >= 1, got {n}")
    c = np.asarray(center, np.float64)
    off = template.origin - c
    dist = float(np.linalg.norm(off))
    el = (math.degrees(math.asin(np.clip(off[1] / dist, -1, 1))) if elevation_deg is None
          else elevation_deg)
    az0 = math.degrees(math.atan2(-off[2], off[0]))
    return [Camera.look_at(c + dist * direction_from_angles(az0 + 360.0 * i / n, el), c,
                           width=template.width, height=template.height,
                           fov_x=template.fov_x)
            for i in range(n)]


def relight_frames(fit: RunFit, cameras, lights, cache: relight.RelightCache,
                   config: relight.RelightConfig | None = None,
                   vis_config: shadow_maps.VisibilityConfig | None = None, progress=False):
    """Yield (index, {"rgb", "alpha"}, seconds) per camera; the shadow maps of ``lights``
    come from ``cache`` (rendered once, inside the first frame's time)."""
    import drjit as dr
    from tqdm import tqdm

    config = config or fit.relight_config
    vis_config = vis_config or fit.vis_config
    factor = relight.indirect_factor(fit.model, lights, config)
    for i, cam in enumerate(tqdm(cameras, desc="relight", unit="frame", disable=not progress)):
        dr.sync_thread()
        t0 = time.perf_counter()
        maps = cache.shadow_maps(fit.model, lights, fit.bounds, vis_config)
        out = relight.relight_view(fit.model, cam, lights, maps, factor, only_rgb=True)
        yield i, out, time.perf_counter() - t0  # numpy read-back: synced


def write_video(path: Path, frames: list[np.ndarray], fps: float) -> tuple[Path, str | None]:
    """An MP4 (H.264) of sRGB uint8 frames through imageio's ffmpeg plugin (the
    ``imageio-ffmpeg`` dependency, whose wheel ships ffmpeg), or a GIF where that package or
    its encoder is missing or fails; returns (file written, why not MP4 or None)."""
    import importlib.util

    import imageio.v3 as iio

    from mi_shadowgs.io.atomic import atomic_path

    why = ("MP4 (H.264) unavailable: the imageio-ffmpeg package (a dependency of "
           "mi_shadowgs) is not installed")
    if importlib.util.find_spec("imageio_ffmpeg") is not None:
        try:
            with atomic_path(path.with_suffix(".mp4")) as tmp:
                iio.imwrite(tmp, np.stack(frames), extension=".mp4", plugin="FFMPEG", fps=fps,
                            codec="libx264", macro_block_size=1)
            return path.with_suffix(".mp4"), None
        except Exception as exc:  # noqa: BLE001 -- a missing encoder falls back to a GIF
            why = (f"MP4 (H.264) unavailable: {type(exc).__name__}: " +
                   (str(exc).splitlines()[0] if str(exc) else ""))
    with atomic_path(path.with_suffix(".gif")) as tmp:
        iio.imwrite(tmp, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)
    return path.with_suffix(".gif"), why + "; wrote a GIF instead"


def frame_stats(seconds: list[float]) -> dict:
    """First frame (shadow maps included) and the median of the others."""
    return {"frames": len(seconds), "first_s": seconds[0] if seconds else None,
            "later_median_s": float(np.median(seconds[1:])) if len(seconds) > 1 else None}


@dataclasses.dataclass(frozen=True)
class RelightResult:
    folder: Path
    views: int
    light_directions: int
    stats: dict  # frame_stats
    video: Path | None
    video_note: str | None  # why the video is not an MP4
    rendered: int  # views this call rendered; the others were written by an earlier call


def run_relight(run: str | Path, out: str | Path, lights=(), envmap: str | None = None,
                rotate_deg: float = 0.0, envmap_scale: float = 1.0, scene: str | None = None,
                cameras: str | None = None, orbit: int | None = None,
                orbit_elevation: float | None = None, video: bool = False, fps: float = 12.0,
                fit: str = "full", overwrite: bool = False,
                progress: bool = True, points=()) -> RelightResult:
    """The fit ``material/<fit>`` of the finished run ``run`` under new lights (module
    docstring), into the folder ``out``: ``NAME.exr`` / ``NAME.png`` per view,
    ``relight.json`` (lights, views, the per-frame times of the views this call rendered)
    and, with ``video``, a turntable. Views: ``cameras`` (a transforms.json), an ``orbit``
    of N views, else the run's test views. Every argument is checked before the run is
    read; ``out`` is new or an earlier relight: the same relight is continued (a killed one
    renders only its missing views) or reused when finished, another is refused unless
    ``overwrite`` (which removes only its files)."""
    from mi_shadowgs.dataset.loader import load_cameras
    from mi_shadowgs.io.images import linear_to_srgb, read_exr, to_uint8
    from mi_shadowgs.io.provenance import Output, Provenance, input_ref
    from mi_shadowgs.stages.common import settings_dict
    from mi_shadowgs.stages.render import missing_views, view_stems, write_rgba

    if not lights and not points and envmap is None and scene is None:
        raise ValueError(NO_LIGHT)
    check_light_args(lights, envmap, rotate_deg, envmap_scale, scene, points)
    _check_view_args(fps, orbit, orbit_elevation)
    run_dir = Path(run)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder not found: {run_dir}")
    named = []
    if cameras is not None:
        if not Path(cameras).is_file():
            raise FileNotFoundError(f"--cameras {cameras}: file not found")
        named = list(load_cameras(cameras))
    run_fit = load_run(run_dir, fit, [c for _, c in named])
    cache = relight.RelightCache()
    light_set = build_lights(lights, envmap, rotate_deg, envmap_scale, scene,
                             run_fit.relight_config, cache, points, run_fit.bounds)
    if orbit is not None or not named:
        named = _default_views(run_dir, run_fit, orbit, orbit_elevation)
    names = view_stems(n for n, _ in named)
    inputs = [run_dir / "material" / fit / n for n in ("model.ply", "light.json")]
    extra = [Path(p) for p in (envmap, scene, cameras) if p]
    bounds = run_fit.bounds
    provenance = Provenance(
        inputs={p.name: input_ref(p) for p in inputs + extra},
        settings={"lights": list(lights), "envmap": envmap, "rotate": rotate_deg,
                  "envmap_scale": envmap_scale, "scene": scene, "orbit": orbit,
                  "orbit_elevation": orbit_elevation, "fit": fit, "video": video,
                  "fps": fps,
                  # What else a view depends on, read from the run and its dataset: a
                  # continued relight must not mix views of other maps or bounds.
                  "visibility": settings_dict(run_fit.vis_config),
                  "relight": settings_dict(run_fit.relight_config),
                  "shadow_bounds": {"center": [float(c) for c in bounds.center],
                                    "radius": float(bounds.radius),
                                    "mean_camera_distance": float(bounds.mean_camera_distance)},
                  # only with lamps: earlier relights without them are continued as before
                  **({"points": list(points)} if points else {})})
    suffixes = (".exr", ".png")
    with Output.open(out, "relight", provenance, overwrite=overwrite, reuse=True,
                     inputs=inputs + extra + ([run_fit.dataset] if run_fit.dataset else [])
                     ) as output:
        if output.complete:
            summary = output.folder / "relight.json"
            info = json.loads(summary.read_text()) if summary.is_file() else {}
            movie = output.folder / info["video"] if info.get("video") else None
            return RelightResult(output.folder, len(names), light_set.count, frame_stats([]),
                                 movie, info.get("video_note"), 0)
        output.claim(*(f"{n}{x}" for n in names for x in suffixes), "relight.json")
        warn_other_backend(output)  # views of an earlier call on another backend stay
        todo = missing_views(output.folder, names, suffixes)
        seconds = []
        for j, img, secs in relight_frames(run_fit, [named[i][1] for i in todo], light_set,
                                           cache, progress=progress):
            write_rgba(output.folder, names[todo[j]], img["rgb"], img["alpha"][..., None])
            seconds.append(secs)
        movie, why = None, None
        if video:
            output.claim("turntable.mp4", "turntable.gif")
            # From the views' files, which an earlier (killed) call may have written: the
            # EXR holds the float32 colour exactly, so the video is the same either way.
            frames = []
            for name in names:
                rgb = read_exr(output.folder / f"{name}.exr")[..., :3]
                frames.append(to_uint8(linear_to_srgb(np.clip(rgb, 0, 1)), srgb=False))
            movie, why = write_video(output.folder / "turntable", frames, fps)
        stats = frame_stats(seconds)
        summary_json(output.path("relight.json"), {
            "run": str(run_dir.resolve()), "fit": fit, "views": names,
            "light_directions": light_set.count, "shadow_maps_rendered": cache.rendered,
            "rendered_views": [names[i] for i in todo], "frame_seconds": seconds, **stats,
            "video": movie.name if movie else None, "video_note": why})
        output.finish()
    return RelightResult(output.folder, len(names), light_set.count, stats, movie, why,
                         len(todo))


def _check_view_args(fps: float, orbit: int | None, orbit_elevation: float | None) -> None:
    """``--fps`` and ``--orbit-elevation`` (which needs ``--orbit``), before the run is read."""
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"--fps must be > 0, got {fps:g}")
    if orbit_elevation is not None:
        if orbit is None:  # it would be dropped without a word
            raise ValueError("--orbit-elevation sets the elevation of --orbit N's views: give "
                             "--orbit N with it")
        if not (math.isfinite(orbit_elevation) and -90.0 < orbit_elevation < 90.0):
            raise ValueError(f"--orbit-elevation must be a finite angle in (-90, 90) degrees, "
                             f"got {orbit_elevation:g}")


def _default_views(run_dir: Path, fit: RunFit, orbit: int | None,
                   orbit_elevation: float | None) -> list[tuple[str, Camera]]:
    """(name, camera) of an orbit of ``orbit`` views, or of the run's test views."""
    test = dataset_cameras(fit.dataset, "test") if fit.dataset else []
    if orbit is None:
        if not test:
            raise FileNotFoundError(f"{run_dir}: its dataset's test views are gone; give "
                                    "--cameras or --orbit")
        return [(f"test_{i:03d}", c) for i, c in enumerate(test)]
    template = (test or dataset_cameras(fit.dataset, "train"))[0] if fit.dataset else None
    if template is None:
        raise FileNotFoundError(f"{run_dir}: no camera to orbit with (its dataset is gone); "
                                "give --cameras")
    return [(f"orbit_{i:03d}", c) for i, c in enumerate(orbit_cameras(
        orbit, template, fit.bounds.center, orbit_elevation))]


def summary_json(path: Path, info: dict) -> None:
    from mi_shadowgs.io.atomic import write_json

    write_json(path, json.loads(json.dumps(info, default=float)))
