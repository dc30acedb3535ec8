"""Where a training step's time goes: a stage-1 step (``train_geometry``'s loop body) and a
stage-4 step (``fit_step``), split into their parts, each with its wall time, its Dr.Jit
kernel launches (``dr.kernel_history``) and its host syncs.

    python -m benchmarks.profile_step [--quick] [--out DIR] [--steps N] [--case C]
                                      [--baseline PROFILE_JSON] [--results DIR]

``--baseline`` takes an earlier run's ``profile.json`` (another commit, the same machine,
best run just before this one): each table gains its per-part times and the speed-up.
``--results DIR`` also writes ``DIR/step_profile.json`` (the schema ``make results``
renders into RESULTS.md).

The scene is the benchmarks' workload (a sphere of surfels on a plane of them,
``benchmarks.workloads``), seen by a ring of cameras whose images the rasterizer renders
from it. Stage 1 starts from the workload's surfels jittered, inside the densification
window; stage 4 fits the unjittered ones (one segment) from ``setup_fit``'s state.

How a part is measured: the package's functions are wrapped from here (nothing in the
package knows); on entering and leaving a part, the pending work is evaluated and
``dr.sync_thread()`` runs before the timer is read, so each part's time includes its kernels.
This splits kernels that the loop would fuse across parts, so "step (instrumented)" is
above the plain step's time, which is measured too, with one sync per step. Every kernel
is compiled before the timed steps (the "compiles" column counts kernel-cache misses
left). Host syncs are the host reads that Python code makes (``.numpy()``, ``np.asarray``,
``bool(mask)``, a scalar ``x[i]``, ``dr.sync_thread()``), counted by wrapping those in a
separate pass so that the wrappers' cost stays out of the times; the profiler's own syncs
and reads inside C++ are not counted.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core.camera import Camera

# The host reads of Python code: the array methods and functions that wait for the device.
# ``x[i]`` of a flat array is a read when it returns a Python scalar.
SYNC_METHODS = ("numpy", "__array__", "__bool__")
SCALAR_TYPES = ("Float", "Float64", "UInt32", "Int32", "UInt64", "Int64", "Bool")
_sync_thread = dr.sync_thread  # the profiler's own syncs, never counted

CASES = {  # name: (width, height, surfels, views)
    "128x128/30k": (128, 128, 30_000, 8),
    "512x384/80k": (512, 384, 80_000, 8),
}
QUICK_CASES = {"32x32/2k": (32, 32, 2_000, 3)}


@dataclasses.dataclass
class Part:
    ms: float = 0.0
    kernels: int = 0
    kernel_ms: float = 0.0
    compiles: int = 0
    syncs: int = 0


class Profiler:
    """Attributes wall time, kernels and host syncs to named parts; parts nest (time in an
    outer part outside its inner ones is the outer part's)."""

    def __init__(self, count_syncs: bool = False):
        self.parts: dict[str, Part] = {}
        self.stack: list[str] = []
        self.count_syncs = count_syncs
        self.steps = 0
        self._syncs = 0
        self._t = time.perf_counter()

    # -- the clock -------------------------------------------------------------------------
    def start(self) -> None:
        _sync_thread()
        dr.kernel_history()  # drop what ran before
        self._syncs = 0
        self._t = time.perf_counter()

    def stop(self) -> None:
        self.mark(self.stack[-1] if self.stack else "other (loop glue)")

    def mark(self, name: str) -> None:
        """Close the interval since the last mark as part ``name``."""
        _sync_thread()
        now = time.perf_counter()
        part = self.parts.setdefault(name, Part())
        part.ms += (now - self._t) * 1e3
        for k in dr.kernel_history():
            part.kernels += 1
            part.kernel_ms += float(k.get("execution_time", 0.0))
            part.compiles += not k.get("cache_hit", True)
        part.syncs += self._syncs
        self._syncs = 0
        self._t = time.perf_counter()

    def host_read(self) -> None:
        self._syncs += 1

    @contextlib.contextmanager
    def part(self, name: str, outputs=None):
        self.mark(self.stack[-1] if self.stack else "other (loop glue)")
        self.stack.append(name)
        try:
            yield
        finally:
            if outputs is not None:
                dr.eval(outputs())
            self.mark(name)
            self.stack.pop()

    def wrapped(self, fn, name: str):
        """``fn`` timed as part ``name``; its result is evaluated before the part closes."""
        def timed(*args, **kwargs):
            with self.part(name):
                out = fn(*args, **kwargs)
                _eval(out)
            return out
        return timed


def _eval(out) -> None:
    if isinstance(out, tuple | list):
        for o in out:
            _eval(o)
    elif isinstance(out, dict):
        _eval(list(out.values()))
    elif dataclasses.is_dataclass(out) and not isinstance(out, type):
        _eval([getattr(out, f.name) for f in dataclasses.fields(out)])
    elif dr.is_array_v(out):
        dr.eval(out)


def replace(stack: contextlib.ExitStack, owner, attr: str, new) -> None:
    """``owner.attr = new`` until ``stack`` closes."""
    own = attr in getattr(owner, "__dict__", {})
    original = getattr(owner, attr)
    setattr(owner, attr, new)
    stack.callback(lambda: setattr(owner, attr, original) if own else delattr(owner, attr))


def patch(stack: contextlib.ExitStack, prof: Profiler, owner, attr: str, name: str) -> None:
    """Replace ``owner.attr`` by its timed wrapper until ``stack`` closes."""
    replace(stack, owner, attr, prof.wrapped(getattr(owner, attr), name))


def count_syncs_(stack: contextlib.ExitStack, prof: Profiler) -> None:
    """Count the host reads of Python code into ``prof`` until ``stack`` closes."""
    def counted(fn, scalar_only=False):
        def read(*args, **kwargs):
            out = fn(*args, **kwargs)
            if not scalar_only or isinstance(out, int | float | bool):
                prof.host_read()
            return out
        return read

    replace(stack, dr, "sync_thread", counted(_sync_thread))
    for name in SYNC_METHODS:
        replace(stack, dr.ArrayBase, name, counted(getattr(dr.ArrayBase, name)))
    for name in SCALAR_TYPES:
        cls = getattr(mi, name, None)
        if cls is not None:
            replace(stack, cls, "__getitem__", counted(cls.__getitem__, scalar_only=True))


# -- the scene --------------------------------------------------------------------------------
@dataclasses.dataclass
class View:
    """What the stages read of a dataset view."""

    name: str
    camera: Camera
    image: np.ndarray  # [H, W, 3] float32
    mask: np.ndarray  # [H, W] bool
    has_mask: bool = True
    normal: np.ndarray | None = None
    depth: np.ndarray | None = None


def scene(width: int, height: int, n: int, n_views: int):
    """(workload, training views rendered from its surfels by the rasterizer)."""
    from benchmarks.workloads import build_workload
    from mi_shadowgs.core.directions import direction_from_angles
    from mi_shadowgs.stages.geometry.train import render_view

    wl = build_workload(n=n, resolution=width)
    surfels = workload_surfels(wl)
    centre = np.array([0.0, wl.config.sphere_center_y, 0.0])
    views = []
    for k in range(n_views):
        eye = centre + wl.config.camera_distance * direction_from_angles(
            360.0 * k / n_views, 25.0 + 10.0 * (k % 2))
        cam = Camera.look_at(eye, centre, width=width, height=height,
                             fov_x=math.radians(wl.config.fov_deg))
        r = render_view(surfels, cam)
        views.append(View(f"v{k}", cam, np.clip(r["rgb"], 0, 1).astype(np.float32),
                          r["alpha"] > 0.5))
    return wl, views


def workload_params(wl, sh_columns: int, jitter: float = 0.0) -> dict[str, np.ndarray]:
    """The workload's surfels as stage 1's raw parameters [N, C]."""
    from benchmarks.workloads import SH_C0

    rng = np.random.default_rng(1)
    pos = wl.position + rng.normal(scale=jitter * wl.spacing, size=wl.position.shape)
    sh = np.zeros((wl.n, sh_columns))
    sh[:, :3] = (wl.color - 0.5) / SH_C0
    op = np.clip(wl.opacity, 1e-4, 1 - 1e-4)
    return {"position": pos.astype(np.float32),
            "log_scale": np.log(wl.scale).astype(np.float32),
            "rotation": wl.rotation.astype(np.float32),
            "opacity_logit": np.log(op / (1 - op))[:, None].astype(np.float32),
            "sh": sh.astype(np.float32)}


def workload_surfels(wl):
    from mi_shadowgs.core.optim import surfels_from_params

    params = {k: mi.TensorXf(v) for k, v in workload_params(wl, 3).items()}
    return surfels_from_params(params)


class _Plain:
    """The profiler's interface, measuring nothing: the loop as it runs in the package."""

    def part(self, name, outputs=None):
        return contextlib.nullcontext()

    def host_read(self, n: int = 1) -> None:
        pass


# -- stage 1 ----------------------------------------------------------------------------------
def _settings_tree():
    """``mi_shadowgs.presets.build``, or None at a commit from before it (7f1b378, which the
    speed issue's figures are measured against)."""
    try:
        from mi_shadowgs.presets import build
    except ImportError:
        return None
    return build


def geometry_setup(wl, views, n: int):
    """(config, training state, views as Dr.Jit tensors, the first step to profile): past
    ``normal_from`` and ``dist_from``, just after a densification, so that every loss term is
    on and the step's own work is measured (densification is timed on its own)."""
    from mi_shadowgs.stages.geometry import train

    build = _settings_tree()
    # a commit before the settings tree (7f1b378): the stage's own table
    config = build("cpu-small").geometry if build else train.PRESETS["cpu-small"]
    config = dataclasses.replace(config, densify=dataclasses.replace(
        config.densify, max_surfels=max(n, config.densify.max_surfels)))
    d = config.densify
    start = max(config.normal_from, config.dist_from, d.start) // d.interval * d.interval + 1
    if start >= d.stop:
        raise ValueError("profile_step: the preset's densification window ends too early")
    sh_cols = (config.sh_degree + 1) ** 2 * 3
    params = workload_params(wl, sh_cols, jitter=0.2)
    state = train.state_from_params(params, [v.camera for v in views], config, step=start)
    state.step = start
    data = [train._view_data(v) for v in views]
    return config, state, data


def geometry_step(config, state, views, prof) -> None:
    """One iteration of ``train_geometry``'s loop, the same calls in the same order."""
    from mi_shadowgs.core import losses
    from mi_shadowgs.stages.geometry import train

    opt, strategy, sums = state.opt, state.strategy, state.log_sums
    step = state.step
    with prof.part("lr schedule + view"):
        opt.lr.update(train._learning_rates_split(config, step, state.extent))
        view = views[train.view_order(config, len(views), step)]
    with prof.part("model surfels (SH gather)"):
        surfels = train.model_surfels(opt.params, train.active_sh_degree(config, step))
        _eval(dataclasses.astuple(surfels))
    with prof.part("losses (L1, mask, normal, dist, mse)"):
        total, terms = train.geometry_loss(surfels, view, config, step)
        dr.eval(total, terms)
    with prof.part("backward (losses, D-SSIM, SH, glue)"):
        dr.backward(total)
    with prof.part("densify statistics"):
        strategy.observe(opt.params["position"], opt.params["log_scale"], view.camera)
    with prof.part("log sums"):
        for k, val in terms.items():
            sums[k] = sums[k] + val if k in sums else val
        dr.schedule(sums)
    with prof.part("optimiser (Adam)"):
        opt.step()
    state.step = step + 1
    state.log_count += 1
    with prof.part("densify schedule (check only)"):
        strategy.step(state.step, opt)
    if state.step % config.log_every == 0:
        with prof.part("host read (log)"):
            rec = {k: float(v[0]) / state.log_count for k, v in sums.items()}
            losses.psnr_from_mse(rec.pop("mse"))
            dr.sync_thread()
            sums.clear()
            state.log_count = 0


def geometry_patches(stack: contextlib.ExitStack, prof: Profiler) -> None:
    from mi_shadowgs.core import losses, raster_tiles
    from mi_shadowgs.stages.geometry import train

    patch(stack, prof, train, "rasterize", "rasterize forward")
    patch(stack, prof, train, "sh_colors", "SH colours")
    patch(stack, prof, losses, "d_ssim", "D-SSIM forward")
    patch(stack, prof, raster_tiles._TiledOp, "backward", "rasterize backward (tiled)")


def profile_geometry(wl, views, n: int, steps: int, warmup: int) -> dict:
    """Stage 1: the parts of ``steps`` steps, per step; densification amortised over its
    interval; the plain step's time."""
    config, state, data = geometry_setup(wl, views, n)
    first = state.step
    plain = _Plain()
    for _ in range(warmup):  # compile every kernel first, as the loop and as profiled
        geometry_step(config, state, data, plain)
    _profiled(lambda p: geometry_step(config, state, data, p), geometry_patches, warmup)
    prof = _profiled(lambda p: geometry_step(config, state, data, p), geometry_patches, steps)
    syncs = _profiled(lambda p: geometry_step(config, state, data, p), geometry_patches,
                      steps, count_syncs=True)
    plain_ms = _plain_ms(lambda: geometry_step(config, state, data, plain), steps)
    surfels = state.opt.count
    densify = _densify_once(state, config)
    interval = config.densify.interval
    parts = _per_step(prof.parts, steps)
    _merge_syncs(parts, _per_step(syncs.parts, syncs.steps))
    parts[f"densify/prune (1 in {interval} steps)"] = _per_step(densify.parts,
                                                                interval)["densify/prune"]
    return {"parts": parts, "plain_ms": plain_ms, "surfels": surfels, "steps": steps,
            "first_step": first, "views": len(views)}


def _densify_once(state, config) -> Profiler:
    """One densification at the current model, as ``strategy.step`` runs it (its syncs
    counted too)."""
    prof = Profiler(count_syncs=True)
    prof.start()
    with prof.part("densify/prune"):
        big = 0 < config.densify.opacity_reset_interval < state.step
        state.strategy.densify_and_prune(state.opt, state.step, big)
    prof.stop()
    return prof


# -- measuring --------------------------------------------------------------------------------
def _profiled(step, patches, steps: int, count_syncs: bool = False) -> Profiler:
    """``steps`` calls of ``step(profiler)`` with ``patches(stack, profiler)`` in place."""
    prof = Profiler(count_syncs)
    prof.steps = steps
    with contextlib.ExitStack() as stack:
        patches(stack, prof)
        if count_syncs:
            count_syncs_(stack, prof)
        prof.start()
        try:
            for _ in range(steps):
                step(prof)
        finally:
            prof.stop()
    return prof


def _per_step(parts: dict[str, Part], steps: int) -> dict[str, Part]:
    return {k: Part(p.ms / steps, p.kernels / steps, p.kernel_ms / steps, p.compiles / steps,
                    p.syncs / steps) for k, p in parts.items()}


def _merge_syncs(parts: dict[str, Part], counted: dict[str, Part]) -> None:
    """The sync counts of the counting pass into the timed parts (by name)."""
    for p in parts.values():
        p.syncs = 0.0
    for name, c in counted.items():
        parts.setdefault(name, Part()).syncs = c.syncs


def _plain_ms(step, steps: int) -> float:
    """ms per step of the loop as it runs (one sync per step, to bound the queue)."""
    dr.sync_thread()
    t = time.perf_counter()
    for _ in range(steps):
        step()
        dr.sync_thread()
    return (time.perf_counter() - t) * 1e3 / steps


# -- stage 4 ----------------------------------------------------------------------------------
def material_setup(wl, views, lights: int | None):
    """(fit, state) from ``setup_fit`` on the workload's surfels (one segment). ``lights``:
    None keeps the warm-up (every grid light, the warm-up's maps); a number moves to the
    main phase (``_end_warmup``) with that many lights left, as after pruning, and their
    full-resolution maps."""
    from mi_shadowgs.presets import build
    from mi_shadowgs.stages.material import fit as fit_mod
    from mi_shadowgs.stages.material.runner import occluder_bounds

    run = build("cpu-small")
    config, vis = run.material, run.visibility
    surfels = workload_surfels(wl)
    surfels = surfels.with_channels({"segment": mi.TensorXf(np.zeros((wl.n, 1), np.float32))})
    cams = [v.camera for v in views]
    bounds = occluder_bounds(surfels, cams, run.bounds_quantile)
    fit, state = fit_mod.setup_fit(surfels, cams, [v.image for v in views],
                                   [v.mask for v in views], config, bounds, vis,
                                   progress=False)
    if lights is not None:
        fit_mod._end_warmup(state, config)
        up = state.directions[:, 1] if state.directions.shape[1] == 3 else None
        keep = np.argsort(-up, kind="stable")[:lights] if up is not None else slice(lights)
        log_light = state.opt["log_light"].numpy()[keep]
        state.directions = state.directions[keep]
        fit.maps = fit.shadow_maps(state.directions)
        state.opt["log_light"] = mi.Float(log_light)
        state.opt.set_learning_rate({"log_light": config.lr_light})
        state.step = config.warmup + 1
    return fit, state


def material_patches(fit):
    def patches(stack: contextlib.ExitStack, prof: Profiler) -> None:
        from mi_shadowgs.core import shading
        from mi_shadowgs.stages.material import fit as fit_mod
        from mi_shadowgs.stages.material import views

        if fit.maps is not None:
            patch(stack, prof, fit.maps, "evaluate", "visibility (shadow-map lookups)")
        patch(stack, prof, fit_mod, "view_loss", "view loss (rest)")
        patch(stack, prof, views, "view_maps", "splat material maps")
        patch(stack, prof, shading, "shade", "shade (BRDF x lights)")
        patch(stack, prof, dr, "backward", "backward")
        patch(stack, prof, fit_mod, "_clamp_channels", "clamp channels")
        patch(stack, prof, fit_mod, "hold_albedo_scale", "albedo scale")
        patch(stack, prof, fit_mod, "albedo_scale_factor", "albedo scale factor (NumPy)")
        patch(stack, prof, fit_mod, "_count_step", "loss bookkeeping (log read)")
    return patches


def profile_material(wl, views, steps: int, warmup: int, lights: int | None) -> dict:
    """Stage 4: the parts of ``steps`` ``fit_step`` calls, per step; the plain step."""
    from mi_shadowgs.stages.material import fit as fit_mod

    fit, state = material_setup(wl, views, lights)
    first = state.step
    opt_step = state.opt.step

    def step(prof):
        fit_mod.fit_step(fit, state)

    def patches(stack, prof):
        material_patches(fit)(stack, prof)
        state.opt.step = prof.wrapped(opt_step, "optimiser (Adam)")
        stack.callback(delattr, state.opt, "step")

    for _ in range(warmup):  # compile every kernel first, as the loop and as profiled
        fit_mod.fit_step(fit, state)
    _profiled(step, patches, warmup)
    prof = _profiled(step, patches, steps)
    syncs = _profiled(step, patches, steps, count_syncs=True)
    plain_ms = _plain_ms(lambda: fit_mod.fit_step(fit, state), steps)
    parts = _per_step(prof.parts, steps)
    _merge_syncs(parts, _per_step(syncs.parts, steps))
    return {"parts": parts, "plain_ms": plain_ms, "surfels": fit.surfels.count,
            "steps": steps, "first_step": first, "lights": len(state.directions),
            "views": len(views)}


# -- the report -------------------------------------------------------------------------------
def table(result: dict) -> str:
    """Markdown: part, ms per step, share of the instrumented step, kernels, syncs."""
    parts = result["parts"]
    total = sum(p.ms for p in parts.values())
    rows = ["| part | ms / step | share | kernels / step | kernel ms | compiles | syncs / step |",
            "|---|---:|---:|---:|---:|---:|---:|"]
    for name, p in sorted(parts.items(), key=lambda kv: -kv[1].ms):
        rows.append(f"| {name} | {p.ms:.2f} | {p.ms / total:.1%} | {p.kernels:.1f} | "
                    f"{p.kernel_ms:.2f} | {p.compiles:.1f} | {p.syncs:.2f} |")
    k = sum(p.kernels for p in parts.values())
    s = sum(p.syncs for p in parts.values())
    rows.append(f"| **step (instrumented)** | **{total:.2f}** | 100% | {k:.1f} | "
                f"{sum(p.kernel_ms for p in parts.values()):.2f} | "
                f"{sum(p.compiles for p in parts.values()):.1f} | {s:.2f} |")
    rows.append(f"| step as the loop runs it (1 sync/step) | {result['plain_ms']:.2f} | | | | | |")
    return "\n".join(rows)


# Parts of the stage-1 step named in the results table; the others are summed into one row.
RESULT_PARTS = 5


def result_doc(report: dict, baseline: dict | None) -> dict:
    """The results/ record (``scripts.results`` schema) of a profile, one table per case: the
    stage-1 step's largest parts, and each step's instrumented and plain time, with the
    baseline's beside this run's where one is given."""
    m = report["machine"]
    base_commit = baseline["machine"]["commit"] if baseline else None
    cols = ["step", "part", f"ms at {m['commit']}"]
    if baseline:
        cols[2:2] = [f"ms at {base_commit}"]

    def row(stage, name, new, old):
        out = [stage, name, f"{new:.2f}"]
        if baseline:
            out[2:2] = ["-" if old is None else f"{old:.2f}"]
        return out

    tables = []
    for case, stages in report["cases"].items():
        rows = []
        for stage, r in stages.items():
            if not isinstance(r, dict):
                continue
            old = (baseline or {}).get("cases", {}).get(case, {}).get(stage) or {}
            old_parts = old.get("parts", {})

            def old_ms(names, parts=old_parts):
                return sum(parts[n]["ms"] for n in names) if all(n in parts
                                                                 for n in names) else None

            parts = sorted(r["parts"].items(), key=lambda kv: -kv[1]["ms"])
            if stage == "stage 1":
                for name, part in parts[:RESULT_PARTS]:
                    rows.append(row(stage, name, part["ms"], old_ms([name])))
                rest = [n for n, _ in parts[RESULT_PARTS:]]
                rows.append(row(stage, f"the other {len(rest)} parts",
                                sum(r["parts"][n]["ms"] for n in rest), old_ms(rest)))
            names = list(r["parts"])
            rows.append(row(stage, "**step (instrumented)**",
                            sum(p["ms"] for p in r["parts"].values()), old_ms(names)))
            rows.append(row(stage, "step as the loop runs it (1 sync)", r["plain_ms"],
                            old.get("plain_ms")))
        first = next(r for r in stages.values() if isinstance(r, dict))
        tables.append({"caption": f"{case}: {first['surfels']} surfels, {first['views']} "
                                  f"views, {first['steps']} steps per part; stage 4 main "
                                  f"with 3 lights, its warm-up with every grid light",
                       "columns": cols, "rows": rows})
    command = _public_command(m["command"]) + (
        f"; BASE: this command without --baseline and --results at {base_commit}, with this "
        "commit's benchmarks/profile_step.py, run just before" if baseline else "")
    return {"order": 9, "title": "Where a training step's time goes",
            "command": command, "produced_by": "the command above, with --results results",
            "machine": f"{m['cpu']}, {m['cores']} cores ({m['threads']} Dr.Jit threads), "
                       f"{m['variant']}, Mitsuba {m['mitsuba']} / Dr.Jit {m['drjit']}",
            "commit": m["commit"], "date": m["date"][:10],
            "text": ["A stage-1 and a stage-4 step on the benchmarks' workload (a sphere of "
                     "surfels on a plane of them, seen by a ring of cameras), split into their "
                     "parts (profile.md has them all). The profiler syncs at every part's "
                     "edges, so the instrumented step is above the plain one; a part also "
                     "runs the pending work it is the first to read (the last kernel of the "
                     "loss's gradient runs in the rasterizer's backward)."],
            "tables": tables}


def _public_command(command: str) -> str:
    """``command`` with the paths of this machine named by their role (``--out`` dropped,
    ``--baseline BASE/profile.json``, ``--results results``)."""
    words, out, skip = command.split(), [], False
    for i, w in enumerate(words):
        if skip:
            skip = False
            continue
        if w == "--out":
            skip = True
        elif w in ("--baseline", "--results") and i + 1 < len(words):
            out += [w, "BASE/profile.json" if w == "--baseline" else "results"]
            skip = True
        else:
            out.append(w)
    return " ".join(out)


def machine(argv: list[str]) -> dict:
    def git(*args):
        try:
            return subprocess.run(["git", *args], capture_output=True, text=True,
                                  check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return None

    return {"command": " ".join(["python -m benchmarks.profile_step", *argv]),
            "commit": git("rev-parse", "--short", "HEAD"),
            "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
            "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
            "host": platform.node(), "cpu": _cpu_name(),
            "cores": os.cpu_count(), "threads": dr.thread_count(),
            "python": platform.python_version(), "drjit": dr.__version__,
            "mitsuba": mi.__version__, "variant": mi.variant()}


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run_case(name: str, size: tuple, steps: int, warmup: int, lights: int) -> dict:
    width, height, n, n_views = size
    wl, views = scene(width, height, n, n_views)
    out = {"stage 1": profile_geometry(wl, views, n, steps, warmup)}
    if _settings_tree() is None:
        print(f"{name}: stage 4 not profiled: this commit has no settings tree "
              "(mi_shadowgs.presets)", flush=True)
        return out
    out["stage 4 (warm-up, all lights)"] = profile_material(wl, views, steps, warmup, None)
    out[f"stage 4 (main, {lights} lights)"] = profile_material(wl, views, steps, warmup, lights)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.profile_step", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny sizes: a smoke test")
    ap.add_argument("--out", default="bench-out/profile",
                    help="folder for profile.md and profile.json")
    ap.add_argument("--steps", type=int, default=None, help="profiled steps (default 25)")
    ap.add_argument("--case", action="append", choices=sorted(CASES),
                    help="only these cases (repeatable)")
    ap.add_argument("--baseline", default=None, metavar="PROFILE_JSON",
                    help="an earlier run's profile.json: its times beside this run's")
    ap.add_argument("--results", default=None, metavar="DIR",
                    help="also write DIR/step_profile.json (make results renders it)")
    args = ap.parse_args(argv)
    baseline = None
    if args.baseline:
        try:
            baseline = json.loads(Path(args.baseline).read_text())
            baseline["machine"]["commit"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            ap.error(f"--baseline {args.baseline}: not a profile.json of this tool ({exc})")
    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb")
    cases = QUICK_CASES if args.quick else {k: CASES[k] for k in (args.case or CASES)}
    steps = args.steps or (3 if args.quick else 25)
    warmup = 1 if args.quick else 3
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    report = {"machine": machine(sys.argv[1:] if argv is None else list(argv)),
              "steps": steps, "cases": {}}
    md = [f"# Step profile\n\n`{report['machine']['command']}` at "
          f"{report['machine']['commit']}, {report['machine']['date']}, "
          f"{report['machine']['cpu']} ({report['machine']['threads']} threads), "
          f"Dr.Jit {dr.__version__}, Mitsuba {mi.__version__}.\n"]
    try:
        for name, size in cases.items():
            t = time.perf_counter()
            res = run_case(name, size, steps, warmup, lights=3)
            report["cases"][name] = {}
            for stage, r in res.items():
                head = (f"## {name}, {stage}: {r['surfels']} surfels, {r['views']} views, "
                        f"{r['steps']} steps from step {r['first_step']}"
                        + (f", {r['lights']} lights" if "lights" in r else ""))
                md += [head, "", table(r), ""]
                print(head + "\n\n" + table(r) + "\n", flush=True)
                report["cases"][name][stage] = {
                    **{k: v for k, v in r.items() if k != "parts"},
                    "parts": {k: dataclasses.asdict(p) for k, p in r["parts"].items()}}
            report["cases"][name]["seconds"] = time.perf_counter() - t
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "profile.md").write_text("\n".join(md))
    (out / "profile.json").write_text(json.dumps(report, indent=1))
    print(f"wrote {out / 'profile.md'} and {out / 'profile.json'}")
    if args.results:
        from scripts.results import write_result

        path = Path(args.results) / "step_profile.json"
        write_result(path, result_doc(report, baseline))
        print(f"wrote {path}")
    return report


if __name__ == "__main__":
    main()
