"""The 2D Gaussian surfel model: parameters, activations, tangent frames and SH colour.

Conventions (docs/conventions.md): a surfel has a centre, two tangent standard deviations
(stored as logs), a quaternion in (w, x, y, z) order (stored unnormalised, normalised at use)
and an opacity (stored as a logit). The rotation's first two columns are the tangent axes
``t_u``, ``t_v``; the third is the normal. Named per-surfel channels ride along as [N, C]
tensors ("sh", "albedo", "roughness", "metallic", "feature", "segment", ...).
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit
from mi_shadowgs.core.surfel_checks import (
    LOG_SCALE_MAX,
    LOG_SCALE_MIN,
    QUAT_NORM_MIN,
    check_finite,
    check_log_scale,
    check_nonempty,
    check_quaternion,
    refuse,
)

# Real SH basis constants of 3DGS/2DGS (degree 0..3).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
SH_MAX_DEGREE = 3

# Quaternions with |q|^2 below this are treated as the identity (no NaN from 0/0).
_QUAT_NORM2_MIN = 1e-30


def stable_sigmoid(x: mi.Float) -> mi.Float:
    """1 / (1 + exp(-x)) without inf/inf or 0*inf in value or gradient, also at x = +-inf."""
    pos = x >= 0
    # exp(-|x|) in (0, 1], finite with a finite derivative; select, not abs, whose
    # derivative vanishes at x = 0.
    e = dr.exp(dr.select(pos, -x, x))
    return dr.select(pos, 1.0 / (1.0 + e), e / (1.0 + e))


def quaternion_frame(q: mi.Vector4f) -> tuple[mi.Vector3f, mi.Vector3f, mi.Vector3f]:
    """(t_u, t_v, normal): the columns of the rotation of quaternion ``q`` [N] (w, x, y, z).

    ``q`` is normalised here; a zero (or denormal) quaternion gives the identity.
    """
    n2 = dr.squared_norm(q)
    ok = n2 > _QUAT_NORM2_MIN
    safe = dr.select(ok, q, mi.Vector4f(1.0, 0.0, 0.0, 0.0))
    safe = safe * dr.rsqrt(dr.select(ok, n2, 1.0))
    w, x, y, z = safe[0], safe[1], safe[2], safe[3]
    t_u = mi.Vector3f(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y))
    t_v = mi.Vector3f(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x))
    nrm = mi.Vector3f(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y))
    return t_u, t_v, nrm


def _tensor_nc(values, n: int, what: str) -> mi.TensorXf:
    """A [N, C] float32 TensorXf from numpy/TensorXf input, with a clear error on bad shape."""
    if isinstance(values, mi.TensorXf):
        t = values
    else:
        a = np.asarray(values, dtype=np.float32)
        if a.ndim == 1:
            a = a[:, None]
        t = jit.tensor(a)
    if len(t.shape) != 2 or t.shape[0] != n:
        raise ValueError(f"{what}: expected shape [N={n}, C], got {tuple(t.shape)}")
    return t


@dataclasses.dataclass
class Surfels:
    """A set of N 2D Gaussian surfels (raw, optimisable parameters)."""

    position: mi.Point3f  # [N] centres, world space
    log_scale: mi.Point2f  # [N] log of the two tangent standard deviations
    rotation: mi.Vector4f  # [N] quaternion (w, x, y, z), unnormalised
    opacity_logit: mi.Float  # [N] logit of opacity
    channels: dict[str, mi.TensorXf] = dataclasses.field(default_factory=dict)  # name -> [N, C]

    @property
    def count(self) -> int:
        return dr.width(self.position)

    def with_channels(self, channels: dict[str, mi.TensorXf]) -> Surfels:
        """A new set with the same geometry arrays and ``channels`` [N, C] added to (or
        replacing) this one's; this set is left as it is."""
        return dataclasses.replace(self, channels={**self.channels, **channels})

    def subset(self, keep: np.ndarray) -> Surfels:
        """A new set of the surfels where ``keep`` [N] (bool) is True, in their order."""
        keep = np.asarray(keep, bool).reshape(-1)
        if len(keep) != self.count:
            raise ValueError(f"Surfels.subset: keep has {len(keep)} entries for "
                             f"{self.count} surfels")
        rows = np.flatnonzero(keep)
        index = jit.host(rows.astype(np.uint32), mi.UInt32)
        geometry = {k: dr.gather(type(v), v, index) for k, v in self.params().items()
                    if not k.startswith("channels.")}
        channels = {k: jit.tensor(np.asarray(t)[rows]) for k, t in self.channels.items()}
        return Surfels(**geometry, channels=channels)

    # -- activations ------------------------------------------------------------------
    def scale(self) -> mi.Point2f:
        """Activated tangent standard deviations [N] (exp of log_scale)."""
        return dr.exp(self.log_scale)

    def opacity(self) -> mi.Float:
        """Activated opacity [N] in [0, 1] (sigmoid of the logit)."""
        return stable_sigmoid(self.opacity_logit)

    def tangent_frame(self) -> tuple[mi.Vector3f, mi.Vector3f, mi.Vector3f]:
        """World-space (t_u, t_v, normal) [N] from the normalised quaternion."""
        return quaternion_frame(self.rotation)

    # -- optimiser interface ----------------------------------------------------------
    def params(self) -> dict:
        """The raw parameters by name (the same objects, e.g. for ``mi.ad.Adam``)."""
        d = {"position": self.position, "log_scale": self.log_scale,
             "rotation": self.rotation, "opacity_logit": self.opacity_logit}
        for name, t in self.channels.items():
            d[f"channels.{name}"] = t
        return d

    def set_params(self, params: dict) -> None:
        """Replace parameters from a dict with the keys of :meth:`params` (any subset)."""
        n = self.count
        kinds = {"position": mi.Point3f, "log_scale": mi.Point2f, "rotation": mi.Vector4f,
                 "opacity_logit": mi.Float}
        for key, value in params.items():
            if key in kinds:
                v = kinds[key](value)
                if dr.width(v) != n:
                    raise ValueError(f"Surfels.set_params: {key!r} has {dr.width(v)} "
                                     f"entries, expected {n}")
                setattr(self, key, v)
            elif key.startswith("channels."):
                name = key[len("channels."):]
                self.channels[name] = _tensor_nc(value, n, f"Surfels.set_params {key!r}")
            else:
                raise KeyError(f"Surfels.set_params: unknown parameter {key!r}")

    def check_params(self, where: str, keys=None) -> None:
        """Refuse non-finite values in the raw parameters ``keys`` (names of :meth:`params`;
        default all), log-scales out of float32's range and zero quaternions, as a PLY's are
        refused on reading
        (``mi_shadowgs.core.surfel_checks``): a ValueError from ``where`` naming the
        parameter, the first bad row and the number of bad rows.

        For parameters set from outside (``mi.traverse`` and an optimiser step): the kernels
        draw a NaN surfel as nothing and a zero quaternion as the identity, silently. While
        all is well this costs one reduction for the geometry, one per channel and one host
        read; the values are copied to NumPy only to name a bad one. Runs with gradients
        suspended, so it adds nothing to an AD graph.
        """
        params = self.params()
        names = [k for k in params if keys is None or k in keys]
        if not names:
            return
        with dr.suspend_grad():
            # One mask over the [N] geometry arrays, so one reduction for all of them; each
            # channel ([N * C] entries) gets its own.
            row_bad, bad = mi.Bool(False), mi.Bool(False)
            for k in names:
                v = params[k]
                if isinstance(v, mi.TensorXf):
                    bad |= dr.any(~dr.isfinite(v.array), axis=None)
                else:
                    m = ~dr.isfinite(v)
                    row_bad |= dr.any(m, axis=0) if dr.depth_v(m) > 1 else m  # any component
            if "log_scale" in names:
                ls = self.log_scale
                row_bad |= dr.any((ls < LOG_SCALE_MIN) | (ls > LOG_SCALE_MAX), axis=0)
            if "rotation" in names:
                # float32 |q|^2 of |q| = 1e-12 is 1e-24, a normal number: the same test
                # as the float64 one below to rounding.
                row_bad |= dr.squared_norm(self.rotation) < QUAT_NORM_MIN ** 2
            bad |= dr.any(row_bad, axis=None)
            if not bad[0]:
                return
        # The float64 NumPy checks name the value; where they find nothing (|q| within
        # rounding of the threshold) the parameters stand.
        for k in names:
            check_finite(where, k, self._rows(params[k]))
        if "log_scale" in names:
            rows = self._rows(self.log_scale)
            for i in range(2):
                check_log_scale(where, f"log_scale[:, {i}]", rows[:, i])
        if "rotation" in names:
            check_quaternion(where, "rotation (w, x, y, z)", self._rows(self.rotation))

    def _rows(self, value) -> np.ndarray:
        """A parameter as a numpy array of one row per surfel ([N] or [N, C])."""
        a = np.asarray(value)
        if isinstance(value, mi.TensorXf) or a.ndim == 1:
            return a
        return a.reshape(a.shape[0], -1).T  # a Point3f etc. is [3, N]

    # -- numpy exchange ---------------------------------------------------------------
    @staticmethod
    def from_numpy(position, scale, rotation, opacity, channels: dict | None = None) -> Surfels:
        """Surfels from activated numpy values.

        position [N, 3]; scale [N, 2] standard deviations in [FLT_MIN, 1e12]; rotation
        [N, 4] (w, x, y, z), not zero; opacity [N] in [0, 1]; channels name -> [N, C] (or
        [N]). N >= 1 and every value finite (``mi_shadowgs.core.surfel_checks``); a ValueError
        names the field and the first bad vertex.
        """
        p = np.asarray(position, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"Surfels.from_numpy: position must be [N, 3], got {p.shape}")
        n = p.shape[0]
        s = np.asarray(scale, dtype=np.float64)
        r = np.asarray(rotation, dtype=np.float64)
        o = np.asarray(opacity, dtype=np.float64).reshape(-1)
        for name, arr, shape in (("scale", s, (n, 2)), ("rotation", r, (n, 4)),
                                 ("opacity", o, (n,))):
            if arr.shape != shape:
                raise ValueError(f"Surfels.from_numpy: {name} must be {list(shape)}, "
                                 f"got {list(arr.shape)}")
        where = "Surfels.from_numpy"
        check_nonempty(where, n)
        for name, arr in (("position", p), ("scale", s), ("rotation", r), ("opacity", o)):
            check_finite(where, name, arr)
        refuse(where, "field 'scale' must be > 0 (standard deviations)",
               (s <= 0).any(axis=1))
        refuse(where, "field 'opacity' must lie in [0, 1]", (o < 0) | (o > 1))
        log_s = np.log(s)
        for i in range(2):
            check_log_scale(where, f"scale[:, {i}] (log)", log_s[:, i])
        check_quaternion(where, "rotation", r)
        with np.errstate(divide="ignore"):
            logit = np.log(o) - np.log1p(-o)  # 1 -> +inf, 0 -> -inf (handled by the sigmoid)
        f32 = np.float32
        surf = Surfels(
            position=mi.Point3f(*(jit.host(p[:, i].astype(f32)) for i in range(3))),
            log_scale=mi.Point2f(*(jit.host(log_s[:, i].astype(f32)) for i in range(2))),
            rotation=mi.Vector4f(*(jit.host(r[:, i].astype(f32)) for i in range(4))),
            opacity_logit=jit.host(logit.astype(f32)),
        )
        for name, arr in (channels or {}).items():
            surf.channels[name] = _tensor_nc(arr, n, f"Surfels.from_numpy channel {name!r}")
            check_finite(where, f"channel {name}", np.asarray(arr))
        return surf

    def to_numpy(self) -> dict[str, np.ndarray]:
        """Activated values as float64 numpy: position, scale, rotation (normalised wxyz),
        opacity, and one entry per channel ([N, C])."""
        n = self.count
        q = self.rotation
        n2 = dr.squared_norm(q)
        qn = dr.select(n2 > _QUAT_NORM2_MIN, q * dr.rsqrt(n2), mi.Vector4f(1.0, 0.0, 0.0, 0.0))
        out = {
            "position": np.array(self.position, dtype=np.float64).reshape(3, n).T.copy(),
            "scale": np.array(self.scale(), dtype=np.float64).reshape(2, n).T.copy(),
            "rotation": np.array(qn, dtype=np.float64).reshape(4, n).T.copy(),
            "opacity": np.array(self.opacity(), dtype=np.float64).reshape(n),
        }
        for name, t in self.channels.items():
            out[name] = np.array(t, dtype=np.float64).reshape(n, -1)
        return out


# -- spherical harmonics ------------------------------------------------------------------
def sh_degree(num_coeffs: int) -> int:
    """Degree of an SH expansion with ``num_coeffs`` = (degree + 1)^2 coefficients per colour."""
    for deg in range(SH_MAX_DEGREE + 1):
        if (deg + 1) ** 2 == num_coeffs:
            return deg
    raise ValueError(f"SH: {num_coeffs} coefficients per colour is not (degree+1)^2 "
                     f"with degree <= {SH_MAX_DEGREE}")


def sh_basis(d: mi.Vector3f, degree: int) -> list:
    """The real SH basis values [K] (each [N]) of 3DGS/2DGS at unit directions ``d`` [N]."""
    x, y, z = d.x, d.y, d.z
    b = [dr.full(mi.Float, SH_C0, dr.width(x))]
    if degree >= 1:
        b += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        b += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2.0 * zz - xx - yy),
              SH_C2[3] * x * z, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        b += [SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * x * y * z,
              SH_C3[2] * y * (4.0 * zz - xx - yy), SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
              SH_C3[4] * x * (4.0 * zz - xx - yy), SH_C3[5] * z * (xx - yy),
              SH_C3[6] * x * (xx - 3.0 * yy)]
    return b


def eval_sh(sh: mi.TensorXf, directions: mi.Vector3f, offset: float = 0.5,
            floor: float | None = 0.0) -> mi.TensorXf:
    """RGB [N, 3] = max(SH(sh [N, K*3] coefficient-major) at ``directions`` [N] + offset,
    floor): 3DGS's colours with the default 0.5, stage 4's indirect irradiance with 0.
    ``floor`` None: no clamp. At the floor itself the gradient is the one from above.

    ``directions`` need not be normalised (zero -> the DC term only).
    """
    if len(sh.shape) != 2 or sh.shape[1] % 3 != 0:
        raise ValueError(f"eval_sh: sh must be [N, K*3], got {tuple(sh.shape)}")
    n, kc = sh.shape
    degree = sh_degree(kc // 3)
    n2 = dr.squared_norm(directions)
    d = directions * dr.rsqrt(dr.select(n2 > 0, n2, 1.0))
    basis = sh_basis(d, degree)
    idx = dr.arange(mi.UInt32, n) * kc
    rgb = []
    for c in range(3):
        acc = mi.Float(0.0)
        for k, bk in enumerate(basis):
            acc = acc + bk * dr.gather(mi.Float, sh.array, idx + (k * 3 + c))
        v = acc + offset
        rgb.append(v if floor is None else dr.select(v >= floor, v, floor))
    return mi.TensorXf(dr.ravel(mi.Vector3f(*rgb)), shape=(n, 3))


def sh_colors(surfels: Surfels, camera_origin) -> mi.TensorXf:
    """View-dependent RGB [N, 3] of channel "sh" seen from ``camera_origin`` [3] (3DGS: the
    direction from the camera to the centre)."""
    if "sh" not in surfels.channels:
        raise KeyError("sh_colors: the surfels have no 'sh' channel")
    o = np.asarray(camera_origin, dtype=np.float64).reshape(3)
    # Opaque: as literals, every camera would compile its own kernel (``core.jit``).
    d = surfels.position - mi.Point3f(*(jit.opaque(v) for v in o))
    return eval_sh(surfels.channels["sh"], mi.Vector3f(d))
