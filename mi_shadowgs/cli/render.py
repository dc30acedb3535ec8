"""``mi-shadowgs render MODEL.ply --cameras transforms.json --out DIR``: render a surfel model
(``stages.render.render_views``, whose docstring says what is written where)."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="surfel model (PLY, 2DGS layout)")
    parser.add_argument("--cameras", required=True,
                        help="NeRF-synthetic transforms_*.json with the views to render")
    parser.add_argument("--out", required=True,
                        help="output folder: new, or holding an earlier render (the same "
                             "render is continued where it stopped)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier render there (only its files)")
    parser.add_argument("--aov", action="append", default=[], metavar="NAME",
                        help="extra output: alpha, depth, median_depth, normal, distortion, "
                             "count, or a per-surfel channel (repeatable)")
    parser.add_argument("--background", default=None, metavar="R,G,B",
                        help="composite colour over this linear RGB (default: premultiplied "
                             "over black)")
    parser.add_argument("--color-channel", default="sh",
                        help="channel giving RGB: 'sh' (view-dependent, default) or e.g. "
                             "'albedo'")
    parser.add_argument("--sh-space", choices=("linear", "srgb"), default=None,
                        help="what the PLY's SH colours are: 'linear' (our models) or "
                             "'srgb' (display values, as 3DGS/2DGS and splat viewers store "
                             "them); default: the PLY's header record, else linear")
    parser.add_argument("--world-up", choices=("+y", "+z"), default=None,
                        help="the up axis of a model whose PLY records no world frame: +y "
                             "(ours) or +z (Blender's: e.g. 3DGS/2DGS trained on "
                             "NeRF-synthetic, in its cameras' frame as given); default: the "
                             "cameras' recorded frame; with neither, render exits 2 asking "
                             "for it")
    parser.add_argument("--splat-conventions", action="store_true",
                        help="read the PLY as the splat tools write it: sRGB SH in the "
                             "OpenCV frame (Y down); for an export of ours that a tool "
                             "stripped of its header records (splat-transform)")
    parser.add_argument("--memory-budget", default=None, metavar="SIZE",
                        help="most memory this process may hold while rendering, e.g. 4G "
                             "(default: what it holds plus half of the available memory); "
                             "a render over it takes larger tiles (the same bytes), or exits "
                             "2 naming it")


def run(args) -> int:
    from mi_shadowgs.io.ply import SPLAT_TOOLS
    from mi_shadowgs.stages.render import render_views

    sh_space, frame = args.sh_space, None
    if args.splat_conventions:
        if sh_space not in (None, SPLAT_TOOLS["sh_space"]):
            raise ValueError("--splat-conventions reads the SH as srgb; drop --sh-space")
        sh_space, frame = SPLAT_TOOLS["sh_space"], SPLAT_TOOLS["frame"]
    result = render_views(args.model, args.cameras, args.out, args.aov, args.background,
                          args.color_channel, args.memory_budget, args.overwrite,
                          sh_space=sh_space, world_up=args.world_up, frame=frame)
    if result.rendered == 0:
        print(f"{result.folder} already holds these {result.views} view(s) (same model, "
              "cameras and settings); nothing to render")
        return 0
    earlier = result.views - result.rendered
    print(f"rendered {result.rendered} view(s) of {result.surfels} surfels to {result.folder}"
          + (f"; the other {earlier} were there from an earlier call" if earlier else ""))
    return 0
