"""Run every registered validation and gather their reports in one folder (``make validate``).

A validation is a function ``fn(out_dir: Path, quick: bool) -> dict`` that writes its files
into ``out_dir`` and returns a summary with a ``markdown`` entry. To add one, import it here
and give it a name in ``VALIDATIONS``::

    python -m validation.run_all --out validation-out [--quick] [--only visibility]
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.io.atomic import atomic_dir, write_json, write_text


def _visibility(out_dir: Path, quick: bool) -> dict:
    """Table 2 on ground-truth surfels, plus its stage-1 rows for the models the pipeline
    validation (run before it) trained, when there are any."""
    from . import visibility

    models = sorted((out_dir.parent / "pipeline").glob("*/run/geometry/model.ply"))
    datas = [m.parents[2] / "data" for m in models]
    return visibility.run(out_dir, quick=quick, model=models, data=datas)


def _pipeline(out_dir: Path, quick: bool) -> dict:
    from . import pipeline

    return pipeline.run(out_dir, quick=quick)


def _lowpass_drift(out_dir: Path, quick: bool) -> dict:
    from . import lowpass_drift

    return lowpass_drift.run(out_dir, quick=quick)


# name -> fn(out_dir, quick) -> {"markdown": ...}; each writes under out_dir/<name>/.
VALIDATIONS: dict[str, Callable[[Path, bool], dict]] = {
    "pipeline": _pipeline,  # stages 1-5 per scene: issues 4, 6, 7 and Tables 1 and 3
    "visibility": _visibility,  # after the pipeline: its stage-1 models get Table 2 rows
    "lowpass_drift": _lowpass_drift,  # does stage 1 keep a correct surface in place?
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Run the mi_shadowgs validations.")
    ap.add_argument("--out", required=True, help="output folder (replaced atomically)")
    ap.add_argument("--quick", action="store_true", help="small smoke runs")
    ap.add_argument("--only", action="append", choices=sorted(VALIDATIONS),
                    help="run only this validation (repeatable)")
    args = ap.parse_args(argv)
    chosen = args.only or list(VALIDATIONS)
    t0 = time.perf_counter()
    load0 = os.getloadavg()
    sections, failed = [], []
    with atomic_dir(args.out, overwrite=True) as tmp:
        for name in chosen:
            print(f"validation: {name}", flush=True)
            t = time.perf_counter()
            try:
                summary = VALIDATIONS[name](tmp / name, args.quick)
                sections.append(summary.get("markdown", f"## {name}\n(no summary)"))
            except Exception as exc:  # one broken stage must not hide the others' reports
                failed.append(name)
                sections.append(f"## {name}\nFAILED: {type(exc).__name__}: {exc}")
                print(f"validation {name} FAILED: {exc!r}", file=sys.stderr, flush=True)
            print(f"validation: {name} took {time.perf_counter() - t:.0f} s", flush=True)
        info = {"date_utc": datetime.datetime.now(datetime.timezone.utc)
                .strftime("%Y-%m-%d %H:%M UTC"), "cpu_count": os.cpu_count(),
                "loadavg_start": list(load0), "loadavg_end": list(os.getloadavg()),
                "wall_s": time.perf_counter() - t0, "quick": args.quick,
                "command": " ".join(["python", "-m", "validation.run_all", *sys.argv[1:]]),
                "failed": failed}
        write_json(tmp / "run.json", info)
        header = ["# Validation (latest run)", "", f"- Command: `{info['command']}`",
                  f"- Date: {info['date_utc']}; {info['wall_s'] / 60:.1f} min; "
                  f"{info['cpu_count']} cores, load {load0[0]:.2f} at start", ""]
        write_text(tmp / "README.md", "\n".join(header + sections) + "\n")
    print("\n\n".join(sections))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
