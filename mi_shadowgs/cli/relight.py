"""``mi-shadowgs relight RUN --out DIR``: a finished run's model under new lights.

Lights (together, in one light set): ``--light AZ,EL,IRRADIANCE`` (repeatable; degrees and
W/m^2, or ``AZ,EL,R,G,B``), ``--point X,Y,Z,INTENSITY[,RADIUS]`` (repeatable; a lamp at a
position of the run's world frame, its radiant intensity in W/sr, or
``X,Y,Z,R,G,B[,RADIUS]``; a radius > 0 is a sphere lamp; write ``--point=-1,2,3,50`` where
X is negative), ``--envmap FILE [--rotate DEG] [--envmap-scale S]``, ``--scene XML`` (its
directional, infinite, point, spot and sphere area emitters). A lamp must stand above the
base (y = 0) and outside the scene's bounding sphere, and a spot's cone must reach the
scene. Views: ``--cameras transforms.json``,
``--orbit N`` (a circle about the object at the run's camera distance), else the run's test
views. Writes ``NAME.exr`` (linear RGBA) and ``NAME.png`` (sRGB) per view, ``relight.json``
(lights, views, the per-frame times of the views this call rendered) and, with ``--video``,
a turntable (MP4, or GIF where no H.264 encoder is installed, said on the terminal). Shadow
maps are rendered once per light direction and reused by every frame. DIR is new or holds
an earlier relight: the same relight again continues it (a killed one renders only its
missing views) or, finished, is reused; another is refused unless ``--overwrite`` (which
removes only its files).
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="a finished run folder (mi-shadowgs run)")
    parser.add_argument("--out", required=True,
                        help="output folder: new, or an earlier relight (the same relight is "
                             "continued where it stopped)")
    parser.add_argument("--light", action="append", default=[], metavar="AZ,EL,IRRADIANCE",
                        help="directional light: azimuth and elevation (degrees; "
                             "docs/conventions.md) and irradiance (W/m^2, or R,G,B); "
                             "repeatable")
    parser.add_argument("--point", action="append", default=[],
                        metavar="X,Y,Z,INTENSITY[,RADIUS]",
                        help="lamp: position in the run's world frame, radiant intensity "
                             "(W/sr, or R,G,B) and optional sphere radius (world units; 0: a "
                             "point light); above the base and outside the scene; repeatable "
                             "(a negative X: --point=-1,2,3,50)")
    parser.add_argument("--envmap", default=None, metavar="FILE",
                        help="env map (lat-long EXR, Y-up) integrated over 128 directions")
    parser.add_argument("--rotate", type=float, default=0.0, metavar="DEG",
                        help="turn the env map about +Y (as azimuth turns)")
    parser.add_argument("--envmap-scale", type=float, default=1.0, metavar="S",
                        help="multiply the env map's radiance")
    parser.add_argument("--scene", default=None, metavar="XML",
                        help="a Mitsuba scene whose emitters light the model (directional, "
                             "point, spot, sphere area, envmap, constant)")
    views = parser.add_mutually_exclusive_group()
    views.add_argument("--cameras", default=None, metavar="JSON",
                       help="NeRF-synthetic transforms.json with the views")
    views.add_argument("--orbit", type=int, default=None, metavar="N",
                       help="N views on a circle about the object")
    parser.add_argument("--orbit-elevation", type=float, default=None, metavar="DEG",
                        help="elevation of the orbit (default: the run's first test camera's)")
    parser.add_argument("--video", action="store_true", help="also write a turntable video")
    parser.add_argument("--fps", type=float, default=12.0, help="video frame rate")
    parser.add_argument("--fit", default="full", help="which fit of the run (material/NAME)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier relight there (only its files)")
    parser.add_argument("--no-progress", action="store_true", help="hide progress bars")


def run(args) -> int:
    from mi_shadowgs.stages.relight.runner import run_relight

    result = run_relight(args.run, args.out, args.light, args.envmap, args.rotate,
                         args.envmap_scale, args.scene, args.cameras, args.orbit,
                         args.orbit_elevation, args.video, args.fps, args.fit, args.overwrite,
                         progress=not args.no_progress, points=args.point)
    stats = result.stats
    earlier = result.views - result.rendered
    if result.rendered == 0:
        print(f"{result.folder} already holds these {result.views} relit view(s) (same run, "
              "lights, views and settings); nothing to render")
    else:
        later = (f", later frames {stats['later_median_s']:.3f} s (median)"
                 if stats["later_median_s"] is not None else "")
        print(f"relit {result.rendered} view(s) under {result.light_directions} light "
              f"direction(s) into {result.folder}: first frame {stats['first_s']:.2f} s "
              f"(shadow maps included){later}"
              + (f"; the other {earlier} were there from an earlier call" if earlier else ""))
    if result.video_note:
        print(f"video: {result.video_note}")
    if result.video:
        print(f"video: {result.video}")
    return 0
