"""``mi-shadowgs segment RUN_OR_MODEL --data DATA --out OUT``: stage 2, material segments.

RUN_OR_MODEL is a surfel model PLY, or a run folder holding ``geometry/model.ply``.
Trains per-surfel features on the training views' label maps (``--masks material``: the
dataset's material ids; ``chromaticity``: shadow-invariant automatic masks), clusters
them, and writes to OUT:

- ``model.ply``: the model with channels ``feature_0..D-1`` and ``segment`` (id 0..K-1);
- ``segments/NAME.png``: the rendered segment map of every view of ``--split``
  (colour-coded, black = background), ``segments/NAME_overlay.png``: it over the image;
- ``segmentation.json``: settings, K, timings, and where the split has material ids, the
  adjusted Rand index, mIoU (Hungarian matching) and the lit/shadowed check of the base;
- the manifest (``mi_shadowgs.io.provenance``): dataset fingerprint, input model digest,
  settings and the files written (``--overwrite`` removes only those).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mi_shadowgs.config import PRESET_NAMES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", metavar="RUN_OR_MODEL",
                        help="surfel model PLY, or a run folder with geometry/model.ply")
    parser.add_argument("--data", required=True, help="dataset folder (training views)")
    parser.add_argument("--out", required=True,
                        help="output folder: new, or holding an earlier segment output")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier segment output there (only its files)")
    parser.add_argument("--resume", action="store_true",
                        help="continue an interrupted segment output there from its checkpoint")
    parser.add_argument("--preset", default="cpu-small",
                        help=f"{', '.join(PRESET_NAMES)} (default cpu-small)")
    parser.add_argument("--masks", default="material", choices=("material", "chromaticity"),
                        help="label maps to train on (default: the dataset's material ids)")
    parser.add_argument("--segments", "--k", dest="k", type=int, default=None,
                        help="number of segments K (default: the number of mask labels with "
                        "enough pixels; --set k_select=silhouette: the K of best silhouette "
                        "up to it)")
    parser.add_argument("--split", default="test",
                        help="views to render segment maps of (default: test)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a segmentation setting (repeatable)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def resolve_model(path: str | Path) -> Path:
    """The model PLY of a run folder or a PLY path (FileNotFoundError naming it)."""
    p = Path(path)
    if p.is_dir():
        cand = p / "geometry" / "model.ply"
        if not cand.is_file():
            raise FileNotFoundError(f"{p}: run folder without geometry/model.ply")
        return cand
    if not p.is_file():
        raise FileNotFoundError(f"model file not found: {p}")
    return p


def run(args) -> int:
    from mi_shadowgs.presets import build, merge, parse_sets
    from mi_shadowgs.stages.segmentation import run_segmentation

    if args.resume and args.overwrite:  # as `train` refuses them
        raise ValueError("--resume continues the stage's files and --overwrite removes them: "
                         "pass one of them")
    overrides = parse_sets(args.set, section="segmentation")
    if args.k is not None:
        overrides = merge(overrides, {"segmentation": {"n_segments": args.k}})
    config = build(args.preset, overrides)  # before any file
    result = run_segmentation(resolve_model(args.model), args.data, args.out,
                              config.segmentation, masks=args.masks,
                              chromaticity=config.chromaticity, preset=args.preset,
                              split=args.split,
                              overwrite=args.overwrite, reuse=args.resume,
                              progress=not args.quiet)
    print(result.summary)
    return 0
