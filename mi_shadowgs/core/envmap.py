"""Mitsuba's ``envmap`` emitter, built so that it also loads on a one-thread Dr.Jit.

Measured (mitsuba 3.9, drjit 1.5): with ``dr.set_thread_count(1)`` (what the byte-compare
tests use, and what ``DRJIT_NUM_THREADS=1`` gives a user) the envmap constructor never
returns: it waits on work for a pool with no free thread. It is therefore built on two
threads, and the count put back; rendering afterwards is unaffected.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def load_envmap(filename: str, scale: float = 1.0):
    """The ``envmap`` emitter of a lat-long image (Y-up, identity to_world)."""
    desc = {"type": "envmap", "filename": str(filename), "scale": float(scale)}
    threads = dr.thread_count()
    if threads >= 2:
        return mi.load_dict(desc)
    dr.set_thread_count(2)
    try:
        return mi.load_dict(desc)
    finally:
        dr.set_thread_count(threads)
