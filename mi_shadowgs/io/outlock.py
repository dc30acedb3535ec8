"""One writer per output folder, and the output path checked before any work.

Every command that writes holds an advisory lock on its output folder while it runs: a
hidden sibling file ``.NAME.mi_shadowgs-lock`` (beside the folder, never inside it, so that
the folder's own checks of what it holds see nothing new), locked with ``fcntl.flock`` and
holding the writer's PID and command. A second command into the same folder finds it locked
and stops at once, naming that PID.

``flock`` rather than the ``filelock`` package: the kernel drops a flock when its process
ends however it ends (SIGKILL included), so a killed command's lock is stale by
construction and the next command simply takes it; the PID written into the file names the
holder, which ``filelock`` does not record. The file is removed when the lock is let go; a
killed command's file stays, and the next command says that it took it over.

The same step checks the path: its parent can be written, the name is not too long for the
file system, and some free space is left. Those faults then exit 2 naming the path before
any input is read; what happens later (a disk filling up mid-run) is named by the CLI.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

LOCK_SUFFIX = ".mi_shadowgs-lock"
# Below this much free space a command is refused before it starts: a run's checkpoints and
# images need more, and a full disk mid-run costs the user a restart.
MIN_FREE_BYTES = 64 * 2**20
# OS errors that say the output path cannot take what is written (the CLI names the path and
# the reason in one line, exit 2). ENOSPC and EDQUOT mid-run leave a resumable state.
SYSTEM_ERRNOS = frozenset({errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.ENAMETOOLONG,
                           errno.EACCES, errno.EPERM, errno.EFBIG, errno.EIO, errno.EMFILE,
                           errno.ENFILE, errno.EXDEV, errno.ELOOP, errno.ENOTDIR})
SPACE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


class OutputPathError(ValueError):
    """The output folder cannot be written (busy, read-only, full, a name too long)."""


class FolderBusyError(OutputPathError):
    """Another live process holds the output folder's lock."""


def lock_file(folder: str | os.PathLike) -> Path:
    """The lock file of ``folder`` (its real path: two names of one folder share it)."""
    real = Path(os.path.realpath(folder))
    name = f".{real.name}{LOCK_SUFFIX}"
    if len(name.encode()) > 255:  # a long folder name still gets a lock of legal length
        name = f".{hashlib.sha256(real.name.encode()).hexdigest()[:16]}{LOCK_SUFFIX}"
    return real.parent / name


def _holder(fd: int) -> tuple[int | None, str]:
    """(pid, command) written in a lock file; the writer may not have written yet."""
    for _ in range(20):
        text = os.pread(fd, 256, 0).decode(errors="replace").split()
        if text:
            try:
                return int(text[0]), " ".join(text[1:])
            except ValueError:
                return None, ""
        time.sleep(0.01)
    return None, ""


def _reason(exc: OSError) -> str:
    return exc.strerror or os.strerror(exc.errno or 0)


def file_in_the_way(folder: Path) -> str | None:
    """The message for an output ``folder`` that is a file or lies under one (it could never
    be made), else None."""
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    if existing.is_dir():
        return None
    where = "is" if existing == folder else f"lies under {existing}, which is"
    return f"{folder}: {where} a file, not a folder: choose another folder"


def _check_path(folder: Path, parent: Path) -> None:
    """OutputPathError naming ``folder`` when it cannot be written at all."""
    try:
        limit = os.pathconf(parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    if len(folder.name.encode()) > limit:
        raise OutputPathError(f"{folder}: the name is too long ({len(folder.name.encode())} "
                              f"bytes; this file system allows {limit})")
    if (blocked := file_in_the_way(folder)) is not None:
        raise OutputPathError(blocked)
    target = folder if folder.is_dir() else parent
    if not os.access(target, os.W_OK | os.X_OK):
        read_only = bool(os.statvfs(target).f_flag & os.ST_RDONLY)
        why = "a read-only file system" if read_only else "no permission to write there"
        raise OutputPathError(f"{folder}: cannot be written ({why})")
    free = shutil.disk_usage(target).free
    if free < MIN_FREE_BYTES:
        raise OutputPathError(f"{folder}: only {free / 2**20:.0f} MiB free on its file system; "
                              f"at least {MIN_FREE_BYTES // 2**20} MiB are needed to start")


def _make_parents(parent: Path) -> list[Path]:
    """Create ``parent`` and its missing ancestors; returns those it made, deepest first."""
    made = []
    p = parent
    while not p.exists():
        made.append(p)
        p = p.parent
    for d in reversed(made):
        d.mkdir()
    return made


def _acquire(lock: Path, folder: Path, command: str) -> tuple[int, int | None]:
    """(fd of the held lock, pid of a dead holder whose lock was taken over, or None)."""
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid, other = _holder(fd)
            os.close(fd)
            who = f"process {pid}" if pid is not None else "another process"
            what = f" (mi-shadowgs {other})" if other else ""
            raise FolderBusyError(
                f"{folder}: {who}{what} is writing there now (lock {lock}); wait for it to "
                "end or choose another --out") from None
        # The last holder removes the file as it lets go: a lock on a file that is no
        # longer (or no longer this one) at the path guards nothing, so try again.
        try:
            st = os.stat(lock)
            same = (st.st_ino, st.st_dev) == (os.fstat(fd).st_ino, os.fstat(fd).st_dev)
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        previous, _ = _holder(fd) if os.fstat(fd).st_size else (None, "")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {command}\n".encode(), 0)
        return fd, previous


@contextlib.contextmanager
def output_lock(folder: str | os.PathLike, command: str,
                note=None) -> Iterator[Path]:
    """Hold the lock of output ``folder`` for ``command`` during the block, after checking
    that the folder can be written. ``note(line)`` is told when a killed command's lock is
    taken over. Raises FolderBusyError (naming the holder's PID) or OutputPathError."""
    folder = Path(folder)
    real = Path(os.path.realpath(folder))
    lock = lock_file(folder)
    try:
        made = _make_parents(lock.parent)
    except OSError as exc:
        raise OutputPathError(f"{folder}: cannot be made ({_reason(exc)})") from None
    try:
        _check_path(real, lock.parent)
        try:
            fd, stale = _acquire(lock, folder, command)
        except OSError as exc:
            raise OutputPathError(f"{folder}: cannot be written ({_reason(exc)})") from None
    except BaseException:
        _remove_empty(made)
        raise
    if stale is not None and stale != os.getpid() and note is not None:
        note(f"{folder}: took over the lock of process {stale}, which ended without "
             "letting it go (killed?)")
    try:
        yield lock
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)
        _remove_empty(made)


def _remove_empty(made: list[Path]) -> None:
    for d in made:
        with contextlib.suppress(OSError):
            d.rmdir()


def describe_os_error(exc: OSError, folder: str | os.PathLike | None,
                      resume_hint: str) -> str | None:
    """One line for an OSError that the output path caused (read-only, full, a name too
    long, ...), naming the file (or the output folder when the OS named none) and the
    reason; None for any other OSError."""
    if exc.errno not in SYSTEM_ERRNOS:
        return None
    where = exc.filename if exc.filename is not None else folder
    if where is None:
        return None
    line = f"{where}: {_reason(exc)}"
    if exc.errno in SPACE_ERRNOS:
        line += f"; the work so far is kept: free some space and {resume_hint}"
    return line
