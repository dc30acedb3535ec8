"""Surfel parameters as [N, C] tensors and an Adam optimiser whose rows can be gathered.

``mi.ad.Adam`` keeps its moments in private state that densification (which adds, copies
and drops surfels) would have to reach into; this small Adam keeps them as plain [N, C]
tensors beside the parameters, so a row selection applies to all three alike, and a
checkpoint is a set of NumPy arrays. Learning rates and the bias correction enter the
kernels as opaque values: a schedule does not recompile anything.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit
from mi_shadowgs.core.surfels import Surfels


def tensor_nc(a: np.ndarray) -> mi.TensorXf:
    """[N, ...] -> an [N, C] tensor in memory Dr.Jit allocated: the first step after a
    densification then runs the same kernels as every other (``core.jit``)."""
    a = np.asarray(a, dtype=np.float32)
    return jit.tensor(a.reshape(a.shape[0], -1))


def surfels_from_params(params: dict[str, mi.TensorXf], sh_columns: int | None = None
                        ) -> Surfels:
    """``Surfels`` viewing the [N, C] parameter tensors (differentiably).

    ``sh_columns`` keeps only the first columns of "sh" (the active SH degree).
    """
    sh = params["sh"]
    n = sh.shape[0]
    kc = sh.shape[1]
    if sh_columns is not None and sh_columns < kc:
        idx = dr.arange(mi.UInt32, n * sh_columns)
        row = idx // sh_columns
        sh = mi.TensorXf(dr.gather(mi.Float, sh.array, row * kc + (idx - row * sh_columns)),
                         shape=(n, sh_columns))
    return Surfels(position=dr.unravel(mi.Point3f, params["position"].array),
                   log_scale=dr.unravel(mi.Point2f, params["log_scale"].array),
                   rotation=dr.unravel(mi.Vector4f, params["rotation"].array),
                   opacity_logit=mi.Float(params["opacity_logit"].array),
                   channels={"sh": sh})


class SurfelAdam:
    """Adam (Kingma & Ba) over a dict of [N, C] tensors with one learning rate per group."""

    def __init__(self, params: dict[str, np.ndarray], lr: dict[str, float],
                 beta_1: float = 0.9, beta_2: float = 0.999, eps: float = 1e-15):
        self.beta_1, self.beta_2, self.eps = beta_1, beta_2, eps
        self.lr = dict(lr)
        self.t = 0
        self.params: dict[str, mi.TensorXf] = {}
        self.m: dict[str, mi.TensorXf] = {}
        self.v: dict[str, mi.TensorXf] = {}
        self.load({k: np.asarray(a, np.float32) for k, a in params.items()})

    @property
    def count(self) -> int:
        return int(next(iter(self.params.values())).shape[0])

    def load(self, params: dict[str, np.ndarray], m: dict | None = None, v: dict | None = None,
             t: int | None = None) -> None:
        """Replace the parameters (and moments; zero when not given) from NumPy arrays."""
        n = {a.shape[0] for a in params.values()}
        if len(n) != 1:
            raise ValueError(f"SurfelAdam: parameter row counts differ: {sorted(n)}")
        for key, a in params.items():
            if key not in self.lr:
                raise KeyError(f"SurfelAdam: no learning rate for parameter {key!r}")
            p = tensor_nc(a)
            dr.enable_grad(p)
            self.params[key] = p
            self.m[key] = tensor_nc(m[key]) if m else dr.zeros(mi.TensorXf, p.shape)
            self.v[key] = tensor_nc(v[key]) if v else dr.zeros(mi.TensorXf, p.shape)
        if t is not None:
            self.t = int(t)

    def to_numpy(self) -> tuple[dict, dict, dict]:
        def np_(d):
            return {k: np.asarray(x.numpy(), np.float32).reshape(x.shape) for k, x in d.items()}
        return np_(self.params), np_(self.m), np_(self.v)

    def step(self) -> None:
        """One Adam step with the gradients now on the parameters (no host read)."""
        self.t += 1
        b1, b2 = self.beta_1, self.beta_2
        # Opaque: these change every step and must not be baked into the kernel.
        c1 = dr.opaque(mi.Float, 1.0 / (1.0 - b1 ** self.t))
        c2 = dr.opaque(mi.Float, 1.0 / (1.0 - b2 ** self.t))
        for key, p in self.params.items():
            g = dr.grad(p.array)
            m = dr.fma(self.m[key].array, b1, (1.0 - b1) * g)
            v = dr.fma(self.v[key].array, b2, (1.0 - b2) * g * g)
            lr = dr.opaque(mi.Float, self.lr[key])
            new = dr.detach(p.array) - lr * (m * c1) / (dr.sqrt(v * c2) + self.eps)
            shape = p.shape
            self.m[key] = mi.TensorXf(m, shape=shape)
            self.v[key] = mi.TensorXf(v, shape=shape)
            q = mi.TensorXf(new, shape=shape)
            dr.enable_grad(q)
            self.params[key] = q
        dr.eval(self.params, self.m, self.v)


# -- checkpoints of drjit.opt.Adam (mi.ad.Adam) ------------------------------------------------
# Its state per parameter is (value, promoted, lr, (t, m, v, v_max)) (Dr.Jit 1.5, pinned in
# pyproject.toml); these two functions are the only code that knows that layout.
def adam_to_numpy(opt, prefix: str) -> dict[str, np.ndarray]:
    """The parameters, moments, step counts and learning rates of ``opt`` as arrays named
    ``prefix + "<key>/value"`` etc., ``prefix + "keys"`` (the registration order) and
    ``prefix + "lr"`` (the default learning rate)."""
    out = {prefix + "keys": np.array(list(opt.keys()), dtype=str),
           prefix + "lr": np.array([opt.lr], np.float64)}
    for key, (value, _, lr, (t, m, v, _)) in opt.state.items():
        shape = value.shape if isinstance(value, mi.TensorXf) else (dr.width(value),)
        out[f"{prefix}{key}/value"] = np.asarray(value.numpy(), np.float32).reshape(shape)
        out[f"{prefix}{key}/m"] = np.asarray(m.numpy(), np.float32)
        out[f"{prefix}{key}/v"] = np.asarray(v.numpy(), np.float32)
        out[f"{prefix}{key}/t"] = np.asarray(t.numpy(), np.uint32)
        if lr is not None:
            out[f"{prefix}{key}/lr"] = np.array([lr], np.float64)
    return out


def adam_from_numpy(opt, arrays: dict[str, np.ndarray], prefix: str) -> None:
    """Register the parameters of ``adam_to_numpy`` in ``opt`` with their whole state (in
    the saved order: a resumed loop visits them as the original did). A 1-D value comes
    back as ``mi.Float``, any other as ``mi.TensorXf``."""
    opt.set_learning_rate(float(arrays[prefix + "lr"][0]))
    for key in arrays[prefix + "keys"].tolist():
        a = arrays[f"{prefix}{key}/value"]
        opt[key] = jit.host(a.astype(np.float32)) if a.ndim == 1 else jit.tensor(a)
        value, promoted, _, _ = opt.state[key]
        lr = arrays.get(f"{prefix}{key}/lr")
        extra = (jit.array(arrays[f"{prefix}{key}/t"], mi.UInt32),
                 jit.host(arrays[f"{prefix}{key}/m"].astype(np.float32)),
                 jit.host(arrays[f"{prefix}{key}/v"].astype(np.float32)), None)
        opt.state[key] = (value, promoted, None if lr is None else float(lr[0]), extra)
