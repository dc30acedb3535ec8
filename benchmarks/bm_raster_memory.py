"""Peak memory of the rasterizer per pixel-splat pair (sets RasterConfig.bytes_per_pair).

Each case runs in a fresh subprocess: N surfels with standard deviations of 1e6 (every
surfel's box is the whole image, so the pair list holds exactly N * H * W pairs, all kept)
are rendered once, forward only or forward + backward over every AOV, and the process's
peak RSS growth is recorded. A least-squares line over the cases gives bytes per pair
(slope) and a fixed cost (intercept: kernel compilation, per-pixel images). The last cases
render the same model through ``mi-shadowgs render --memory-budget`` and record peak RSS
against the budget::

    python -m benchmarks.bm_raster_memory [--quick] [--method tiles]

``--method tiles``: the tiled renderer (``RasterConfig.method``); its memory grows with the
surfel-tile pairs (N * (RES / tile_size)^2 here), which the fit uses instead of the pixel
pairs (sets ``RasterConfig.bytes_per_tile_pair``); no budget cases.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RES = 128
SIZES = (100, 250, 500, 1000, 1500, 2000)  # surfels: 1.6M .. 33M pairs at 128^2
QUICK_SIZES = (100, 500, 1000)
# The last is the issue-12 case (20k surfels of scale 1e6: 21.7 GB before the guard).
BUDGET_CASES = ((2000, "400M"), (2000, "1G"), (20000, "2G"))
MODES = ("fwd", "fwd+bwd")


def _model(n: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {"position": rng.uniform(-0.5, 0.5, (n, 3)), "scale": np.full((n, 2), 1e6),
            "rotation": rng.normal(size=(n, 4)), "opacity": np.full(n, 0.05),
            "colors": rng.uniform(0.0, 1.0, (n, 3))}


def _camera(res: int):
    from mi_shadowgs.core.camera import Camera

    return Camera.look_at((0.3, 0.4, 2.5), (0.0, 0.0, 0.0), width=res, height=res, fov_x=0.8)


def run_case(n: int, res: int, mode: str, method: str = "pairs") -> dict:
    """In this process: render once, return pairs and RSS figures (bytes)."""
    from mi_shadowgs import backend
    from mi_shadowgs.core import memory

    backend.set_variant(None)
    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.core.raster import AOV_CHANNELS, RasterConfig, rasterize
    from mi_shadowgs.core.surfels import Surfels

    m = _model(n)
    s = Surfels.from_numpy(m["position"], m["scale"], m["rotation"], m["opacity"])
    colors = mi.TensorXf(m["colors"].astype(np.float32))
    dr.eval(s.position, s.log_scale, s.rotation, s.opacity_logit, colors)
    base = memory.resident_bytes()
    t0 = time.perf_counter()
    if mode == "fwd+bwd":
        params = [*s.params().values(), colors]
        for v in params:
            dr.enable_grad(v)
    aovs = tuple(AOV_CHANNELS) if mode == "fwd+bwd" else ("alpha",)
    config = RasterConfig(method=method)
    out = rasterize(s, _camera(res), {"rgb": colors}, aovs=aovs, config=config)
    if mode == "fwd+bwd":
        dr.backward(sum((dr.sum(v.array) for k, v in out.items() if k != "count"),
                        mi.Float(0.0)))
        dr.eval(*(dr.grad(v) for v in params))
    else:
        dr.eval(*(v.array for v in out.values()))
    dr.sync_thread()
    peak = memory.peak_resident_bytes() or \
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # see peak_resident_bytes
    tiles = (-(-res // config.tile_size)) ** 2  # ceil(res / tile_size)^2
    return {"n": n, "res": res, "mode": mode, "method": method, "pairs": n * res * res,
            "tile_pairs": n * tiles, "base": base, "peak": peak, "growth": peak - base,
            "seconds": time.perf_counter() - t0}


def _subprocess_case(n: int, res: int, mode: str, method: str = "pairs") -> dict:
    out = subprocess.run([sys.executable, "-m", "benchmarks.bm_raster_memory", "--case",
                          str(n), str(res), mode, "--method", method], capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def budget_case(n: int, res: int, budget: str, folder: Path) -> dict:
    """``mi-shadowgs render --memory-budget`` of the 1e6-scale model: exit code, peak RSS."""
    from mi_shadowgs.core.memory import parse_bytes
    from mi_shadowgs.io import ply

    m = _model(n)
    logit = np.log(m["opacity"]) - np.log1p(-m["opacity"])
    model = ply.PlyModel(position=m["position"].astype(np.float32),
                         log_scale=np.log(m["scale"]).astype(np.float32),
                         rotation=m["rotation"].astype(np.float32),
                         opacity_logit=logit.astype(np.float32),
                         channels={"sh": m["colors"].astype(np.float32)})
    ply.write_ply_model(folder / "big.ply", model)
    cam = _camera(res)
    meta = {"camera_angle_x": cam.fov_x, "w": res, "h": res, "world_up": "+y",
            "frames": [cam.to_frame_json("./test/r_0")]}
    (folder / "t.json").write_text(json.dumps(meta))
    code = ("import resource, subprocess, sys; "
            "rc = subprocess.run(sys.argv[1:], capture_output=True).returncode; "
            "print(rc, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024)")
    cli = Path(sys.executable).with_name("mi-shadowgs")
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code, str(cli), "render",
                          str(folder / "big.ply"), "--cameras", str(folder / "t.json"), "--out",
                          str(folder / f"out_{budget}"), "--memory-budget", budget],
                         capture_output=True, text=True, check=True).stdout.split()
    return {"n": n, "res": res, "pairs": n * res * res, "budget": parse_bytes(budget, "budget"),
            "budget_text": budget, "rc": int(out[0]), "peak": int(out[1]),
            "seconds": time.perf_counter() - t0}


def run_suite(out: Path, preset: str = "paper", log=print, method: str = "pairs") -> dict:
    sizes = QUICK_SIZES if preset == "cpu-small" else SIZES
    rows, fits = [], {}
    per = "pairs" if method == "pairs" else "tile_pairs"  # what the memory grows with
    for mode in MODES:
        for n in sizes:
            row = _subprocess_case(n, RES, mode, method)
            rows.append(row)
            log(f"[raster_memory] {method} {mode:8s} n={n:5d} {per}={row[per]:9d} "
                f"growth={row['growth'] / 2**20:7.1f} MiB ({row['seconds']:.1f} s)")
        sel = [r for r in rows if r["mode"] == mode]
        slope, icpt = np.polyfit([r[per] for r in sel], [r["growth"] for r in sel], 1)
        fits[mode] = {"bytes_per_pair": float(slope), "fixed_bytes": float(icpt),
                      "max_growth_per_pair": max(r["growth"] / r[per] for r in sel)}
    budgets = []
    with tempfile.TemporaryDirectory() as tmp:
        for n, budget in (BUDGET_CASES if method == "pairs" else ()):
            b = budget_case(n, RES, budget, Path(tmp))
            budgets.append(b)
            log(f"[raster_memory] render --memory-budget {budget}: rc {b['rc']}, peak "
                f"{b['peak'] / 2**20:.0f} MiB ({b['seconds']:.1f} s)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "raster_memory.json").write_text(json.dumps({"cases": rows, "fits": fits,
                                                        "budget_cases": budgets}, indent=1))
    md = [f"## Rasterizer memory per {'pixel-splat' if method == 'pairs' else 'surfel-tile'}"
          f" pair (method {method})", "",
          f"Peak RSS growth of one {RES}x{RES} render of N surfels of scale 1e6 (N * {RES}^2 "
          "pairs, all kept), fresh process per case; line fit over the cases.", "",
          "| mode | bytes/pair (slope) | fixed (MiB) | max growth/pair |", "|---|---|---|---|"]
    for mode, f in fits.items():
        md.append(f"| {mode} | {f['bytes_per_pair']:.1f} | {f['fixed_bytes'] / 2**20:.1f} | "
                  f"{f['max_growth_per_pair']:.1f} |")
    md += ["", "| `render --memory-budget` | pairs | exit | peak RSS (MiB) | budget (MiB) | s |",
           "|---|---|---|---|---|---|"]
    for b in budgets:
        md.append(f"| {b['budget_text']} | {b['pairs']} | {b['rc']} | {b['peak'] / 2**20:.0f} "
                  f"| {b['budget'] / 2**20:.0f} | {b['seconds']:.1f} |")
    return {"fits": fits, "budget_cases": budgets, "markdown": "\n".join(md)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", nargs=3, metavar=("N", "RES", "MODE"),
                    help="run one case in this process and print its JSON")
    ap.add_argument("--quick", action="store_true", help="fewer sizes")
    ap.add_argument("--method", default="pairs", help="RasterConfig.method (pairs, tiles)")
    args = ap.parse_args(argv)
    if args.case:
        n, res, mode = int(args.case[0]), int(args.case[1]), args.case[2]
        print(json.dumps(run_case(n, res, mode, args.method)))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_suite(Path(tmp), "cpu-small" if args.quick else "paper",
                            method=args.method)
    print(summary["markdown"])
    print(f"\n{os.cpu_count()} cores; command: python -m benchmarks.bm_raster_memory"
          f"{' --quick' if args.quick else ''} --method {args.method}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
