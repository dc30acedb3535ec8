"""How many training views the method needs: the whole run on subsets of one dataset
(the threshold of ``stages.common.MIN_TRAIN_VIEWS``).

For each N of ``--views``, ``OUT/data-N`` is a copy of ``DATA`` whose training split keeps N
views spread around the object (farthest-point sampling of the camera centres, from view
0); the test split, lights and env maps are unchanged, so every N is scored against the
same ground truth. ``mi-shadowgs run`` (the preset's settings) goes into ``OUT/run-N``,
and the table gathers stage 1 (test PSNR, normal error), stage 2 (ARI) and stage 5
(albedo PSNR, light cosine, shadow IoU, relight PSNR)::

    python -m validation.view_count --data DATA --out OUT [--views 2 4 8 16 32]
        [--preset cpu-small] [--full RUN] [--threads N]

``--full RUN`` adds an existing run on all of DATA's views as a row. Finished runs are
reused. Writes ``OUT/view_count.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from validation import claim_out, fail

# (label, file under the run, key): the figures of a row
FIGURES = (("test PSNR", "geometry/metrics.json", "psnr"),
           ("normal err deg", "geometry/metrics.json", "normal_error_median_deg"),
           ("ARI", "segmentation/segmentation.json", "ari"),
           ("albedo PSNR", "material/full/metrics.json", "albedo_psnr"),
           ("light cos", "material/full/metrics.json", "light_cosine"),
           ("shadow IoU", "material/full/metrics.json", "shadow_iou"),
           ("relight PSNR", "material/full/metrics.json", "relight_psnr"))


def spread_views(centres: np.ndarray, n: int) -> list[int]:
    """``n`` indices of ``centres`` [M, 3] by farthest-point sampling from index 0 (the
    directions from their centroid), in the order chosen."""
    d = centres - centres.mean(axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    chosen = [0]
    dist = np.linalg.norm(d - d[0], axis=1)
    while len(chosen) < min(n, len(d)):
        i = int(np.argmax(dist))
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(d - d[i], axis=1))
    return chosen


def subset_copy(src: Path, dst: Path, n: int) -> Path:
    """``dst``: ``src`` with its training split cut to ``n`` spread views (kept when done)."""
    from mi_shadowgs.dataset import layout
    from mi_shadowgs.io.atomic import atomic_dir

    if dst.is_dir():
        return dst
    tname = layout.transforms_name("train")
    meta = json.loads((src / tname).read_text())
    frames = meta["frames"]
    if n > len(frames):
        fail(f"--views {n}: {src / tname} has only {len(frames)} training views")
    centres = np.array([np.asarray(f["transform_matrix"], np.float64)[:3, 3] for f in frames])
    keep = [frames[i] for i in sorted(spread_views(centres, n))]
    stems = {Path(f["file_path"]).name for f in keep}
    with atomic_dir(dst) as tmp:
        for f in sorted(src.iterdir()):
            if f.name.startswith(".mi_shadowgs"):
                continue  # generate's manifest describes the original, not this copy
            if f.is_file() and f.name != tname:
                shutil.copy2(f, tmp / f.name)
            elif f.is_dir() and f.name != "train":
                shutil.copytree(f, tmp / f.name)
        (tmp / tname).write_text(json.dumps({**meta, "frames": keep}, indent=1))
        (tmp / "train").mkdir()
        for f in sorted((src / "train").iterdir()):
            # a view's files are "<stem>.<ext>" and "<stem>_<buffer>.<ext>"
            if any(f.name.startswith((s + ".", s + "_")) for s in stems):
                shutil.copy2(f, tmp / "train" / f.name)
    return dst


def row(n: int, run: Path) -> dict:
    out = {"views": n, "run": str(run)}
    for label, rel, key in FIGURES:
        rec = json.loads((run / rel).read_text())
        rec = rec.get("metrics", rec) if rel.startswith("segmentation") else rec
        out[label] = rec.get(key)
    out["segments"] = json.loads((run / "segmentation" / "segmentation.json").read_text()
                                 ).get("k")
    out["stage_s"] = {s["name"]: s.get("seconds") for s in json.loads(
        (run / "summary.json").read_text()).get("stages", [])}
    return out


def markdown(rows: list[dict]) -> str:
    labels = [f[0] for f in FIGURES]
    lines = ["| training views | " + " | ".join(labels) + " | segments |",
             "|" + "---|" * (len(labels) + 2)]
    for r in rows:
        cells = ["-" if r[k] is None else f"{r[k]:.3f}" if abs(r[k]) < 2 else f"{r[k]:.2f}"
                 for k in labels]
        lines.append(f"| {r['views']} | " + " | ".join(cells) + f" | {r['segments']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--views", type=int, nargs="+", default=[2, 4, 8, 16, 32])
    ap.add_argument("--preset", default="cpu-small")
    ap.add_argument("--full", default=None, help="a finished run on all of DATA's views")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    claim_out(args.out, "validation.view_count", ('view_count.json',))
    import drjit as dr

    from mi_shadowgs.io.atomic import write_json, write_text
    from mi_shadowgs.pipeline import run_pipeline
    from mi_shadowgs.presets import get_config

    if args.threads:
        dr.set_thread_count(args.threads)
    data, out = Path(args.data), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for n in sorted(args.views):
        sub = subset_copy(data, out / f"data-{n}", n)
        run_pipeline(sub, out / f"run-{n}", get_config(args.preset), progress=True)
        rows.append(row(n, out / f"run-{n}"))
    if args.full:
        meta = json.loads((data / "transforms_train.json").read_text())
        rows.append(row(len(meta["frames"]), Path(args.full)))
    write_json(out / "view_count.json", rows)
    md = markdown(rows)
    write_text(out / "view_count.md", md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
