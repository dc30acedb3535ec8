"""Stage 2: contrastive surfel features, K-means segments, metrics, and the CLI."""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowgs import presets as run_presets
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.stages.segmentation import features as seg
from mi_shadowgs.stages.segmentation import maps as seg_maps
from mi_shadowgs.stages.segmentation import metrics as seg_metrics

# Float32 kernels against float64 references: sums of a few thousand O(1) terms carry a
# relative rounding error of ~1e-6; 1e-5 leaves margin without hiding a wrong term.
RTOL = 1e-5


# -- metrics: hand-computed cases ---------------------------------------------------------
def test_ari_hand_cases():
    # a = {0,0,1,1}, b = {0,0,1,2}: index 1, sum_a 2, sum_b 1, C(4,2) = 6 ->
    # (1 - 1/3) / (3/2 - 1/3) = 4/7.
    assert seg_metrics.adjusted_rand_index([0, 0, 1, 1], [0, 0, 1, 2]) == pytest.approx(4 / 7,
                                                                                  1e-12)
    # index 2, sum_a 6, sum_b 3, C(6,2) = 15: (2 - 1.2) / (4.5 - 1.2) = 8/33.
    a, b = [0, 0, 0, 1, 1, 1], [0, 0, 1, 1, 2, 2]
    assert seg_metrics.adjusted_rand_index(a, b) == pytest.approx(8 / 33, 1e-12)
    # Renaming labels changes nothing; the index is symmetric.
    assert seg_metrics.adjusted_rand_index([3, 3, 7, 7, 9], [1, 1, 0, 0, 5]) == 1.0
    assert seg_metrics.adjusted_rand_index(b, a) == pytest.approx(8 / 33, 1e-12)
    # Independent labelings score about 0 (expected value 0; |ARI| < 0.01 at n = 20000).
    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 4, 20000), rng.integers(0, 4, 20000)
    assert abs(seg_metrics.adjusted_rand_index(x, y)) < 0.01


def test_miou_hungarian_hand_cases():
    gt = [1, 1, 1, 2, 2, 3]
    pred = [5, 5, 7, 7, 7, 9]
    # IoU(1,5) = 2/3, IoU(2,7) = 2/3, IoU(3,9) = 1 -> (2/3 + 2/3 + 1) / 3 = 7/9.
    miou, match = seg_metrics.miou_hungarian(pred, gt)
    assert miou == pytest.approx(7 / 9, 1e-12)
    assert match == {1: 5, 2: 7, 3: 9}
    # One predicted class for two ground-truth ones: IoU 1/2 matched, the other counts 0.
    miou, _ = seg_metrics.miou_hungarian([0, 0, 0, 0], [1, 1, 2, 2])
    assert miou == pytest.approx(0.25, 1e-12)


def test_evaluate_maps_excludes_background():
    gt = np.array([[0, 1, 1], [0, 2, 2]])
    pred = np.array([[4, 3, 3], [4, 0, 0]])  # background pixels of gt are ignored
    m = seg_metrics.evaluate_maps([pred], [gt])
    assert m["ari"] == 1.0 and m["miou"] == 1.0 and m["pixels"] == 4
    assert m["pred_background"] == pytest.approx(0.5)


def test_shadow_consistency_counts():
    gt = np.full((2, 4), 5)
    vis = np.ones((2, 4, 2))
    vis[1, :, 0] = 0.0  # bottom row shadowed from light 0
    pred = np.array([[2, 2, 2, 2], [2, 2, 3, 3]])
    r = seg_metrics.shadow_consistency([pred], [gt], [vis], 5)
    assert r["segment"] == 2 and r["lit_fraction"] == 1.0 and r["shadow_fraction"] == 0.5
    # No shadowed pixel: its own error, which the stage reports as a fact of the views; a
    # malformed input (maps of other sizes) is another error, not reported as that one.
    with pytest.raises(seg_metrics.NoPixelsToCompare, match="no shadowed pixel"):
        seg_metrics.shadow_consistency([pred], [gt], [np.ones((2, 4, 2))], 5)
    with pytest.raises(ValueError) as err:
        seg_metrics.shadow_consistency([pred], [gt[:1]], [vis], 5)
    assert not isinstance(err.value, seg_metrics.NoPixelsToCompare)


# -- loss kernels against float64 NumPy -----------------------------------------------------
def _ref_losses(f1, l1, f2, l2, margin, temperature):
    u1 = f1 / np.linalg.norm(f1, axis=1, keepdims=True)
    u2 = f2 / np.linalg.norm(f2, axis=1, keepdims=True)
    s = u1 @ u2.T
    same = l1[:, None] == l2[None, :]
    pos = -(s * same).sum() / s.size
    neg = (s * (~same & (s > margin))).sum() / s.size
    f = np.concatenate([u1, u2])
    lab = np.concatenate([l1, l2])
    ks = np.unique(lab)
    mu = {k: f[lab == k].mean(0) / np.linalg.norm(f[lab == k].mean(0)) for k in ks}
    intra = np.mean([1.0 - f[i] @ mu[lab[i]] for i in range(len(lab))])
    inter = 0.0
    if len(ks) > 1:
        inter = np.mean([temperature * math.log(sum(math.exp(mu[a] @ mu[b] / temperature)
                                                    for b in ks if b != a)) for a in ks])
    return pos, neg, intra, inter


def _cols(a):
    return [mi.Float(a[:, k].astype(np.float32)) for k in range(a.shape[1])]


@pytest.mark.parametrize("margin", [-2.0, 0.2, 0.5])
def test_losses_match_numpy(margin):
    rng = np.random.default_rng(1)
    n1, n2, d, nl = 37, 29, 6, 5
    f1, f2 = rng.normal(size=(n1, d)), rng.normal(size=(n2, d))
    l1, l2 = rng.integers(1, nl + 1, n1), rng.integers(1, nl, n2)  # label 5 only in X1
    f1 = f1.astype(np.float32).astype(np.float64)
    f2 = f2.astype(np.float32).astype(np.float64)
    pos, neg = seg.contrastive_losses(_cols(f1), mi.UInt32(l1), _cols(f2), mi.UInt32(l2),
                                      margin)
    intra, inter = seg.mask_loss(_cols(np.concatenate([f1, f2])),
                                 mi.UInt32(np.concatenate([l1, l2])), nl + 2, 0.3)
    ref = _ref_losses(f1, l1, f2, l2, margin, 0.3)
    got = [float(x.numpy()[0]) for x in (pos, neg, intra, inter)]
    np.testing.assert_allclose(got, ref, rtol=RTOL, atol=1e-6)


@pytest.mark.parametrize("margin", [-2.0, 0.2])
def test_contrastive_gradient_matches_float64_differences(margin):
    # The pair sums' hand-written backward (two transposed loops, no pair list) against
    # central differences of the float64 NumPy losses: h = 1e-6 leaves ~1e-10 of rounding
    # and truncation; a margin-0.2 hinge pair within h of the margin would flip (none is:
    # the seed's closest is checked below). The float32 AD sums 29-37 terms of O(1/n1n2):
    # 1e-5 of the largest entry covers its rounding.
    rng = np.random.default_rng(6)
    n1, n2, d = 37, 29, 6
    f1, f2 = rng.normal(size=(n1, d)), rng.normal(size=(n2, d))
    l1, l2 = rng.integers(1, 5, n1), rng.integers(1, 5, n2)
    f1 = f1.astype(np.float32).astype(np.float64)
    f2 = f2.astype(np.float32).astype(np.float64)
    u1 = f1 / np.linalg.norm(f1, axis=1, keepdims=True)
    u2 = f2 / np.linalg.norm(f2, axis=1, keepdims=True)
    assert np.abs(u1 @ u2.T - margin).min() > 1e-4

    def ref(a, b):
        pos, neg, _, _ = _ref_losses(a, l1, b, l2, margin, 0.3)
        return pos + 0.7 * neg

    c1, c2 = _cols(f1), _cols(f2)
    for c in c1 + c2:
        dr.enable_grad(c)
    pos, neg = seg.contrastive_losses(c1, mi.UInt32(l1), c2, mi.UInt32(l2), margin)
    dr.backward(pos + 0.7 * neg)
    got = [np.stack([np.asarray(dr.grad(c), np.float64) for c in cs], 1) for cs in (c1, c2)]
    h = 1e-6
    for which, (f, g) in enumerate(zip((f1, f2), got, strict=True)):
        fd = np.zeros_like(f)
        for i in range(f.shape[0]):
            for k in range(d):
                fp, fm = f.copy(), f.copy()
                fp[i, k] += h
                fm[i, k] -= h
                args_p = (fp, f2) if which == 0 else (f1, fp)
                args_m = (fm, f2) if which == 0 else (f1, fm)
                fd[i, k] = (ref(*args_p) - ref(*args_m)) / (2 * h)
        assert np.abs(fd).max() > 1e-4  # not vacuous
        np.testing.assert_allclose(g, fd, atol=1e-5 * np.abs(fd).max())


def test_mask_loss_single_label_has_no_inter_term():
    rng = np.random.default_rng(2)
    f = rng.normal(size=(10, 4))
    intra, inter = seg.mask_loss(_cols(f), mi.UInt32(np.full(10, 3)), 4, 0.3)
    assert float(inter.numpy()[0]) == 0.0
    assert float(intra.numpy()[0]) > 0.0


def test_norm_loss_matches_numpy():
    rng = np.random.default_rng(3)
    f = rng.normal(size=(50, 7)).astype(np.float32)
    got = float(seg.norm_loss(mi.TensorXf(f)).numpy()[0])
    ref = np.mean((np.linalg.norm(f.astype(np.float64), axis=1) - 1.0) ** 2)
    assert got == pytest.approx(ref, rel=RTOL)


# -- gradient through the rasterizer against central differences ----------------------------
def _tiny_scene():
    """Two overlapping rows of surfels facing a 12x12 camera."""
    rng = np.random.default_rng(4)
    n = 12
    pos = np.stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.6, 0.6, n),
                    rng.uniform(-0.1, 0.1, n)], -1)
    surf = Surfels.from_numpy(pos, np.full((n, 2), 0.3), np.tile([1.0, 0, 0, 0], (n, 1)),
                              np.full(n, 0.7))
    c2w = np.eye(4)
    c2w[2, 3] = 3.0  # on +Z looking down -Z (OpenGL)
    return surf, Camera(c2w, 12, 12, fov_x=math.radians(40.0))


def test_segmentation_loss_gradient_matches_central_differences():
    surf, cam = _tiny_scene()
    n, d = surf.count, 4
    rng = np.random.default_rng(5)
    f0 = rng.normal(size=(n, d)).astype(np.float32)
    pix = np.arange(cam.width * cam.height, dtype=np.uint32)
    rng.shuffle(pix)
    p1, p2 = mi.UInt32(pix[:30]), mi.UInt32(pix[30:60])
    lab = rng.integers(1, 4, 60).astype(np.uint32)
    q1, q2 = mi.UInt32(lab[:30]), mi.UInt32(lab[30:])
    # margin -2: every negative pair is active, so the loss is smooth in the features.
    cfg = seg.SegmentationConfig(margin=-2.0, lambda_norm=0.1)
    from mi_shadowgs.core.raster import rasterize

    def loss(f, grad=False):
        t = mi.TensorXf(f)
        if grad:
            dr.enable_grad(t)
        img = rasterize(surf, cam, {"feature": t}, aovs=())["feature"]
        val = seg.segmentation_loss(img, t, p1, q1, p2, q2, 4, cfg)["total"]
        if grad:
            dr.backward(val)
            return np.asarray(t.grad.numpy(), np.float64).reshape(n, d)
        return float(val.numpy()[0])

    g = loss(f0, grad=True)
    h = 1e-2  # float32 loss ~1: rounding error 1e-7 / h = 1e-5, truncation ~h^2 = 1e-4
    checked = 0
    for i, k in [(0, 0), (1, 2), (3, 1), (5, 3), (7, 0), (11, 2)]:
        fp, fm = f0.copy(), f0.copy()
        fp[i, k] += h
        fm[i, k] -= h
        fd = (loss(fp) - loss(fm)) / (2 * h)
        # 3e-4 absolute: the truncation and rounding bounds above, with a 2.5x margin (the
        # errors measured are ~5e-6), under a tenth of the gradients checked (2e-3 to 3e-2).
        assert g[i, k] == pytest.approx(fd, abs=3e-4), (i, k, g[i, k], fd)
        checked += abs(fd) > 3e-3
    assert checked >= 3  # the check is not vacuous: most entries have a real gradient


# -- labels, K-means ---------------------------------------------------------------------
def test_prepare_labels_remaps_and_checks():
    cam = Camera(np.eye(4), 3, 2, fov_x=1.0)
    maps = [np.array([[0, 7, 7], [9, 0, 2]]), np.array([[2, 2, 0], [0, 0, 0]])]
    ls = seg.prepare_labels(maps, [cam, cam])
    assert ls.n_labels == 3 and list(ls.original) == [2, 7, 9]
    assert list(ls.pixels[0]) == [1, 2, 3, 5] and list(ls.labels[0]) == [2, 2, 3, 1]
    assert list(ls.pixel_counts) == [3, 2, 1]
    with pytest.raises(ValueError, match="view 1"):
        seg.prepare_labels([maps[0], np.zeros((3, 3), int)], [cam, cam])
    with pytest.raises(ValueError, match="empty"):
        seg.prepare_labels([np.zeros((2, 3), int)], [cam])
    with pytest.raises(ValueError, match="integers >= 0"):
        seg.prepare_labels([-np.ones((2, 3), int)], [cam])


def test_kmeans_prototype_seeds_keep_a_small_cluster():
    rng = np.random.default_rng(6)
    big = np.array([1.0, 0, 0]) + rng.normal(0, 0.2, (3000, 3))
    mid = np.array([0, 1.0, 0]) + rng.normal(0, 0.05, (300, 3))
    tiny = np.array([0, 0, 1.0]) + rng.normal(0, 0.05, (8, 3))
    f = np.concatenate([big, mid, tiny])
    truth = np.repeat([0, 1, 2], [3000, 300, 8])
    seeds = np.eye(3)
    lab, _ = seg.kmeans_segments(f, 3, init=seeds)
    assert seg_metrics.adjusted_rand_index(lab, truth) > 0.99
    # Same seed, same answer.
    a, _ = seg.kmeans_segments(f, 3, seed=3)
    b, _ = seg.kmeans_segments(f, 3, seed=3)
    assert np.array_equal(a, b)


def test_kmeans_from_prototypes_one_lloyd_step_against_numpy():
    """``kmeans_segments`` seeded with ``init`` at one iteration: every surfel goes to its
    nearest seed, the centres become the means of their surfels' unit features, and every
    surfel then goes to its nearest centre (float64, written out here)."""
    rng = np.random.default_rng(8)
    f = rng.normal(0, 1, (500, 4))
    u = f / np.linalg.norm(f, axis=1, keepdims=True)
    seeds = u[[3, 77, 150]]

    def nearest(c):
        return ((u[:, None] - c[None]) ** 2).sum(-1).argmin(1)

    first = nearest(seeds)
    centres = np.stack([u[first == k].mean(0) for k in range(3)])
    lab, got = seg.kmeans_segments(f, 3, init=seeds, iterations=1)
    np.testing.assert_allclose(got, centres, atol=1e-12)
    np.testing.assert_array_equal(lab, nearest(centres))


def test_kmeans_steps_from_the_prototypes_drift_into_a_spread_surface():
    """Why ``cpu-small`` takes one K-means step from the label prototypes: a small part (40
    surfels, the default scene's pillar cap) just past the end of a spread surface (an arc
    of 60 deg, the pillar's side in shade and light) takes more of the surface's end at
    each further step, as its centre follows what it took (on the default scene at stage
    seed 5: the cap's IoU 0.18, mIoU 0.795; one step: 0.970)."""
    rng = np.random.default_rng(3)
    t = np.radians(rng.uniform(-30, 30, 2000))
    arc = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], -1) + rng.normal(0, 0.01,
                                                                             (2000, 3))
    cap = np.array([np.cos(np.radians(38)), np.sin(np.radians(38)), 0.0]) + \
        rng.normal(0, 0.01, (40, 3))
    far = np.array([0, 0, 1.0]) + rng.normal(0, 0.05, (1000, 3))
    f = np.concatenate([arc, cap, far])
    truth = np.repeat([0, 1, 2], [2000, 40, 1000])
    u = f / np.linalg.norm(f, axis=1, keepdims=True)
    protos = np.stack([u[truth == k].mean(0) for k in range(3)])
    protos /= np.linalg.norm(protos, axis=1, keepdims=True)
    taken = {}
    for steps in (1, 2, 5, 50):
        lab, _ = seg.kmeans_segments(f, 3, init=protos, iterations=steps)
        taken[steps] = int(np.sum((truth == 0) & (lab == lab[2000])))  # arc labelled as cap
    assert taken[1] < taken[2] < taken[5] <= taken[50], taken
    assert taken[50] > 1.3 * taken[1], taken


def test_prototype_iterations_only_from_the_prototypes(monkeypatch):
    """``prototype_iterations`` sets K-means' steps when it starts from the label
    prototypes; with more segments than labels (no seed for some) it starts from k-means++
    and runs ``kmeans_iterations``, as one step from random seeds would leave them where
    they fell."""
    surf, _ = _plane(12, 0.12)
    c2w = np.eye(4)
    c2w[2, 3] = 3.0
    cam = Camera(c2w, 24, 24, fov_x=math.radians(40.0))
    label_map = np.where(np.arange(24)[None, :] < 12, 1, 2).repeat(24, 0)  # [24, 24]
    calls = []
    real = seg.kmeans_segments

    def recording(features, k, seen=None, seed=0, restarts=5, iterations=50, init=None):
        calls.append((k, iterations, init is not None))
        return real(features, k, seen, seed, restarts, iterations, init)

    monkeypatch.setattr(seg, "kmeans_segments", recording)
    cfg = seg.SegmentationConfig(iterations=8, lr=0.02, n_samples=128, feature_dim=4,
                                 kmeans_iterations=7, prototype_iterations=1)
    seg.segment_surfels(surf, [cam], [label_map], cfg, progress=False)
    seg.segment_surfels(surf, [cam], [label_map], dataclasses.replace(cfg, n_segments=3),
                        progress=False)
    assert calls == [(2, 1, True), (3, 7, False)]


def test_auto_k_counts_labels_with_enough_pixels():
    ls = seg.LabelSet([], [], 3, np.array([1, 2, 3]), np.array([500, 5, 40]))
    cfg = seg.SegmentationConfig(min_label_pixels=20)
    assert seg.auto_k(ls, cfg) == 2
    assert seg.auto_k(ls, seg.SegmentationConfig(n_segments=7)) == 7
    # 40 of 545 pixels is 7.3 %: dropped at a 10 % share.
    assert seg.auto_k(ls, seg.SegmentationConfig(min_label_fraction=0.1)) == 1


def test_silhouette_matches_brute_force():
    rng = np.random.default_rng(7)
    x = rng.normal(size=(23, 3))
    lab = rng.integers(0, 4, 23)
    lab[:4] = [0, 1, 2, 3]
    lab[22] = 9  # a cluster of one point: scores 0
    ref = []
    for i in range(len(x)):
        d = np.linalg.norm(x - x[i], axis=1)
        own = lab == lab[i]
        if own.sum() == 1:
            ref.append(0.0)
            continue
        a = d[own].sum() / (own.sum() - 1)
        b = min(d[lab == c].mean() for c in np.unique(lab) if c != lab[i])
        ref.append((b - a) / max(a, b))
    # rel 1e-8: the distances come from the Gram form |x|^2 + |y|^2 - 2 x.y (cancellation).
    assert seg.silhouette(x, lab) == pytest.approx(np.mean(ref), rel=1e-8)
    with pytest.raises(ValueError, match="clusters"):
        seg.silhouette(x, np.zeros(23, int))


def test_choose_k_ignores_labels_the_features_do_not_separate():
    # Five labels from images alone, but the trained features form three clusters (two
    # pairs of labels, e.g. a surface in and out of shadow, got the same feature): K = 3.
    rng = np.random.default_rng(8)
    centres = np.eye(6)[:3]
    f = np.concatenate([c + rng.normal(0, 0.05, (300, 6)) for c in centres])
    cfg = seg.SegmentationConfig(k_select="silhouette", silhouette_samples=500)
    k, scores = seg.choose_k(f, 5, config=cfg)
    assert k == 3 and set(scores) == {2, 3, 4, 5}
    # Six well-separated clusters: the cap (the label count) wins.
    f6 = np.concatenate([c + rng.normal(0, 0.05, (100, 6)) for c in np.eye(6)])
    assert seg.choose_k(f6, 6, config=cfg)[0] == 6
    assert seg.choose_k(f6, 1, config=cfg) == (1, {})


def test_label_count_keeps_close_materials_apart_where_silhouette_merges_them():
    """Why K is the label count: with a dominant surface (the base) and two materials whose
    features lie close (the red sphere and the yellow pillar of the default scene), the
    silhouette prefers fewer clusters and merges them, while K-means at the label count,
    seeded by the label prototypes as stage 2 does, recovers every material."""
    rng = np.random.default_rng(3)
    centres = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1],
                        [0, 0, 0.8, 0.6]], float)  # the last two 37 degrees apart
    sizes = [3000, 200, 200, 150, 150]
    f = np.concatenate([c + rng.normal(0, 0.08, (n, 4))
                        for c, n in zip(centres, sizes, strict=True)])
    truth = np.repeat(np.arange(5), sizes)
    cfg = seg.SegmentationConfig(k_select="silhouette", silhouette_samples=1500)
    k_sil, _ = seg.choose_k(f, 5, config=cfg)
    assert k_sil < 5  # the silhouette merges the close pair
    lab, _ = seg.kmeans_segments(f, 5, init=centres)
    assert seg_metrics.adjusted_rand_index(lab, truth) > 0.99


def test_k_selection_settings():
    from mi_shadowgs.cli import build_parser
    from mi_shadowgs.presets import build
    from mi_shadowgs.stages.segmentation import label_fraction

    # K = the label count for material ids and for masks from images alone (whose checks
    # drop leaky regions and slivers: min_label_fraction); silhouette only when asked.
    config = build("cpu-small").segmentation
    assert config.k_select == "labels"
    assert label_fraction(config, "chromaticity") == 0.005
    assert label_fraction(config, "material") == 0.0
    assert build("cpu-small", {"segmentation": {"k_select": "silhouette"}}
                 ).segmentation.k_select == "silhouette"
    args = build_parser().parse_args(["segment", "m.ply", "--data", "d", "--out", "o",
                                      "--segments", "4"])
    assert args.k == 4
    with pytest.raises(ValueError, match="k_select"):
        seg.segment_surfels(None, [], [], seg.SegmentationConfig(k_select="bic"))


def test_presets():
    assert run_presets.segmentation_config("paper") == seg.SegmentationConfig()
    p = run_presets.segmentation_config("paper")
    assert (p.lambda_neg, p.lambda_norm, p.lambda_mask, p.lr, p.temperature, p.n_samples,
            p.iterations) == (0.1, 1e-4, 0.5, 0.005, 0.3, 10_000, 1000)
    assert run_presets.segmentation_config("cpu-small").iterations < p.iterations


# -- the stage end to end on a synthetic two-material plane ---------------------------------
def _plane(side: int, scale: float):
    """(surfels on a side x side grid over [-1, 1]^2 at z = 0, facing +Z; positions [N, 3])."""
    g = np.linspace(-1.0, 1.0, side)
    xx, yy = np.meshgrid(g, g)
    pos = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], -1)
    n = len(pos)
    return Surfels.from_numpy(pos, np.full((n, 2), scale), np.tile([1.0, 0, 0, 0], (n, 1)),
                              np.full(n, 0.95)), pos


def test_two_material_plane_is_segmented():
    surf, pos = _plane(24, 0.06)
    n = len(pos)
    cams = []
    for ang in (-0.3, 0.0, 0.3):
        c2w = np.eye(4)
        c2w[:3, :3] = [[math.cos(ang), 0, math.sin(ang)], [0, 1, 0],
                       [-math.sin(ang), 0, math.cos(ang)]]
        c2w[:3, 3] = [3.0 * math.sin(ang), 0.0, 3.0 * math.cos(ang)]
        cams.append(Camera(c2w, 32, 32, fov_x=math.radians(30.0)))
    # Label maps: left of x = 0 is material 1, right is 2; from each camera's own render.
    side = mi.TensorXf((pos[:, :1] > 0).astype(np.float32))
    from mi_shadowgs.core.raster import rasterize

    maps = []
    for c in cams:
        out = rasterize(surf, c, {"side": side}, aovs=("alpha",))
        a = out["alpha"].numpy()[..., 0]
        s = out["side"].numpy()[..., 0] / np.maximum(a, 1e-6)
        maps.append(np.where(a > 0.5, np.where(s > 0.5, 2, 1), 0))
    cfg = seg.SegmentationConfig(iterations=40, lr=0.02, n_samples=256, feature_dim=8)
    res = seg.segment_surfels(surf, cams, maps, cfg, progress=False)
    assert res.k == 2
    truth = (pos[:, 0] > 0).astype(int)
    # Surfels on the boundary column straddle both labels, and the plane's rim is outside
    # every view (random features): leave both out. Of the rest, surfels at a frame edge,
    # seen by a sliver of one view, get few updates: 0.97 allows ~2 of ~350 to be wrong.
    away = (np.abs(pos[:, 0]) > 0.1) & (res.train.coverage >= cfg.min_coverage)
    assert away.sum() > 300
    assert seg_metrics.adjusted_rand_index(res.segments[away], truth[away]) > 0.97
    pred = seg_maps.render_segment_map(res.surfels, res.segments, res.k, cams[1])
    m = seg_metrics.evaluate_maps([pred], [maps[1]])
    assert m["ari"] > 0.9  # only the pixels of the boundary column may differ
    assert res.surfels.channels["segment"].shape == (n, 1)
    assert res.surfels.channels["feature"].shape == (n, 8)
