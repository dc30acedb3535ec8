"""Re-run stages 3-5 (visibility, material/light fit, evaluation) of a finished run with
today's stage-4 code, into a folder of one's own, and set the light metrics beside the run's:
how a change to the light fit moves a scene without redoing stages 1-2.

    python -m validation.refit_lights --run RUN --data DATA --out DIR [--set KEY=VALUE ...]
    python -m validation.refit_lights --table DIR ...   (gather the refit.json under DIRs)
    python -m validation.refit_lights --run RUN --data DATA --settle-only

``--set`` overrides a stage-4 setting (e.g. ``refine_global=0 refine_again_global=False
drop_share=0`` for the fit without dropped lights). Writes (atomically) ``refit.json``
(before/after metrics), ``light.json`` and ``metrics.json`` into ``--out``; reads the run,
never writes there. The fit is a unit (``validation.units``, ``OUT/units/refit/``, with stage
4's checkpoint): a killed call, run again, continues it; other settings or another model
exit 2 naming them.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import time
from pathlib import Path

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs import presets as run_presets
from validation import claim_out, fail

KEYS = ("fitted_lights", "angular_error_deg", "spurious_irradiance_fraction", "light_cosine",
        "shadow_iou", "albedo_psnr", "albedo_psnr_global", "relight_psnr")


def _value(text: str):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def material_config(preset: str, overrides: dict):
    """Stage 4's settings of preset ``preset`` with ``overrides`` ({field: value})."""
    from mi_shadowgs.presets import build

    return build(preset, {"material": overrides}).material


def with_label_source(run: Path, preset: str, overrides: dict) -> dict:
    """``overrides`` with the stage-4 settings that ``run`` fitted with for the source of its
    segments' labels (stage 2's ``masks`` in ``segmentation.json``: on chromaticity ones
    ``MaterialConfig.chromaticity_*``, as ``run`` applies them); a setting in ``overrides``
    wins."""
    from mi_shadowgs.stages.material.config import label_source_overrides

    record = run / "segmentation" / "segmentation.json"
    try:
        source = json.loads(record.read_text()).get("masks") if record.is_file() else None
        if source is None:  # no record of it: the preset's, as before these settings
            return overrides
        changed = label_source_overrides(material_config(preset, overrides), source)
    except (ValueError, AttributeError) as e:  # unreadable JSON, not a dict, unknown source
        raise ValueError(f"{record}: field 'masks': {e}") from e
    return {**changed, **overrides}


def refit(run: Path, data: Path, overrides: dict, progress: bool = True,
          before: bool = True, checkpoints: dict | None = None) -> dict:
    """Stages 3-5 of ``run`` again on ``data``; ``checkpoints``: ``state`` and
    ``on_checkpoint`` of stage 4."""
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.io.provenance import read_manifest
    from mi_shadowgs.presets import get_config
    from mi_shadowgs.stages.common import load_training_views
    from mi_shadowgs.stages.evaluation.evaluate import evaluate_decomposition
    from mi_shadowgs.stages.material.outputs import light_json
    from mi_shadowgs.stages.material.runner import decompose, occluder_bounds

    before_path = run / "material" / "full" / "metrics.json"
    settings = (read_manifest(run / "material" / "full") or {}).get("settings", {})
    preset = run_presets.recorded(run).preset
    train = load_training_views(data)
    test = load_dataset(data, "test")
    surfels = load_ply(run / "segmentation" / "model.ply")
    bounds = occluder_bounds(surfels, train.cameras, float(settings.get("bounds_quantile", 0.98)))
    t0 = time.perf_counter()
    tree = get_config(preset)
    res = decompose(surfels, train, material_config(preset, overrides), tree.visibility, bounds,
                    progress=progress, **(checkpoints or {}))
    fit_s = time.perf_counter() - t0
    metrics, _ = evaluate_decomposition(res, train, test, bounds, tree.visibility, tree.relight)
    metrics["fit_s"] = fit_s
    # Read at the end: the run's own stage 4 may still be running when this starts. With
    # another dataset than the run's (the same scene and cameras under other lights: a
    # stress test of the light fit on the run's geometry) there is no "before".
    if before and not before_path.is_file():
        raise FileNotFoundError(f"{before_path}: not found (is the run finished?)")
    before = json.loads(before_path.read_text()) if before else {}
    name = run.parent.name if run.name == "run" else run.name
    if not before:
        name = f"{name} model on {data.parent.name if data.name == 'data' else data.name}"
    return {"name": name, "run": str(run), "data": str(data), "overrides": overrides,
            "before": {k: before.get(k) for k in KEYS},
            "after": {k: metrics.get(k) for k in KEYS}, "fit_s": fit_s,
            "loadavg": list(os.getloadavg()), "metrics": metrics, "light": light_json(res)}


def settle_only(run: Path, data: Path) -> dict:
    """``settle_lights`` (merge, then drop by joint NNLS) on the lights of a finished run's
    stage-4 fit, its materials held fixed, scored on the refinement's training views: which
    lights the data needs (seconds; no refit)."""
    import dataclasses

    import numpy as np

    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.presets import material_config as get_config
    from mi_shadowgs.stages.common import load_training_views
    from mi_shadowgs.stages.evaluation import metrics as evaluation
    from mi_shadowgs.stages.material.lights import settle_lights
    from mi_shadowgs.stages.material.runner import occluder_bounds
    from mi_shadowgs.stages.material.views import prepare_view
    from mi_shadowgs.stages.visibility import shadow_maps

    folder = run / "material" / "full"
    light = json.loads((folder / "light.json").read_text())
    model = load_ply(folder / "model.ply")
    train = load_training_views(data)
    cfg, vcfg = get_config("cpu-small"), run_presets.visibility_config("cpu-small")
    bounds = occluder_bounds(load_ply(run / "segmentation" / "model.ply"), train.cameras, 0.98)
    pick = np.unique(np.linspace(0, len(train.views) - 1, cfg.refine_views).round()
                     .astype(int))
    views = [prepare_view(model, train.views[i].camera, train.views[i].image,
                          train.views[i].mask, cfg,
                          receiver_band=vcfg.receiver_band) for i in pick]
    ch = {k: model.channels[k] for k in ("albedo", "roughness", "metallic", "indirect_sh")}

    def render(d, resolution=None):
        vc = vcfg if resolution is None else dataclasses.replace(vcfg, resolution=resolution)
        return shadow_maps.render_shadow_maps(model, d, bounds, vc)

    gt = train.lights["training"]["lights"]
    gt_dirs = np.array([g["direction"] for g in gt])
    gt_w = np.array([np.mean(g["irradiance"]) for g in gt])
    dirs, irr = np.asarray(light["directions"]), np.asarray(light["irradiance"], float)
    d2, e2, _ = settle_lights(views, ch, dirs, irr, render(dirs), render, cfg,
                              light["specular"])
    out = {}
    for key, (d, e) in (("run", (dirs, irr)), ("settled", (d2, e2))):
        out[key] = {**evaluation.light_angular_errors(d, e, gt_dirs),
                    "light_cosine": evaluation.light_cosine(d, e, gt_dirs, gt_w),
                    "irradiance": np.asarray(e).tolist()}
    return out


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, list):
        return ", ".join(f"{x:.1f}" for x in v)
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)


def markdown(rows: list[dict]) -> str:
    cols = ("fitted_lights", "angular_error_deg", "spurious_irradiance_fraction",
            "light_cosine", "shadow_iou", "albedo_psnr", "albedo_psnr_global", "relight_psnr")
    head = "| run | overrides | " + " | ".join(f"{c} (before -> after)" for c in cols) + \
        " | fit s |"
    lines = [head, "|---|---|" + "---|" * len(cols) + "---|"]
    for r in rows:
        ov = " ".join(f"{k}={v}" for k, v in r["overrides"].items()) or "defaults"
        cells = [f"{_fmt(r['before'].get(c))} -> {_fmt(r['after'].get(c))}" for c in cols]
        lines.append(f"| {r['name']} | {ov} | " + " | ".join(cells) + f" | {r['fit_s']:.0f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from mi_shadowgs.dataset.fingerprint import dataset_ref
    from mi_shadowgs.io.atomic import write_json, write_text
    from mi_shadowgs.io.provenance import Provenance, input_ref
    from validation.units import run_unit, settings_of

    ap = argparse.ArgumentParser(description="Re-run stages 3-5 of a finished run with "
                                             "today's light fit into a folder of one's own.")
    ap.add_argument("--run", type=Path)
    ap.add_argument("--data", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="stage-4 setting overrides")
    ap.add_argument("--other-data", action="store_true",
                    help="DATA is not the run's dataset (same scene and cameras, other "
                         "lights): the run's stages 1-2 model, no 'before' column")
    ap.add_argument("--settle-only", action="store_true",
                    help="only settle_lights on the run's fitted lights (no refit); prints")
    ap.add_argument("--table", type=Path, nargs="*", default=None)
    ap.add_argument("--quiet", action="store_true")
    ap.add_argument("--threads", type=int, default=None, help="Dr.Jit threads")
    args = ap.parse_args(argv)
    if args.threads:
        import drjit as dr

        dr.set_thread_count(args.threads)
    if args.settle_only:
        if args.run is None or args.data is None:
            ap.error("--settle-only needs --run and --data")
        print(json.dumps(settle_only(args.run, args.data), indent=1))
        return 0
    if args.table is not None:
        rows = [json.loads(p.read_text()) for d in args.table
                for p in sorted(Path(d).rglob("refit.json"))]
        if not rows:
            fail(f"no refit.json under {args.table}")
        print(markdown(rows))
        return 0
    if args.run is None or args.data is None or args.out is None:
        ap.error("--run, --data and --out are required (or --table)")
    overrides = {}
    for item in args.set:
        if "=" not in item:
            fail(f"--set {item!r}: expected KEY=VALUE")
        k, v = item.split("=", 1)
        overrides[k] = _value(v)
    from mi_shadowgs.config import ConfigError

    try:  # before any work, the run's folder too: a setting the config refuses exits 2
        material_config("cpu-small", overrides)
    except (ConfigError, ValueError) as e:
        fail(f"--set: {e}")
    try:
        preset = run_presets.recorded(args.run).preset
    except ConfigError as e:
        fail(str(e))
    try:  # and at the run's own preset
        material_config(preset, overrides)
    except (ConfigError, ValueError) as e:
        fail(f"--set: {e}")
    try:
        overrides = with_label_source(args.run, preset, overrides)
    except ValueError as e:
        fail(str(e))
    model = args.run / "segmentation" / "model.ply"
    if not model.is_file():
        fail(f"{model}: not found (--run takes a finished run)")
    if args.run.resolve() in (args.out.resolve(), *args.out.resolve().parents):
        fail(f"--out {args.out}: inside the run {args.run}, which this tool only reads")
    claim_out(args.out, "validation.refit_lights", ("refit.json",),
              inputs=(args.run, args.data))

    def fit(unit) -> dict:
        from mi_shadowgs.stages.common import checkpoint_hooks
        from mi_shadowgs.stages.material.state import MaterialState

        return refit(args.run, args.data, overrides, not args.quiet, not args.other_data,
                     checkpoint_hooks(unit, MaterialState.from_checkpoint))

    provenance = Provenance(dataset_ref(args.data), {"model": input_ref(model)},
                            settings_of(preset=preset, overrides=overrides,
                                        other_data=args.other_data))
    res = run_unit(args.out, "refit", "validation.refit_lights", provenance, fit,
                   inputs=(args.run, args.data))
    write_json(args.out / "refit.json", {k: v for k, v in res.items() if k != "metrics"})
    write_json(args.out / "metrics.json", res["metrics"])
    write_json(args.out / "light.json", res["light"])
    write_text(args.out / "refit.md", markdown([res]) + "\n")
    print(markdown([res]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
