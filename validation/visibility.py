"""Visibility against Mitsuba ray tracing: paper Table 2 and a speed-vs-error sweep.

For each scene (the embedded default and the bunny), views on the test spiral and 8 light
directions spread in azimuth and elevation (down to 10 degrees), the ground truth is Mitsuba's
``ray_test`` toward the light from the true surface (``dataset.generate.trace_ground_truth``).
Every method gets the same ground-truth surface points (unprojected GT depth) and normals and
surfels sampled on the true shapes (object dense, base sparse near the object); the score is
the IoU of the shadowed set (V < 0.5, ground truth V = 0 or n . l <= 0) inside the mask,
averaged over views and directions. With ``--model`` (a stage-1 PLY, or a later stage's,
named by its stage) and ``--data`` (its dataset), the points come from the model's own
rendered median depth and normals instead (with their pixel footprints, so the methods'
receiver offset applies); both repeat, in pairs, for one table over several scenes.
``--receiver-band B`` renders a model's receivers as stages 4-5 of the ``cpu-*`` presets
do (each pixel's median surface, ``VisibilityConfig.receiver_band``) instead of the paper's
median depth and blended normals.
The pixel method's maps have the paper's settings (Table 2 as published: perspective maps
at 30x, the relative tau); ``--preset P`` gives them preset P's (``shadow_maps.PRESETS``:
for the ``cpu-*`` presets orthographic maps, a one-texel bias and the occluder layer's
slack) and its receiver band: the method as a run at P has it.
``--factors`` also splits each stage-1 model's IoU (``model_factors``): its receivers and
occluders swapped for the truth's, the method on exact geometry, and what the pixel area
allows; ``--models-only`` leaves out the ground-truth scenes, the sweep and the timing
(about a minute per model instead of five). ``--lights`` replaces the 8 directions, e.g. by
a fitted light's own.

    python -m validation.visibility --out validation-out/visibility [--quick]
        [--model RUN/geometry/model.ply --data DATASET ...] [--factors] [--models-only]
        [--receiver-band B] [--preset P] [--lights AZ,EL ...] [--overwrite]
    python -m validation.visibility --lamp --out validation-out/lamp [--quick] [...]

``--lamp``: shadow maps from a lamp (a lab capture's sphere lamp) against Mitsuba's hard and
soft visibility of it instead: ``validation.lamp_visibility``, which takes the other options.

Writes ``table2.md``, ``table2.csv``, ``sweep.csv``, ``sweep.png``, ``sweep.md``,
``timing.csv``, ``summary.json``, ``README.md`` (and ``factors.md``), each atomically, from
its units under ``units/`` (``validation.units``): each case's row of each method, each
model's factor split, each setting of the sweep and of the timing. A rerun after a kill
redoes only the unfinished units; one made from other inputs or settings exits 2 naming what
differs (``--overwrite`` makes this call's units again).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import io
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM, selects the variant)
from mi_shadowgs.core.depth import pixel_footprint, unproject_depth
from mi_shadowgs.core.directions import direction_from_angles, light_grid, parse_angle_fields
from mi_shadowgs.core.frames import frame_to_quaternion
from mi_shadowgs.core.sampling import sample_surface
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.dataset.cameras import test_cameras
from mi_shadowgs.dataset.fingerprint import dataset_ref
from mi_shadowgs.dataset.generate import (
    box_filtered_ground_truth,
    facing_lights,
    trace_ground_truth,
)
from mi_shadowgs.dataset.layout import NERF_CAMERA_ANGLE_X, transforms_name
from mi_shadowgs.dataset.scene import Light, dataset_scene, load_scene
from mi_shadowgs.io.atomic import write_json, write_text
from mi_shadowgs.io.provenance import Provenance, device_name, input_ref
from mi_shadowgs.presets import visibility_config as get_visibility_config
from mi_shadowgs.stages.visibility.baselines import (
    GaussianTraceConfig,
    VoxelConfig,
    trace_surfels,
    voxelize_surfels,
)
from mi_shadowgs.stages.visibility.shadow_maps import (
    SceneBounds,
    VisibilityConfig,
    mean_camera_distance,
    render_shadow_maps,
)
from validation import claim_out, fail
from validation.units import UNITS, run_unit, settings_of, smoke_name, unit_name

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
BUNNY = SHARED / "meshes" / "bunny" / "bunny.ply"

# 8 light directions (azimuth, elevation) in degrees: all azimuth octants, low to high.
LIGHTS = ((20.0, 10.0), (65.0, 25.0), (110.0, 40.0), (155.0, 60.0),
          (200.0, 15.0), (245.0, 30.0), (290.0, 50.0), (335.0, 75.0))


@dataclasses.dataclass(frozen=True)
class ValidationConfig:
    """Sizes of the visibility validation; ``quick`` is a smoke run."""

    n_views: int = 8  # views on the test spiral
    resolution: int = 128  # view width = height (the cpu-small dataset's)
    camera_distance: float = 4.0  # as the dataset generator (object radius 1)
    object_surfels: int = 20_000  # sampled on the object's shapes
    base_surfels: int = 4_000  # on the base, within base_radius object radii of the centre
    base_radius: float = 2.5
    sigma_factor: float = 0.7  # surfel std-dev / mean sample spacing
    lights: tuple = LIGHTS
    timing_views: int = 200  # maps amortised over this many views (the paper's test set)
    repeats: int = 2  # Table 2 and N_l timings: median of this many warm runs
    sweep_repeats: int = 1  # sweep timings (many settings; the 1024^2 maps are slow on CPU)
    timing_map_resolutions: tuple = (128, 256)  # map sizes of the N_l timing
    sweep_resolutions: tuple = (64, 128, 256, 512, 1024)
    sweep_taus: tuple = (0.0, 1e-4, 3e-4, 8e-4, 2e-3, 5e-3, 1e-2, 3e-2)
    sweep_distances: tuple = (2.0, 5.0, 10.0, 30.0, 100.0)
    sweep_lights: tuple = (8, 32, 128)


QUICK = ValidationConfig(n_views=2, resolution=96, object_surfels=8_000, base_surfels=1_500,
                         repeats=1, timing_map_resolutions=(128,), sweep_resolutions=(128, 512),
                         sweep_taus=(0.0, 8e-4, 1e-2),
                         sweep_distances=(5.0, 30.0), sweep_lights=(8, 128))


# -- set-up -------------------------------------------------------------------------------
@dataclasses.dataclass
class Case:
    """One scene's ground truth and the inputs every method gets."""

    name: str
    surfels: Surfels
    bounds: SceneBounds
    directions: np.ndarray  # [L, 3]
    cameras: list
    points: list  # per view: mi.Point3f [H*W]
    normals: list  # per view: mi.Vector3f [H*W]
    mask: np.ndarray  # [V, H, W] bool
    gt_shadow: np.ndarray  # [V, H, W, L] bool
    # per view: mi.Float [H*W] pixel footprints when the points come from rendered depth
    # (the receiver offset applies); None for exact ray-traced points
    footprints: list | None = None
    # a model's case (``model_case``): its dataset's scene and that scene traced for these
    # views and lights, which ``model_factors`` reuses
    setup: object = None
    truth: dict | None = None

    def footprint(self, view: int):
        return None if self.footprints is None else self.footprints[view]


def scene_surfels(setup, cfg: ValidationConfig, seed: int = 0) -> Surfels:
    """Surfels on the true shapes: the object densely, the base sparsely near the object."""
    shapes = setup.scene.shapes()
    obj = [s for s in shapes if s.id().startswith("object_")]
    base = [s for s in shapes if s.id() == "base"]
    parts = []
    for group, count, keep_radius in ((obj, cfg.object_surfels, None),
                                      (base, cfg.base_surfels, cfg.base_radius)):
        if not group or count == 0:
            continue
        total = count
        if keep_radius is not None:  # sample the whole base densely enough, keep a disk
            area = sum(float(np.asarray(s.surface_area()).ravel()[0]) for s in group)
            disk = math.pi * (keep_radius * setup.object_radius) ** 2
            total = int(count * max(1.0, area / disk))
        s = sample_surface(group, total, seed)
        keep = np.ones(len(s.position), bool)
        if keep_radius is not None:
            dxz = (s.position - setup.object_center)[:, [0, 2]]
            keep = np.linalg.norm(dxz, axis=1) <= keep_radius * setup.object_radius
        sigma = cfg.sigma_factor * math.sqrt(s.total_area / total)
        parts.append((s.position[keep], s.normal[keep], np.full(keep.sum(), sigma)))
    pos = np.concatenate([p for p, _, _ in parts])
    nrm = np.concatenate([n for _, n, _ in parts])
    sig = np.concatenate([s for _, _, s in parts])
    return Surfels.from_numpy(pos, np.stack([sig, sig], 1), frame_to_quaternion(nrm),
                              np.full(len(pos), 0.99))


def checked_lights(angles) -> tuple:
    """``angles`` (``AZ,EL`` strings or pairs of numbers, degrees) as a tuple of (azimuth,
    elevation) float pairs, elevation in (0, 90]: a shadow map needs the light above the
    horizon. A ValueError names ``--lights`` and the bad entry."""
    out = tuple(tuple(parse_angle_fields(entry, "--lights", "AZ,EL (degrees)",
                                         {2: ("azimuth", "elevation")}, (0.0, 90.0, False)))
                for entry in angles)
    if not out:
        raise ValueError("--lights: give at least one AZ,EL pair")
    return out


def make_lights(angles) -> tuple[list[Light], np.ndarray]:
    lights, dirs = [], []
    for k, (az, el) in enumerate(angles):
        d = direction_from_angles(az, el)
        lights.append(Light(f"v{k}", tuple(d.tolist()), (1.0, 1.0, 1.0), az, el))
        dirs.append(d)
    return lights, np.stack(dirs)


def truth_shadow(gt: dict, dirs: np.ndarray) -> np.ndarray:
    """The traced truth's shadow [V, H, W, L]: the light's shadow ray occluded, or the
    light below the surface's horizon (n . l <= 0)."""
    return (gt["visibility"] < 0.5) | ~facing_lights(gt["normal"], dirs)


def ground_truth_case(name: str, scene_path, overrides, cfg: ValidationConfig) -> Case:
    setup = load_scene(scene_path, overrides)
    cams = test_cameras(cfg.n_views, setup.object_center, cfg.camera_distance,
                        NERF_CAMERA_ANGLE_X, cfg.resolution, cfg.resolution, 15.0, 60.0)
    lights, dirs = make_lights(cfg.lights)
    gt = trace_ground_truth(setup, cams, lights)
    mask = gt["mask"].astype(bool)
    gt_shadow = truth_shadow(gt, dirs)
    points, normals = traced_receivers(gt, cams)
    bounds = SceneBounds(tuple(np.asarray(setup.object_center, float).tolist()),
                         float(setup.object_radius),
                         mean_camera_distance(cams, setup.object_center))
    return Case(name, scene_surfels(setup, cfg), bounds, dirs, cams, points, normals, mask,
                gt_shadow)


# -- scoring ------------------------------------------------------------------------------
def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return float("nan") if union == 0 else np.count_nonzero(a & b) / union


def score(vis: list[np.ndarray], case: Case) -> dict:
    """Mean over views and lights of shadow IoU, visible IoU and accuracy within the mask."""
    s_iou, v_iou, acc = [], [], []
    for v, vv in enumerate(vis):  # vv [H, W, L]
        m = case.mask[v]
        for k in range(vv.shape[-1]):
            pred = vv[..., k][m] < 0.5
            gt = case.gt_shadow[v, ..., k][m]
            s_iou.append(iou(pred, gt))
            v_iou.append(iou(~pred, ~gt))
            acc.append(float(np.mean(pred == gt)))
    return {"shadow_iou": float(np.nanmean(s_iou)), "visible_iou": float(np.nanmean(v_iou)),
            "accuracy": float(np.mean(acc)), "pairs": len(acc)}


def _sync_time(fn):
    dr.sync_thread()
    t0 = time.perf_counter()
    out = fn()
    dr.sync_thread()
    return out, time.perf_counter() - t0


def run_method(build, case: Case, repeats: int = 1) -> dict:
    """Build a method, evaluate every view; build and per-view times (median of warm runs)."""
    times_b, times_e, method = [], [], None
    for r in range(repeats + 1):  # run 0 compiles the kernels; it is not timed
        method, tb = _sync_time(build)
        vis = []
        te = 0.0
        for v in range(len(case.cameras)):
            out, t = _sync_time(lambda v=v, m=method: np.asarray(
                m.evaluate(case.points[v], case.normals[v], case.footprint(v)),
                dtype=np.float32))
            te += t
            h, w = case.mask.shape[1:]
            vis.append(out.reshape(h, w, method.count))
        if r > 0 or repeats == 0:
            times_b.append(tb)
            times_e.append(te / len(case.cameras))
    res = score(vis, case)
    res["build_s"] = float(np.median(times_b))
    res["eval_ms_per_view"] = 1e3 * float(np.median(times_e))
    res["vis"] = vis
    return res


def method_configs(cfg_vis: VisibilityConfig, quick: bool) -> dict[str, object]:
    """Table 2's methods: name -> the settings of its visibility (``BUILDERS``' configs).
    Perspective maps (the paper's) also get an orthographic row; maps already orthographic
    (a ``cpu-*`` preset's) would repeat it."""
    out = {
        "Voxel-based": VoxelConfig(resolution=48) if quick else VoxelConfig(),
        "Gaussian-based": GaussianTraceConfig(max_hits=16) if quick else GaussianTraceConfig(),
        "Pixel-based (ours)": cfg_vis,
    }
    if cfg_vis.projection != "orthographic":
        out["Pixel-based (ours, orthographic)"] = dataclasses.replace(
            cfg_vis, projection="orthographic")
    return out


# A method's config type -> its builder(surfels, directions, bounds, config).
BUILDERS = {VoxelConfig: voxelize_surfels, GaussianTraceConfig: trace_surfels,
            VisibilityConfig: render_shadow_maps}


# -- stage-1 model ------------------------------------------------------------------------
def model_stage(model: Path) -> tuple[str, Path]:
    """(label, run folder) of a model PLY in a run's layout: ``RUN/geometry/model.ply``
    "stage-1", ``RUN/segmentation/model.ply`` "stage-2", ``RUN/material/VARIANT/model.ply``
    "stage-4" ("stage-4 VARIANT" for an ablation); any other PLY "model", its folder the
    run."""
    model = Path(model).absolute()
    folder = model.parent
    if folder.name == "geometry":
        return "stage-1", folder.parent
    if folder.name == "segmentation":
        return "stage-2", folder.parent
    if folder.parent.name == "material":
        return ("stage-4" if folder.name == "full" else f"stage-4 {folder.name}",
                folder.parent.parent)
    return "model", folder


def model_case_names(models: list[Path], datas: list[Path]) -> list[str]:
    """Each model case's name: its stage (``model_stage``) and the dataset folder (its
    parent when the folder is called "data"). When two cases would share that name (two
    runs of one dataset, or of two datasets of one scene), each also names its run folder,
    with as many of the folders above it as tell the runs apart. One model given twice is
    refused."""
    def scene(data: Path) -> str:
        return data.parent.name if data.name == "data" else data.name

    stages = [model_stage(Path(m)) for m in models]
    keys = [f"{label} {scene(Path(d))}" for (label, _), d in zip(stages, datas, strict=True)]
    parts = [run.parts for _, run in stages]
    names = []
    for i, key in enumerate(keys):
        group = [parts[j] for j in range(len(models)) if keys[j] == key]
        if len(group) == 1:
            names.append(key)
            continue
        if group.count(parts[i]) > 1:
            raise ValueError(f"--model: {models[i]} is given twice for {key}; its results "
                             f"could not be told apart")
        depth = next(k for k in range(1, max(map(len, group)) + 1)
                     if len({p[-k:] for p in group}) == len(group))
        names.append(f"{key} ({'/'.join(parts[i][-depth:])})")
    return names


def rendered_receivers(surfels: Surfels, cameras, band: float = 0.0
                       ) -> tuple[list, list, list, list]:
    """Receivers as the method renders them from ``surfels``: per camera, the points, the
    unit normals, the pixel footprints and the alpha [H, W]. ``band`` 0: the paper's points
    of the median depth and blended normals; > 0: each pixel's median surface, the splats
    within ``band`` pixel footprints of its median splat (``shading.surface_aovs``)."""
    from mi_shadowgs.core import shading
    from mi_shadowgs.core.raster import rasterize

    points, normals, footprints, alphas = [], [], [], []
    for cam in cameras:
        if band > 0:
            g = shading.pixel_geometry(surfels, cam, surface_band=band)
            alphas.append(np.asarray(g.alpha).reshape(cam.height, cam.width))
            points.append(g.points)
            normals.append(g.normal)
            footprints.append(g.footprint)
            continue
        with dr.suspend_grad():
            out = rasterize(surfels, cam, None, aovs=("alpha", "median_depth", "normal"))
        alphas.append(np.asarray(out["alpha"].array).reshape(cam.height, cam.width))
        points.append(unproject_depth(out["median_depth"], cam))
        footprints.append(pixel_footprint(out["median_depth"], cam))
        n = np.asarray(out["normal"].array, dtype=np.float64).reshape(-1, 3)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        n = n.astype(np.float32)
        normals.append(mi.Vector3f(n[:, 0], n[:, 1], n[:, 2]))
    return points, normals, footprints, alphas


def traced_receivers(gt: dict, cameras) -> tuple[list, list]:
    """Receivers of the true scene (``trace_ground_truth``'s buffers): per camera, the points
    of the depth at the pixel centre and the normals facing the camera."""
    points, normals = [], []
    for v, cam in enumerate(cameras):
        points.append(unproject_depth(mi.TensorXf(gt["depth"][v].astype(np.float32)[..., None]),
                                      cam))
        n = gt["normal"][v].reshape(-1, 3).astype(np.float32)
        normals.append(mi.Vector3f(n[:, 0], n[:, 1], n[:, 2]))
    return points, normals


def model_case(model: Path, data: Path, cfg: ValidationConfig, name: str | None = None,
               receiver_band: float = 0.0) -> Case:
    """The test views of ``data`` with points from the stage-1 model's rendered geometry
    (``rendered_receivers`` at ``receiver_band``); named ``name`` (default
    ``model_case_names``' for this model alone)."""
    from mi_shadowgs.dataset.loader import load_cameras
    from mi_shadowgs.io.ply import load_ply

    setup = dataset_scene(data)
    cams = [c for _, c in load_cameras(data / transforms_name("test"))][:cfg.n_views]
    surfels = load_ply(model)
    lights, dirs = make_lights(cfg.lights)
    gt = trace_ground_truth(setup, cams, lights)
    gt_shadow = truth_shadow(gt, dirs)
    points, normals, footprints, alphas = rendered_receivers(surfels, cams, receiver_band)
    masks = [gt["mask"][v].astype(bool) & (alpha > 0.5) for v, alpha in enumerate(alphas)]
    # Frame the maps on the occluders: the model's own surface points inside the object masks
    # (an input of the method), not every surfel (the base would blow the map up).
    obj = np.concatenate([np.asarray(p, dtype=np.float64).reshape(3, -1).T[
        (gt["object"][v].astype(bool) & masks[v]).ravel()] for v, p in enumerate(points)])
    if len(obj) == 0:
        raise ValueError(f"{model}: the model covers no object pixel of the test views")
    bounds = SceneBounds.from_points(obj, cams)
    name = name or model_case_names([model], [data])[0]
    return Case(name, surfels, bounds, dirs, cams, points, normals,
                np.stack(masks), gt_shadow, footprints, setup, gt)


# -- where a stage-1 model's IoU is lost --------------------------------------------------
# (key, label): the pixel method's IoU with each input swapped for the truth's, in the
# order of the factor table's columns.
FACTORS = (("run", "run"),
           ("true_points", "true points"),
           ("true_normals", "true normals"),
           ("true_horizon", "true normals, horizon test alone"),
           ("pixel_horizon", "pixel-area horizon test"),
           ("true_receivers", "true receivers"),
           ("exact_occluders", "exact occluders"),
           ("true_receivers_exact_occluders", "true receivers + exact occluders"),
           ("exact_geometry", "exact geometry, rendered receivers"),
           ("pixel_ceiling", "pixel-area truth"))


def exact_surfel_config(cfg: ValidationConfig, camera, object_surfels: int | None = None,
                        base_surfels: int | None = None) -> ValidationConfig:
    """``cfg`` with the exact geometry's surfel counts for views the size of ``camera``: the
    counts given for ``cfg.resolution``^2 views (``object_surfels``, ``base_surfels``;
    default ``cfg``'s), scaled with the pixel count, so that the surfels are as many per
    pixel at every view size (a fixed count is too sparse for larger views)."""
    scale = camera.width * camera.height / float(cfg.resolution ** 2)
    obj = cfg.object_surfels if object_surfels is None else object_surfels
    base = cfg.base_surfels if base_surfels is None else base_surfels
    return dataclasses.replace(cfg, object_surfels=max(1, round(obj * scale)),
                               base_surfels=max(1, round(base * scale)))


def model_factors(case: Case, cfg: ValidationConfig, base: VisibilityConfig,
                  samples: int = 4, exact_surfels: int | None = None,
                  receiver_band: float = 0.0) -> dict[str, float]:
    """Where a stage-1 model's shadow IoU (the pixel method, ``base``) is lost (``case``:
    a ``model_case``, whose scene and traced truth are reused). The model's
    receivers (rendered median depth and normals) and occluders (its surfels' shadow maps)
    are swapped for the truth's, one at a time and together: the ray-traced points and
    normals at each pixel's centre; surfels sampled on the true shapes (``scene_surfels``)
    in maps framed as the model's. **Exact geometry** renders those surfels' receivers as
    the method renders a model's: what a perfect stage 1 would score at this view size.
    **Pixel-area truth** thresholds the true lit fraction over ``samples``^2 points of each
    pixel (``box_filtered_ground_truth``) at 0.5: what an answer that resolves the scene to
    the pixel scores against the point-sampled truth. The truth's normals enter twice, in
    the horizon test (V = 0 where n . l <= 0: attached shadow) and the normal offset; the
    **horizon test alone** keeps the model's cast shadows (its maps, points and offset) and
    takes the truth's test at each pixel's centre, the **pixel-area horizon test** the test
    passed by most of the pixel's area (over the same ``samples``^2 points): what normals
    right at the pixel scale, but not within it, allow. ``exact_surfels``: on the object for
    ``cfg.resolution``^2 views (default ``cfg.object_surfels``), scaled with the views' pixel
    count as the base's are (``exact_surfel_config``). ``receiver_band``: the receivers
    rendered from surfels (the case's were made with it too). Returns key -> IoU
    (``FACTORS``)."""
    if case.setup is None:
        raise ValueError(f"{case.name}: the factor split is for a model's case (model_case)")
    setup, gt = case.setup, case.truth
    lights, dirs = make_lights(cfg.lights)
    true_pts, true_nrm = traced_receivers(gt, case.cameras)
    exact = scene_surfels(setup, exact_surfel_config(cfg, case.cameras[0], exact_surfels))
    exact_pts, exact_nrm, exact_fp, _ = rendered_receivers(exact, case.cameras,
                                                           receiver_band)
    views = range(len(case.cameras))
    model_maps = render_shadow_maps(case.surfels, case.directions, case.bounds, base)
    exact_maps = render_shadow_maps(exact, case.directions, case.bounds, base)
    no_fp = [None] * len(case.cameras)  # exact points: no receiver offset
    combos = {
        "run": (model_maps, case.points, case.normals, case.footprints),
        "true_points": (model_maps, true_pts, case.normals, no_fp),
        "true_normals": (model_maps, case.points, true_nrm, case.footprints),
        "true_receivers": (model_maps, true_pts, true_nrm, no_fp),
        "exact_occluders": (exact_maps, case.points, case.normals, case.footprints),
        "true_receivers_exact_occluders": (exact_maps, true_pts, true_nrm, no_fp),
        "exact_geometry": (exact_maps, exact_pts, exact_nrm, exact_fp),
    }
    h, w = case.mask.shape[1:]

    def visibility(maps, pts, nrm, fp) -> list[np.ndarray]:
        return [np.asarray(maps.evaluate(pts[v], nrm[v], fp[v]), np.float32).reshape(
            h, w, len(dirs)) for v in views]  # per view [H, W, L]

    out = {key: score(visibility(*combo), case)["shadow_iou"] for key, combo in combos.items()}
    box = box_filtered_ground_truth(setup, case.cameras, lights, samples)
    out["pixel_ceiling"] = score(list(box["lit"]), case)["shadow_iou"]
    # The model's cast shadows alone (no horizon test), then each truth's horizon test.
    cast_maps = dataclasses.replace(model_maps, config=dataclasses.replace(
        base, horizon_cos=-math.inf))
    cast = visibility(cast_maps, case.points, case.normals, case.footprints)
    horizons = {"true_horizon": facing_lights(gt["normal"], dirs),  # [V, H, W, L]
                "pixel_horizon": box["facing"] > 0.5}
    for key, facing in horizons.items():
        out[key] = score([c * facing[v] for v, c in enumerate(cast)], case)["shadow_iou"]
    return {key: out[key] for key, _ in FACTORS}


def factors_markdown(factors: dict[str, dict[str, float]]) -> str:
    """One row per stage-1 case: its IoU under each swap of ``FACTORS``."""
    lines = ["| model | " + " | ".join(label for _, label in FACTORS) + " |",
             "|---|" + "---|" * len(FACTORS)]
    for name, row in factors.items():
        lines.append(f"| {name} | " + " | ".join(f"{row[k]:.3f}" for k, _ in FACTORS) + " |")
    return "\n".join(lines)


# -- sweep --------------------------------------------------------------------------------
def sweep_configs(cfg: ValidationConfig, base: VisibilityConfig) -> list[tuple[str, dict]]:
    out = [("paper", {})]
    out += [("resolution", {"resolution": r}) for r in cfg.sweep_resolutions
            if r != base.resolution]
    out += [("tau", {"tau": t}) for t in cfg.sweep_taus if t != base.tau]
    out += [("distance_factor", {"distance_factor": d}) for d in cfg.sweep_distances
            if d != base.distance_factor]
    out += [("projection", {"projection": "orthographic"}),
            ("projection", {"projection": "orthographic", "resolution": 256}),
            ("depth", {"depth": "expected"}),
            ("normal_offset", {"normal_offset": 1.0})]
    return out


def sweep_row(case: Case, cfg: ValidationConfig, vc: VisibilityConfig, group: str,
              over: dict) -> dict:
    """One setting of the sweep (``sweep_configs``' ``group``, ``over``; ``vc`` the maps'
    config with it): the scores and times of the pixel method on ``case``."""
    res = run_method(lambda: render_shadow_maps(case.surfels, case.directions, case.bounds,
                                                vc), case, cfg.sweep_repeats)
    n_l = len(case.directions)
    return {"group": group, "setting": sweep_label(over), **dataclasses.asdict(vc),
            "shadow_iou": res["shadow_iou"], "visible_iou": res["visible_iou"],
            "accuracy": res["accuracy"], "map_ms_per_direction": 1e3 * res["build_s"] / n_l,
            "lookup_ms_per_view": res["eval_ms_per_view"],
            "ms_per_view_amortised": res["eval_ms_per_view"]
            + 1e3 * res["build_s"] / cfg.timing_views}


def sweep_label(over: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in over.items()) or "paper defaults"


def timing_row(case: Case, cfg: ValidationConfig, vc: VisibilityConfig, n_l: int) -> dict:
    """Shadow-map visibility time for ``n_l`` grid directions (maps of ``vc``) for a view of
    cfg.resolution^2 pixels (all pixels, as the training pipeline does)."""
    pts, nrm, foot = case.points[0], case.normals[0], case.footprint(0)
    dirs = light_grid(n_l)
    tm, tl = [], []
    for r in range(cfg.repeats + 1):
        maps, t_map = _sync_time(lambda: render_shadow_maps(case.surfels, dirs, case.bounds,
                                                            vc))
        _, t_look = _sync_time(lambda m=maps: dr.eval(m.evaluate(pts, nrm, foot)))
        if r > 0 or cfg.repeats == 0:
            tm.append(t_map)
            tl.append(t_look)
    t_map, t_look = float(np.median(tm)), float(np.median(tl))
    return {"map_resolution": vc.resolution, "n_directions": n_l,
            "view_pixels": dr.width(pts), "maps_s": t_map, "lookup_s_per_view": t_look,
            "s_per_view_amortised": t_look + t_map / cfg.timing_views,
            "s_single_view_with_maps": t_look + t_map}


# -- reports ------------------------------------------------------------------------------
def _csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def plot_sweep(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_shadowgs.io.atomic import atomic_path

    fig, ax = plt.subplots(figsize=(7, 4.5))
    groups = sorted({r["group"] for r in rows})
    for g in groups:
        rs = [r for r in rows if r["group"] == g]
        ax.scatter([r["ms_per_view_amortised"] for r in rs], [r["shadow_iou"] for r in rs],
                   label=g, s=30)
        for r in rs:
            ax.annotate(r["setting"].replace("distance_factor", "df"),
                        (r["ms_per_view_amortised"], r["shadow_iou"]), fontsize=6,
                        xytext=(3, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("ms per view (lookup + maps amortised over views), 8 directions")
    ax.set_ylabel("mean shadow IoU vs ray tracing")
    ax.set_title("Shadow-map visibility: speed vs error (default scene)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


def table2_markdown(results: dict, cases: list[str]) -> str:
    head = "| Method | " + " | ".join(f"IoU {c}" for c in cases) + \
        " | mean IoU | build (s) | eval ms/view | ms/view (200 views) |"
    lines = [head, "|" + "---|" * (len(cases) + 5)]
    for m, per in results.items():
        ious = [per[c]["shadow_iou"] for c in cases]
        build = np.mean([per[c]["build_s"] for c in cases])
        ev = np.mean([per[c]["eval_ms_per_view"] for c in cases])
        lines.append(f"| {m} | " + " | ".join(f"{x:.3f}" for x in ious)
                     + f" | {np.mean(ious):.3f} | {build:.2f} | {ev:.0f} | "
                       f"{ev + 1e3 * build / 200:.0f} |")
    return "\n".join(lines)


def tau_summary(rows: list[dict]) -> str:
    taus = sorted([r for r in rows if r["group"] in ("tau", "paper")], key=lambda r: r["tau"])
    out = ["| tau | shadow IoU | visible IoU | accuracy |", "|---|---|---|---|"]
    out += [f"| {r['tau']:g} | {r['shadow_iou']:.4f} | {r['visible_iou']:.4f} | "
            f"{r['accuracy']:.4f} |" for r in taus]
    best = max(taus, key=lambda r: r["shadow_iou"])
    out += ["", f"Best tau here: {best['tau']:g} (shadow IoU {best['shadow_iou']:.4f}). "
            "tau is relative to the map depth (the light camera stands at 30x the camera "
            "distance, so d_l ~ 120 scene units and tau = 8e-4 is ~0.1 scene units): too small "
            "and the surfels' own depth (median-depth jitter, tangent planes of curved parts) "
            "shadows the receiver (acne, shadow IoU falls through false positives); too large "
            "and occluders closer than tau * d_l to the receiver are ignored (contact shadows "
            "shrink, light leaks under the object)."]
    return "\n".join(out)


def projection_note(rows: list[dict]) -> str:
    """Why orthographic maps can beat the paper's far perspective camera."""
    by = {r["setting"]: r for r in rows}
    persp, ortho = by.get("paper defaults"), by.get("projection=orthographic")
    if not persp or not ortho:
        return ""
    return (f"Projection: orthographic maps give shadow IoU {ortho['shadow_iou']:.4f} against "
            f"{persp['shadow_iou']:.4f} for the paper's perspective camera at 30x the camera "
            "distance. A perspective map is the shadow of a point light at that distance: its "
            "rays diverge from l by up to r / D (~0.5 degrees here), which shifts shadow edges "
            "by (occluder-receiver distance) x that angle; moving the camera farther does not "
            "fix it because tau is relative, so the absolute slack tau * d_l grows with the "
            "distance and contact shadows are lost (see the distance_factor rows).")


def best_tradeoff(rows: list[dict]) -> dict:
    """Fastest setting within 0.005 of the best shadow IoU."""
    top = max(r["shadow_iou"] for r in rows)
    ok = [r for r in rows if r["shadow_iou"] >= top - 0.005]
    return min(ok, key=lambda r: r["ms_per_view_amortised"])


# -- units -------------------------------------------------------------------------------
STUDY = "validation.visibility"
# Top-level files that only some calls write (the sweep's with the ground-truth scenes,
# factors.md with --factors): a call without them removes an earlier call's, so that the
# folder's files tell of one call.
ONE_CALL_FILES = ("sweep.csv", "sweep.md", "timing.csv", "sweep.png", "factors.md")


@dataclasses.dataclass
class CaseSpec:
    """A case and what its units are made from; the case is built on first use (``case``),
    so that a rerun whose units are finished builds none."""

    name: str
    dataset: dict | None  # dataset_ref of a model's dataset
    inputs: dict  # name -> input_ref: the scene's files, a model's PLY
    settings: dict  # what every unit of the case depends on
    case: Callable[[], Case]  # cached
    files: tuple = ()  # inputs that a unit's folder must not hold

    def provenance(self, **settings) -> Provenance:
        return Provenance(self.dataset, self.inputs, settings_of(**self.settings, **settings))


# The ValidationConfig fields a case's surfels, views and lights are made from; the timing
# and sweep fields are settings of the units that use them.
CASE_FIELDS = ("n_views", "resolution", "camera_distance", "object_surfels", "base_surfels",
               "base_radius", "sigma_factor", "lights")


def case_settings(cfg: ValidationConfig) -> dict:
    return {field: getattr(cfg, field) for field in CASE_FIELDS}


def scene_spec(name: str, scene_path: Path, overrides: dict | None,
               cfg: ValidationConfig) -> CaseSpec:
    """A ground-truth scene's case (``ground_truth_case``)."""
    inputs = {"scene": input_ref(scene_path)}
    inputs.update({key: input_ref(path) for key, path in (overrides or {}).items()})
    return CaseSpec(name, None, inputs,
                    {"case": name, "config": case_settings(cfg)},
                    functools.cache(lambda: ground_truth_case(name, scene_path, overrides,
                                                              cfg)))


def model_spec(model: Path, data: Path, cfg: ValidationConfig, name: str,
               receiver_band: float) -> CaseSpec:
    """A model's case (``model_case``)."""
    return CaseSpec(name, dataset_ref(data), {"model": input_ref(model)},
                    {"case": name, "config": case_settings(cfg),
                     "receiver_band": receiver_band},
                    functools.cache(lambda: model_case(model, data, cfg, name,
                                                       receiver_band)),
                    (model, data))


def table2_result(case: Case, config, repeats: int) -> dict:
    """One method's Table 2 figures on ``case`` (``config``: one of ``method_configs``)."""
    res = run_method(lambda: BUILDERS[type(config)](case.surfels, case.directions,
                                                    case.bounds, config), case, repeats)
    res.pop("vis")
    return res


# -- entry points -------------------------------------------------------------------------
def _progress(quiet: bool):
    from tqdm import tqdm

    return lambda it, desc: tqdm(list(it), desc=desc, disable=quiet, leave=False)


def run(out_dir, quick: bool = False, model=None, data=None, quiet: bool = False,
        factors: bool = False, factor_samples: int = 4, factor_surfels: int | None = None,
        models_only: bool = False, receiver_band: float | None = None,
        preset: str | None = None, overwrite: bool = False, lights=None) -> dict:
    """Everything above; writes into ``out_dir`` (new, or this validation's: ``claim_out``):
    each case's row of each method, each model's factor split, each setting of the sweep
    and of the timing is a unit (``validation.units``), so that a rerun after a kill redoes
    only the unfinished ones and exits 2 naming what differs where a unit was made from
    other inputs or settings (``overwrite``: its units made again); the tables are written
    from the units at the end. ``model`` and
    ``data``: a stage-1 PLY and its dataset, or equally long lists of them; ``factors``:
    each model's ``model_factors`` too (``factor_samples``^2 points per pixel for the
    pixel-area truth, ``factor_surfels`` exact surfels on the object); ``models_only``: the
    models' rows alone (no ground-truth scenes, sweep or timing); ``preset``: the pixel
    method's maps at that preset's visibility settings (``shadow_maps.PRESETS``) instead of
    the paper's, and its receiver band; ``receiver_band``: the models' receivers
    (``rendered_receivers``; None: the preset's band, 0 without a preset); ``lights``:
    (azimuth, elevation) pairs in degrees in place of ``LIGHTS`` (a fitted light's own
    direction, say). Returns a summary dict with a ``markdown`` entry."""
    models = [model] if isinstance(model, str | Path) else list(model or [])
    datas = [data] if isinstance(data, str | Path) else list(data or [])
    if len(models) != len(datas):
        raise ValueError(f"every --model needs its --data (the dataset it was trained on): "
                         f"{len(models)} models, {len(datas)} datasets")
    if factors and not models:
        raise ValueError("--factors splits a stage-1 model's IoU: give --model and --data")
    if models_only and not models:
        raise ValueError("--models-only scores stage-1 models: give --model and --data")
    if factor_samples < 1:
        raise ValueError(f"--factor-samples must be >= 1, got {factor_samples}")
    if factor_surfels is not None and factor_surfels < 1:
        raise ValueError(f"--factor-surfels must be >= 1, got {factor_surfels}")
    # The paper's maps (Table 2 as published), or a preset's: what a run at it uses.
    base = VisibilityConfig() if preset is None else get_visibility_config(preset)
    if receiver_band is not None and not receiver_band >= 0:
        raise ValueError(f"--receiver-band must be >= 0, got {receiver_band}")
    if receiver_band is not None and receiver_band > 0 and not models:
        raise ValueError("--receiver-band renders a stage-1 model's receivers: give --model "
                         "and --data")
    case_names = model_case_names([Path(m) for m in models], [Path(d) for d in datas])
    cfg = QUICK if quick else ValidationConfig()
    if lights is not None:
        cfg = dataclasses.replace(cfg, lights=checked_lights(lights))
    receiver_band = base.receiver_band if receiver_band is None else receiver_band
    progress = _progress(quiet)
    scenes, notes = [], []
    if not models_only:
        scenes.append(("default", REPO / "mi_shadowgs" / "scenes" / "default.xml", None))
        if BUNNY.is_file():
            scenes.append(("bunny", REPO / "mi_shadowgs" / "scenes" / "mesh.xml",
                           {"mesh": str(BUNNY)}))
        else:
            notes.append(f"bunny skipped: {BUNNY} is absent (shared data not installed)")
            print(f"visibility validation: {notes[-1]}", flush=True)
    scene_specs = [scene_spec(n, p, o, cfg) for n, p, o in scenes]
    model_specs = [model_spec(Path(m), Path(d), cfg, n, receiver_band)
                   for m, d, n in zip(models, datas, case_names, strict=True)]
    specs = scene_specs + model_specs
    if len({unit_name(s.name) for s in specs}) < len(specs):
        raise ValueError(f"the cases {[s.name for s in specs]} do not all make distinct "
                         f"folder names under {UNITS}/; rename a run folder")
    out = claim_out(out_dir, STUDY, ("summary.json",),
                    inputs=[f for spec in specs for f in spec.files])
    t_start = time.perf_counter()

    # Rows hold timings as well as scores: a unit timed on another device is not reused.
    device = device_name(mi.variant())

    def unit(name: str, spec: CaseSpec, work, **settings) -> dict:
        """Unit ``name``: ``work(case)`` on ``spec``'s case, with ``settings`` besides the
        case's own; a smoke run's are its own (``smoke_name``)."""
        return run_unit(out, smoke_name(name, quick), STUDY,
                        spec.provenance(device=device, **settings),
                        lambda _: work(spec.case()), overwrite=overwrite, inputs=spec.files)

    names = [s.name for s in specs]  # results are keyed by case name
    results = {}
    for method, config in method_configs(base, quick).items():
        results[method] = {}
        for spec in progress(specs, desc=method):
            results[method][spec.name] = unit(
                unit_name("table2", spec.name, method), spec,
                functools.partial(table2_result, config=config, repeats=cfg.repeats),
                method=method, method_settings=dataclasses.asdict(config),
                repeats=cfg.repeats)
    split = {}
    if factors:
        for spec in progress(model_specs, desc="factors"):
            split[spec.name] = unit(
                unit_name("factors", spec.name), spec,
                functools.partial(model_factors, cfg=cfg, base=base, samples=factor_samples,
                                  exact_surfels=factor_surfels, receiver_band=receiver_band),
                visibility=dataclasses.asdict(base), factor_samples=factor_samples,
                factor_surfels=factor_surfels)
    gt_names = [s.name for s in scene_specs]
    model_names = [s.name for s in model_specs]
    sweep, timing = [], []
    if scene_specs:  # on the default scene's exact surfels
        for group, over in progress(sweep_configs(cfg, base), desc="sweep"):
            vc = dataclasses.replace(base, **over)
            sweep.append(unit(unit_name("sweep", sweep_label(over)), scene_specs[0],
                              functools.partial(sweep_row, cfg=cfg, vc=vc, group=group,
                                                over=over),
                              visibility=dataclasses.asdict(vc),
                              sweep_repeats=cfg.sweep_repeats, timing_views=cfg.timing_views))
        for res_map in cfg.timing_map_resolutions:
            vc = dataclasses.replace(base, resolution=res_map)
            for n_l in progress(cfg.sweep_lights, desc=f"N_l @ {res_map}^2"):
                timing.append(unit(unit_name("timing", f"{res_map}px", f"{n_l}lights"),
                                   scene_specs[0],
                                   functools.partial(timing_row, cfg=cfg, vc=vc, n_l=n_l),
                                   visibility=dataclasses.asdict(vc), n_directions=n_l,
                                   repeats=cfg.repeats, timing_views=cfg.timing_views))
    baselines = [m for m in results if not m.startswith("Pixel")]
    wins_md = []
    for m in (m for m in results if m.startswith("Pixel")):
        wins = {c: all(results[m][c]["shadow_iou"] > results[b][c]["shadow_iou"]
                       for b in baselines) for c in names}
        wins_md.append(f"{m} beats both baselines on: "
                       f"{', '.join(c for c, w in wins.items() if w) or 'none'}; not on: "
                       f"{', '.join(c for c, w in wins.items() if not w) or 'none'}.")
    t128 = [r for r in timing if r["map_resolution"] == 128 and r["n_directions"] == 128]
    table = table2_markdown(results, gt_names) if gt_names else ""
    if model_names:
        table += ("\n\n" if table else "") + "From the models' surfels (their own rendered " \
            "depth and normals):\n\n" + table2_markdown(results, model_names)
    table_rows = [{"method": m, "case": c, **{k: v for k, v in r.items()}}
                  for m, per in results.items() for c, r in per.items()]
    # the spiral views and exact surfels are the ground-truth scenes' (none with --models-only)
    scenes_note = (f"{cfg.n_views} test-spiral views at {cfg.resolution}^2; surfels sampled on "
                   f"the true shapes ({cfg.object_surfels} object + {cfg.base_surfels} base, "
                   f"sigma {cfg.sigma_factor} x spacing). ") if gt_names else ""
    receivers = ("the median depth and blended normals" if receiver_band == 0 else
                 f"each pixel's median surface (receiver band {receiver_band:g})")
    models_note = (f"Stage-1 models: the first {cfg.n_views} test views of their datasets, at "
                   f"the datasets' size; receivers from {receivers}. ") if model_names else ""
    maps_note = ("The pixel method's maps: the paper's settings. " if preset is None else
                 f"The pixel method's maps: the visibility settings of preset {preset!r} "
                 f"({base.projection}, {base.resolution} texels). ")
    md = [f"## Visibility ({'quick' if quick else 'full'})", "",
          f"{len(cfg.lights)} light directions (az, el deg): {list(cfg.lights)}; "
          f"{scenes_note}{models_note}{maps_note}Shadow IoU (V < 0.5) vs Mitsuba ray "
          "tracing.", "",
          "### Table 2", "", table, ""]
    md += wins_md + [""]
    if split:
        md += ["### Where each model's IoU is lost", "",
               "The pixel method's IoU with the model's receivers (points, normals) and "
               "occluders swapped for the truth's; horizon test alone: the model's cast "
               "shadows with the truth's attached ones (n . l <= 0) at the pixel's centre; "
               "pixel-area horizon test: with the attached shadows of most of the pixel's "
               "area; exact geometry: surfels on the true shapes, "
               f"{factor_surfels or cfg.object_surfels} on the object at {cfg.resolution}^2 "
               "views (scaled with the views' pixel count), receivers rendered from "
               "them as from a model; pixel-area truth: the true lit fraction over "
               f"{factor_samples}^2 points per pixel, thresholded at 0.5.", "",
               factors_markdown(split), ""]
    pixel = [m for m in results if m.startswith("Pixel")]
    if any(results[b][c]["shadow_iou"] >= results[m][c]["shadow_iou"]
           for m in pixel for b in baselines for c in gt_names):  # exact surfels' cases
        md += ["Where a baseline wins: on surfels sampled exactly on the surface, tracing them "
               "is nearly exact; the pixel method loses map texels, the tau slack and "
               "(perspective maps) the divergence of the light camera's rays from l.", ""]
    if t128:
        r = t128[0]
        md += [f"Shadow-map visibility, 128 directions, maps 128^2, view {cfg.resolution}^2: "
               f"maps {r['maps_s']:.2f} s (once for all views), lookup "
               f"{r['lookup_s_per_view']:.3f} s/view, amortised over {cfg.timing_views} views "
               f"{r['s_per_view_amortised']:.3f} s/view, one view with its maps "
               f"{r['s_single_view_with_maps']:.2f} s.", ""]
    best = best_tradeoff(sweep) if sweep else None
    if sweep:
        md += [f"Sweep best trade-off (fastest within 0.005 IoU of the best): "
               f"{best['setting']} -> IoU {best['shadow_iou']:.4f}, "
               f"{best['ms_per_view_amortised']:.1f} ms/view.", ""]
        md += ["### Threshold tau", "", tau_summary(sweep), "", projection_note(sweep), ""]
    md += [f"Note: {n}" for n in notes]
    markdown = "\n".join(md)
    summary = {"config": dataclasses.asdict(cfg), "receiver_band": receiver_band,
               "visibility_preset": preset, "visibility": dataclasses.asdict(base),
               "results": results, "best_tradeoff": best,
               "timing": timing, "factors": split, "notes": notes,
               # this call's: a call that finds its units finished only gathers
               "wall_s": time.perf_counter() - t_start, "loadavg": list(os.getloadavg())}
    texts = {"table2.md": table + "\n", "table2.csv": _csv(table_rows)}
    if sweep:
        texts.update({"sweep.csv": _csv(sweep), "timing.csv": _csv(timing),
                      "sweep.md": tau_summary(sweep) + "\n\n" + projection_note(sweep) + "\n"})
        plot_sweep(sweep, out / "sweep.png")
    if split:
        texts["factors.md"] = factors_markdown(split) + "\n"
    for name, text in texts.items():
        write_text(out / name, text)
    written = {*texts, *(["sweep.png"] if sweep else [])}
    for name in ONE_CALL_FILES:
        if name not in written:  # an earlier call's, which this call lacks
            (out / name).unlink(missing_ok=True)
    write_json(out / "summary.json", summary)
    write_text(out / "README.md", markdown + "\n")
    summary["markdown"] = markdown
    return summary


def main(argv=None) -> int:
    import sys

    argv = sys.argv[1:] if argv is None else list(argv)
    if "--lamp" in argv:  # the lamp's rows: validation.lamp_visibility takes the rest
        from validation import lamp_visibility

        return lamp_visibility.main([a for a in argv if a != "--lamp"],
                                    "python -m validation.visibility --lamp")
    ap = argparse.ArgumentParser(description="Visibility validation against ray tracing "
                                             "(paper Table 2, speed-vs-error sweep).")
    ap.add_argument("--out", required=True, help="output folder: new or an earlier "
                    "output of this validation (its finished units are reused)")
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    ap.add_argument("--model", action="append",
                    help="model PLY (RUN/geometry/model.ply, or a later stage's); repeat with "
                         "--data")
    ap.add_argument("--data", action="append",
                    help="the dataset folder each --model was trained on, in the same order")
    ap.add_argument("--factors", action="store_true",
                    help="also split each --model's IoU: its receivers and occluders "
                         "swapped for the truth's, exact geometry, the pixel-area truth")
    ap.add_argument("--factor-samples", type=int, default=4,
                    help="points per pixel side of the pixel-area truth (default 4)")
    ap.add_argument("--factor-surfels", type=int, default=None,
                    help="exact surfels on the object for the split (default: Table 2's)")
    ap.add_argument("--models-only", action="store_true",
                    help="only the --model rows (no ground-truth scenes, sweep or timing)")
    ap.add_argument("--preset", default=None,
                    help="the pixel method's maps at this preset's visibility settings, "
                         "as a run at it has them (e.g. cpu-small: orthographic, a one-texel "
                         "bias and the occluder layer's slack), and its receiver band "
                         "(default: the paper's settings, Table 2 as published)")
    ap.add_argument("--receiver-band", type=float, default=None,
                    help="render the models' receivers on each pixel's median surface, the "
                         "splats within this many pixel footprints of it, as stages 4-5 of "
                         "the cpu presets do (default: the preset's; 0 without --preset: "
                         "the paper's median depth and blended normals)")
    ap.add_argument("--lights", nargs="+", default=None, metavar="AZ,EL",
                    help="light directions, azimuth and elevation in degrees "
                         "(docs/conventions.md), in place of the 8 fixed ones; e.g. a fitted "
                         "light's own direction")
    ap.add_argument("--overwrite", action="store_true",
                    help="make this call's units again (those made from other inputs or "
                         "settings exit 2 otherwise)")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    ap.add_argument("--lamp", action="store_true",
                    help="shadow maps from a lamp against Mitsuba's hard and soft visibility "
                         "instead (validation.lamp_visibility; see its --help)")
    args = ap.parse_args(argv)
    try:
        summary = run(args.out, args.quick, args.model, args.data, args.quiet,
                      args.factors, args.factor_samples, args.factor_surfels,
                      args.models_only, args.receiver_band, args.preset, args.overwrite,
                      args.lights)
    except (ValueError, FileNotFoundError, FileExistsError) as e:  # names the file or option
        fail(str(e))
    print(summary["markdown"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
