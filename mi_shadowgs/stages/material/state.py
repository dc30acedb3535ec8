"""What a stage-4 fit holds: the fitted light (``LightModel``), the result, the resumable
state that a checkpoint saves (``MaterialState``) and the fixed set-up (``MaterialFit``)."""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit, shading
from mi_shadowgs.core.directions import light_grid, solid_angle
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.stages.material.config import MaterialConfig
from mi_shadowgs.stages.material.lights import Refinement
from mi_shadowgs.stages.material.views import TrainView
from mi_shadowgs.stages.visibility.shadow_maps import (
    MapCache,
    SceneBounds,
    VisibilityConfig,
)


@dataclasses.dataclass
class LightModel:
    """The fitted white light.

    ``radiance`` is L_dir over the grid (0 for pruned directions), the paper's light map; the
    K lights that carry it sit at ``directions`` (grid directions, or merged neighbours at
    their energy-weighted mean direction; see ``merge_directions``) with ``weights``
    (irradiance L dw). ``active`` are the grid cells the lights fall in.
    """

    radiance: np.ndarray  # [n_directions] white radiance per grid direction
    active: np.ndarray  # [K] grid index of each light
    directions: np.ndarray | None = None  # [K, 3] unit; None: the grid directions
    weights: np.ndarray | None = None  # [K] irradiance; None: radiance[active] * dw
    # Local lights (lamps): [K, 3] positions with NaN rows for directional lights, their
    # radii [K] and the point where a lamp's weight is its irradiance; None: all directional.
    positions: np.ndarray | None = None
    radii: np.ndarray | None = None
    center: np.ndarray | None = None

    def light_set(self, n_directions: int | None = None) -> shading.LightSet:
        n = len(self.radiance) if n_directions is None else n_directions
        dirs = light_grid(n)[self.active] if self.directions is None else self.directions
        w = (self.radiance[self.active] * solid_angle(n) if self.weights is None
             else self.weights)
        w = np.asarray(w, np.float32)
        return shading.LightSet(np.asarray(dirs, np.float64), mi.Color3f(w, w, w),
                                self.positions, self.radii, self.center)


@dataclasses.dataclass
class MaterialResult:
    surfels: Surfels  # input geometry plus albedo/roughness/metallic/indirect_sh channels
    light: LightModel
    specular: bool  # whether the GGX lobe is modelled
    use_visibility: bool
    history: list  # (step, loss) read every log_every steps
    timings: dict  # seconds: prepare, warmup, main, per-step medians
    # What the light decisions did (``MaterialState.light_log``): where a light was dropped.
    light_log: list = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class MaterialState:
    """Everything a checkpoint of ``fit_material`` needs to continue it exactly.

    The shadow maps are not saved: they follow from ``directions`` (each map is rendered on
    its own, so re-rendering the survivors equals the maps the fit gathered them from), at
    the warm-up resolution up to the end of the warm-up and at the full one after it.
    """

    step: int  # finished iterations
    opt: mi.ad.Adam  # the fitted channels and log L_dir, with their Adam state
    # name -> mi.TensorXf [N, C]: all four (those not in opt keep their value), and the
    # shading normals [N, 3] from the normal phase on
    channels: dict
    directions: np.ndarray  # [K, 3] the lights: the grid, then pruned, merged, refined
    specular: bool  # whether the GGX lobe is still modelled
    rng: np.random.Generator  # the training views' order
    loss_sum: mi.Float  # [1] loss summed since the last history entry
    history: list
    timings: dict  # seconds: "prepare_s", finished phases, "phase_s" into the current one
    # A refinement of step ``step`` (not finished) that a checkpoint interrupted.
    refine: Refinement | None = None
    # The lights after each decision on them, in order: dicts of "step", "event" ("prune",
    # "refine", "settle"), "directions" [K][3] and "irradiance" [K] (JSON; ``log_lights``).
    # A light lost on the way shows at which decision it went.
    light_log: list = dataclasses.field(default_factory=list)
    # The lights' directions [K, 3] when the albedo detail joined, whose shadows' edges its
    # gates follow (``detail_gates``); None before.
    detail_directions: np.ndarray | None = None
    # [K, 3] the lamps' positions (NaN rows: directional lights; ``lamps``); None: every
    # light directional. A lamp's ``directions`` row points from the scene centre to it.
    positions: np.ndarray | None = None
    detail_positions: np.ndarray | None = None  # ``positions`` when the detail joined

    def light_set(self, weights: mi.Float, center) -> shading.LightSet:
        """The current lights with white ``weights`` [K] (irradiance; a lamp's at
        ``center``)."""
        return shading.LightSet(self.directions, mi.Color3f(weights, weights, weights),
                                self.positions, None, None if self.positions is None
                                else np.asarray(center, np.float64))

    def log_lights(self, event: str, dw: float, details: list | None = None) -> None:
        """Record the current lights (directions, irradiance L_dir dw, lamps' positions)
        after ``event``, with its ``details``."""
        irr = np.exp(self.opt["log_light"].numpy().astype(np.float64)) * dw
        entry = {"step": self.step, "event": event,
                 "directions": np.round(self.directions, 6).tolist(),
                 "irradiance": np.round(irr, 6).tolist()}
        if self.positions is not None:
            entry["positions"] = [np.round(p, 6).tolist() if np.all(np.isfinite(p)) else None
                                  for p in self.positions]
        if details is not None:
            entry["details"] = details
        self.light_log.append(entry)

    def to_checkpoint(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, JSON meta) for ``mi_shadowgs.io.checkpoint.save_checkpoint``."""
        from mi_shadowgs.core.optim import adam_to_numpy

        arrays = adam_to_numpy(self.opt, "adam/")
        arrays.update({f"channel/{k}": np.asarray(v.numpy(), np.float32)
                       for k, v in self.channels.items()})
        arrays["directions"] = np.asarray(self.directions, np.float64)
        arrays["loss_sum"] = np.asarray(self.loss_sum.numpy(), np.float32)
        if self.detail_directions is not None:
            arrays["detail/directions"] = self.detail_directions
        if self.positions is not None:
            arrays["positions"] = np.asarray(self.positions, np.float64)
        if self.detail_positions is not None:
            arrays["detail/positions"] = self.detail_positions
        if self.refine is not None:
            arrays.update({"refine/dirs": self.refine.dirs,
                           "refine/irradiance": self.refine.irradiance,
                           "refine/lights": self.refine.lights,
                           "refine/done": np.array([self.refine.done]),
                           "refine/global": np.array([int(self.refine.global_pass)]),
                           "refine/again": np.array([int(self.refine.again)])})
        return arrays, {"step": self.step, "specular": self.specular,
                        "rng": self.rng.bit_generator.state, "history": self.history,
                        "timings": self.timings, "light_log": self.light_log}

    @staticmethod
    def from_checkpoint(arrays: dict[str, np.ndarray], meta: dict) -> MaterialState:
        from mi_shadowgs.core.optim import adam_from_numpy

        opt = mi.ad.Adam(lr=0.0)
        adam_from_numpy(opt, arrays, "adam/")
        rng = np.random.default_rng()
        rng.bit_generator.state = meta["rng"]
        channels = {k[len("channel/"):]: jit.tensor(a) for k, a in arrays.items()
                    if k.startswith("channel/")}
        refine = None
        if "refine/dirs" in arrays:
            refine = Refinement(arrays["refine/dirs"], arrays["refine/irradiance"],
                                arrays["refine/lights"], int(arrays["refine/done"][0]),
                                bool(arrays.get("refine/global", [0])[0]),
                                bool(arrays.get("refine/again", [0])[0]))
        return MaterialState(int(meta["step"]), opt, channels, arrays["directions"],
                             bool(meta["specular"]), rng, jit.array(arrays["loss_sum"]),
                             [(int(i), float(x)) for i, x in meta["history"]],
                             dict(meta["timings"]), refine, list(meta.get("light_log", [])),
                             arrays.get("detail/directions"), arrays.get("positions"),
                             arrays.get("detail/positions"))


_LIGHT_KEYS = ("log_light",)


@dataclasses.dataclass
class MaterialFit:
    """What a fit holds fixed (the surfels, the prepared views, the segments) and the shadow
    maps of its current lights; made by ``setup_fit``."""

    surfels: Surfels
    views: list[TrainView]
    seg: mi.UInt32  # [N] segment id per surfel
    n_seg: int
    config: MaterialConfig
    vis_config: VisibilityConfig
    bounds: SceneBounds
    maps: object  # the current lights' shadow maps (None without visibility)
    support: np.ndarray | None = None  # [N] surfel_support, made when first needed
    # The maps rendered so far: the refinement asks again for the candidates' current
    # direction and, after a move, for every light's map (the moved one a candidate's).
    # 96 MB: a local pass's 49 candidate maps at 512^2 and the lights'.
    map_cache: MapCache | None = None
    start_normals: mi.Vector3f | None = None  # [N] the normal phase's n0, made at its start
    held_normals: mi.Bool | None = None  # [N] the surfels whose normal the phase holds
    # The normal phase's per-view material maps (held there, so made once per view), by view
    # index; kept while they fit in HELD_MAPS_BYTES.
    held_maps: dict = dataclasses.field(default_factory=dict)

    def shadow_maps(self, directions, resolution=None, positions=None):
        """Shadow maps of ``directions`` (at ``resolution``, default the visibility's), or
        of lamps at ``positions`` [K, 3] where a row is finite."""
        if not self.config.use_visibility:
            return None
        if self.map_cache is None:
            self.map_cache = MapCache(self.surfels, self.bounds, max_bytes=96 << 20)
        if positions is None:
            return self.map_cache.maps(directions, self.vis_config, resolution)
        return self.map_cache.maps(directions, self.vis_config, resolution,
                                   positions=positions)

    def state_maps(self, state: MaterialState, resolution=None):
        """The shadow maps of ``state``'s lights."""
        return self.shadow_maps(state.directions, resolution, state.positions)


def _count_step(state: MaterialState, config: MaterialConfig, total: mi.Float) -> float | None:
    """A finished step's bookkeeping; the mean loss on a ``log_every`` step, else None."""
    state.loss_sum += dr.detach(total)
    state.step += 1
    if state.step % config.log_every != 0:
        return None
    # A host read every log_every steps.
    mean = float(state.loss_sum.numpy()[0]) / config.log_every
    state.history.append((state.step, mean))
    state.loss_sum = mi.Float(0.0)
    return mean
