"""The whole method on the synthetic scenes: paper Tables 1 and 3, with stage figures.

For the embedded default scene and, when ``../shared/data`` is present, the five asset
scenes (bunny, armadillo, hotdog, ficus substitute, toy-train substitute for Lego), each under
two light pairs (``tuned``: the pair the presets were tuned on; ``low``: a second pair with
its strong light at 20 deg elevation), it generates the ``--preset`` dataset (``cpu-small``:
128^2, 64 views; ``cpu-medium``: 256^2, 96 views; ``gpu-large``: 512^2, 96 views, for a
GPU with ``MI_SHADOWGS_VARIANT=cuda_ad_rgb``), runs
``mi-shadowgs run`` (with the two Table 3 ablations under the tuned pair), and tabulates
stage 1, stage 2 and the decomposition/relighting metrics per scene and on average
(Tables 1 and 3)::

    python -m validation.pipeline --out OUT [--quick] [--scene NAME ...] [--lights PAIR ...]
                                  [--threads N] [--preset cpu-small|cpu-medium|gpu-large]
                                  [--seed N ...]

``--quick`` runs the default scene under the tuned pair only. Each scene and pair lives under
``OUT/<scene>-<pair>/`` (dataset, run, ``row.json``) and is resumed, not redone, on a second
call; the tables gather every ``row.json`` under OUT, so two processes with disjoint
``--scene``/``--lights`` subsets may share one OUT. One OUT holds one preset: a row or a
dataset of another preset already there is refused (exit 2), never reused or mixed; so is a
dataset made from other scene files or settings (its fingerprint).

``--address ADDR`` runs the rows as items of a batch on Ray (``mi_shadowgs.batch``): each
row (its dataset, its run, its ``row.json``) is one Ray task of ``--threads`` CPUs (default
1), run as ``python -m validation.pipeline ... --rows-only`` on a worker; ADDR is a cluster
(``auto``, HOST:PORT, ``ray://HOST:10001``) or ``local`` for a Ray runtime on this machine
(``--workers`` rows at once). The folders are the same as a serial call's, so the table is
gathered from them as before, and ``OUT/batch.csv`` and ``OUT/batch.html`` add each row's
status, time and error. A row of a later seed waits for the row that makes its dataset.

``--seed N`` (repeatable; default 0) runs each row at those seeds of every stage's random
draws (``RunConfig.seed``), on the one dataset: seed 0 in ``OUT/<scene>-<pair>/``, seed N in
``OUT/<scene>-<pair>-seed<N>/`` (its run and row only). The table then adds the spread over
seeds, so that a difference between two tables can be told from chance. The seeds of one row
share its dataset: give them to one process, or start a second process on other seeds of the
row only once the first has written the dataset.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.io.provenance import git_commit
from validation import claim_out, fail

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
# Light pairs: scene-XML overrides (azimuth and elevation in degrees, irradiance W/m^2).
LIGHT_PAIRS = {
    # the pair of default.xml/mesh.xml, on which the presets were tuned
    "tuned": {"light0_azimuth": "35", "light0_elevation": "50", "light0_irradiance": "3.0",
              "light1_azimuth": "215", "light1_elevation": "35", "light1_irradiance": "1.5"},
    # opposing azimuths away from the tuned ones; the strong light grazes at 20 deg, so its
    # shadows are long and leave the base, the weak one is high
    "low": {"light0_azimuth": "150", "light0_elevation": "20", "light0_irradiance": "3.0",
            "light1_azimuth": "330", "light1_elevation": "60", "light1_irradiance": "1.5"},
}
# The code a row ran: the checkout's commit when this module was imported (a later commit
# while a table runs does not change the code already loaded).
CODE_COMMIT = git_commit()
# The table's env-map relit views: the procedural sky alone. The shipped maps (GenerateConfig
# "auto") add three path-traced test sets per row, scored apart. One choice for every row
# keeps the rows comparable.
ENVMAPS = "sky"
# The presets a table can be made at (gpu-large's 512^2 runs take minutes each on a GPU,
# hours on 2 cores; the paper preset's 800^2 runs, with 40k stage-1 steps, longer still).
TABLE_PRESETS = ("cpu-small", "cpu-medium", "gpu-large")
TABLE_KEYS = ("albedo_psnr", "albedo_psnr_global", "albedo_ssim", "albedo_lpips",
              "light_cosine", "shadow_iou", "shadow_iou_decided", "relight_psnr",
              "relight_ssim", "relight_lpips", "relight_render_s")


def available_scenes() -> dict[str, Path | None]:
    out = {}
    for name, rel in SCENES.items():
        if rel is None:
            out[name] = None
        elif (SHARED_DATA / "meshes" / rel).is_file():
            out[name] = SHARED_DATA / "meshes" / rel
    return out


class PresetMismatch(ValueError):
    """A dataset or row under the output folder was made at another preset."""

    def __init__(self, path: Path, made: str | None, asked: str):
        super().__init__(f"{path}: made at preset {made!r}, this call asks for {asked!r}; "
                         "use another output folder")


class DatasetMismatch(ValueError):
    """A row's dataset folder holds a dataset of other scene files or settings."""


def row_preset(row: dict) -> str:
    """The preset a row was made at (rows from before the field: cpu-small)."""
    return row.get("preset", "cpu-small")


def dataset_preset(path: Path) -> str:
    """The preset a generated dataset (its ``dataset.json``) was made at; cpu-small where the
    file predates the field, as the rows of that time."""
    return json.loads(Path(path).read_text()).get("preset") or "cpu-small"


def make_dataset(name: str, mesh: Path | None, folder: Path, lights: str = "tuned",
                 envmaps: str = ENVMAPS, resolution: int | None = None,
                 preset: str = "cpu-small", pair: dict | None = None,
                 scene_overrides: dict | None = None, settings: dict | None = None,
                 photos: bool = False) -> Path:
    """The scene's ``preset`` dataset in ``folder/data`` under a light pair
    (``LIGHT_PAIRS[lights]``, or the scene-XML overrides ``pair``) with ``envmaps``
    (GenerateConfig's choice) for its env-map relit views, at ``resolution`` pixels square
    (None: the preset's); kept when it is already complete and made from the same scene
    files and settings (its fingerprint), refused (``DatasetMismatch``) when not.
    ``scene_overrides`` adds scene parameters (e.g. ``base_texture``), ``settings``
    GenerateConfig fields, and ``photos`` the photo set (``write_dataset``)."""
    import dataclasses

    from mi_shadowgs.dataset.writer import write_dataset
    from mi_shadowgs.presets import generate_config as get_config
    from mi_shadowgs.scenes import scene_path

    data = folder / "data"
    if (data / "dataset.json").is_file():
        made = dataset_preset(data / "dataset.json")
        if made != preset:
            raise PresetMismatch(data / "dataset.json", made, preset)
    # Kept only when its fingerprint is this row's (scene files, lights, settings).
    overrides = {**(LIGHT_PAIRS[lights] if pair is None else pair), **(scene_overrides or {})}
    if mesh is not None:
        overrides["mesh"] = str(mesh)
    config = dataclasses.replace(get_config(preset), envmaps=envmaps, **(settings or {}))
    if resolution is not None:
        config = dataclasses.replace(config, width=resolution, height=resolution)
    from mi_shadowgs.dataset.writer import OutputExistsError

    try:
        write_dataset(scene_path("default" if mesh is None else "mesh"), data,
                      config, preset, seed=0, progress=True,
                      overrides=overrides, photos=photos)
    except OutputExistsError:
        raise DatasetMismatch(
            f"{data}: holds a dataset made from other scene files or settings than this "
            "row's (its fingerprint differs); move it away or use another output folder"
        ) from None
    return data


def row_name(scene: str, lights: str, seed: int = 0) -> str:
    """A row's folder under the table's OUT, and its name in the tables."""
    return f"{scene}-{lights}" + (f"-seed{seed}" if seed else "")


def _row_label(row: dict) -> str:
    return row_name(row["scene"], row.get("lights", "tuned"), row.get("seed", 0))


def run_scene(name: str, mesh: Path | None, out: Path, lights: str = "tuned",
              ablations: bool = True, envmaps: str = ENVMAPS, pair: dict | None = None,
              preset: str = "cpu-small", seed: int = 0) -> dict:
    """One scene under one light pair (``LIGHT_PAIRS[lights]``, or ``pair`` named
    ``lights``) at ``preset`` (its dataset and every stage) and ``seed`` (every stage's
    random draws); its row is also written to ``row.json``. Every seed of a row runs on the
    dataset in the seed-0 folder, made there by whichever seed comes first."""
    import mitsuba as mi

    from mi_shadowgs.io.atomic import write_json
    from mi_shadowgs.pipeline import run_pipeline
    from mi_shadowgs.presets import build

    folder = out / row_name(name, lights, seed)
    if (folder / "row.json").is_file():  # finished: its row stands as recorded
        row = json.loads((folder / "row.json").read_text())
        if row_preset(row) != preset:
            raise PresetMismatch(folder / "row.json", row_preset(row), preset)
        return row
    t0 = time.perf_counter()
    pair = LIGHT_PAIRS[lights] if pair is None else pair
    data = make_dataset(name, mesh, out / row_name(name, lights), lights, envmaps,
                        preset=preset, pair=pair)
    t_gen = time.perf_counter() - t0
    # Table 3's ablations under the tuned pair only: the second pair measures the light fit
    ablations = ablations and lights == "tuned"
    summary = run_pipeline(data, folder / "run",
                           build(preset, {"ablations": ablations}, seed=seed),
                           progress=True)
    run = folder / "run"
    geo = json.loads((run / "geometry" / "metrics.json").read_text())
    seg = json.loads((run / "segmentation" / "segmentation.json").read_text())
    # every finished variant (an ablation may have finished before a run without them)
    variants = {v: json.loads((run / "material" / v / "metrics.json").read_text())
                for v in ("full", "no_visibility", "no_segmentation")
                if v == "full" or (run / "material" / v / "metrics.json").is_file()}
    row = {"scene": name, "lights": lights, "seed": seed, "light_pair": pair, "preset": preset,
           "variant": mi.variant(), "commit": CODE_COMMIT, "envmaps": envmaps,
           "generate_s": t_gen, "wall_s": time.perf_counter() - t0,
           "stage_s": {st["name"]: st.get("seconds") for st in summary.get("stages", [])},
           "load_end": os.getloadavg()[0],
           "report": str(run / "report.html"), "geometry": geo,
           "segmentation": seg.get("metrics", {}), "segments": seg.get("k"),
           "variants": variants, "summary_title": summary.get("title")}
    write_json(folder / "row.json", row)
    return row


STAGE_KEYS = {"stage1_s": "Stage 1: geometry", "stage2_s": "Stage 2: material segmentation",
              "stage4_s": "Stages 3-5: visibility, decomposition, relighting"}


def stage_seconds(stage_s: dict, run: Path | None = None) -> dict:
    """Stage 1, 2 and 3-5 seconds ({"stage1_s", "stage2_s", "stage4_s"}) from a summary's
    stage timers; those it lacks (a stage reused from an earlier call) from the run's own
    files: the last ``time`` of ``geometry/log.csv``, ``seconds_stage`` of
    ``segmentation.json``, ``fit_s`` of ``material/full/metrics.json`` (the fit alone)."""
    import csv

    out = {k: stage_s.get(v) for k, v in STAGE_KEYS.items()}
    if run is None or all(v is not None for v in out.values()):
        return out
    found = {}
    log = run / "geometry" / "log.csv"
    if log.is_file():
        with open(log, newline="") as f:
            rows = list(csv.DictReader(f))
        if rows and rows[-1].get("time"):
            found["stage1_s"] = float(rows[-1]["time"])
    seg = run / "segmentation" / "segmentation.json"
    if seg.is_file():
        found["stage2_s"] = json.loads(seg.read_text()).get("seconds_stage")
    met = run / "material" / "full" / "metrics.json"
    if met.is_file():
        found["stage4_s"] = json.loads(met.read_text()).get("fit_s")
    return {k: v if v is not None else found.get(k) for k, v in out.items()}


def _wall(row: dict) -> str:
    """The row's wall time in minutes. A row whose stages 1-2 were reused from an earlier
    call shows "a + b" (a: those stages' seconds from the run's files; b: this call); a row
    only gathered by its call (every stage reused) shows n/a."""
    own = row.get("stage_s") or {}
    if not any(own.values()):
        return "n/a (resumed)"
    if all(own.get(STAGE_KEYS[k]) is not None for k in ("stage1_s", "stage2_s")):
        return f"{row['wall_s'] / 60:.1f}"
    run = Path(row["report"]).parent
    secs = stage_seconds(own, run)
    earlier = sum(secs[k] or 0.0 for k in ("stage1_s", "stage2_s")
                  if own.get(STAGE_KEYS[k]) is None)
    return f"{earlier / 60:.1f} + {row['wall_s'] / 60:.1f}"


def _commits(rows: list[dict]) -> str:
    """The commits that wrote the rows, each with its rows when they differ."""
    by: dict[str, list[str]] = {}
    for r in rows:
        commit = str(r.get("commit", "unrecorded"))
        # the short hash, and the checkout's uncommitted changes when there were any
        short = commit[:12] + (" +changes" if commit.endswith("+changes") else "")
        by.setdefault(short, []).append(_row_label(r))
    if len(by) <= 1:
        return next(iter(by), "n/a")
    return "; ".join(f"{c} ({', '.join(names)})" for c, names in by.items())


# Evaluation changes a table must not mix silently: the metrics.json key each one added, and
# the note naming the rows evaluated before it.
EVALUATION_CHANGES = (
    ("albedo_estimate", "Albedo of {}: scored as rendered (alpha-blended), before the "
     "evaluation divided it by the pixel's coverage; not comparable with rows evaluated since."),
    ("scored_pixels", "Albedo and shadow IoU of {}: scored on every mask pixel, also where the "
     "ground truth has no surface, before the evaluation left those out; not comparable with "
     "rows evaluated since."),
    ("shadow_iou_decided", "Shadow IoU (decided) of {}: evaluated before the figure existed "
     "(nan)."),
)


def markdown(rows: list[dict], command: str) -> str:
    lines = ["## Whole pipeline (paper Tables 1 and 3)", "",
             f"`{command}`; {time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores, "
             f"load average {os.getloadavg()[0]:.1f} at the end; "
             f"{', '.join(sorted({r.get('variant', 'llvm_ad_rgb') for r in rows})) or 'n/a'}; "
             f"{', '.join(sorted({row_preset(r) for r in rows})) or 'n/a'}; "
             f"rows made by commit {_commits(rows)}; env maps: "
             f"{', '.join(sorted({str(r.get('envmaps', 'sky')) for r in rows})) or 'n/a'}.",
             "",
             "Stage 1 and 2 (test views):", "",
             "| scene | lights | PSNR dB | median normal err deg | mask IoU | segments | ARI | "
             "mIoU | wall min |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        g, s = r["geometry"], r["segmentation"]
        lines.append(f"| {r['scene']} | {_lights_cell(r)} | {g['psnr']:.2f} | "
                     f"{g.get('normal_error_median_deg', float('nan')):.2f} | "
                     f"{g['mask_iou']:.4f} | {r['segments']} | {s.get('ari', float('nan')):.3f} "
                     f"| {s.get('miou', float('nan')):.3f} | {_wall(r)} |")
    lines += ["", "Decomposition and relighting per variant (Table 1: full; Table 3: "
              "ablations, tuned pair); angle err: each true light's angular error to the "
              "fitted light set; fitted: lights kept; mean rows per light pair and over all, and "
              "the median over all:",
              "", "| scene | lights | variant | albedo PSNR | albedo PSNR (one scale) | "
              "albedo SSIM | albedo LPIPS | "
              "light cos | angle err deg | fitted | shadow IoU | shadow IoU (decided) | "
              "relit PSNR | relit SSIM | relit LPIPS | relight s (32 views) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    col = TABLE_KEYS.index("light_cosine") + 1

    def fmt(vals):
        return [f"{v:.4g}" for v in vals]

    for variant in ("full", "no_visibility", "no_segmentation"):
        groups: dict[str, list] = {}
        for r in rows:
            m = r["variants"].get(variant)
            if m is None:
                continue
            vals = [float("nan") if m.get(k) is None else m[k] for k in TABLE_KEYS]
            groups.setdefault(r.get("lights", "tuned"), []).append(vals)
            errs = "/".join(f"{e:.1f}" for e in m.get("angular_error_deg") or [])
            cells = fmt(vals)
            cells[col:col] = [errs or "n/a", str(m.get("fitted_lights", "n/a"))]
            lines.append(f"| {r['scene']} | {_lights_cell(r)} | {variant} | " +
                         " | ".join(cells) + " |")
        summaries = [(f"mean {k}", v, np.nanmean) for k, v in groups.items()]
        if len(groups) > 1:
            summaries.append(("mean all", [v for vs in groups.values() for v in vs],
                              np.nanmean))
        # The median beside the mean: a mean of PSNRs is carried by its best rows (the
        # single-material objects' 50-65 dB albedo), the median is what a typical row gets.
        if summaries:
            label, vals, _ = summaries[-1]
            summaries.append((label.replace("mean", "median", 1), vals, np.nanmedian))
        for label, vals, reduce in summaries:
            cells = fmt(reduce(np.array(vals, dtype=np.float64), axis=0))
            cells[col:col] = ["", ""]
            lines.append(f"| **{label}** ({len(vals)}) | | **{variant}** | " +
                         " | ".join(cells) + " |")
    # Rows evaluated before a change of the evaluation (their metrics.json lacks its key):
    # the columns named are not comparable with rows evaluated since.
    for key, note in EVALUATION_CHANGES:
        older = [_row_label(r) for r in rows
                 if (m := r["variants"].get("full")) and m.get("albedo_psnr") is not None
                 and m.get(key) is None]
        if older:
            lines += ["", note.format(", ".join(older))]
    lines += seed_spread(rows)
    return "\n".join(lines) + "\n"


def _lights_cell(row: dict) -> str:
    seed = row.get("seed", 0)
    return row.get("lights", "tuned") + (f", seed {seed}" if seed else "")


# The columns whose spread over seeds the table gives (the acceptance figures), and
# their headers.
SPREAD_KEYS = ("albedo_psnr", "light_cosine", "shadow_iou", "relight_psnr")
SPREAD_HEADERS = ("albedo PSNR", "light cos", "shadow IoU", "relit PSNR")


def seed_spread(rows: list[dict]) -> list[str]:
    """Markdown lines of the full variant's spread over seeds, when the rows hold more than
    one seed: per scene and pair, the mean with [min, max] over its seeds; then the table's
    mean at each seed that every scene and pair has, and the mean of the rows' seed means
    (every scene and pair weighted once). Empty for a table of one seed."""
    seeds = sorted({r.get("seed", 0) for r in rows})
    if len(seeds) < 2:
        return []
    by_row: dict[tuple[str, str], dict[int, dict]] = {}
    for r in rows:
        m = r["variants"].get("full")
        if m is not None:
            by_row.setdefault((r["scene"], r.get("lights", "tuned")), {})[r.get("seed", 0)] = m

    def value(m: dict, key: str) -> float:
        return float("nan") if m.get(key) is None else float(m[key])

    lines = ["", "Spread over seeds (full variant): mean [min, max] over each row's seeds:", "",
             "| scene | lights | seeds | " + " | ".join(SPREAD_HEADERS) + " |",
             "|---|---|---|" + "---|" * len(SPREAD_KEYS)]
    means = []
    for (scene, lights), per_seed in by_row.items():
        cells = []
        row_means = []
        for key in SPREAD_KEYS:
            vals = np.array([value(m, key) for m in per_seed.values()])
            row_means.append(np.nanmean(vals))
            cells.append(f"{np.nanmean(vals):.4g} [{np.nanmin(vals):.4g}, "
                         f"{np.nanmax(vals):.4g}]")
        means.append(row_means)
        lines.append(f"| {scene} | {lights} | {','.join(map(str, sorted(per_seed)))} | " +
                     " | ".join(cells) + " |")
    common = [s for s in seeds if all(s in per_seed for per_seed in by_row.values())]
    for s in common:
        vals = np.nanmean([[value(per_seed[s], k) for k in SPREAD_KEYS]
                           for per_seed in by_row.values()], axis=0)
        lines.append(f"| **mean all, seed {s}** ({len(by_row)}) | | {s} | " +
                     " | ".join(f"{v:.4g}" for v in vals) + " |")
    lines.append(f"| **mean all of the seed means** ({len(by_row)}) | | | " +
                 " | ".join(f"{v:.4g}" for v in np.nanmean(means, axis=0)) + " |")
    return lines


def gather_rows(out_dir: Path) -> list[dict]:
    """Every finished scene/pair row under ``out_dir``, in table order."""
    rows = [json.loads(p.read_text()) for p in Path(out_dir).glob("*/row.json")]
    order = {name: i for i, name in enumerate(SCENES)}
    pairs = {name: i for i, name in enumerate(LIGHT_PAIRS)}
    return sorted(rows, key=lambda r: (pairs.get(r.get("lights", "tuned"), 99),
                                       order.get(r["scene"], 99), r.get("seed", 0)))


def check_preset(out_dir: Path, preset: str) -> None:
    """Refuse (PresetMismatch) an output folder holding a row or a dataset of another
    preset: its tables would mix them."""
    for path in sorted(Path(out_dir).glob("*/row.json")):
        made = row_preset(json.loads(path.read_text()))
        if made != preset:
            raise PresetMismatch(path, made, preset)
    for path in sorted(Path(out_dir).glob("*/data/dataset.json")):
        made = dataset_preset(path)
        if made != preset:
            raise PresetMismatch(path, made, preset)


def batch_items(out_dir: Path, jobs: list[tuple[str, str]], seeds: list[int], preset: str,
                envmaps: str, ablations: bool, threads: int) -> list:
    """The rows as batch items (``mi_shadowgs.batch``): one ``validation.pipeline
    --rows-only`` call each, of ``threads`` CPUs (and a GPU under cuda_ad_rgb); done once
    its ``row.json`` is there; a row waits for the row of the same scene and pair that makes
    its dataset (the first seed's)."""
    from mi_shadowgs.backend import VARIANT_ENV
    from mi_shadowgs.batch.spec import Item, Step

    out = Path(out_dir).resolve()
    variant = os.environ.get(VARIANT_ENV)
    env = ((VARIANT_ENV, variant),) if variant else ()
    items, first = [], {}
    for seed in seeds:
        for scene, lights in jobs:
            name = row_name(scene, lights, seed)
            args = ("--out", str(out), "--scene", scene, "--lights", lights, "--seed",
                    str(seed), "--preset", preset, "--envmap", envmaps, "--threads",
                    str(threads), "--rows-only", *(() if ablations else ("--no-ablations",)))
            after = (first[(scene, lights)],) if (scene, lights) in first else ()
            first.setdefault((scene, lights), name)
            items.append(Item(name=name, folder=name, run=f"{name}/run",
                              steps=(Step("row", "validation.pipeline", args),), cpus=threads,
                              gpus=int(variant == "cuda_ad_rgb"), env=env, after=after,
                              done=f"{name}/row.json", preset=preset,
                              source=f"{scene}, {lights} lights, seed {seed}"))
    return items


def run(out_dir: Path, quick: bool = False, scenes: list[str] | None = None,
        command: str = "python -m validation.pipeline", lights: list[str] | None = None,
        ablations: bool = True, order: str = "pair", envmaps: str = ENVMAPS,
        preset: str = "cpu-small", seeds: list[int] | None = None,
        address: str | None = None, threads: int | None = None, workers: int | None = None,
        rows_only: bool = False, launcher=None) -> dict:
    """validation.run_all entry. With ``address``, the rows run as batch items on Ray
    (``batch_items``; ``threads`` CPUs each, ``workers`` rows at once on a local runtime,
    ``launcher``: how a worker starts a row, ``mi_shadowgs.batch.runner.Launcher``);
    ``rows_only`` leaves the tables to the caller. The result's ``failed`` lists the rows
    that failed (with ``address``; a serial call stops at the first)."""
    from mi_shadowgs.io.atomic import write_json, write_text

    out_dir = Path(out_dir)
    avail = available_scenes()
    chosen = ["default"] if quick else (scenes or list(avail))
    pairs = ["tuned"] if quick else (lights or list(LIGHT_PAIRS))
    missing = [s for s in chosen if s not in avail]
    if missing:
        raise FileNotFoundError(f"scenes {missing} need meshes under {SHARED_DATA / 'meshes'}")
    if preset not in TABLE_PRESETS:
        raise ValueError(f"preset must be one of {TABLE_PRESETS}, got {preset!r}")
    check_preset(out_dir, preset)
    # order "pair": the whole table under one pair first; "scene": both pairs of a scene
    jobs = [(s, p) for p in pairs for s in chosen] if order == "pair" else \
        [(s, p) for s in chosen for p in pairs]
    failed = []
    if address is not None:
        from mi_shadowgs.batch.runner import run_batch

        items = batch_items(out_dir, jobs, seeds or [0], preset, envmaps, ablations,
                            threads or 1)
        done = run_batch(items, out_dir, address=address, launcher=launcher,
                         num_cpus=None if workers is None else workers * (threads or 1))
        failed = [r for r in done if r["status"] not in ("finished", "reused")]
    else:
        for seed in seeds or [0]:
            for s, pair in jobs:
                run_scene(s, avail[s], out_dir, pair, ablations, envmaps, preset=preset,
                          seed=seed)
    if rows_only:
        return {"rows": [], "markdown": "", "failed": failed}
    rows = gather_rows(out_dir)
    md = markdown(rows, command)
    write_json(out_dir / "pipeline.json", rows)
    write_text(out_dir / "pipeline.md", md)
    return {"rows": rows, "markdown": md, "failed": failed}


def main(argv=None) -> int:
    import sys

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="output folder (datasets, runs, tables)")
    ap.add_argument("--quick", action="store_true", help="the default scene only")
    ap.add_argument("--scene", action="append", choices=sorted(SCENES),
                    help="run only this scene (repeatable)")
    ap.add_argument("--lights", action="append", choices=sorted(LIGHT_PAIRS),
                    help="run only this light pair (repeatable)")
    ap.add_argument("--threads", type=int, default=None,
                    help="Dr.Jit threads (default: all cores); two processes with one "
                         "thread each and disjoint subsets may share --out")
    ap.add_argument("--no-ablations", action="store_true",
                    help="skip the Table 3 ablations (two more stage-4 fits per tuned row)")
    ap.add_argument("--order", choices=("pair", "scene"), default="pair",
                    help="pair: every scene under one pair first; scene: both pairs of a "
                         "scene first")
    ap.add_argument("--envmap", choices=("sky", "auto", "none"), default=ENVMAPS,
                    help="env maps of the datasets' env-map relit views (default: the "
                         "procedural sky; auto: the shipped maps when present)")
    ap.add_argument("--preset", choices=TABLE_PRESETS, default="cpu-small",
                    help="the datasets' and every stage's preset (default cpu-small; one "
                         "preset per --out)")
    ap.add_argument("--seed", type=int, action="append", default=None,
                    help="run every row at this seed of every stage's random draws "
                         "(repeatable; default 0); the table adds the spread over seeds")
    ap.add_argument("--table-only", action="store_true",
                    help="only gather the finished rows under --out into the tables")
    ap.add_argument("--address", default=None,
                    help="run the rows as Ray tasks (--threads CPUs each, default 1) on this "
                         "cluster (auto, HOST:PORT, ray://HOST:10001) or 'local' (a Ray "
                         "runtime on this machine); needs pip install .[cluster]")
    ap.add_argument("--workers", type=int, default=None,
                    help="with --address local: rows at once (default: cores / --threads)")
    ap.add_argument("--rows-only", action="store_true",
                    help="run the rows, leave the tables to the caller (how a Ray worker "
                         "runs one row)")
    args = ap.parse_args(argv)
    if args.threads is not None and args.threads < 1:
        fail(f"--threads must be >= 1, got {args.threads}")
    if args.workers is not None and (args.workers < 1 or args.address not in (None, "local")):
        fail("--workers takes a count >= 1, with --address local (a cluster has the CPUs "
             "it has)")
    if args.threads:
        import drjit as dr

        dr.set_thread_count(args.threads)
    command = "python -m validation.pipeline " + " ".join(argv or sys.argv[1:])
    claim_out(args.out, "validation.pipeline", ("pipeline.json",))
    if args.table_only:
        from mi_shadowgs.io.atomic import write_text

        md = markdown(gather_rows(Path(args.out)), command)
        write_text(Path(args.out) / "pipeline.md", md)
        print(md)
        return 0
    if any(s < 0 for s in args.seed or []):
        fail(f"--seed must be >= 0, got {args.seed}")
    from mi_shadowgs.batch.runner import BatchError, RayMissing
    from mi_shadowgs.io.outlock import OutputPathError

    try:
        res = run(Path(args.out), args.quick, args.scene, command, args.lights,
                  not args.no_ablations, args.order, args.envmap, args.preset,
                  sorted(set(args.seed or [0])), address=args.address,
                  threads=args.threads, workers=args.workers, rows_only=args.rows_only)
    except (PresetMismatch, DatasetMismatch, RayMissing, BatchError, OutputPathError) as e:
        fail(str(e))
    print(res["markdown"])
    for r in res["failed"]:
        print(f"row {r['name']} failed: {r['error']}", file=sys.stderr)
    return 1 if res["failed"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
