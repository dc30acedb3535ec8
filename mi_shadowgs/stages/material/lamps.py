"""Local lights: each refined light tested as a lamp against a directional light.

A lamp at a finite distance lights the scene from a direction that changes across it and
with an irradiance that falls off as 1/r^2; its shadows diverge. A directional fit of such
a capture explains the falloff with a second light and leaves the lamp's shadows where a
directional light would not cast them. ``localize_lights`` starts from the refined
directional lights: for each light (strongest first) it scores, with the closed-form
candidate scores of the direction search, the directional light against lamps along its
direction at ``MaterialConfig.lamp_distances`` (scene-bound radii), each with its own
shadow maps rendered from the lamp's position, by ``lamp_score`` (by default each segment's
albedo re-fitted: the albedo fitted under the light so far holds its falloff); a lamp is kept only
when it lowers the views' error by ``lamp_min_gain`` (a sun stays directional: far lamps
explain it no better). A kept lamp's position is then searched locally (``lamp_passes``): a
pattern search over its direction from the scene centre and its distance, scale by scale,
each candidate scored by its photometric error times its shadows' disagreement with the
photos (``lamp_position_score`` "shadows", ``shadow_mismatch``): with one albedo per
segment, a print's gradients pass for a lamp's falloff; its shadows' place does not.
A light newly kept as a lamp is also searched from the best of a global scan
(``lamp_scan_directions`` x ``lamp_scan_distances``), and the better of the two ends is
kept: the directional fit that it started from can put a near lamp far off, toward the
horizon, where grazing light explains its falloff over the support; from a good start, a
scan's coarse lamp can stop in another dip of the flat error.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit, shading
from mi_shadowgs.core.directions import light_grid
from mi_shadowgs.stages.material.config import MaterialConfig, lamp_scoring
from mi_shadowgs.stages.material.scoring import (
    _candidate_scores,
    _view_direct,
    others_shading,
)
from mi_shadowgs.stages.material.views import TrainView

# A pattern search's moves at one scale: enough to cross a pass's start error (the coarse
# pass starts from the candidate distances' spacing, ~30%, and a refined direction).
LAMP_MOVES = 8


def lamp_rows(count: int, positions: np.ndarray | None) -> np.ndarray:
    """[count, 3] positions with NaN rows for directional lights."""
    if positions is None:
        return np.full((count, 3), np.nan)
    return np.array(positions, np.float64).reshape(count, 3)


def candidate_set(center: np.ndarray, directions: np.ndarray, distances: np.ndarray
                  ) -> shading.LightSet:
    """Candidates [C] along ``directions`` [C, 3] from ``center`` at ``distances`` [C]
    (world units; inf: a directional light), as lights of unit weight."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    dist = np.asarray(distances, np.float64).reshape(-1)
    pos = np.where(np.isfinite(dist)[:, None], center + d * np.where(
        np.isfinite(dist), dist, 0.0)[:, None], np.nan)
    return shading.LightSet(d, mi.Color3f(1.0), pos, np.zeros(len(d)), center)


def distance_of(center: np.ndarray, position: np.ndarray) -> float:
    """A light's distance from the centre (inf for a directional light's NaN row)."""
    if not np.all(np.isfinite(position)):
        return math.inf
    return float(np.linalg.norm(np.asarray(position) - center))


class LampSearch:
    """The candidates' scores for one light at a time, the other lights held."""

    def __init__(self, views: list[TrainView], channels: dict, render_maps,
                 config: MaterialConfig, with_specular: bool, center: np.ndarray,
                 radius: float):
        self.views, self.channels, self.render_maps = views, channels, render_maps
        self.config, self.with_specular = config, with_specular
        self.scoring = lamp_scoring(config)  # how the candidates are scored
        self.center = np.asarray(center, np.float64)
        self.radius = float(radius)  # the scene bound's
        # no lamp nearer than the nearest candidate distance
        self.min_distance = self.radius * min(config.lamp_distances)
        # the global scan's views: those of the refinements' global pass
        self.scan_views = views[::max(1, -(-len(views) // config.refine_global_views))]

    def lights(self, dirs: np.ndarray, positions: np.ndarray, irr: np.ndarray
               ) -> shading.LightSet:
        w = jit.array(np.asarray(irr, np.float32))
        return shading.LightSet(dirs, mi.Color3f(w, w, w), positions, None, self.center)

    def score(self, dirs, positions, irr, k: int, cand: shading.LightSet,
              scan: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(error [C], fitted irradiance at the centre [C]) of light ``k`` moved to each of
        ``cand``; ``scan``: on the global scan's views, with its maps' resolution."""
        return self._scores(dirs, positions, irr, k, cand, scan)[:2]

    def place(self, dirs, positions, irr, k: int, cand: shading.LightSet
              ) -> tuple[np.ndarray, np.ndarray]:
        """As ``score``, with the error that places a lamp (``lamp_position_score``; the
        photometric error where the fit has no shadow maps)."""
        err, fit, mismatch = self._scores(dirs, positions, irr, k, cand, False,
                                          self.config.lamp_position_score == "shadows")
        # the product: each cue weighs by its relative change (log err + log mismatch)
        return (err if mismatch is None else err * (mismatch + 1.0)), fit

    def _scores(self, dirs, positions, irr, k, cand, scan, shadows=False):
        views, res = ((self.scan_views, self.config.refine_global_map_resolution) if scan
                      else (self.views, None))
        maps = self.render_maps(dirs, None, positions)
        cand_maps = self.render_maps(cand.directions, res, cand.positions)
        lights = self.lights(dirs, positions, irr)
        err, fit = _candidate_scores(views, self.channels, lights, maps, k, cand_maps,
                                     self.config, self.with_specular, cand, self.scoring)
        mismatch = (shadow_mismatch(views, self.channels, self.config, self.with_specular,
                                    lights, maps, k, cand_maps)
                    if shadows and cand_maps is not None else None)  # no maps: no shadows
        return err, fit, mismatch


# Pixels that face light k at under this share of the view's 90th percentile of its
# unshadowed shading are left out of ``shadow_mismatch``: near grazing, the photo's ratio to
# the shading is noise.
FACING_SHARE = 0.2
# ... and pixels that the surfels cover less than this: a pixel on the support's outline
# is dark in the photo where the backdrop fills its rest.
WHOLE_PIXEL = 0.99


def _grey(c) -> np.ndarray:
    """A colour [P] (``mi.Color3f``) as its channels' mean, float64 NumPy [P]."""
    return np.mean([np.asarray(c[i], np.float64) for i in range(3)], 0)


def _ambient(v: TrainView, albedo, metal, ind, sup: np.ndarray) -> np.ndarray:
    """The indirect light's part of each pixel [P] (grey) with each segment's median
    indirect irradiance over the view's pixels ``sup``: the room's light and the bounce
    reach the shadows too. Not each surfel's own: where the lamp's shadow is off, the
    indirect light fitted with it has filled the difference."""
    e = _grey(ind)
    a = _grey((1.0 - metal) * albedo)
    seg = np.asarray(v.segment.numpy())
    level = np.zeros_like(e)
    for s in np.unique(seg[sup]):
        level[seg == s] = np.median(e[sup & (seg == s)])
    return a * level


def shadow_mismatch(views: list[TrainView], channels: dict, config: MaterialConfig,
                    with_specular: bool, lights: shading.LightSet, maps, k: int,
                    cand_maps) -> np.ndarray:
    """The shadows' disagreement [C] when light ``k`` moves to each candidate of
    ``cand_maps``: the sum of (V_c - lit)^2 over the views' supervised pixels that face
    light ``k`` and that the surfels cover whole, where lit says whether the photo, less
    the other lights' shading and the indirect light (``_ambient``), is over
    ``lamp_lit_ratio`` of light ``k``'s unshadowed shading (materials fitted, grey): the
    visibility of light ``k`` that the photo shows, cut at the penumbra's middle.

    The photometric scores weigh a lamp's position by its falloff over the support, which a
    support's print and its room light explain as well; where its shadows fall is geometry.
    """
    n_cand = cand_maps.count
    total = np.zeros(n_cand)
    with dr.suspend_grad():
        for v in views:
            albedo, rough, metal, ind, per, _ = _view_direct(
                v, channels, config, maps, lights.directions, with_specular, lights.positions,
                lights.center)
            npix = dr.width(v.geom.alpha)
            rest = others_shading(lights, per, k, npix)
            pos_k = None if lights.positions is None else lights.positions[k:k + 1]
            own = shading.direct_per_light(v.geom, albedo, rough, metal,
                                           lights.directions[k:k + 1], None, with_specular,
                                           pos_k, lights.center)
            own = own * dr.gather(mi.Color3f, lights.weights, mi.UInt32(k))
            vis = cand_maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint)
            dr.eval(rest, own, vis)
            u, t = _grey(own), _grey(v.target - rest)  # [P]
            # supervised pixels whole on the surface: an outline pixel's photo is part
            # backdrop, dark though lit
            sup = (np.asarray(v.weight.numpy()) > 0) & (np.asarray(v.geom.alpha.numpy())
                                                        > WHOLE_PIXEL)
            if not sup.any() or not (u[sup] > 0).any():
                continue
            ok = sup & (u > FACING_SHARE * np.percentile(u[sup], 90))
            if ind is not None:
                t = t - _ambient(v, albedo, metal, ind, sup)
            lit = (t > config.lamp_lit_ratio * u).astype(np.float64)
            vc = np.asarray(vis.numpy(), np.float64).reshape(npix, n_cand)[ok]
            total += ((vc - lit[ok, None]) ** 2).sum(0)
    return total


def _best(err: np.ndarray, fit: np.ndarray) -> int:
    ok = fit > 0
    if not ok.any():
        return 0
    return int(np.flatnonzero(ok)[np.argmin(err[ok])])


def localize_lights(search: LampSearch, dirs: np.ndarray, positions: np.ndarray | None,
                    irradiance: np.ndarray, order: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
    """Each light of ``order`` as a lamp or directional, and a kept lamp's position searched.

    ``dirs`` [K, 3], ``positions`` [K, 3] (NaN rows directional; None: all), ``irradiance``
    [K] at the centre. Returns (dirs, positions, irradiance,
    decisions: per light its errors as directional and as the best lamp, and the choice).
    """
    config, center = search.config, search.center
    dirs = np.array(dirs, np.float64)
    pos = lamp_rows(len(dirs), positions)
    irr = np.array(irradiance, np.float64)
    log = []
    for k in (int(i) for i in order):
        dist = distance_of(center, pos[k])
        scan = np.array([math.inf, *(search.radius * np.asarray(config.lamp_distances))])
        if math.isfinite(dist):
            scan = np.append(scan, dist)
        cand = candidate_set(center, np.repeat(dirs[k][None], len(scan), 0), scan)
        err, fit = search.score(dirs, pos, irr, k, cand)
        lamp = 1 + _best(err[1:], fit[1:])
        gain = (err[0] - err[lamp]) / max(err[0], 1e-30)
        entry = {"light": k, "error_directional": float(err[0]),
                 "error_lamp": float(err[lamp]), "distance": float(scan[lamp])}
        if gain < config.lamp_min_gain or fit[lamp] <= 0:
            if math.isfinite(dist):  # a lamp no better than a directional light
                pos[k] = np.nan
                if fit[0] > 0:
                    irr[k] = fit[0]
            log.append({**entry, "kept": "directional"})
            continue
        pos[k], irr[k] = cand.positions[lamp], fit[lamp]
        starts = [(dirs, pos, irr)]
        if config.lamp_scan_directions and not math.isfinite(dist):  # newly a lamp
            *scanned, entry["scan"] = _lamp_scan(search, dirs, pos, irr, k)
            if entry["scan"]["moved"]:
                starts.append(tuple(scanned))
        ends = [_lamp_passes(search, *start, k) for start in starts]
        if len(ends) > 1:  # the better end; a scan's lamp can stop in another dip
            ends_at = candidate_set(center, np.array([e[0][k] for e in ends]),
                                    np.array([distance_of(center, e[1][k]) for e in ends]))
            err, _ = search.place(dirs, pos, irr, k, ends_at)
            entry["scan"]["kept"] = "scan" if err[1] < err[0] else "start"
            ends = [ends[int(np.argmin(err))]]
        dirs, pos, irr = ends[0]
        log.append({**entry, "kept": "lamp", "position": pos[k].tolist(),
                    "distance": distance_of(center, pos[k])})
    return dirs, pos, irr, log


def _lamp_passes(search: LampSearch, dirs, pos, irr, k: int):
    """Lamp ``k``'s position searched by ``lamp_passes``, coarse to fine."""
    for step_deg, share in search.config.lamp_passes:
        dirs, pos, irr = _lamp_pass(search, dirs, pos, irr, k, step_deg, share)
    return dirs, pos, irr


def _lamp_scan(search: LampSearch, dirs, pos, irr, k: int):
    """Lamp ``k`` moved to the best of its place and the scan's lamps (the other lights
    held), scored on the global pass's views and map resolution. Returns (dirs, pos, irr,
    the scan's record)."""
    config, center = search.config, search.center
    grid = light_grid(config.lamp_scan_directions)
    dist = search.radius * np.asarray(config.lamp_scan_distances, np.float64)
    dist = dist[dist >= search.min_distance]
    scan_dirs = np.concatenate([dirs[k][None], np.tile(grid, (len(dist), 1))])
    lengths = np.concatenate([[distance_of(center, pos[k])], np.repeat(dist, len(grid))])
    cand = candidate_set(center, scan_dirs, lengths)
    err, fit = search.score(dirs, pos, irr, k, cand, scan=True)
    best = _best(err, fit)
    record = {"candidates": int(cand.count), "error_before": float(err[0]),
              "error_after": float(err[best]), "moved": best != 0}
    dirs, pos, irr = _moved(dirs, pos, irr, k, cand, best, fit)
    return dirs, pos, irr, record


def _lamp_pass(search: LampSearch, dirs, pos, irr, k: int, step_deg: float, share: float):
    """A pattern search of lamp ``k``'s position at one scale: the 3 x 3 x 3 stencil of its
    direction from the centre (two tangent steps of ``step_deg``) and its distance (steps of
    ``share``), moved to the best until the middle wins (at most ``LAMP_MOVES`` times).
    Joint steps, because a lamp moved sideways and one moved nearer cast alike."""
    center = search.center
    for _ in range(LAMP_MOVES):
        dist = distance_of(center, pos[k])
        d = dirs[k]
        t1 = np.cross(d, [0.0, 1.0, 0.0] if abs(d[1]) < 0.99 else [1.0, 0.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(d, t1)
        tan = math.tan(math.radians(step_deg))
        steps = [(0, 0, 0)] + [(i, j, m) for i in (-1, 0, 1) for j in (-1, 0, 1)
                               for m in (-1, 0, 1) if i or j or m]
        cand_dirs = np.array([d + tan * (i * t1 + j * t2) for i, j, _ in steps])
        lengths = np.array([dist * (1.0 + share) ** m for _, _, m in steps])
        ok = (lengths >= search.min_distance) & (cand_dirs[:, 1] > 0)
        ok[0] = True
        cand = candidate_set(center, cand_dirs[ok], lengths[ok])
        err, fit = search.place(dirs, pos, irr, k, cand)
        best = _best(err, fit)
        dirs, pos, irr = _moved(dirs, pos, irr, k, cand, best, fit)
        if best == 0:
            break
    return dirs, pos, irr


def _moved(dirs, pos, irr, k, cand: shading.LightSet, best: int, fit: np.ndarray):
    dirs, pos, irr = dirs.copy(), pos.copy(), irr.copy()
    dirs[k], pos[k] = cand.directions[best], cand.positions[best]
    if fit[best] > 0:
        irr[k] = fit[best]
    return dirs, pos, irr


def lamp_share(irradiance: np.ndarray, positions: np.ndarray | None) -> float:
    """The share of the lights' irradiance at the centre that lamps carry."""
    irr = np.asarray(irradiance, np.float64)
    if positions is None or irr.sum() <= 0:
        return 0.0
    local = np.all(np.isfinite(np.asarray(positions)), axis=1)
    return float(irr[local].sum() / irr.sum())
