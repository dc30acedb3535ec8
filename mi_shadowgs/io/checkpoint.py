"""Atomic training checkpoints: one ``.npz`` of named arrays plus a JSON header.

``save_checkpoint(dir, arrays, meta)`` writes ``dir/checkpoint.npz`` through a temporary
sibling and ``os.replace`` (``mi_shadowgs.io.atomic``): a run killed while writing leaves the
previous checkpoint whole. ``load_checkpoint(dir)`` returns ``(arrays, meta)`` or raises
``CheckpointError`` naming the file.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from mi_shadowgs.io.atomic import atomic_path

CHECKPOINT_NAME = "checkpoint.npz"
_META_KEY = "__meta__"
FORMAT_VERSION = 2  # 2: stage 1 saves its log sums; stages 2 and 4 have checkpoints


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable or from an incompatible run."""


def checkpoint_path(directory: str | Path) -> Path:
    return Path(directory) / CHECKPOINT_NAME


def save_checkpoint(directory: str | Path, arrays: dict[str, np.ndarray], meta: dict) -> Path:
    """Write ``arrays`` and the JSON-serialisable ``meta`` atomically; returns the path."""
    if _META_KEY in arrays:
        raise ValueError(f"save_checkpoint: {_META_KEY!r} is a reserved name")
    path = checkpoint_path(directory)
    header = json.dumps({"format_version": FORMAT_VERSION, **meta})
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **{_META_KEY: np.frombuffer(header.encode(), np.uint8)},
                     **{k: np.asarray(v) for k, v in arrays.items()})
    return path


def has_checkpoint(directory: str | Path) -> bool:
    return checkpoint_path(directory).is_file()


def load_checkpoint(directory: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    path = checkpoint_path(directory)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint to resume from")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise CheckpointError(f"{path}: unreadable checkpoint: {exc}") from None
    if _META_KEY not in arrays:
        raise CheckpointError(f"{path}: not a mi_shadowgs checkpoint (no header)")
    meta = json.loads(arrays.pop(_META_KEY).tobytes().decode())
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format {meta.get('format_version')!r}, "
                              f"this version reads {FORMAT_VERSION}")
    return arrays, meta
