"""Host values into Dr.Jit kernels without a new kernel for every value.

Dr.Jit reuses a compiled kernel only when its source text is the same. Two kinds of host
data change that text without changing what the kernel computes:

- **Python scalars** become literals. A camera's matrix, a light's direction or a scale
  factor then compiles one kernel per camera, light or factor. ``opaque`` makes each a
  kernel parameter instead.
- **Size-1 arrays made from NumPy** are read as a broadcast scalar whose load carries the
  alignment of the memory it wraps (``align 1`` or ``align 4``, depending on where NumPy put
  it), so two calls with the same code can differ in their source. ``array`` copies host
  values into memory Dr.Jit allocated, whose alignment does not vary. Gathers from larger
  arrays are not affected.

Measured on the default scene's cpu-small evaluation (32 test views at 128^2): every test
view of a one-light relighting compiled a new ~1,300-operation shading kernel (~100 ms
each, 9 s per relighting against 1.2 s for the two-light one; BENCHMARKS.md, "Kernels
compiled once", session 9).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def opaque(value, cls=None):
    """``value`` as an opaque scalar (a kernel parameter, not a literal); ``cls`` defaults
    to ``mi.Float`` (``value`` then any real number, NumPy's included)."""
    return dr.opaque(cls, value) if cls is not None else dr.opaque(mi.Float, float(value))


def opaque_matrix(matrix: np.ndarray) -> list[list]:
    """A host matrix [R, C] as rows of opaque ``mi.Float`` scalars."""
    m = np.asarray(matrix, np.float64)
    return [[opaque(float(v)) for v in row] for row in m]


def array(values, cls=None):
    """A flat host array [K] as a Dr.Jit array in memory Dr.Jit allocated (see the module
    docstring); ``cls`` defaults to ``mi.Float``."""
    cls = cls or mi.Float
    src = cls(np.ascontiguousarray(values).ravel())
    if dr.width(src) != 1:
        return src
    out = dr.empty(cls, 1)
    dr.scatter(out, src, dr.zeros(mi.UInt32, 1))
    dr.eval(out)
    return out
