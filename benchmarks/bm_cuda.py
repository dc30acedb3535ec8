"""The GPU suite (``make bench`` on a machine with an NVIDIA GPU): ``cuda_ad_rgb`` against
``llvm_ad_rgb`` on the same machine. Without a GPU it records that it was skipped, and why.

- **CUDA tests**: ``pytest -m cuda`` (each compares cuda_ad_rgb with llvm_ad_rgb).
- **Rasterizer**: one training step of ``benchmarks.bm_raster`` per case, ours on cuda and on
  llvm (all cores), Mitsuba's ``ellipsoids`` + ``volprim_rf_basic`` on cuda; one process each.
- **The whole method**: the default scene generated once (cpu-small), then ``mi-shadowgs run``
  on each backend, with its wall time and stage 5's figures.

Every process gets an empty Dr.Jit kernel cache (``bm_raster.run_subprocess``), so both
backends pay their JIT compilation alike.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mi_shadowgs.config import get_preset
from mi_shadowgs.io.atomic import write_json

from .bm_raster import case_cmd, run_subprocess

BACKENDS = ("cuda_ad_rgb", "llvm_ad_rgb")
# (renderer, variant) of each rasterizer case, in run order.
RASTER_RUNS = (("ours", "cuda_ad_rgb"), ("ours", "llvm_ad_rgb"), ("mitsuba", "cuda_ad_rgb"))
RUN_FIGURES = ("albedo_psnr", "light_cosine", "shadow_iou", "relight_psnr")


@dataclasses.dataclass(frozen=True)
class CudaBenchConfig:
    raster_cases: tuple[tuple[int, int], ...] = ((20_000, 256), (100_000, 512), (300_000, 800))
    warmup: int = 2
    iters: int = 9
    whole_run: bool = True  # the default scene, generated and run at run_preset
    run_preset: str = "cpu-small"
    case_timeout_s: float = 300.0
    run_timeout_s: float = 1800.0


PRESETS = {"paper": CudaBenchConfig(),
           "cpu-small": CudaBenchConfig(raster_cases=((20_000, 256),), iters=5,
                                        whole_run=False)}


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "mi_shadowgs.cli", *args]


def cuda_tests(log) -> dict:
    """``pytest -m cuda`` from the repository root: its last line and exit status."""
    root = Path(__file__).resolve().parent.parent
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-m", "cuda", "tests"],
                          cwd=root, capture_output=True, text=True)
    lines = proc.stdout.strip().splitlines()
    result = {"returncode": proc.returncode, "summary": lines[-1] if lines else ""}
    log(f"[cuda] tests: {result['summary']}")
    return result


def raster_rows(cfg: CudaBenchConfig, raw: Path, log) -> list[dict]:
    rows = []
    for n, res in cfg.raster_cases:
        for renderer, variant in RASTER_RUNS:
            path = raw / f"{renderer}_{variant}_{res}_{n}.json"
            status, err = run_subprocess(case_cmd(renderer, n, res, cfg, path),
                                         cfg.case_timeout_s, env={"MI_SHADOWGS_VARIANT": variant})
            row = json.loads(path.read_text()) if status == "ok" else {"error": err}
            row.update(renderer=renderer, variant=variant, n=n, res=res, status=status)
            rows.append(row)
            log(f"[cuda] {renderer:7s} {variant:11s} {res}^2 n={n}: "
                + (f"{row['fwd_bwd_ms']:.2f} ms fwd+bwd" if status == "ok" else status))
    return rows


def whole_runs(cfg: CudaBenchConfig, log) -> list[dict]:
    """The default scene (cpu-small), generated once; the whole method on each backend."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="bm_cuda_") as tmp:
        data = Path(tmp) / "data"
        status, err = run_subprocess(_cli("generate", "default", "--out", str(data),
                                          "--preset", cfg.run_preset, "--no-progress"),
                                     cfg.run_timeout_s)
        if status != "ok":
            return [{"variant": "generate", "status": status, "error": err}]
        for variant in BACKENDS:
            run = Path(tmp) / f"run_{variant}"
            t0 = time.perf_counter()
            status, err = run_subprocess(
                _cli("--variant", variant, "run", str(data), "--out", str(run), "--preset",
                     cfg.run_preset, "--no-progress"), cfg.run_timeout_s)
            row = {"variant": variant, "status": status, "wall_s": time.perf_counter() - t0}
            if status == "ok":
                metrics = json.loads((run / "material" / "full" / "metrics.json").read_text())
                row.update({k: metrics.get(k) for k in RUN_FIGURES})
            else:
                row["error"] = err
            rows.append(row)
            log(f"[cuda] run on {variant}: {status}, {row['wall_s']:.1f} s")
    return rows


def _find(rows: list[dict], **key) -> dict | None:
    return next((r for r in rows if all(r.get(k) == v for k, v in key.items())
                 and r.get("status") == "ok"), None)


def markdown(result: dict) -> str:
    """The suite's section: the tests, the rasterizer table with its ratios, the runs."""
    lines = ["## cuda_ad_rgb against llvm_ad_rgb", ""]
    if result.get("skipped"):
        return "\n".join(lines + [f"Skipped: {result['skipped']}"]) + "\n"
    lines += [f"CUDA tests (`pytest -m cuda`): {result['tests']['summary']}", "",
              "One rasterizer training step (medians, ms fwd+bwd):", "",
              "| workload | ours cuda | ours llvm | Mitsuba cuda | cuda vs llvm | "
              "ours vs Mitsuba (cuda) |", "|---|---|---|---|---|---|"]

    def ms(row):
        return f"{row['fwd_bwd_ms']:.2f}" if row else "failed"

    def ratio(num, den):
        return f"{num['fwd_bwd_ms'] / den['fwd_bwd_ms']:.1f}x" if num and den else "-"

    cases = sorted({(r["n"], r["res"]) for r in result["raster"]}, key=lambda c: (c[1], c[0]))
    for n, res in cases:
        ours, llvm, peer = (_find(result["raster"], renderer=r, variant=v, n=n, res=res)
                            for r, v in RASTER_RUNS)
        lines.append(f"| {res}^2, {n} surfels | {ms(ours)} | {ms(llvm)} | {ms(peer)} | "
                     f"{ratio(llvm, ours)} | {ratio(peer, ours)} |")
    if result.get("runs"):
        lines += ["", "The whole method, default scene (`mi-shadowgs run`):", "",
                  "| backend | wall s | albedo PSNR | light cos | shadow IoU | relight PSNR |",
                  "|---|---|---|---|---|---|"]
        for r in result["runs"]:
            if r["status"] != "ok":
                lines.append(f"| {r['variant']} | {r['status']} | | | | |")
                continue
            lines.append(f"| {r['variant']} | {r['wall_s']:.1f} | " + " | ".join(
                "n/a" if r.get(k) is None else f"{r[k]:.4g}" for k in RUN_FIGURES) + " |")
    return "\n".join(lines) + "\n"


def run_suite(out: Path, preset: str = "paper", log=print) -> dict:
    from mi_shadowgs import backend

    cfg = get_preset(PRESETS, preset, "CUDA benchmark")
    out = Path(out)
    if not backend.variant_available("cuda_ad_rgb"):
        result = {"skipped": "cuda_ad_rgb needs an NVIDIA GPU and its driver; this machine "
                             "has none"}
        log(f"[cuda] skipped: {result['skipped']}")
    else:
        raw = out / "cuda_raw"
        raw.mkdir(parents=True, exist_ok=True)
        result = {"tests": cuda_tests(log), "raster": raster_rows(cfg, raw, log),
                  "runs": whole_runs(cfg, log) if cfg.whole_run else []}
    write_json(out / "cuda.json", result)
    return {**result, "markdown": markdown(result)}
