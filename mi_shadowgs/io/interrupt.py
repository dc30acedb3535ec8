"""Stop cleanly at SIGINT/SIGTERM, and decide when a training loop writes its checkpoint.

``handle_signals()`` (the CLI wraps every command in it) turns SIGINT and SIGTERM into an
``Interrupted`` exception, which the CLI reports in one line with exit status 130 / 143.
Inside ``CheckpointClock.running()`` a signal is deferred instead: the loop finishes its
step, writes a checkpoint (``due`` says so) and only then raises ``Interrupted``
(``raise_pending``), so the state it saves is that of a whole step. A second signal stops
at once. Outside the CLI (library use, tests) nothing is installed and signals keep their
default action.

``CheckpointClock`` also times the regular checkpoints: every ``every`` steps, and by wall
time so that no more than ``seconds`` pass between two checkpoints: a ``kill -9`` loses at
most that much work. A loop can only checkpoint between its steps (or the units of a long
step), so the clock checkpoints early when the next step, taken to last as long as the
longest stretch between two of its calls so far, would end past ``seconds``.
"""

from __future__ import annotations

import contextlib
import signal
import time
from collections.abc import Iterator

SIGNALS = (signal.SIGINT, signal.SIGTERM)

_deferring = 0  # nesting depth of CheckpointClock.running()
_pending: int | None = None  # a deferred signal


class Interrupted(KeyboardInterrupt):
    """A SIGINT/SIGTERM stopped the command; a BaseException, so that no ``except
    Exception`` on the way up swallows it."""

    def __init__(self, signum: int, detail: str = ""):
        self.signum = signum
        self.detail = detail
        super().__init__(signal.Signals(signum).name + (f" ({detail})" if detail else ""))

    @property
    def exit_code(self) -> int:
        return 128 + self.signum  # what a shell reports for a process the signal killed


def _handler(signum, frame) -> None:
    global _pending
    if _deferring and _pending is None:
        _pending = signum
        return
    _pending = None  # this one stops the command
    raise Interrupted(signum)


@contextlib.contextmanager
def handle_signals() -> Iterator[None]:
    """SIGINT/SIGTERM raise ``Interrupted`` (deferred inside a running CheckpointClock)."""
    global _pending
    previous = {s: signal.signal(s, _handler) for s in SIGNALS}
    _pending = None
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _pending = None


def raise_pending(detail: str) -> None:
    """Raise ``Interrupted`` for a deferred signal (after the caller saved its state)."""
    global _pending
    if _pending is not None:
        signum, _pending = _pending, None
        raise Interrupted(signum, detail)


class CheckpointClock:
    """When a loop writes a checkpoint: every ``every`` steps (0: never by count), within
    ``seconds`` of wall time of the last one (see the module doc), and when a signal is
    pending. Created when the work starts: initialisation counts as work a kill loses."""

    def __init__(self, every: int, seconds: float):
        if every < 0 or not seconds > 0:
            raise ValueError(f"checkpoint intervals must be every >= 0 steps and seconds > 0, "
                             f"got {every} and {seconds}")
        self.every = every
        self.seconds = seconds
        self.last = self.previous = time.monotonic()  # last checkpoint, last call
        self.longest = 0.0  # the longest stretch between two calls

    def due(self, step: int | None = None) -> bool:
        """Whether to checkpoint after ``step`` finished steps (None: inside a step, where
        only the wall time and a signal count). Call it at every point where the loop could
        checkpoint."""
        now = time.monotonic()
        self.longest = max(self.longest, now - self.previous)
        self.previous = now
        return ((step is not None and self.every > 0 and step % self.every == 0)
                or _pending is not None or now - self.last + self.longest >= self.seconds)

    def saved(self) -> None:
        self.last = time.monotonic()

    @contextlib.contextmanager
    def running(self) -> Iterator[CheckpointClock]:
        """Defer signals while the loop runs (see the module doc). The clock keeps counting
        from its creation: work before the loop (initialisation) is work a kill loses too."""
        global _deferring
        _deferring += 1
        try:
            yield self
        finally:
            _deferring -= 1
