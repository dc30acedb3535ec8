"""The fitted per-surfel channels: their initial values, the projection after each step
(the box constraints, then the segment averaging), and the hold on the albedo x light
scale."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit, shading
from mi_shadowgs.core.brdf import ROUGHNESS_MIN
from mi_shadowgs.core.surfels import SH_C0, Surfels
from mi_shadowgs.stages.material.config import MaterialConfig

# The per-surfel albedo detail, log factor [N, 3] (``MaterialConfig.detail_prior``); only
# while fitting: the result carries the detailed albedo in its "albedo" channel.
DETAIL_CHANNEL = "albedo_detail"


def init_channels(surfels: Surfels, config: MaterialConfig) -> dict[str, mi.TensorXf]:
    """Initial material and indirect channels [N, C]."""
    n = surfels.count
    k = (config.sh_degree + 1) ** 2
    sh = np.zeros((n, 3 * k), np.float32)
    sh[:, :3] = config.indirect_init / SH_C0
    return {"albedo": jit.tensor(np.full((n, 3), config.albedo_init, np.float32)),
            "roughness": jit.tensor(np.full((n, 1), config.roughness_init, np.float32)),
            "metallic": jit.tensor(np.full((n, 1), config.metallic_init, np.float32)),
            shading.INDIRECT_CHANNEL: jit.tensor(sh)}


def segment_ids(surfels: Surfels) -> mi.UInt32:
    """The per-surfel integer "segment" channel as UInt32 [N]; clear errors otherwise."""
    if "segment" not in surfels.channels:
        raise ValueError("stage 4: the surfels have no 'segment' channel (run segmentation, "
                         "or give every surfel segment 0)")
    seg = np.asarray(surfels.channels["segment"].numpy()).reshape(-1)
    if (len(seg) != surfels.count or not np.all(np.isfinite(seg)) or np.any(seg < 0)
            or np.any(seg != np.round(seg))):
        raise ValueError("stage 4: channel 'segment' must hold one non-negative integer per "
                         "surfel")
    return jit.host(seg.astype(np.uint32), mi.UInt32)


def segment_average(values: mi.TensorXf, seg: mi.UInt32, n_segments: int) -> mi.TensorXf:
    """Replace each row of ``values`` [N, C] by the mean over its segment (``seg`` [N])."""
    n, c = values.shape
    counts = dr.zeros(mi.Float, n_segments)
    dr.scatter_reduce(dr.ReduceOp.Add, counts, mi.Float(1.0), seg)
    out = []
    for k in range(c):
        col = dr.gather(mi.Float, values.array, dr.arange(mi.UInt32, n) * c + k)
        sums = dr.zeros(mi.Float, n_segments)
        dr.scatter_reduce(dr.ReduceOp.Add, sums, col, seg)
        mean = sums / dr.maximum(counts, 1.0)
        out.append(dr.gather(mi.Float, mean, seg))
    flat = dr.zeros(mi.Float, n * c)
    for k in range(c):
        dr.scatter(flat, out[k], dr.arange(mi.UInt32, n) * c + k)
    return mi.TensorXf(flat, (n, c))


def detailed_albedo(albedo: mi.TensorXf, detail: mi.TensorXf) -> mi.TensorXf:
    """The albedo [N, 3] times exp(detail) [N, 3], in [0, 1]."""
    return mi.TensorXf(dr.clip(albedo.array * dr.exp(detail.array), 0.0, 1.0), albedo.shape)


def _clamp_channels(ch: dict, seg, n_seg: int, config: MaterialConfig, with_specular: bool):
    """Projection after a step: the box constraints, then the segment averaging."""
    a = mi.TensorXf(dr.clip(ch["albedo"].array, 0.0, 1.0), ch["albedo"].shape)
    if config.segment_average:
        a = segment_average(a, seg, n_seg)
    ch["albedo"] = a
    if DETAIL_CHANNEL in ch:  # zero-mean per segment: the segment's albedo keeps its scale
        d = ch[DETAIL_CHANNEL]
        d = mi.TensorXf(d.array - segment_average(d, seg, n_seg).array, d.shape)
        ch[DETAIL_CHANNEL] = mi.TensorXf(dr.clip(d.array, -config.detail_max,
                                                 config.detail_max), d.shape)
    if with_specular:
        ch["roughness"] = mi.TensorXf(dr.clip(ch["roughness"].array, ROUGHNESS_MIN, 1.0),
                                      ch["roughness"].shape)
        ch["metallic"] = mi.TensorXf(dr.clip(ch["metallic"].array, 0.0, 1.0),
                                     ch["metallic"].shape)


def albedo_scale_factor(albedo: np.ndarray, support: np.ndarray, config: MaterialConfig
                        ) -> float:
    """The factor c that brings the support-weighted ``albedo_scale_quantile`` of the
    surfels' brightest channel (``albedo`` [N, 3]) to ``albedo_scale``. Weighted by what the
    views see: a segment under the base, with no supervised pixel, drifts freely under Adam
    and must not set the scale."""
    top = np.asarray(albedo, np.float64).reshape(len(support), -1).max(axis=1)  # [N]
    order = np.argsort(top)
    cum = np.cumsum(support[order])
    if cum[-1] <= 0:
        return 1.0
    k = min(int(np.searchsorted(cum, config.albedo_scale_quantile * cum[-1])), len(top) - 1)
    return config.albedo_scale / max(float(top[order[k]]), 1e-6)


def hold_albedo_scale(ch: dict, opt, c: float) -> None:
    """Scale the albedo by ``c``, the light (``opt["log_light"]``) and the indirect light by
    1 / c: diffuse shading a (E + ind) is unchanged. ``c`` enters as an opaque scalar: as a
    literal it changed the source of the next step's kernels every time, and each was
    compiled again (a stage-4 fit 102 s against 66 s without the holds)."""
    if c == 1.0:
        return
    a = ch["albedo"]
    ch["albedo"] = mi.TensorXf(a.array * jit.opaque(c), a.shape)
    ind = ch.get(shading.INDIRECT_CHANNEL)
    if ind is not None:
        ch[shading.INDIRECT_CHANNEL] = mi.TensorXf(ind.array * jit.opaque(1.0 / c), ind.shape)
    opt["log_light"] = dr.detach(opt["log_light"]) - jit.opaque(math.log(c))
