"""The run's summary and report assembly: ``summary.json`` (the tables, figures and
provenance that ``mi_shadowgs.io.report`` renders as ``report.html``), built from the files
of a run folder, and the report's figures."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from mi_shadowgs.core.directions import angles_from_direction, direction_from_angles
from mi_shadowgs.io.atomic import write_json
from mi_shadowgs.presets import RunConfig
from mi_shadowgs.stages.geometry.gains import GAINS_FILE

# The ground truth of the stage-1 and stage-2 metrics (stage 5's: relight.METRIC_NEEDS); a
# metric whose ground truth the dataset lacks is not computed, and the summary says so.
STAGE_METRIC_NEEDS = {
    "geometry normal error": ("test normals",),
    "geometry depth error": ("test depth",),
    "segmentation ARI/mIoU": ("test material ids",),
    "segmentation lit/shadowed base check": ("test material ids", "test visibility"),
}


def _csv_columns(path: Path) -> dict[str, list[float]]:
    """Numeric columns of a CSV file (empty or non-numeric cells: NaN); {} if absent."""
    import csv

    if not path.is_file():
        return {}
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))

    def num(v) -> float:
        try:
            return float(v)
        except (TypeError, ValueError):
            return float("nan")

    return {k: [num(r.get(k)) for r in rows] for k in (rows[0] if rows else {})}


def _light_map_figure(path: Path, variant: Path, data: Path, earlier: Path | None = None
                      ) -> bool:
    """The labelled 22x12 light map of a variant's ``light.json`` beside the dataset's
    ground truth (``lights.json``); False when the fit has no light.json. Both maps hold
    radiance on the light grid's directions only, and a light (true, or fitted and refined
    off the grid) lies between them: the figure marks the grid and where the maps put each
    true light."""
    import numpy as np

    from mi_shadowgs.core.directions import light_grid, map_to_blocks, nearest_grid_index
    from mi_shadowgs.io.plots import light_map_png

    fit = _json_or_empty(variant / "light.json")
    if not fit.get("radiance"):
        return False

    def blocks(radiance) -> np.ndarray:
        r = np.asarray(radiance, np.float64)
        return map_to_blocks(r.mean(-1) if r.ndim == 2 else r)

    truth = _json_or_empty(data / "lights.json").get("training", {})
    gt_map = truth.get("light_map", {}).get("radiance")
    grid = light_grid(len(fit["radiance"]))
    errors = _json_or_empty(variant / "metrics.json").get("angular_error_deg") or []
    gt_lights = []
    for k, lt in enumerate(truth.get("lights", [])):
        if "azimuth_deg" in lt and "elevation_deg" in lt:
            az, el = float(lt["azimuth_deg"]), float(lt["elevation_deg"])
        elif "direction" in lt:
            az, el = angles_from_direction(lt["direction"])
        else:
            continue
        err = errors[k] if k < len(errors) and errors[k] is not None else None
        err_text = f", error {err:.1f}\u00b0" if err is not None and err == err else ""
        g_az, g_el = angles_from_direction(grid[int(nearest_grid_index(
            direction_from_angles(az, el), grid)[0])])
        gt_lights.append({"azimuth": az % 360.0, "elevation": el, "label":
                          f"{lt.get('name', f'light {k}')} (az {az:.0f}\u00b0, "
                          f"el {el:.0f}\u00b0){err_text}", "grid_azimuth": g_az,
                          "grid_elevation": g_el})
    fitted = []
    dirs = np.asarray(fit.get("directions") or np.zeros((0, 3)), np.float64).reshape(-1, 3)
    w = np.asarray(fit.get("irradiance") if fit.get("irradiance") is not None
                   else np.ones(len(dirs)), np.float64)
    if w.ndim == 2 and w.shape[0] != len(dirs):
        w = w.T  # [3, K] -> [K, 3]
    w = w.mean(-1) if w.ndim == 2 else w
    for d, weight in zip(dirs, w.reshape(-1) if w.size == len(dirs) else np.ones(len(dirs)),
                         strict=True):
        az, el = angles_from_direction(d)
        fitted.append({"azimuth": az, "elevation": el, "weight": float(weight)})
    light_map_png(path, blocks(fit["radiance"]), blocks(gt_map) if gt_map else None,
                  gt_lights, fitted, np.asarray([angles_from_direction(d) for d in grid
                                                 if d[1] > 0]), earlier=earlier)
    return True


# Stage 1's loss terms that start late: (setting of the start, of the weight, the term).
_LATE_TERMS = (("normal_from", "lambda_normal", "normal loss"),
               ("dist_from", "lambda_dist", "distortion loss"))


def loss_term_starts(run: Path) -> list[dict]:
    """Where stage 1's late loss terms start, as the curves mark them: ``{"x": iteration,
    "setting": "normal_from", "label": ...}``, read from the run's recorded settings
    (``geometry/config.json``, else ``RUN/config.json``); a term with weight 0, or that
    starts at 0 or after the last iteration, is not marked."""
    cfg = (_json_or_empty(run / "geometry" / "config.json").get("config")
           or _json_or_empty(run / "config.json").get("geometry") or {})
    out = []
    for start, weight, term in _LATE_TERMS:
        x, w, last = cfg.get(start), cfg.get(weight), cfg.get("iterations")
        if (isinstance(x, int) and isinstance(w, int | float) and w > 0 and x > 0
                and (not isinstance(last, int) or x < last)):
            out.append({"x": x, "setting": start,
                        "label": f"{term} from iteration {x} ({start})"})
    return out


def write_report_figures(folder: Path, run: Path, data: Path, earlier: Path | None = None
                         ) -> None:
    """The report's plots into ``folder`` from the run's files, each only when its data is
    there: stage-1 training curves (``geometry/log.csv``, with where each late loss
    term starts: ``loss_term_starts``), stage-4 loss
    (``material/*/history.csv``), the labelled light map of the full fit and the colour bar
    of the error maps. A plot that ``earlier`` (the report's folder) holds drawn from the
    same inputs is copied from there (``io.plots``)."""
    from mi_shadowgs.io.plots import colorbar_png, curves_png

    log = _csv_columns(run / "geometry" / "log.csv")
    if log.get("iteration"):
        it = log["iteration"]
        panels = [{"ylabel": label, "log": key == "loss",
                   "lines": [{"x": it, "y": log[key]}]}
                  for key, label in (("loss", "training loss"), ("psnr", "training PSNR (dB)"),
                                     ("surfels", "surfels")) if key in log]
        curves_png(folder / "geometry_curves.png", panels, title="Stage 1: geometry",
                   markers=loss_term_starts(run), earlier=earlier)
    lines = []
    for hist in [v / "history.csv" for v in _variant_folders(run)]:
        h = _csv_columns(hist)
        if h.get("step"):
            lines.append({"x": h["step"], "y": h["loss"], "label": hist.parent.name})
    if lines:
        curves_png(folder / "material_loss.png",
                   [{"ylabel": "loss (mean since last entry)", "log": True, "lines": lines}],
                   xlabel="step", title="Stage 4: material and light", earlier=earlier)
    _light_map_figure(folder / "light_map.png", run / "material" / "full", data, earlier)
    if (run / "material" / "full" / "grid.json").is_file():
        colorbar_png(folder / "error_scale.png", earlier=earlier)


def _json_or_empty(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def skipped_table(results: dict, available: dict | None) -> dict | None:
    """The metrics not computed for want of ground truth: what each needs and why."""
    rows = []
    if available is not None:
        for metric, needs in STAGE_METRIC_NEEDS.items():
            why = [available[n] for n in needs if available.get(n)]
            if why:
                rows.append([metric, ", ".join(needs), "; ".join(why)])
    for item in (results.get("full") or {}).get("skipped") or []:
        rows.append([item["metric"], ", ".join(item["needs"]), item["why"]])
    if not rows:
        return None
    return {"title": "Metrics not computed (the dataset lacks their ground truth)",
            "columns": ["metric", "needs", "why not"], "rows": rows,
            "note": "n/a in the tables above: not computed. The decomposition and the relit "
                    "previews below need no ground truth."}


def build_summary(run: Path, data: Path, config: RunConfig, results: dict, stages: list,
                  seconds: float, available: dict | None = None,
                  reused: list[str] | None = None) -> dict:
    """The report's ``summary.json`` (see ``mi_shadowgs.io.report``) from the run's files;
    ``available``: the dataset's ground truth (``relight.evaluate.ground_truth``), for the
    table of skipped metrics. ``seconds`` are this call's; ``reused`` names the stages an
    earlier call made (their seconds are not in it: a resumed run's figure is not the
    run's)."""
    import mitsuba as mi

    from mi_shadowgs.stages.evaluation.metrics import SHADOW_UNDECIDED_BAND

    geo = _json_or_empty(run / "geometry" / "metrics.json")
    seg = _json_or_empty(run / "segmentation" / "segmentation.json")
    cols = ["variant", "albedo PSNR", "albedo PSNR (one scale)", "albedo SSIM", "albedo LPIPS",
            "light cosine", "shadow IoU", "shadow IoU (decided)", "relight PSNR", "relight SSIM",
            "relight LPIPS", "relight time (s)"]
    rows = [[name, r.get("albedo_psnr"), r.get("albedo_psnr_global"), r.get("albedo_ssim"),
             r.get("albedo_lpips"), r.get("light_cosine"), r.get("shadow_iou"),
             r.get("shadow_iou_decided"), r.get("relight_psnr"), r.get("relight_ssim"),
             r.get("relight_lpips"), r.get("relight_render_s")]
            for name, r in results.items()]
    skipped = sorted({r["lpips_skipped"] for r in results.values() if r.get("lpips_skipped")})
    secs = {name: s for name, s in stages}
    info = _json_or_empty(data / "dataset.json")
    scene = Path(str(info.get("scene", data.name))).stem
    summary = {
        "title": f"mi_shadowgs run: {scene} ({data.name})",
        "dataset": str(data.resolve()), "preset": config.preset, "variant": mi.variant(),
        "date": time.strftime("%Y-%m-%d %H:%M"), "total_seconds": seconds,
        "reused_stages": list(reused or []),
        "tables": [{"title": "Decomposition and relighting (paper Tables 1 and 3)",
                    "columns": cols, "rows": rows,
                    "note": "Albedo: per-channel median scale per material region; relit "
                            "views: one global per-channel albedo scale; shadow IoU: "
                            "direct irradiance below half the view's median ((decided): "
                            "without the pixels whose true irradiance is within "
                            f"{SHADOW_UNDECIDED_BAND:.0%} of that, where round-off decides "
                            "the truth); LPIPS: AlexNet "
                            "v0.1 on sRGB views, background at 0."
                            + "".join(f" LPIPS not computed: {why}." for why in skipped)}],
        "stages": [],
    }
    if geo:
        scalars = {k: v for k, v in geo.items() if not isinstance(v, (list, dict))}
        summary["stages"].append({"name": "Stage 1: geometry", "seconds": secs.get("geometry"),
                                  "metrics": scalars, "figures": _previews(run)})
    if seg:
        m = dict(seg.get("metrics", {}))
        m.update({"K": seg.get("k"), "masks": seg.get("masks")})
        segs = _listed(run / "segmentation", "segments/", "_overlay.png")[:4]
        summary["stages"].append({
            "name": "Stage 2: material segmentation", "seconds": secs.get("segmentation"),
            "metrics": m, "figures": [{"title": p.stem, "path": str(p.relative_to(run))}
                                      for p in segs]})
    if ((run / "report" / "geometry_curves.png").is_file() and summary["stages"]
            and summary["stages"][0]["name"].startswith("Stage 1")):
        summary["stages"][0]["figures"].insert(0, {
            "title": "training curves (geometry/log.csv)", "path": "report/geometry_curves.png",
            "wide": True, "markers": loss_term_starts(run)})
    skipped_tab = skipped_table(results, available)
    if skipped_tab:
        summary["tables"].insert(1, skipped_tab)
        summary["skipped_metrics"] = [{"metric": r[0], "needs": r[1], "why": r[2]}
                                      for r in skipped_tab["rows"]]
    lights_tab = _fitted_lights_table(run / "material" / "full" / "light.json")
    if lights_tab:
        summary["tables"].append(lights_tab)
    gains_tab = view_gains_table(run / "geometry" / GAINS_FILE)
    if gains_tab:
        summary["tables"].append(gains_tab)
    summary["tables"] += _per_view_tables(results.get("full", {}))
    speed = _speed_table(results.get("full", {}), info)
    if speed:
        summary["tables"].append(speed)
    summary["provenance"] = _provenance(run, config, mi.variant())
    _add_material_stage(summary, run, data, results, secs)
    held = _held_channels(results, config)
    for grid in [summary.get("grid")] + list(summary.get("grids") or []):
        notes = {c: held[c] for c in (grid or {}).get("columns", []) if c in held}
        if notes:
            grid["column_notes"] = notes
    summary["stages"].append(speed_error_stage(run))
    return summary


def _add_material_stage(summary: dict, run: Path, data: Path, results: dict, secs: dict
                        ) -> None:
    """The full fit's figure grid(s) and the stages 3-5 entry (light map, relit previews,
    loss curve) into ``summary``, when the fit wrote its grid."""
    full = run / "material" / "full"
    if (full / "grid.json").is_file():
        grid = json.loads((full / "grid.json").read_text())
        grid["rows"] = [{"label": r["label"],
                         "cells": [f"material/full/figures/{c}" for c in r["cells"]]}
                        for r in grid["rows"]]
        previews = grid.pop("previews", None)
        grids = _split_grid(grid)
        if any(c.endswith(" error") for c in grids[0]["columns"]):
            grids[0]["note"] = ("error: |estimate - ground truth| as displayed (sRGB, mean "
                                "over RGB); estimates aligned to ground truth as in the table "
                                "above")
            if (run / "report" / "error_scale.png").is_file():
                grids[0]["legend"] = "report/error_scale.png"
        summary["grid"] = grids[0]
        if len(grids) > 1:
            summary["grids"] = grids[1:]
        figures = []
        has_truth = bool(_json_or_empty(data / "lights.json").get("training", {})
                         .get("light_map"))
        if (run / "report" / "light_map.png").is_file():
            figures.append({"title": "light map, 22x12 blocks: estimate | ground truth; "
                                     "rings: true lights, crosses: fitted lights (their "
                                     "own directions); dots: the 128-direction light grid. "
                                     "Both maps hold radiance on the grid's directions only, "
                                     "so a light's bright block is that of its nearest grid "
                                     "direction (+), beside its ring or cross, not an error"
                                     if has_truth else
                                     "light map, 22x12 blocks over azimuth/elevation: "
                                     "estimate (no ground truth); crosses: fitted lights "
                                     "(their own directions); dots: the light grid, the only "
                                     "directions the map holds radiance on",
                            "path": "report/light_map.png", "wide": True})
        else:
            figures.append({"title": "light map 22x12: estimate | ground truth",
                            "path": "material/full/figures/light_map.png"})
        for strip in (previews or {}).get("strips", []):
            figures.append({"title": "relit preview, " + strip["title"] + "; exposure: the "
                            "fitted light's irradiance on an upward surface",
                            "path": f"material/full/figures/{strip['file']}", "wide": True})
        if (run / "report" / "material_loss.png").is_file():
            figures.append({"title": "stage-4 loss (material/*/history.csv)",
                            "path": "report/material_loss.png", "wide": True})
        summary["stages"].append({
            "name": "Stages 3-5: visibility, decomposition, relighting",
            "seconds": secs.get("material (full)"),
            "metrics": {k: v for k, v in results.get("full", {}).items()
                        if not isinstance(v, (dict, list))},
            "figures": figures})


# Columns of the decomposition (no ground truth needed) and of the comparison with ground
# truth; "input" leads both.
_DECOMPOSITION = ("albedo", "roughness", "metallic", "normal", "irradiance", "visibility",
                  "segments")


def _held_channels(results: dict, config: RunConfig) -> dict[str, str]:
    """What the grid says under a channel the full fit did not fit (its images a constant):
    metallic and roughness when the fit modelled no specular lobe, because the preset has
    none (``specular "off"``) or because the fit dropped it after the warm-up (``"auto"``)."""
    if (results.get("full") or {}).get("specular") is not False:
        return {}
    if config.variants()["full"].specular == "off":
        return {"metallic": "held at 0 by the preset (specular \"off\")",
                "roughness": "not fitted: the preset models no specular lobe"}
    return {"metallic": "held at 0: the fit dropped the specular lobe (specular \"auto\")",
            "roughness": "not fitted after the warm-up (no specular lobe)"}


def _split_grid(grid: dict) -> list[dict]:
    """The figures grid as [comparison with ground truth, decomposition] when the dataset
    has ground truth (the comparison keeps the paper's Fig. 3 layout), else
    [decomposition]."""
    cols = grid["columns"]

    def pick(keep, title) -> dict:
        idx = [i for i, c in enumerate(cols) if c == "input" or keep(c)]
        return {"title": title, "columns": [cols[i] for i in idx],
                "rows": [{"label": r["label"], "cells": [r["cells"][i] for i in idx]}
                         for r in grid["rows"]]}

    decomposition = pick(lambda c: c.startswith(_DECOMPOSITION) and "(GT)" not in c and
                         not c.endswith(" error"),
                         "Decomposition of test views: albedo, roughness/metallic, normals, "
                         "irradiance, visibility of the strongest fitted lights, segments")
    truth = [c for c in cols if "(GT)" in c]
    if not truth:
        return [decomposition]
    compare = pick(lambda c: c.startswith(("albedo", "irradiance", "relit ")),
                   "Input, albedo, irradiance and relighting against ground truth "
                   "(cf. paper Fig. 3)")
    return [compare, decomposition]


def _fitted_lights_table(path: Path) -> dict | None:
    """The full fit's lights (``light.json``): azimuth, elevation, irradiance, strongest
    first."""
    import numpy as np

    fit = _json_or_empty(path)
    dirs = np.asarray(fit.get("directions") or np.zeros((0, 3)), np.float64).reshape(-1, 3)
    if not len(dirs):
        return None
    w = np.asarray(fit.get("irradiance") if fit.get("irradiance") is not None
                   else np.full(len(dirs), np.nan), np.float64).reshape(len(dirs), -1).mean(-1)
    total = np.nansum(w)
    rows = []
    lamps = _lamp_cells(fit, len(dirs))
    for k in np.argsort(-np.nan_to_num(w)):
        az, el = angles_from_direction(dirs[k])
        rows.append([int(len(rows) + 1), az, el, float(w[k]),
                     float(w[k] / total) if total > 0 else None, *(lamps[k] if lamps else [])])
    note = ("Azimuth about +Y from +X toward -Z, elevation above the base "
            "(docs/conventions.md); irradiance in the fit's own scale (albedo and "
            "light are known only up to a common factor).")
    if lamps:
        note += (" A lamp's azimuth, elevation and irradiance are those at the fit's centre "
                 f"({', '.join(f'{v:.3g}' for v in fit['center'])}), its distance from there "
                 "and its position in world units; a directional light has neither.")
    return {"title": "Fitted lights (material/full/light.json)",
            "columns": ["light", "azimuth (deg)", "elevation (deg)", "irradiance",
                        "share of irradiance",
                        *(["distance", "position (x, y, z)", "radius"] if lamps else [])],
            "rows": rows, "note": note}


def _lamp_cells(fit: dict, count: int) -> list | None:
    """Per light of a light.json: [distance from its centre, "(x, y, z)", radius] for a
    lamp, [None, "directional", None] for another; None when no light is a lamp."""
    import numpy as np

    positions = fit.get("positions")
    if not positions or len(positions) != count or all(p is None for p in positions):
        return None
    c = np.asarray(fit.get("center") or [0.0, 0.0, 0.0], np.float64)
    radii = list(fit.get("radii") or [0.0] * count)
    return [[None, "directional", None] if p is None else
            [float(np.linalg.norm(np.asarray(p, np.float64) - c)),
             "({:.3g}, {:.3g}, {:.3g})".format(*p), float(radii[k])]
            for k, p in enumerate(positions)]


def view_gains_table(path: Path) -> dict | None:
    """Stage 1's per-view exposure and white balance (``geometry/view_gains.json``, with
    ``GeometryConfig.view_gains`` on): each training view's EV and RGB gain, and beside them
    the truth and the error where the capture's true gains are known; None without the file."""
    record = _json_or_empty(path)
    views = record.get("views") or []
    if not views:
        return None
    truth = record.get("truth")
    cols = ["view", "photo", "fit PSNR (dB)", "EV", "gain R", "gain G", "gain B"]
    if truth:
        cols += ["true EV", "true R", "true G", "true B", "error (%)"]
    rows = []
    for v in views:
        row = [v["name"], v.get("photo") or "", v.get("psnr"), v["ev"], *v["gain"]]
        if truth:
            scale = truth["scale"]  # the truth in the fit's scale, channel by channel
            t = [g / s for g, s in zip(v["true_gain"], scale, strict=True)]
            row += [v["true_ev"] - sum(map(math.log2, scale)) / 3.0, *t, 100.0 * v["error"]]
        rows.append(row)
    note = ("gain: photo = gain * render, per channel; EV: the mean of the channels' log2 "
            "gains; the gains' log has mean 0 over the views in every channel (the colours "
            "take the rest); fit PSNR: the gained render against the photo (where it is low "
            "the model does not explain the photo, and its gain is not measured).")
    backdrop = _json_or_empty(path.parent / "backdrop.json").get("rgb")
    if backdrop:
        note += (" The renders lie over the backdrop estimated from the pixels that miss the "
                 "SfM support (geometry/backdrop.json): linear RGB "
                 + ", ".join(f"{c:.4f}" for c in backdrop) + ".")
    if truth:
        note += (f" True gains ({truth['file']}) divided by one scale per channel; error: "
                 f"the largest over the channels of |gain / true - 1|: max "
                 f"{100 * truth['max_error']:.2f}%, mean {100 * truth['mean_error']:.2f}%.")
    return {"title": "Exposure and white balance per training view (geometry/view_gains.json)",
            "columns": cols, "rows": rows, "note": note}


SPEED_ERROR_STAGE = "Speed against error"
# Where ``validation.speed_error --attach`` says which sweep its plots came from.
SPEED_ERROR_SOURCE = "speed_error/source.json"


def speed_error_stage(run: Path) -> dict:
    """The report's speed-against-error section: the PNGs in ``RUN/speed_error/`` (which
    ``python -m validation.speed_error --attach RUN`` puts there), with the sweep they came
    from, or a note saying how to make them."""
    plots = sorted((run / "speed_error").glob("*.png"))
    if not plots:
        note = ("No speed-against-error plots for this run (`python -m validation.speed_error "
                "--attach RUN` puts them into RUN/speed_error/).")
    else:
        note = ("A study of the method, not a measurement of this run: each plot is a sweep "
                "of settings around cpu-small on the scene its title names")
        try:
            source = json.loads((run / SPEED_ERROR_SOURCE).read_text())
            note += (f"; attached {source.get('date', '?')} from {source.get('sweep', '?')}"
                     + (f" (`{source['command']}`)" if source.get("command") else "") + ".")
        except (OSError, ValueError, AttributeError):
            note += "; put here by hand (no speed_error/source.json)."
    return {"name": SPEED_ERROR_STAGE,
            "figures": [{"title": p.stem, "path": p.relative_to(run).as_posix(), "wide": True}
                        for p in plots],
            "note": note}


def refresh_speed_error(run: Path) -> bool:
    """Bring ``RUN/summary.json``'s speed-against-error section up to date with the files
    in ``RUN/speed_error/`` (plots added after the run); True when it changed."""
    from mi_shadowgs.io.report import read_summary

    path = Path(run) / "summary.json"
    try:
        summary = read_summary(path)
    except (OSError, ValueError):
        return False  # write_report names the missing or malformed file
    stages = summary.setdefault("stages", [])
    new = speed_error_stage(Path(run))
    old = [i for i, st in enumerate(stages) if st.get("name") == SPEED_ERROR_STAGE]
    if old and stages[old[0]] == new:
        return False
    if old:
        stages[old[0]] = new
    else:
        stages.append(new)
    write_json(path, summary)
    return True


PAPER_RENDER_S = 100.0  # paper Sec. V-A4: "Rendering the 200 test views takes ~100 seconds"
PAPER_VIEWS = 200


def _per_view_tables(metrics: dict) -> list[dict]:
    """PSNR/SSIM/LPIPS of each test view: albedo and every relighting (full fit), one row
    per view and lighting, so that the table keeps its five columns however many
    relightings the dataset has."""
    per = {"albedo": metrics.get("albedo_per_view")}
    per.update({name: r.get("per_view") for name, r in (metrics.get("relighting") or {}).items()})
    per = {k: v for k, v in per.items() if isinstance(v, dict) and v.get("psnr")}
    if not per:
        return []
    n = max(len(v["psnr"]) for v in per.values())
    names = metrics.get("test_views") or []
    rows = []
    for i in range(n):
        for kind, v in per.items():
            vals = [(v.get(m) or [])[i] if i < len(v.get(m) or []) else None
                    for m in ("psnr", "ssim", "lpips")]
            rows.append([names[i] if i < len(names) else f"view {i}", kind, *vals])
    return [{"title": "Per test view (full fit)",
             "columns": ["view", "image", "PSNR", "SSIM", "LPIPS"], "rows": rows,
             "note": "image: the albedo, or the view relit under that lighting (albedo scaled "
                     "by one global per-channel factor); n/a: not computed (see the table "
                     "above)"}]


def _speed_table(metrics: dict, dataset: dict) -> dict | None:
    """Render time of the test views per relighting and extrapolated to the paper's 200."""
    rows = []
    relit = metrics.get("relighting") or {}
    views = len(metrics.get("test_views") or (metrics.get("albedo_per_view") or {})
                .get("psnr") or []) or max([r.get("views") or 0 for r in relit.values()],
                                           default=0)
    if metrics.get("decomposition_render_s") is not None and views:
        t = metrics["decomposition_render_s"]
        rows.append(["decomposition (albedo, irradiance)", "fitted",
                     metrics.get("active_directions"), views, t, t / views,
                     PAPER_VIEWS * t / views])
    for name, r in relit.items():
        if r.get("render_s") is None or not r.get("views"):
            continue
        t, n = r["render_s"], r["views"]
        rows.append([name, r.get("type"), r.get("light_directions"), n, t, t / n,
                     PAPER_VIEWS * t / n])
    if not rows:
        return None
    rows.append(["paper (one RTX A6000)", "", 128, PAPER_VIEWS, PAPER_RENDER_S,
                 PAPER_RENDER_S / PAPER_VIEWS, PAPER_RENDER_S])
    cfg = dataset.get("config") or {}
    size = f" of {cfg['width']}x{cfg['height']} px" if "width" in cfg and "height" in cfg else ""
    return {"title": f"Render speed for {PAPER_VIEWS} test views (paper Sec. V-A4)",
            "columns": ["render", "lights", "light directions", "views rendered", "time (s)",
                        "per view (s)", f"{PAPER_VIEWS} views (s)"],
            "rows": rows,
            "note": f"Measured on the run's test views{size}; the {PAPER_VIEWS}-view time is "
                    "extrapolated linearly from the measured time per view, not measured. "
                    "Shadow maps are rendered once per light and reused for every view, so "
                    "the extrapolation overestimates. The paper's row is its own figure "
                    "(its resolution and GPU), not measured here."}


def _provenance(run: Path, config: RunConfig, variant: str) -> list[dict]:
    """Commit, versions, variant, device and settings of the run, with links to the
    stages' resolved settings (manifests, config files). Commit, variant, device and Dr.Jit
    threads are this call's, unless the stages' manifests record others (``made_with``: a
    stage made or resumed on another backend or by another commit): then each value names
    the stages it made."""
    import platform

    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.io.provenance import MANIFEST_NAME, device_name, made_with

    made = _stage_backends(run)
    threads = dr.thread_count() if variant.startswith("llvm") else None
    backend = [{"name": name, "value": _per_stage(made, key, now)}
               for name, key, now in (("variant", "variant", variant),
                                      ("device", "device", device_name(variant)),
                                      ("Dr.Jit threads", "threads", threads))]
    commit = _per_stage(made, "mi_shadowgs", made_with()["mi_shadowgs"])
    out = [{"name": "commit", "value": commit},
           {"name": "Mitsuba", "value": mi.__version__},
           {"name": "Dr.Jit", "value": dr.__version__},
           {"name": "Python", "value": platform.python_version()},
           *[row for row in backend if row["value"] is not None],
           {"name": "preset", "value": config.preset}]
    links = [run / "geometry" / "config.json"]
    links += [run / part / MANIFEST_NAME for part in ("", "geometry", "segmentation")]
    links += [v / MANIFEST_NAME for v in _variant_folders(run)]
    for path in links:
        if path.is_file():
            rel = path.relative_to(run).as_posix()
            out.append({"name": "settings", "value": rel, "href": rel})
    return out


def _stage_backends(run: Path) -> list[tuple[str, list[dict]]]:
    """(stage, its manifest's ``made_with`` entries) of the run's stages: geometry,
    segmentation and each stage-4 fit; stages from before the record have none."""
    from mi_shadowgs.io.provenance import ProvenanceError, read_manifest, recorded_backends

    out = []
    for stage in ("geometry", "segmentation",
                  *(f"material/{v.name}" for v in _variant_folders(run))):
        try:
            manifest = read_manifest(run / stage)
        except (OSError, ProvenanceError):
            manifest = None
        out.append((stage, recorded_backends(manifest)))
    return out


def _per_stage(made: list[tuple[str, list[dict]]], key: str, now):
    """The report's value of ``key`` (variant, device, threads, mi_shadowgs's commit):
    ``now`` (this call's) when every stage's record agrees with it or none has one, else
    each recorded value with the stages it made: "cuda_ad_rgb (geometry), llvm_ad_rgb
    (segmentation, material/full)"."""
    seen: dict = {}
    for stage, entries in made:
        for entry in entries:
            if isinstance(entry.get(key), str | int | float):
                stages = seen.setdefault(entry[key], [])
                if stage not in stages:
                    stages.append(stage)
    if not seen or set(seen) == {now}:
        return now
    return ", ".join(f"{value} ({', '.join(stages)})" for value, stages in seen.items())


def _listed(folder: Path, prefix: str, suffix: str) -> list[Path]:
    """The files of ``folder``'s manifest named ``prefix...suffix`` that are there, sorted:
    a file put beside them by hand is not shown as the run's."""
    from mi_shadowgs.io.provenance import read_manifest

    files = (read_manifest(folder) or {}).get("files") or []
    return sorted(folder / n for n in files if n.startswith(prefix) and n.endswith(suffix)
                  and (folder / n).is_file())


def _variant_folders(run: Path) -> list[Path]:
    """The folders of the run's stage-4 fits (``run_fits``: a folder put under
    ``material/`` by hand is not read as a fit)."""
    from mi_shadowgs.stages.relight.runner import run_fits

    return [run / "material" / name for name in run_fits(run)]


def _previews(run: Path) -> list[dict]:
    prev = _listed(run / "geometry", "previews/", ".png")
    return [{"title": f"training preview {p.stem}", "path": str(p.relative_to(run))}
            for p in prev[-1:]]
