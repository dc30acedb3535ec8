"""``mi-shadowgs render MODEL.ply --cameras transforms.json --out DIR``: render a surfel model.

Per view (named after the frame's ``file_path``): ``NAME.exr`` linear RGBA (colour
premultiplied over black, or composited over ``--background``), ``NAME.png`` an sRGB preview,
and for each ``--aov``: ``NAME_AOV.exr`` plus a normalised ``NAME_AOV.png`` preview.
OUT is new, or holds an earlier render: ``--overwrite`` removes the files its manifest lists
(``mi_shadowgs.io.provenance``) so that old and new renders never mix. OUT is never a dataset
folder or inside one.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

# Preview normalisation per AOV kind (see _preview).
_RANGE_AOVS = ("depth", "median_depth")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="surfel model (PLY, 2DGS layout)")
    parser.add_argument("--cameras", required=True,
                        help="NeRF-synthetic transforms_*.json with the views to render")
    parser.add_argument("--out", required=True,
                        help="output folder: new, or holding an earlier render")
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
    parser.add_argument("--memory-budget", default=None, metavar="SIZE",
                        help="most memory this process may hold while rendering, e.g. 4G "
                             "(default: what it holds plus half of the available memory); "
                             "larger renders are drawn in bands of rows")


def _exr_names(width: int) -> list[str]:
    if width in (1, 3):
        return ["Y"] if width == 1 else ["R", "G", "B"]
    return [f"C{i:02d}" for i in range(width)]  # zero-padded: EXR sorts channel names


def _preview(name: str, img: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """A displayable [H, W, 1 or 3] image in [0, 1] for AOV ``name`` (linear)."""
    covered = alpha[..., 0] > 0
    if name == "normal":
        return np.where(covered[..., None], img * 0.5 + 0.5, 0.0)
    if name == "alpha":
        return img
    if name in _RANGE_AOVS:
        # min-max over covered pixels; background stays black.
        vals = img[covered]
        lo, hi = (float(vals.min()), float(vals.max())) if vals.size else (0.0, 1.0)
        out = (img - lo) / max(hi - lo, 1e-12)
        return np.where(covered[..., None], 0.1 + 0.9 * np.clip(out, 0, 1), 0.0)
    if img.shape[-1] == 3 and name not in ("distortion", "count"):
        return img  # a colour-like channel (e.g. albedo): premultiplied linear colour
    img = img[..., :3] if img.shape[-1] >= 3 else img[..., :1]
    lo, hi = float(img.min()), float(img.max())
    return (img - lo) / max(hi - lo, 1e-12)


def run(args) -> int:
    from mi_shadowgs.core.memory import parse_bytes
    from mi_shadowgs.core.raster import RasterConfig
    from mi_shadowgs.core.render import aov_layout, parse_background
    from mi_shadowgs.dataset.loader import load_cameras
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.io.provenance import Output, Provenance, input_ref

    model = Path(args.model)
    if not model.is_file():
        raise FileNotFoundError(f"model file not found: {model}")
    if not Path(args.cameras).is_file():
        raise FileNotFoundError(f"cameras file not found: {args.cameras}")
    surfels = load_ply(model)
    aovs = list(dict.fromkeys(args.aov))
    aov_layout(aovs, surfels)  # unknown names fail before any rendering
    background = parse_background(args.background, "--background")
    raster = RasterConfig() if args.memory_budget is None else \
        RasterConfig(memory_budget_bytes=parse_bytes(args.memory_budget, "--memory-budget"))
    if args.color_channel not in surfels.channels:
        raise ValueError(f"{model}: no channel {args.color_channel!r} for --color-channel "
                         f"(channels: {sorted(surfels.channels)})")
    cameras = load_cameras(args.cameras)
    stems = [Path(name).name or f"view_{i:03d}" for i, (name, _) in enumerate(cameras)]
    if len(set(stems)) != len(stems):  # frames from different folders with equal names
        stems = [f"{i:03d}_{s}" for i, s in enumerate(stems)]
    provenance = Provenance(
        inputs={"model": input_ref(model), "cameras": input_ref(args.cameras)},
        settings={"aovs": aovs, "background": background, "color_channel": args.color_channel})
    with Output.open(args.out, "render", provenance, overwrite=args.overwrite,
                     inputs=[model, args.cameras]) as out:
        out.claim(*(f"{stem}{suffix}" for stem in stems for suffix in
                    [".exr", ".png"] + [f"_{a}{ext}" for a in aovs for ext in (".exr", ".png")]))
        _render_views(out.folder, surfels, cameras, stems, aovs, background, args.color_channel,
                      raster)
        out.finish()
    print(f"rendered {len(cameras)} view(s) of {surfels.count} surfels to {out.folder}")
    return 0


def _render_views(out: Path, surfels, cameras, stems, aovs, background, color_channel,
                  raster) -> None:
    from tqdm import tqdm

    from mi_shadowgs.core.render import render_surfels
    from mi_shadowgs.io.images import write_exr, write_png

    for stem, (_, camera) in tqdm(list(zip(stems, cameras, strict=True)), desc="render",
                                  unit="view"):
        images = render_surfels(surfels, camera, color_channel=color_channel, aovs=aovs,
                                background=background, config=raster)
        arrays = {k: np.asarray(v.numpy(), dtype=np.float32) for k, v in images.items()}
        rgb, alpha = arrays["rgb"], arrays["alpha"]
        write_exr(out / f"{stem}.exr", np.concatenate([rgb, alpha], axis=-1))
        if background is None:
            # PNG alpha is straight: un-premultiply the colour for the preview.
            straight = np.where(alpha > 0, rgb / np.maximum(alpha, 1e-12), 0.0)
            write_png(out / f"{stem}.png", np.concatenate([straight, alpha], axis=-1))
        else:
            write_png(out / f"{stem}.png", rgb)
        for name in aovs:
            img = arrays[name]
            write_exr(out / f"{stem}_{name}.exr", img, channels=_exr_names(img.shape[-1]))
            write_png(out / f"{stem}_{name}.png", _preview(name, img, alpha),
                      srgb=name not in ("normal", "alpha") + _RANGE_AOVS)
