"""Mask sources for stage 2: material ids and the shadow-invariant chromaticity segmentation,
and the ``segment`` command on a tiny dataset."""

from __future__ import annotations

import json

import numpy as np
import pytest
from segmentation_fixtures import standin_surfels, tiny_dataset

from mi_shadowgs.dataset.loader import load_dataset
from mi_shadowgs.stages.segmentation import masks
from mi_shadowgs.stages.segmentation import metrics as seg_metrics


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return tiny_dataset(tmp_path_factory.mktemp("seg") / "tiny")


def test_chromaticity_matches_numpy():
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 2, (4, 5, 3))
    ref = (img + 1e-3 / 3) / (img.sum(-1, keepdims=True) + 1e-3)
    np.testing.assert_allclose(masks.chromaticity(img, 1e-3), ref, rtol=1e-12)
    # Scaling the intensity (a white-light shadow) leaves it unchanged up to the eps share.
    np.testing.assert_allclose(masks.chromaticity(0.2 * img, 0.0), masks.chromaticity(img, 0.0),
                               rtol=1e-12)


def _synthetic_view(seed=1):
    """A grey-green base (albedo a) lit, with a hard shadow (irradiance x0.25) and a red disk;
    path-tracing-like noise of 3% per channel."""
    rng = np.random.default_rng(seed)
    h = w = 64
    yy, xx = np.mgrid[:h, :w]
    albedo = np.tile([0.45, 0.55, 0.40], (h, w, 1))
    disk = (yy - 20) ** 2 + (xx - 44) ** 2 < 10 ** 2
    albedo[disk] = [0.7, 0.1, 0.08]
    shadow = (xx < 30) & (yy > 10)
    light = np.where(shadow, 0.25, 1.0)[..., None]
    img = albedo * light * (1 + 0.03 * rng.normal(size=(h, w, 3)))
    return img, disk, shadow


def test_shadow_boundary_is_not_a_segment_boundary_synthetic():
    img, disk, shadow = _synthetic_view()
    mask = np.ones(disk.shape, bool)
    lab = masks.merge_regions([img], [masks.segment_view(img, mask)])[0]
    base = ~disk
    # The whole base (lit and shadowed) is one segment and the disk another; 2 pixels of
    # tolerance at the disk rim (blurred colours mix there).
    major = np.bincount(lab[base]).argmax()
    assert (lab[base & shadow] == major).mean() > 0.99
    assert (lab[base & ~shadow] == major).mean() > 0.99
    dmaj = np.bincount(lab[disk]).argmax()
    assert dmaj != major and (lab[disk] == dmaj).mean() > 0.9


def test_merge_unlabels_leaky_regions_and_slivers():
    # One 40x40 view: a grey base (region 1), a blue block (region 2), a region 3 that
    # leaked across their edge (half grey, half blue, as Felzenszwalb does in dark, noisy
    # shadows), and a 2-pixel red sliver (region 4, 0.1 % of the pixels).
    rng = np.random.default_rng(3)
    img = np.tile([0.3, 0.3, 0.3], (40, 40, 1)) * (1 + 0.02 * rng.normal(size=(40, 40, 3)))
    reg = np.ones((40, 40), int)
    reg[:, 20:] = 2
    img[:, 20:] = [0.1, 0.2, 0.5]
    reg[30:, 10:30] = 3
    reg[0, :2] = 4
    img[0, :2] = [0.8, 0.1, 0.1]
    lab = masks.merge_regions([img], [reg])[0]
    assert (lab[reg == 3] == 0).all()  # the leak is unlabelled, not a third material
    assert (lab[reg == 4] == 0).all()  # so is the sliver
    assert len(np.unique(lab[reg == 1])) == 1 and len(np.unique(lab[reg == 2])) == 1
    assert lab[5, 5] != lab[5, 35] and min(lab[5, 5], lab[5, 35]) > 0
    # With the checks off, both would be labels of their own.
    cfg = masks.ChromaticityConfig(max_region_spread=1.0, min_label_fraction=0.0)
    off = masks.merge_regions([img], [reg], cfg)[0]
    assert (off[reg == 3] > 0).all() and (off[reg == 4] > 0).all()


def test_shadow_boundary_on_ground_truth_images(tiny):
    ds = load_dataset(tiny, "train")
    info = json.loads((tiny / "dataset.json").read_text())
    base = next(m["id"] for m in info["materials"] if m["name"] == "base")
    labels = masks.chromaticity_masks(ds)
    across = same = 0
    for v, lab in zip(ds.views, labels, strict=True):
        on = v.material == base
        lit = v.visibility.min(-1) >= 0.5
        # Horizontally and vertically adjacent base pixels on either side of a shadow edge.
        for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                     ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
            edge = on[a] & on[b] & (lit[a] != lit[b])
            across += int(edge.sum())
            same += int((edge & (lab[a] == lab[b])).sum())
    assert across > 50  # the views do show shadow edges on the base
    # Measured 0.953 on this 48 px, 16 spp dataset (1149 edge pairs): the misses are dark,
    # noisy umbra pixels whose chromaticity is tinted by indirect light. 0.9 stays clear of
    # that noise and fails for Felzenszwalb on the sRGB image itself (measured 0.54).
    assert same / across > 0.9


def test_chromaticity_separates_materials(tiny):
    ds = load_dataset(tiny, "train")
    labels = masks.chromaticity_masks(ds)
    m = seg_metrics.evaluate_maps(labels, [v.material for v in ds.views])
    # Not perfect (dark and edge pixels, the glossy pillar), but far from chance.
    assert m["ari"] > 0.6


def test_material_masks_and_errors(tiny):
    ds = load_dataset(tiny, "train")
    maps = masks.material_masks(ds)
    assert all(np.array_equal(a, v.material) for a, v in zip(maps, ds.views, strict=True))
    ds.views[1].material = None
    with pytest.raises(masks.MaskError, match="r_001"):
        masks.material_masks(ds)
    with pytest.raises(masks.MaskError, match="unknown mask source"):
        masks.masks_for(ds, "sam")
    with pytest.raises(masks.MaskError, match="NaN"):
        masks.segment_view(np.full((4, 4, 3), np.nan), np.ones((4, 4), bool))


def test_segment_command(tiny, tmp_path):
    from mi_shadowgs.cli import main
    from mi_shadowgs.io.ply import load_ply, save_ply

    surf, _ = standin_surfels(3000)
    save_ply(tmp_path / "model.ply", surf)
    out = tmp_path / "out"
    rc = main(["segment", str(tmp_path / "model.ply"), "--data", str(tiny), "--out", str(out),
               "--set", "iterations=20", "--set", "n_samples=256", "--quiet"])
    assert rc == 0
    model = load_ply(out / "model.ply")
    segs = model.channels["segment"].numpy().ravel()
    report = json.loads((out / "segmentation.json").read_text())
    assert report["k"] == 5 and set(np.unique(segs)) <= set(range(5))
    assert model.channels["feature"].shape == (surf.count, 16)
    assert (out / "segments" / "r_000.png").is_file()
    assert (out / "segments" / "r_000_overlay.png").is_file()
    assert 0.0 <= report["metrics"]["ari"] <= 1.0 and "base_shadow" in report
    # A run folder without geometry/model.ply is a clear error.
    rc = main(["segment", str(tmp_path), "--data", str(tiny), "--out", str(out)])
    assert rc == 2
