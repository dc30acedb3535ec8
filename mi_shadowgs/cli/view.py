"""``mi-shadowgs view RUN``: a finished run in the browser, relit as you move the light.

Starts a local web viewer (viser) on ``--host`` (default 127.0.0.1) and ``--port``: orbit
the camera; move one or two directional lights (azimuth, elevation, intensity) or light with
a shipped env map turned about +Y; switch shadows off (the "w/o visibility" ablation);
show albedo, irradiance, relit or segments; the fitted lights are orange arrows. Frames are
rendered by the relighting code on this machine: a preview at half ``--resolution`` while
you drag, then the full frame (about N^2 pixels at the window's shape). A run without
stage 4 shows geometry (normals) and segments, and the page says why relighting is off.
Stop with Ctrl-C.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="a run folder (mi-shadowgs run)")
    parser.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to bind (default 127.0.0.1: this machine only)")
    parser.add_argument("--resolution", type=int, default=256, metavar="N",
                        help="frames of about N x N pixels (default 256); previews at N/2")
    parser.add_argument("--light", action="append", default=[], metavar="AZ,EL,IRRADIANCE",
                        help="start with this white directional light (degrees, W/m^2; up to "
                             "two); default: the strongest fitted lights")
    parser.add_argument("--fit", default="full", help="which fit of the run (material/NAME)")


def run(args) -> int:
    import time
    from pathlib import Path

    from mi_shadowgs.cli import CLIError
    from mi_shadowgs.stages.relight import runner
    from mi_shadowgs.stages.viewer import server as viewer_server
    from mi_shadowgs.stages.viewer import viewer

    if not 0 <= args.port <= 65535:
        raise CLIError(f"--port must be in [0, 65535], got {args.port}")
    if not 16 <= args.resolution <= 2048:
        raise CLIError(f"--resolution must be in [16, 2048], got {args.resolution}")
    if len(args.light) > 2:
        raise CLIError(f"--light: the viewer has two light sliders, got {len(args.light)}")
    lights = []
    for text in args.light:
        # the viewer's elevation slider spans (0, 90]
        az, el, rgb = runner.parse_light(text, elevation=(0.0, 90.0, False))
        if rgb.max() > rgb.min():  # one intensity slider per light: the viewer's lights are white
            raise CLIError(f"--light {text!r}: the viewer's lights are white (one intensity "
                           "slider); give AZ,EL,IRRADIANCE (or R = G = B); `mi-shadowgs relight "
                           "--light` renders coloured lights")
        lights.append(viewer.DirectionalLight(az % 360.0, el, float(rgb[0])))
    run_dir = Path(args.run)
    if run_dir.is_file():
        raise CLIError(f"{run_dir} is a file; give the run folder (mi-shadowgs run --out)")
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder not found: {run_dir}")
    check_fit(run_dir, args.fit)
    # A busy port or an unknown host fails before the (slow) model load.
    try:
        viewer_server.check_port(args.host, args.port)
    except viewer_server.AddressUnusable as exc:
        raise CLIError(str(exc)) from None
    session = viewer.ViewerSession(run_dir, args.fit)
    if session.relight_off:
        print(f"mi-shadowgs view: {session.relight_off}")
    server = viewer_server.ViewerServer(session, args.host, args.port, args.resolution,
                                        initial_lights=lights)
    try:
        server.start()
    except viewer_server.AddressUnusable as exc:
        raise CLIError(str(exc)) from None
    print(f"mi-shadowgs view: {run_dir} at {server.url} (Ctrl-C to stop)", flush=True)
    # Ctrl-C or SIGTERM ends it: the CLI says "stopped" (cli.STOPPED_BY_SIGNAL).
    try:
        while True:
            time.sleep(3600)
    finally:
        server.stop()


def check_fit(run_dir, fit: str) -> None:
    """CLIError naming --fit when the run has stage-4 fits and ``fit`` is not one of them; a
    run with none is viewed without relighting (the page says why)."""
    from mi_shadowgs.cli import CLIError
    from mi_shadowgs.stages.relight.runner import run_fits

    fits = run_fits(run_dir)
    model = run_dir / "material" / fit / "model.ply"
    if fits and fit not in fits:
        why = "is not one of the run's fits" if model.is_file() else "is missing"
        raise CLIError(f"--fit {fit!r}: {model} {why}; the run's fits: {', '.join(fits)}")
