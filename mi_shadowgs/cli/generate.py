"""``mi-shadowgs generate SCENE.xml --out DIR``: render a shadowed synthetic dataset.

Killed part-way, the same command again continues from the views already rendered."""

from __future__ import annotations

import argparse

from mi_shadowgs.config import PRESET_NAMES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", default="default",
                        help="scene XML path, or the name of a shipped scene "
                             "(default: the embedded 'default' scene)")
    parser.add_argument("--out", required=True, help="output dataset folder")
    parser.add_argument("--preset", default="cpu-small",
                        help=f"generation preset: {', '.join(PRESET_NAMES)} (default cpu-small)")
    parser.add_argument("--spp", type=int, default=None,
                        help="samples per pixel (preset): one pass up to 64, else a "
                             "multiple of 64 in passes of 64")
    # No choices= here: the parser is built before the libLLVM check, and the list lives
    # in mi_shadowgs.dataset.generate (importing it here would start Dr.Jit); an unknown name
    # exits 2 listing them (GenerateConfig).
    parser.add_argument("--sampler", default=None,
                        help="Mitsuba pixel sampler (default multijitter; a pass count it "
                             "would round, such as 32 -> 35, exits 2)")
    parser.add_argument("--width", type=int, default=None, help="image width (preset)")
    parser.add_argument("--height", type=int, default=None, help="image height (preset)")
    parser.add_argument("--n-train", type=int, default=None, help="training views (preset)")
    parser.add_argument("--n-test", type=int, default=None, help="test views (preset)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--envmap", action="append", default=None, metavar="PATH|sky|auto|none",
                        help="an env map (EXR/HDR) of one env-map relit test set; repeatable. "
                             "'sky': the procedural sky; 'auto' (the preset's default): the "
                             "shipped maps in ../shared/data/envmaps (or "
                             "$MI_SHADOWGS_SHARED_DATA/envmaps) when present, else the sky; "
                             "'none': no env-map relighting")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a dataset that generate wrote before (refused when "
                             "the folder holds files not in its .mi_shadowgs_manifest.json)")
    parser.add_argument("-D", dest="defines", action="append", default=[],
                        metavar="NAME=VALUE",
                        help="set a scene <default> parameter, or one that every scene "
                             "takes: base_texture=mat, and the capture's (docs/capture.md): "
                             "capture=lab (a lamp at 6 object radii, room light, the photos' "
                             "exposure and white-balance jitter, noise, JPEG), lamp_*, "
                             "room_radiance, photo_*")
    parser.add_argument("--photos", action="store_true",
                        help="also write every view as a user's photo (sRGB JPEG, no camera, "
                             "no mask) under DIR/photos/, for `mi-shadowgs import`; pair it "
                             "with -D base_texture=mat so that SfM finds features")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _parse_defines(defines: list[str]) -> dict[str, str]:
    out = {}
    for d in defines:
        name, sep, value = d.partition("=")
        if not sep or not name.strip():
            raise ValueError(f"-D {d!r}: expected NAME=VALUE")
        out[name.strip()] = value.strip()
    return out


def _resolve_scene(name: str):
    from pathlib import Path

    from mi_shadowgs.scenes import scene_path

    p = Path(name)
    if p.suffix.lower() == ".xml" or p.exists() or "/" in name:
        return p
    return scene_path(name)


def run(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    from mi_shadowgs.config import with_overrides
    from mi_shadowgs.dataset.writer import write_dataset
    from mi_shadowgs.presets import generate_config

    config = generate_config(args.preset)
    over = {k: v for k, v in (("spp", args.spp), ("width", args.width),
                              ("height", args.height), ("n_train", args.n_train),
                              ("n_test", args.n_test)) if v is not None}
    for k, v in over.items():
        if v < 1:
            raise ValueError(f"--{k.replace('_', '-')} must be >= 1, got {v}")
    if args.sampler:
        over["sampler"] = args.sampler
    if args.envmap:
        from mi_shadowgs.dataset.writer import ENVMAP_KEYWORDS

        # absolute paths: the dataset records them, and its fingerprint covers their content
        over["envmaps"] = tuple(e if e in ENVMAP_KEYWORDS else str(Path(e).resolve())
                                for e in args.envmap)
    config = with_overrides(config, over, "dataset generation")
    t0 = time.perf_counter()
    out, written = write_dataset(_resolve_scene(args.scene), args.out, config, args.preset,
                                 seed=args.seed, overrides=_parse_defines(args.defines),
                                 overwrite=args.overwrite,
                                 progress=not args.no_progress, photos=args.photos)
    if written:
        print(f"wrote {out} in {time.perf_counter() - t0:.1f} s")
    else:
        print(f"{out} already holds this dataset (same inputs); nothing to do")
    return 0
