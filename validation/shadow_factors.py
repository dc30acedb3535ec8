"""Where a finished run's shadow IoU is lost: swap in ground truth one factor at a time.

Stage 5 scores shadows on the test views by the IoU of the masks where the white direct
irradiance sum_k E_k (n . l_k)^+ V_k falls below half the view's median
(``stages.relight.evaluation.shadow_iou``). The estimate has three ingredients, each of which
is swapped here for the ground truth of the dataset's scene (reloaded and ray-traced with
Mitsuba, as ``validation.visibility`` does):

- **lights** (L): the fitted directions and irradiance (``light.json``) -> the true ones;
- **receivers** (R): the points and normals rasterized from the surfels (as stage 5's,
  ``VisibilityConfig.receiver_band``) -> the ray-traced ground-truth depth and normals of
  each pixel;
- **occluders** (O): the surfels' shadow maps -> Mitsuba's ``ray_test`` toward each light
  through the true scene, from the same receiver points (from a surfel point the ray starts
  ``TRACE_LIFT`` pixel footprints off the surface along n and l: such points lie up to a
  pixel inside the true surface, which would otherwise shadow them).

All 2^3 combinations are scored; a factor's share of the loss is its Shapley value (its gain
averaged over the 3! orders of swapping), so the three shares add up to IoU(all ground truth)
- IoU(run). What remains below 1 with everything swapped is the metric's own floor
(anti-aliased ground-truth irradiance vs pixel-centre rays).

**Exact geometry**: the method itself on a perfect stage 1 and perfect lights. Surfels
sampled on the true shapes (``validation.visibility.scene_surfels``; ``--exact-surfels`` on
the object at 128^2 views, scaled with the test views' pixel count) give both the receivers
(rasterized as the run's) and the shadow maps, under the true lights: an estimate of what
this view size allows the method.

**Threshold/bias**: the shadow maps' depth bias tau and normal offset are swept with the
run's own lights and receivers, and the best setting's gain is reported beside the factors,
as are the gains of swapping only the receivers' points or only their normals (and the
normals only in the shading's n . l, or only in the shadow-map lookup's normal offset), and
of fractional (opacity) shadow maps (``VisibilityConfig.fractional``) instead of the binary
depth test.

    python -m validation.shadow_factors --run RUN --data DATA --out DIR [--variant full]
                                        [--views N] [--exact-surfels N] [--quiet]

Writes (atomically) ``shadow_factors.json`` and ``shadow_factors.md`` into ``--out``
(never inside the run: it reads only); ``--table`` gathers every ``shadow_factors.json`` under
the folders given into one markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM, selects the variant)
from mi_shadowgs.core.depth import pixel_footprint, unproject_depth
from mi_shadowgs.dataset.scene import Light
from mi_shadowgs.stages.relight import evaluation
from validation import fail

FACTORS = ("lights", "receivers", "occluders")
TRACE_LIFT = 1.5  # pixel footprints off a surfel receiver before tracing (see above)
# (tau, normal_offset, bias_texels) settings of the bias sweep; the paper preset's are (8e-4,
# 1.5, None), cpu-small's (-, 1.5, 1.0) with the layer slack. With bias_texels the threshold is
# absolute, in map texels, tau is unused and the run's layer slack applies.
BIAS_SWEEP = ((0.0, 1.5, None), (2e-4, 1.5, None), (8e-4, 0.0, None), (8e-4, 0.75, None),
              (8e-4, 3.0, None), (2e-3, 1.5, None), (5e-3, 1.5, None), (8e-4, 1.5, 1.0),
              (8e-4, 1.5, 2.0), (8e-4, 1.5, 3.0), (8e-4, 1.5, 5.0), (8e-4, 1.5, 8.0))


@dataclasses.dataclass
class RunInputs:
    """What the analysis reads from a finished run and its dataset."""

    name: str
    model: object  # Surfels with the material channels (stage 4's model.ply)
    fit_dirs: np.ndarray  # [K, 3]
    fit_irr: np.ndarray  # [K] white irradiance
    true_dirs: np.ndarray  # [G, 3]
    true_irr: np.ndarray  # [G] mean-RGB irradiance
    cameras: list  # test cameras
    mask: np.ndarray  # [V, H, W] bool
    gt_irr: np.ndarray  # [V, H, W] the dataset's white direct irradiance
    bounds: object  # SceneBounds of stage 3-5
    vis_config: object  # VisibilityConfig of the run's preset
    recorded_iou: float | None  # the run's metrics.json shadow_iou
    preset: str


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found (is the run finished?)")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: malformed JSON ({e})") from None


def load_inputs(run: Path, data: Path, variant: str = "full", views: int | None = None
                ) -> RunInputs:
    from mi_shadowgs.dataset.loader import load_cameras, load_dataset
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.io.provenance import read_manifest
    from mi_shadowgs.stages.material.runner import occluder_bounds
    from mi_shadowgs.stages.relight.evaluate import scored_pixels
    from mi_shadowgs.stages.relight.runner import recorded_config, run_preset
    from mi_shadowgs.stages.visibility import shadow_maps

    folder = run / "material" / variant
    light = _read_json(folder / "light.json")
    metrics = _read_json(folder / "metrics.json")
    settings = (read_manifest(folder) or {}).get("settings", {})
    preset = run_preset(run)
    if light.get("directions") is None or light.get("irradiance") is None:
        raise ValueError(f"{folder / 'light.json'}: no 'directions'/'irradiance' (an older run)")
    test = load_dataset(data, "test")
    if views:
        test.views = test.views[:views]
    gt_lights = (test.lights or {}).get("training", {}).get("lights") or []
    if not gt_lights:
        raise ValueError(f"{data}: lights.json has no training lights")
    train_cams = [c for _, c in load_cameras(data / "transforms_train.json")]
    seg = load_ply(run / "segmentation" / "model.ply")
    bounds = occluder_bounds(seg, train_cams, float(settings.get("bounds_quantile", 0.98)))
    # the visibility settings stage 4 ran with, as relighting reads them
    vcfg = recorded_config(shadow_maps.VisibilityConfig, settings.get("visibility"),
                           lambda: shadow_maps.get_config(preset))
    name = run.parent.name if run.name == "run" else run.name
    return RunInputs(
        name, load_ply(folder / "model.ply"),
        np.asarray(light["directions"], np.float64),
        np.asarray(light["irradiance"], np.float64).reshape(len(light["directions"]), -1)
        .mean(-1),
        np.array([lt["direction"] for lt in gt_lights], np.float64),
        np.array([np.mean(lt["irradiance"]) for lt in gt_lights], np.float64),
        [v.camera for v in test.views], scored_pixels(test),
        test.stack("irradiance").sum(axis=3).mean(-1), bounds, vcfg,
        metrics.get("shadow_iou"), preset)


@dataclasses.dataclass
class Receivers:
    """Per view: points [P], normals [P] (Dr.Jit), footprints [P] or None."""

    points: list
    normals: list
    footprints: list
    normals_np: list  # [P, 3] float64


def surfel_receivers(model, cameras, receiver_band: float = 0.0) -> Receivers:
    """Stage 5's receivers: the surfels' rasterized depth and normals, blended over the
    pixel or over its median surface (``VisibilityConfig.receiver_band``)."""
    from mi_shadowgs.core import shading

    pts, nrm, foot, nnp = [], [], [], []
    for cam in cameras:
        # the shading normals where the model has them
        geom = shading.pixel_geometry(model, cam, surface_band=receiver_band)
        pts.append(geom.points)
        nrm.append(geom.normal)
        foot.append(geom.footprint)
        nnp.append(np.stack([np.asarray(geom.normal[k], np.float64) for k in range(3)], -1))
    return Receivers(pts, nrm, foot, nnp)


def gt_receivers(gt: dict, cameras) -> Receivers:
    """Ray-traced ground-truth depth and normals as receivers (exact: no footprint)."""
    pts, nrm, foot, nnp = [], [], [], []
    for v, cam in enumerate(cameras):
        depth = mi.TensorXf(gt["depth"][v].astype(np.float32)[..., None])
        pts.append(unproject_depth(depth, cam))
        n = gt["normal"][v].reshape(-1, 3).astype(np.float32)
        nrm.append(mi.Vector3f(n[:, 0], n[:, 1], n[:, 2]))
        foot.append(pixel_footprint(depth, cam))  # only for the trace lift
        nnp.append(n.astype(np.float64))
    return Receivers(pts, nrm, [None] * len(cameras), nnp)


def traced_visibility(scene, rec: Receivers, dirs: np.ndarray, lift_from: list | None
                      ) -> list[np.ndarray]:
    """V [P, L] per view by Mitsuba's ray_test toward each direction through the true scene.
    ``lift_from``: per-view footprints when the points are surfel points (see TRACE_LIFT);
    None for ray-traced points (spawned as Mitsuba does, with its own epsilon)."""
    out = []
    for v, p in enumerate(rec.points):
        cols = []
        n = rec.normals[v]
        for d in dirs:
            l_dir = mi.Vector3f(*(float(x) for x in d))
            if lift_from is None:
                o = p + n * 1e-4 + l_dir * 1e-4
            else:
                o = p + (n + l_dir) * (TRACE_LIFT * lift_from[v])
            ray = mi.Ray3f(mi.Point3f(o), l_dir)
            occ = scene.ray_test(ray)
            cols.append(np.asarray(dr.select(occ, 0.0, 1.0), np.float64))
        out.append(np.stack(cols, -1))
    return out


def map_visibility(model, rec: Receivers, dirs: np.ndarray, bounds, vcfg) -> list[np.ndarray]:
    from mi_shadowgs.stages.visibility.shadow_maps import render_shadow_maps

    maps = render_shadow_maps(model, dirs, bounds, vcfg)
    out = []
    with dr.suspend_grad():
        for v, p in enumerate(rec.points):
            vis = maps.evaluate(p, rec.normals[v], rec.footprints[v])
            out.append(np.asarray(vis, np.float64).reshape(-1, len(dirs)))
    return out


def irradiance(rec: Receivers, vis: list[np.ndarray], dirs: np.ndarray, irr: np.ndarray,
               shape) -> np.ndarray:
    """White direct irradiance [V, H, W] = sum_k E_k (n . l_k)^+ V_k."""
    out = []
    for v, n in enumerate(rec.normals_np):
        cos = np.maximum(n @ dirs.T, 0.0)  # [P, L]
        out.append((cos * vis[v] * irr[None]).sum(-1).reshape(shape))
    return np.stack(out)


def method_irradiance(surfels, cameras, dirs: np.ndarray, irr: np.ndarray, bounds, vcfg
                      ) -> np.ndarray:
    """The method's white direct irradiance [V, H, W] with ``surfels`` as both receivers
    (rasterized as stage 5's) and occluders (their shadow maps), lights ``dirs`` [L, 3] of
    irradiance ``irr`` [L]: the run's model, or surfels on the true shapes."""
    rec = surfel_receivers(surfels, cameras, vcfg.receiver_band)
    vis = map_visibility(surfels, rec, dirs, bounds, vcfg)
    return irradiance(rec, vis, dirs, irr, (cameras[0].height, cameras[0].width))


def shapley(scores: dict[tuple, float]) -> dict[str, float]:
    """Each factor's gain in IoU averaged over the orders of swapping it in.
    ``scores`` maps (lights, receivers, occluders) booleans (True = ground truth) to IoU."""
    out = {f: 0.0 for f in FACTORS}
    orders = list(itertools.permutations(range(len(FACTORS))))
    for order in orders:
        state = [False] * len(FACTORS)
        for i in order:
            before = scores[tuple(state)]
            state[i] = True
            out[FACTORS[i]] += (scores[tuple(state)] - before) / len(orders)
    return out


def analyse(run: Path, data: Path, variant: str = "full", views: int | None = None,
            progress: bool = True, exact_surfels: int | None = None) -> dict:
    """The split of one run (see the module's doc); ``exact_surfels``: on the object for the
    exact geometry at 128^2 views (default the visibility validation's), scaled with the
    test views' pixel count, the base's too (``visibility.exact_surfel_config``)."""
    from tqdm import tqdm

    from mi_shadowgs.dataset.generate import trace_ground_truth
    from mi_shadowgs.dataset.scene import dataset_scene
    from validation.visibility import ValidationConfig, exact_surfel_config, scene_surfels

    t0 = time.perf_counter()
    inp = load_inputs(run, data, variant, views)
    setup = dataset_scene(data)
    h, w = inp.mask.shape[1:]
    light_sets = {False: (inp.fit_dirs, inp.fit_irr), True: (inp.true_dirs, inp.true_irr)}
    gt = trace_ground_truth(setup, inp.cameras, [
        Light(f"t{k}", tuple(d.tolist()), (1.0, 1.0, 1.0), 0.0, 0.0)
        for k, d in enumerate(inp.true_dirs)])
    recs = {False: surfel_receivers(inp.model, inp.cameras, inp.vis_config.receiver_band),
            True: gt_receivers(gt, inp.cameras)}
    scores, vis_cache = {}, {}
    combos = list(itertools.product((False, True), repeat=3))
    for key in tqdm(combos, desc=f"{inp.name}: factors", disable=not progress):
        gl, gr, go = key
        dirs, irr = light_sets[gl]
        rec = recs[gr]
        ck = (gl, gr, go)
        if go:
            vis = traced_visibility(setup.scene, rec, dirs, None if gr else rec.footprints)
        else:
            vis = map_visibility(inp.model, rec, dirs, inp.bounds, inp.vis_config)
        vis_cache[ck] = vis
        est = irradiance(rec, vis, dirs, irr, (h, w))
        scores[key] = evaluation.shadow_iou(est, inp.gt_irr, inp.mask)
    base = scores[(False, False, False)]
    full = scores[(True, True, True)]
    vcfg = exact_surfel_config(ValidationConfig(), inp.cameras[0], exact_surfels)
    exact = method_irradiance(scene_surfels(setup, vcfg), inp.cameras, inp.true_dirs,
                              inp.true_irr, inp.bounds, inp.vis_config)
    exact_iou = evaluation.shadow_iou(exact, inp.gt_irr, inp.mask)
    shares = shapley(scores)
    single = {f: scores[tuple(i == j for j in range(3))] - base for i, f in enumerate(FACTORS)}
    bias = []
    rec = recs[False]
    for tau, off, texels in tqdm(BIAS_SWEEP, desc=f"{inp.name}: bias", disable=not progress):
        # A tau row is Eq. 6-7's test alone (the old preset), without the layer slack.
        vc = dataclasses.replace(inp.vis_config, tau=tau, normal_offset=off,
                                 bias_texels=texels,
                                 layer_bias=inp.vis_config.layer_bias if texels else 0.0)
        vis = map_visibility(inp.model, rec, inp.fit_dirs, inp.bounds, vc)
        est = irradiance(rec, vis, inp.fit_dirs, inp.fit_irr, (h, w))
        bias.append({"tau": tau, "normal_offset": off, "bias_texels": texels,
                     "shadow_iou": evaluation.shadow_iou(est, inp.gt_irr, inp.mask)})
    best_bias = max(bias, key=lambda r: r["shadow_iou"])
    # Fractional (opacity) maps instead of the binary test, all else the run's.
    vc = dataclasses.replace(inp.vis_config, fractional=True)
    vis = map_visibility(inp.model, rec, inp.fit_dirs, inp.bounds, vc)
    est = irradiance(rec, vis, inp.fit_dirs, inp.fit_irr, (h, w))
    fractional_gain = evaluation.shadow_iou(est, inp.gt_irr, inp.mask) - base
    # The receivers split: ground-truth points with the surfels' normals and the reverse
    # (the run's lights and shadow maps); the normals split again into where they act: the
    # shading's n . l, or the shadow-map lookup's normal offset.
    split = {}
    fit_rec, gt_rec = recs[False], recs[True]

    def mix(points: Receivers, normals: Receivers) -> Receivers:
        return Receivers(points.points, normals.normals, points.footprints, normals.normals_np)

    # (part, receivers of the shadow-map lookup, receivers of the shading: None = the same)
    for part, at_map, shaded in (("points", mix(gt_rec, fit_rec), None),
                                 ("normals", mix(fit_rec, gt_rec), None),
                                 ("normals_shading", fit_rec, mix(fit_rec, gt_rec)),
                                 ("normals_offset", mix(fit_rec, gt_rec), fit_rec)):
        shaded = at_map if shaded is None else shaded
        vis = map_visibility(inp.model, at_map, inp.fit_dirs, inp.bounds, inp.vis_config)
        est = irradiance(shaded, vis, inp.fit_dirs, inp.fit_irr, (h, w))
        split[part] = evaluation.shadow_iou(est, inp.gt_irr, inp.mask) - base
    errs = evaluation.light_angular_errors(inp.fit_dirs, inp.fit_irr, inp.true_dirs)
    ranked = sorted(FACTORS, key=lambda f: -shares[f])
    return {
        "run": str(run), "data": str(data), "name": inp.name, "variant": variant,
        "views": len(inp.cameras), "preset": inp.preset,
        "recorded_shadow_iou": inp.recorded_iou, "shadow_iou": base,
        "all_ground_truth_iou": full, "exact_geometry_iou": exact_iou,
        "exact_surfels": vcfg.object_surfels, "base_surfels": vcfg.base_surfels,
        "exact_surfels_128": exact_surfels or ValidationConfig().object_surfels,
        "loss": 1.0 - base,
        "scores": {"".join("LRO"[i] if k[i] else "-" for i in range(3)): s
                   for k, s in scores.items()},
        "shapley": shares, "single_swap_gain": single, "receiver_split_gain": split,
        "metric_floor": 1.0 - full,
        "bias_sweep": bias, "bias_gain": best_bias["shadow_iou"] - base,
        "fractional_gain": fractional_gain,
        "best_bias": {"tau": best_bias["tau"], "normal_offset": best_bias["normal_offset"],
                      "bias_texels": best_bias["bias_texels"]},
        "biggest": ranked[0],
        "lights": {"fitted": len(inp.fit_dirs), "true": len(inp.true_dirs),
                   "angular_error_deg": errs["angular_error_deg"],
                   "spurious_irradiance_fraction": errs["spurious_irradiance_fraction"]},
        "wall_s": time.perf_counter() - t0, "loadavg": list(os.getloadavg()),
    }


HEADER = ("| run | IoU (run / here) | all GT | exact geometry | lights | receivers (points / "
          "normals alone) | normals in n.l / in the map offset | occluders | bias (best) | "
          "fractional maps | biggest | fitted lights, angular err deg |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|---|")


def _bias_label(b: dict) -> str:
    """A sweep setting as text: the relative tau or the absolute threshold in texels."""
    depth = f"tau {b['tau']:g}" if b.get("bias_texels") is None else \
        f"{b['bias_texels']:g} texels"
    return f"{depth}, off {b['normal_offset']:g}"


def _gain(r: dict, part: str) -> str:
    g = r["receiver_split_gain"].get(part)  # absent from files written before the split
    return "-" if g is None else f"{g:+.3f}"


def row_markdown(r: dict) -> str:
    sh = r["shapley"]
    err = ", ".join(f"{e:.1f}" for e in r["lights"]["angular_error_deg"] if not math.isnan(e))
    rec = r["recorded_shadow_iou"]
    b = r["best_bias"]
    exact = r.get("exact_geometry_iou")  # absent from files written before it
    return (f"| {r['name']} | {rec if rec is None else f'{rec:.3f}'} / {r['shadow_iou']:.3f} | "
            f"{r['all_ground_truth_iou']:.3f} | {'-' if exact is None else f'{exact:.3f}'} | "
            f"{sh['lights']:+.3f} | {sh['receivers']:+.3f} "
            f"({r['receiver_split_gain']['points']:+.3f} / "
            f"{r['receiver_split_gain']['normals']:+.3f}) | "
            f"{_gain(r, 'normals_shading')} / {_gain(r, 'normals_offset')} | "
            f"{sh['occluders']:+.3f} | {r['bias_gain']:+.3f} ({_bias_label(b)}) | "
            f"{r.get('fractional_gain', math.nan):+.3f} | "
            f"{r['biggest']} | {r['lights']['fitted']}: {err} |")


def markdown(rows: list[dict]) -> str:
    lines = ["Shadow-IoU loss split by factor (Shapley shares: gain in IoU when the factor is "
             "swapped for ground truth, averaged over the swap orders; lights + receivers + "
             "occluders = all GT - run). Exact geometry: the method on surfels sampled on the "
             "true shapes, under the true lights. Bias: best gain of the tau / normal-offset "
             "sweep with the run's own lights and receivers.", "", HEADER]
    lines += [row_markdown(r) for r in rows]
    lines += ["", "All 8 combinations (L = true lights, R = ground-truth receivers, O = "
              "ray-traced occluders; - = the run's own):", "",
              "| run | " + " | ".join(rows[0]["scores"]) + " |",
              "|---|" + "---|" * len(rows[0]["scores"])]
    lines += [f"| {r['name']} | " + " | ".join(f"{s:.3f}" for s in r["scores"].values()) + " |"
              for r in rows]
    return "\n".join(lines)


def main(argv=None) -> int:
    from mi_shadowgs.io.atomic import atomic_dir, check_replaceable, write_json, write_text

    ap = argparse.ArgumentParser(description="Split a run's shadow-IoU loss by swapping in "
                                             "ground truth one factor at a time.")
    ap.add_argument("--run", type=Path, help="a finished run folder (RUN/material/VARIANT)")
    ap.add_argument("--data", type=Path, help="the dataset the run was made from")
    ap.add_argument("--out", type=Path, help="output folder (required with --run; replaced "
                    "only when it holds a shadow_factors.json)")
    ap.add_argument("--variant", default="full")
    ap.add_argument("--views", type=int, default=None, help="first N test views only")
    ap.add_argument("--exact-surfels", type=int, default=None,
                    help="surfels on the object for the exact geometry at 128^2 views "
                         "(default 20000), scaled with the test views' pixel count")
    ap.add_argument("--table", type=Path, nargs="*", default=None,
                    help="only gather the shadow_factors.json under these folders")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    if args.table is not None:
        rows = [json.loads(p.read_text()) for d in args.table
                for p in sorted(Path(d).rglob("shadow_factors.json"))]
        if not rows:
            fail(f"no shadow_factors.json under {args.table}")
        print(markdown(rows))
        return 0
    if args.run is None or args.data is None or args.out is None:
        ap.error("--run, --data and --out are required (or --table)")
    out = args.out
    try:
        check_replaceable(out, "shadow_factors.json")
    except FileExistsError as e:
        fail(str(e))
    if args.exact_surfels is not None and args.exact_surfels < 1:
        fail(f"--exact-surfels must be >= 1, got {args.exact_surfels}")
    res = analyse(args.run, args.data, args.variant, args.views, not args.quiet,
                  args.exact_surfels)
    md = markdown([res])
    with atomic_dir(out, overwrite=True) as tmp:
        write_json(tmp / "shadow_factors.json", res)
        write_text(tmp / "shadow_factors.md", md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
