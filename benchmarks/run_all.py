"""Run every benchmark suite and write its figures into one folder (``make bench``).

Each ``benchmarks/bm_*.py`` module that defines ``run_suite(out, preset, log) -> dict``
(with a ``markdown`` entry) is a suite. The folder is built beside ``--out`` and moved into
place when every suite has run, so a reader never sees a half-written report::

    python -m benchmarks.run_all --out BENCHMARKS-latest [--quick] [--only raster]
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import os
import pkgutil
import platform
import subprocess
import sys
import time
from pathlib import Path

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.io.atomic import atomic_dir, check_replaceable, write_json, write_text


def discover_suites() -> dict[str, object]:
    """name (module name without ``bm_``) -> module, for every bm_* module with run_suite."""
    import benchmarks

    suites = {}
    for info in sorted(pkgutil.iter_modules(benchmarks.__path__), key=lambda i: i.name):
        if info.name.startswith("bm_"):
            module = importlib.import_module(f"benchmarks.{info.name}")
            if hasattr(module, "run_suite"):
                suites[info.name[3:]] = module
    return suites


def machine_info() -> dict:
    """What a reader needs to compare figures: CPU, cores, load, library versions, date."""
    import drjit
    import mitsuba

    model = platform.processor() or "unknown"
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                model = line.split(":", 1)[1].strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu_model": model,
        "cpu_count": os.cpu_count(),
        "loadavg_start": list(os.getloadavg()),
        "python": platform.python_version(),
        "mitsuba": mitsuba.__version__,
        "drjit": drjit.__version__,
        "variant": mitsuba.variant(),
        "command": " ".join([Path(sys.executable).name, "-m", "benchmarks.run_all",
                             *sys.argv[1:]]),
    }


def main(argv=None) -> int:
    suites = discover_suites()
    ap = argparse.ArgumentParser(description="Run the mi_shadowgs benchmarks.")
    ap.add_argument("--out", required=True, help="output folder: new or an earlier "
                    "benchmark run's (replaced atomically)")
    ap.add_argument("--quick", action="store_true",
                    help="reduced sweep (the cpu-small presets) for a fast check")
    ap.add_argument("--only", action="append", choices=sorted(suites),
                    help="run only this suite (repeatable)")
    args = ap.parse_args(argv)
    try:
        check_replaceable(args.out, "machine.json")
    except FileExistsError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    preset = "cpu-small" if args.quick else "paper"
    chosen = args.only or sorted(suites)
    info = machine_info()
    info["preset"] = preset
    print(f"benchmarks: {', '.join(chosen)} ({preset}) on {info['cpu_model']}, "
          f"{info['cpu_count']} cores, load {info['loadavg_start']}", flush=True)
    t0 = time.perf_counter()
    sections = []
    with atomic_dir(args.out, overwrite=True) as tmp:
        for name in chosen:
            summary = suites[name].run_suite(
                tmp, preset=preset, log=lambda msg: print(msg, flush=True))
            sections.append(summary.get("markdown", f"## {name}\n(no summary)"))
        info["loadavg_end"] = list(os.getloadavg())
        info["wall_s"] = time.perf_counter() - t0
        write_json(tmp / "machine.json", info)
        header = [
            "# Benchmarks (latest run)", "",
            f"- Command: `{info['command']}`",
            f"- Date: {info['date_utc']}; total {info['wall_s'] / 60:.1f} min",
            f"- Machine: {info['cpu_model']}, {info['cpu_count']} cores; load average "
            f"{info['loadavg_start'][0]:.2f} at start, {info['loadavg_end'][0]:.2f} at end "
            "(above ~0.5 means other processes shared the cores)",
            f"- Mitsuba {info['mitsuba']}, Dr.Jit {info['drjit']}, {info['variant']}, "
            f"Python {info['python']}", "",
        ]
        write_text(tmp / "README.md", "\n".join(header + sections) + "\n")
    print("\n".join(sections))
    print(f"benchmarks: wrote {args.out} in {(time.perf_counter() - t0) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
