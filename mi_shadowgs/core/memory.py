"""Host memory figures for the render memory guard (Linux /proc; None where unreadable)."""

from __future__ import annotations

import os


def available_bytes() -> int | None:
    """MemAvailable of /proc/meminfo: what can be allocated without swapping."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # kB
    except OSError:
        pass
    return None


def resident_bytes() -> int | None:
    """This process's resident set size now."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def peak_resident_bytes() -> int | None:
    """This process's peak resident set size (``VmHWM``). Not ``ru_maxrss``: Linux carries
    that over from the parent through fork and exec, so a benchmark process started by a
    large parent reported the parent's size (496 MB for every case of a ``make bench``
    whose parent had loaded a dataset)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def parse_bytes(text: str, what: str) -> int:
    """'2G', '512M', '64k' or a plain number of bytes (binary units) -> bytes > 0."""
    units = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
    s = str(text).strip().upper().removesuffix("B").removesuffix("I")
    unit = s[-1:] if s[-1:] in units else ""
    try:
        value = float(s[: len(s) - len(unit)]) * units[unit]
    except ValueError:
        raise ValueError(f"{what} must be a size such as 2G, 512M or 1000000, got "
                         f"{text!r}") from None
    if not 1 <= value < float("inf"):
        raise ValueError(f"{what} must be at least one byte, got {text!r}")
    return int(value)
