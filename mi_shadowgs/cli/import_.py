"""``mi-shadowgs import PHOTOS --out DATA``: your own photos (SfM on the CPU) or a COLMAP
model of them, as a dataset in this project's layout and world frame (import.json says how).
"""

from __future__ import annotations

import argparse

from mi_shadowgs.config import PRESET_NAMES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", help="folder of photos (JPEG/PNG, one camera, one size), or "
                        "a nerfstudio transforms.json")
    parser.add_argument("--out", required=True, help="new dataset folder")
    parser.add_argument("--colmap", default=None, metavar="SPARSE",
                        help="an existing COLMAP model of these photos (e.g. sparse/0): no SfM")
    parser.add_argument("--masks", default=None, metavar="DIR",
                        help="masks of the object and the ground its shadows fall on (the "
                             "ground is the shadows' receiver), one per photo with the "
                             "photo's name (PNG; alpha or grey)")
    parser.add_argument("--preset", default="cpu-small",
                        help=f"import preset: {', '.join(PRESET_NAMES)} (default cpu-small)")
    parser.add_argument("--test-every", type=int, default=None,
                        help="hold out every K-th registered view for testing (preset: 8)")
    parser.add_argument("--max-size", type=int, default=None,
                        help="longest side of the training images in pixels (preset); the "
                             "full-size undistorted photos are kept under DATA/colmap/")
    parser.add_argument("--focal-px", type=float, default=None,
                        help="known focal length in pixels of the photos (else EXIF or a guess)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args: argparse.Namespace) -> int:
    from mi_shadowgs.config import with_overrides
    from mi_shadowgs.dataset.importer import ground_outside_masks_warning, import_capture
    from mi_shadowgs.presets import import_config

    config = import_config(args.preset)
    over = {k: v for k, v in (("test_every", args.test_every), ("max_size", args.max_size),
                              ("focal_px", args.focal_px)) if v is not None}
    for k, v in over.items():
        if v <= 0:
            raise ValueError(f"--{k.replace('_', '-')} must be > 0, got {v}")
    config = with_overrides(config, over, "import")
    rec = import_capture(args.source, args.out, config, colmap=args.colmap, masks=args.masks,
                         progress=not args.no_progress)
    n = len(rec["registered"]) + len(rec["rejected"])
    err = rec["mean_reprojection_error_px"]
    print(f"wrote {args.out}: {len(rec['registered'])}/{n} views registered, "
          f"{rec['points']} points"
          + ("" if err is None else f", {err:.2f} px reprojection error")
          + f", {rec['timings']['total_s']:.1f} s")
    # the next step, and the one setting a photographed ground needs (README, "Your own photos")
    print(f"next: mi-shadowgs run {args.out} --out RUN   (a printed or textured ground: add "
          "--albedo-detail 0.1)")
    if (note := ground_outside_masks_warning(rec)) is not None:
        from mi_shadowgs.stages.common import warn

        warn(note)
    return 0
