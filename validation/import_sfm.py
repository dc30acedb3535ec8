"""SfM accuracy and speed of ``mi-shadowgs import`` on the generator's photo sets.

A photo set (``generate ... --photos -D base_texture=mat``) is imported ``--repeats`` times;
each import's cameras are compared with the ground truth by photo name: registered
fraction, camera-centre RMS after a similarity alignment as % of the camera distance,
rotation error, the world frame (tilt and scale of that similarity) and the import's
timings. The first import's COLMAP model is then imported again with ``--colmap`` and its
cameras compared with the first import's. Without ``--data`` a photo set is generated
first (``--mesh`` on the mat).

    python -m validation.import_sfm --out OUT [--data DATA] [--repeats 3] [--size 512]
        [--views 64] [--mesh PATH]

Writes (atomically) ``OUT/import_sfm.json`` and ``OUT/import_sfm.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.io.atomic import write_json, write_text
from validation import claim_out


def cameras_by_photo(data: Path) -> dict:
    """Photo name -> camera of every registered view of an import (both splits)."""
    from mi_shadowgs.dataset.loader import load_cameras

    cams = {}
    for split in ("train", "test"):
        meta = json.loads((data / f"transforms_{split}.json").read_text())
        for (_, cam), fr in zip(load_cameras(data / f"transforms_{split}.json"),
                                meta["frames"], strict=True):
            cams[fr.get("source_image", f"{split}_{len(cams):03d}.jpg")] = cam
    return cams


def truth(data: Path) -> dict:
    from mi_shadowgs.dataset import layout
    from mi_shadowgs.dataset.loader import load_cameras

    return {layout.photo_name(s, i): c for s in layout.SPLITS
            for i, (_, c) in enumerate(load_cameras(data / layout.transforms_name(s)))}


def score(imported: Path, gt: dict) -> dict:
    from mi_shadowgs.dataset.world_frame import camera_errors, umeyama

    cams = cameras_by_photo(imported)
    names = sorted(cams)
    est = np.stack([cams[n].c2w for n in names])
    ref = np.stack([gt[n].c2w for n in names])
    err = camera_errors(est, ref)
    sim = umeyama(est[:, :3, 3], ref[:, :3, 3])
    err["frame_tilt_deg"] = float(np.degrees(np.arccos(np.clip(sim.rotation[1, 1], -1, 1))))
    err["frame_scale"] = sim.scale
    err["frame_y_offset"] = float(sim.translation[1])
    return err


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--data", default=None, help="a generated dataset with photos/")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--views", type=int, default=64)
    parser.add_argument("--mesh", default=None, help="an asset mesh (default scene if none)")
    parser.add_argument("--preset", default="cpu-small")
    args = parser.parse_args(argv)
    claim_out(args.out, "validation.import_sfm", ('import_sfm.json', 'import_0'))
    from mi_shadowgs.dataset.importer import import_capture
    from mi_shadowgs.dataset.sfm import sfm_work_folder
    from mi_shadowgs.dataset.writer import write_dataset
    from mi_shadowgs.presets import generate_config as gen_config
    from mi_shadowgs.presets import import_config as get_config
    from mi_shadowgs.scenes import scene_path

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = Path(args.data) if args.data else out / "photoset"
    if args.data is None:
        cfg = gen_config("cpu-small")
        n_test = max(1, args.views // 16)
        cfg = type(cfg)(**{**cfg.__dict__, "width": args.size, "height": args.size,
                           "n_train": args.views - n_test, "n_test": n_test, "spp": 64,
                           "envmaps": "none"})  # SfM needs no relit views
        over = {"base_texture": "mat"}
        if args.mesh:
            over["mesh"] = args.mesh
        write_dataset(scene_path("mesh" if args.mesh else "default"), data, cfg, "cpu-small",
                      seed=1, overrides=over, photos=True)
    gt = truth(data)
    runs = []
    for r in range(args.repeats):
        target, row_file = out / f"import_{r}", out / f"import_{r}.json"
        if row_file.is_file() and (target / "import.json").is_file():  # done before a kill
            runs.append(json.loads(row_file.read_text()))
            continue
        # Each repeat is timed whole: no earlier import's folder or SfM work is resumed.
        shutil.rmtree(target, ignore_errors=True)
        shutil.rmtree(sfm_work_folder(target), ignore_errors=True)
        t = time.perf_counter()
        rec = import_capture(data / "photos", target, get_config(args.preset))
        wall = time.perf_counter() - t
        row = {"run": r, "registered": len(rec["registered"]), "photos": len(gt),
               "points": rec["points"],
               "reprojection_px": rec["mean_reprojection_error_px"],
               "timings": rec["timings"], "wall_s": wall, **score(target, gt)}
        write_json(row_file, row)
        runs.append(row)
        print(json.dumps(row))
    # The COLMAP model the first import wrote, imported again with --colmap: same cameras?
    again = out / "import_colmap"
    shutil.rmtree(again, ignore_errors=True)
    rec = import_capture(data / "photos", again, get_config(args.preset),
                         colmap=out / "import_0" / "colmap" / "sparse" / "0")
    a, b = cameras_by_photo(out / "import_0"), cameras_by_photo(again)
    colmap_check = {
        "same_views": sorted(a) == sorted(b),
        "max_c2w_diff": max(float(np.abs(a[n].c2w - b[n].c2w).max()) for n in a),
        "max_intrinsics_diff_px": max(float(np.abs(np.subtract(
            a[n].focal_xy + a[n].principal_point, b[n].focal_xy + b[n].principal_point)).max())
            for n in a),
        "timings": rec["timings"]}
    print(json.dumps(colmap_check))
    summary = {"data": str(data.resolve()), "preset": args.preset, "runs": runs,
               "colmap_again": colmap_check,
               "loadavg": Path("/proc/loadavg").read_text().split()[:3]}
    write_json(out / "import_sfm.json", summary)
    lines = ["| run | registered | points | reproj px | centre RMS % | rot mean / RMS / max deg | "
             "tilt deg | scale | extract / match / map s | total s |", "|" + "---|" * 10]
    for r in runs:
        t = r["timings"]
        lines.append(
            f"| {r['run']} | {r['registered']}/{r['photos']} | {r['points']} | "
            f"{r['reprojection_px']:.2f} | {r['centre_rms_pct']:.3f} | "
            f"{r['rotation_mean_deg']:.3f} / {r['rotation_rms_deg']:.3f} / "
            f"{r['rotation_max_deg']:.3f} | "
            f"{r['frame_tilt_deg']:.2f} | {r['frame_scale']:.3f} | {t['extract_s']:.0f} / "
            f"{t['match_s']:.0f} / {t['map_s']:.0f} | {t['total_s']:.0f} |")
    lines.append(f"\nmedian total: {statistics.median(r['timings']['total_s'] for r in runs):.0f}"
                 f" s; load average at the end: {' '.join(summary['loadavg'])}")
    write_text(out / "import_sfm.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
