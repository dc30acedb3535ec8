"""The whole method on the synthetic scenes: paper Tables 1 and 3, with stage figures.

For the embedded default scene and, when ``../shared/data`` is present, the five asset
scenes (bunny, armadillo, hotdog, ficus substitute, toy-train substitute for Lego), it
generates the ``cpu-small`` dataset, runs ``mi-shadowgs run`` with the two ablations, and
tabulates stage 1 (issue 4), stage 2 (issue 6) and the decomposition/relighting metrics per
scene and on average (Tables 1 and 3)::

    python -m validation.pipeline --out OUT [--quick] [--scene NAME ...]

``--quick`` runs the default scene only. Each scene's dataset and run live under
``OUT/<scene>/`` and are resumed, not redone, on a second call.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MI_SHADOWGS_SHARED_DATA", REPO.parent / "shared" / "data"))
# scene name -> mesh path under shared/data/meshes (None: the embedded default scene)
SCENES = {
    "default": None,
    "bunny": "bunny/bunny.ply",
    "armadillo": "armadillo/armadillo.ply",
    "hotdog": "hotdog/hotdog.ply",
    "ficus": "ficus/ficus.ply",
    "toy_train": "toy_train/toy_train.ply",
}
TABLE_KEYS = ("albedo_psnr", "albedo_ssim", "albedo_lpips", "light_cosine", "shadow_iou",
              "relight_psnr", "relight_ssim", "relight_lpips", "relight_render_s")


def available_scenes() -> dict[str, Path | None]:
    out = {}
    for name, rel in SCENES.items():
        if rel is None:
            out[name] = None
        elif (SHARED_DATA / "meshes" / rel).is_file():
            out[name] = SHARED_DATA / "meshes" / rel
    return out


def make_dataset(name: str, mesh: Path | None, folder: Path) -> Path:
    """The scene's cpu-small dataset (kept when it is already complete and the same)."""
    from mi_shadowgs.dataset.generate import get_config
    from mi_shadowgs.dataset.writer import write_dataset
    from mi_shadowgs.scenes import scene_path

    data = folder / "data"
    if (data / "dataset.json").is_file():
        return data
    overrides = None if mesh is None else {"mesh": str(mesh)}
    write_dataset(scene_path("default" if mesh is None else "mesh"), data,
                  get_config("cpu-small"), "cpu-small", seed=0, progress=True,
                  overrides=overrides)
    return data


def run_scene(name: str, mesh: Path | None, out: Path) -> dict:
    from mi_shadowgs.pipeline import RunConfig, run_pipeline

    folder = out / name
    data = make_dataset(name, mesh, folder)
    t0 = time.perf_counter()
    summary = run_pipeline(data, folder / "run", RunConfig(ablations=True), progress=True)
    run = folder / "run"
    geo = json.loads((run / "geometry" / "metrics.json").read_text())
    seg = json.loads((run / "segmentation" / "segmentation.json").read_text())
    variants = {v: json.loads((run / "material" / v / "metrics.json").read_text())
                for v in ("full", "no_visibility", "no_segmentation")}
    return {"scene": name, "wall_s": time.perf_counter() - t0,
            "report": str(run / "report.html"), "geometry": geo,
            "segmentation": seg.get("metrics", {}), "segments": seg.get("k"),
            "variants": variants, "summary_title": summary.get("title")}


def markdown(rows: list[dict], command: str) -> str:
    lines = ["## Whole pipeline (paper Tables 1 and 3)", "",
             f"`{command}`; {time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores, "
             f"load average {os.getloadavg()[0]:.1f} at the end; llvm_ad_rgb; cpu-small.", "",
             "Stage 1 and 2 (test views):", "",
             "| scene | PSNR dB | median normal err deg | mask IoU | segments | ARI | mIoU |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        g, s = r["geometry"], r["segmentation"]
        lines.append(f"| {r['scene']} | {g['psnr']:.2f} | "
                     f"{g.get('normal_error_median_deg', float('nan')):.2f} | "
                     f"{g['mask_iou']:.4f} | {r['segments']} | {s.get('ari', float('nan')):.3f} "
                     f"| {s.get('miou', float('nan')):.3f} |")
    lines += ["", "Decomposition and relighting per variant (Table 1: full; Table 3: "
              "ablations); last row: mean over scenes:", "",
              "| scene | variant | albedo PSNR | albedo SSIM | albedo LPIPS | light cos | "
              "shadow IoU | relit PSNR | relit SSIM | relit LPIPS | relight s (32 views) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for variant in ("full", "no_visibility", "no_segmentation"):
        vals = []
        for r in rows:
            m = r["variants"][variant]
            vals.append([float("nan") if m.get(k) is None else m[k] for k in TABLE_KEYS])
            lines.append(f"| {r['scene']} | {variant} | " +
                         " | ".join(f"{v:.4g}" for v in vals[-1]) + " |")
        mean = np.nanmean(np.array(vals, dtype=np.float64), axis=0)
        lines.append(f"| **mean** | **{variant}** | " +
                     " | ".join(f"{v:.4g}" for v in mean) + " |")
    return "\n".join(lines) + "\n"


def run(out_dir: Path, quick: bool = False, scenes: list[str] | None = None,
        command: str = "python -m validation.pipeline") -> dict:
    """validation.run_all entry."""
    from mi_shadowgs.io.atomic import write_json, write_text

    out_dir = Path(out_dir)
    avail = available_scenes()
    chosen = ["default"] if quick else (scenes or list(avail))
    missing = [s for s in chosen if s not in avail]
    if missing:
        raise FileNotFoundError(f"scenes {missing} need meshes under {SHARED_DATA / 'meshes'}")
    rows = [run_scene(s, avail[s], out_dir) for s in chosen]
    md = markdown(rows, command)
    write_json(out_dir / "pipeline.json", rows)
    write_text(out_dir / "pipeline.md", md)
    return {"rows": rows, "markdown": md}


def main(argv=None) -> int:
    import sys

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="output folder (datasets, runs, tables)")
    ap.add_argument("--quick", action="store_true", help="the default scene only")
    ap.add_argument("--scene", action="append", choices=sorted(SCENES),
                    help="run only this scene (repeatable)")
    args = ap.parse_args(argv)
    res = run(Path(args.out), args.quick, args.scene,
              "python -m validation.pipeline " + " ".join(argv or sys.argv[1:]))
    print(res["markdown"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
