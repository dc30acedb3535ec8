"""Chromaticity label maps of a dataset's training views against its material ids.

Stage 2 without material ids trains on ``chromaticity_masks``; this scores those label
maps themselves (no feature training, no surfels), before and after the leak and sliver
checks (``ChromaticityConfig.max_region_spread`` / ``min_label_fraction``)::

    python -m validation.segmentation_masks DATA [DATA ...] [--preset cpu-small] [--threads 1]

Per dataset and variant: ARI on the labelled pixels and on all object pixels (label 0
counted as a class), the unlabelled share, the label count (and those above 0.5 % of the
labelled pixels), and the lit / shadowed base pixels in the label of most lit base pixels.
"""

from __future__ import annotations

import argparse
import dataclasses

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs import presets as run_presets


def score(labels, gt, vis, base: int) -> dict:
    """The figures above for label maps ``labels`` ([H, W] each) against ``gt`` ids."""
    import numpy as np

    from mi_shadowgs.stages.segmentation.metrics import adjusted_rand_index, evaluate_maps

    p = np.concatenate([np.asarray(m).ravel() for m in labels])
    g = np.concatenate([np.asarray(m).ravel() for m in gt])
    v = np.concatenate([np.asarray(m).ravel() for m in vis])
    on = (g > 0) & (p > 0)
    counts = np.bincount(p)[1:]
    lit, shadow = (g == base) & (v >= 0.5) & (p > 0), (g == base) & (v < 0.5) & (p > 0)
    major = int(np.bincount(p[lit]).argmax()) if lit.any() else -1
    return {"ari_labelled": adjusted_rand_index(p[on], g[on]),
            "ari_all": evaluate_maps(labels, gt)["ari"],
            "unlabelled": 1.0 - on.sum() / max((g > 0).sum(), 1),
            "labels": int((counts > 0).sum()),
            "labels_over_0.5%": int((counts >= 0.005 * counts.sum()).sum()),
            "base_lit": float((p[lit] == major).mean()) if lit.any() else float("nan"),
            "base_shadowed": float((p[shadow] == major).mean()) if shadow.any()
            else float("nan")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="+", help="dataset folders with material ids")
    ap.add_argument("--preset", default="cpu-small")
    ap.add_argument("--threads", type=int, default=0, help="Dr.Jit threads (0: all)")
    args = ap.parse_args(argv)
    import drjit as dr

    if args.threads:
        dr.set_thread_count(args.threads)
    from mi_shadowgs.stages.common import load_training_views
    from mi_shadowgs.stages.segmentation import masks

    cfg = run_presets.chromaticity_config(args.preset)
    variants = {"no checks": dataclasses.replace(cfg, max_region_spread=float("inf"),
                                                 min_label_fraction=0.0),
                args.preset: cfg}
    for data in args.data:
        ds = load_training_views(data)
        mats = (ds.info or {}).get("materials") or []
        gt = [v.material for v in ds.views]
        base = next((m["id"] for m in mats if m.get("name") == "base"),
                    max(int(g.max()) for g in gt))
        vis = [v.visibility.min(-1) for v in ds.views]
        regions = [masks.segment_view(v.image, v.mask, cfg) for v in ds.views]
        images = [v.image for v in ds.views]
        for name, c in variants.items():
            s = score(masks.merge_regions(images, regions, c), gt, vis, int(base))
            print(f"{data} [{name}] " + " ".join(
                f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in s.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
