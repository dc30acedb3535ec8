"""Each photo's exposure and white balance: one RGB gain per training view, fitted in stage 1.

A camera in auto mode scales each photo by its own exposure and white balance. Stage 1
explains that as a gain ``g_v = exp(l_v)`` [3] per training view: the photometric loss
compares ``g_v * render`` with the photo. The render is linear in the surfels' colours, so
the gain multiplies the colours before they are composited (``apply_gain`` on [N, 3]): the
same image, at the cost of N products, not H * W (multiplying the image changed how Dr.Jit
fused the loss's backward kernels: a stage-1 step took 20% longer at 128^2). The log gains
``l`` [V, 3] have their own Adam (``GeometryConfig.lr_view_gain``). The surfels' colours
can take any per-channel factor that the gains give up, so after each step every channel's
log gains are shifted to mean 0 (``project``): the gains are relative to the views'
geometric mean.

Stage 4 holds them (``mi_shadowgs.stages.material.views.held_images``: each training photo
divided by its gain once, before the fit). The gains are saved as ``GAINS_FILE`` in stage
1's folder (``write_gains``) with each view's photo, and scored against a lab capture's true
gains (``photos/gains.json``, written by ``generate --photos``) after one scale per channel
(``gain_errors``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit

GAINS_FILE = "view_gains.json"  # in stage 1's folder
# A fitted gain outside this range (3 EV either way) did not converge: a photo that dark or
# bright has nothing left to fit.
GAIN_RANGE = (1.0 / 8.0, 8.0)


def is_photo_import(root) -> bool:
    """Whether dataset folder ``root`` was imported from photos (``mi-shadowgs import``
    records ``import.json``): a camera's exposure and white balance vary per photo."""
    from mi_shadowgs.dataset.importer import IMPORT_JSON

    return root is not None and (Path(root) / IMPORT_JSON).is_file()


def enabled(config, root) -> bool:
    """Whether stage 1 fits the gains on dataset folder ``root`` with ``config`` (a
    ``GeometryConfig``): ``view_gains`` "on", or "auto" and ``is_photo_import(root)``."""
    return config.view_gains == "on" or (config.view_gains == "auto" and is_photo_import(root))


# -- the maths ------------------------------------------------------------------------------
def apply_gain(image: mi.TensorXf, log_gain: mi.TensorXf, index) -> mi.TensorXf:
    """``image`` [..., 3] (colours [N, 3], or an image [H, W, 3]) times
    ``exp(log_gain[index])`` per channel; ``log_gain`` [V, 3], ``index`` an opaque
    ``mi.UInt32`` (every view runs the same kernel). Differentiable in both."""
    n = dr.width(image.array)
    channel = dr.arange(mi.UInt32, n) % 3
    lg = dr.gather(mi.Float, log_gain.array, index * 3 + channel)
    return mi.TensorXf(image.array * dr.exp(lg), image.shape)


def project(log_gain: mi.Float, views: int) -> mi.Float:
    """``log_gain`` [V * 3] with each channel's mean over the views subtracted."""
    channel = dr.arange(mi.UInt32, views * 3) % 3
    total = dr.zeros(mi.Float, 3)
    dr.scatter_reduce(dr.ReduceOp.Add, total, log_gain, channel)
    return log_gain - dr.gather(mi.Float, total, channel) * (1.0 / views)


class ViewGains:
    """The training views' log gains [V, 3] and their optimiser: Adam per view.

    A view's gain gets a gradient only in the steps that render it, one in V. Adam over all
    steps would average its second moment over the V - 1 steps without one as well and so
    scale the view's step up by about sqrt(V) (8x for 64 views): the gains would jitter by
    several percent about their optimum. So each view's moments, and its bias correction,
    advance only at its own steps (as a sparse Adam does); a step moves about ``lr``.
    """

    BETA_1, BETA_2, EPS = 0.9, 0.999, 1e-15

    def __init__(self, log_gain: np.ndarray, m: np.ndarray | None = None,
                 v: np.ndarray | None = None, visits: np.ndarray | None = None):
        log_gain = np.asarray(log_gain, np.float32).reshape(-1, 3)
        self.views = n = len(log_gain)
        self.m = jit.tensor(np.zeros((n, 3)) if m is None else m).array  # [V * 3]
        self.v = jit.tensor(np.zeros((n, 3)) if v is None else v).array  # [V * 3]
        self.visits = jit.tensor(np.zeros(n) if visits is None else visits).array  # [V]
        self.log_gain = jit.tensor(log_gain)  # [V, 3]
        dr.enable_grad(self.log_gain)

    @classmethod
    def fresh(cls, views: int) -> ViewGains:
        return cls(np.zeros((views, 3), np.float32))

    def apply(self, image: mi.TensorXf, index: int) -> mi.TensorXf:
        """``image`` [..., 3] (colours or an image) of training view ``index`` times its
        gain."""
        return apply_gain(image, self.log_gain, jit.opaque(index, mi.UInt32))

    def step(self, index: int, lr: float) -> None:
        """Adam's step of view ``index``'s log gains with the gradient on them, at learning
        rate ``lr``, then ``project`` (no host read)."""
        b1, b2 = self.BETA_1, self.BETA_2
        i = jit.opaque(index, mi.UInt32)
        hit = dr.arange(mi.UInt32, self.views * 3) // 3 == i  # [V * 3] this view's entries
        g = dr.grad(self.log_gain.array)
        self.visits = self.visits + dr.select(dr.arange(mi.UInt32, self.views) == i, 1.0, 0.0)
        k = dr.gather(mi.Float, self.visits, i)  # this view's steps, this one included
        self.m = dr.select(hit, dr.fma(self.m, b1, (1.0 - b1) * g), self.m)
        self.v = dr.select(hit, dr.fma(self.v, b2, (1.0 - b2) * g * g), self.v)
        c1 = 1.0 / (1.0 - dr.exp(k * math.log(b1)))
        c2 = 1.0 / (1.0 - dr.exp(k * math.log(b2)))
        move = jit.opaque(lr) * (self.m * c1) / (dr.sqrt(self.v * c2) + self.EPS)
        p = dr.detach(self.log_gain.array) - dr.select(hit, move, 0.0)
        self.log_gain = mi.TensorXf(project(p, self.views), (self.views, 3))
        dr.enable_grad(self.log_gain)
        dr.eval(self.log_gain, self.m, self.v, self.visits)

    def set(self, gains: np.ndarray) -> None:
        """Set the gains to ``gains`` [V, 3], projected (the moments stay)."""
        lg = np.log(np.asarray(gains, np.float64).reshape(self.views, 3))
        self.log_gain = jit.tensor(lg - lg.mean(0))
        dr.enable_grad(self.log_gain)

    def gains(self) -> np.ndarray:
        """The gains [V, 3] (float64)."""
        return np.exp(np.asarray(self.log_gain.numpy(), np.float64).reshape(-1, 3))

    def to_numpy(self, prefix: str) -> dict[str, np.ndarray]:
        def host(x, shape):
            return np.asarray(x.numpy(), np.float32).reshape(shape)
        n = self.views
        return {prefix + "log_gain": host(self.log_gain.array, (n, 3)),
                prefix + "adam_m": host(self.m, (n, 3)), prefix + "adam_v": host(self.v, (n, 3)),
                prefix + "visits": host(self.visits, (n,))}

    @classmethod
    def from_numpy(cls, arrays: dict[str, np.ndarray], prefix: str) -> ViewGains | None:
        """The gains saved by ``to_numpy(prefix)``; None when ``arrays`` has none."""
        if prefix + "log_gain" not in arrays:
            return None
        return cls(arrays[prefix + "log_gain"], arrays[prefix + "adam_m"],
                   arrays[prefix + "adam_v"], arrays[prefix + "visits"])


def check_gains(gains: np.ndarray, names: list[str]) -> None:
    """A ValueError naming the first view whose gain [3] is not finite or outside
    ``GAIN_RANGE`` (the fit did not converge), and the settings to change."""
    lo, hi = GAIN_RANGE
    for name, g in zip(names, np.asarray(gains, np.float64), strict=True):
        if not (np.all(np.isfinite(g)) and np.all(g >= lo) and np.all(g <= hi)):
            raise ValueError(
                f"GeometryConfig.view_gains: the fitted RGB gain of training view {name!r} "
                f"is {[round(float(x), 4) for x in g]}, outside [1/8, 8]: the gains did not "
                "converge (lower GeometryConfig.lr_view_gain, or set view_gains to 'off' if "
                "the photos share one exposure)")


# -- files ------------------------------------------------------------------------------------
def ev_and_white_balance(gains: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(EV [V], white balance [V, 3]) of gains [V, 3]: EV the mean of the channels' log2
    gains, the white balance what is left (its channels' geometric mean is 1)."""
    g = np.asarray(gains, np.float64).reshape(-1, 3)
    ev = np.log2(g).mean(-1)
    return ev, g / np.exp2(ev)[:, None]


def photo_names(root, split: str = "train") -> list[str | None]:
    """The photo each frame of ``root``'s ``transforms_<split>.json`` was made from (its
    ``source_image``, as ``mi-shadowgs import`` writes it), in frame order; None for a frame
    without one."""
    from mi_shadowgs.dataset import layout

    path = Path(root) / layout.transforms_name(split)
    frames = json.loads(path.read_text()).get("frames", []) if path.is_file() else []
    return [fr.get("source_image") for fr in frames]


def truth_file(root) -> Path | None:
    """A lab capture's true gains (``photos/gains.json`` of ``generate --photos``) beside
    the photos that dataset ``root`` was imported from; None when there are none."""
    from mi_shadowgs.dataset import layout
    from mi_shadowgs.dataset.importer import IMPORT_JSON

    record = Path(root) / IMPORT_JSON
    if not record.is_file():
        return None
    source = json.loads(record.read_text()).get("source")
    path = Path(source) / layout.PHOTO_GAINS if source else None
    return path if path is not None and path.is_file() else None


def gain_errors(fitted: np.ndarray, truth: np.ndarray) -> dict:
    """Fitted gains [V, 3] against true ones [V, 3] after one scale per channel (the
    geometric mean of truth / fitted over the views: the photos fix the gains only up to
    it). Relative errors |s * fitted / truth - 1|: their max and mean over views and
    channels, per view (the max of its channels), and the scale [3]."""
    f = np.asarray(fitted, np.float64).reshape(-1, 3)
    t = np.asarray(truth, np.float64).reshape(-1, 3)
    if f.shape != t.shape or not len(f):
        raise ValueError(f"gain_errors: {f.shape} fitted gains for {t.shape} true ones")
    scale = np.exp(np.mean(np.log(t) - np.log(f), axis=0))
    rel = np.abs(f * scale / t - 1.0)
    return {"max": float(rel.max()), "mean": float(rel.mean()),
            "per_view": rel.max(-1).tolist(), "scale": scale.tolist()}


def gains_record(gains: np.ndarray, psnr: list[float], names: list[str], root) -> dict:
    """The JSON of ``GAINS_FILE``: each training view's name, photo, gain, EV, white
    balance and the PSNR of its gained render (``psnr``: a low one says the gain is not
    measured); with a true gain for every view's photo (``truth_file``), the truth and the
    errors (``gain_errors``)."""
    g = np.asarray(gains, np.float64).reshape(-1, 3)
    photos = photo_names(root) if root is not None else []
    photos = photos if len(photos) == len(g) else [None] * len(g)
    ev, wb = ev_and_white_balance(g)
    views = [{"name": n, "photo": p, "gain": gk.tolist(), "ev": float(e),
              "white_balance": w.tolist(), "psnr": float(q)}
             for n, p, gk, e, w, q in zip(names, photos, g, ev, wb, psnr, strict=True)]
    out = {"convention": "photo = gain * render, per channel; the gains' log has mean 0 "
                         "over the views in every channel; ev = mean of log2(gain), "
                         "white_balance = gain / 2^ev",
           "views": views}
    path = truth_file(root) if root is not None else None
    true = json.loads(path.read_text()).get("photos", {}) if path is not None else {}
    if true and all(p in true for p in photos):
        t = np.array([true[p]["gain"] for p in photos], np.float64)
        err = gain_errors(g, t)
        for view, tk, e in zip(views, t, err["per_view"], strict=True):
            view.update(true_gain=tk.tolist(), true_ev=float(np.log2(tk).mean()),
                        error=e)
        out["truth"] = {"file": str(path), "max_error": err["max"],
                        "mean_error": err["mean"], "scale": err["scale"],
                        "note": "relative error |s * gain / true gain - 1| after one scale "
                                "s per channel"}
    return out


def write_gains(path: Path, gains: np.ndarray, psnr: list[float], names: list[str], root
                ) -> dict:
    """``gains_record`` into ``path`` (atomically); returns it."""
    from mi_shadowgs.io.atomic import write_json

    record = gains_record(gains, psnr, names, root)
    write_json(path, record)
    return record


def read_gains(path: Path, names: list[str]) -> list[np.ndarray]:
    """The gains [3] of training views ``names`` from ``GAINS_FILE`` at ``path``, in that
    order; a ValueError naming the file and the view where one is missing or bad."""
    try:
        record = json.loads(Path(path).read_text())
        by_name = {v["name"]: np.asarray(v["gain"], np.float64) for v in record["views"]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a view-gains record ({exc})") from None
    out = []
    for name in names:
        g = by_name.get(name)
        if g is None or g.shape != (3,) or not np.all(np.isfinite(g)) or np.any(g <= 0):
            raise ValueError(f"{path}: no valid gain for training view {name!r}")
        out.append(g)
    return out


# Without masks, a view's gain is measured on the pixels whose alpha is over GAIN_COVER,
# unless they are under GAIN_MIN_SHARE of the view (then on every pixel).
GAIN_COVER = 0.99
GAIN_MIN_SHARE = 0.01


def covered_pixels(alpha: np.ndarray) -> np.ndarray:
    """[H, W] bool: the pixels of a render's ``alpha`` over ``GAIN_COVER`` (or every pixel,
    where they are under ``GAIN_MIN_SHARE`` of them), on which a view without a mask gets
    its gain: the backdrop is one colour for every view, and the room behind the object is
    not."""
    keep = np.asarray(alpha) > GAIN_COVER
    return keep if keep.mean() >= GAIN_MIN_SHARE else np.ones(keep.shape, bool)


def l1_gain(render: np.ndarray, image: np.ndarray, mask: np.ndarray | None = None
            ) -> np.ndarray:
    """The per-channel gain [3] that minimises sum |gain * render - image| over the pixels
    of ``mask`` [H, W] (all without): the median of image / render weighted by render, over
    the pixels the render covers; 1 for a channel it leaves empty."""
    r = np.asarray(render, np.float64).reshape(-1, 3)
    i = np.asarray(image, np.float64).reshape(-1, 3)
    keep = np.ones(len(r), bool) if mask is None else np.asarray(mask, bool).reshape(-1)
    out = np.ones(3)
    for c in range(3):
        ok = keep & (r[:, c] > 1e-6)
        if ok.any():
            ratio, weight = i[ok, c] / r[ok, c], r[ok, c]
            order = np.argsort(ratio, kind="stable")
            total = np.cumsum(weight[order])
            out[c] = ratio[order][np.searchsorted(total, 0.5 * total[-1])]
    return out


def least_squares_gain(render: np.ndarray, image: np.ndarray) -> np.ndarray:
    """The per-channel gain [3] that best maps ``render`` [H, W, 3] to ``image``
    (least squares: sum(r * i) / sum(r * r)); 1 for an empty channel."""
    r = np.asarray(render, np.float64).reshape(-1, 3)
    i = np.asarray(image, np.float64).reshape(-1, 3)
    num, den = (r * i).sum(0), (r * r).sum(0)
    return np.where(den > 0, num / np.maximum(den, 1e-300), 1.0)

