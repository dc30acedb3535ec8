"""Adaptive density control of 3DGS/2DGS: clone, split, prune and opacity reset.

``DensifyStrategy`` holds its statistics (accumulated screen-space gradient norm, view
count and largest screen radius per surfel) and edits a ``SurfelAdam`` in place.

**The screen-space gradient.** 3DGS thresholds |dL/d(mean2D)| in NDC units, read off a
dummy 2D-mean tensor. Our rasterizer has no such input, so we derive it from the gradient
of the world-space centre: moving the centre by ``delta`` along the camera's right (down)
axis moves its projection by ``f delta / z`` pixels, hence
``dL/dx_pix ~= (dL/dp . right) z / f`` (and likewise for y), and NDC = pixels * 2 / W,
``dL/dx_ndc = dL/dx_pix * W / 2``. This ignores the part of dL/dp that comes from moving
the centre in depth and from the perspective change of the splat's shape, both second
order for a small splat; the paper-preset threshold (0.0002) keeps its 3DGS meaning.

Statistics accumulate with Dr.Jit operations (no host read); ``step`` at the densification
interval reads the model to NumPy once, edits it, and loads it back.
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.config import check_fields
from mi_shadowgs.core import jit
from mi_shadowgs.core.frames import quaternion_to_matrix
from mi_shadowgs.core.optim import SurfelAdam


@dataclasses.dataclass(frozen=True)
class DensifyConfig:
    """Density control; defaults are 2DGS's (3DGS's) reference values."""

    start: int = 500  # first iteration that densifies
    stop: int = 15000  # no densification from here on
    interval: int = 100
    opacity_reset_interval: int = 3000  # 0: never reset
    grad_threshold: float = 0.0002  # on the mean NDC-space gradient norm
    percent_dense: float = 0.01  # clone below / split above this fraction of the extent
    min_opacity: float = 0.05  # prune below
    # px (3-sigma radius, largest since the last densify); prune larger after the first
    # opacity reset. None: no screen-space prune (the world-space one below still applies).
    screen_size_threshold: float | None = 20.0
    world_size_fraction: float = 0.1  # prune tangent std-dev above this * extent (idem)
    # The world-space prune from this iteration on; None: with the screen-space one, after
    # the first opacity reset (3DGS; never without resets).
    world_prune_after: int | None = None
    split_count: int = 2
    split_scale_factor: float = 0.8  # split children get scale / (factor * split_count)
    reset_opacity: float = 0.01  # opacity reset caps opacity here
    max_surfels: int = 2_000_000  # no clone/split beyond this count

    def __post_init__(self):
        check_fields(self, (
            ("start", self.start >= 0, ">= 0"), ("interval", self.interval >= 1, ">= 1"),
            ("opacity_reset_interval", self.opacity_reset_interval >= 0, ">= 0 (0: never)"),
            ("grad_threshold", self.grad_threshold > 0, "> 0"),
            ("percent_dense", self.percent_dense > 0, "> 0"),
            ("min_opacity", 0 <= self.min_opacity < 1, "in [0, 1)"),
            ("screen_size_threshold", self.screen_size_threshold is None
             or self.screen_size_threshold > 0, "> 0 or None"),
            ("world_size_fraction", self.world_size_fraction > 0, "> 0"),
            ("world_prune_after", self.world_prune_after is None or self.world_prune_after >= 0,
             ">= 0 or None"),
            ("split_count", self.split_count >= 2, ">= 2"),
            ("split_scale_factor", self.split_scale_factor > 0, "> 0"),
            ("reset_opacity", 0 < self.reset_opacity < 1, "in (0, 1)"),
            ("max_surfels", self.max_surfels >= 1, ">= 1")))


def _logit(p: float) -> float:
    return float(np.log(p) - np.log1p(-p))


class DensifyStrategy:
    """Clone/split/prune and opacity reset, with the per-surfel statistics they need."""

    def __init__(self, config: DensifyConfig, extent: float, count: int, seed: int = 0,
                 iterations: int | None = None):
        if not extent > 0:
            raise ValueError(f"DensifyStrategy: scene extent must be > 0, got {extent}")
        self.config = config
        # The schedule's length: no opacity reset in its last ``opacity_reset_interval``
        # steps, so that every reset has a whole interval to win its opacities back (3DGS's
        # last reset, at 12k of 30k, has 18k). A reset at the end saved a transparent
        # model: `train --iterations 1000` at cpu-small, mask IoU 0.0009.
        self.iterations = iterations
        self.extent = float(extent)
        self.seed = int(seed)
        self.reset_stats(count)

    def reset_stats(self, count: int) -> None:
        self.grad_accum = dr.zeros(mi.Float, count)  # [N] sum of NDC gradient norms
        self.denom = dr.zeros(mi.Float, count)  # [N] views that saw the surfel
        self.max_radii = dr.zeros(mi.Float, count)  # [N] largest screen radius (px)

    # -- statistics ---------------------------------------------------------------------
    def observe(self, position: mi.TensorXf, log_scale: mi.TensorXf, camera) -> None:
        """Accumulate after a backward pass: ``position`` [N, 3] holds dL/dp as its gradient."""
        if dr.width(self.grad_accum) != position.shape[0]:
            raise ValueError("DensifyStrategy.observe: statistics and model sizes differ")
        rows = jit.opaque_matrix(camera.world_to_cv()[:3])
        r, t = [row[:3] for row in rows], [row[3] for row in rows]
        f = jit.opaque(camera.focal)
        half_w, half_h = jit.opaque(0.5 * camera.width), jit.opaque(0.5 * camera.height)
        p = dr.unravel(mi.Vector3f, dr.detach(position.array))
        g = dr.unravel(mi.Vector3f, dr.grad(position.array))
        z = r[2][0] * p.x + r[2][1] * p.y + r[2][2] * p.z + t[2]
        gx = r[0][0] * g.x + r[0][1] * g.y + r[0][2] * g.z
        gy = r[1][0] * g.x + r[1][1] * g.y + r[1][2] * g.z
        zs = dr.maximum(z, 1e-6)
        gn = dr.sqrt(dr.square(gx * half_w) + dr.square(gy * half_h)) * zs / f
        seen = (z > camera.near) & (dr.squared_norm(g) > 0)
        self.grad_accum = self.grad_accum + dr.select(seen, gn, 0.0)
        self.denom = self.denom + dr.select(seen, 1.0, 0.0)
        s = dr.unravel(mi.Vector2f, dr.detach(log_scale.array))
        radius = 3.0 * dr.exp(dr.maximum(s.x, s.y)) * f / zs  # 3-sigma, pixels
        self.max_radii = dr.select(seen, dr.maximum(self.max_radii, radius), self.max_radii)
        dr.schedule(self.grad_accum, self.denom, self.max_radii)

    # -- the edits ----------------------------------------------------------------------
    def step(self, iteration: int, opt: SurfelAdam) -> bool:
        """Run what is due after ``iteration`` (1-based count of finished steps).

        Returns True when the model changed size or was reset (callers re-read it).
        """
        c = self.config
        changed = False
        if c.start <= iteration < c.stop and iteration % c.interval == 0:
            after_reset = 0 < c.opacity_reset_interval < iteration
            world = (after_reset if c.world_prune_after is None
                     else iteration > c.world_prune_after)
            self.densify_and_prune(opt, iteration, world, screen_prune=after_reset)
            changed = True
        if self.reset_due(iteration):
            self.reset_opacity(opt)
            changed = True
        return changed

    def reset_due(self, iteration: int) -> bool:
        """Whether the opacities are reset after ``iteration``."""
        c = self.config
        every = c.opacity_reset_interval
        if every <= 0 or iteration >= c.stop or iteration % every:
            return False
        return self.iterations is None or iteration <= self.iterations - every

    def densify_and_prune(self, opt: SurfelAdam, iteration: int, big_prune: bool,
                          screen_prune: bool | None = None) -> None:
        """Clone, split and prune once. ``big_prune``: also the surfels larger than
        ``world_size_fraction`` of the extent, and (``screen_prune``, default ``big_prune``)
        those larger than ``screen_size_threshold`` on screen."""
        c = self.config
        screen_prune = big_prune if screen_prune is None else screen_prune
        params, m, v = opt.to_numpy()
        n = params["position"].shape[0]
        accum = np.asarray(self.grad_accum, np.float64)
        denom = np.asarray(self.denom, np.float64)
        radii = np.asarray(self.max_radii, np.float64)
        grad = np.where(denom > 0, accum / np.maximum(denom, 1.0), 0.0)
        scale = np.exp(params["log_scale"].astype(np.float64))  # [N, 2]
        smax = scale.max(axis=1)
        hot = grad >= c.grad_threshold
        room = max(c.max_surfels - n, 0)
        clone = hot & (smax <= c.percent_dense * self.extent)
        split = hot & ~clone
        # Respect max_surfels: keep the hottest candidates.
        for mask, per in ((clone, 1), (split, c.split_count - 1)):
            idx = np.flatnonzero(mask)
            if per > 0 and idx.size * per > room:
                keep = idx[np.argsort(-grad[idx], kind="stable")[:room // per]]
                mask[:] = False
                mask[keep] = True
            room -= int(mask.sum()) * per
        rng = np.random.default_rng([self.seed, iteration])
        new = {k: [a[clone]] for k, a in params.items()}
        si = np.flatnonzero(split)
        if si.size:
            rot = quaternion_to_matrix(params["rotation"][si])  # [S, 3, 3]
            for _ in range(c.split_count):
                local = rng.standard_normal((si.size, 2)) * scale[si]  # [S, 2] tangent offsets
                off = rot[:, :, 0] * local[:, :1] + rot[:, :, 1] * local[:, 1:]
                for k, a in params.items():
                    rows = a[si].copy()
                    if k == "position":
                        rows = (rows + off).astype(np.float32)
                    elif k == "log_scale":
                        rows = (np.log(scale[si] / (c.split_scale_factor * c.split_count))
                                ).astype(np.float32)
                    new[k].append(rows)
        opacity = 1.0 / (1.0 + np.exp(-params["opacity_logit"][:, 0].astype(np.float64)))
        prune = split | (opacity < c.min_opacity)
        if big_prune:
            prune |= smax > c.world_size_fraction * self.extent
        if screen_prune and c.screen_size_threshold is not None:
            prune |= radii > c.screen_size_threshold
        keep = ~prune
        added = {k: np.concatenate(rows, axis=0) for k, rows in new.items()}
        # New surfels' candidates were computed before pruning; prune them by opacity too.
        new_ok = 1.0 / (1.0 + np.exp(-added["opacity_logit"][:, 0])) >= c.min_opacity
        if keep.sum() + new_ok.sum() == 0:
            raise RuntimeError(f"densify at iteration {iteration}: every surfel would be "
                               "pruned (opacity below DensifyConfig.min_opacity)")
        out_p, out_m, out_v = {}, {}, {}
        for k in params:
            zeros = np.zeros((int(new_ok.sum()), params[k].shape[1]), np.float32)
            out_p[k] = np.concatenate([params[k][keep], added[k][new_ok]], axis=0)
            out_m[k] = np.concatenate([m[k][keep], zeros], axis=0)
            out_v[k] = np.concatenate([v[k][keep], zeros], axis=0)
        opt.load(out_p, out_m, out_v)
        self.reset_stats(out_p["position"].shape[0])

    def reset_opacity(self, opt: SurfelAdam) -> None:
        """Cap opacity at ``reset_opacity`` and zero that group's Adam moments (3DGS)."""
        cap = _logit(self.config.reset_opacity)
        p = opt.params["opacity_logit"]
        q = mi.TensorXf(dr.minimum(dr.detach(p.array), cap), shape=p.shape)
        dr.enable_grad(q)
        opt.params["opacity_logit"] = q
        opt.m["opacity_logit"] = dr.zeros(mi.TensorXf, p.shape)
        opt.v["opacity_logit"] = dr.zeros(mi.TensorXf, p.shape)
        dr.eval(opt.params["opacity_logit"])

    # -- checkpoints --------------------------------------------------------------------
    def state_numpy(self) -> dict[str, np.ndarray]:
        return {"grad_accum": np.asarray(self.grad_accum, np.float32),
                "denom": np.asarray(self.denom, np.float32),
                "max_radii": np.asarray(self.max_radii, np.float32)}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.grad_accum = jit.host(np.asarray(state["grad_accum"], np.float32))
        self.denom = jit.host(np.asarray(state["denom"], np.float32))
        self.max_radii = jit.host(np.asarray(state["max_radii"], np.float32))
