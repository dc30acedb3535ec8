"""Atomic outputs: a reader never sees a half-written file or dataset folder.

Temporary siblings are hidden (``.NAME.PID-XXXXXXXX.tmp.EXT`` files,
``.NAME.PID-XXXXXXXX.partial`` folders), named by the writing process. A write killed
half-way leaves one behind; the next write of the same output removes it once its process
has ended. Another process's write in flight is left alone: processes that share an output
folder (``validation.pipeline``'s rows) each write its tables. Outputs get the permissions
of a plain ``open`` (0666 / 0777 less the umask), not the 0600 / 0700 that ``tempfile``
gives its files and folders.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

_TMP_FILE = ".tmp"  # suffix stem of atomic_path's files
_TMP_DIR = ".partial"  # suffix of atomic_dir's folders


def _umask() -> int:
    # Reading the umask means setting it; the CLI is single-threaded where this runs.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


# The temporaries this process is writing now (a thread's write is never another's stale),
# by absolute path: a caller may name the same output relatively and absolutely.
_IN_FLIGHT: set[str] = set()


def _key(tmp: Path) -> str:
    return os.path.abspath(tmp)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _is_stale(tmp: Path, pid: str | None) -> bool:
    """A temporary is stale unless its writer is still writing it: names from before the
    writer's pid was recorded are always stale; this process's are stale unless in flight
    (a killed run's pid is often reused in a container); another's while it lives are not."""
    if pid is None:
        return True
    if int(pid) == os.getpid():
        return _key(tmp) not in _IN_FLIGHT
    return not _process_alive(int(pid))


def _stale_siblings(path: Path, suffix: str) -> list[Path]:
    """Temporaries that ``tempfile`` made for ``path`` with ``suffix`` (the writer's pid and
    8 random characters between the prefix and the suffix), so that another output's are
    never matched, and whose writer is no longer writing them."""
    prefix = f".{path.name}."
    pattern = re.compile(re.escape(prefix) + r"(?:(\d+)-)?[A-Za-z0-9_]{8}" + re.escape(suffix))
    if not path.parent.is_dir():
        return []
    # Every write scans its folder (a dataset's 600+ files: quadratic), so the scan stays
    # on plain names: a prefix test before the pattern, a Path only for a match.
    with os.scandir(path.parent) as entries:
        matches = [(path.parent / e.name, m.group(1)) for e in entries
                   if e.name.startswith(prefix) and (m := pattern.fullmatch(e.name))]
    return [tmp for tmp, pid in matches if _is_stale(tmp, pid)]


def _temp_prefix(path: Path) -> str:
    return f".{path.name}.{os.getpid()}-"


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def remove_stale(path: str | os.PathLike) -> None:
    """Remove the temporaries that killed atomic writes of ``path`` left beside it."""
    path = Path(path)
    for stale in (_stale_siblings(path, _TMP_FILE + path.suffix)
                  + _stale_siblings(path, _TMP_DIR)):
        _remove(stale)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; it replaces ``path`` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale(path)
    fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=_TMP_FILE + path.suffix,
                               dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    _IN_FLIGHT.add(_key(tmp))
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        _IN_FLIGHT.discard(_key(tmp))
        if tmp.exists():
            tmp.unlink()


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def check_replaceable(path: str | os.PathLike, marker: str) -> None:
    """Raise FileExistsError unless ``path`` is absent or holds ``marker``, the file an
    earlier output of the same command writes there: ``atomic_dir`` with ``overwrite``
    replaces a folder whole, so a command checks this before any work."""
    path = Path(path)
    if path.exists() and not (path / marker).is_file():
        raise FileExistsError(f"{path}: exists and holds no {marker}; not replacing it")


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Build a folder in a temporary sibling and move it into place when the block succeeds.

    With ``overwrite`` an existing folder is replaced (moved aside to ``.NAME.old``, then
    deleted). A crash in between leaves the old folder whole there; the next call puts it
    back before anything else, so ``path`` is never lost and never a mix.
    """
    path = Path(path)
    old = path.with_name(f".{path.name}.old")
    with staged_dir(path) as tmp:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())
        if path.exists():
            if not overwrite:
                raise FileExistsError(f"{path} already exists")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old)
        else:
            os.replace(tmp, path)


@contextlib.contextmanager
def staged_dir(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary sibling of the folder ``path``, named and cleaned up as ``atomic_dir``'s
    (which moves it into place whole); removed after the block, whatever the block moved
    out of it. A ``.NAME.old`` that a killed ``atomic_dir`` left is put back first."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    old = path.with_name(f".{path.name}.old")
    if old.exists():
        if path.exists():
            shutil.rmtree(old)
        else:
            os.replace(old, path)
    remove_stale(path)
    tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=_TMP_DIR, dir=path.parent))
    _IN_FLIGHT.add(_key(tmp))
    try:
        yield tmp
    finally:
        _IN_FLIGHT.discard(_key(tmp))
        if tmp.exists():
            shutil.rmtree(tmp)
