"""Does the stage-1 objective keep a correct surface where it is? (the rasterizer's filter)

Surfels are placed on the true surface of a generated dataset's scene (opacity 0.9, colour
from the images), then trained with the stage-1 loss for ``steps`` steps with the cpu-small
schedule from ``start_step`` and no densification, once per low-pass filter strength
``k = RasterConfig.lowpass_inv_var``. A filter that dilates splats makes the fit shrink the
surface: reported is the signed depth error of the model's median depth against the ground
truth on the test views (positive: behind the true surface), with PSNR and normal error.

    python -m validation.lowpass_drift --out OUT [--data DATA] [--quick] [--overwrite]

Writes (atomically) ``OUT/lowpass_drift.json`` and ``OUT/lowpass_drift.md``. Each k is a
unit of its own (``validation.units``, ``OUT/units/k_<k>/``, ``quick-k_<k>/`` with
``--quick``, with the training's checkpoint): a killed call, run again, reuses the finished
ks and continues the one in progress when the dataset and the settings are the same, and
exits 2 naming what differs otherwise; ``--overwrite`` trains them again.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs import presets as run_presets
from mi_shadowgs.io.atomic import write_json, write_text
from validation import claim_out, fail
from validation.units import run_unit, settings_of, smoke_name

STUDY = "validation.lowpass_drift"
KS = (2.0, 8.0, 12.0, 32.0)


@dataclasses.dataclass(frozen=True)
class DriftConfig:
    ks: tuple = KS  # filter strengths (2: 2DGS; 12: ours, a one-pixel box's std)
    steps: int = 600
    start_step: int = 1200  # position learning rate as at this cpu-small step
    object_surfels: int = 20_000
    base_surfels: int = 12_000
    base_radius: float = 4.0  # in object radii: the whole base
    test_views: int = 8


QUICK = DriftConfig(ks=(2.0, 12.0), steps=300, object_surfels=8_000, base_surfels=4_000,
                    test_views=4)


def _initial_params(setup, train, cfg: DriftConfig, sh_degree: int) -> dict:
    from mi_shadowgs.stages.geometry import train as G
    from validation.visibility import ValidationConfig, scene_surfels

    vcfg = ValidationConfig(object_surfels=cfg.object_surfels, base_surfels=cfg.base_surfels,
                            base_radius=cfg.base_radius)
    d = scene_surfels(setup, vcfg).to_numpy()
    n = len(d["position"])
    sh = np.zeros((n, 3 * (sh_degree + 1) ** 2), np.float32)
    sh[:, :3] = (G.mean_colour(train.views, d["position"]) - 0.5) / G.SH_C0
    return {"position": d["position"].astype(np.float32),
            "log_scale": np.log(d["scale"]).astype(np.float32),
            "rotation": d["rotation"].astype(np.float32),
            "opacity_logit": np.full((n, 1), math.log(0.9 / 0.1), np.float32), "sh": sh}


def depth_bias(surfels, test, raster, views: int, base_id: int | None) -> float:
    """Median over the object's pixels (material id > 0, not the base) of
    (median depth - true depth) / true depth."""
    from mi_shadowgs.core.raster import rasterize

    rel = []
    for view in test.views[:views]:
        out = rasterize(surfels, view.camera, None, aovs=("alpha", "median_depth"),
                        config=raster)
        md = out["median_depth"].numpy().reshape(view.mask.shape)
        ok = view.mask.astype(bool) & (out["alpha"].numpy().reshape(view.mask.shape) > 0.5)
        ok &= (view.depth > 0) & (view.material > 0)
        if base_id is not None:
            ok &= view.material != base_id
        rel.append((md[ok] - view.depth[ok]) / view.depth[ok])
    return float(np.median(np.concatenate(rel)))


def drift_geometry_config(base, cfg: DriftConfig, k: float):
    """Stage 1's settings for filter strength ``k``: ``base`` (cpu-small) with the filter,
    ``cfg``'s steps after ``start_step`` and no densification."""
    from mi_shadowgs.stages.geometry.densify import DensifyConfig

    raster = dataclasses.replace(base.raster, lowpass_inv_var=k)
    return dataclasses.replace(
        base, raster=raster, iterations=cfg.start_step + cfg.steps,
        densify=DensifyConfig(start=10**9, stop=0, opacity_reset_interval=0))


def train_k(unit, k: float, gcfg, inputs: dict, cfg: DriftConfig) -> dict:
    """One filter strength's row: ``cfg.steps`` stage-1 steps from the surfels on the true
    surface, checkpointed in ``unit`` (continued from there when it has one)."""
    from mi_shadowgs.stages.common import checkpoint_hooks
    from mi_shadowgs.stages.geometry import train as G

    train, test, base_id = inputs["train"], inputs["test"], inputs["base_id"]
    hooks = checkpoint_hooks(unit, lambda arrays, meta: G.TrainState.from_numpy(arrays, gcfg))
    # The start is made again when continuing (it is seeded) for its depth bias.
    start = G.state_from_params(inputs["params"], train.cameras, gcfg, cfg.start_step)
    bias0 = depth_bias(G.model_surfels(dict(start.opt.params)), test, gcfg.raster,
                       cfg.test_views, base_id)
    state = start if hooks["state"] is None else hooks["state"]
    model = G.train_geometry(train, gcfg, state=state, progress=False,
                             callbacks=G.Callbacks(on_checkpoint=hooks["on_checkpoint"]))
    m = G.evaluate(model, test, gcfg.raster)
    return {"k": k, "filter_std_px": 1.0 / math.sqrt(k),
            "depth_bias_start": bias0,
            "depth_bias": depth_bias(model, test, gcfg.raster, cfg.test_views, base_id),
            "depth_error_mean_rel": m.get("depth_error_mean_rel", float("nan")),
            "psnr": m["psnr"], "normal_error_median_deg":
                m.get("normal_error_median_deg", float("nan"))}


def run_drift(data: Path, cfg: DriftConfig, out: Path, overwrite: bool = False,
              quick: bool = False) -> list[dict]:
    """One row per k of ``cfg.ks``, each the unit ``OUT/units/k_<k>`` (a smoke run's:
    ``smoke_name``)."""
    from mi_shadowgs.dataset.fingerprint import dataset_ref
    from mi_shadowgs.dataset.layout import DATASET_JSON
    from mi_shadowgs.dataset.loader import DatasetError, load_dataset
    from mi_shadowgs.dataset.scene import SceneError, dataset_scene
    from mi_shadowgs.io.provenance import Provenance
    from mi_shadowgs.stages.common import settings_dict

    if not (data / DATASET_JSON).is_file():
        fail(f"--data {data}: no {DATASET_JSON}; name a dataset of mi-shadowgs generate")
    base = run_presets.geometry_config("cpu-small")
    inputs = {}

    def loaded() -> dict:
        """The views and the initial surfels, read once and only when a k is to train."""
        if not inputs:
            try:
                setup = dataset_scene(data)
                inputs["train"] = load_dataset(data, "train")
                inputs["test"] = load_dataset(data, "test")
            except (DatasetError, SceneError) as exc:
                fail(str(exc))
            info = json.loads((data / DATASET_JSON).read_text())
            inputs["base_id"] = next((m["id"] for m in info.get("materials", [])
                                      if m.get("name") == "base"), None)
            inputs["params"] = _initial_params(setup, inputs["train"], cfg, base.sh_degree)
        return inputs

    data_ref = dataset_ref(data)
    drift = {f: v for f, v in dataclasses.asdict(cfg).items() if f != "ks"}  # the unit's k
    rows = []
    for k in cfg.ks:
        gcfg = drift_geometry_config(base, cfg, k)
        provenance = Provenance(data_ref, settings=settings_of(
            drift=drift, k=k, geometry=settings_dict(gcfg)))
        row = run_unit(out, smoke_name(f"k_{k:g}", quick), STUDY, provenance,
                       lambda unit, k=k, gcfg=gcfg: train_k(unit, k, gcfg, loaded(), cfg),
                       overwrite=overwrite, inputs=[data])
        rows.append(row)
        print(f"k={k:g}: depth bias {row['depth_bias']:+.4%} "
              f"(start {row['depth_bias_start']:+.4%}), PSNR {row['psnr']:.2f} dB", flush=True)
    return rows


def markdown(rows: list[dict], cfg: DriftConfig, data: Path) -> str:
    out = [f"## Low-pass filter drift ({data})", "",
           f"Surfels on the true surface, {cfg.steps} stage-1 steps (cpu-small schedule from "
           f"step {cfg.start_step}, no densification); object depth bias = median of (model "
           "median depth - true depth) / true depth over the object's pixels of the test "
           "views (positive: behind the true surface); mean depth error over all pixels.", "",
           "| k | filter std (px) | object depth bias at start | after | mean rel. depth "
           "error after | test PSNR | median normal error |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['k']:g} | {r['filter_std_px']:.2f} | {r['depth_bias_start']:+.3%} "
                   f"| {r['depth_bias']:+.3%} | {r['depth_error_mean_rel']:.3%} | "
                   f"{r['psnr']:.2f} dB | "
                   f"{r['normal_error_median_deg']:.2f} deg |")
    return "\n".join(out) + "\n"


def run(out_dir, quick: bool = False, data: str | None = None,
        overwrite: bool = False) -> dict:
    out_dir = Path(out_dir)
    cfg = QUICK if quick else DriftConfig()
    if data is None:
        from validation.pipeline import make_dataset

        data_path = make_dataset("default", None, out_dir)
    else:
        data_path = Path(data)
    rows = run_drift(data_path, cfg, out_dir, overwrite, quick)
    md = markdown(rows, cfg, data_path)
    write_json(out_dir / "lowpass_drift.json", {"config": dataclasses.asdict(cfg),
                                                "rows": rows})
    write_text(out_dir / "lowpass_drift.md", md)
    return {"markdown": md, "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--data", help="a generated dataset (default: generate the default scene)")
    ap.add_argument("--quick", action="store_true", help="a short smoke run")
    ap.add_argument("--overwrite", action="store_true", help="train every k again")
    args = ap.parse_args(argv)
    claim_out(args.out, STUDY, ('lowpass_drift.json',))
    print(run(args.out, args.quick, args.data, args.overwrite)["markdown"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
