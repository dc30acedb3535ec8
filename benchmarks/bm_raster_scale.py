"""The rasterizer at capture resolutions: fwd+bwd of 200k surfels at 512^2 and 800^2.

Each case is one ``benchmarks.bm_raster`` process (the shared sphere-on-plane workload,
our default ``RasterConfig``, gradients of every parameter) run without the pair-count
statistics pass, so that the process's peak RSS (``ru_maxrss`` of the child, imports and
workload included) is the render's. The goal is each under 2 GB::

    python -m benchmarks.bm_raster_scale [--quick]

The 1e6-scale model through ``mi-shadowgs render --memory-budget`` is a case of
``bm_raster_memory``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CASES = ((512, 200_000), (800, 200_000))
QUICK_CASES = ((256, 50_000),)
PEAK_LIMIT_BYTES = 2 << 30  # each case under 2 GB peak
ITERS, WARMUP = 5, 1


def run_case(res: int, n: int, folder: Path, iters: int = ITERS,
             warmup: int = WARMUP) -> dict:
    """One case in a fresh process: bm_raster's row plus the child's peak RSS (bytes)."""
    row_path = folder / f"scale_{res}_{n}.json"
    code = ("import resource, subprocess, sys; "
            "rc = subprocess.run(sys.argv[1:]).returncode; "
            "print(rc, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024)")
    cmd = [sys.executable, "-m", "benchmarks.bm_raster", "--renderer", "ours", "--n", str(n),
           "--res", str(res), "--iters", str(iters), "--warmup", str(warmup), "--no-stats",
           "--json", str(row_path)]
    root = Path(__file__).resolve().parent.parent
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code, *cmd], cwd=root, capture_output=True,
                         text=True, check=True)
    rc, peak = (int(v) for v in out.stdout.split()[-2:])
    row = json.loads(row_path.read_text()) if rc == 0 else {"error": out.stderr[-2000:]}
    return {"res": res, "n": n, "rc": rc, "peak_bytes": peak, "wall_s": time.perf_counter() - t0,
            **{k: row.get(k) for k in ("method", "tile_size", "fwd_ms", "fwd_bwd_ms",
                                       "fwd_bwd_ms_all", "first_ms", "load1_start", "error")}}


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.0f}"


def run_suite(out: Path, preset: str = "paper", log=print) -> dict:
    cases = QUICK_CASES if preset == "cpu-small" else CASES
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for res, n in cases:
            r = run_case(res, n, Path(tmp))
            rows.append(r)
            log(f"[raster_scale] {res}^2 n={n}: rc {r['rc']}, fwd {r['fwd_ms']} ms, "
                f"fwd+bwd {r['fwd_bwd_ms']} ms, peak {r['peak_bytes'] / 2**20:.0f} MiB "
                f"({r['wall_s']:.1f} s)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "raster_scale.json").write_text(json.dumps(rows, indent=1))
    md = ["## The rasterizer at capture resolutions", "",
          "fwd+bwd of the shared workload (gradients of every parameter), one fresh process "
          f"per case, median of {ITERS} steps after {WARMUP} warm-up; peak RSS of the whole "
          f"process; limit {PEAK_LIMIT_BYTES / 2**30:.0f} GiB.", "",
          "| res | surfels | method (tile) | fwd ms | fwd+bwd ms | first step ms | peak RSS MiB "
          "| under the limit |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ok = r["rc"] == 0 and r["peak_bytes"] < PEAK_LIMIT_BYTES
        md.append(f"| {r['res']}^2 | {r['n']:,} | {r['method']} ({r['tile_size']}) | "
                  f"{_fmt(r['fwd_ms'])} | {_fmt(r['fwd_bwd_ms'])} | {_fmt(r['first_ms'])} | "
                  f"{r['peak_bytes'] / 2**20:.0f} | {'yes' if ok else 'NO'} |")
    return {"cases": rows, "markdown": "\n".join(md)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one small case")
    ap.add_argument("--out", default=None, help="write raster_scale.json here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        res = run_suite(Path(args.out or tmp), "cpu-small" if args.quick else "paper")
    print(res["markdown"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
