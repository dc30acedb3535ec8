"""Rasterizer benchmark: our 2DGS rasterizer against Mitsuba's Gaussian renderer.

Both renderers get the same workload (``benchmarks.workloads``), the same camera and
resolution, an L1 loss against a constant image, gradients for every parameter, and a
position nudge every iteration (so binning / BVH rebuilds are inside the timed step).

One configuration runs per process, so that peak RSS belongs to it alone::

    python -m benchmarks.bm_raster --renderer ours --n 20000 --res 128 --json out.json

``--method tiles`` (``--tile-size T``) times our tiled renderer (``RasterConfig.method``)
instead of the pair list; ``--threads K`` caps Dr.Jit's worker threads.

Timing of one training step (``_Runner.step``): nudge + render + loss, ``dr.eval`` +
``dr.sync_thread`` -> "forward"; then ``dr.backward`` and evaluating every gradient ->
"forward+backward". The first step of a process is reported apart (JIT compilation: run_all
gives each process an empty kernel cache); the medians are taken after ``warmup`` further
steps.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM, selects llvm_ad_rgb)
from mi_shadowgs.config import get_preset
from mi_shadowgs.io.atomic import atomic_path, write_json, write_text

from .workloads import Workload, WorkloadConfig, build_workload

RENDERERS = ("ours", "mitsuba")


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """The rasterizer sweep. ``paper``: the issue's sizes; ``cpu-small``: the --quick sweep."""

    resolutions: tuple[int, ...] = (128, 256)
    counts: tuple[int, ...] = (5_000, 20_000, 100_000)
    # Extra resolutions run for ours only, to spread the pair counts of the linearity fit.
    linearity_resolutions: tuple[int, ...] = (64, 96, 192)
    warmup: int = 2  # steps after the first, untimed
    iters: int = 9  # timed steps; medians are reported
    # (n, res) configurations where the peer is not run (too slow for the time budget).
    peer_skip: tuple[tuple[int, int], ...] = ()
    # The whole sweep runs this many times (renderers interleaved); per configuration the
    # best round's median is kept, so that other processes on the cores (a burst in one
    # round) weigh less on the figures and on the ratios.
    rounds: int = 3
    case_timeout_s: float = 300.0  # per subprocess
    image_case: tuple[int, int] = (20_000, 128)  # (n, res) of the side-by-side render


PRESETS = {
    "paper": BenchConfig(),
    "cpu-small": BenchConfig(resolutions=(64, 128), counts=(2_000, 5_000, 20_000),
                             linearity_resolutions=(96,), warmup=1, iters=3, rounds=1,
                             case_timeout_s=120.0),
}


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (``memory.peak_resident_bytes``; where
    /proc is missing, ``ru_maxrss``, which may include the parent's)."""
    from mi_shadowgs.core.memory import peak_resident_bytes

    peak = peak_resident_bytes()
    if peak is None:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return peak / (1024.0 * 1024.0)


def current_rss_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


class _Runner:
    """One renderer set up on one workload; ``step`` runs and times one training step."""

    name = ""

    def __init__(self, workload: Workload):
        import drjit as dr
        import mitsuba as mi

        self.workload = workload
        rng = np.random.default_rng(workload.config.seed + 1)
        d = rng.normal(size=(workload.n, 3))
        # [N, 3] fixed random offsets; the sign alternates so positions oscillate, not drift.
        self.offset = workload.config.nudge * d / np.linalg.norm(d, axis=-1, keepdims=True)
        self.sign = 1.0
        self.target = workload.config.target_value
        self._dr, self._mi = dr, mi

    def render(self):  # -> mi.TensorXf [H, W, 3]
        raise NotImplementedError

    def nudge(self) -> None:
        raise NotImplementedError

    def grads(self) -> list:
        raise NotImplementedError

    grad_names: tuple[str, ...] = ()

    def grad_l1(self) -> dict[str, float]:
        """Sum of |gradient| per parameter group after the last step (all must be > 0)."""
        return {name: float(np.abs(np.asarray(g.numpy(), dtype=np.float64)).sum())
                for name, g in zip(self.grad_names, self.grads(), strict=True)}

    def step(self, backward: bool = True) -> tuple[float, float, float, float]:
        """(forward s, forward+backward s, forward+backward CPU s of all threads, loss)."""
        dr = self._dr
        c0 = time.process_time()
        t0 = time.perf_counter()
        self.nudge()
        image = self.render()
        loss = dr.mean(dr.abs(image - self.target), axis=None)
        dr.eval(loss)
        dr.sync_thread()
        t1 = time.perf_counter()
        if backward:
            dr.backward(loss)
            grads = self.grads()
            dr.eval(*grads)
            dr.sync_thread()
        t2 = time.perf_counter()
        c2 = time.process_time()
        return t1 - t0, t2 - t0, c2 - c0, float(np.asarray(loss.numpy()).ravel()[0])

    def image(self) -> np.ndarray:
        """[H, W, 3] float32 render at the current parameters (no gradients)."""
        with self._dr.suspend_grad():
            return np.asarray(self.render().numpy(), dtype=np.float32)[..., :3]

    def stats(self) -> dict:
        return {}


class OursRunner(_Runner):
    """``mi_shadowgs.core.raster.rasterize`` with an "rgb" channel and the "alpha" AOV."""

    name = "ours"
    grad_names = ("position", "log_scale", "rotation", "opacity_logit", "rgb")

    def __init__(self, workload: Workload, raster_config=None):
        super().__init__(workload)
        from mi_shadowgs.core.raster import RasterConfig
        from mi_shadowgs.core.surfels import Surfels

        mi, dr = self._mi, self._dr
        wl = workload
        self.config = raster_config or RasterConfig()
        self.surfels = Surfels.from_numpy(wl.position, wl.scale, wl.rotation, wl.opacity, {})
        self.colors = mi.TensorXf(np.ascontiguousarray(wl.color, dtype=np.float32))  # [N, 3]
        self.offset_dr = mi.Vector3f(*(self.offset.T.astype(np.float32)))
        for value in self._leaves():
            dr.enable_grad(value)

    def _leaves(self) -> list:
        params = self.surfels.params()
        return [params[k] for k in ("position", "log_scale", "rotation", "opacity_logit")] + [
            self.colors]

    def nudge(self) -> None:
        dr = self._dr
        for value in self._leaves():
            dr.clear_grad(value)
        self.sign = -self.sign
        pos = dr.detach(self.surfels.position) + self.sign * self.offset_dr
        # An optimiser step leaves its parameters evaluated; so do we. (Unevaluated, the
        # nudge expression is recomputed inside the rasterizer's kernels: ~3x slower at
        # 64^2/5k.)
        dr.eval(pos)
        dr.enable_grad(pos)
        self.surfels.position = pos

    def render(self):
        from mi_shadowgs.core.raster import rasterize

        out = rasterize(self.surfels, self.workload.camera, {"rgb": self.colors},
                        aovs=("alpha",), config=self.config)
        return out["rgb"]

    def grads(self) -> list:
        return [self._dr.grad(v) for v in self._leaves()]

    def stats(self) -> dict:
        return count_pairs(self.surfels, self.workload.camera, self.config)


def count_pairs(surfels, camera, config) -> dict:
    """Pixel-splat pair counts of our rasterizer for this view.

    "box_pairs": pairs inside the splats' bounding boxes (the detached first pass);
    "pairs": those kept after the alpha/cutoff tests, sorted and composited with AD (the
    main cost); "contributing": those that pass the transmittance cut (the "count" AOV).
    """
    import drjit as dr

    from mi_shadowgs.core import raster

    box_pairs, pairs = raster.pair_counts(surfels, camera, config)
    with dr.suspend_grad():
        count = raster.rasterize(surfels, camera, {}, aovs=("count",), config=config)["count"]
        return {
            "box_pairs": box_pairs,
            "pairs": pairs,
            "contributing": int(round(float(np.asarray(count.numpy(), np.float64).sum()))),
        }


class MitsubaRunner(_Runner):
    """Mitsuba 3's ``ellipsoids`` shape rendered by ``volprim_rf_basic`` (spp=1)."""

    name = "mitsuba"
    grad_names = ("data (centre, scale, quaternion)", "opacities", "sh_coeffs")
    KEYS = ("p.data", "p.opacities", "p.sh_coeffs")
    DATA_STRIDE = 10  # per-ellipsoid record of p.data: centre 3, scale 3, quaternion xyzw 4

    def __init__(self, workload: Workload, spp: int = 1, extent: float = 3.0):
        super().__init__(workload)
        mi = self._mi
        wl = workload

        def tensor(a):
            return mi.TensorXf(np.ascontiguousarray(a, dtype=np.float32))

        self.spp = spp
        self.scene = mi.load_dict({
            "type": "scene",
            # Colours are linear, as ours; max_depth = the integrator's default.
            "integrator": {"type": "volprim_rf_basic", "srgb_primitives": False,
                           "max_depth": 64},
            "sensor": wl.camera.to_mitsuba_dict(spp=spp, film={"pixel_format": "rgb"}),
            "gaussians": {
                "type": "ellipsoids",
                "centers": tensor(wl.position),
                "scales": tensor(wl.ellipsoid_scales()),
                "quaternions": tensor(wl.quaternions_xyzw()),
                "opacities": tensor(wl.opacity[:, None]),
                "sh_coeffs": tensor(wl.sh_dc()),
                "extent": extent,  # bounding shell in sigmas, as our cutoff_sigma
            },
        })
        self.params = mi.traverse(self.scene)
        keys = [k.replace("p.", "gaussians.") for k in self.KEYS]
        self.keys = keys
        self.params.keep(keys)
        offset = np.zeros((wl.n, self.DATA_STRIDE), dtype=np.float32)
        offset[:, :3] = self.offset
        self.offset_dr = mi.Float(offset.ravel())
        self._check_layout()

    def _check_layout(self) -> None:
        """Fail loudly if Mitsuba's packed ellipsoid record is not (centre, scale, quat)."""
        data = np.asarray(self.params[self.keys[0]].numpy()).reshape(-1, self.DATA_STRIDE)
        expect = np.concatenate([self.workload.position, self.workload.ellipsoid_scales()], -1)
        if data.shape[0] != self.workload.n or not np.allclose(data[:, :6], expect, atol=1e-5):
            raise RuntimeError("Mitsuba's ellipsoids 'data' layout is not the expected "
                               "[centre 3, scale 3, quaternion 4] per primitive")

    def nudge(self) -> None:
        dr, p = self._dr, self.params
        self.sign = -self.sign
        data = dr.detach(p[self.keys[0]]) + self.sign * self.offset_dr
        dr.eval(data)  # as after an optimiser step (and as for ours)
        p[self.keys[0]] = data
        p.update()  # rebuilds the BVH: part of the timed step
        for k in self.keys:
            dr.enable_grad(p[k])

    def render(self):
        return self._mi.render(self.scene, self.params, spp=self.spp)

    def grads(self) -> list:
        return [self._dr.grad(self.params[k]) for k in self.keys]


def make_runner(renderer: str, workload: Workload, raster_config=None):
    if renderer == "ours":
        return OursRunner(workload, raster_config)
    if renderer == "mitsuba":
        return MitsubaRunner(workload)
    raise ValueError(f"unknown renderer {renderer!r}; choose one of {RENDERERS}")


def run_case(renderer: str, n: int, res: int, warmup: int = 2, iters: int = 5,
             image_path: str | Path | None = None, seed: int = 0, raster_config=None,
             stats: bool = True) -> dict:
    """Time one (renderer, n, res) configuration in this process; returns a result row.
    ``raster_config``: ours's RasterConfig (default: ``RasterConfig()``); ``stats``: add
    the renderer's pair counts (ours: a pass over the pixel-splat pair list, whose memory
    can exceed the render's at 800^2)."""
    rss_start = current_rss_mb()
    workload = build_workload(WorkloadConfig(n=n, resolution=res, seed=seed))
    runner = make_runner(renderer, workload, raster_config)
    t_setup = time.perf_counter()
    load = os.getloadavg()[0]
    _, first, _, loss0 = runner.step()
    for _ in range(warmup):
        runner.step()
    fwd, total, cpu, losses = [], [], [], []
    for _ in range(iters):
        f, t, c, loss = runner.step()
        fwd.append(f)
        total.append(t)
        cpu.append(c)
        losses.append(loss)
    # Nudges are 1e-4 against sigmas of ~1e-2, so the loss barely moves; a jump means a
    # renderer lost the scene between steps (e.g. a failed BVH update).
    drift = max(abs(v - loss0) for v in losses) / max(abs(loss0), 1e-12) if losses else 0.0
    row = {
        "renderer": renderer, "n": n, "res": res, "n_sphere": workload.n_sphere,
        "method": runner.config.method if renderer == "ours" else None,
        "tile_size": runner.config.tile_size if renderer == "ours" else None,
        "n_plane": workload.n_plane, "iters": iters, "warmup": warmup,
        "first_ms": 1e3 * first,
        "fwd_ms": 1e3 * statistics.median(fwd) if fwd else float("nan"),
        "fwd_bwd_ms": 1e3 * statistics.median(total) if total else float("nan"),
        "fwd_bwd_ms_min": 1e3 * min(total) if total else float("nan"),
        # CPU time of all threads: less sensitive than wall time to other processes on the
        # cores (they slow the wall clock, not the work done).
        "fwd_bwd_cpu_ms": 1e3 * statistics.median(cpu) if cpu else float("nan"),
        "fwd_ms_all": [1e3 * v for v in fwd], "fwd_bwd_ms_all": [1e3 * v for v in total],
        "load1_start": load,
        "loss": loss0, "loss_drift": drift,
        "rss_start_mb": rss_start,
        "peak_rss_mb": peak_rss_mb(),  # before the extra stats/image passes below
        "wall_s": time.perf_counter() - t_setup,
    }
    row["grad_l1"] = runner.grad_l1()
    if stats:
        row.update(runner.stats())
    if image_path is not None:
        np.save(image_path, runner.image())
    return row


def fit_line(x, y) -> tuple[float, float, float]:
    """Least-squares y = slope * x + intercept; returns (slope, intercept, R^2)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if len(x) < 2:
        raise ValueError("fit_line needs at least two points")
    a = np.stack([x, np.ones_like(x)], axis=-1)
    (slope, intercept), *_ = np.linalg.lstsq(a, y, rcond=None)
    ss_res = float(np.sum((y - (slope * x + intercept)) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else 1.0
    return float(slope), float(intercept), r2


def case_cmd(renderer: str, n: int, res: int, cfg, json_path: Path,
             image_path: Path | None = None) -> list[str]:
    """One case's command line; ``cfg`` gives ``warmup`` and ``iters`` (BenchConfig)."""
    cmd = [sys.executable, "-m", "benchmarks.bm_raster", "--renderer", renderer, "--n", str(n),
           "--res", str(res), "--warmup", str(cfg.warmup), "--iters", str(cfg.iters),
           "--json", str(json_path)]
    if image_path is not None:
        cmd += ["--image", str(image_path)]
    return cmd


def run_subprocess(cmd: list[str], timeout: float, env: dict | None = None) -> tuple[str, str]:
    """(status, stderr tail) of one benchmark process run from the repository root, with
    ``env`` added to the environment."""
    root = Path(__file__).resolve().parent.parent
    # A private, empty HOME gives Dr.Jit an empty on-disk kernel cache (~/.drjit), so the
    # first step's time is the real JIT compilation, the same for every case.
    with tempfile.TemporaryDirectory(prefix="bm_home_") as home:
        env = dict(os.environ, **(env or {}), HOME=home)
        try:
            proc = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True,
                                  timeout=timeout)
        except subprocess.TimeoutExpired:
            return "timeout", f"killed after {timeout:.0f} s"
    if proc.returncode != 0:
        return "error", proc.stderr[-2000:]
    return "ok", ""


def sweep_cases(cfg: BenchConfig) -> list[tuple[str, int, int]]:
    """(renderer, n, res) in run order: the comparison grid, then ours-only linearity points."""
    cases = []
    for res in cfg.resolutions:
        for n in cfg.counts:
            cases.append(("ours", n, res))
            if (n, res) not in cfg.peer_skip:
                cases.append(("mitsuba", n, res))
    for res in cfg.linearity_resolutions:
        for n in cfg.counts:
            cases.append(("ours", n, res))
    return cases


def run_suite(out: Path, preset: str = "paper", log=print) -> dict:
    """Run the whole rasterizer sweep, one subprocess per case; write the report into out."""
    cfg = get_preset(PRESETS, preset, "rasterizer benchmark")
    out = Path(out)
    raw = out / "raster_raw"
    raw.mkdir(parents=True, exist_ok=True)
    rows, images = [], {}
    cases = [(k, *c) for k in range(cfg.rounds) for c in sweep_cases(cfg)]
    for k, renderer, n, res in cases:
        json_path = raw / f"{renderer}_{res}_{n}_round{k}.json"
        image_path = raw / f"{renderer}_{res}_{n}.npy" \
            if (n, res) == cfg.image_case and k == 0 else None
        t0 = time.perf_counter()
        status, err = run_subprocess(case_cmd(renderer, n, res, cfg, json_path, image_path),
                                     cfg.case_timeout_s)
        if status == "ok":
            row = json.loads(json_path.read_text())
            row["status"] = "ok"
            if image_path is not None:
                images[renderer] = np.load(image_path)
        else:
            row = {"renderer": renderer, "n": n, "res": res, "status": status, "error": err}
        row["round"] = k
        rows.append(row)
        log(f"[raster] round {k} {renderer:8s} {res:4d}^2 n={n:6d}: {_row_summary(row)} "
            f"({time.perf_counter() - t0:.1f} s)")
    for res, n in cfg.peer_skip:
        rows.append({"renderer": "mitsuba", "n": n, "res": res, "status": "skipped",
                     "error": "skipped for the time budget (BenchConfig.peer_skip)"})
    summary = write_report(out, rows, images, cfg, preset)
    return summary


def best_of_rounds(rows: list[dict]) -> list[dict]:
    """One row per (renderer, n, res): times from the round with the lowest fwd+bwd median,
    the largest peak RSS of all rounds, the median first-step time; ``rounds_ok`` counts."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["renderer"], r["n"], r["res"]), []).append(r)
    out = []
    for runs in groups.values():
        ok = [r for r in runs if r.get("status") == "ok"]
        if not ok:
            out.append(dict(runs[-1]))
            continue
        best = dict(min(ok, key=lambda r: r["fwd_bwd_ms"]))
        best["peak_rss_mb"] = max(r["peak_rss_mb"] for r in ok)
        best["first_ms"] = statistics.median(r["first_ms"] for r in ok)
        best["fwd_bwd_cpu_ms"] = min(r.get("fwd_bwd_cpu_ms", float("nan")) for r in ok)
        best["fwd_bwd_ms_rounds"] = [r["fwd_bwd_ms"] for r in ok]
        best["rounds_ok"] = len(ok)
        out.append(best)
    return out


def _row_summary(row: dict) -> str:
    if row.get("status") != "ok":
        return f"{row.get('status')}: {row.get('error', '')[-300:]}"
    pairs = f", pairs {row['pairs']}" if "pairs" in row else ""
    return (f"fwd {row['fwd_ms']:.1f} ms, fwd+bwd {row['fwd_bwd_ms']:.1f} ms, "
            f"first {row['first_ms']:.0f} ms, peak RSS {row['peak_rss_mb']:.0f} MB{pairs}")


def _find(rows, renderer, n, res):
    for r in rows:
        if (r["renderer"], r["n"], r["res"]) == (renderer, n, res) and r.get("status") == "ok":
            return r
    return None


def comparison_table(rows: list[dict], cfg: BenchConfig) -> tuple[list[dict], str]:
    """One record per (res, n) of the grid, and its markdown table."""
    table, lines = [], []
    head = ("| res | N | pairs (ours) | ours fwd ms | ours fwd+bwd ms | Mitsuba fwd ms | "
            "Mitsuba fwd+bwd ms | fwd+bwd Mitsuba/ours | fwd Mitsuba/ours | "
            "fwd+bwd CPU-time Mitsuba/ours | "
            "ours peak RSS MB | Mitsuba peak RSS MB | ours first ms | Mitsuba first ms |")
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for res in cfg.resolutions:
        for n in cfg.counts:
            o, m = _find(rows, "ours", n, res), _find(rows, "mitsuba", n, res)
            rec = {"res": res, "n": n}
            for tag, r in (("ours", o), ("mitsuba", m)):
                for k in ("fwd_ms", "fwd_bwd_ms", "fwd_bwd_cpu_ms", "peak_rss_mb", "first_ms"):
                    rec[f"{tag}_{k}"] = r.get(k, float("nan")) if r else float("nan")
            rec["pairs"] = o.get("pairs", float("nan")) if o else float("nan")
            rec["ratio_fwd_bwd"] = rec["mitsuba_fwd_bwd_ms"] / rec["ours_fwd_bwd_ms"]
            rec["ratio_fwd"] = rec["mitsuba_fwd_ms"] / rec["ours_fwd_ms"]
            rec["ratio_fwd_bwd_cpu"] = rec["mitsuba_fwd_bwd_cpu_ms"] / rec["ours_fwd_bwd_cpu_ms"]
            table.append(rec)

            def f(v, fmt="{:.1f}"):
                return "n/a" if v != v else fmt.format(v)

            lines.append(
                f"| {res}^2 | {n} | {f(rec['pairs'], '{:,.0f}')} | {f(rec['ours_fwd_ms'])} | "
                f"{f(rec['ours_fwd_bwd_ms'])} | {f(rec['mitsuba_fwd_ms'])} | "
                f"{f(rec['mitsuba_fwd_bwd_ms'])} | {f(rec['ratio_fwd_bwd'], '{:.2f}x')} | "
                f"{f(rec['ratio_fwd'], '{:.2f}x')} | {f(rec['ratio_fwd_bwd_cpu'], '{:.2f}x')} | "
                f"{f(rec['ours_peak_rss_mb'], '{:.0f}')} | "
                f"{f(rec['mitsuba_peak_rss_mb'], '{:.0f}')} | {f(rec['ours_first_ms'], '{:.0f}')}"
                f" | {f(rec['mitsuba_first_ms'], '{:.0f}')} |")
    return table, "\n".join(lines)


CSV_FIELDS = ("renderer", "n", "res", "round", "rounds_ok", "status", "pairs", "box_pairs",
              "contributing", "fwd_ms", "fwd_bwd_ms", "fwd_bwd_ms_min", "fwd_bwd_cpu_ms",
              "first_ms", "peak_rss_mb", "rss_start_mb", "load1_start", "loss", "loss_drift",
              "n_sphere", "n_plane", "iters", "warmup")


def linearity(rows: list[dict]) -> dict:
    """Fit of our fwd and fwd+bwd medians against the number of pixel-splat pairs."""
    pts = [r for r in rows if r["renderer"] == "ours" and r.get("status") == "ok"
           and r.get("pairs")]
    if len(pts) < 3:
        return {"points": len(pts)}
    x = [r["pairs"] for r in pts]
    out = {"points": len(pts), "pairs": x, "cpu_count": os.cpu_count() or 1,
           "n": [r["n"] for r in pts], "res": [r["res"] for r in pts]}
    for key in ("fwd_ms", "fwd_bwd_ms", "fwd_bwd_cpu_ms"):
        y = [r.get(key, float("nan")) for r in pts]
        if not all(math.isfinite(v) for v in y):
            continue
        slope, intercept, r2 = fit_line(x, y)
        out[key] = {"ms": y, "slope_ns_per_pair": 1e6 * slope, "intercept_ms": intercept,
                    "r2": r2}
    return out


def plot_linearity(path: Path, lin: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=110)
    x = np.asarray(lin["pairs"], dtype=np.float64)
    markers = dict(zip(sorted(set(lin["res"])), "osD^v<>", strict=False))
    series = (("fwd_bwd_ms", "C0", "forward+backward"), ("fwd_ms", "C1", "forward"),
              ("fwd_bwd_cpu_ms", "0.5", "fwd+bwd CPU time / cores"))
    for key, colour, label in series:
        if key not in lin:
            continue
        scale = 1.0 / lin.get("cpu_count", 1) if "cpu" in key else 1.0
        y = np.asarray(lin[key]["ms"]) * scale
        for res, mk in markers.items():
            sel = np.asarray(lin["res"]) == res
            ax.scatter(x[sel] / 1e6, y[sel], c=colour, marker=mk, s=28,
                       label=f"{label}, {res}^2")
        xs = np.linspace(0.0, x.max() * 1.05, 50)
        fit = lin[key]
        ax.plot(xs / 1e6, scale * (fit["intercept_ms"] + fit["slope_ns_per_pair"] * 1e-6 * xs),
                c=colour, lw=1, label=f"{label} fit: R^2 = {fit['r2']:.3f}")
    ax.set_xlabel("pixel-splat pairs (millions)")
    ax.set_ylabel("median time per step (ms)")
    ax.set_title("Our rasterizer (llvm_ad_rgb): time vs pixel-splat pairs")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def plot_renders(path: Path, images: dict, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_shadowgs.io.images import linear_to_srgb

    panels = [("ours: 2DGS rasterizer" if k == "ours" else "Mitsuba ellipsoids + volprim_rf_basic",
               images[k]) for k in ("ours", "mitsuba") if k in images]
    if len(panels) == 2:
        diff = np.abs(images["ours"] - images["mitsuba"]).mean(axis=-1)
        panels.append((f"|ours - Mitsuba| (mean {diff.mean():.3f})", diff))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.3 * len(panels), 3.6), dpi=110)
    for ax, (name, img) in zip(np.atleast_1d(axes), panels, strict=True):
        if img.ndim == 2:
            ax.imshow(img, cmap="magma", vmin=0.0, vmax=max(float(img.max()), 1e-6))
        else:
            ax.imshow(np.clip(linear_to_srgb(np.clip(img, 0, 1)), 0, 1),
                      interpolation="nearest")
        ax.set_title(name, fontsize=8)
        ax.axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def write_report(out: Path, rows: list[dict], images: dict, cfg: BenchConfig,
                 preset: str) -> dict:
    """raster.csv (best of rounds), raster_runs.csv (every run), raster.json, raster.md and
    the two PNG figures, into ``out``."""
    runs = rows
    rows = best_of_rounds(runs)
    table, md_table = comparison_table(rows, cfg)
    lin = linearity(rows)
    for name, data in (("raster.csv", rows), ("raster_runs.csv", runs)):
        with atomic_path(out / name) as tmp, open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=CSV_FIELDS, extrasaction="ignore")
            w.writeheader()
            for r in data:
                w.writerow(r)
    if lin.get("points", 0) >= 3:
        plot_linearity(out / "raster_linearity.png", lin)
    n_img, res_img = cfg.image_case
    if images:
        plot_renders(out / f"raster_render_{res_img}_{n_img}.png", images,
                     f"{res_img}^2, {n_img} Gaussians, final step of the benchmark")

    goals = {}
    # The targets (the first asked for 4x and 512 MB with the pair list).
    for res, target in ((128, 10.0), (256, 8.0)):
        speed = next((t for t in table if (t["n"], t["res"]) == (20_000, res)), None)
        if speed is not None:
            goals[f"speedup_fwd_bwd_{res}_20k"] = speed["ratio_fwd_bwd"]
            goals[f"speedup_goal_{res}_met"] = bool(speed["ratio_fwd_bwd"] >= target)
    mem = next((t for t in table if (t["n"], t["res"]) == (20_000, 256)), None)
    if mem is not None:
        goals["ours_peak_rss_mb_256_20k"] = mem["ours_peak_rss_mb"]
        goals["memory_goal_met"] = bool(mem["ours_peak_rss_mb"] <= 256.0)
    summary = {"preset": preset, "config": dataclasses.asdict(cfg), "table": table,
               "linearity": lin, "goals": goals, "rows": rows, "runs": runs}
    write_json(out / "raster.json", summary)

    starts = [r["rss_start_mb"] for r in rows if r.get("status") == "ok" and "rss_start_mb" in r]
    base_rss = statistics.median(starts) if starts else float("nan")
    methods = sorted({f"{r.get('method')} (tile {r.get('tile_size')})" for r in rows
                      if r.get("renderer") == "ours" and r.get("status") == "ok"})
    md = ["## Rasterizer vs Mitsuba's Gaussian renderer (issues 3 and 18)", "",
          f"Ours: `RasterConfig.method` {', '.join(methods) or 'n/a'}. "
          f"Preset `{preset}`; medians of {cfg.iters} steps after 1 + {cfg.warmup} warm-up "
          f"steps, best of {cfg.rounds} interleaved round(s) (all runs: raster_runs.csv); "
          "one process per (renderer, N, res) with an empty Dr.Jit kernel cache "
          "(\"first\" = the first step, JIT compilation included); peak RSS of that whole "
          f"process (Python + Mitsuba after import: {base_rss:.0f} MB). Forward = nudge + "
          "render + L1 loss, evaluated; forward+backward adds `dr.backward` and evaluating "
          "all gradients. CPU time counts all threads: less sensitive to other processes.",
          "",
          md_table, ""]
    if "fwd_bwd_ms" in lin:
        fb, fw = lin["fwd_bwd_ms"], lin["fwd_ms"]
        md += [f"Linearity ({lin['points']} configurations of ours, incl. extra resolutions "
               f"{list(cfg.linearity_resolutions)}): forward+backward = "
               f"{fb['intercept_ms']:.1f} ms + {fb['slope_ns_per_pair']:.1f} ns/pair, "
               f"R^2 = {fb['r2']:.4f}; forward = {fw['intercept_ms']:.1f} ms + "
               f"{fw['slope_ns_per_pair']:.1f} ns/pair, R^2 = {fw['r2']:.4f}"
               + (f"; fwd+bwd CPU time R^2 = {lin['fwd_bwd_cpu_ms']['r2']:.4f}"
                  if "fwd_bwd_cpu_ms" in lin else "")
               + " (`raster_linearity.png`). Pairs: those kept after the alpha/cutoff tests "
               "and composited with AD (`box_pairs`, `contributing` in raster.csv).", ""]
    for res, target in ((128, 10.0), (256, 8.0)):
        if f"speedup_fwd_bwd_{res}_20k" in goals:
            md.append(f"- Goal fwd+bwd >= {target:.0f}x faster than Mitsuba at {res}^2/20k: "
                      f"{goals[f'speedup_fwd_bwd_{res}_20k']:.2f}x -> "
                      f"{'met' if goals[f'speedup_goal_{res}_met'] else 'NOT met'}")
    if "ours_peak_rss_mb_256_20k" in goals:
        md.append(f"- Goal peak RSS <= 256 MB at 256^2/20k: "
                  f"{goals['ours_peak_rss_mb_256_20k']:.0f} MB -> "
                  f"{'met' if goals['memory_goal_met'] else 'NOT met'}")
    bad = [r for r in rows if r.get("status") != "ok"]
    for r in bad:
        md.append(f"- {r['renderer']} {r['res']}^2 N={r['n']}: {r['status']} "
                  f"({r.get('error', '').strip().splitlines()[-1:] or ''})")
    write_text(out / "raster.md", "\n".join(md) + "\n")
    summary["markdown"] = "\n".join(md)
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--renderer", choices=RENDERERS, required=True)
    ap.add_argument("--n", type=int, required=True)
    ap.add_argument("--res", type=int, required=True)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="write the result row here (atomically)")
    ap.add_argument("--image", help="save the final render here as .npy")
    ap.add_argument("--no-stats", action="store_true",
                    help="skip the pair counts (their pass can take more memory than the "
                         "render)")
    ap.add_argument("--method", default=None, help="ours: RasterConfig.method "
                    "(pairs, tiles; default: RasterConfig's)")
    ap.add_argument("--tile-size", type=int, default=None,
                    help="ours, --method tiles: RasterConfig.tile_size")
    ap.add_argument("--threads", type=int, default=None,
                    help="Dr.Jit worker threads (default: all cores)")
    args = ap.parse_args(argv)
    if args.threads is not None:
        import drjit as dr

        dr.set_thread_count(args.threads)
    raster_config = None
    if args.method is not None or args.tile_size is not None:
        from mi_shadowgs.core.raster import RasterConfig

        over = {k: v for k, v in (("method", args.method), ("tile_size", args.tile_size))
                if v is not None}
        raster_config = RasterConfig(**over)
    row = run_case(args.renderer, args.n, args.res, args.warmup, args.iters, args.image,
                   args.seed, raster_config, stats=not args.no_stats)
    if args.json:
        write_json(args.json, row)
    json.dump(row, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
