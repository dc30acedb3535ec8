"""The public face of mi_shadowgs: what a user scripts from Python.

    import mi_shadowgs.api as msg

    data = msg.generate_dataset(msg.scene_path("default"), "runs/data", preset="cpu-small")
    summary = msg.run("runs/data", "runs/run", preset="cpu-small")    # stages 1-5 + report
    model = msg.load_model("runs/run/segmentation/model.ply")
    images = msg.render(model, msg.load_dataset("runs/data", "test").cameras[0])

A model's views go to files with ``render_views`` (``mi-shadowgs render``), a finished run's
relit views with ``run_relight`` (``mi-shadowgs relight``).

Each stage can also be run alone (``run_geometry``, ``run_segmentation``) or used through
its package (``mi_shadowgs.stages.<stage>``: its config, its maths, its runner); the
settings of a run are one tree (``mi_shadowgs.presets``: ``build``, ``RunConfig``).
Everything here is a re-export or a thin wrapper; the CLI (``mi-shadowgs``) calls the same
functions.
"""

from __future__ import annotations

import os
from pathlib import Path

from mi_shadowgs import backend, stages
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.render import render_surfels
from mi_shadowgs.dataset.loader import Dataset, load_dataset
from mi_shadowgs.dataset.scene import dataset_scene
from mi_shadowgs.io.ply import load_ply, save_ply
from mi_shadowgs.pipeline import run_pipeline
from mi_shadowgs.presets import RunConfig, build, get_config
from mi_shadowgs.scenes import scene_path
from mi_shadowgs.stages.geometry import run_geometry
from mi_shadowgs.stages.relight import (
    RelightModel,
    directional_light_set,
    lights_from_json,
    point_light_set,
    relight_views,
)
from mi_shadowgs.stages.relight.runner import run_relight
from mi_shadowgs.stages.render import render_views
from mi_shadowgs.stages.segmentation import run_segmentation

set_variant = backend.set_variant


def generate_dataset(scene: str | Path, out: str | Path, preset: str = "cpu-small",
                     seed: int = 0, overwrite: bool = False, progress: bool = False) -> Path:
    """Render a shadowed synthetic dataset of the scene XML ``scene`` into ``out``
    (``mi-shadowgs generate``): train/test views, masks, ground truth and ``lights.json``."""
    from mi_shadowgs.dataset.writer import write_dataset
    from mi_shadowgs.presets import generate_config

    write_dataset(scene, out, generate_config(preset), preset, seed=seed, overwrite=overwrite,
                  progress=progress)
    return Path(out)


def run(data: str | Path, out: str | Path, preset: str = "cpu-small", progress: bool = False,
        overwrite: bool = False, seed: int | None = None, config: RunConfig | None = None,
        **settings) -> dict:
    """The whole method (stages 1-5, evaluation, report) on dataset ``data`` into run folder
    ``out`` (``mi-shadowgs run``). The settings are ``config`` (a ``RunConfig``) or else
    preset ``preset`` with ``settings`` laid over it: a stage's section as a dict
    (``material={"iterations": 300}``) or a run option (``masks="chromaticity"``,
    ``ablations=True``, ``preview_envmaps=[...]``), each checked by name and type as the
    command line's ``--set`` is; ``seed`` sets every stage's seed. Returns the summary."""
    from mi_shadowgs.pipeline import check_preview_envmaps
    from mi_shadowgs.presets import build

    if config is None:
        if "preview_envmaps" in settings:
            settings["preview_envmaps"] = check_preview_envmaps(settings["preview_envmaps"])
        config = build(preset, settings, seed=seed)
    elif settings or seed is not None:
        raise TypeError("api.run: pass either config= or preset/settings/seed, not both")
    return run_pipeline(data, out, config, progress=progress, overwrite=overwrite)


def load_model(path: str | Path, sh_space: str | None = None):
    """A surfel model (``Surfels``) from a PLY in the 2DGS layout plus channels (a stage's,
    an export's or another tool's). Its SH come out linear: ``sh_space`` ("linear" or
    "srgb") says what the file holds; by default its header record, else linear, so give
    "srgb" for another tool's 3DGS/2DGS PLY (``mi_shadowgs.io.ply``)."""
    return load_ply(path, sh_space)


def export_ply(path: str | Path, surfels) -> None:
    """Write ``surfels`` as a PLY (atomically; the 2DGS layout plus named channels)."""
    from mi_shadowgs.core.surfels import Surfels

    if not isinstance(surfels, Surfels):  # a list or arrays failed inside the writer
        raise TypeError(f"export_ply: 'surfels' must be a surfel model (load_model, "
                        f"Surfels.from_numpy), got {type(surfels).__name__}")
    save_ply(path, surfels)


def export_asset(run_folder: str | Path, out: str | Path, fmt: str = "mesh",
                 color: str = "sh", preset: str | None = None, overwrite: bool = False):
    """A finished run's stage-4 model as ``fmt`` ("3dgs-ply", "2dgs-ply" or "mesh": a mesh
    with per-vertex materials and a Mitsuba ``scene.xml``) in the folder ``out``, at
    ``preset``'s export settings (default: the run's own, ``presets.recorded``)."""
    from mi_shadowgs.presets import recorded
    from mi_shadowgs.stages.export.export import export_run

    config = get_config(preset).export if preset else recorded(run_folder).export
    return export_run(run_folder, out, fmt, color=color, config=config, overwrite=overwrite)


def _model(surfels, what: str):
    """A Surfels model, or the one the PLY at ``surfels`` holds; TypeError naming ``what``."""
    from mi_shadowgs.core.surfels import Surfels

    if isinstance(surfels, str | os.PathLike):
        return load_ply(surfels)
    if not isinstance(surfels, Surfels):
        raise TypeError(f"{what}: 'surfels' must be a surfel model (load_model) or the path "
                        f"of its PLY, got {type(surfels).__name__}")
    return surfels


def render(surfels, camera: Camera, aovs=(), background=None,
           color_channel: str = "sh") -> dict:
    """Rasterize a surfel model (or the PLY at that path) from one ``camera``: {"rgb",
    "alpha", AOV...} as [H, W, C] Mitsuba tensors (the ``surfel_raster`` plugin renders the
    same). ``aovs`` is a sequence of names, e.g. ``("depth", "normal")``; ``color_channel``
    gives "rgb": "sh" seen from the camera, or a channel of 1 or 3 columns (e.g. "albedo")."""
    surfels = _model(surfels, "render")
    if not isinstance(camera, Camera):
        raise TypeError(f"render: 'camera' must be one Camera (render each of a list in "
                        f"turn), got {type(camera).__name__}")
    if not isinstance(color_channel, str):
        raise TypeError(f"render: 'color_channel' must be a channel's name, got "
                        f"{type(color_channel).__name__}")
    return render_surfels(surfels, camera, aovs=aovs, background=background,
                          color_channel=color_channel)


def relight(surfels, cameras, lights, bounds=None, specular: bool | None = None,
            preset: str | None = None):
    """Render a fitted model (stage 4's: a ``Surfels`` or its PLY's path) from each of
    ``cameras`` (a list of Camera) under ``lights`` (``directional_light_set``,
    ``point_light_set`` or ``lights_from_json``) with shadows recomputed from the surfels;
    returns (views, seconds), a view being ``relight_view``'s dict of numpy images.

    The shadow maps and receivers are ``preset``'s (``VisibilityConfig``); without one,
    those a PLY given by path records (the ones it was fitted with, as the
    ``surfel_relight`` plugin reads them), else cpu-small's. ``specular`` (the GGX lobe):
    by default whether a PLY given by path was fitted with it (``cpu-*`` fits without it),
    else on. ``bounds`` (a ``SceneBounds``)
    is the sphere the maps cover; default: the surfels' bounding sphere, as the plugin's.
    The fitted indirect light (``indirect_sh``) is added unchanged: the training light it
    would be scaled by is not known here (``run_relight`` scales it)."""
    import dataclasses

    from mi_shadowgs.core.shading import LightSet
    from mi_shadowgs.stages.material.runner import occluder_bounds
    from mi_shadowgs.stages.relight.render import recorded_specular, recorded_visibility
    from mi_shadowgs.stages.visibility.shadow_maps import SceneBounds

    by_path = isinstance(surfels, str | os.PathLike)
    recorded = recorded_visibility(surfels) if by_path and preset is None else None
    if specular is None:
        found = recorded_specular(surfels) if by_path else None
        specular = True if found is None else found
    model_surfels = _model(surfels, "relight")
    if (isinstance(cameras, Camera) or not isinstance(cameras, list | tuple)
            or not all(isinstance(c, Camera) for c in cameras)):
        raise TypeError(f"relight: 'cameras' must be a list of Camera, got "
                        f"{type(cameras).__name__}")
    if not isinstance(lights, LightSet):
        raise TypeError(f"relight: 'lights' must be a LightSet (directional_light_set, "
                        f"point_light_set, lights_from_json), got {type(lights).__name__}")
    if bounds is None:
        bounds = occluder_bounds(model_surfels, cameras, quantile=1.0)
    elif not isinstance(bounds, SceneBounds):
        raise TypeError(f"relight: 'bounds' must be a SceneBounds or None, got "
                        f"{type(bounds).__name__}")
    tree = get_config(preset or "cpu-small")
    vis_config = recorded or tree.visibility
    config = dataclasses.replace(tree.relight, indirect="keep")
    model = RelightModel(model_surfels, specular, True, receiver_band=vis_config.receiver_band)
    return relight_views(model, cameras, lights, bounds, config, vis_config)


__all__ = [
    "Camera", "Dataset", "RunConfig", "dataset_scene", "directional_light_set", "export_asset",
    "export_ply",
    "build", "generate_dataset", "lights_from_json", "load_dataset", "load_model",
    "point_light_set",
    "relight", "render", "render_views", "run", "run_geometry", "run_pipeline", "run_relight",
    "run_segmentation", "scene_path", "set_variant", "stages",
]
