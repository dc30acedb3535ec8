"""Checks of raw surfel arrays before they become a model (PLY files, user arrays).

Numpy only. Each check raises ``ValueError`` (or the given subclass) naming where the values
came from, the field, the first offending vertex and how many vertices are bad; the CLI
turns that into one line and exit status 2. Kernels stay robust to all of these (a zero
quaternion is drawn as the identity, a zero scale is culled), but a model that holds them
is almost always a corrupt file or a diverged fit, so it is refused at the door rather than
rendered silently wrong.
"""

from __future__ import annotations

import math

import numpy as np

# Below log(FLT_MIN) exp(log-scale) is subnormal, which the JIT flushes to zero (a
# degenerate surfel). Above log(FLT_MAX) = 88.7 it overflows, but the rasterizer fails
# earlier: its float32 conic products hold (focal * scale)^2, which overflow past
# focal * scale ~ 1e19 px, and the surfel is then drawn as a dot. 1e12 scene units (far
# beyond any scene) keeps focal lengths up to 1e7 px exact.
LOG_SCALE_MAX = math.log(1e12)  # 27.63
LOG_SCALE_MIN = math.log(float(np.finfo(np.float32).tiny))  # -87.34
# Quaternions are normalised at use; the kernels fall back to the identity below
# |q|^2 = 1e-30. Refusing |q| < 1e-12 keeps every accepted one six orders of magnitude
# clear of that fallback, where float32 normalisation is still exact to rounding.
QUAT_NORM_MIN = 1e-12


def refuse(where: str, what: str, bad: np.ndarray, exc: type[ValueError] = ValueError) -> None:
    """Raise ``exc`` if any of ``bad`` [N] holds: the first index and the count."""
    idx = np.flatnonzero(bad)
    if idx.size:
        raise exc(f"{where}: {what} at vertex {int(idx[0])} ({idx.size} of {bad.size} "
                  f"vertices)")


def check_nonempty(where: str, count: int, exc: type[ValueError] = ValueError) -> None:
    if count == 0:
        raise exc(f"{where}: no surfels (0 vertices)")


def check_finite(where: str, field: str, values: np.ndarray,
                 exc: type[ValueError] = ValueError) -> None:
    """``values`` [N] or [N, C]: every entry finite."""
    v = np.asarray(values)
    if v.dtype.kind != "f" or v.size == 0:
        return
    v = v.reshape(v.shape[0], -1)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        kind = "NaN" if np.isnan(v[np.argmax(bad)]).any() else "Inf"
        refuse(where, f"field {field!r} holds {kind}", bad, exc)


def check_log_scale(where: str, field: str, log_scale: np.ndarray,
                    exc: type[ValueError] = ValueError) -> None:
    """``log_scale`` [N] (finite): in [LOG_SCALE_MIN, LOG_SCALE_MAX]."""
    ls = np.asarray(log_scale, dtype=np.float64)
    refuse(where, f"field {field!r} holds a log-scale above {LOG_SCALE_MAX:.2f} (a "
                   f"standard deviation over 1e12, beyond float32 rendering)",
            ls > LOG_SCALE_MAX, exc)
    refuse(where, f"field {field!r} holds a log-scale whose exp is zero in float32 "
                   f"(< {LOG_SCALE_MIN:.2f}, a degenerate surfel)", ls < LOG_SCALE_MIN, exc)


def check_quaternion(where: str, field: str, rotation: np.ndarray,
                     exc: type[ValueError] = ValueError) -> None:
    """``rotation`` [N, 4] (finite): no zero or near-zero quaternion."""
    norm = np.linalg.norm(np.asarray(rotation, dtype=np.float64), axis=1)
    refuse(where, f"fields {field} hold a zero quaternion (|q| < {QUAT_NORM_MIN:g}, no "
                   f"orientation)", norm < QUAT_NORM_MIN, exc)
