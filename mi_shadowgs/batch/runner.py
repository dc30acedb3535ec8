"""A batch's items as Ray tasks: on a local Ray runtime, or on a cluster (``address``).

Each item is one Ray task with its resources (``Item.cpus``, ``Item.gpus``). The task runs
the item's steps as child processes of its worker (``python -m MODULE ...``): every command
starts with fresh Dr.Jit state, prints into the item's ``batch.log``, and leaves its
ordinary output folder with its manifest. That folder is what makes a batch safe to run
again: a finished run is reused (its stages' provenance matches) and an interrupted one
continues from its checkpoints; a step that made a folder (``Step.creates``: an import's
dataset) is skipped when its inputs are the same, and refused when they are not.

- A step that exits with an error fails its item, with the error's line in ``batch.csv``;
  the other items go on.
- A task whose worker dies (a node lost, the OOM killer, ``kill -9``) is tried again by Ray
  (``retries``), and its run continues from its checkpoint. The child processes die with
  their worker (``PR_SET_PDEATHSIG``), so that no orphan keeps writing into the run.
- A step killed by a signal (while its worker lives) counts as lost too: its task is tried
  again rather than failed.
- An item that asks for more than any node of the cluster has (a GPU where there is none)
  fails at once with a message saying so, instead of waiting for ever.

The driver (this process) holds the batch folder's lock (``mi_shadowgs.io.outlock``) so
that two batches into one folder refuse each other, and rewrites ``batch.csv`` and
``batch.html`` (``mi_shadowgs.batch.report``) as each item ends.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

from mi_shadowgs.batch.spec import Item, Step
from mi_shadowgs.io.interrupt import Interrupted

RAY_HINT = "pip install 'mi_shadowgs[cluster]' (in a checkout: pip install -e '.[cluster]')"
OK = ("finished", "reused")
LOG = "batch.log"
STEP_KEYS = "batch-steps.json"  # in an item's folder: what each created folder was made from
MARK = "batch.json"  # the batch folder's record of its items (and the sign that it is ours)
# A local runtime passes only small results through Ray's object store.
LOCAL_OBJECT_STORE_BYTES = 200 * 2**20
# CLI exit statuses of a command stopped by SIGINT / SIGTERM (mi_shadowgs.io.interrupt).
INTERRUPTED_STATUSES = (130, 143)
# Arguments that say how a step runs, not what it makes (left out of a step's key).
HOW_ARGS = ("--threads", "--variant")
# Run as ``python -c SHIM PARENT_PID ARGV...``: the command dies with the worker that started
# it (Linux; elsewhere a no-op), or not at all when that worker is already gone.
_SHIM = ("import ctypes, os, signal, sys\n"
         "try:\n"
         "    ctypes.CDLL(None).prctl(1, signal.SIGKILL)\n"  # PR_SET_PDEATHSIG
         "except (OSError, AttributeError):\n"
         "    pass\n"
         "if os.getppid() != int(sys.argv[1]):\n"
         "    sys.exit(137)\n"
         "os.execvp(sys.argv[2], sys.argv[2:])\n")


class RayMissing(RuntimeError):
    """Ray is not installed: the message says what to install."""


class BatchError(ValueError):
    """A batch that cannot start (its folder, its cluster); the message says why."""


class ItemLost(RuntimeError):
    """An item's command was killed by a signal: Ray tries its task again."""


def import_ray():
    """The ``ray`` module, or RayMissing naming the extra to install."""
    try:
        import ray
    except ImportError as exc:
        raise RayMissing(f"batches run on Ray, which is not installed here ({exc}); "
                         f"install it: {RAY_HINT}") from None
    return ray


@dataclasses.dataclass(frozen=True)
class Launcher:
    """How an item's worker starts a step's module."""

    prefix: tuple[str, ...] = ()
    """The command before the module's name (empty: the worker's Python with ``-m``)."""
    env: tuple[tuple[str, str], ...] = ()
    """Environment variables added for every step."""
    cwd: str | None = None
    """The steps' working folder (None: the worker's)."""

    def argv(self, step: Step) -> list[str]:
        return [*(self.prefix or (sys.executable, "-m")), step.module, *step.args]


# How a batch's workers start their steps unless the caller says otherwise.
DEFAULT_LAUNCHER = Launcher()


# -- the task: one item on a worker -----------------------------------------------------------
def _tree_digest(paths: tuple[str, ...]) -> str:
    """The content of files and folders ``paths`` (names and bytes), as one digest."""
    from mi_shadowgs.io.provenance import file_digest

    h = hashlib.blake2b(digest_size=16)
    for p in map(Path, paths):
        files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
        for f in files:
            h.update(f"{f.relative_to(p) if p.is_dir() else f.name}\0"
                     f"{file_digest(f)}\0".encode())
    return h.hexdigest()


def _step_key(step: Step) -> dict:
    args, skip = [], False
    for a in step.args:
        if skip or a in HOW_ARGS:
            skip = not skip
            continue
        args.append(a)
    return {"module": step.module, "args": args, "inputs": _tree_digest(step.inputs)}


def _made_before(step: Step, folder: Path) -> bool:
    """Whether ``step.creates`` is there, made from the same inputs with the same command
    (then the step is skipped); ValueError when it was made from others. Records this
    step's key before the step runs, so that a folder it makes always has one."""
    keys_path = folder / STEP_KEYS
    keys = json.loads(keys_path.read_text()) if keys_path.is_file() else {}
    key = _step_key(step)
    target = folder / step.creates
    if target.exists():
        if keys.get(step.name) == key:
            return True
        why = ("other inputs or arguments" if step.name in keys else
               "something this batch did not record")
        raise ValueError(f"{target}: made from {why} than this item's {step.name} "
                         f"({', '.join(step.inputs)}); remove it to {step.name} again")
    from mi_shadowgs.io.atomic import write_json

    write_json(keys_path, {**keys, step.name: key})
    return False


_ERROR_LINE = re.compile(r"(^|: )error: ")


def error_line(text: str, step: str, status: int) -> str:
    """The line of a failed command's output that says why (its ``error:`` line, else its
    last line), prefixed with the step's name."""
    lines = [ln.strip() for ln in text.replace("\r", "\n").splitlines() if ln.strip()]
    found = next((ln for ln in reversed(lines) if _ERROR_LINE.search(ln)), None)
    line = found or (lines[-1] if lines else f"exit status {status}, no message")
    return f"{step}: {line}"[:500]


def _peak_bytes(pid: int) -> int:
    """The peak resident memory of process ``pid`` so far (``VmHWM``; 0 where unknown).
    Not ``ru_maxrss``: Linux carries the parent's (here a Ray worker's) through fork."""
    try:
        with open(f"/proc/{pid}/status") as f:
            line = next((ln for ln in f if ln.startswith("VmHWM:")), "")
    except OSError:
        return 0
    return int(line.split()[1]) * 1024 if line else 0


def _call(launcher: Launcher, step: Step, env: dict, log: Path) -> tuple[int, str, int]:
    """Run ``step`` with its output appended to ``log``; (exit status, that output, its
    peak resident bytes, read every half second)."""
    argv = launcher.argv(step)
    peak, t0 = 0, time.perf_counter()
    with open(log, "a") as fh:
        fh.write(f"$ {shlex.join(argv)}\n")
        fh.flush()
        start = fh.tell()
        proc = subprocess.Popen([sys.executable, "-c", _SHIM, str(os.getpid()), *argv],
                                stdout=fh, stderr=subprocess.STDOUT, env=env,
                                cwd=launcher.cwd, stdin=subprocess.DEVNULL)
        while True:
            peak = max(peak, _peak_bytes(proc.pid))
            try:
                proc.wait(timeout=0.5)
                break
            except subprocess.TimeoutExpired:
                continue
        end = fh.tell()
        fh.write(f"== {step.name}: exit status {proc.returncode} after "
                 f"{time.perf_counter() - t0:.1f} s, peak memory {peak / 2**20:.0f} MiB\n")
    with open(log, "rb") as fh:
        fh.seek(max(start, end - 65536))
        return proc.returncode, fh.read(end - fh.tell()).decode(errors="replace"), peak


def _attempt(folder: Path, call: str) -> int:
    """Log this attempt of the item in its ``batch.log``; returns its number in this call."""
    log = folder / LOG
    mark = f"== batch {call} attempt"
    before = log.read_text(errors="replace").count(mark) if log.is_file() else 0
    with open(log, "a") as fh:
        fh.write(f"{mark} {before + 1} on {socket.gethostname()} (pid {os.getpid()}) at "
                 f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n")
    return before + 1


def result(item: Item, status: str, seconds: float = 0.0, attempts: int = 0,
           error: str = "", figures: dict | None = None, peak: int = 0) -> dict:
    """An item's row of the tables (``peak``: the most resident bytes one of its commands
    held in this call)."""
    return {"name": item.name, "status": status, "seconds": seconds, "attempts": attempts,
            "error": error, "figures": figures or {}, "source": item.source,
            "preset": item.preset, "run": item.run, "peak_mib": peak / 2**20 or None}


def run_item(item: Item, out: str, launcher: Launcher, call: str, *needed: dict) -> dict:
    """One item's steps, in order (the Ray task; ``needed``: the results of the items it
    waits for). Returns its row; raises ItemLost when a step was killed by a signal."""
    from mi_shadowgs.batch.report import run_figures

    t0 = time.perf_counter()
    folder = Path(out) / item.folder
    folder.mkdir(parents=True, exist_ok=True)
    attempts = _attempt(folder, call)
    for r in needed:
        if r["status"] not in OK:
            return result(item, "failed", 0.0, attempts,
                          f"needs item {r['name']}, which {r['status']}")
    env = {**os.environ, **dict(launcher.env), **dict(item.env)}
    ran, peak = False, 0
    for step in item.steps:
        try:
            if step.creates and _made_before(step, folder):
                continue
        except ValueError as exc:
            return result(item, "failed", time.perf_counter() - t0, attempts,
                          f"{step.name}: {exc}", peak=peak)
        status, text, used = _call(launcher, step, env, folder / LOG)
        peak = max(peak, used)
        if status < 0 or status in INTERRUPTED_STATUSES:
            raise ItemLost(f"{item.name}: {step.name} was stopped by a signal (exit status "
                           f"{status})")
        if status != 0:
            return result(item, "failed", time.perf_counter() - t0, attempts,
                          error_line(text, step.name, status), peak=peak)
        ran = ran or step.creates is not None
    figures, reused = run_figures(Path(out) / item.run)
    return result(item, "reused" if reused and not ran else "finished",
                  time.perf_counter() - t0, attempts, figures=figures, peak=peak)


# -- the driver ------------------------------------------------------------------------------
@contextlib.contextmanager
def ray_runtime(address: str | None = None, num_cpus: int | None = None):
    """Ray for the block: the caller's when it already called ``ray.init`` (used as it is),
    else a local runtime of ``num_cpus`` CPUs (default: this machine's cores) when
    ``address`` is None or ``local``, else the cluster at ``address`` (``auto``, HOST:PORT
    or ``ray://HOST:10001``). Yields a phrase naming where the items run."""
    import logging

    ray = import_ray()
    if address not in (None, "local"):
        _check_reachable(address)
    if ray.is_initialized():
        yield "the Ray runtime of this process"
        return
    quiet = {"logging_level": logging.ERROR, "log_to_driver": False}
    if address in (None, "local"):
        cpus = num_cpus or os.cpu_count() or 1
        ray.init(address="local", num_cpus=cpus, include_dashboard=False,
                 object_store_memory=LOCAL_OBJECT_STORE_BYTES, **quiet)
        where = f"a local Ray runtime of {cpus} CPUs"
    else:
        if num_cpus is not None:
            raise BatchError("--workers sizes a local Ray runtime; a cluster (--address) "
                             "has the CPUs it has")
        try:
            ray.init(address=address, **quiet)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise BatchError(f"--address {address}: no Ray cluster could be reached there "
                             f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
                             ) from None
        where = f"the Ray cluster at {address}"
    try:
        yield where
    finally:
        ray.shutdown()


def _check_reachable(address: str) -> None:
    """BatchError at once when nothing answers at ``address`` (HOST:PORT or
    ray://HOST:PORT): Ray itself would try for minutes. ``auto`` is Ray's to find."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if address == "auto" or not sep or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=10).close()
    except OSError as exc:
        raise BatchError(f"--address {address}: nothing answers there "
                         f"({exc.strerror or exc}); is the Ray head running (ray start "
                         "--head), and is this its address?") from None


def _largest_node() -> dict[str, float]:
    """The most CPUs and GPUs that one live node of the cluster has."""
    ray = import_ray()
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    return {k: max((n.get(k, 0.0) for n in nodes), default=0.0) for k in ("CPU", "GPU")}


def unschedulable(item: Item, largest: dict[str, float], where: str) -> str | None:
    """Why no node of the cluster can run ``item`` (None when one can)."""
    if item.gpus > largest["GPU"]:
        return (f"asks for a GPU (variant cuda_ad_rgb), but {where} has none; run the batch "
                "on a Ray cluster with GPU nodes, or with the llvm_ad_rgb variant")
    if item.cpus > largest["CPU"]:
        return (f"asks for {item.cpus} CPUs, but the largest node of {where} has "
                f"{largest['CPU']:g}; lower its cpus (--cpus-per-item)")
    return None


def _lost_line(exc: BaseException, retries: int) -> str:
    """One line for a task Ray gave up on: lost every time it was tried, or failed."""
    cause = getattr(exc, "cause", None)  # the task's own exception, under Ray's
    text = next((ln.strip() for ln in str(cause or exc).splitlines() if ln.strip()),
                type(cause or exc).__name__)
    if cause is not None and not isinstance(cause, ItemLost):
        return f"its task failed: {type(cause).__name__}: {text}"
    return f"lost {retries + 1} times (tried again {retries}); the last time: {text}"


def run_batch(items: list[Item], out: str | os.PathLike, *, address: str | None = None,
              num_cpus: int | None = None, retries: int = 3, launcher: Launcher | None = None,
              progress: bool = True, lock: bool = True) -> list[dict]:
    """Run ``items`` into the batch folder ``out`` on Ray (``ray_runtime``: the caller's,
    a local runtime of ``num_cpus`` CPUs, or the cluster at ``address``); a task whose
    worker is lost is tried again ``retries`` times; ``launcher``: how a worker starts a
    step (default ``DEFAULT_LAUNCHER``: its own Python). With ``lock``, holds ``out``'s lock
    (``output_lock``) meanwhile. Writes ``out/batch.csv`` and ``out/batch.html`` as items
    end; returns the rows, in the items' order."""
    from mi_shadowgs.io.outlock import output_lock

    import_ray()
    out = Path(out).resolve()
    names = [i.name for i in items]
    for i, item in enumerate(items):
        unknown = [a for a in item.after if a not in names[:i]]
        if unknown:
            raise BatchError(f"item {item.name} waits for {unknown}, which are not earlier "
                             "items of this batch")
    with contextlib.ExitStack() as stack:
        if lock:
            stack.enter_context(output_lock(out, "batch"))
        out.mkdir(parents=True, exist_ok=True)
        where = stack.enter_context(ray_runtime(address, num_cpus))
        return _drive(items, out, retries, launcher or DEFAULT_LAUNCHER, progress, where)


def _drive(items: list[Item], out: Path, retries: int, launcher: Launcher, progress: bool,
           where: str) -> list[dict]:
    """Submit every item (those marked done, unschedulable or waiting for a failed item
    get their row at once), then gather the rows as tasks end."""
    from tqdm import tqdm

    from mi_shadowgs.batch.report import run_figures, write_tables

    ray = import_ray()
    task = ray.remote(run_item)
    largest, call = _largest_node(), uuid.uuid4().hex[:12]
    rows: dict[str, dict] = {}
    refs: dict = {}  # ObjectRef -> item name
    by_name: dict = {}  # item name -> ObjectRef
    for item in items:
        if item.done and (out / item.done).is_file():
            rows[item.name] = result(item, "reused", figures=run_figures(out / item.run)[0])
            continue
        why = unschedulable(item, largest, where)
        failed = [a for a in item.after if a in rows and rows[a]["status"] not in OK]
        if failed:
            why = f"needs item {failed[0]}, which {rows[failed[0]]['status']}"
        if why is not None:
            rows[item.name] = result(item, "failed", error=why)
            continue
        ref = task.options(
            num_cpus=item.cpus, num_gpus=item.gpus, max_retries=retries,
            retry_exceptions=[ItemLost], name=f"mi-shadowgs batch {item.name}",
        ).remote(item, str(out), launcher, call, *(by_name[a] for a in item.after
                                                   if a in by_name))
        refs[ref], by_name[item.name] = item.name, ref
    write_tables(out, items, rows)
    bar = tqdm(total=len(items), initial=len(rows), desc="batch", unit="item",
               disable=not progress)
    pending = list(refs)
    try:
        while pending:
            # with a timeout: a wait without one does not return to Python for Ctrl-C
            ready, pending = ray.wait(pending, num_returns=1, timeout=1.0)
            for ref in ready:
                name = refs[ref]
                try:
                    rows[name] = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    item = next(i for i in items if i.name == name)
                    failed = [a for a in item.after if rows.get(a, {}).get("status") == "failed"]
                    why = (f"needs item {failed[0]}, which failed" if failed
                           else _lost_line(exc, retries))
                    rows[name] = result(item, "failed", error=why)
                write_tables(out, items, rows)
                row = rows[name]
                bar.write(f"{name}: {row['status']} ({row['seconds']:.0f} s)"
                          + (f": {row['error']}" if row["error"] else ""))
                bar.update(1)
                bar.set_postfix(failed=sum(r["status"] not in OK for r in rows.values()))
    except BaseException as exc:
        for ref in pending:  # stopped (Ctrl-C): no task left running for nobody
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
        if isinstance(exc, KeyboardInterrupt) and not isinstance(exc, Interrupted):
            # Ray's wait turns a signal into a plain KeyboardInterrupt: the CLI's own kind
            # says "interrupted; run it again to continue", not a traceback
            raise Interrupted(signal.SIGINT) from None
        raise
    finally:
        bar.close()
    return [rows[i.name] for i in items]


def claim_batch_folder(out: str | os.PathLike, spec: str, items: list[Item]) -> Path:
    """``out`` as a batch folder: new, empty, or one a batch wrote (its ``batch.json``);
    BatchError when it holds other files. Records the batch's spec and items there."""
    from mi_shadowgs.io.atomic import write_json

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise BatchError(f"--out {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / MARK).is_file():
        raise BatchError(f"--out {out}: holds files that no batch wrote (no {MARK}); name a "
                         "new or empty folder, or the folder of an earlier batch")
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / MARK, {"spec": str(spec), "items": [dataclasses.asdict(i)
                                                          for i in items]})
    return out
