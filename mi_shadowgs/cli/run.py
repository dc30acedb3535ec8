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

SET_HELP = ("override any setting of the run's tree, SECTION.FIELD=VALUE (e.g. "
            "material.iterations=300, visibility.resolution=1024, masks=chromaticity); "
            "repeatable; see docs/cli.md and RUN/config.json for the names")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", help="dataset folder (mi-shadowgs generate, or TensoIR layout)")
    parser.add_argument("--out", required=True, help="run folder (created; resumed if present)")
    parser.add_argument("--overwrite", action="store_true",
                        help="start over, removing the files of an earlier run there (only "
                             "those)")
    parser.add_argument("--preset", default=None,
                        help=f"{', '.join(PRESET_NAMES)} (default cpu-small, or the preset "
                             "of --config)")
    parser.add_argument("--config", default=None, metavar="RUN/config.json",
                        help="start from the settings an earlier run recorded (its folder or "
                             "its config.json); --preset, --set and the flags below override")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        dest="settings", help=SET_HELP)
    parser.add_argument("--masks", default=None, choices=("auto", *LABEL_MAP_SOURCES),
                        help="segmentation labels (default: material ids when present)")
    parser.add_argument("--segments", type=int, default=None, metavar="K",
                        help="number of material segments (default: the number of material "
                             "ids, or without ids the number of colour labels); "
                             "= --set segmentation.n_segments=K")
    parser.add_argument("--ablations", action=argparse.BooleanOptionalAction, default=None,
                        help="also fit the w/o visibility and w/o segmentation variants "
                             "(default: the preset's: paper does, the others do not)")
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of every stage's random draws (default 0); a run at "
                             "another seed shows how far its figures move by chance")
    parser.add_argument("--material-iterations", type=int, default=None,
                        help="stage 4's iteration count (= --set material.iterations=N)")
    parser.add_argument("--prune-outside-masks", type=int, default=None, metavar="N",
                        help=PRUNE_HELP + " (= --set geometry.hull_prune_views=N)")
    parser.add_argument("--albedo-detail", type=float, default=None, metavar="W",
                        help="let each surfel's albedo vary within its segment, pulled to "
                             "the segment's by weight W (0.1 suits a textured mat; default 0, "
                             "off: the paper's one albedo per segment; = --set "
                             "material.detail_prior=W)")
    parser.add_argument("--preview-envmap", action="append", default=None, metavar="PATH",
                        help="env map (.exr, or a folder of them) for the report's relit "
                             "previews, beside the dataset's own (repeatable; default: "
                             "$MI_SHADOWGS_ENVMAPS, os.pathsep-separated)")
    parser.add_argument("--no-progress", action="store_true", help="hide progress bars")


# The flags that are short for a setting of the tree: (flag's dest, section, field).
SHORTHANDS = (("masks", None, "masks"), ("ablations", None, "ablations"),
              ("segments", "segmentation", "n_segments"),
              ("material_iterations", "material", "iterations"),
              ("prune_outside_masks", "geometry", "hull_prune_views"),
              ("albedo_detail", "material", "detail_prior"))


def run_config(args):
    """The run's settings tree from the command line: --config, then --preset, --set and
    the shorthand flags, built once (``mi_shadowgs.presets.build``)."""
    from mi_shadowgs.pipeline import check_preview_envmaps
    from mi_shadowgs.presets import build, load_overrides, merge, parse_sets

    preset, overrides = "cpu-small", {}
    if args.config is not None:
        preset, overrides = load_overrides(args.config)
    preset = args.preset or preset
    for dest, section, field in SHORTHANDS:
        value = getattr(args, dest)
        if value is not None:
            overrides = merge(overrides, {section: {field: value}} if section
                              else {field: value})
    overrides = merge(overrides, parse_sets(args.settings))
    envmaps = args.preview_envmap
    source = "--preview-envmap"
    if envmaps is None and os.environ.get("MI_SHADOWGS_ENVMAPS"):
        envmaps = [e for e in os.environ["MI_SHADOWGS_ENVMAPS"].split(os.pathsep) if e]
        source = "$MI_SHADOWGS_ENVMAPS"
    if envmaps:
        overrides["preview_envmaps"] = check_preview_envmaps(envmaps, source)
    return build(preset, overrides, seed=args.seed)


def run(args) -> int:
    from mi_shadowgs.pipeline import run_pipeline

    config = run_config(args)
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
