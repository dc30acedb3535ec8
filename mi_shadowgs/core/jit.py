"""Host values into Dr.Jit kernels without a new kernel for every value.

Dr.Jit reuses a compiled kernel only when its source text is the same. Two kinds of host
data change that text without changing what the kernel computes:

- **Python scalars** become literals. A camera's matrix, a light's direction or a scale
  factor then compiles one kernel per camera, light or factor. ``opaque`` makes each a
  kernel parameter instead.
- **Arrays made from NumPy** keep NumPy's memory, and a kernel that loads them directly
  carries that memory's alignment in its source (``align 1`` or ``align 64``, wherever
  NumPy put it); a size-1 array is read as a broadcast scalar with the same property. Two
  calls with the same code then differ in their source. ``array`` (size 1), ``host`` (flat,
  any size) and ``tensor`` (any shape: images, models read from files, parameters) copy
  host values into memory Dr.Jit allocated, whose alignment does not vary. Gathers do not
  carry it, so ``array`` leaves larger arrays (read by gathers: lights, camera rows) as
  they are.

Without them every test view of a one-light relighting compiled a new ~1,300-operation
shading kernel (~100 ms each).
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
    """A flat host array [K] as a Dr.Jit array; size 1 in memory Dr.Jit allocated (see the
    module docstring); ``cls`` defaults to ``mi.Float``."""
    cls = cls or mi.Float
    src = cls(np.ascontiguousarray(values).ravel())
    return _copy(src) if dr.width(src) == 1 else src


def host(values, cls=None):
    """A flat host array [K] of any size as a Dr.Jit array in memory Dr.Jit allocated (see
    the module docstring), for arrays that kernels load directly; ``cls`` defaults to
    ``mi.Float``."""
    cls = cls or mi.Float
    src = cls(np.ascontiguousarray(values).ravel())
    return _copy(src) if dr.width(src) else src


def tensor(values: np.ndarray) -> mi.TensorXf:
    """A host array of any shape as an ``mi.TensorXf`` in memory Dr.Jit allocated."""
    a = np.asarray(values, np.float32)
    return mi.TensorXf(host(a), a.shape)


def _copy(src):
    out = dr.empty(type(src), dr.width(src))
    dr.scatter(out, src, dr.arange(mi.UInt32, dr.width(src)))
    dr.eval(out)
    return out
