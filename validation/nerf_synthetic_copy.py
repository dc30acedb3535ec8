"""A NeRF-synthetic copy of one of our datasets: the same views in Blender's Z-up world.

Cameras (and normal buffers) are turned from our Y-up world into Blender's
(``inverse(BLENDER_TO_YUP)``); ``dataset.json``, ``lights.json`` and ``world_up`` are left
out, as NeRF-synthetic has none, so the loader must recognise the frame by itself and turn
it back. Stage 1 on the copy must then match stage 1 on the original.

    python -m validation.nerf_synthetic_copy SRC DST
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)


def blender_copy(src: Path, dst: Path) -> None:
    from mi_shadowgs.dataset import layout
    from mi_shadowgs.dataset.loader import BLENDER_TO_YUP
    from mi_shadowgs.io.atomic import atomic_dir
    from mi_shadowgs.io.images import read_exr, write_exr

    if dst.exists():
        raise FileExistsError(f"{dst} already exists; the copy goes to a new folder")
    to_blender = np.linalg.inv(BLENDER_TO_YUP)
    # Whole or not at all: a copy cut short would look like a dataset (its transforms
    # written) with images missing.
    with atomic_dir(dst) as tmp:
        _copy_splits(src, tmp, to_blender, layout, read_exr, write_exr)


def _copy_splits(src: Path, dst: Path, to_blender, layout, read_exr, write_exr) -> None:
    for split in layout.SPLITS:
        meta = json.loads((src / layout.transforms_name(split)).read_text())
        meta.pop("world_up", None)
        for fr in meta["frames"]:
            fr["transform_matrix"] = (to_blender @ np.array(fr["transform_matrix"])).tolist()
        (dst / layout.transforms_name(split)).write_text(json.dumps(meta, indent=1))
        (dst / split).mkdir()
        for f in sorted((src / split).iterdir()):
            if f.name.endswith(layout.NORMAL):
                n = read_exr(f)
                n[..., :3] = n[..., :3] @ to_blender[:3, :3].T
                write_exr(dst / split / f.name, n)
            elif "_relit_" not in f.name:  # relit views need lights.json: not for stage 1
                shutil.copy2(f, dst / split / f.name)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("src")
    parser.add_argument("dst")
    args = parser.parse_args(argv)
    blender_copy(Path(args.src), Path(args.dst))


if __name__ == "__main__":
    main()
