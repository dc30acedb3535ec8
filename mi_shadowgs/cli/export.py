"""``mi-shadowgs export RUN --format {3dgs-ply,2dgs-ply,mesh} --out FOLDER [--color albedo]``:
the run's stage-4 model as files other tools load (``mi_shadowgs.stages.export.export``).

``3dgs-ply``/``2dgs-ply`` write ``FOLDER/point_cloud.ply`` (SH padded to degree 3; colours
as splat viewers display them, ``--color albedo`` for the shadow-free albedo); ``mesh``
writes ``object.ply``/``.obj`` (and ``base.*``), ``scene.xml`` (Mitsuba: principled BSDF
from per-vertex albedo/roughness/metallic, the fitted lights, the test cameras) and
``export.json``. The mesh needs the run's dataset (the run's manifest names it; ``--data``
to give its new place). ``FOLDER`` gets a manifest: rerunning reuses a finished export of
the same inputs and settings, ``--overwrite`` replaces only the files export wrote.
"""

from __future__ import annotations

import argparse

from mi_shadowgs.config import PRESET_NAMES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder written by `mi-shadowgs run` (stage 4 done)")
    parser.add_argument("--format", required=True, dest="fmt", metavar="FORMAT",
                        help="3dgs-ply, 2dgs-ply or mesh")
    parser.add_argument("--out", required=True, help="output folder (new, or an earlier export)")
    parser.add_argument("--color", default="sh",
                        help="splat PLY colour: sh (view-dependent, default) or albedo")
    parser.add_argument("--frame", default=None, choices=("opencv", "y-up"),
                        help="splat PLYs' world frame: opencv (the splat tools' and 3DGS's, "
                             "Y down: upright in SuperSplat; default) or y-up (ours); the "
                             "header records it, so our reader turns it back")
    parser.add_argument("--data", default=None,
                        help="the run's dataset, when it moved (mesh: training cameras)")
    parser.add_argument("--preset", default=None,
                        help=f"{', '.join(PRESET_NAMES)} (default: the run's preset)")
    parser.add_argument("--bsdf", default=None, choices=("model", "principled"),
                        help="mesh: scene.xml's BSDF: model (the fitted Cook-Torrance out of "
                             "Mitsuba's diffuse/roughconductor/blendbsdf; default) or "
                             "principled (Disney; what other tools map)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier export there (only the files it wrote)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")


def run(args) -> int:
    import dataclasses

    from mi_shadowgs.config import ConfigError
    from mi_shadowgs.presets import get_config, recorded
    from mi_shadowgs.stages.export.export import ExportConfig, export_run

    try:  # the run's own export settings; a folder that is no run is named by export_run
        config = get_config(args.preset).export if args.preset else recorded(args.run).export
    except ConfigError:
        config = ExportConfig()
    if args.bsdf is not None:
        config = dataclasses.replace(config, bsdf=args.bsdf)
    result = export_run(args.run, args.out, args.fmt, color=args.color, data=args.data,
                        config=config, overwrite=args.overwrite,
                        progress=not args.no_progress, frame=args.frame)
    print(result.summary)
    return 0
