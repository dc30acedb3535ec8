"""The method from photos alone against the same scene from ground-truth cameras.

For one scene (``validation.pipeline.SCENES``) under one light pair, on the textured mat
(``base_texture=mat``: SfM needs features):

1. ``OUT/photoset/data``: the scene's training views as a user's photos (sRGB JPEG, no camera,
   no mask) at ``--photo-size`` pixels, where SfM registers every view. Only the training
   views' photos are imported (``OUT/photos``): the test cameras stay unseen.
2. ``OUT/import``: ``mi-shadowgs import`` of them (SfM, no cameras, no masks, no material
   ids), resized to the preset's resolution; ``OUT/run-photos``: ``mi-shadowgs run`` on it
   (its own test split has no ground truth; the run skips those metrics).
3. ``OUT/gt/data``, ``OUT/run-gt``: the same scene, cameras (same seed) and lights at the
   preset's resolution with full ground truth, run from ground-truth cameras and masks.
4. Both fits are scored by stage 5's own evaluation on ``OUT/gt/data``'s test views. For the
   photo run the ground-truth test cameras and lights are mapped into its frame by the
   similarity fitted on the imported cameras (ground-truth centres -> imported centres; it
   composes the unknown SfM frame with ``import.json``'s transform). Env-map relighting and
   the light-map cosine are left out of both (the grid map would need resampling under the
   rotation).

    python -m validation.photos --scene NAME --out OUT [--lights tuned] [--preset cpu-small]
        [--photo-size 512] [--threads N] [--albedo-detail W] [--seed N]

``--albedo-detail W`` runs both fits with ``run --albedo-detail W`` (the mat's print in the
albedo); ``--seed N`` runs both at seed N of every stage's random draws (``RunConfig.seed``;
the photos, their import and the cameras stay the same), so that a difference can be told
from a seed's chance. An OUT whose runs were made with other settings exits 2, naming the
setting: give another OUT (the photos and the import may be copied in; they are reused).

Each step is reused when its output is complete. Writes ``OUT/photos.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from validation import claim_out, fail

# The figures compared; the acceptance bounds (photo run against GT-camera run).
FIGURES = ("albedo_psnr", "albedo_ssim", "shadow_iou", "shadow_iou_decided", "relight_psnr",
           "relight_ssim", "light_cosine")
ALBEDO_PSNR_TOLERANCE_DB = 1.5
SHADOW_IOU_TOLERANCE = 0.05


def _generate(scene: str, folder: Path, lights: str, preset: str, size: int | None,
              photos: bool, **settings) -> Path:
    """The scene on the mat in ``folder/data``: ``preset``'s training cameras (seed 0), no
    env maps, ``settings`` GenerateConfig fields."""
    from validation.pipeline import available_scenes, make_dataset

    scenes = available_scenes()
    if scene not in scenes:
        fail(f"--scene {scene}: not available (meshes under ../shared/data); "
             f"available: {', '.join(scenes)}")
    return make_dataset(scene, scenes[scene], folder, lights, envmaps="none",
                        resolution=size, preset=preset,
                        scene_overrides={"base_texture": "mat"}, settings=settings,
                        photos=photos)


def training_photos(photoset: Path, dst: Path) -> Path:
    """``dst``: the photo set's training photos only (the test cameras stay unseen)."""
    from mi_shadowgs.dataset import layout
    from mi_shadowgs.io.atomic import atomic_dir

    if dst.is_dir():
        return dst
    with atomic_dir(dst) as tmp:
        for f in sorted((photoset / layout.PHOTOS).glob("train_*")):
            shutil.copy2(f, tmp / f.name)
    return dst


def fit_frame(imported: dict, truth: dict):
    """The similarity taking ground-truth camera centres onto the imported ones, fitted on
    the photos both have; with the residual (camera_errors of the alignment)."""
    from mi_shadowgs.dataset.world_frame import camera_errors, umeyama

    names = sorted(set(imported) & set(truth))
    if len(names) < 3:
        raise ValueError(f"{len(names)} photos in common with the ground truth: a similarity "
                         "needs 3")
    est = np.stack([imported[n].c2w for n in names])  # [M, 4, 4]
    ref = np.stack([truth[n].c2w for n in names])  # [M, 4, 4]
    sim = umeyama(ref[:, :3, 3], est[:, :3, 3])
    return sim, {"photos": len(names), **camera_errors(est, ref)}


def mapped_lights(lights: dict, frame) -> dict:
    """``lights.json`` in the other frame of ``frame`` (a ``Similarity``, or a rotation
    [3, 3] alone): every light's direction rotated, and a lamp's position moved by the whole
    similarity (p' = s R p + t), its distance and radius scaled by s and its intensity by
    s^2 (its irradiance at the object's centre, which the photos fix, stays); the same for
    the lamps of a point relighting. Env-map relightings and the grid light map (which would
    need resampling) are left out."""
    from mi_shadowgs.dataset.world_frame import Similarity

    if not isinstance(frame, Similarity):
        frame = Similarity(scale=1.0, rotation=np.asarray(frame, np.float64),
                           translation=np.zeros(3))

    def turn(entry: dict) -> dict:
        out = dict(entry)
        if entry.get("direction") is not None:
            d = frame.rotation @ np.asarray(entry["direction"], np.float64)
            out["direction"] = (d / np.linalg.norm(d)).tolist()
        if entry.get("position") is not None:
            out["position"] = frame.points(np.asarray(entry["position"],
                                                      np.float64)[None])[0].tolist()
            for key, power in (("distance", 1), ("radius", 1), ("intensity", 2)):
                if entry.get(key) is not None:
                    out[key] = (np.asarray(entry[key], np.float64) *
                                frame.scale ** power).tolist()
        return out

    training = {k: v for k, v in lights["training"].items() if k != "light_map"}
    training["lights"] = [turn(lt) for lt in lights["training"]["lights"]]
    relit = [{**e, "lights": [turn(lt) for lt in e["lights"]]}
             for e in lights.get("relightings", []) if e.get("type") in ("directional", "point")]
    return {**lights, "training": training, "relightings": relit}


def mapped_split(dataset, sim, lights: dict):
    """The dataset with its cameras moved by ``sim`` and ``lights`` in place of its own."""
    views = [dataclasses.replace(v, camera=dataclasses.replace(v.camera,
                                                               c2w=sim.c2w(v.camera.c2w)))
             for v in dataset.views]
    return dataclasses.replace(dataset, views=views, lights=lights)


def score_run(run: Path, train, test, preset: str, quantile: float, settings=None) -> dict:
    """Stage 5's evaluation of ``run``'s stage-4 fit on ``test`` (cameras and lights in the
    run's frame), with the shadow maps and relighting of ``settings`` (a RunConfig; None:
    ``preset``'s)."""
    from mi_shadowgs.presets import get_config
    from mi_shadowgs.stages.common import load_training_views
    from mi_shadowgs.stages.evaluation import metrics as evaluation
    from mi_shadowgs.stages.evaluation.evaluate import evaluate_decomposition, scored_pixels
    from mi_shadowgs.stages.material.outputs import fit_from_files
    from mi_shadowgs.stages.material.runner import occluder_bounds

    fit_dir = run / "material" / "full"
    result = fit_from_files(fit_dir / "model.ply", fit_dir / "light.json")
    run_train = load_training_views(Path(json.loads((run / "summary.json").read_text())
                                         ["dataset"]))
    bounds = occluder_bounds(result.surfels, run_train.cameras, quantile)
    settings = get_config(preset) if settings is None else settings
    metrics, images = evaluate_decomposition(result, train, test, bounds, settings.visibility,
                                             settings.relight, figure_lights=1)
    # The albedo on the object alone: the mat's printed texture is flattened by stage 4's
    # segment averaging (the paper's piecewise-constant albedo), in both runs alike.
    obj = test.stack("object_mask") & scored_pixels(test)
    object_alb = evaluation.albedo_metrics(images["albedo"], test.stack("albedo"),
                                           test.stack("material"), obj)
    return {k: metrics.get(k) for k in FIGURES} | {
        "object_albedo_psnr": object_alb["psnr"],
        "light_angular_errors_deg": metrics.get("angular_error_deg"),
        "fitted_lights": metrics.get("fitted_lights"),
        "spurious_irradiance_fraction": metrics.get("spurious_irradiance_fraction"),
        "strongest_light_share": metrics.get("strongest_light_share"),
        "lamp_position_error": metrics.get("lamp_position_error"),
        "fitted_lamps": int(np.sum([p is not None for p in json.loads(
            (fit_dir / "light.json").read_text()).get("positions") or []])),
        "relighting": {n: {k: r[k] for k in ("psnr", "ssim")}
                       for n, r in metrics["relighting"].items()}}


def _timed_run(data: Path, out: Path, preset: str, times: Path,
               albedo_detail: float | None = None, seed: int = 0) -> tuple[float, bool]:
    """``timed_run`` at ``preset`` with ``RunConfig.albedo_detail`` and ``RunConfig.seed``."""
    from mi_shadowgs.presets import build

    config = build(preset, {} if albedo_detail is None else
                   {"material": {"detail_prior": albedo_detail}}, seed=seed)
    return timed_run(data, out, config, times)


def timed_run(data: Path, out: Path, config, times: Path, key: str | None = None,
              study: str = "validation.photos") -> tuple[float, bool]:
    """Stages 1-5 on ``data`` with settings ``config`` (a RunConfig); (seconds, resumed). A
    run made whole by this call takes the call's seconds. A run resumed after an
    interruption adds the seconds its reused stages 1, 2 and 4 recorded in their own files
    (``validation.pipeline.stage_seconds``), and is marked resumed: what the interrupted call
    spent on other stages is not known. A finished run is reused and its time read back
    from ``times`` (JSON: ``key``, by default the run folder's name -> [seconds, resumed]).
    A run folder made with other settings exits 2 (``study`` names the command)."""
    from mi_shadowgs.io.atomic import write_json
    from mi_shadowgs.io.provenance import ProvenanceError
    from mi_shadowgs.pipeline import run_pipeline
    from validation.pipeline import STAGE_KEYS, stage_seconds

    key = out.name if key is None else key
    known = json.loads(times.read_text()) if times.is_file() else {}
    finished = (out / "summary.json").is_file()
    try:
        summary = run_pipeline(data, out, config, progress=True)
    except ProvenanceError as exc:  # e.g. another --albedo-detail or --seed into the same OUT
        fail(f"{exc}; {study} has no --overwrite: give another --out")
    if finished and key in known:
        entry = known[key]  # a bare number: written before the resumed flag
        seconds, resumed = (entry, False) if isinstance(entry, int | float) else entry
        return float(seconds), bool(resumed)
    seconds, resumed = float(summary["total_seconds"]), False
    if summary.get("reused_stages"):  # made in part by an earlier, interrupted call
        own = {st["name"]: st.get("seconds") for st in summary.get("stages", [])}
        recorded = stage_seconds(own, out)
        seconds += sum(recorded[k] or 0.0 for k, name in STAGE_KEYS.items()
                       if own.get(name) is None)
        resumed = True
    write_json(times, {**known, key: [seconds, resumed]})
    return seconds, resumed


def markdown(rec: dict) -> str:
    rows = [("ground-truth cameras and masks", rec["gt"]), ("photos only", rec["photos"])]
    lines = ["| run | albedo PSNR | albedo SSIM | object albedo PSNR | shadow IoU | "
             "shadow IoU (decided) | relight PSNR | light cos | light err deg | lights | "
             "wall s |", "|" + "---|" * 11]
    for name, r in rows:
        s = r["scores"]
        err = "/".join(f"{e:.1f}" for e in s["light_angular_errors_deg"] or [])
        lines.append(f"| {name} | {s['albedo_psnr']:.2f} | {s['albedo_ssim']:.4f} | "
                     f"{s['object_albedo_psnr']:.2f} | {s['shadow_iou']:.3f} | "
                     f"{s['shadow_iou_decided']:.3f} | "
                     f"{s['relight_psnr']:.2f} | "
                     f"{s['light_cosine']:.4f} | {err} | {s['fitted_lights']} | "
                     f"{r['wall_s']:.0f}{' (resumed)' if r.get('resumed') else ''} |")
    d = rec["differences"]
    f = rec["frame"]
    lines += ["", f"Photo run minus ground-truth run: albedo PSNR {d['albedo_psnr']:+.2f} dB "
              f"(bound -{ALBEDO_PSNR_TOLERANCE_DB}), shadow IoU {d['shadow_iou']:+.3f} (bound "
              f"-{SHADOW_IOU_TOLERANCE}; decided pixels {d['shadow_iou_decided']:+.3f}), relight "
              f"PSNR {d['relight_psnr']:+.2f} dB: "
              f"**{'within' if rec['within_bounds'] else 'outside'} the bounds**.",
              f"Frame: {f['photos']} photos registered of {rec['photos_imported']}; camera "
              f"centres {f['centre_rms_pct']:.3f}% RMS, rotations {f['rotation_rms_deg']:.3f} "
              "deg RMS after the similarity.",
              f"Photo-only wall time (import + stages 1-5): {rec['photos']['wall_s']:.0f} s "
              f"(import {rec['import_s']:.0f} s)."]
    if any(r.get("resumed") for _, r in rows):
        lines.append("(resumed): the run was interrupted and resumed; its time adds the "
                     "seconds its reused stages 1, 2 and 4 recorded, and leaves out what the "
                     "interrupted call spent on stages 3 and 5.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    from validation.pipeline import LIGHT_PAIRS, SCENES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="default", choices=sorted(SCENES))
    ap.add_argument("--out", required=True)
    ap.add_argument("--lights", default="tuned", choices=sorted(LIGHT_PAIRS))
    ap.add_argument("--preset", default="cpu-small")
    ap.add_argument("--photo-size", type=int, default=512,
                    help="photo size in pixels (SfM registers every view at 512)")
    ap.add_argument("--threads", type=int, default=None, help="Dr.Jit threads")
    ap.add_argument("--albedo-detail", type=float, default=None, metavar="W",
                    help="both runs with `run --albedo-detail W` (default: the preset's, off)")
    ap.add_argument("--seed", type=int, default=0,
                    help="both runs at this seed of the stages' random draws (`run --seed`)")
    args = ap.parse_args(argv)
    from mi_shadowgs.config import ConfigError
    from mi_shadowgs.presets import build

    try:  # the settings' own checks, before any data is made
        base = build(args.preset, {} if args.albedo_detail is None else
              {"material": {"detail_prior": args.albedo_detail}}, seed=args.seed)
    except (ConfigError, ValueError) as exc:  # (a config's own checks raise ValueError)
        fail(f"--albedo-detail / --seed: {exc}")
    claim_out(args.out, "validation.photos", ('photos.json', 'wall_seconds.json'))
    import drjit as dr

    from mi_shadowgs.dataset.importer import import_capture
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.io.atomic import write_json, write_text
    from mi_shadowgs.presets import generate_config as gen_config
    from mi_shadowgs.presets import import_config
    from validation.import_sfm import cameras_by_photo, truth

    if args.threads:
        dr.set_thread_count(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    size = gen_config(args.preset).width
    gt_data = _generate(args.scene, out / "gt", args.lights, args.preset, None, False)
    # SfM wants sharp photos more than clean ones: 64 spp as in validation.import_sfm
    photoset = _generate(args.scene, out / "photoset", args.lights, args.preset,
                         args.photo_size, True, n_test=1, spp=64)
    photos = training_photos(photoset, out / "photos")
    imported = out / "import"
    t = time.perf_counter()
    if not (imported / "import.json").is_file():
        config = dataclasses.replace(import_config(args.preset), max_size=size)
        import_capture(photos, imported, config)
        import_s = time.perf_counter() - t
    else:
        import_s = json.loads((imported / "import.json").read_text())["timings"]["total_s"]
    times = out / "wall_seconds.json"
    run_s, photos_resumed = _timed_run(imported, out / "run-photos", args.preset, times,
                                       args.albedo_detail, args.seed)
    photos_s = import_s + run_s
    gt_s, gt_resumed = _timed_run(gt_data, out / "run-gt", args.preset, times,
                                  args.albedo_detail, args.seed)

    quantile = base.bounds_quantile
    train, test = load_dataset(gt_data, "train"), load_dataset(gt_data, "test")
    sim, frame = fit_frame(cameras_by_photo(imported), truth(photoset))
    lights = mapped_lights(train.lights, sim)
    gt_scores = score_run(out / "run-gt", dataclasses.replace(train, lights=mapped_lights(
        train.lights, np.eye(3))), test, args.preset, quantile)
    photo_scores = score_run(out / "run-photos", mapped_split(train, sim, lights),
                             mapped_split(test, sim, lights), args.preset, quantile)
    diff = {k: photo_scores[k] - gt_scores[k] for k in FIGURES}
    rec = {"scene": args.scene, "lights": args.lights, "preset": args.preset,
           "albedo_detail": args.albedo_detail, "seed": args.seed,
           "photo_size": args.photo_size, "training_size": size,
           "photos_imported": len(list(photos.iterdir())),
           "similarity": sim.to_json(), "frame": frame, "import_s": import_s,
           "gt": {"wall_s": gt_s, "resumed": gt_resumed, "scores": gt_scores},
           "photos": {"wall_s": photos_s, "resumed": photos_resumed, "scores": photo_scores},
           "differences": diff,
           "within_bounds": bool(diff["albedo_psnr"] >= -ALBEDO_PSNR_TOLERANCE_DB and
                                 diff["shadow_iou"] >= -SHADOW_IOU_TOLERANCE)}
    write_json(out / "photos.json", rec)
    md = markdown(rec)
    write_text(out / "photos.md", md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
