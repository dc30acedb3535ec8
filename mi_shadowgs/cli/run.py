"""``mi-shadowgs run DATA --out RUN``: the whole method (stages 1-5), then the report.

Writes ``RUN/geometry/`` (stage 1), ``RUN/segmentation/`` (stage 2),
``RUN/material/<variant>/`` (stages 3-5: model, light map, metrics, figures),
``RUN/summary.json`` and ``RUN/report.html``. Re-running continues an interrupted run;
each stage is reused only when it was made from the same dataset, input model and settings
(manifests, ``mi_shadowgs.io.provenance``), otherwise the run stops naming what differs.
"""

from __future__ import annotations

import argparse
import os

from mi_shadowgs.cli.train import PRUNE_HELP
from mi_shadowgs.config import LABEL_MAP_SOURCES, PRESET_NAMES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", help="dataset folder (mi-shadowgs generate, or TensoIR layout)")
    parser.add_argument("--out", required=True, help="run folder (created; resumed if present)")
    parser.add_argument("--overwrite", action="store_true",
                        help="start over, removing the files of an earlier run there (only "
                             "those)")
    parser.add_argument("--preset", default="cpu-small",
                        help=f"{', '.join(PRESET_NAMES)} (default cpu-small)")
    parser.add_argument("--masks", default=None, choices=("auto", *LABEL_MAP_SOURCES),
                        help="segmentation labels (default: material ids when present)")
    parser.add_argument("--segments", type=int, default=None, metavar="K",
                        help="number of material segments (default: the number of material "
                             "ids, or without ids the number of colour labels)")
    parser.add_argument("--ablations", action=argparse.BooleanOptionalAction, default=None,
                        help="also fit the w/o visibility and w/o segmentation variants "
                             "(default: the preset's: paper does, the others do not)")
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of every stage's random draws (default 0); a run at "
                             "another seed shows how far its figures move by chance")
    parser.add_argument("--material-iterations", type=int, default=None,
                        help="override the stage-4 iteration count")
    parser.add_argument("--prune-outside-masks", type=int, default=None, metavar="N",
                        help=PRUNE_HELP)
    parser.add_argument("--albedo-detail", type=float, default=None, metavar="W",
                        help="let each surfel's albedo vary within its segment, pulled to "
                             "the segment's by weight W (0.1 suits a textured mat; default 0, "
                             "off: the paper's one albedo per segment)")
    parser.add_argument("--preview-envmap", action="append", default=None, metavar="PATH",
                        help="env map (.exr, or a folder of them) for the report's relit "
                             "previews, beside the dataset's own (repeatable; default: "
                             "$MI_SHADOWGS_ENVMAPS, os.pathsep-separated)")
    parser.add_argument("--no-progress", action="store_true", help="hide progress bars")


def run(args) -> int:
    from mi_shadowgs.config import with_overrides
    from mi_shadowgs.pipeline import check_preview_envmaps, get_config, run_pipeline

    config = get_config(args.preset)
    overrides = {}
    if args.masks is not None:
        overrides["masks"] = args.masks
    if args.segments is not None:
        overrides["segments"] = args.segments
    if args.ablations is not None:
        overrides["ablations"] = args.ablations
    if args.material_iterations is not None:
        overrides["material_iterations"] = args.material_iterations
    if args.seed is not None:
        overrides["seed"] = args.seed
    if args.prune_outside_masks is not None:
        overrides["prune_outside_masks"] = args.prune_outside_masks
    if args.albedo_detail is not None:
        overrides["albedo_detail"] = args.albedo_detail
    envmaps = args.preview_envmap
    source = "--preview-envmap"
    if envmaps is None and os.environ.get("MI_SHADOWGS_ENVMAPS"):
        envmaps = [e for e in os.environ["MI_SHADOWGS_ENVMAPS"].split(os.pathsep) if e]
        source = "$MI_SHADOWGS_ENVMAPS"
    if envmaps:
        overrides["preview_envmaps"] = check_preview_envmaps(envmaps, source)
    config = with_overrides(config, overrides, "run")
    summary = run_pipeline(args.data, args.out, config, progress=not args.no_progress,
                           overwrite=args.overwrite)
    table = summary["tables"][0]
    for row in table["rows"]:
        print("  ".join(f"{c}={v:.4g}" if isinstance(v, float) else
                        f"{c}={'n/a' if v is None else v}"
                        for c, v in zip(table["columns"], row, strict=True)))
    for item in summary.get("skipped_metrics", []):
        print(f"not computed: {item['metric']} (needs {item['needs']}: {item['why']})")
    reused = summary.get("reused_stages") or []
    print(f"report: {args.out}/report.html ({summary['total_seconds']:.0f} s"
          + (f"; made by an earlier call: {', '.join(reused)}" if reused else "") + ")")
    return 0
