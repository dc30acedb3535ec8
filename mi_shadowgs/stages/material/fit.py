"""Stage 4's loop: ``setup_fit``, then ``fit_material`` steps through the warm-up, its
pruning and refinement, the main phase and the normal phase, and ``fit_result`` returns
the fitted model. Pure functions over Dr.Jit arrays; no I/O here."""

from __future__ import annotations

import dataclasses
import math
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit, shading
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import light_grid, nearest_grid_index, solid_angle
from mi_shadowgs.core.raster import RasterConfig
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.stages.material.channels import (
    DETAIL_CHANNEL,
    _clamp_channels,
    albedo_scale_factor,
    detailed_albedo,
    hold_albedo_scale,
    init_channels,
    segment_ids,
)
from mi_shadowgs.stages.material.config import MaterialConfig
from mi_shadowgs.stages.material.lamps import LampSearch, localize_lights
from mi_shadowgs.stages.material.lights import Refinement, _prune, settle_lights
from mi_shadowgs.stages.material.normals import _start_normals, normal_step, start_normal_phase
from mi_shadowgs.stages.material.state import (
    _LIGHT_KEYS,
    LightModel,
    MaterialFit,
    MaterialResult,
    MaterialState,
    _count_step,
)
from mi_shadowgs.stages.material.views import (
    DEFAULT_RASTER,
    TrainView,
    held_images,
    prepare_view,
    surfel_support,
    view_loss,
)
from mi_shadowgs.stages.visibility.shadow_maps import (
    SceneBounds,
    VisibilityConfig,
)

DEFAULT_VISIBILITY = VisibilityConfig()


def _current_channels(state: MaterialState) -> dict:
    """The material channels as the optimiser holds them now (its lights left out)."""
    cur = dict(state.channels)
    for key in state.opt.keys():
        if key not in _LIGHT_KEYS:
            cur[key] = state.opt[key]
    return cur


def _irradiance(state: MaterialState, dw: float) -> np.ndarray:
    """The lights' irradiance [K] from the optimiser's log radiance (``dw``: a direction's
    solid angle)."""
    return np.exp(state.opt["log_light"].numpy().astype(np.float64)) * dw


def _set_irradiance(state: MaterialState, irr: np.ndarray, dw: float,
                    config: MaterialConfig) -> None:
    """The optimiser's lights set to irradiance ``irr`` [K], at the light learning rate."""
    state.opt["log_light"] = jit.host(np.log(np.maximum(irr / dw, 1e-12)).astype(np.float32))
    state.opt.set_learning_rate({"log_light": config.lr_light})


def _refinement_views(fit: MaterialFit) -> list:
    """The ``refine_views`` training views the light refinements score, evenly spread."""
    n = len(fit.views)
    pick = np.unique(np.linspace(0, n - 1, min(fit.config.refine_views, n)).round()
                     .astype(int))
    return [fit.views[i] for i in pick]


def _refine(views, state: MaterialState, maps, render_maps, config: MaterialConfig,
            on_unit, global_pass: bool = False, center=None) -> np.ndarray:
    """``refine_directions`` on the optimiser's current state, or the rest of
    ``state.refine`` when a checkpoint was written inside it; sets the refitted light and
    returns the directions."""
    dw = solid_angle(config.n_directions)
    cur = _current_channels(state)
    if state.refine is None:
        irr = _irradiance(state, dw)
        # the end of the warm-up (global_pass) or the main phase's second refinement
        state.refine = Refinement.start(state.directions, irr, config,
                                        global_pass or config.refine_again_global,
                                        again=not global_pass)
    else:
        maps = render_maps(state.refine.dirs, None, state.positions)
    state.refine.run(views, cur, maps, render_maps, config, state.specular, on_unit,
                     state.positions, center)
    dirs, irr = state.refine.dirs, state.refine.irradiance
    state.refine = None
    _set_irradiance(state, irr, dw, config)
    return dirs


def _settle(fit: MaterialFit, state: MaterialState) -> None:
    """``settle_lights`` on the refinement's views and the optimiser's current state."""
    config = fit.config
    dw = solid_angle(config.n_directions)
    dirs, irr, maps, pos = settle_lights(_refinement_views(fit), _current_channels(state),
                                         state.directions, _irradiance(state, dw), fit.maps,
                                         fit.shadow_maps, config, state.specular,
                                         state.positions, fit.bounds.center)
    state.directions, fit.maps, state.positions = dirs, maps, pos
    _set_irradiance(state, irr, dw, config)


def _prune_state(fit: MaterialFit, state: MaterialState) -> None:
    """``_prune`` on the state's lights (lamps keep their positions)."""
    state.directions, fit.maps, state.positions = _prune(
        state.opt, state.directions, fit.maps, fit.config, fit.shadow_maps, state.positions)


def _localize(fit: MaterialFit, state: MaterialState) -> None:
    """``localize_lights`` on the refinement's views and the optimiser's current state,
    then the lights settled again (a lamp explains the falloff a second light was fitted
    to)."""
    config = fit.config
    if not fit.views:
        return
    dw = solid_angle(config.n_directions)
    irr = _irradiance(state, dw)
    search = LampSearch(_refinement_views(fit), _current_channels(state), fit.shadow_maps,
                        config, state.specular, np.asarray(fit.bounds.center, np.float64),
                        fit.bounds.radius)
    order = np.argsort(-irr)[:config.refine_max_lights]
    dirs, pos, irr, log = localize_lights(search, state.directions, state.positions, irr,
                                          order)
    if state.positions is None and not np.isfinite(pos).any():
        state.log_lights("localize", dw, log)  # every light stays as it was
        return
    state.directions = dirs
    state.positions = pos if np.isfinite(pos).any() else None
    _set_irradiance(state, irr, dw, config)
    fit.maps = fit.state_maps(state)
    state.log_lights("localize", dw, log)
    if len(state.directions) > 1:
        _settle(fit, state)
        state.log_lights("settle", dw)


def setup_fit(surfels: Surfels, cameras: list[Camera], images: list[np.ndarray],
              masks: list[np.ndarray], config: MaterialConfig, bounds: SceneBounds,
              vis_config: VisibilityConfig = DEFAULT_VISIBILITY,
              raster: RasterConfig = DEFAULT_RASTER, progress: bool = True,
              state: MaterialState | None = None, gains: list[np.ndarray] | None = None,
              past=None) -> tuple[MaterialFit, MaterialState]:
    """Set-up: the training views' fixed lookups, the state at step 0 (or ``state``, from a
    checkpoint) and the shadow maps of its lights. ``gains``: stage 1's RGB gain [3] per
    view, held: each image is divided by its gain here, once (``held_images``); ``past``:
    pixels left out (``prepare_view``; used where ``backdrop_surfels`` is "skip")."""
    from tqdm import tqdm

    if not (len(cameras) == len(images) == len(masks)) or not cameras:
        raise ValueError("fit_material: need as many images and masks as cameras (>= 1)")
    images = held_images(images, gains)
    t0 = time.perf_counter()
    seg = segment_ids(surfels)
    n_seg = int(np.max(seg.numpy())) + 1 if surfels.count else 1
    past = past if config.backdrop_surfels == "skip" else None
    views = [prepare_view(surfels, c, im, m, config, raster, vis_config.receiver_band, past)
             for c, im, m in zip(tqdm(cameras, desc="stage 4: views", disable=not progress),
                                 images, masks, strict=True)]
    if state is None:
        state = _initial_state(surfels, images, views, seg, n_seg, config)
    state.timings["prepare_s"] = (state.timings.get("prepare_s", 0.0)
                                  + time.perf_counter() - t0)
    fit = MaterialFit(surfels, views, seg, n_seg, config, vis_config, bounds, None)
    # Per-view point/normal lookups are fixed: visibility of all active directions per view
    # is re-evaluated on the fly (cheap gathers) rather than stored (V x H x W x L floats).
    # The warm-up's maps up to its end (unless the checkpoint is inside the refinement that
    # follows it), the full-resolution ones after.
    warmup_res = min(config.warmup_map_resolution, vis_config.resolution)
    fit.maps = fit.state_maps(state, warmup_res if state.step < config.warmup or (
        state.step == config.warmup and state.refine is None) else None)
    if DETAIL_CHANNEL in state.channels and state.step < config.iterations:
        detail_gates(fit, state)  # resumed while the detail fits (the normal phase holds it)
    return fit, state


def refine_lights(fit: MaterialFit, state: MaterialState, on_unit=None,
                  global_pass: bool = False) -> None:
    """The light-direction refinement (or the rest of ``state.refine``), then the refined
    lights' maps (nothing without refinement passes or visibility), then ``settle_lights``
    (merge the lights that met, drop those that explain little)."""
    # the end of the warm-up (global_pass) or the main phase's second refinement
    if ((fit.config.local_passes(not global_pass) or (global_pass and fit.config.refine_global))
            and fit.maps is not None):
        state.directions = _refine(fit.views, state, fit.maps, fit.shadow_maps, fit.config,
                                   on_unit, global_pass, fit.bounds.center)
        fit.maps = fit.state_maps(state)
        state.log_lights("refine", solid_angle(fit.config.n_directions))
    if len(state.directions) > 1:
        _settle(fit, state)
        state.log_lights("settle", solid_angle(fit.config.n_directions))
    if fit.config.lamps != "off":
        _localize(fit, state)


def end_warmup(fit: MaterialFit, state: MaterialState, on_unit=None) -> None:
    """At step ``warmup``: prune the dark lights, the survivors' maps at full resolution,
    settle them (``settle_warmup``; all three skipped when resuming inside the refinement
    that follows), refine the lights, then add the indirect light and decide on the
    specular lobe (``auto``)."""
    if state.refine is None:
        # One host read at the phase boundary.
        if fit.config.prune:
            _prune_state(fit, state)
            state.log_lights("prune", solid_angle(fit.config.n_directions))
        fit.maps = fit.state_maps(state)
        if fit.config.settle_warmup and len(state.directions) > 1:
            _settle(fit, state)
            state.log_lights("settle", solid_angle(fit.config.n_directions))
    refine_lights(fit, state, on_unit, global_pass=True)
    _end_warmup(state, fit.config)


def prune_due(config: MaterialConfig, step: int) -> bool:
    """Whether the main phase prunes the lights before ``step``."""
    return (config.prune and step > config.warmup and config.prune_every > 0
            and (step - config.warmup) % config.prune_every == 0)


def refine_step(config: MaterialConfig) -> int:
    """The main phase's second refinement: half way (-1: none)."""
    return ((config.warmup + config.iterations) // 2
            if config.iterations > config.warmup + 1 else -1)


def fit_step(fit: MaterialFit, state: MaterialState) -> float | None:
    """One optimisation step: loss over ``views_per_step`` random views, Adam, projection.
    Returns the mean loss since the last history entry on a ``log_every`` step, else None."""
    config, opt, ch = fit.config, state.opt, state.channels
    w_light = dr.exp(opt["log_light"]) * solid_angle(config.n_directions)
    lights = state.light_set(w_light, fit.bounds.center)
    cur = _current_channels(state)
    total = mi.Float(0.0)
    for _ in range(config.views_per_step):
        v = fit.views[int(state.rng.integers(len(fit.views)))]
        vis = (None if fit.maps is None
               else fit.maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint))
        total += view_loss(v, cur, lights, vis, config, state.specular)
    total = total / config.views_per_step
    dr.backward(total)
    opt.step()
    for k in opt.keys():
        if k not in _LIGHT_KEYS:
            ch[k] = opt[k]
    _clamp_channels(ch, fit.seg, fit.n_seg, config, state.specular)
    if (config.albedo_scale > 0 and not state.specular
            and state.step % config.albedo_scale_every == 0):  # a host read
        if fit.support is None:
            fit.support = surfel_support(fit.views, fit.surfels.count)
        hold_albedo_scale(ch, opt, albedo_scale_factor(ch["albedo"].numpy(), fit.support,
                                                       config))
    for k in opt.keys():
        if k not in _LIGHT_KEYS:
            opt[k] = ch[k]  # keeps Adam's state (same shape)
    return _count_step(state, config, total)


def detail_step(config: MaterialConfig) -> int:
    """The step the albedo detail joins (after the second refinement, else the warm-up's
    end); -1: never (``detail_prior`` 0)."""
    if config.detail_prior <= 0:
        return -1
    again = refine_step(config)
    return again if again >= 0 else config.warmup


def detail_gates(fit: MaterialFit, state: MaterialState) -> None:
    """Each view's ``detail_gate``: its pixels farther than ``detail_edge_px`` from where a
    light's shadow begins (its visibility crosses 0.5), for the lights the detail joined
    with (``state.detail_directions``: a fit resumed after a light was pruned makes the
    same gates; one host read a view). None (every pixel) without visibility."""
    from scipy.ndimage import maximum_filter, minimum_filter

    if fit.config.detail_edge_px <= 0 or fit.maps is None:
        return
    dirs, pos = state.detail_directions, state.detail_positions
    same = np.array_equal(dirs, state.directions) and (
        (pos is None and state.positions is None)
        or (pos is not None and state.positions is not None
            and np.array_equal(pos, state.positions, equal_nan=True)))
    maps = fit.maps if same else fit.shadow_maps(dirs, None, pos)
    size = (2 * fit.config.detail_edge_px + 1,) * 2 + (1,)
    for k, v in enumerate(fit.views):
        with dr.suspend_grad():
            vis = maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint)
        lit = vis.numpy().reshape(v.pairs.height, v.pairs.width, -1) > 0.5  # [H, W, L]
        edge = np.any(maximum_filter(lit, size) != minimum_filter(lit, size), axis=2)
        fit.views[k] = dataclasses.replace(
            v, detail_gate=jit.host((~edge).reshape(-1).astype(np.float32)))


def start_detail(fit: MaterialFit, state: MaterialState) -> None:
    """At ``detail_step``: the albedo detail joins Adam at 0, and the views' gates."""
    n = fit.surfels.count
    state.channels[DETAIL_CHANNEL] = mi.TensorXf(dr.zeros(mi.Float, n * 3), (n, 3))
    state.opt[DETAIL_CHANNEL] = state.channels[DETAIL_CHANNEL]
    state.opt.set_learning_rate({DETAIL_CHANNEL: fit.config.lr_detail})
    state.detail_directions = np.array(state.directions, np.float64)
    state.detail_positions = (None if state.positions is None
                              else np.array(state.positions, np.float64))
    detail_gates(fit, state)


def fit_result(fit: MaterialFit, state: MaterialState) -> MaterialResult:
    """The fitted model: the input geometry with the material channels, and the light map
    over the grid (each light at its nearest grid direction, as the dataset builds the
    ground-truth map from its directional lights)."""
    config, surfels, ch = fit.config, fit.surfels, state.channels
    light = np.exp(state.opt["log_light"].numpy().astype(np.float64))
    active = nearest_grid_index(state.directions, light_grid(config.n_directions))
    radiance = np.zeros(config.n_directions)
    np.add.at(radiance, active, light)
    out = surfels.with_channels({k: mi.TensorXf(dr.detach(ch[k].array), ch[k].shape)
                                 for k in ("albedo", "roughness", "metallic",
                                           shading.INDIRECT_CHANNEL)})
    if DETAIL_CHANNEL in ch:  # the detailed albedo, which relighting and export read
        a = detailed_albedo(ch["albedo"], ch[DETAIL_CHANNEL])
        out = out.with_channels({"albedo": mi.TensorXf(dr.detach(a.array), a.shape)})
    if shading.SHADING_NORMAL_CHANNEL in ch:  # the normal phase's, as unit vectors
        start, held = _start_normals(fit)
        free = shading.unit_rows(ch[shading.SHADING_NORMAL_CHANNEL])
        n = dr.detach(dr.select(held, start, free))
        out = out.with_channels({shading.SHADING_NORMAL_CHANNEL:
                                 mi.TensorXf(dr.ravel(n), (surfels.count, 3))})
    positions = state.positions
    if positions is not None and not np.isfinite(positions).any():
        positions = None  # every light directional: light.json as without lamps
    center = None if positions is None else np.asarray(fit.bounds.center, np.float64)
    radii = None if positions is None else np.zeros(len(positions))
    return MaterialResult(out, LightModel(radiance, active, state.directions,
                                          light * solid_angle(config.n_directions),
                                          positions, radii, center),
                          state.specular, config.use_visibility, state.history,
                          dict(state.timings), list(state.light_log))


def fit_material(surfels: Surfels, cameras: list[Camera], images: list[np.ndarray],
                 masks: list[np.ndarray], config: MaterialConfig, bounds: SceneBounds,
                 vis_config: VisibilityConfig = DEFAULT_VISIBILITY,
                 raster: RasterConfig = DEFAULT_RASTER, progress: bool = True,
                 state: MaterialState | None = None, on_checkpoint=None,
                 gains: list[np.ndarray] | None = None, past=None) -> MaterialResult:
    """Fit materials, light map and indirect light to the training views (the loop over
    ``setup_fit``, ``end_warmup``, ``prune_due``/``refine_lights``, ``fit_step``, then the
    normal phase's ``start_normal_phase`` and ``normal_step``, and ``fit_result``).

    ``state`` (``MaterialState.from_checkpoint``) continues an interrupted fit;
    ``on_checkpoint(state)`` is called every ``checkpoint_every`` steps, every
    ``checkpoint_seconds``, at the end and at SIGINT/SIGTERM (``mi_shadowgs.io.interrupt``).
    ``gains``: stage 1's RGB gain [3] per view, held, and ``past``: as ``setup_fit``'s.
    """
    from tqdm import tqdm

    from mi_shadowgs.io.interrupt import CheckpointClock, raise_pending

    clock = CheckpointClock(config.checkpoint_every, config.checkpoint_seconds)
    fit, state = setup_fit(surfels, cameras, images, masks, config, bounds, vis_config,
                           raster, progress, state, gains, past)
    total_steps = config.iterations + config.normal_steps
    bar = tqdm(total=total_steps, initial=state.step, desc="stage 4: fit",
               disable=not progress)
    t_phase = time.perf_counter() - state.timings.pop("phase_s", 0.0)
    refine_again = refine_step(config)
    main_phase = "main_s" if config.iterations > config.warmup else "warmup_total_s"

    def save() -> None:
        state.timings["phase_s"] = time.perf_counter() - t_phase
        on_checkpoint(state)
        del state.timings["phase_s"]
        clock.saved()

    def refined_one() -> None:
        """After each unit of a refinement: a refinement can take minutes."""
        if on_checkpoint and clock.due():
            save()
        raise_pending(f"stage 4 stopped in the light refinement of step {state.step + 1}"
                      + (", checkpoint written" if on_checkpoint else ""))

    with bar, clock.running():
        while state.step < total_steps:
            it = state.step
            if it >= config.iterations:  # the normal phase
                if shading.SHADING_NORMAL_CHANNEL not in state.opt.keys():
                    dr.sync_thread()
                    state.timings[main_phase] = time.perf_counter() - t_phase
                    start_normal_phase(fit, state)
                    t_phase = time.perf_counter()
                mean = normal_step(fit, state)
            elif it == config.warmup:
                if state.refine is None:  # else this step resumes inside its refinement
                    dr.sync_thread()
                    state.timings["warmup_total_s"] = time.perf_counter() - t_phase
                end_warmup(fit, state, refined_one)
                t_phase = time.perf_counter()
            else:
                if state.refine is None and prune_due(config, it):
                    # A host read every prune_every steps (not per step): drop dark lights.
                    n_before = len(state.directions)
                    _prune_state(fit, state)
                    if len(state.directions) != n_before:
                        state.log_lights("prune", solid_angle(config.n_directions))
                if it == refine_again:
                    refine_lights(fit, state, refined_one)
            if it == detail_step(config) and DETAIL_CHANNEL not in state.channels:
                start_detail(fit, state)
            if it < config.iterations:
                mean = fit_step(fit, state)
            if mean is not None:
                bar.set_postfix(loss=f"{mean:.4f}", dirs=len(state.directions),
                                spec=int(state.specular))
            bar.update(1)
            if on_checkpoint and (clock.due(state.step) or state.step in
                                  (config.iterations, total_steps)):
                save()
            raise_pending(f"stage 4 stopped at step {state.step} of {total_steps}"
                          + (", checkpoint written" if on_checkpoint else ""))
    dr.sync_thread()
    phase = "normals_s" if config.normal_steps else main_phase
    state.timings[phase] = time.perf_counter() - t_phase
    return fit_result(fit, state)


def _initial_state(surfels: Surfels, images: list[np.ndarray], views: list[TrainView], seg,
                   n_seg: int, config: MaterialConfig) -> MaterialState:
    """Step 0: initial channels, the light on every grid direction, Adam over them."""
    ch = init_channels(surfels, config)
    with_specular = config.specular != "off"
    if not with_specular:
        ch["metallic"] = mi.TensorXf(dr.zeros(mi.Float, surfels.count), (surfels.count, 1))
    _clamp_channels(ch, seg, n_seg, config, with_specular)
    opt = mi.ad.Adam(lr=config.lr_albedo)
    opt["albedo"] = ch["albedo"]
    opt.set_learning_rate({"albedo": config.lr_albedo})
    # The indirect light (per-surfel RGB) joins after the warm-up: fitted from the start it
    # explains colour and shadows per surfel before the segment-constant albedo and the
    # light map can (measured on the tiny test scene: albedo ratio stuck at 1).
    if with_specular:
        for k in ("roughness", "metallic"):
            opt[k] = ch[k]
            opt.set_learning_rate({k: config.lr_material})
    light0 = config.light_init
    if light0 <= 0:
        sup = [np.asarray(im, np.float64).reshape(-1, np.shape(im)[-1])[:, :3]
               [np.asarray(v.weight.numpy(), bool)] for im, v in zip(images, views, strict=True)]
        light0 = max(float(np.mean(np.concatenate(sup))), 1e-3) / config.albedo_init
    grid = light_grid(config.n_directions)
    opt["log_light"] = jit.host(np.full(len(grid), math.log(light0), np.float32))
    opt.set_learning_rate({"log_light": config.lr_light})
    return MaterialState(0, opt, ch, grid, with_specular, np.random.default_rng(config.seed),
                         mi.Float(0.0), [], {})


def _end_warmup(state: MaterialState, config: MaterialConfig) -> None:
    """After the warm-up's pruning and refinement: add the indirect light and decide on the
    specular lobe (one host read)."""
    opt, ch = state.opt, state.channels
    opt[shading.INDIRECT_CHANNEL] = ch[shading.INDIRECT_CHANNEL]
    opt.set_learning_rate({shading.INDIRECT_CHANNEL: config.lr_indirect})
    if state.specular and config.specular == "auto":
        m = opt["metallic"].numpy().reshape(-1)
        r = opt["roughness"].numpy().reshape(-1)
        if m.max() < config.auto_metallic_max and r.min() > config.auto_roughness_min:
            state.specular = False
            for k in ("roughness", "metallic"):
                del opt[k]
            n = len(m)
            ch["metallic"] = mi.TensorXf(dr.zeros(mi.Float, n), (n, 1))
