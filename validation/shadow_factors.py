"""Where a finished run's shadow IoU is lost: swap in ground truth one factor at a time.

Stage 5 scores shadows on the test views by the IoU of the masks where the white direct
irradiance sum_k E_k (n . l_k)^+ V_k falls below half the view's median
(``stages.evaluation.metrics.shadow_iou``). The estimate has three ingredients, each of which
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
                                        [--views N] [--exact-surfels N] [--overwrite] [--quiet]

Writes ``shadow_factors.json`` and ``shadow_factors.md`` into ``--out`` (new, or an earlier
output of this tool; never inside the run: it reads only), each atomically, from four units
under ``units/`` (``validation.units``): the 2^3 factors, the exact geometry, the bias sweep,
the receivers' split (at cpu-small's 32 views of 128^2, 9-18 s for all four on two busy
cores, the first with the loading they share). A rerun after a kill redoes only the
unfinished ones; one made from other inputs or settings exits 2 naming what differs
(``--overwrite`` makes them again). ``--table`` gathers every ``shadow_factors.json`` under
the folders given into one markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
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
from mi_shadowgs import presets as run_presets
from mi_shadowgs.core.depth import pixel_footprint, unproject_depth
from mi_shadowgs.dataset.scene import Light
from mi_shadowgs.stages.evaluation import metrics as evaluation
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


def run_name(run: Path) -> str:
    """A run's name in the tables: its folder's, or its row's for a table row's ``run/``."""
    return run.parent.name if run.name == "run" else run.name


def run_files(run: Path, variant: str = "full") -> dict[str, Path]:
    """The files of a finished run that the analysis reads: name -> path."""
    folder = run / "material" / variant
    files = {"model": folder / "model.ply", "light": folder / "light.json",
             "metrics": folder / "metrics.json",
             "segmentation": run / "segmentation" / "model.ply"}
    for path in files.values():
        if not path.is_file():
            raise FileNotFoundError(f"{path}: not found (is the run finished?)")
    return files


def run_visibility(run: Path, variant: str = "full") -> tuple[str, object, float]:
    """The run's preset, the visibility settings its stage 4 ran with (as relighting reads
    them) and its bounds quantile."""
    from mi_shadowgs.io.provenance import read_manifest
    from mi_shadowgs.stages.relight.runner import recorded_config
    from mi_shadowgs.stages.visibility import shadow_maps

    settings = (read_manifest(run / "material" / variant) or {}).get("settings", {})
    tree = run_presets.recorded(run)
    preset = tree.preset
    vcfg = recorded_config(shadow_maps.VisibilityConfig, settings.get("visibility"),
                           lambda: tree.visibility)
    return preset, vcfg, float(settings.get("bounds_quantile", 0.98))


def load_inputs(run: Path, data: Path, variant: str = "full", views: int | None = None
                ) -> RunInputs:
    from mi_shadowgs.dataset.loader import load_cameras, load_dataset
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.stages.evaluation.evaluate import scored_pixels
    from mi_shadowgs.stages.material.runner import occluder_bounds

    folder = run / "material" / variant
    light = _read_json(folder / "light.json")
    metrics = _read_json(folder / "metrics.json")
    preset, vcfg, quantile = run_visibility(run, variant)
    if light.get("directions") is None or light.get("irradiance") is None:
        raise ValueError(f"{folder / 'light.json'}: no 'directions'/'irradiance' (an older run)")
    lamps = [k for k, p in enumerate(light.get("positions") or []) if p is not None]
    if lamps:  # the factors' receivers, maps and irradiance are those of distant lights
        raise ValueError(f"{folder / 'light.json'}: light {lamps[0]} is a lamp (field "
                         "'positions'); the factor analysis takes directional lights only "
                         "(run stage 4 with --set material.lamps=off)")
    test = load_dataset(data, "test")
    if views:
        test.views = test.views[:views]
    gt_lights = (test.lights or {}).get("training", {}).get("lights") or []
    if not gt_lights:
        raise ValueError(f"{data}: lights.json has no training lights")
    train_cams = [c for _, c in load_cameras(data / "transforms_train.json")]
    seg = load_ply(run / "segmentation" / "model.ply")
    bounds = occluder_bounds(seg, train_cams, quantile)
    return RunInputs(
        run_name(run), load_ply(folder / "model.ply"),
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


class Analysis:
    """What the parts of the analysis share, each made on first use: a rerun whose parts
    are finished makes none of it."""

    def __init__(self, run: Path, data: Path, variant: str, views: int | None):
        self.run, self.data, self.variant, self.views = run, data, variant, views

    @functools.cached_property
    def inp(self) -> RunInputs:
        return load_inputs(self.run, self.data, self.variant, self.views)

    @functools.cached_property
    def setup(self):
        from mi_shadowgs.dataset.scene import dataset_scene

        return dataset_scene(self.data)

    @functools.cached_property
    def recs(self) -> dict[bool, Receivers]:
        """Receivers: the run's (False) and the ray-traced ground truth (True)."""
        from mi_shadowgs.dataset.generate import trace_ground_truth

        inp = self.inp
        gt = trace_ground_truth(self.setup, inp.cameras, [
            Light(f"t{k}", tuple(d.tolist()), (1.0, 1.0, 1.0), 0.0, 0.0)
            for k, d in enumerate(inp.true_dirs)])
        return {False: surfel_receivers(inp.model, inp.cameras, inp.vis_config.receiver_band),
                True: gt_receivers(gt, inp.cameras)}

    def iou(self, rec: Receivers, vis: list[np.ndarray], dirs: np.ndarray,
            irr: np.ndarray) -> float:
        """Stage 5's shadow IoU of the irradiance of ``rec`` under ``vis``, ``dirs``, ``irr``."""
        est = irradiance(rec, vis, dirs, irr, self.inp.mask.shape[1:])
        return evaluation.shadow_iou(est, self.inp.gt_irr, self.inp.mask)

    def run_maps_iou(self, vcfg, at_map: Receivers | None = None,
                     shaded: Receivers | None = None) -> float:
        """The IoU with the run's model, lights and receivers, its shadow maps made with
        ``vcfg``; ``at_map`` / ``shaded``: other receivers for the maps' lookup / for the
        shading."""
        inp, own = self.inp, self.recs[False]
        at_map = at_map or own
        vis = map_visibility(inp.model, at_map, inp.fit_dirs, inp.bounds, vcfg)
        return self.iou(shaded or at_map, vis, inp.fit_dirs, inp.fit_irr)


def combo_label(key: tuple) -> str:
    """(lights, receivers, occluders) booleans as "LRO" letters, "-" for the run's own."""
    return "".join("LRO"[i] if key[i] else "-" for i in range(3))


def factor_scores(a: Analysis, progress: bool) -> dict:
    """The IoU of each of the 2^3 combinations (``combo_label``: IoU), and what the report
    says of the run."""
    from tqdm import tqdm

    inp = a.inp
    light_sets = {False: (inp.fit_dirs, inp.fit_irr), True: (inp.true_dirs, inp.true_irr)}
    scores = {}
    for key in tqdm(list(itertools.product((False, True), repeat=3)),
                    desc=f"{inp.name}: factors", disable=not progress):
        gl, gr, go = key
        dirs, irr = light_sets[gl]
        rec = a.recs[gr]
        if go:
            vis = traced_visibility(a.setup.scene, rec, dirs, None if gr else rec.footprints)
        else:
            vis = map_visibility(inp.model, rec, dirs, inp.bounds, inp.vis_config)
        scores[combo_label(key)] = a.iou(rec, vis, dirs, irr)
    errs = evaluation.light_angular_errors(inp.fit_dirs, inp.fit_irr, inp.true_dirs)
    return {"scores": scores, "views": len(inp.cameras),
            "preset": inp.preset, "recorded_shadow_iou": inp.recorded_iou,
            "lights": {"fitted": len(inp.fit_dirs), "true": len(inp.true_dirs),
                       "angular_error_deg": errs["angular_error_deg"],
                       "spurious_irradiance_fraction": errs["spurious_irradiance_fraction"]}}


def exact_geometry(a: Analysis, exact_surfels: int | None) -> dict:
    """The method on surfels sampled on the true shapes under the true lights."""
    from validation.visibility import ValidationConfig, exact_surfel_config, scene_surfels

    inp = a.inp
    vcfg = exact_surfel_config(ValidationConfig(), inp.cameras[0], exact_surfels)
    exact = method_irradiance(scene_surfels(a.setup, vcfg), inp.cameras, inp.true_dirs,
                              inp.true_irr, inp.bounds, inp.vis_config)
    return {"exact_geometry_iou": evaluation.shadow_iou(exact, inp.gt_irr, inp.mask),
            "exact_surfels": vcfg.object_surfels, "base_surfels": vcfg.base_surfels}


def bias_sweep(a: Analysis, progress: bool) -> dict:
    """The IoU of each ``BIAS_SWEEP`` setting, and of fractional maps, with the run's own
    lights and receivers."""
    from tqdm import tqdm

    vis_config = a.inp.vis_config
    rows = []
    for tau, off, texels in tqdm(BIAS_SWEEP, desc=f"{a.inp.name}: bias",
                                 disable=not progress):
        # A tau row is Eq. 6-7's test alone (the old preset), without the layer slack.
        vc = dataclasses.replace(vis_config, tau=tau, normal_offset=off, bias_texels=texels,
                                 layer_bias=vis_config.layer_bias if texels else 0.0)
        rows.append({"tau": tau, "normal_offset": off, "bias_texels": texels,
                     "shadow_iou": a.run_maps_iou(vc)})
    # Fractional (opacity) maps instead of the binary test, all else the run's.
    fractional = a.run_maps_iou(dataclasses.replace(vis_config, fractional=True))
    return {"bias_sweep": rows, "fractional_iou": fractional}


def receiver_split(a: Analysis) -> dict:
    """The IoU with ground-truth points and the run's normals and the reverse (the run's
    lights and shadow maps); the normals split again into where they act: the shading's
    n . l, or the shadow-map lookup's normal offset."""
    fit_rec, gt_rec = a.recs[False], a.recs[True]

    def mix(points: Receivers, normals: Receivers) -> Receivers:
        return Receivers(points.points, normals.normals, points.footprints, normals.normals_np)

    # (part, receivers of the shadow-map lookup, receivers of the shading: None = the same)
    return {part: a.run_maps_iou(a.inp.vis_config, at_map, shaded)
            for part, at_map, shaded in (("points", mix(gt_rec, fit_rec), None),
                                         ("normals", mix(fit_rec, gt_rec), None),
                                         ("normals_shading", fit_rec, mix(fit_rec, gt_rec)),
                                         ("normals_offset", mix(fit_rec, gt_rec), fit_rec))}


STUDY = "validation.shadow_factors"


def analysis_provenance(run: Path, data: Path, variant: str, views: int | None,
                        **part_settings):
    """What a part of the analysis of ``run`` is made from: the dataset, the run's files it
    reads, the visibility settings the run's stage 4 ran with, the views scored, and the
    part's own options ``part_settings``."""
    from mi_shadowgs.dataset.fingerprint import dataset_ref
    from mi_shadowgs.io.provenance import Provenance, input_ref
    from validation.units import settings_of

    preset, vcfg, quantile = run_visibility(run, variant)
    return Provenance(dataset_ref(data),
                      {name: input_ref(path) for name, path in run_files(run, variant).items()},
                      settings_of(variant=variant, views=views, preset=preset,
                                  visibility=dataclasses.asdict(vcfg),
                                  bounds_quantile=quantile, **part_settings))


def analyse(run: Path, data: Path, variant: str = "full", views: int | None = None,
            progress: bool = True, exact_surfels: int | None = None,
            out: Path | None = None, overwrite: bool = False) -> dict:
    """The split of one run (see the module's doc); ``exact_surfels``: on the object for the
    exact geometry at 128^2 views (default the visibility validation's), scaled with the
    test views' pixel count, the base's too (``visibility.exact_surfel_config``). With
    ``out`` (new, or this tool's: ``claim_out``) its four parts (the 2^3 factors, the exact
    geometry, the bias sweep, the receivers' split) are units there (``validation.units``):
    a rerun after a kill redoes only the unfinished ones, and exits 2 naming what differs
    where one was made from other inputs or settings (``overwrite``: made again)."""
    from validation.visibility import ValidationConfig

    t0 = time.perf_counter()
    run, data = Path(run), Path(data)
    a = Analysis(run, data, variant, views)
    if out is None:
        def part(name, work, **settings):
            return work()
    else:
        from validation import claim_out
        from validation.units import run_unit

        out = claim_out(out, STUDY, ("shadow_factors.json",), inputs=(run, data))

        def part(name, work, **settings):
            """Unit ``name``, made from the run and ``settings``, its own options: another
            value of one part's option leaves the other parts reusable."""
            return run_unit(out, name, STUDY,
                            analysis_provenance(run, data, variant, views, **settings),
                            lambda _: work(), overwrite=overwrite, inputs=(run, data))
    factors = part("factors", lambda: factor_scores(a, progress), trace_lift=TRACE_LIFT)
    exact = part("exact_geometry", lambda: exact_geometry(a, exact_surfels),
                 exact_surfels=exact_surfels or ValidationConfig().object_surfels)
    bias = part("bias_sweep", lambda: bias_sweep(a, progress), bias_sweep=BIAS_SWEEP)
    split = part("receiver_split", lambda: receiver_split(a))
    scores = factors["scores"]
    base, full = scores["---"], scores["LRO"]
    # the Shapley split reads the scores by (lights, receivers, occluders) booleans
    shares = shapley({key: scores[combo_label(key)]
                      for key in itertools.product((False, True), repeat=3)})
    single = {f: scores[combo_label(tuple(i == j for j in range(3)))] - base
              for i, f in enumerate(FACTORS)}
    best_bias = max(bias["bias_sweep"], key=lambda r: r["shadow_iou"])
    ranked = sorted(FACTORS, key=lambda f: -shares[f])
    return {
        "run": str(run), "data": str(data), "name": run_name(run), "variant": variant,
        "views": factors["views"], "preset": factors["preset"],
        "recorded_shadow_iou": factors["recorded_shadow_iou"], "shadow_iou": base,
        "all_ground_truth_iou": full, "exact_geometry_iou": exact["exact_geometry_iou"],
        "exact_surfels": exact["exact_surfels"], "base_surfels": exact["base_surfels"],
        "exact_surfels_128": exact_surfels or ValidationConfig().object_surfels,
        "loss": 1.0 - base, "scores": scores,
        "shapley": shares, "single_swap_gain": single,
        "receiver_split_gain": {part: iou - base for part, iou in split.items()},
        "metric_floor": 1.0 - full,
        "bias_sweep": bias["bias_sweep"], "bias_gain": best_bias["shadow_iou"] - base,
        "fractional_gain": bias["fractional_iou"] - base,
        "best_bias": {"tau": best_bias["tau"], "normal_offset": best_bias["normal_offset"],
                      "bias_texels": best_bias["bias_texels"]},
        "biggest": ranked[0], "lights": factors["lights"],
        # this call's: a call that finds its units finished only gathers
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
    from mi_shadowgs.io.atomic import write_json, write_text

    ap = argparse.ArgumentParser(description="Split a run's shadow-IoU loss by swapping in "
                                             "ground truth one factor at a time.")
    ap.add_argument("--run", type=Path, help="a finished run folder (RUN/material/VARIANT)")
    ap.add_argument("--data", type=Path, help="the dataset the run was made from")
    ap.add_argument("--out", type=Path, help="output folder (required with --run): new or an "
                    "earlier output of this tool (its finished units are reused)")
    ap.add_argument("--variant", default="full")
    ap.add_argument("--views", type=int, default=None, help="first N test views only")
    ap.add_argument("--exact-surfels", type=int, default=None,
                    help="surfels on the object for the exact geometry at 128^2 views "
                         "(default 20000), scaled with the test views' pixel count")
    ap.add_argument("--table", type=Path, nargs="*", default=None,
                    help="only gather the shadow_factors.json under these folders")
    ap.add_argument("--overwrite", action="store_true",
                    help="make the units again (those made from other inputs or settings "
                         "exit 2 otherwise)")
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
    if args.exact_surfels is not None and args.exact_surfels < 1:
        fail(f"--exact-surfels must be >= 1, got {args.exact_surfels}")
    try:
        res = analyse(args.run, args.data, args.variant, args.views, not args.quiet,
                      args.exact_surfels, args.out, args.overwrite)
    except (ValueError, FileNotFoundError) as e:  # names the file
        fail(str(e))
    md = markdown([res])
    write_json(args.out / "shadow_factors.json", res)
    write_text(args.out / "shadow_factors.md", md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
