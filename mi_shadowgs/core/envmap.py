"""Mitsuba's ``envmap`` emitter, built so that it also loads on a one-thread Dr.Jit.

Measured (mitsuba 3.9, drjit 1.5): with ``dr.set_thread_count(1)`` (``--threads 1``, what
the byte-compare tests use) Mitsuba's EXR reads and writes, and so the envmap constructor
and a scene file naming an EXR, never return: they wait on work for a pool with no free
thread. They therefore run on two threads (``two_threads``), and the count is put back;
rendering afterwards is unaffected.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np


class EnvmapError(ValueError):
    """An env map whose texels are no radiance (NaN, Inf, negative); the line names the file,
    the count and the first texel of each kind."""


@contextlib.contextmanager
def two_threads():
    """Dr.Jit on two threads at least inside (for Mitsuba's EXR reads and writes, which never
    return on one), its count put back after."""
    threads = dr.thread_count()
    if threads < 2:
        dr.set_thread_count(2)
    try:
        yield
    finally:
        if threads < 2:
            dr.set_thread_count(threads)


def _bitmap(filename):
    """The file as a Mitsuba Bitmap, read on two threads at least."""
    try:
        with two_threads():
            return mi.Bitmap(str(filename))
    except RuntimeError as exc:  # Mitsuba's message names the file; keep its first line
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise EnvmapError(f"{filename}: not a readable env map: {first}") from None


# HDR encoders leave texels a little below 0 around bright sources (the shipped city, forest
# and night maps: down to -0.2% to -2.5% of their mean radiance). Such ringing leaves the
# relighting as it is (128 of 128 directions, 2e-5 change against the map clamped at 0); a
# texel further below 0 than this share of the mean is no radiance.
NEGATIVE_TOLERANCE = 0.05


def check_envmap(filename: str | Path) -> None:
    """EnvmapError unless every texel of ``filename`` is finite and not below 0 by more than
    ``NEGATIVE_TOLERANCE`` of the mean (its colour channels; alpha is not light). Mitsuba
    loads such maps without a word, and its sampling then drops or darkens directions (one
    NaN texel: 121 of 128 directions, 10% darker)."""
    bitmap = _bitmap(filename)
    if bitmap.component_format() not in (mi.Struct.Type.Float16, mi.Struct.Type.Float32,
                                         mi.Struct.Type.Float64):
        return  # integers are always finite and >= 0
    texels = np.asarray(bitmap, dtype=np.float64)
    if texels.ndim == 2:
        texels = texels[..., None]
    if bitmap.has_alpha():
        texels = texels[..., :-1]
    problems = []
    finite = texels[np.isfinite(texels)]
    floor = -NEGATIVE_TOLERANCE * (float(finite.mean()) if finite.size else 0.0)
    for what, bad in (("NaN", np.isnan(texels)), ("Inf", np.isinf(texels)),
                      ("a negative value", texels < min(floor, 0.0))):
        where = np.argwhere(bad.any(axis=-1))
        if len(where):
            row, col = (int(v) for v in where[0])
            problems.append(f"{len(where)} hold {what} (the first at row {row}, column {col})")
    if problems:
        h, w = texels.shape[:2]
        raise EnvmapError(f"{filename}: env map texels that are no radiance, of its {w}x{h}: "
                          f"{'; '.join(problems)}; every texel must be finite and >= 0 "
                          f"(HDR ringing down to {NEGATIVE_TOLERANCE:.0%} of the mean below 0 "
                          "is kept)")


def load_envmap(filename: str, scale: float = 1.0):
    """The ``envmap`` emitter of a lat-long image (Y-up, identity to_world), after
    ``check_envmap``."""
    check_envmap(filename)
    with two_threads():
        return mi.load_dict({"type": "envmap", "filename": str(filename),
                             "scale": float(scale)})


def low_dynamic_range(filename: str) -> bool:
    """Whether the image stores integers (an 8- or 16-bit PNG, JPEG, ...): Mitsuba takes its
    sRGB values to linear radiance, but whatever was brighter than white when it was saved
    (the sun, lamps) is clipped, so the light it casts is too weak and its shadows too soft."""
    # Read by content, whatever the name: a PNG named .exr is still 8-bit.
    fmt = _bitmap(filename).component_format()
    return fmt in (mi.Struct.Type.UInt8, mi.Struct.Type.UInt16, mi.Struct.Type.UInt32)


def low_dynamic_range_warning(filename, given_as: str) -> str | None:
    """The warning for an env map ``filename`` given as ``given_as`` (an option) that stores
    integers (``low_dynamic_range``), else None; the caller prints it. Checks the file first
    (``check_envmap``): where a map is given is where it is refused, before any work."""
    check_envmap(filename)
    if not low_dynamic_range(filename):
        return None
    return (f"{given_as} {filename} stores integers (low dynamic range): its brightest parts "
            "(the sun, lamps) are clipped at white, so it lights the scene too weakly and "
            "casts soft shadows; an EXR or HDR map keeps them")
