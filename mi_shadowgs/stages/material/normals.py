"""The normal phase (not in the paper): with the lights, materials and indirect light held,
each surfel's shading normal is fitted to the views, pulled toward stage 2's normal."""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi

from mi_shadowgs.core import shading
from mi_shadowgs.core.directions import solid_angle
from mi_shadowgs.stages.material.state import _LIGHT_KEYS, MaterialFit, MaterialState, _count_step
from mi_shadowgs.stages.material.views import TrainView, view_loss, view_maps


def start_normal_phase(fit: MaterialFit, state: MaterialState) -> None:
    """At step ``iterations`` (``normal_steps`` > 0): the materials and the indirect light
    are final and leave Adam (their values stay in ``state.channels``), the light stays in it
    at learning rate 0 (as fitted), and the shading normals join it, started from the
    surfels' own (stage 2's)."""
    opt, n = state.opt, fit.surfels.count
    fit.held_maps.clear()  # made again from the materials held from here on
    for k in list(opt.keys()):
        if k not in _LIGHT_KEYS:
            state.channels[k] = opt[k]
            del opt[k]
    opt.set_learning_rate({k: 0.0 for k in _LIGHT_KEYS})
    start, _ = _start_normals(fit)
    opt[shading.SHADING_NORMAL_CHANNEL] = mi.TensorXf(dr.ravel(start), (n, 3))
    opt.set_learning_rate({shading.SHADING_NORMAL_CHANNEL: fit.config.lr_normal})
    state.channels[shading.SHADING_NORMAL_CHANNEL] = opt[shading.SHADING_NORMAL_CHANNEL]


# A shading normal this far (degrees) from its surfel's rotation normal was set by stage 2's
# planes (every other surfel's is a float32 copy of its rotation normal).
FLATTENED_MIN_DEG = 0.1


def _start_normals(fit: MaterialFit) -> tuple[mi.Vector3f, mi.Bool]:
    """The surfels' unit shading normals [N] as stage 2 left them (the prior's n0) and
    which of them the phase holds (``normal_hold_planar``: those stage 2 flattened)."""
    if fit.start_normals is None:
        with dr.suspend_grad():
            n0 = shading.shading_normals(fit.surfels)  # unit
            held = dr.zeros(mi.Bool, fit.surfels.count)
            if (fit.config.normal_hold_planar
                    and shading.SHADING_NORMAL_CHANNEL in fit.surfels.channels):
                own = fit.surfels.tangent_frame()[2]
                held = dr.abs(dr.dot(n0, own)) < math.cos(math.radians(FLATTENED_MIN_DEG))
            dr.eval(n0, held)
        fit.start_normals, fit.held_normals = n0, held
    return fit.start_normals, fit.held_normals


def with_surfel_normals(view: TrainView, normals: mi.Vector3f, position: mi.Point3f
                        ) -> TrainView:
    """``view`` with its pixel normals blended from per-surfel ``normals`` [N] (facing its
    camera, as the rasterizer flips them) over the pairs its receivers blend (the median
    surface's, with ``receiver_band``): differentiable in ``normals``; points, depth and
    the shadow-map lookups stay the view's."""
    from mi_shadowgs.core.raster import face_camera

    n = dr.width(normals)
    facing = face_camera(normals, position, view.camera)
    pairs = view.geom.surface_pairs or view.pairs
    flat = shading.splat(pairs, mi.TensorXf(dr.ravel(facing), (n, 3)))  # [H * W * 3]
    pn = shading.unit_or_zero(mi.Vector3f(*(shading.channel(flat, 3, k) for k in range(3))))
    return dataclasses.replace(view, geom=dataclasses.replace(view.geom, normal=pn))


# Memory for the normal phase's held per-view maps (8 floats a pixel: 33 MB for cpu-small's 64
# views at 128^2); views beyond it make theirs at each step.
HELD_MAPS_BYTES = 256 << 20


def _held_view_maps(fit: MaterialFit, state: MaterialState, k: int) -> tuple:
    """View ``k``'s ``view_maps`` of the held materials, made once while they fit."""
    if k in fit.held_maps:
        return fit.held_maps[k]
    v = fit.views[k]
    with dr.suspend_grad():
        maps = view_maps(v.pairs, state.channels, v.surfel_normal, state.specular)
        dr.eval(*(m for m in maps if m is not None))
    if (len(fit.held_maps) + 1) * 32 * v.pairs.height * v.pairs.width <= HELD_MAPS_BYTES:
        fit.held_maps[k] = maps
    return maps


def normal_step(fit: MaterialFit, state: MaterialState) -> float | None:
    """One step of the normal phase: Eq. 18's loss over ``views_per_step`` random views with
    the pixel normals blended from the shading-normal channel, plus the prior toward stage
    2's normals; everything else held. Returns as ``fit_step``."""
    config, opt = fit.config, state.opt
    w_light = dr.detach(dr.exp(opt["log_light"])) * solid_angle(config.n_directions)
    lights = state.light_set(w_light, fit.bounds.center)
    start, held = _start_normals(fit)
    free = shading.unit_rows(opt[shading.SHADING_NORMAL_CHANNEL])  # [N]
    normals = dr.select(held, start, free)
    position = dr.detach(fit.surfels.position)
    total = mi.Float(0.0)
    for _ in range(config.views_per_step):
        k = int(state.rng.integers(len(fit.views)))
        v = fit.views[k]
        # The lookup keeps the view's own normals: its offset is part of the occluder test.
        vis = (None if fit.maps is None
               else fit.maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint))
        total += view_loss(with_surfel_normals(v, normals, position), state.channels, lights,
                           vis, config, state.specular, _held_view_maps(fit, state, k))
    total = total / config.views_per_step
    prior = config.lambda_normal_prior * dr.mean(1.0 - dr.dot(normals, start))
    dr.backward(total + prior)
    opt.step()
    state.channels[shading.SHADING_NORMAL_CHANNEL] = opt[shading.SHADING_NORMAL_CHANNEL]
    return _count_step(state, config, total)
