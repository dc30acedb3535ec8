"""Stage 2: material segmentation with contrastive per-surfel features and K-means (Sec. IV-B).

Every surfel carries a feature f_i [D] (channel "feature"), rendered like colour:
F(x) = sum_i T_i alpha_i f_i. Given one integer label map per training view (material ids,
or the chromaticity segments of ``mi_shadowgs.stages.segmentation.masks``; label 0 =
unlabelled, e.g. background), the features are trained with (Eq. 8-11)

- ``L_pos``  = -1/(|X1||X2|) sum_{x1, x2} [M1 = M2] S(x1, x2),
- ``L_neg``  =  1/(|X1||X2|) sum_{x1, x2} [M1 != M2] [S > delta] S(x1, x2),
- ``L_mask`` = ``L_intra`` + ``L_inter`` over label prototypes mu_k (the mean of the
  normalised features of the samples with label k, renormalised):
  ``L_intra`` = mean_x (1 - cos(F(x), mu_M(x))) pulls features to their prototype;
  ``L_inter`` = mean_k tau * log sum_{l != k} exp(cos(mu_k, mu_l) / tau), a soft maximum (at
  temperature tau) of each prototype's similarity to the others, pushes prototypes apart;
- ``L_norm`` = mean_i (|f_i| - 1)^2 over the per-surfel features (unit length: cosine
  similarity ignores the magnitude, which would otherwise drift),

L_seg = L_pos + lambda_neg L_neg + lambda_norm L_norm + lambda_mask L_mask, with S the cosine
similarity of rendered features. The paper gives neither the form of L_intra/L_inter nor
where tau enters; the forms above are our choice. X1 and X2 are the two halves of
``n_samples`` labelled pixels drawn uniformly from one training view per iteration.
After training, K-means on the normalised features of the surfels the training views see
gives each surfel a segment id (channel "segment", 0..K-1); surfels no training view sees
take the nearest centre.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.config import check_fields
from mi_shadowgs.core import jit
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.packed import Packed
from mi_shadowgs.core.raster import RasterConfig, rasterize
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.stages.segmentation.planes import (
    SUPPORT_SPLITS,
    PlaneConfig,
    planar_shading_normals,
    support_split,
    support_split_applies,
)

FEATURE = "feature"
SEGMENT = "segment"
_RASTER = RasterConfig()


@dataclasses.dataclass(frozen=True)
class SegmentationConfig:
    """Stage-2 hyperparameters; defaults are the paper's (Sec. V-A1) where it gives them."""

    # D: not given in the paper. 16 separates the 14 labels of the hotdog with room to
    # spare, and each extra dimension costs one more rendered channel per iteration.
    feature_dim: int = 16
    iterations: int = 1000
    lr: float = 0.005  # Adam
    n_samples: int = 10_000  # labelled pixels per iteration, split into X1 and X2
    lambda_neg: float = 0.1
    lambda_norm: float = 1e-4
    lambda_mask: float = 0.5
    temperature: float = 0.3  # tau of L_inter
    margin: float = 0.5  # delta of Eq. 9 (not given in the paper): cos 0.5 = 60 degrees
    n_segments: int | None = None  # K; None: chosen by ``k_select``
    # How K is chosen when n_segments is None: "labels" counts the mask labels with enough
    # pixels (material ids, and chromaticity masks, whose checks already drop leaky regions
    # and slivers); "silhouette" picks the K in [2, that count] with the best silhouette of
    # the trained surfel features (a label the features do not separate earns no segment).
    # Silhouette is not the default, not even for chromaticity masks: its scores are close
    # together and a large base favours fewer clusters (docs/decisions.md).
    k_select: str = "labels"
    silhouette_samples: int = 2000  # seen surfels drawn for the silhouette ([n, n] distances)
    min_label_pixels: int = 20  # labels with fewer pixels (all views) do not count for K
    # ... nor labels below this share of the labelled pixels (0.005 suits the chromaticity
    # masks, whose edge and highlight slivers would otherwise each count; material ids of
    # the hotdog go down to 0.11 %, hence 0 by default).
    min_label_fraction: float = 0.0
    # ... for label maps from chromaticity (``masks`` "chromaticity"), in its place.
    chromaticity_min_label_fraction: float = 0.005
    kmeans_restarts: int = 5
    kmeans_iterations: int = 50  # Lloyd steps after k-means++ seeding
    # ... and after seeding with the label prototypes (``prototype_seeds``; k-means++ when
    # fewer than K labels have one). From the prototypes each step lets the centres leave
    # what the labels taught (cpu-small takes one).
    prototype_iterations: int = 50
    min_coverage: float = 0.5  # surfels with less summed splat weight (pixels) are "unseen"
    segment_alpha: float = 0.5  # rendered segment maps: background where alpha is lower
    # Initial features N(0, init_std^2 / D) per coordinate: small, so that the trained
    # direction dominates surfels that received few updates.
    init_std: float = 0.01
    # The label prototypes (the mean feature of each label) average the features over this
    # last share of the iterations: nearly trained, and many samples.
    prototype_share: float = 0.25
    seed: int = 0
    log_every: int = 25  # iterations between progress-bar loss reads (host syncs)
    # Resumable checkpoints: every so many iterations and at least this often in wall time.
    checkpoint_every: int = 500
    checkpoint_seconds: float = 60.0
    # After K-means, segments whose surfels lie on one plane are made flat (not in the
    # paper; off in its preset): ``planes.PlaneConfig``.
    planes: PlaneConfig = PlaneConfig()
    # Label maps from colour (``masks`` "chromaticity"): split every segment into its surfels
    # on the scene's dominant plane and those off it (``planes.support_split``; not in the
    # paper): an object and what it stands on are different objects, as the paper's SAM masks
    # have them, while colour labels give a grey object and a grey mat one label. "auto":
    # only where colour found a single segment (not a K set by n_segments); "on": always;
    # "off" (docs/decisions.md).
    support_split: str = "auto"

    def __post_init__(self):
        if isinstance(self.support_split, bool):  # runs recorded before "auto": a switch
            object.__setattr__(self, "support_split", "on" if self.support_split else "off")
        check_fields(self, (
            *((name, getattr(self, name) >= 1, ">= 1") for name in (
                "feature_dim", "iterations", "silhouette_samples", "kmeans_restarts",
                "kmeans_iterations", "prototype_iterations", "log_every",
                "checkpoint_every")),
            ("n_samples", self.n_samples >= 4, ">= 4 (two halves of pairs)"),
            ("lr", self.lr > 0, "> 0"), ("temperature", self.temperature > 0, "> 0"),
            *((name, getattr(self, name) >= 0, ">= 0") for name in (
                "lambda_neg", "lambda_norm", "lambda_mask", "min_label_pixels", "init_std")),
            ("n_segments", self.n_segments is None or self.n_segments >= 1, ">= 1 or None"),
            ("k_select", self.k_select in ("labels", "silhouette"), "'labels' or 'silhouette'"),
            ("support_split", self.support_split in SUPPORT_SPLITS,
             " or ".join(repr(x) for x in SUPPORT_SPLITS)),
            ("min_label_fraction", 0 <= self.min_label_fraction < 1, "in [0, 1)"),
            ("chromaticity_min_label_fraction", 0 <= self.chromaticity_min_label_fraction < 1,
             "in [0, 1)"),
            ("min_coverage", self.min_coverage >= 0, ">= 0"),
            ("prototype_share", 0 < self.prototype_share <= 1, "in (0, 1]"),
            ("segment_alpha", 0 <= self.segment_alpha <= 1, "in [0, 1]"),
            ("checkpoint_seconds", self.checkpoint_seconds > 0, "> 0")))


# -- feature helpers ----------------------------------------------------------------------
def init_features(count: int, dim: int, seed: int = 0, std: float = 1.0) -> mi.TensorXf:
    """Random features [N, D], N(0, std^2 / D) per coordinate (norm ~ std)."""
    rng = np.random.default_rng(seed)
    f = rng.normal(0.0, std / math.sqrt(dim), size=(count, dim)).astype(np.float32)
    return jit.tensor(f)


def normalize_rows(f: list) -> list:
    """Unit vectors from a feature given as D arrays [n]; a zero vector stays zero."""
    n2 = f[0] * f[0]
    for c in f[1:]:
        n2 = n2 + c * c
    inv = dr.select(n2 > 1e-24, dr.rsqrt(dr.maximum(n2, 1e-24)), 0.0)
    return [c * inv for c in f]


def gather_pixels(image: mi.TensorXf, pixels: mi.UInt32) -> list:
    """The D channels of ``image`` ([H, W, D], or [P, D] sampled pixels) at flat pixel
    (row) indices [n]: D arrays [n]."""
    d = image.shape[-1]
    return [dr.gather(mi.Float, image.array, pixels * d + k) for k in range(d)]


# -- losses (Eq. 8-11) --------------------------------------------------------------------
def contrastive_losses(f1: list, l1: mi.UInt32, f2: list, l2: mi.UInt32,
                       margin: float) -> tuple[mi.Float, mi.Float]:
    """(L_pos, L_neg) of Eq. 8 and 9 over all pairs of X1 (D arrays [n1], labels [n1]) and
    X2 (D arrays [n2], labels [n2]); features need not be normalised."""
    u1, u2 = normalize_rows(f1), normalize_rows(f2)
    sums = dr.custom(_PairSums, u1, u2, l1, l2, float(margin))
    inv = 1.0 / (dr.width(l1) * dr.width(l2))
    return -sums[0] * inv, sums[1] * inv


class _PairSums(dr.CustomOp):
    """[sum over pairs with equal labels of s_ij, sum over pairs with different labels and
    s_ij > margin of s_ij], s_ij = u1_i . u2_j, and its gradient, without the pair list.

    Written with gathers over the n1 * n2 pairs (1M at cpu-small), the forward kernel and
    the scatter-adds of its adjoint took 37 of stage 2's ~80 ms per iteration. Here one lane
    per row i walks the other set in a symbolic loop, reading the same j in every lane (its
    features and label packed, ``core.packed``: one packet gather): u1_i and the row's
    gradient stay in registers, nothing is scattered, and the backward walks the
    transposed loop for u2's gradient. The mask uses s_ij as computed (detached), as Eq.
    9's hinge does."""

    def eval(self, u1, u2, l1, l2, margin):
        self.args = (u1, u2, l1, l2, jit.opaque(margin))
        pos, neg = self._rows(u1, u2, l1, l2, self.args[4], None)
        return mi.Float(dr.sum(pos)), mi.Float(dr.sum(neg))

    @staticmethod
    def _rows(ua, ub, la, lb, margin, coef):
        """Per lane (row of ``ua``): the pos and neg sums over ``ub`` (``coef`` None), or
        the gradient sum_j c_ij ub_j with c_ij = coef[0] on equal labels, coef[1] on
        different ones above the margin."""
        n = dr.width(la)
        count = dr.opaque(mi.UInt32, dr.width(lb))
        d = len(ua)
        rows = Packed.of([*ub, dr.reinterpret_array(mi.Float, lb)])
        if coef is None:
            acc = [dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)]
        else:
            acc = [dr.zeros(mi.Float, n) for _ in range(d)]

        def cond(j, acc):
            return j < count

        def body(j, acc):
            *v, lbj = rows.read(j, n)
            sij = ua[0] * v[0]
            for a, b in zip(ua[1:], v[1:], strict=True):
                sij = dr.fma(a, b, sij)
            same = la == dr.reinterpret_array(mi.UInt32, lbj)
            neg = ~same & (sij > margin)
            if coef is None:
                acc = [acc[0] + dr.select(same, sij, 0.0), acc[1] + dr.select(neg, sij, 0.0)]
            else:
                c = dr.select(same, coef[0], dr.select(neg, coef[1], 0.0))
                acc = [dr.fma(c, b, a) for a, b in zip(acc, v, strict=True)]
            return j + 1, acc

        _, acc = dr.while_loop((dr.zeros(mi.UInt32, n), acc), cond, body,
                               label="segmentation_pair_sums")
        return acc

    def backward(self):
        u1, u2, l1, l2, margin = self.args
        g_pos, g_neg = (dr.detach(g) for g in self.grad_out())
        coef = (mi.Float(g_pos), mi.Float(g_neg))  # dL/ds_ij on equal / negative pairs
        self.set_grad_in("u1", self._rows(u1, u2, l1, l2, margin, coef))
        self.set_grad_in("u2", self._rows(u2, u1, l2, l1, margin, coef))

    def name(self):
        return "segmentation_pair_sums"


def mask_loss(f: list, labels: mi.UInt32, n_labels: int,
              temperature: float) -> tuple[mi.Float, mi.Float]:
    """(L_intra, L_inter) of Eq. 10 for features (D arrays [n]) with labels in
    [1, n_labels] (0 is not allowed here: pass labelled samples only)."""
    u = normalize_rows(f)
    nl = n_labels + 1  # slot 0 unused, so labels index directly
    sums = []
    for c in u:
        acc = dr.zeros(mi.Float, nl)
        dr.scatter_reduce(dr.ReduceOp.Add, acc, c, labels)
        sums.append(acc)
    count = dr.zeros(mi.Float, nl)
    dr.scatter_reduce(dr.ReduceOp.Add, count, mi.Float(1.0), labels)
    present = dr.detach(count) > 0
    mu = normalize_rows(sums)  # [nl] each; the mean's direction = the sum's direction
    # intra: 1 - cos(F(x), mu_M(x))
    cos_own = mi.Float(0.0)
    for c, m in zip(u, mu, strict=True):
        cos_own = cos_own + c * dr.gather(mi.Float, m, labels)
    intra = dr.mean(1.0 - cos_own)
    # inter: soft maximum over l != k of cos(mu_k, mu_l), for present k, l
    kk = dr.arange(mi.UInt32, nl * nl)
    a = kk // nl
    b = kk - a * nl
    cos_ab = mi.Float(0.0)
    for m in mu:
        cos_ab = cos_ab + dr.gather(mi.Float, m, a) * dr.gather(mi.Float, m, b)
    valid = (dr.gather(mi.Bool, present, a) & dr.gather(mi.Bool, present, b)) & (a != b)
    e = dr.select(valid, dr.exp(cos_ab / temperature), 0.0)
    row = dr.zeros(mi.Float, nl)
    dr.scatter_reduce(dr.ReduceOp.Add, row, e, a)
    has_other = row > 0
    lse = dr.select(has_other, temperature * dr.log(dr.select(has_other, row, 1.0)), 0.0)
    n_rows = dr.sum(dr.select(dr.detach(has_other), mi.Float(1.0), 0.0))
    inter = dr.sum(lse) / dr.maximum(n_rows, 1.0)
    return intra, inter


def norm_loss(features: mi.TensorXf) -> mi.Float:
    """L_norm = mean_i (|f_i| - 1)^2 over per-surfel features [N, D]."""
    n, d = features.shape
    idx = dr.arange(mi.UInt32, n) * d
    n2 = mi.Float(0.0)
    for k in range(d):
        c = dr.gather(mi.Float, features.array, idx + k)
        n2 = n2 + c * c
    return dr.mean(dr.square(dr.sqrt(n2) - 1.0))


def segmentation_loss(image: mi.TensorXf, features: mi.TensorXf, pix1: mi.UInt32,
                      lab1: mi.UInt32, pix2: mi.UInt32, lab2: mi.UInt32, n_labels: int,
                      config: SegmentationConfig) -> dict[str, mi.Float]:
    """Eq. 11 for one view: ``image`` [H, W, D] (or [P, D]) rendered features,
    ``features`` [N, D] the per-surfel ones, X1/X2 as flat pixel (row) indices with labels
    in [1, n_labels]."""
    f1, f2 = gather_pixels(image, pix1), gather_pixels(image, pix2)
    pos, neg = contrastive_losses(f1, lab1, f2, lab2, config.margin)
    intra, inter = mask_loss([dr.concat([a, b]) for a, b in zip(f1, f2, strict=True)],
                             dr.concat([lab1, lab2]), n_labels, config.temperature)
    nrm = norm_loss(features)
    total = (pos + config.lambda_neg * neg + config.lambda_norm * nrm
             + config.lambda_mask * (intra + inter))
    return {"total": total, "pos": pos, "neg": neg, "intra": intra, "inter": inter,
            "norm": nrm}


# -- labels -------------------------------------------------------------------------------
@dataclasses.dataclass
class LabelSet:
    """Training labels prepared once (host side): per view the labelled pixels and their
    labels remapped to 1..n_labels (consistent across views)."""

    pixels: list[np.ndarray]  # per view [m_v] flat pixel indices (uint32)
    labels: list[np.ndarray]  # per view [m_v] labels in 1..n_labels (uint32)
    n_labels: int
    original: np.ndarray  # [n_labels] the input label value of each remapped label
    pixel_counts: np.ndarray  # [n_labels] labelled pixels over all views


def prepare_labels(label_maps: Sequence[np.ndarray], cameras: Sequence[Camera],
                   names: Sequence[str] | None = None) -> LabelSet:
    """Check the label maps ([H, W] int, 0 = unlabelled) against the cameras and remap them."""
    if len(label_maps) != len(cameras):
        raise ValueError(f"segmentation: {len(label_maps)} label maps for {len(cameras)} views")
    names = list(names) if names is not None else [f"view {i}" for i in range(len(cameras))]
    maps = []
    for m, cam, name in zip(label_maps, cameras, names, strict=True):
        m = np.asarray(m)
        if m.shape != (cam.height, cam.width):
            raise ValueError(f"segmentation: label map of {name} is {m.shape}, the camera is "
                             f"{cam.height}x{cam.width}")
        if not np.issubdtype(m.dtype, np.integer) or (m < 0).any():
            raise ValueError(f"segmentation: label map of {name} must hold integers >= 0")
        maps.append(m.astype(np.int64).ravel())
    values = np.unique(np.concatenate(maps))
    values = values[values > 0]
    if values.size == 0:
        raise ValueError("segmentation: every label map is empty (all 0 = unlabelled)")
    pixels, labels = [], []
    counts = np.zeros(values.size, np.int64)
    for m in maps:
        idx = np.flatnonzero(m > 0)
        lab = np.searchsorted(values, m[idx]) + 1
        counts += np.bincount(lab - 1, minlength=values.size)
        pixels.append(idx.astype(np.uint32))
        labels.append(lab.astype(np.uint32))
    return LabelSet(pixels, labels, int(values.size), values, counts)


def auto_k(labels: LabelSet, config: SegmentationConfig,
           min_label_fraction: float | None = None) -> int:
    """K: ``config.n_segments``, else the number of labels with enough pixels (at least
    ``min_label_pixels`` and ``min_label_fraction`` of them; default: the config's)."""
    if config.n_segments is not None:  # (>= 1: SegmentationConfig checks it)
        return int(config.n_segments)
    if min_label_fraction is None:
        min_label_fraction = config.min_label_fraction
    least = max(config.min_label_pixels,
                min_label_fraction * float(labels.pixel_counts.sum()))
    return max(1, int((labels.pixel_counts >= least).sum()))


def silhouette(x: np.ndarray, labels: np.ndarray) -> float:
    """Mean silhouette (Rousseeuw 1987) of points ``x`` [n, D] in clusters ``labels`` [n]
    (Euclidean); points alone in their cluster score 0. Needs 2 <= clusters < n."""
    x = np.asarray(x, dtype=np.float64)
    lab = np.unique(np.asarray(labels), return_inverse=True)[1].reshape(-1)
    k = int(lab.max(initial=-1)) + 1
    if k < 2 or k >= len(x):
        raise ValueError(f"silhouette: need 2 <= clusters < points, got {k} and {len(x)}")
    sq = (x * x).sum(1)
    d = np.sqrt(np.maximum(sq[:, None] + sq[None, :] - 2.0 * x @ x.T, 0.0))  # [n, n]
    np.fill_diagonal(d, 0.0)  # the Gram form leaves ~1e-8 there
    onehot = np.zeros((len(x), k))
    onehot[np.arange(len(x)), lab] = 1.0
    size = onehot.sum(0)  # [k]
    mean_to = (d @ onehot) / np.maximum(size, 1.0)  # [n, k] mean distance to each cluster
    own = size[lab]
    a = mean_to[np.arange(len(x)), lab] * own / np.maximum(own - 1.0, 1.0)  # excludes self
    other = np.where(onehot > 0, np.inf, mean_to)
    b = other.min(1)
    s = np.where(own > 1, (b - a) / np.maximum(np.maximum(a, b), 1e-12), 0.0)
    return float(s.mean())


def choose_k(features: np.ndarray, k_max: int, seen: np.ndarray | None = None,
             config: SegmentationConfig = SegmentationConfig()) -> tuple[int, dict[int, float]]:
    """(K, {K: silhouette}) for K in [2, k_max]: K-means (best of ``kmeans_restarts``
    k-means++ seedings) on ``silhouette_samples`` unit features [N, D] of the ``seen``
    surfels, K with the largest silhouette. k_max < 2: (max(k_max, 1), {})."""
    f = np.asarray(features, dtype=np.float64)
    u = f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)
    if seen is not None and np.any(seen):
        u = u[np.asarray(seen, bool)]
    rng = np.random.default_rng(config.seed)
    if len(u) > config.silhouette_samples:
        u = u[rng.choice(len(u), config.silhouette_samples, replace=False)]
    k_max = int(min(k_max, len(u) - 1))
    if k_max < 2:
        return max(k_max, 1), {}
    scores = {}
    for k in range(2, k_max + 1):
        lab, _ = kmeans_segments(u, k, seed=config.seed, restarts=config.kmeans_restarts,
                                 iterations=config.kmeans_iterations)
        scores[k] = silhouette(u, lab) if len(np.unique(lab)) >= 2 else -1.0
    return max(scores, key=lambda k: (scores[k], -k)), scores


# -- training -----------------------------------------------------------------------------
@dataclasses.dataclass
class TrainResult:
    features: np.ndarray  # [N, D] trained per-surfel features
    coverage: np.ndarray  # [N] summed splat weight over the rendered training views
    prototypes: np.ndarray  # [n_labels, D] summed unit rendered features per label (last
    # quarter of the iterations); a zero row: the label was never sampled then
    history: list  # (iteration, {term: value}) read every log_every iterations
    seconds: float


@dataclasses.dataclass
class FeatureState:
    """Everything a checkpoint of ``train_features`` needs to continue it exactly."""

    step: int  # finished iterations
    opt: mi.ad.Adam  # the features [N, D] and their Adam state
    coverage: mi.Float  # [N] summed splat weight so far
    proto: list  # D x mi.Float [n_labels + 1], the prototype sums so far
    rng: np.random.Generator  # view order and pixel samples
    order: list  # views left in the current shuffled round
    history: list
    elapsed: float = 0.0  # seconds of training before this process

    def to_checkpoint(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, JSON meta) for ``mi_shadowgs.io.checkpoint.save_checkpoint``."""
        from mi_shadowgs.core.optim import adam_to_numpy

        arrays = adam_to_numpy(self.opt, "adam/")
        arrays["coverage"] = np.asarray(self.coverage.numpy(), np.float32)
        arrays["proto"] = np.stack([np.asarray(c.numpy(), np.float32) for c in self.proto])
        arrays["order"] = np.asarray(self.order, np.int64)
        return arrays, {"step": self.step, "elapsed": self.elapsed, "history": self.history,
                        "rng": self.rng.bit_generator.state}

    @staticmethod
    def from_checkpoint(arrays: dict[str, np.ndarray], meta: dict) -> FeatureState:
        from mi_shadowgs.core.optim import adam_from_numpy

        opt = mi.ad.Adam(lr=0.0)
        adam_from_numpy(opt, arrays, "adam/")
        rng = np.random.default_rng()
        rng.bit_generator.state = meta["rng"]
        return FeatureState(int(meta["step"]), opt, jit.host(arrays["coverage"]),
                            [jit.host(c) for c in arrays["proto"]], rng,
                            arrays["order"].tolist(),
                            [(int(i), dict(v)) for i, v in meta["history"]],
                            float(meta["elapsed"]))


def train_features(surfels: Surfels, cameras: Sequence[Camera], labels: LabelSet,
                   config: SegmentationConfig, raster: RasterConfig = _RASTER,
                   progress: bool = True, state: FeatureState | None = None,
                   on_checkpoint=None) -> TrainResult:
    """Optimise per-surfel features (geometry fixed) with Eq. 11 for ``config.iterations``.

    Each iteration draws ``n_samples`` of the labelled pixels of one training view (views
    visited in shuffled rounds) and renders the features at those pixels alone
    (``rasterize(pixels=)``: the values of the whole image, at an eighth of its compositing
    at cpu-small). Views without labelled pixels are skipped. The per-surfel coverage (summed
    splat weight) of each visited view is added on every visit, as a sum over the visits'
    whole images; each view's is rendered once (the gradient of a constant channel) and kept.

    ``state`` (``FeatureState.from_checkpoint``) continues an interrupted run;
    ``on_checkpoint(state)`` is called every ``checkpoint_every`` iterations, every
    ``checkpoint_seconds``, at the end and at SIGINT/SIGTERM (``mi_shadowgs.io.interrupt``).
    """
    import time

    from tqdm import tqdm

    from mi_shadowgs.io.interrupt import CheckpointClock, raise_pending

    clock = CheckpointClock(config.checkpoint_every, config.checkpoint_seconds)
    if surfels.count == 0:
        raise ValueError("segmentation: the model has no surfels")
    usable = [v for v in range(len(cameras)) if labels.pixels[v].size >= 2]
    if not usable:
        raise ValueError("segmentation: no training view has labelled pixels")
    n = surfels.count
    geom = Surfels(dr.detach(surfels.position), dr.detach(surfels.log_scale),
                   dr.detach(surfels.rotation), dr.detach(surfels.opacity_logit))
    if state is None:
        state = _initial_state(surfels, labels, config)
    opt, rng, proto = state.opt, state.rng, state.proto
    proto_from = config.iterations - max(1, int(config.iterations * config.prototype_share))
    half = max(1, config.n_samples // 2)
    rows1 = dr.arange(mi.UInt32, half)  # X1 and X2: the sampled render's rows
    rows2 = dr.arange(mi.UInt32, half, 2 * half)
    view_coverage: dict[int, mi.Float] = {}  # view -> [N] its summed splat weights

    def coverage_of(v: int) -> mi.Float:
        if v not in view_coverage:
            ones = dr.ones(mi.TensorXf, (n, 1))
            dr.enable_grad(ones)
            img = rasterize(geom, cameras[v], {"cover": ones}, aovs=(), config=raster)
            # d(sum of the cover image)/d(ones_i) = surfel i's summed splat weight.
            dr.backward(dr.sum(img["cover"].array))
            view_coverage[v] = dr.detach(ones.grad.array)
            dr.eval(view_coverage[v])
        return view_coverage[v]

    t0 = time.perf_counter() - state.elapsed
    bar = tqdm(total=config.iterations, initial=state.step, desc="segment", unit="it",
               disable=not progress)
    with bar, clock.running():
        while state.step < config.iterations:
            it = state.step
            if not state.order:
                state.order = rng.permutation(usable).tolist()
            v = state.order.pop()
            feats = opt[FEATURE]
            # Samples drawn on the host from host-side label lists: no device read-back.
            pix, lab = labels.pixels[v], labels.labels[v]
            pick = rng.integers(0, pix.size, size=2 * half)
            img = rasterize(geom, cameras[v], {FEATURE: feats}, aovs=(), config=raster,
                            pixels=pix[pick])
            q1 = jit.host(lab[pick[:half]].astype(np.uint32), mi.UInt32)
            q2 = jit.host(lab[pick[half:]].astype(np.uint32), mi.UInt32)
            terms = segmentation_loss(img[FEATURE], feats, rows1, q1, rows2, q2,
                                      labels.n_labels, config)
            dr.backward(terms["total"])
            state.coverage = state.coverage + coverage_of(v)
            if it >= proto_from:  # label prototypes of the (nearly) trained features
                img_d = dr.detach(img[FEATURE])
                for p, q in ((rows1, q1), (rows2, q2)):
                    for acc, c in zip(proto, normalize_rows(gather_pixels(img_d, p)),
                                      strict=True):
                        dr.scatter_reduce(dr.ReduceOp.Add, acc, c, q)
            opt.step()
            dr.eval(state.coverage, proto)
            state.step = it + 1
            if state.step % config.log_every == 0 or state.step == config.iterations:
                vals = {k: float(t.numpy().reshape(-1)[0]) for k, t in terms.items()}
                state.history.append((state.step, vals))
                bar.set_postfix(loss=f"{vals['total']:.4f}")
            bar.update(1)
            if on_checkpoint and (clock.due(state.step) or state.step == config.iterations):
                state.elapsed = time.perf_counter() - t0
                on_checkpoint(state)
                clock.saved()
            raise_pending(f"segmentation stopped at iteration {state.step} of "
                          f"{config.iterations}" + (", checkpoint written" if on_checkpoint
                                                    else ""))
    return _train_result(state, n, config, time.perf_counter() - t0)


def _initial_state(surfels: Surfels, labels: LabelSet, config: SegmentationConfig
                   ) -> FeatureState:
    """The feature training's state before its first step: the model's features where it
    has them (of ``feature_dim``), else random ones."""
    n = surfels.count
    start = surfels.channels.get(FEATURE)
    if start is None or start.shape[1] != config.feature_dim:
        start = init_features(n, config.feature_dim, config.seed, config.init_std)
    opt = mi.ad.Adam(lr=config.lr)
    opt[FEATURE] = mi.TensorXf(start)
    return FeatureState(0, opt, dr.zeros(mi.Float, n),
                        [dr.zeros(mi.Float, labels.n_labels + 1)
                         for _ in range(config.feature_dim)],
                        np.random.default_rng(config.seed), [], [])


def _train_result(state: FeatureState, n: int, config: SegmentationConfig,
                  seconds: float) -> TrainResult:
    """The trained features, coverage and label prototypes as NumPy arrays."""
    out = np.asarray(state.opt[FEATURE].numpy(), dtype=np.float32).reshape(n,
                                                                            config.feature_dim)
    cov = np.asarray(state.coverage.numpy(), dtype=np.float64)
    protos = np.stack([np.asarray(c.numpy(), dtype=np.float64) for c in state.proto],
                      axis=-1)[1:]
    dr.sync_thread()
    return TrainResult(out, cov, protos, state.history, seconds)


# -- K-means ------------------------------------------------------------------------------
def kmeans_segments(features: np.ndarray, k: int, seen: np.ndarray | None = None,
                    seed: int = 0, restarts: int = 5, iterations: int = 50,
                    init: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(segment id per surfel [N] in 0..k-1, centres [k, D]) from K-means on the
    unit-normalised features [N, D] of the ``seen`` surfels; every surfel then takes its
    nearest centre.

    Seeding: ``init`` [k, D] (e.g. the label prototypes) when given, else the best of
    ``restarts`` k-means++ seedings. Prototype seeding matters when surfaces are very
    unequal in size: from random seeds, K-means lowers its cost more by splitting the large
    base than by giving a small part its own centre."""
    from scipy.cluster.vq import kmeans2

    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or not np.all(np.isfinite(f)):
        raise ValueError("kmeans_segments: features must be a finite [N, D] array")
    u = f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)
    fit = u if seen is None or not np.any(seen) else u[np.asarray(seen, bool)]
    k = int(min(k, len(fit)))
    if k < 1:
        raise ValueError("kmeans_segments: no surfels to cluster")
    rng = np.random.default_rng(seed)
    best, best_cost = None, np.inf
    if init is not None:
        c0 = np.asarray(init, dtype=np.float64)
        if c0.shape != (k, u.shape[1]):
            raise ValueError(f"kmeans_segments: init must be [{k}, {u.shape[1]}], got "
                             f"{c0.shape}")
        best, _ = kmeans2(fit, c0, iter=iterations, minit="matrix", missing="warn")
    for _ in range(max(1, restarts) if init is None else 0):
        centres, lab = kmeans2(fit, k, iter=iterations, minit="++", seed=rng, missing="warn")
        cost = float(((fit - centres[lab]) ** 2).sum())
        if cost < best_cost:
            best, best_cost = centres, cost
    d2 = ((u[:, None, :] - best[None, :, :]) ** 2).sum(-1) if len(u) * k <= 5e7 else None
    if d2 is None:  # large models: assign in chunks
        seg = np.concatenate([((c[:, None, :] - best[None]) ** 2).sum(-1).argmin(1)
                              for c in np.array_split(u, max(1, len(u) * k // 10_000_000))])
    else:
        seg = d2.argmin(1)
    return seg.astype(np.int32), best


def prototype_seeds(prototypes: np.ndarray, labels: LabelSet, k: int) -> np.ndarray | None:
    """K-means seeds [k, D] from the label prototypes: the unit prototypes of the k labels
    with the most pixels, or None when fewer than k labels were sampled."""
    p = np.asarray(prototypes, dtype=np.float64)
    norm = np.linalg.norm(p, axis=1)
    ok = np.flatnonzero(norm > 0)
    if ok.size < k:
        return None
    top = ok[np.argsort(-labels.pixel_counts[ok], kind="stable")[:k]]
    return p[top] / norm[top, None]


@dataclasses.dataclass
class SegmentationResult:
    surfels: Surfels  # the input with channels "feature" [N, D] and "segment" [N, 1]
    segments: np.ndarray  # [N] int, 0..k-1
    k: int
    train: TrainResult
    k_scores: dict | None = None  # {K: silhouette} when K was chosen by silhouette
    planes: list | None = None  # the segments' plane fits (``planes.planar_shading_normals``)
    support: dict | None = None  # the support's plane where segments were split at it


def segment_surfels(surfels: Surfels, cameras: Sequence[Camera],
                    label_maps: Sequence[np.ndarray], config: SegmentationConfig,
                    raster: RasterConfig = _RASTER, progress: bool = True,
                    names: Sequence[str] | None = None, state: FeatureState | None = None,
                    on_checkpoint=None, min_label_fraction: float | None = None,
                    split_support: str = "off") -> SegmentationResult:
    """The whole stage: train features on ``label_maps`` (one per camera), then K-means,
    then the segments split at the support's plane (``planes.support_split``) where
    ``split_support`` says: "on", or "auto" when the labels gave one segment and
    ``n_segments`` did not set it (see ``SegmentationConfig.support_split``). ``state`` and
    ``on_checkpoint``: see ``train_features``; ``min_label_fraction``: see ``auto_k``."""
    labels = prepare_labels(label_maps, cameras, names)
    k = auto_k(labels, config, min_label_fraction)
    tr = train_features(surfels, cameras, labels, config, raster, progress, state,
                        on_checkpoint)
    seen = tr.coverage >= config.min_coverage
    scores = None
    if config.n_segments is None and config.k_select == "silhouette":
        k, scores = choose_k(tr.features, k, seen, config)
    seeds = prototype_seeds(tr.prototypes, labels, k)  # None: k-means++ seeding
    seg, _ = kmeans_segments(tr.features, k, seen, config.seed, config.kmeans_restarts,
                             config.kmeans_iterations if seeds is None
                             else config.prototype_iterations, seeds)
    support = None
    if support_split_applies(split_support, k, forced=config.n_segments is not None):
        seg, support = support_split(surfels.to_numpy()["position"], seg, config.seed)
        k = int(seg.max()) + 1 if support else k
    out = surfels.with_channels({FEATURE: jit.tensor(tr.features),
                                 SEGMENT: jit.tensor(seg[:, None])})
    out, planes = planar_shading_normals(out, seg, config.planes)
    return SegmentationResult(out, seg, k, tr, scores, planes, support)
