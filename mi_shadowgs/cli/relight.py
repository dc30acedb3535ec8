"""``mi-shadowgs relight RUN --out DIR``: a finished run's model under new lights.

Lights (together, in one light set): ``--light AZ,EL,IRRADIANCE`` (repeatable; degrees and
W/m^2, or ``AZ,EL,R,G,B``), ``--envmap FILE [--rotate DEG] [--envmap-scale S]``, ``--scene
XML`` (its directional and infinite emitters). Views: ``--cameras transforms.json``,
``--orbit N`` (a circle about the object at the run's camera distance), else the run's test
views. Writes ``NAME.exr`` (linear RGBA) and ``NAME.png`` (sRGB) per view,
``relight.json`` (lights, views, per-frame times) and, with ``--video``, a turntable
(MP4, or GIF where no H.264 encoder is installed, said on the terminal). Shadow maps are
rendered once per light direction and reused by every frame. DIR is new or holds an
earlier relight (``--overwrite`` removes only its files).
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="a finished run folder (mi-shadowgs run)")
    parser.add_argument("--out", required=True, help="output folder: new, or an earlier relight")
    parser.add_argument("--light", action="append", default=[], metavar="AZ,EL,IRRADIANCE",
                        help="directional light: azimuth and elevation (degrees; "
                             "docs/conventions.md) and irradiance (W/m^2, or R,G,B); "
                             "repeatable")
    parser.add_argument("--envmap", default=None, metavar="FILE",
                        help="env map (lat-long EXR, Y-up) integrated over 128 directions")
    parser.add_argument("--rotate", type=float, default=0.0, metavar="DEG",
                        help="turn the env map about +Y (as azimuth turns)")
    parser.add_argument("--envmap-scale", type=float, default=1.0, metavar="S",
                        help="multiply the env map's radiance")
    parser.add_argument("--scene", default=None, metavar="XML",
                        help="a Mitsuba scene whose emitters light the model")
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
    from pathlib import Path

    import numpy as np

    from mi_shadowgs.cli import CLIError
    from mi_shadowgs.dataset.loader import load_cameras
    from mi_shadowgs.io.images import linear_to_srgb, to_uint8, write_exr, write_png
    from mi_shadowgs.io.provenance import Output, Provenance, input_ref
    from mi_shadowgs.stages.relight import render as relight
    from mi_shadowgs.stages.relight import runner

    if not args.light and args.envmap is None and args.scene is None:
        raise CLIError("no light: give --light AZ,EL,IRRADIANCE, --envmap FILE or --scene XML")
    # Bad light arguments fail before anything is loaded.
    runner.check_light_args(args.light, args.envmap, args.rotate, args.envmap_scale,
                            args.scene)
    if args.fps <= 0 or not np.isfinite(args.fps):
        raise CLIError(f"--fps must be > 0, got {args.fps:g}")
    run_dir = Path(args.run)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder not found: {run_dir}")
    named = []
    if args.cameras is not None:
        if not Path(args.cameras).is_file():
            raise FileNotFoundError(f"--cameras {args.cameras}: file not found")
        named = [(Path(n).name or f"view_{i:03d}", c)
                 for i, (n, c) in enumerate(load_cameras(args.cameras))]
    fit = runner.load_run(run_dir, args.fit, [c for _, c in named])
    cache = relight.RelightCache()
    lights = runner.build_lights(args.light, args.envmap, args.rotate, args.envmap_scale,
                                 args.scene, relight.get_config(fit.preset), cache)
    if args.orbit is not None or not named:
        test = runner.dataset_cameras(fit.dataset, "test") if fit.dataset else []
        if args.orbit is None:
            if not test:
                raise CLIError(f"{run_dir}: its dataset's test views are gone; give "
                               "--cameras or --orbit")
            named = [(f"test_{i:03d}", c) for i, c in enumerate(test)]
        else:
            template = (test or runner.dataset_cameras(fit.dataset, "train"))[0] \
                if fit.dataset else None
            if template is None:
                raise CLIError(f"{run_dir}: no camera to orbit with (its dataset is gone); "
                               "give --cameras")
            named = [(f"orbit_{i:03d}", c) for i, c in enumerate(runner.orbit_cameras(
                args.orbit, template, fit.bounds.center, args.orbit_elevation))]
    if len({n for n, _ in named}) != len(named):
        named = [(f"{i:03d}_{n}", c) for i, (n, c) in enumerate(named)]
    inputs = [run_dir / "material" / args.fit / n for n in ("model.ply", "light.json")]
    extra = [Path(p) for p in (args.envmap, args.scene, args.cameras) if p]
    provenance = Provenance(
        inputs={p.name: input_ref(p) for p in inputs + extra},
        settings={"lights": args.light, "envmap": args.envmap, "rotate": args.rotate,
                  "envmap_scale": args.envmap_scale, "scene": args.scene,
                  "orbit": args.orbit, "orbit_elevation": args.orbit_elevation,
                  "fit": args.fit, "video": args.video, "fps": args.fps})
    seconds, frames = [], []
    with Output.open(args.out, "relight", provenance, overwrite=args.overwrite,
                     inputs=inputs + extra + ([fit.dataset] if fit.dataset else [])) as out:
        out.claim(*(f"{n}{x}" for n, _ in named for x in (".exr", ".png")), "relight.json")
        for i, img, secs in runner.relight_frames(fit, [c for _, c in named], lights, cache,
                                                   progress=not args.no_progress):
            name = named[i][0]
            rgb, alpha = img["rgb"], img["alpha"][..., None]
            write_exr(out.folder / f"{name}.exr", np.concatenate([rgb, alpha], -1))
            straight = np.where(alpha > 0, rgb / np.maximum(alpha, 1e-12), 0.0)
            write_png(out.folder / f"{name}.png", np.concatenate([straight, alpha], -1))
            seconds.append(secs)
            if args.video:
                frames.append(to_uint8(linear_to_srgb(np.clip(rgb, 0, 1)), srgb=False))
        video, why = None, None
        if args.video:
            out.claim("turntable.mp4", "turntable.gif")
            video, why = runner.write_video(out.folder / "turntable", frames, args.fps)
        stats = runner.frame_stats(seconds)
        runner.summary_json(out.path("relight.json"), {
            "run": str(run_dir.resolve()), "fit": args.fit, "views": [n for n, _ in named],
            "light_directions": lights.count, "shadow_maps_rendered": cache.rendered,
            "frame_seconds": seconds, **stats,
            "video": video.name if video else None, "video_note": why})
        out.finish()
    later = f", later frames {stats['later_median_s']:.3f} s (median)" \
        if stats["later_median_s"] is not None else ""
    print(f"relit {len(named)} view(s) under {lights.count} light direction(s) into "
          f"{out.folder}: first frame {stats['first_s']:.2f} s (shadow maps included){later}")
    if why:
        print(f"video: {why}")
    if video:
        print(f"video: {video}")
    return 0
