"""Decisions on the lights: merge the grid directions that share a light and prune the
dark ones, search each light's direction on candidate grids (``Refinement``), and settle
the refined lights (merge those that met, drop those that explain little)."""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit, shading
from mi_shadowgs.core.directions import light_grid
from mi_shadowgs.stages.material.config import MaterialConfig
from mi_shadowgs.stages.material.scoring import (
    _candidate_scores,
    drop_unexplained,
    light_normal_equations,
)
from mi_shadowgs.stages.material.views import TrainView


def subset_maps(maps, keep: np.ndarray):
    """The shadow maps of the kept directions (no re-rendering: a gather of the texels)."""
    return maps.subset(keep)


def prune_lights(dirs: np.ndarray, radiance: np.ndarray, config: MaterialConfig,
                 merge: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Group the directions into lights (``merge_directions``), then drop the lights that
    carry less than ``prune_threshold`` times the strongest light's irradiance.

    Lights are judged after grouping, by what they carry: a light the warm-up localizes
    poorly is spread over many grid cells, each dim (bunny under the low pair: the true
    60 degree light, a third of the irradiance, was 13 cells within 25 degrees of it, the
    brightest at 0.07 of the strong light's single bright cell, so a per-direction
    threshold of 0.1 dropped all of it; merged first, those cells are one light at 1.8
    degrees from the truth with 0.16 of the strongest light's irradiance).

    ``dirs`` [K, 3], ``radiance`` [K] (L_dir); ``merge`` False: no grouping, whatever
    ``merge_angle_deg`` says. Returns (directions [K'], radiance [K'], index [K'] of the
    kept input lights, or None when some merged: new directions).
    """
    dirs = np.asarray(dirs, np.float64)
    light = np.asarray(radiance, np.float64)
    idx = np.arange(len(dirs))
    if merge and config.merge_angle_deg > 0 and len(dirs) > 1:
        merged, light_m = merge_directions(dirs, light, config.merge_angle_deg)
        if len(merged) < len(dirs):
            dirs, light, idx = merged, light_m, None
    keep = light >= config.prune_threshold * light.max()
    if not keep.all():
        dirs, light = dirs[keep], light[keep]
        idx = None if idx is None else idx[keep]
    return dirs, light, idx


def _prune(opt, dirs: np.ndarray, maps, config: MaterialConfig, render_maps,
           positions: np.ndarray | None = None):
    """``prune_lights`` on the optimiser's L_dir: the kept lights' maps are a subset of
    ``maps``, or rendered anew where lights merged. With lamps (``positions`` rows finite)
    nothing merges: a lamp and a light near its direction are different lights. Returns
    (dirs, maps, positions)."""
    if len(dirs) <= 1:
        return dirs, maps, positions
    light = np.exp(opt["log_light"].numpy().astype(np.float64))
    new_dirs, light, idx = prune_lights(dirs, light, config, merge=positions is None)
    if idx is None:
        maps = render_maps(new_dirs)
    elif len(idx) < len(dirs):
        keep = np.zeros(len(dirs), bool)
        keep[idx] = True
        if maps is not None:
            maps = subset_maps(maps, keep)
        if positions is not None:
            positions = positions[keep]
    if len(light) != dr.width(opt["log_light"]):
        opt["log_light"] = jit.host(np.log(light).astype(np.float32))
        opt.set_learning_rate({"log_light": config.lr_light})
    return new_dirs, maps, positions


def merge_directions(dirs: np.ndarray, energy: np.ndarray, max_angle_deg: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Merge lights closer than ``max_angle_deg`` into one at their energy-weighted mean.

    A directional light between grid directions is fitted as a few neighbouring grid lights
    whose shadows are copies offset by the grid spacing (~13 degrees at 128 directions);
    one light at their weighted mean direction casts the single, sharp shadow the data
    shows. Greedy from the strongest light. Returns (directions [K', 3], energy [K']).
    """
    dirs = np.asarray(dirs, np.float64)
    energy = np.asarray(energy, np.float64)
    cos_max = math.cos(math.radians(max_angle_deg))
    order = np.argsort(-energy)
    centres: list[np.ndarray] = []
    members: list[list[int]] = []
    for i in order:
        best = -1
        for c, centre in enumerate(centres):
            if dirs[i] @ centre >= cos_max and (best < 0 or dirs[i] @ centre >
                                                 dirs[i] @ centres[best]):
                best = c
        if best < 0:
            centres.append(dirs[i])
            members.append([i])
        else:
            members[best].append(i)
    out_d, out_e = [], []
    for idx in members:
        e = energy[idx]
        d = (dirs[idx] * e[:, None]).sum(0)
        out_d.append(d / np.linalg.norm(d))
        out_e.append(e.sum())
    return np.array(out_d), np.array(out_e)


def candidate_directions(direction: np.ndarray, radius_deg: float, step_deg: float
                         ) -> np.ndarray:
    """Unit directions [C, 3] on a square grid of ``step_deg`` in the tangent plane of
    ``direction`` [3] (gnomonic), within ``radius_deg`` of it and above the horizon (y > 0);
    the first is ``direction`` itself."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    t1 = np.cross(d, [0.0, 1.0, 0.0] if abs(d[1]) < 0.99 else [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(d, t1)
    k = int(math.floor(radius_deg / step_deg + 1e-9))
    out = [d]
    for i in range(-k, k + 1):
        for j in range(-k, k + 1):
            if (i or j) and math.hypot(i, j) * step_deg <= radius_deg + 1e-9:
                c = (d + math.tan(math.radians(i * step_deg)) * t1
                     + math.tan(math.radians(j * step_deg)) * t2)
                out.append(c / np.linalg.norm(c))
    out = np.array(out)
    keep = out[:, 1] > 0.0
    keep[0] = True  # the current direction stays a candidate even at the horizon
    return out[keep]


def settle_lights(views: list[TrainView], channels: dict, dirs: np.ndarray,
                  irradiance: np.ndarray, maps, render_maps, config: MaterialConfig,
                  with_specular: bool, positions: np.ndarray | None = None, center=None
                  ) -> tuple[np.ndarray, np.ndarray, object, np.ndarray | None]:
    """After a refinement: lights that moved within ``merge_angle_deg`` of each other merge
    (a light split over two grid cells is refined onto one spot twice; not with lamps,
    ``positions`` rows finite), then ``drop_unexplained``. Returns (dirs [K'],
    irradiance [K'], their maps, positions [K'] or None)."""
    dirs, irr = np.asarray(dirs, np.float64), np.asarray(irradiance, np.float64)
    if config.merge_angle_deg > 0 and len(dirs) > 1 and positions is None:
        merged, irr_m = merge_directions(dirs, irr, config.merge_angle_deg)
        if len(merged) < len(dirs):
            dirs, irr = merged, irr_m
            maps = render_maps(dirs)
    if config.drop_share > 0 and len(dirs) > 1:
        gram, h, rr = light_normal_equations(views, channels, dirs, maps, config,
                                             with_specular, config.settle_score == "segment",
                                             positions, center)
        keep, e = drop_unexplained(gram, h, rr, config)
        dirs, irr = dirs[keep], e[keep]  # the joint re-fit: better than one at a time
        if not keep.all() and maps is not None:
            maps = subset_maps(maps, keep)
        if positions is not None:
            positions = positions[keep]
    return dirs, irr, maps, positions


@dataclasses.dataclass
class Refinement:
    """A light-direction refinement (``refine_directions``) in progress: it continues after
    each finished (light, pass) unit, so that a checkpoint can be written between units
    (cpu-small, 25k surfels, 2 cores: 40 s per refinement on quiet cores, 80 s on loaded
    ones; a unit ~10 s)."""

    dirs: np.ndarray  # [K, 3] the lights' directions so far
    irradiance: np.ndarray  # [K]
    lights: np.ndarray  # [R] the lights refined, strongest first
    done: int = 0  # finished (light, pass) units
    global_pass: bool = False  # each light starts with the global pass (refine_global)
    again: bool = False  # the main phase's second refinement (refine_again_passes)

    @staticmethod
    def start(dirs: np.ndarray, irradiance: np.ndarray, config: MaterialConfig,
              global_pass: bool = False, again: bool = False) -> Refinement:
        irr = np.array(irradiance, np.float64)
        # The strongest first: it shapes the residual most.
        return Refinement(np.array(dirs, np.float64), irr,
                          np.argsort(-irr)[:config.refine_max_lights],
                          global_pass=global_pass and config.refine_global > 0, again=again)

    def units(self, config: MaterialConfig) -> list[tuple[int, float, float, int | None]]:
        """(light, radius, step, candidates' map resolution or None: the visibility's) in
        order; radius inf: the global pass."""
        # after a global pass the local passes start a grid cell away: the first
        # refinement's, whichever refinement this is
        passes = (([(math.inf, 0.0, config.refine_global_map_resolution)]
                   if self.global_pass else [])
                  + list(config.local_passes(self.again and not self.global_pass)))
        return [(int(k), p[0], p[1], int(p[2]) if len(p) > 2 else None)
                for k in self.lights for p in passes]

    def run(self, views: list[TrainView], channels: dict, maps, render_maps,
            config: MaterialConfig, with_specular: bool, on_unit=None, positions=None,
            center=None) -> None:
        """The units left; ``maps``: the shadow maps of ``dirs``; ``on_unit()`` after each.
        Lamps (``positions`` rows finite, the lamp search's) keep their place."""
        pick = np.unique(np.linspace(0, len(views) - 1, min(config.refine_views, len(views)))
                         .round().astype(int))
        sub = [views[i] for i in pick]
        sub_global = sub[::max(1, -(-len(sub) // config.refine_global_views))]
        for k, radius, step, resolution in self.units(config)[self.done:]:
            if positions is not None and np.all(np.isfinite(positions[k])):
                self.done += 1
                if on_unit:
                    on_unit()
                continue
            scored = sub
            if math.isinf(radius):
                cand = np.concatenate([self.dirs[k][None], light_grid(config.refine_global)])
                scored = sub_global
            else:
                cand = candidate_directions(self.dirs[k], radius, step)
            cand_maps = render_maps(cand, resolution)
            irr = jit.array(self.irradiance.astype(np.float32))
            lights = shading.LightSet(self.dirs, mi.Color3f(irr, irr, irr), positions, None,
                                      center)
            err, fit = _candidate_scores(scored, channels, lights, maps, k, cand_maps,
                                         config, with_specular)
            best = int(np.argmin(err))
            if best != 0 and fit[best] > 0:
                self.dirs[k], self.irradiance[k] = cand[best], fit[best]
                maps = (render_maps(self.dirs) if positions is None
                        else render_maps(self.dirs, None, positions))
            self.done += 1
            if on_unit:
                on_unit()


def refine_directions(views: list[TrainView], channels: dict, dirs: np.ndarray,
                      irradiance: np.ndarray, maps, render_maps, config: MaterialConfig,
                      with_specular: bool, global_pass: bool = False
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Grid search of each light's direction: the global pass (``global_pass`` and
    ``MaterialConfig.refine_global``), then the local ``refine_passes``.

    ``dirs`` [K, 3] and ``irradiance`` [K] are the current lights; ``maps`` their shadow
    maps; ``render_maps(directions, resolution=None)`` renders maps. Returns the refined
    (dirs, irradiance).
    """
    refinement = Refinement.start(dirs, irradiance, config, global_pass)
    refinement.run(views, channels, maps, render_maps, config, with_specular)
    return refinement.dirs, refinement.irradiance
