"""Acceptance figures of stage 2: rendered segment maps against ground-truth ids.

For the default scene and the hotdog (cpu-small datasets, generated under --data-root when
missing), on stand-in geometry (surfels on the true surfaces; stage 1 is not needed) or on a
stage-1 model (``--model-default`` / ``--model-hotdog``): train features on the material-id
masks and on the chromaticity masks, cluster, render the test views' segment maps, and
report ARI, Hungarian mIoU, the lit/shadowed base check, and the stage's wall time::

    python -m validation.segmentation --out OUT [--data-root DIR] [--quick] [--overwrite]

A killed call, run again, reuses the datasets and the finished stages and continues the
stage in progress from its checkpoint, when they were made from the same inputs and
settings; it exits 2 naming what differs otherwise (``--overwrite`` makes them again).
"""

from __future__ import annotations

import argparse
import datetime
import platform
from pathlib import Path

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.io.provenance import ProvenanceError
from validation import claim_out, fail

HOTDOG = Path("/work/shared/data/meshes/hotdog/hotdog.ply")
SCENES = {
    "default": ("default", {}),
    "hotdog": ("mesh", {"mesh": str(HOTDOG), "parts": "auto"}),
}


def standin_surfels(setup, n_object: int, n_base: int, object_sigma: float = 0.7,
                    seed: int = 0):
    """Surfels on the true shapes, denser on the object than on the (large) base: a
    stand-in for a trained stage-1 model. Returns (surfels, true material id per surfel)."""
    import numpy as np

    from mi_shadowgs.core.sampling import sample_surface, surfels_on_surface
    from mi_shadowgs.core.surfels import Surfels

    shapes = list(setup.scene.shapes())
    ids = setup.shape_material_ids()
    obj = [s for s in shapes if s.id().startswith("object_")]
    base = [s for s in shapes if s.id() == "base"]
    parts = []
    for group, n, sig in ((obj, n_object, object_sigma), (base, n_base, 1.0)):
        s = surfels_on_surface(group, n, seed=seed, sigma_factor=sig).to_numpy()
        idx = sample_surface(group, n, seed=seed).shape_index
        s["material"] = np.array([ids[group[i].id()] for i in idx])
        parts.append(s)
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    surf = Surfels.from_numpy(cat["position"], cat["scale"], cat["rotation"], cat["opacity"],
                              {"albedo": cat["albedo"]})
    return surf, cat["material"]


def _dataset(root: Path, scene: str, overwrite: bool = False) -> Path:
    """The scene's cpu-small dataset in ``root``: kept when it is this one (its fingerprint),
    else made; one made from other scene files or settings is replaced only with
    ``overwrite`` (exit 2 naming the folder otherwise)."""
    from mi_shadowgs.dataset.writer import OutputExistsError, write_dataset
    from mi_shadowgs.presets import generate_config as get_config
    from mi_shadowgs.scenes import scene_path

    name, overrides = SCENES[scene]
    generate = (scene_path(name), root, get_config("cpu-small"), "cpu-small")
    try:
        write_dataset(*generate, overrides=overrides or None, progress=False)
    except OutputExistsError as exc:
        if not overwrite:
            fail(f"{exc} (validation.segmentation)")
        write_dataset(*generate, overrides=overrides or None, overwrite=True, progress=False)
    return root


def evaluate(scene: str, data: Path, model: Path | None, masks: str, out: Path,
             preset: str = "cpu-small", n_object: int = 8000, n_base: int = 12000,
             overrides: dict | None = None, overwrite: bool = False) -> dict:
    """Stage 2 through its library runner (``run_segmentation``, into
    ``OUT/<scene>_<masks>/``: reused when finished, continued from its checkpoint when not,
    exit 2 naming the difference when made otherwise) on the stand-in geometry or
    ``model``; one table row."""
    import json

    import numpy as np

    from mi_shadowgs.dataset.scene import load_scene
    from mi_shadowgs.io.images import read_png, write_png
    from mi_shadowgs.io.ply import load_ply, save_ply
    from mi_shadowgs.presets import build
    from mi_shadowgs.scenes import scene_path
    from mi_shadowgs.stages.segmentation import run_segmentation

    if model is None:
        name, scene_overrides = SCENES[scene]
        setup = load_scene(scene_path(name), scene_overrides or None)
        surfels, _ = standin_surfels(setup, n_object, n_base)
        geometry = f"stand-in ({n_object} object + {n_base} base surfels on the true shapes)"
        model = out / f"{scene}_standin.ply"
        # Made again each call, the same bytes (seeded): the stage's input digest matches.
        save_ply(model, surfels)
    else:
        geometry = f"stage-1 model {model} ({load_ply(model).count} surfels)"
    config = build(preset, {"segmentation": overrides or {}})
    try:
        stage = run_segmentation(model, data, out / f"{scene}_{masks}", config.segmentation,
                                 masks=masks, chromaticity=config.chromaticity, preset=preset,
                                 overwrite=overwrite, reuse=True, progress=False)
    except ProvenanceError as exc:
        fail(f"{exc} (validation.segmentation)")
    report = json.loads((stage.folder / "segmentation.json").read_text())
    metrics, shadow = report["metrics"], report["base_shadow"]
    firsts = sorted((stage.folder / "segments").glob("*.png"))
    firsts = [p for p in firsts if not p.stem.endswith("_overlay")][:6]
    strip = np.concatenate([read_png(p)[..., :3] for p in firsts], axis=1)  # r_000...: in order
    write_png(out / f"{scene}_{masks}_segments.png", strip)
    return {"scene": scene, "masks": masks, "geometry": geometry, "k": report["k"],
            "surfels": report["surfels"], "iterations": config.segmentation.iterations,
            "seconds_masks": round(report["seconds_masks"], 1),
            "seconds_stage": round(report["seconds_stage"], 1),
            "ari": metrics["ari"], "miou": metrics["miou"],
            "base_lit_fraction": shadow["lit_fraction"],
            "base_shadow_fraction": shadow["shadow_fraction"],
            "base_shadow_pixels": shadow["shadow_pixels"],
            "accept": (metrics["ari"] >= 0.9 or metrics["miou"] >= 0.85)}


def markdown(rows: list[dict], command: str) -> str:
    import os

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        "## Segmentation",
        "",
        f"`{command}` ({datetime.date.today()}, {platform.machine()} "
        f"{os.cpu_count()} cores, load average {load:.1f} at the end; llvm_ad_rgb).",
        "Test views of the cpu-small datasets (32 views, 128 px); metrics over pixels with "
        "a ground-truth material (background excluded; a predicted background there counts "
        "as its own class). Base check: of the base pixels shadowed from some training "
        "light, the fraction in the segment of most lit base pixels. Stage time = masks + "
        "feature training + K-means (not the evaluation renders).",
        "",
        "| scene | masks | geometry | K | ARI | mIoU | base lit / shadowed in one segment "
        "| stage s | accept |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['masks']} | {r['geometry']} | {r['k']} | "
                     f"{r['ari']:.3f} | {r['miou']:.3f} | {r['base_lit_fraction']:.3f} / "
                     f"{r['base_shadow_fraction']:.3f} | {r['seconds_stage']:.0f} | "
                     f"{'yes' if r['accept'] else 'no'} |")
    return "\n".join(lines) + "\n"


def run(out_dir: Path, quick: bool = False, data_root: Path | None = None,
        models: dict | None = None, mask_sources=("material", "chromaticity"),
        command: str = "python -m validation.segmentation", overwrite: bool = False) -> dict:
    from mi_shadowgs.io.atomic import write_json, write_text

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    overrides = {"iterations": 40} if quick else None
    rows = []
    for scene in SCENES:
        if scene == "hotdog" and not HOTDOG.is_file():
            continue
        # Its own folders, kept while the dataset code and the scene are the same.
        root = out_dir / "data" if data_root is None else Path(data_root)
        data = _dataset(root / f"seg_val_{scene}", scene, overwrite)
        for masks in mask_sources:  # chromaticity: see runner.label_fraction
            r = evaluate(scene, data, (models or {}).get(scene), masks, out_dir,
                         overrides=overrides, overwrite=overwrite)
            print(r, flush=True)
            rows.append(r)
    md = markdown(rows, command)
    write_json(out_dir / "segmentation.json", rows)
    write_text(out_dir / "segmentation.md", md)
    return {"rows": rows, "markdown": md}


def main(argv=None) -> int:
    import sys

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--data-root", default=None,
                    help="where the datasets are (made); default: OUT/data")
    ap.add_argument("--quick", action="store_true", help="40 iterations: a smoke run")
    ap.add_argument("--model-default", default=None, help="stage-1 model PLY (default)")
    ap.add_argument("--model-hotdog", default=None, help="stage-1 model PLY (hotdog)")
    ap.add_argument("--masks", action="append", choices=("material", "chromaticity"))
    ap.add_argument("--overwrite", action="store_true",
                    help="make the stages (and datasets made otherwise) again")
    args = ap.parse_args(argv)
    models = {k: Path(v) for k, v in (("default", args.model_default),
                                      ("hotdog", args.model_hotdog)) if v}
    for scene, model in models.items():
        if not model.is_file():
            fail(f"--model-{scene} {model}: no such file")
    claim_out(args.out, "validation.segmentation", ('segmentation.json',))
    res = run(Path(args.out), args.quick, args.data_root, models,
              tuple(args.masks or ("material", "chromaticity")),
              "python -m validation.segmentation " + " ".join(argv or sys.argv[1:]),
              overwrite=args.overwrite)
    print(res["markdown"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

