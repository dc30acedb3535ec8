"""Where the optional shared assets are: ``../shared/data`` beside the repository (meshes,
env maps), or the folder named by ``MI_SHADOWGS_SHARED_DATA``. Nothing needs them: callers
fall back to what is built in code (the embedded scene, the procedural sky)."""

from __future__ import annotations

import os
from pathlib import Path

SHARED_DATA_ENV = "MI_SHADOWGS_SHARED_DATA"
ENVMAP_SUFFIXES = (".exr", ".hdr")


def shared_data_dir() -> Path:
    """``$MI_SHADOWGS_SHARED_DATA``, else ``shared/data`` beside the repository."""
    env = os.environ.get(SHARED_DATA_ENV)
    return Path(env) if env else Path(__file__).resolve().parents[2].parent / "shared" / "data"


def shipped_envmaps() -> list[Path]:
    """The shared env maps (``envmaps/*.exr``, ``*.hdr``), sorted by name; [] when absent."""
    folder = shared_data_dir() / "envmaps"
    if not folder.is_dir():
        return []
    return sorted(p.resolve() for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in ENVMAP_SUFFIXES)
