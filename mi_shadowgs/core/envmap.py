"""Mitsuba's ``envmap`` emitter, built so that it also loads on a one-thread Dr.Jit.

Measured (mitsuba 3.9, drjit 1.5): with ``dr.set_thread_count(1)`` (what the byte-compare
tests use, and what ``DRJIT_NUM_THREADS=1`` gives a user) the envmap constructor never
returns: it waits on work for a pool with no free thread. It is therefore built on two
threads, and the count put back; rendering afterwards is unaffected.
"""

from __future__ import annotations

from pathlib import Path

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


def low_dynamic_range(filename: str) -> bool:
    """Whether the image stores integers (an 8- or 16-bit PNG, JPEG, ...): Mitsuba takes its
    sRGB values to linear radiance, but whatever was brighter than white when it was saved
    (the sun, lamps) is clipped, so the light it casts is too weak and its shadows too soft."""
    if Path(filename).suffix.lower() in (".exr", ".hdr"):  # floats: not read to find out
        return False
    fmt = mi.Bitmap(str(filename)).component_format()
    return fmt in (mi.Struct.Type.UInt8, mi.Struct.Type.UInt16, mi.Struct.Type.UInt32)


def low_dynamic_range_warning(filename, given_as: str) -> str | None:
    """The warning for an env map ``filename`` given as ``given_as`` (an option) that stores
    integers (``low_dynamic_range``), else None; the caller prints it."""
    if not low_dynamic_range(filename):
        return None
    return (f"{given_as} {filename} stores integers (low dynamic range): its brightest parts "
            "(the sun, lamps) are clipped at white, so it lights the scene too weakly and "
            "casts soft shadows; an EXR or HDR map keeps them")
