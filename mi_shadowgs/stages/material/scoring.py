"""Closed-form scores of the lights: a candidate direction's squared error on the training
views (``refine_score``: irradiance, per segment, or per segment albedo), the lights'
normal equations and their non-negative least squares, and the backward elimination of
lights that explain little (``drop_unexplained``)."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import shading
from mi_shadowgs.stages.material.config import MaterialConfig
from mi_shadowgs.stages.material.views import TrainView, view_maps


def _view_direct(v: TrainView, channels: dict, config: MaterialConfig, maps, dirs,
                 with_specular: bool, positions=None, center=None):
    """A view's materials (albedo, roughness, metallic, indirect or None), its direct
    shading per light of ``dirs`` [P * K] pixel-major (lamps where ``positions`` rows are
    finite) and that visibility [P * K] (from ``maps``; None without)."""
    albedo, rough, metal, ind = view_maps(v.pairs, channels, v.surfel_normal, with_specular)
    vis = (None if maps is None
           else maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint))
    per = shading.direct_per_light(v.geom, albedo, rough, metal, dirs, vis, with_specular,
                                   positions, center)
    # [P * K] both, in one kernel: their readers (per channel, per sum, the albedo score's
    # unit-albedo shading) would each recompute the lookups
    dr.eval(per, vis)
    return albedo, rough, metal, ind, per, vis


def others_shading(lights: shading.LightSet, per: mi.Color3f, k: int, npix: int
                   ) -> mi.Color3f:
    """The shading [P] of every light but ``k``, from ``per`` [P * K] (``_view_direct``)."""
    kk = lights.count
    li = dr.arange(mi.UInt32, npix * kk) % kk
    others = dr.select(li == k, 0.0, 1.0) * dr.gather(mi.Color3f, lights.weights, li) * per
    return mi.Color3f(*(dr.block_reduce(dr.ReduceOp.Add, others[c], kk) for c in range(3)))


def _candidate_scores(views: list[TrainView], channels: dict, lights: shading.LightSet, maps,
                      k: int, cand_maps, config: MaterialConfig, with_specular: bool,
                      cand_lights: shading.LightSet | None = None,
                      score: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(squared error [C], fitted irradiance [C]) of the views when light ``k`` moves to
    each candidate direction of ``cand_maps``, its irradiance re-fitted by least squares
    with the fitted materials. The error is that of ``config.refine_score``: with that one
    irradiance re-fitted ("irradiance"), with the light's scale re-fitted per segment
    ("segment", ``segment_errors``), or with each segment's albedo re-fitted per channel
    ("albedo", ``albedo_errors``). ``cand_lights``: the candidates as lights (lamps among
    them; their weights unused), else the directions of ``cand_maps``. ``score``: in place
    of ``config.refine_score``."""
    score = score or config.refine_score
    cand = cand_lights or shading.LightSet(cand_maps.directions, mi.Color3f(1.0))
    n_cand = cand.count
    s_rb = dr.zeros(mi.Float64, n_cand)  # summed in Dr.Jit, read once at the end
    s_bb = dr.zeros(mi.Float64, n_cand)
    s_rr = mi.Float64(0.0)
    n_seg = max(v.n_segments for v in views) if views else 1
    seg_sums = _SegmentSums(n_cand, n_seg) if score != "irradiance" else None
    alb_sums = _AlbedoSums(n_cand, n_seg) if score == "albedo" else None
    with dr.suspend_grad():
        for v in views:
            albedo, rough, metal, ind, per, vis_k = _view_direct(
                v, channels, config, maps, lights.directions, with_specular, lights.positions,
                lights.center)
            npix = dr.width(v.geom.alpha)
            rest = others_shading(lights, per, k, npix)
            if ind is not None:
                rest = rest + (1.0 - metal) * albedo * ind
            resid = (v.target - rest) * v.weight  # [P], what light k has to explain
            vis = (None if cand_maps is None
                   else cand_maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint))
            if alb_sums is not None and vis is not None:
                dr.eval(vis)  # [P * C]: read by both shadings below
            b = shading.direct_per_light(v.geom, albedo, rough, metal, cand.directions,
                                         vis, with_specular, cand.positions,
                                         cand.center)  # [P * C] pixel-major
            dr.eval(b)  # once: r.b and b.b below would each recompute the lookups
            pi = dr.arange(mi.UInt32, npix * n_cand) // n_cand
            r = dr.gather(mi.Color3f, resid, pi)
            b = b * dr.gather(mi.Float, v.weight, pi)
            # Candidate-major for the per-candidate sums over pixels.
            cm = dr.arange(mi.UInt32, npix * n_cand)
            src = (cm % npix) * n_cand + cm // npix
            rb = dr.gather(mi.Float, dr.sum(r * b), src)
            bb = dr.gather(mi.Float, dr.squared_norm(b), src)
            s_rb += mi.Float64(dr.block_reduce(dr.ReduceOp.Add, rb, npix))
            s_bb += mi.Float64(dr.block_reduce(dr.ReduceOp.Add, bb, npix))
            s_rr += mi.Float64(dr.sum(dr.squared_norm(resid)))
            if seg_sums is not None:
                seg_sums.add(v, resid, rb, bb)
            if alb_sums is not None:
                _add_albedo_sums(alb_sums, v, lights, vis_k, k, cand, vis)
            dr.eval(s_rb, s_bb, s_rr)  # one kernel per view, not one growing graph
    s_rb, s_bb = s_rb.numpy(), s_bb.numpy()
    s_rr = float(s_rr.numpy()[0])
    irr = np.where(s_bb > 0, np.maximum(s_rb, 0.0) / np.maximum(s_bb, 1e-30), 0.0)
    err = s_rr - 2.0 * irr * s_rb + irr * irr * s_bb
    if seg_sums is not None:
        err = segment_errors(*seg_sums.read())
    if alb_sums is not None:
        weights = np.asarray(lights.weights.numpy(), np.float64).reshape(3, -1).mean(0)
        err_a, e_a = albedo_errors(*alb_sums.read(), max(float(weights.sum()), 1e-12))
        if e_a[np.argmin(err_a)] >= ALBEDO_MIN_SHARE * weights[k]:
            err = err_a
    return err, irr


def _add_albedo_sums(sums: _AlbedoSums, v: TrainView, lights: shading.LightSet,
                     vis: mi.Float | None, k: int, cand: shading.LightSet,
                     cand_vis: mi.Float | None) -> None:
    """One view's sums of ``albedo_errors`` (no lobe): the target, the other lights' shading
    X at unit albedo (``vis`` [P * K] the lights' visibility, None: V = 1) and the
    candidates' B (``cand_vis`` [P * C] theirs). Only the target, the geometry, the shadow
    maps and the lights enter, not the fitted materials."""
    npix = dr.width(v.geom.alpha)
    zero = dr.zeros(mi.Float, npix)
    # a unit albedo splatted as the model's albedo is: the pixel's coverage (a silhouette
    # pixel's target is the blend with what lies behind)
    white = mi.Color3f(v.geom.alpha, v.geom.alpha, v.geom.alpha)
    per = shading.direct_per_light(v.geom, white, zero, zero, lights.directions, vis, False,
                                   lights.positions, lights.center)
    x = others_shading(lights, per, k, npix)
    b = shading.direct_per_light(v.geom, white, zero, zero, cand.directions, cand_vis, False,
                                 cand.positions, cand.center)
    dr.eval(x, b)  # [P], [P * C] pixel-major (b grey)
    sums.add(v, v.target * v.weight, x * v.weight, b[0])


class _SegmentSums:
    """The per-(candidate, segment) sums of ``segment_errors``, accumulated over views."""

    def __init__(self, n_cand: int, n_seg: int):
        # one bin more than the segments: the mixed pixels (TrainView.segment), dropped
        self.n_cand, self.n_seg = n_cand, n_seg + 1
        self.rr = dr.zeros(mi.Float64, self.n_seg)  # [S + 1] r.r
        # [C * (S + 1)] (candidate-major): r.B, B.B
        self.rb = dr.zeros(mi.Float64, n_cand * self.n_seg)
        self.bb = dr.zeros(mi.Float64, n_cand * self.n_seg)

    def add(self, v: TrainView, resid: mi.Color3f, rb: mi.Float, bb: mi.Float) -> None:
        """One view: the residual ``resid`` [P] that the light has to explain, and r.B_c and
        B_c.B_c [C * P] candidate-major (pixel weights applied)."""
        npix = dr.width(v.weight)
        seg = dr.select(v.segment >= v.n_segments, self.n_seg - 1, v.segment)  # [P]
        dr.scatter_reduce(dr.ReduceOp.Add, self.rr, mi.Float64(dr.squared_norm(resid)), seg)
        cm = dr.arange(mi.UInt32, npix * self.n_cand)  # candidate-major: c * P + p
        idx = (cm // npix) * self.n_seg + dr.gather(mi.UInt32, seg, cm % npix)
        dr.scatter_reduce(dr.ReduceOp.Add, self.rb, mi.Float64(rb), idx)
        dr.scatter_reduce(dr.ReduceOp.Add, self.bb, mi.Float64(bb), idx)
        dr.eval(self.rr, self.rb, self.bb)

    def read(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        shape = (self.n_cand, self.n_seg)
        return (self.rr.numpy()[:-1], self.rb.numpy().reshape(shape)[:, :-1],
                self.bb.numpy().reshape(shape)[:, :-1])


class _AlbedoSums:
    """The sums of ``albedo_errors`` over the views, per segment (and candidate) and colour
    channel; mixed pixels (``TrainView.segment`` = S) go to a last bin, dropped."""

    def __init__(self, n_cand: int, n_seg: int):
        self.n_cand, self.n_seg = n_cand, n_seg + 1
        # [(S + 1) * 3]: t.t, t.X, X.X
        self.tt, self.tx, self.xx = (dr.zeros(mi.Float64, self.n_seg * 3) for _ in range(3))
        # [C * (S + 1) * 3]: t.B, X.B; [C * (S + 1)]: B.B
        self.tb, self.xb = (dr.zeros(mi.Float64, n_cand * self.n_seg * 3) for _ in range(2))
        self.bb = dr.zeros(mi.Float64, n_cand * self.n_seg)

    def add(self, v: TrainView, t: mi.Color3f, x: mi.Color3f, b: mi.Float) -> None:
        """One view: target ``t`` [P] and other lights' shading ``x`` [P] (supervised pixels,
        else 0), the candidates' shading ``b`` [P * C] pixel-major (any pixel)."""
        npix, nc = dr.width(v.weight), self.n_cand
        seg = dr.select(v.segment >= v.n_segments, self.n_seg - 1, v.segment)  # [P]
        pi = dr.arange(mi.UInt32, npix * nc) // nc
        ci = dr.arange(mi.UInt32, npix * nc) % nc
        cs = ci * self.n_seg + dr.gather(mi.UInt32, seg, pi)  # [P * C] (candidate, segment)
        b = b * dr.gather(mi.Float, v.weight, pi)
        dr.scatter_reduce(dr.ReduceOp.Add, self.bb, mi.Float64(b * b), cs)
        for c in range(3):
            dr.scatter_reduce(dr.ReduceOp.Add, self.tt, mi.Float64(t[c] * t[c]), seg * 3 + c)
            dr.scatter_reduce(dr.ReduceOp.Add, self.tx, mi.Float64(t[c] * x[c]), seg * 3 + c)
            dr.scatter_reduce(dr.ReduceOp.Add, self.xx, mi.Float64(x[c] * x[c]), seg * 3 + c)
            dr.scatter_reduce(dr.ReduceOp.Add, self.tb,
                              mi.Float64(dr.gather(mi.Float, t[c], pi) * b), cs * 3 + c)
            dr.scatter_reduce(dr.ReduceOp.Add, self.xb,
                              mi.Float64(dr.gather(mi.Float, x[c], pi) * b), cs * 3 + c)
        dr.eval(self.tt, self.tx, self.xx, self.tb, self.xb, self.bb)

    def read(self) -> tuple[np.ndarray, ...]:
        """tt, tx, xx [S, 3]; tb, xb [C, S, 3]; bb [C, S] (the mixed bin dropped)."""
        s3, c3 = (self.n_seg, 3), (self.n_cand, self.n_seg, 3)
        return (self.tt.numpy().reshape(s3)[:-1], self.tx.numpy().reshape(s3)[:-1],
                self.xx.numpy().reshape(s3)[:-1], self.tb.numpy().reshape(c3)[:, :-1],
                self.xb.numpy().reshape(c3)[:, :-1],
                self.bb.numpy().reshape(self.n_cand, self.n_seg)[:, :-1])


# The 1-D search of albedo_errors: E over [1e-3, 1e3] x the lights' total irradiance on a
# log grid (steps of 5.9%), then a finer grid over the best cell's neighbours (steps of
# 0.29%). With the albedo free the other lights' scale is free too, relative to E: at the
# top of the range they are all but gone, so a light split over two grid cells (the
# warm-up's) is scored as if it were the only one.
ALBEDO_SEARCH = (241, 41, 1e-3, 1e3)


# Under "albedo", the moved light's irradiance at the best candidate, below this share of
# its current irradiance, means the other lights explain the views once the albedo is
# re-fitted, and the score is flat: then the "segment" score decides. Once one half of a
# light split over two grid cells is at the truth, the other half's best E was 0.03 of its
# 1.07, and the "albedo" score alone moved it 11 deg away; the two merged 5.8 deg off
# (tests/test_light_fit.py, the grid-cell boundary). The "segment" score, with the fitted
# albedo, has that half's energy left to place. On the sweep's s6 the weak light's best E
# was ~0.9 of its own. Without other lights' shading (X = 0) nothing else explains the views
# and E is inf (``albedo_errors``): the albedo score holds.
ALBEDO_MIN_SHARE = 0.25


def albedo_errors(tt: np.ndarray, tx: np.ndarray, xx: np.ndarray, tb: np.ndarray,
                  xb: np.ndarray, bb: np.ndarray, scale: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Squared error [C] and irradiance E [C] of each candidate when every segment s and
    channel c takes its own albedo a_sc >= 0 in t ~ a_sc (X_c + E B) (``refine_score``
    "albedo"): per (s, c) the least-squares a_sc leaves tt - (tX + E tB)^2 / |X + E B|^2,
    summed; E >= 0, one per candidate, is searched on ``ALBEDO_SEARCH``'s grids around
    ``scale``. Sums as ``_AlbedoSums.read``.

    Where X is 0 on every supervised pixel (one light, or the others dark) the albedo
    absorbs E: the error is the same at every E, and E is inf (unbounded) for all."""
    def err(e: np.ndarray) -> np.ndarray:  # e [C, G] -> [C, G]
        e4 = e[:, :, None, None]
        num = tx[None, None] + e4 * tb[:, None]
        den = xx[None, None] + 2.0 * e4 * xb[:, None] + e4 * e4 * bb[:, None, :, None]
        gain = np.where(den > 0, np.maximum(num, 0.0) ** 2 / np.where(den > 0, den, 1.0), 0.0)
        return (tt[None, None] - gain).sum((2, 3))

    if not (np.any(tx) or np.any(xx) or np.any(xb)):
        # t ~ a_sc E B: flat in E up to round-off. The search's argmin was round-off's
        # choice (0.18 or 164 of a one-light test's 1.5 as a float atomic's order on two
        # threads changed one pixel's last bit), and with it ALBEDO_MIN_SHARE's branch.
        return err(np.full((len(tb), 1), float(scale)))[:, 0], np.full(len(tb), np.inf)
    n_coarse, n_fine, lo_e, hi_e = ALBEDO_SEARCH
    grid = scale * np.geomspace(lo_e, hi_e, n_coarse)
    coarse = err(np.broadcast_to(grid, (len(tb), n_coarse)))
    j = np.argmin(coarse, 1)
    lo, hi = grid[np.maximum(j - 1, 0)], grid[np.minimum(j + 1, n_coarse - 1)]
    fine_e = np.geomspace(lo, hi, n_fine, axis=1)  # [C, F]
    fine = err(fine_e)
    i = np.argmin(fine, 1)
    rows = np.arange(len(tb))
    return fine[rows, i], fine_e[rows, i]


def segment_errors(rr: np.ndarray, rb: np.ndarray, bb: np.ndarray) -> np.ndarray:
    """Squared error [C] of the views when, in each segment s, the residual r = t - R that
    the moved light has to explain is fitted by least squares as b_s B_c, b_s >= 0
    (``MaterialConfig.refine_score`` "segment").

    Sums over the segment's supervised pixels and colour channels: ``rr`` [S] of r.r;
    ``rb``, ``bb`` [C, S] of r.B_c and B_c.B_c. A segment where B_c is zero (all in shadow)
    keeps its whole residual.
    """
    gain = np.where(bb > 0, np.maximum(rb, 0.0) ** 2 / np.where(bb > 0, bb, 1.0), 0.0)
    return (rr[None] - gain).sum(1)


def light_normal_equations(views: list[TrainView], channels: dict, dirs: np.ndarray, maps,
                           config: MaterialConfig, with_specular: bool,
                           per_segment: bool = False, positions=None, center=None):
    """Least squares of the views in the lights' irradiance e [K] (albedo, materials and
    indirect light fixed): the squared error is rr - 2 e . h + e^T G e. Returns (G [K, K],
    h [K], rr), float64; rr is the squared direct signal (target minus indirect).
    ``per_segment``: the same sums per material segment, over the pixels that one segment
    holds (``TrainView.segment``): G [S, K, K], h [S, K], rr [S]."""
    k = len(dirs)
    n_seg = max(v.n_segments for v in views) if per_segment else 1
    gram, h, rr = np.zeros((n_seg, k, k)), np.zeros((n_seg, k)), np.zeros(n_seg)
    with dr.suspend_grad():
        for v in views:
            albedo, rough, metal, ind, per, _ = _view_direct(
                v, channels, config, maps, dirs, with_specular, positions, center)  # [P * K]
            resid = v.target - (1.0 - metal) * albedo * ind if ind is not None else v.target
            wgt = np.asarray(v.weight.numpy(), np.float64)  # [P]
            b = np.stack([np.asarray(per[c], np.float64).reshape(-1, k) for c in range(3)])
            r = np.stack([np.asarray(resid[c], np.float64) for c in range(3)])  # [3, P]
            b *= wgt[None, :, None]  # [3, P, K]
            r *= wgt[None]
            seg = v.segment.numpy() if per_segment else None  # [P]
            for s_id in range(n_seg):
                bs, rs = b, r
                if seg is not None:  # mixed pixels (seg == v.n_segments) are in no segment
                    on = seg == s_id
                    bs, rs = b[:, on], r[:, on]
                gram[s_id] += np.einsum("cpk,cpj->kj", bs, bs)
                h[s_id] += np.einsum("cpk,cp->k", bs, rs)
                rr[s_id] += float(np.sum(rs * rs))
    if not per_segment:
        return gram[0], h[0], float(rr[0])
    return gram, h, rr


# segment_nnls's alternations of the light and the segments' scales; each lowers the error,
# and a fixed count (not a tolerance) keeps the light drops the same on every machine.
SEGMENT_NNLS_ALTERNATIONS = 20


def segment_nnls(gram: np.ndarray, h: np.ndarray, keep: np.ndarray,
                 iterations: int = SEGMENT_NNLS_ALTERNATIONS) -> tuple[np.ndarray, float]:
    """argmin over e >= 0 (0 off ``keep``) and one scale c_s >= 0 per segment of
    sum_s c_s^2 e^T G_s e - 2 c_s e . h_s (``gram`` [S, K, K], ``h`` [S, K]), by
    alternating the two (each step lowers it); returns (e, that minimum). e's scale is
    arbitrary (traded with the c_s)."""
    c = np.ones(len(h))
    e, err = np.zeros(h.shape[1]), 0.0
    idx = np.flatnonzero(keep)
    for _ in range(iterations):
        # nnls_irradiance's fit, without its error (not needed here)
        e = _nnls_kept(np.einsum("s,skj->kj", c * c, gram), np.einsum("s,sk->k", c, h), idx)
        q = np.einsum("k,skj,j->s", e, gram, e)  # [S]
        p = h @ e  # [S]
        c = np.where(q > 0, np.maximum(p, 0.0) / np.where(q > 0, q, 1.0), 0.0)
        err = float(np.sum(c * c * q - 2.0 * c * p))
    return e, err


def nnls_irradiance(gram: np.ndarray, h: np.ndarray, keep: np.ndarray
                    ) -> tuple[np.ndarray, float]:
    """argmin_{e >= 0, e = 0 off ``keep``} of e^T G e - 2 e . h, and that minimum."""
    e = _nnls_kept(gram, h, np.flatnonzero(keep))
    return e, float(e @ gram @ e - 2.0 * e @ h)  # 0 with no light kept


def _nnls_kept(gram: np.ndarray, h: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """argmin_{e >= 0, e = 0 off the lights ``idx``} of e^T G e - 2 e . h [K]."""
    from scipy.optimize import nnls

    e = np.zeros(len(h))
    if len(idx) == 0:
        return e
    g = gram[np.ix_(idx, idx)]
    # A relative ridge keeps the factorization defined for lights with identical images.
    g = g + np.eye(len(idx)) * (1e-9 * max(float(np.trace(g)) / len(idx), 1e-30))
    chol = np.linalg.cholesky(g)  # g = chol chol^T
    e[idx] = nnls(chol.T, np.linalg.solve(chol, h[idx]))[0]
    return e


def drop_unexplained(gram: np.ndarray, h: np.ndarray, rr, config: MaterialConfig
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Backward elimination of lights (see ``MaterialConfig.drop_share``): repeatedly drop
    the light whose removal costs least, while it carries < drop_share of the re-fitted
    irradiance and raises the squared error by < drop_gain times the error with it.
    Per-segment sums (``gram`` [S, K, K], ``h`` [S, K], ``rr`` [S]) are fitted with a scale
    per segment (``segment_nnls``). Returns (keep [K] bool, irradiance [K]); the irradiance
    is the global fit of the kept lights (the segments' sums added)."""
    if gram.ndim == 3:
        keep = _eliminate(gram, h, float(np.sum(rr)), config, segment_nnls)
        return keep, nnls_irradiance(gram.sum(0), h.sum(0), keep)[0]
    keep = _eliminate(gram, h, float(rr), config, nnls_irradiance)
    return keep, nnls_irradiance(gram, h, keep)[0]


def _eliminate(gram: np.ndarray, h: np.ndarray, rr: float, config: MaterialConfig, solve
               ) -> np.ndarray:
    """``drop_unexplained``'s loop with the fit ``solve(gram, h, keep) -> (e, error)``."""
    keep = np.ones(h.shape[-1], bool)
    e, err = solve(gram, h, keep)
    while keep.sum() > 1:
        total = e[keep].sum()
        best, best_cost, best_fit = -1, math.inf, None
        for k in np.flatnonzero(keep):
            if total > 0 and e[k] >= config.drop_share * total:
                continue
            trial = keep.copy()
            trial[k] = False
            e_k, err_k = solve(gram, h, trial)
            if err_k - err < best_cost:
                best, best_cost, best_fit = k, err_k - err, (e_k, err_k)
        # The error with every current light: a light the data needs raises it by far more
        # than any threshold (a fit explaining the views exactly has error ~0).
        if best < 0 or best_cost >= config.drop_gain * max(rr + err, 1e-12 * rr):
            break
        keep[best] = False
        e, err = best_fit
    return keep
