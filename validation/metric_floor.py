"""What stage 5's albedo and shadow metrics can tell apart at a dataset's resolution.

The dataset's ground truth is point-sampled: each pixel holds the albedo and irradiance at
the hit of its centre ray. The photos, and anything fitted to them, are box-filtered over
the pixel. Here the exact scene itself is scored as an estimate: its box-filtered albedo and
irradiance (``dataset.generate.box_filtered_ground_truth``, ``--samples``^2 rays per pixel,
Mitsuba ray tracing) against the point-sampled truth, with stage 5's own metrics
(``stages.evaluation.metrics``: shadow IoU of the direct irradiance under the training lights,
albedo PSNR with per-region and with one per-channel scale). Where a thin or small part
spans a few pixels, the two references disagree, and an estimate that resolves the scene to
the pixel scores about what the filtered truth scores; at larger view sizes (``--sizes``,
the same cameras) the disagreement shrinks.

    python -m validation.metric_floor --data DATA [--data DATA ...] --out DIR
        [--sizes 128 256 512] [--views N] [--samples 4]
        [--exact PRESET [--exact-surfels N] [--map-resolution N]] [--overwrite]

``--exact`` also scores the method itself on exact geometry at each size: surfels sampled on
the true shapes give the receivers (rasterized as a run's) and the shadow maps (that
preset's visibility settings), under the true lights. It estimates what a perfect stage 1
and stage 4 could reach at that view size.

``--sizes`` defaults to the dataset's own size; ``--views``, to all its test views (the
views stage 5 scores). Writes ``metric_floor.json`` and ``metric_floor.md`` into ``--out``
(new, or an earlier output of this study), each atomically, from its units under ``units/``
(``validation.units``), one per dataset and view size: a rerun after a kill redoes only the
unfinished ones; one made from another dataset or settings exits 2 naming what differs
(``--overwrite`` makes this call's units again).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import sys
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM, selects the variant)
from mi_shadowgs import presets as run_presets
from mi_shadowgs.dataset.generate import box_filtered_ground_truth, trace_ground_truth
from mi_shadowgs.stages.evaluation import metrics as evaluation


def exact_visibility_config(preset: str, map_resolution: int | None):
    """The shadow maps' settings of the method on exact geometry: ``preset``'s, at
    ``map_resolution`` texels when given."""

    vcfg = run_presets.visibility_config(preset)
    return vcfg if map_resolution is None else \
        dataclasses.replace(vcfg, resolution=map_resolution)


def exact_geometry_iou(setup, data: Path, cameras, point: dict, preset: str,
                       surfels_128: int, map_resolution: int | None) -> float:
    """Stage 5's shadow IoU of the method itself on exact geometry at the size of
    ``cameras``: surfels sampled on the true shapes (``surfels_128`` on the object at
    128^2 views, scaled with the pixel count; a fifth of that on the base) give the
    receivers, rasterized as a run's, and the shadow maps (the visibility settings of
    ``preset``, at ``map_resolution`` texels when given), under the true lights; scored
    against the point truth ``point`` (``trace_ground_truth`` at these cameras)."""
    from mi_shadowgs.dataset.loader import load_cameras
    from mi_shadowgs.stages.material.runner import occluder_bounds
    from validation.shadow_factors import method_irradiance
    from validation.visibility import ValidationConfig, exact_surfel_config, scene_surfels

    exact = scene_surfels(setup, exact_surfel_config(ValidationConfig(), cameras[0],
                                                     surfels_128, max(1, surfels_128 // 5)))
    train = [c for _, c in load_cameras(data / "transforms_train.json")]
    bounds = occluder_bounds(exact, train, 0.98)  # as a run frames its maps
    vcfg = exact_visibility_config(preset, map_resolution)
    dirs = np.array([lt.direction for lt in setup.lights], np.float64)  # [L, 3]
    irr = np.array([np.mean(lt.irradiance) for lt in setup.lights], np.float64)  # [L]
    est = method_irradiance(exact, cameras, dirs, irr, bounds, vcfg)
    return evaluation.shadow_iou(est, point["irradiance"].sum(axis=3).mean(-1),
                                 point["mask"].astype(bool))


def dataset_name(data: Path) -> str:
    """The dataset's name in the table: its folder's (the parent's when it is "data")."""
    return data.parent.name if data.name == "data" else data.name


@dataclasses.dataclass
class DatasetViews:
    """A dataset's test views to score (the first ``views``, or all) and its scene, which is
    loaded on first use (``setup``): a rerun whose units are finished loads none."""

    data: Path
    cameras: list

    @functools.cached_property
    def setup(self):
        from mi_shadowgs.dataset.scene import dataset_scene

        return dataset_scene(self.data)  # its lights are the dataset's training lights

    @classmethod
    def load(cls, data: Path, views: int | None) -> DatasetViews:
        from mi_shadowgs.dataset.layout import transforms_name
        from mi_shadowgs.dataset.loader import load_cameras

        # The cameras alone: a call that only gathers finished units reads no image.
        cams = [c for _, c in load_cameras(data / transforms_name("test"))]
        cams = cams[:views] if views else cams
        if not cams:
            raise ValueError(f"{data}: no test views")
        return cls(data, cams)


def size_row(views: DatasetViews, size: int, samples: int, exact: str | None = None,
             exact_surfels: int = 40_000, map_resolution: int | None = None) -> dict:
    """The row of one view size: the filtered truth's shadow IoU and albedo PSNR against the
    point-sampled truth on the dataset's test views at width ``size``; with ``exact`` (a
    preset name) also ``exact_geometry_iou`` with that preset's visibility settings."""
    t0 = time.perf_counter()
    setup, data = views.setup, views.data
    at = [c.with_size(size, round(size * c.height / c.width)) for c in views.cameras]
    point = trace_ground_truth(setup, at)
    box = box_filtered_ground_truth(setup, at, samples=samples)
    mask = point["mask"].astype(bool)  # [V, H, W]
    iou = evaluation.shadow_iou(box["irradiance"].sum(axis=3).mean(-1),
                                point["irradiance"].sum(axis=3).mean(-1), mask)
    alb = evaluation.albedo_metrics(box["albedo"], point["albedo"], point["material"], mask)
    row = {"dataset": dataset_name(data), "data": str(data), "size": size, "views": len(at),
           "samples": samples, "shadow_iou": iou, "albedo_psnr": alb["psnr"],
           "albedo_psnr_global": alb["psnr_global"],
           "partly_covered_share": float(np.mean(box["coverage"][mask] < 1.0))}
    if exact is not None:
        row.update(exact_geometry_iou=exact_geometry_iou(
            setup, data, at, point, exact, exact_surfels, map_resolution),
            exact_preset=exact, exact_surfels_128=exact_surfels,
            map_resolution=map_resolution)
    return {**row, "wall_s": time.perf_counter() - t0}


def markdown(rows: list[dict]) -> str:
    exact = [r for r in rows if "exact_geometry_iou" in r]
    lines = ["The exact scene, box-filtered over each pixel, scored by stage 5's metrics "
             "against the dataset's point-sampled ground truth" +
             (f"; beside it the method itself on exact geometry under the true lights "
              f"({exact[0]['exact_preset']} visibility settings)" if exact else "") + ":", "",
             "| dataset | view size | views | shadow IoU | albedo PSNR per region | "
             "albedo PSNR one scale | mask pixels partly covered |" +
             (" method on exact geometry: shadow IoU |" if exact else ""),
             "|---|---|---|---|---|---|---|" + ("---|" if exact else "")]
    for r in rows:
        lines.append(f"| {r['dataset']} | {r['size']} | {r['views']} | {r['shadow_iou']:.3f} | "
                     f"{r['albedo_psnr']:.2f} | {r['albedo_psnr_global']:.2f} | "
                     f"{r['partly_covered_share']:.3f} |" +
                     (f" {r['exact_geometry_iou']:.3f} |" if "exact_geometry_iou" in r else
                      " - |" if exact else ""))
    return "\n".join(lines)


STUDY = "validation.metric_floor"


def unit_labels(datas: list[Path]) -> list[str]:
    """Each dataset's part of its units' names: its name in the table, and where two
    datasets share one, a digest of its folder too (their units would mix otherwise)."""
    import hashlib

    names = [dataset_name(d) for d in datas]
    folders = [str(d.resolve()) for d in datas]
    return [n if len({f for m, f in zip(names, folders, strict=True) if m == n}) == 1 else
            f"{n}-{hashlib.blake2b(f.encode(), digest_size=4).hexdigest()}"
            for n, f in zip(names, folders, strict=True)]


def run(out_dir: Path, datas: list[Path], sizes: list[int] | None = None,
        views: int | None = None, samples: int = 4, progress: bool = True,
        command: list[str] | None = None, exact: str | None = None,
        exact_surfels: int = 40_000, map_resolution: int | None = None,
        overwrite: bool = False) -> dict:
    """Every dataset's rows into ``out_dir`` (new, or this study's: ``claim_out``). Each
    (dataset, view size) is a unit (``validation.units``): a rerun after a kill redoes only
    the unfinished ones, and exits 2 naming what differs where one was made from another
    dataset or settings (``overwrite``: made again). The tables are written from the units
    at the end. Returns {"rows", "markdown"}."""
    from tqdm import tqdm

    from mi_shadowgs.dataset.fingerprint import dataset_ref
    from mi_shadowgs.io.atomic import write_json, write_text
    from mi_shadowgs.io.provenance import Provenance
    from validation import claim_out, fail
    from validation.units import run_unit, settings_of, unit_name

    datas = [Path(d) for d in datas]
    exact_visibility = None  # the maps' settings: a preset's may change with the code
    if exact is not None:
        exact_visibility = dataclasses.asdict(exact_visibility_config(exact, map_resolution))
    try:  # before any file is written
        tests = [DatasetViews.load(d, views) for d in datas]
    except ValueError as exc:  # (DatasetError too) naming the file
        fail(str(exc))
    out_dir = claim_out(out_dir, STUDY, ("metric_floor.json",), inputs=datas)
    rows = []
    for test, label in zip(tests, unit_labels(datas), strict=True):
        dataset = dataset_ref(test.data)
        for size in tqdm(sizes or [test.cameras[0].width],
                         desc=f"{dataset_name(test.data)}: sizes", disable=not progress):
            settings = settings_of(size=size, views=len(test.cameras), samples=samples,
                                   exact=exact, exact_visibility=exact_visibility,
                                   exact_surfels=exact_surfels if exact else None)
            rows.append(run_unit(
                out_dir, unit_name(label, f"{size}px"), STUDY,
                Provenance(dataset, settings=settings),
                lambda _, t=test, s=size: size_row(t, s, samples, exact, exact_surfels,
                                                   map_resolution),
                overwrite=overwrite, inputs=(test.data,)))
    md = markdown(rows) if rows else "No dataset to score."
    write_json(out_dir / "metric_floor.json", {"rows": rows, "command": command or sys.argv,
                                               "loadavg": list(os.getloadavg())})
    write_text(out_dir / "metric_floor.md", md + "\n")
    return {"rows": rows, "markdown": "## What the metrics can tell apart\n\n" + md}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Score the exact scene's box-filtered albedo "
                                 "and irradiance with stage 5's metrics against the "
                                 "point-sampled ground truth.")
    ap.add_argument("--data", type=Path, action="append", required=True,
                    help="a generated dataset (repeat for several)")
    ap.add_argument("--out", type=Path, required=True,
                    help="output folder: new or an earlier output of this study (its "
                         "finished units are reused)")
    ap.add_argument("--sizes", type=int, nargs="*", default=None,
                    help="view widths to score at (default: the dataset's own)")
    ap.add_argument("--views", type=int, default=None, help="first N test views only")
    ap.add_argument("--samples", type=int, default=4,
                    help="sub-pixel rays per pixel side for the box filter (default 4)")
    ap.add_argument("--exact", default=None, metavar="PRESET",
                    help="also the method itself on exact geometry under the true lights, "
                         "with this preset's visibility settings (cpu-small, paper, ...)")
    ap.add_argument("--exact-surfels", type=int, default=40_000,
                    help="exact surfels on the object at 128^2, scaled with the pixel count "
                         "(default 40000)")
    ap.add_argument("--map-resolution", type=int, default=None,
                    help="shadow-map texels for --exact (default: the preset's)")
    ap.add_argument("--overwrite", action="store_true",
                    help="make this call's units again (those made from another dataset or "
                         "settings exit 2 otherwise)")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    if args.exact is not None:
        from mi_shadowgs.config import ConfigError

        try:
            run_presets.visibility_config(args.exact)
        except ConfigError as e:
            ap.error(f"--exact: {e}")
    if args.exact_surfels < 1 or (args.map_resolution is not None and args.map_resolution < 1):
        ap.error("--exact-surfels and --map-resolution must be >= 1")
    if args.samples < 1:
        ap.error(f"--samples must be >= 1, got {args.samples}")
    if args.views is not None and args.views < 1:
        ap.error(f"--views must be >= 1, got {args.views}")
    if any(s < 1 for s in args.sizes or []):
        ap.error(f"--sizes must be >= 1, got {args.sizes}")
    for d in args.data:
        if not (d / "dataset.json").is_file():
            ap.error(f"{d / 'dataset.json'}: not found (--data takes a dataset made by "
                     "`mi-shadowgs generate`, whose scene can be reloaded)")
    summary = run(args.out, args.data, args.sizes, args.views, args.samples, not args.quiet,
                  None, args.exact, args.exact_surfels, args.map_resolution, args.overwrite)
    print(markdown(summary["rows"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
