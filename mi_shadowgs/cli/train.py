"""``mi-shadowgs train DATA --out RUN [--preset P] [--resume]``: stage 1, the 2DGS geometry.

Writes ``RUN/geometry/``: ``model.ply`` (2DGS layout), ``checkpoint/checkpoint.npz``
(atomic; ``--resume`` continues from it), ``log.csv`` (iteration, loss terms, PSNR, surfel
count, seconds), ``previews/iter_NNNNNN.png`` (render | ground truth of the first training
view), ``metrics.json`` (test-view evaluation), ``config.json`` and the manifest
(``mi_shadowgs.io.provenance``): ``--resume`` continues only a run of the same dataset and
settings, ``--overwrite`` removes only the files the manifest lists.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mi_shadowgs.config import PRESET_NAMES

GEOMETRY_FOLDER = "geometry"  # the stage's subfolder of the run, as `mi-shadowgs run` has it
PRUNE_HELP = ("after stage 1, remove the surfels whose centre falls outside the training masks "
              "(dilated 1 px) in at least N views: floaters along a textured base's outline "
              "(default: the preset's, 0: off)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", help="dataset folder (transforms_train.json, ...)")
    parser.add_argument("--out", required=True, help="run folder; the stage writes a subfolder")
    parser.add_argument("--preset", default="cpu-small",
                        help=f"stage 1's preset: {', '.join(PRESET_NAMES)} (default cpu-small)")
    parser.add_argument("--iterations", type=int, default=None, help="override the preset")
    parser.add_argument("--prune-outside-masks", type=int, default=None, metavar="N",
                        help=PRUNE_HELP)
    parser.add_argument("--resume", action="store_true",
                        help="continue from the stage's last checkpoint (from step 0 when "
                             "it was stopped before its first)")
    parser.add_argument("--overwrite", action="store_true",
                        help="start afresh, removing the files of an earlier train there")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="override a stage-1 setting (GeometryConfig; e.g. "
                             "lambda_normal=0.2, densify.max_surfels=50000); repeatable")
    parser.add_argument("--no-eval", action="store_true", help="skip the test-view metrics")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args) -> int:
    from mi_shadowgs.presets import build, merge, parse_sets
    from mi_shadowgs.stages.geometry import run_geometry

    overrides = parse_sets(args.set, section="geometry")
    for flag, field in (("iterations", "iterations"), ("prune_outside_masks", "hull_prune_views")):
        if getattr(args, flag) is not None:
            overrides = merge(overrides, {"geometry": {field: getattr(args, flag)}})
    config = build(args.preset, overrides).geometry
    result = run_geometry(args.data, Path(args.out) / GEOMETRY_FOLDER, config, preset=args.preset,
                          resume=args.resume, overwrite=args.overwrite,
                          evaluate=not args.no_eval, progress=not args.no_progress)
    if result.summary:
        print(result.summary)
    return 0
