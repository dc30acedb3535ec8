"""Lab captures against their ideal control: the acceptance figures of the lamp model.

For each scene (``validation.pipeline.SCENES``: ``default``, and the asset meshes when
``../shared/data`` is present) and lamp distance (object radii), on the textured mat:

1. ``OUT/<scene>/lamp<D>/``: the generator's lab capture (``-D capture=lab -D
   lamp_distance=D``: a sphere lamp of radius 0.15 radii at azimuth 35 and elevation 50
   deg, irradiance 3 at the object's centre, dim room light, +-0.35 EV and +-4% white
   balance per photo, sensor noise, JPEG) as ``--views`` training photos of
   ``--photo-size`` (``photoset/data``, its training photos and ``gains.json`` in
   ``photos``); its ground truth at the preset's resolution (``gt/data``, for scoring);
   ``mi-shadowgs import`` of the photos (``import``) and ``mi-shadowgs run`` on it
   (``run``, with ``material.lamps=auto``).
2. ``OUT/<scene>/control/``: the ideal control, the same cameras under one directional
   light of the lamp's direction and irradiance at the object's centre, with no room
   light, jitter or noise (``-D light0_azimuth=35 -D light0_elevation=50 -D
   light0_irradiance=3 -D light1_irradiance=0``), made, imported and run alike, with the
   preset's ``material.lamps`` (a directional capture's light must stay directional). One
   control serves every distance of its scene.
3. Both runs scored by stage 5's evaluation on their ground truth's test views, mapped
   into the import's frame by the similarity fitted from the true camera centres to the
   imported ones (``validation.photos.fit_frame``): a lamp's position by the whole
   similarity. The fitted per-view gains (``RUN/geometry/view_gains.json``, when the run
   fits them) against ``photos/gains.json`` after one global scale.
4. ``OUT/lab.json`` and ``OUT/lab.md``: per case, the figures of lab and control beside
   the acceptance bounds (``BOUNDS``), each marked pass or fail, and each step's wall
   time.

    python -m validation.lab --scene default[,bunny] --distance 6[,12] --out OUT
        [--preset cpu-small] [--photo-size 640x480] [--views 48] [--max-size N]
        [--set SECTION.FIELD=V ...] [--seed N] [--threads N]

``--set`` items reach both runs. The imported views are at most ``--max-size`` pixels on
their longest side (default: the preset's generated width, the resolution the truth is
scored at). Each step is reused when its output is complete; an OUT made with other
settings exits 2 naming the setting.
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

STUDY = "validation.lab"
SETTINGS_FILE = "lab_settings.json"
TIMES_FILE = "wall_seconds.json"
GAINS_FILE = Path("geometry") / "view_gains.json"  # a run's fitted per-view gains
GT_TRAIN_VIEWS = 4  # the truth is scored on its test views; its training views are unused
PHOTO_SPP = 64  # SfM wants sharp photos more than clean ones (validation.import_sfm)
KINDS = ("control", "lab")
# The acceptance bounds: the lamp's position error as a share of its distance; its direction
# in degrees; the strongest fitted light's share of the fitted irradiance; how far the lab's
# shadow IoU and albedo PSNR may fall below the control's; the fitted gains' largest
# relative error after one global scale.
BOUNDS = {"lamp_position": 0.05, "lamp_direction_deg": 2.0, "strongest_share": 0.90,
          "shadow_iou_drop": 0.05, "albedo_psnr_drop_db": 1.0, "gain_error": 0.03}


def capture_params() -> dict:
    """The lab capture preset's parameters (``mi_shadowgs.dataset.capture.CAPTURES``)."""
    from mi_shadowgs.dataset.capture import CAPTURES

    return dict(CAPTURES["lab"])


def scene_lights(kind: str, distance: float) -> dict:
    """The scene parameters of a case's lights: the lab capture with its lamp at
    ``distance`` object radii, or the control's one directional light of the lamp's
    direction and irradiance (the scene's second light off)."""
    if kind == "lab":
        return {"capture": "lab", "lamp_distance": f"{distance:g}"}
    lab = capture_params()
    return {"light0_azimuth": lab["lamp_azimuth"], "light0_elevation": lab["lamp_elevation"],
            "light0_irradiance": lab["lamp_irradiance"], "light1_irradiance": "0"}


def kind_dir(out: Path, scene: str, kind: str, distance: float) -> Path:
    return out / scene / ("control" if kind == "control" else f"lamp{distance:g}")


def parse_size(text: str) -> tuple[int, int]:
    """``WxH`` (or ``N``: square) as (width, height); ValueError naming the option."""
    w, _, h = text.lower().partition("x")
    try:
        width, height = int(w), int(h or w)
    except ValueError:
        raise ValueError(f"--photo-size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480") from None
    if min(width, height) < 16:
        raise ValueError(f"--photo-size {text!r}: at least 16 pixels a side")
    return width, height


def check_settings(out: Path, settings: dict) -> None:
    """Record the study's settings in ``out``, or exit 2 naming the first that differs
    from those its earlier outputs were made with."""
    from mi_shadowgs.io.atomic import write_json

    path = out / SETTINGS_FILE
    if path.is_file():
        made = json.loads(path.read_text())
        for key in sorted(set(made) | set(settings)):
            if made.get(key) != settings.get(key):
                fail(f"--out {out}: made with {key} = {made.get(key)!r}, this call asks for "
                     f"{settings.get(key)!r} ({path}); give another --out")
        return
    write_json(path, settings)


class Times:
    """Each step's wall seconds, kept in ``OUT/wall_seconds.json`` so that a step reused on
    a later call reports the seconds it took when it was made."""

    def __init__(self, path: Path):
        self.path = path

    def known(self) -> dict:
        return json.loads(self.path.read_text()) if self.path.is_file() else {}

    def step(self, key: str, done: bool, work):
        """``work()``'s result and seconds: those recorded for ``key`` when its output was
        ``done`` before the call (None if never recorded), else the call's."""
        from mi_shadowgs.io.atomic import write_json

        t = time.perf_counter()
        result = work()
        seconds = time.perf_counter() - t
        known = self.known()
        if done:
            return result, known.get(key)
        write_json(self.path, {**known, key: seconds})
        return result, seconds


def make_kind(out: Path, scene: str, mesh, kind: str, distance: float, settings: dict,
              times: Times) -> dict:
    """A case's photo set, truth and import (steps 1-2 of the module doc); their seconds."""
    from mi_shadowgs.dataset import layout
    from mi_shadowgs.dataset.importer import import_capture
    from mi_shadowgs.presets import import_config
    from validation.photos import training_photos
    from validation.pipeline import DatasetMismatch, PresetMismatch, make_dataset

    folder = kind_dir(out, scene, kind, distance)
    rel = folder.relative_to(out).as_posix()
    pair = scene_lights(kind, distance)
    preset = settings["preset"]
    width, height = settings["photo_size"]

    def generate(sub: str, **config):
        data = folder / sub / "data"
        try:
            return times.step(f"{rel}/{sub}", (data / layout.DATASET_JSON).is_file(),
                              lambda: make_dataset(
                                  scene, mesh, folder / sub, envmaps="none", preset=preset,
                                  pair=pair, scene_overrides={"base_texture": "mat"},
                                  settings=config, photos=sub == "photoset"))
        except (DatasetMismatch, PresetMismatch) as exc:
            fail(str(exc))

    photoset, photoset_s = generate("photoset", width=width, height=height,
                                    n_train=settings["views"], n_test=1, spp=PHOTO_SPP)
    gt, gt_s = generate("gt", n_train=GT_TRAIN_VIEWS)
    photos = folder / "photos"
    training_photos(photoset, photos)  # kept when there
    gains = photoset / layout.PHOTOS / layout.PHOTO_GAINS
    if gains.is_file() and not (photos / gains.name).is_file():
        # beside the photos: import.json's source leads a run to the true gains
        shutil.copy2(gains, photos / gains.name)
    imported = folder / "import"
    config = dataclasses.replace(import_config(preset), max_size=settings["max_size"])
    done = (imported / "import.json").is_file()
    try:
        _, import_s = times.step(f"{rel}/import", done, lambda: done or import_capture(
            photos, imported, config))
    except (ValueError, FileExistsError) as exc:  # e.g. SfM registered too few photos
        fail(f"import of {photos}: {exc}")
    return {"photoset": photoset, "gt": gt, "import": imported, "run": folder / "run",
            "times": {"photoset_s": photoset_s, "gt_s": gt_s, "import_s": import_s}}


def run_config(kind: str, settings: dict):
    """The run's settings tree: the preset with the study's ``--set`` items, and for the
    lab capture ``material.lamps=auto`` (unless a ``--set`` names it)."""
    from mi_shadowgs.presets import build, merge, parse_sets

    overrides = {"material": {"lamps": "auto"}} if kind == "lab" else {}
    overrides = merge(overrides, parse_sets(settings["sets"]))
    return build(settings["preset"], overrides, seed=settings["seed"])


def run_kind(out: Path, paths: dict, kind: str, settings: dict) -> dict:
    """``mi-shadowgs run`` on the import (step 2); its seconds, and each stage's."""
    from validation.photos import timed_run
    from validation.pipeline import stage_seconds

    run = paths["run"]
    key = run.relative_to(out).as_posix()
    seconds, resumed = timed_run(paths["import"], run, run_config(kind, settings),
                                 out / TIMES_FILE, key=key, study=STUDY)
    summary = json.loads((run / "summary.json").read_text())
    own = {st["name"]: st.get("seconds") for st in summary.get("stages", [])}
    return {"run_s": seconds, "run_resumed": resumed, **stage_seconds(own, run)}


def gain_errors(fitted: np.ndarray, truth: np.ndarray) -> dict:
    """Fitted per-view gains [V, 3] against the true ones after one global scale (the
    geometric mean of truth / fitted over views and channels: the photos fix the gains only
    up to it), and after one scale per channel: relative errors |s * fitted / truth - 1|,
    their largest and mean."""
    f = np.asarray(fitted, np.float64).reshape(-1, 3)
    t = np.asarray(truth, np.float64).reshape(-1, 3)
    if f.shape != t.shape or not len(f) or np.any(f <= 0) or np.any(t <= 0):
        raise ValueError(f"gain_errors: {f.shape} fitted gains for {t.shape} true ones, all "
                         "> 0")
    log_ratio = np.log(t) - np.log(f)
    out = {}
    for name, scale in (("global", np.exp(log_ratio.mean())),
                        ("per_channel", np.exp(log_ratio.mean(axis=0)))):
        rel = np.abs(f * scale / t - 1.0)
        out[name] = {"max": float(rel.max()), "mean": float(rel.mean()),
                     "scale": np.broadcast_to(scale, (3,)).tolist()}
    return out


def gain_scores(run: Path, photoset: Path) -> dict | None:
    """The run's fitted gains (``GAINS_FILE``: ``views``, each with its ``photo`` and
    ``gain``) against ``photos/gains.json`` of the photo set (1 for every photo of a set
    without jitter); None when the run fitted none."""
    from mi_shadowgs.dataset import layout

    path = run / GAINS_FILE
    if not path.is_file():
        return None
    try:
        views = json.loads(path.read_text())["views"]
        fitted = {v["photo"]: v["gain"] for v in views if v.get("photo")}
    except (ValueError, KeyError, TypeError) as exc:
        fail(f"{path}: not a view-gains record ({exc})")
    true_file = photoset / layout.PHOTOS / layout.PHOTO_GAINS
    truth = (json.loads(true_file.read_text())["photos"] if true_file.is_file() else
             dict.fromkeys(fitted, {"gain": [1.0, 1.0, 1.0]}))
    names = sorted(n for n in fitted if n in truth)
    if not names:
        return {"file": str(path), "views": 0, "error": "no view names a photo of the truth"}
    return {"file": str(path), "views": len(names), "truth": str(true_file)
            if true_file.is_file() else "1 (no jitter)",
            **gain_errors(np.array([fitted[n] for n in names]),
                          np.array([truth[n]["gain"] for n in names]))}


def _registered(imported: Path) -> dict:
    record = json.loads((imported / "import.json").read_text())
    return {"registered": len(record.get("registered", [])),
            "photos": len(record.get("registered", [])) + len(record.get("rejected", []))}


def score_kind(paths: dict, settings: dict) -> dict:
    """Step 3 for one run: the frame, stage 5's figures and the gains' errors."""
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.presets import recorded
    from validation.import_sfm import cameras_by_photo, truth
    from validation.photos import fit_frame, mapped_lights, mapped_split, score_run

    t = time.perf_counter()
    train, test = load_dataset(paths["gt"], "train"), load_dataset(paths["gt"], "test")
    try:
        sim, frame = fit_frame(cameras_by_photo(paths["import"]), truth(paths["photoset"]))
    except ValueError as exc:
        fail(f"{paths['import']}: {exc}")
    lights = dict(train.lights)
    # a light of zero irradiance (the control's second light, off) is no light to find
    lights["training"] = {**lights["training"], "lights": [
        lt for lt in lights["training"]["lights"] if max(lt["irradiance"]) > 0]}
    lights = mapped_lights(lights, sim)
    config = recorded(paths["run"])
    scores = score_run(paths["run"], mapped_split(train, sim, lights),
                       mapped_split(test, sim, lights), settings["preset"],
                       config.bounds_quantile, settings=config)
    return {**_registered(paths["import"]), "frame": frame, "similarity": sim.to_json(),
            "scores": scores, "gains": gain_scores(paths["run"], paths["photoset"]),
            "score_s": time.perf_counter() - t}


def _psnr(scores: dict, relighting: str):
    return (scores.get("relighting") or {}).get(relighting, {}).get("psnr")


def _status(value, ok) -> str:
    return "n/a" if value is None else ("pass" if ok(value) else "fail")


def acceptance(lab: dict, control: dict) -> list[dict]:
    """The acceptance rows of one case from the scores of its lab and control runs
    (``score_kind``): each figure of both, its bound, and the lab's pass, fail or n/a (not
    measured)."""
    from mi_shadowgs.dataset.capture import RELIGHT_LAMP_NAME

    ls, cs = lab["scores"], control["scores"]
    b = BOUNDS

    def first(seq):
        return None if not seq or seq[0] is None or not np.isfinite(seq[0]) else seq[0]

    pos = ls.get("lamp_position_error")
    rows = [
        ("lamp position error (share of its distance)", None,
         "fitted as directional" if pos and pos[0] is None else first(pos),
         f"<= {b['lamp_position']:g}",
         "fail" if pos and pos[0] is None else _status(first(pos),
                                                       lambda v: v <= b["lamp_position"])),
        ("light direction error (deg)", first(cs.get("light_angular_errors_deg")),
         first(ls.get("light_angular_errors_deg")), f"<= {b['lamp_direction_deg']:g}",
         _status(first(ls.get("light_angular_errors_deg")),
                 lambda v: v <= b["lamp_direction_deg"])),
        ("strongest light's share of the irradiance", cs.get("strongest_light_share"),
         ls.get("strongest_light_share"), f">= {b['strongest_share']:g}",
         _status(ls.get("strongest_light_share"), lambda v: v >= b["strongest_share"])),
        ("lights kept", cs.get("fitted_lights"), ls.get("fitted_lights"), "", "info"),
        ("of them lamps (the control's must stay directional)", cs.get("fitted_lamps"),
         ls.get("fitted_lamps"), "control: 0",
         _status(cs.get("fitted_lamps"), lambda v: v == 0))]
    for key, label, bound in (("shadow_iou", "shadow IoU", "shadow_iou_drop"),
                              ("albedo_psnr", "albedo PSNR (dB)", "albedo_psnr_drop_db")):
        lv, cv = ls.get(key), cs.get(key)
        diff = None if lv is None or cv is None else lv - cv
        rows.append((label, cv, lv, f">= control - {b[bound]:g}",
                     _status(diff, lambda d, k=bound: d >= -b[k])))
    lg, cg = lab.get("gains"), control.get("gains")

    def gmax(g):
        return None if not g or "global" not in g else g["global"]["max"]

    rows += [("per-view gain error after one global scale (max)", gmax(cg), gmax(lg),
              f"<= {b['gain_error']:g}", _status(gmax(lg), lambda v: v <= b["gain_error"])),
             ("relight PSNR (dB), mean of the relightings", cs.get("relight_psnr"),
              ls.get("relight_psnr"), "", "info"),
             ("relight PSNR (dB) under a new point lamp", _psnr(cs, RELIGHT_LAMP_NAME),
              _psnr(ls, RELIGHT_LAMP_NAME), "", "info"),
             ("photos registered by SfM", f"{control['registered']}/{control['photos']}",
              f"{lab['registered']}/{lab['photos']}", "", "info")]
    out = [dict(zip(("figure", "control", "lab", "bound", "status"), r, strict=True))
           for r in rows]
    for kind, run in (("lab", lab), ("control", control)):
        if "error" in run:  # a run that failed fails every bound on it
            out = [{**r, "status": "fail"} if r["status"] != "info" and (
                kind == "lab" or "control" in r["bound"]) else r for r in out]
    return out


def passed(rows: list[dict]) -> bool | None:
    """False when a bounded row fails; else None when one is not measured; else True."""
    marks = {r["status"] for r in rows}
    return False if "fail" in marks else (None if "n/a" in marks else True)


def _cell(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1 else f"{v:.2f}"
    return str(v)


def _secs(v) -> str:
    return "n/a" if v is None else f"{v:.0f}"


def case_markdown(case: dict) -> list[str]:
    verdict = {True: "passes", False: "fails", None: "not wholly measured"}[case["passed"]]
    lines = [f"### {case['scene']}, lamp at {case['distance']:g} object radii: {verdict}", ""]
    for kind, label in (("control", "The ideal control's"), ("lab", "The lab capture's")):
        if "error" in case[kind]:
            lines += [f"{label} run failed: `{case[kind]['error']}` ({case[kind]['where']}).",
                      ""]
    lines += ["| figure | ideal control | lab capture | bound | result |",
              "|---|---|---|---|---|"]
    for r in case["acceptance"]:
        status = {"pass": "**pass**", "fail": "**FAIL**", "n/a": "not measured",
                  "info": ""}[r["status"]]
        lines.append(f"| {r['figure']} | {_cell(r['control'])} | {_cell(r['lab'])} | "
                     f"{r['bound']} | {status} |")
    lines += ["", "| step (wall s) | ideal control | lab capture |", "|---|---|---|"]
    steps = (("generate the photos", "photoset_s"), ("generate the truth", "gt_s"),
             ("import (SfM)", "import_s"), ("run: stage 1", "stage1_s"),
             ("run: stage 2", "stage2_s"), ("run: stages 3-5", "stage4_s"),
             ("run: total", "run_s"), ("score", "score_s"))
    for label, key in steps:
        vals = [case[k]["times"].get(key) for k in KINDS]
        lines.append(f"| {label} | {_secs(vals[0])} | {_secs(vals[1])} |")
    c, lab = (case[k]["times"] for k in KINDS)
    if c.get("run_s") and lab.get("run_s"):
        lines.append(f"| run, lab / control | | {lab['run_s'] / c['run_s']:.2f}x |")
    if any(case[k]["times"].get("run_resumed") for k in KINDS):
        lines.append("\nA resumed run's total adds what its reused stages 1, 2 and 4 "
                     "recorded; what the interrupted call spent on stages 3 and 5 is left out.")
    return lines + [""]


def markdown(record: dict) -> str:
    s = record["settings"]
    lines = ["## Lab captures against their ideal control", "",
             f"`{record['command']}`; {record['date']}; commit {record['commit']}; preset "
             f"{s['preset']}; {s['views']} photos of {s['photo_size'][0]}x"
             f"{s['photo_size'][1]}, imported at {s['max_size']} px; extra settings: "
             f"{', '.join(s['sets']) or 'none'}; seed {s['seed']}.", "",
             "Bounds: the lamp's position within 5% of its distance and its direction "
             "within 2 deg (a fitted lamp's direction taken from the object's centre, "
             "as the lamp's is given); the strongest fitted light carries >= 90% of the fitted "
             "irradiance; the lab's shadow IoU and albedo PSNR at most 0.05 and 1 dB below "
             "the control's; the fitted per-photo gains within 3% after one global scale; "
             "the control's lights all directional. "
             "n/a: not measured (a run without fitted gains; the control's lights are "
             "directional).", ""]
    for case in record["cases"]:
        lines += case_markdown(case)
    return "\n".join(lines)


def run_case(out: Path, scene: str, mesh, distance: float, settings: dict,
             times: Times) -> dict:
    """Both runs of one case, made or reused, and scored: its record. A run that fails
    (the method raising, not a bad input) is recorded with its error, and the case fails."""
    import traceback

    from validation.pipeline import stage_seconds

    case = {"scene": scene, "distance": distance, "lamp": capture_params()}
    for kind in KINDS:  # the control first: shared by the scene's distances
        paths = make_kind(out, scene, mesh, kind, distance, settings, times)
        try:
            run_times = run_kind(out, paths, kind, settings)
        except Exception as exc:  # noqa: BLE001  (the method failed: recorded, not fatal)
            traceback.print_exc()
            frame = traceback.extract_tb(exc.__traceback__)[-1]
            # the stages it finished: their seconds from their own files
            stages = stage_seconds({}, paths["run"]) if paths["run"].is_dir() else {}
            case[kind] = {"error": f"{type(exc).__name__}: {exc}",
                          "where": f"{frame.filename}:{frame.lineno}", "scores": {},
                          "times": {**paths["times"], **stages},
                          **_registered(paths["import"])}
            continue
        record = score_kind(paths, settings)
        record["times"] = {**paths["times"], **run_times, "score_s": record.pop("score_s")}
        case[kind] = record
    case["acceptance"] = acceptance(case["lab"], case["control"])
    case["passed"] = passed(case["acceptance"])
    return case


def parse_args(argv):
    from validation.pipeline import SCENES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", "--scenes", default="default", dest="scenes",
                    help=f"scene or comma-separated scenes ({', '.join(SCENES)})")
    ap.add_argument("--distance", "--distances", default="6", dest="distances",
                    help="the lamp's distance(s) from the object's centre, in object radii "
                         "(comma-separated)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--preset", default="cpu-small")
    ap.add_argument("--photo-size", default="640x480", help="the photos' WIDTHxHEIGHT")
    ap.add_argument("--views", type=int, default=48, help="training photos")
    ap.add_argument("--max-size", type=int, default=None,
                    help="the imported views' longest side (default: the preset's width)")
    ap.add_argument("--set", action="append", default=[], dest="sets",
                    metavar="SECTION.FIELD=VALUE", help="a setting of both runs (repeatable)")
    ap.add_argument("--seed", type=int, default=0, help="both runs' seed (`run --seed`)")
    ap.add_argument("--threads", type=int, default=None, help="Dr.Jit threads")
    ap.add_argument("--results", default=None, metavar="DIR",
                    help="also write the table as DIR/lab.json (scripts.results)")
    return ap.parse_args(argv)


def _cases(args) -> tuple[list[tuple[str, object, float]], dict]:
    """The (scene, mesh, distance) cases and the study's settings, checked; exit 2 naming
    a bad option."""
    from mi_shadowgs.config import ConfigError
    from mi_shadowgs.presets import generate_config
    from validation.pipeline import available_scenes

    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    avail = available_scenes()
    for s in scenes:
        if s not in avail:
            fail(f"--scene {s}: not available (meshes under ../shared/data); available: "
                 f"{', '.join(avail)}")
    try:
        distances = [float(d) for d in args.distances.split(",") if d.strip()]
        size = parse_size(args.photo_size)
        width = generate_config(args.preset).width
    except (ValueError, ConfigError) as exc:
        fail(f"--distance / --photo-size / --preset: {exc}")
    lab = capture_params()
    least = 1.0 + float(lab["lamp_radius"])
    if not distances or any(not least < d < 1e3 for d in distances):
        fail(f"--distance {args.distances}: each must be > 1 + lamp radius = {least:g} "
             "object radii (a lamp outside the object)")
    if args.views < 3 or args.seed < 0 or (args.max_size is not None and args.max_size < 16):
        fail(f"--views {args.views} (>= 3), --seed {args.seed} (>= 0), --max-size "
             f"{args.max_size} (>= 16)")
    settings = {"preset": args.preset, "photo_size": list(size), "views": args.views,
                "max_size": args.max_size or width, "sets": list(args.sets),
                "seed": args.seed}
    try:  # the settings' own checks, before any data is made
        for kind in KINDS:
            run_config(kind, settings)
    except (ConfigError, ValueError) as exc:
        fail(f"--set / --seed: {exc}")
    return [(s, avail[s], d) for s in scenes for d in distances], settings


def main(argv=None) -> int:
    import sys

    args = parse_args(argv)
    cases, settings = _cases(args)
    out = claim_out(args.out, STUDY, ("lab.json",))
    check_settings(out, settings)
    if args.threads:
        import drjit as dr

        dr.set_thread_count(args.threads)
    from mi_shadowgs.io.atomic import write_json, write_text
    from mi_shadowgs.io.provenance import git_commit

    times = Times(out / TIMES_FILE)
    record = {"command": "python -m validation.lab " + " ".join(argv or sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d"), "commit": git_commit(),
              "settings": settings, "bounds": BOUNDS, "cases": []}
    for scene, mesh, distance in cases:
        record["cases"].append(run_case(out, scene, mesh, distance, settings, times))
        write_json(out / "lab.json", record)  # each finished case at once
        write_text(out / "lab.md", markdown(record))
    print(markdown(record))
    if args.results:
        import os
        import platform

        from scripts.results import lab_result, write_result

        machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
        write_result(Path(args.results) / "lab.json", lab_result(record, machine))
    failed = [f"{c['scene']} at {c['distance']:g} ({k})" for c in record["cases"]
              for k in KINDS if "error" in c[k]]
    if failed:
        print(f"runs that failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
