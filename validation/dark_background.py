"""Dark is not background: stage 1 without masks against the truth of a generated capture.

A generated capture (``generate --photos``, e.g. ``-D capture=lab``) imported with
``mi-shadowgs import`` has no masks; stage 1's dark-alpha prior then decides which dark
pixels may be empty (``stages/geometry/background.py``). This scores, on the ground-truth
views (cameras mapped into the import's frame by the similarity fitted on the imported
cameras, as ``validation.photos`` does), at ``--scale`` of their size:

- the rule itself, from the photos and the import's SfM points (no training): the share of
  the true cast shadow on the ground (alpha 1, not the object, hard visibility 0) and of the
  true background (alpha 0) that the prior would act on, with each ``dark_alpha_support``;
- each ``--run`` (a stage-1 folder trained on the import): its rendered alpha there, the
  share of the cast shadow it leaves open (alpha < 0.5, holes), the share of the background
  it covers (alpha > 0.5), and its own test PSNR.

    python -m validation.dark_background --truth GT --data IMPORT [--run NAME=RUN/geometry]
        [--scale 0.5] [--dark-max 0.0039] [--out OUT.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from validation import fail


def _views(truth: Path, data: Path, scale: float):
    """[(photo name, GT view, camera in the import's frame at ``scale``)] of every GT view."""
    from mi_shadowgs.dataset.loader import load_dataset
    from validation.import_sfm import cameras_by_photo
    from validation.import_sfm import truth as truth_cameras
    from validation.photos import fit_frame

    sim, frame = fit_frame(cameras_by_photo(data), truth_cameras(truth))
    out = []
    for split in ("train", "test"):
        for i, v in enumerate(load_dataset(truth, split).views):
            cam = dataclasses.replace(v.camera, c2w=sim.c2w(v.camera.c2w))
            w, h = round(cam.width * scale), round(cam.height * scale)
            out.append((f"{split}_{i:03d}.jpg", v, cam.with_size(w, h)))
    return out, frame


def _down(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A full-size map [H, W] (bool or float) at ``shape`` by box averaging."""
    h, w = a.shape
    fy, fx = h // shape[0], w // shape[1]
    return a[: shape[0] * fy, : shape[1] * fx].reshape(shape[0], fy, shape[1], fx).mean((1, 3))


def regions(view, shape) -> dict[str, np.ndarray]:
    """The truth's regions at ``shape``, each [h, w] bool (pixels wholly in the region)."""
    vis = view.visibility[..., 0] if view.visibility.ndim == 3 else view.visibility
    ground = view.mask & ~view.object_mask
    return {"shadow": _down(ground & (vis < 0.5), shape) == 1.0,
            "lit_ground": _down(ground & (vis >= 0.5), shape) == 1.0,
            "object": _down(view.object_mask, shape) == 1.0,
            "object_shadow": _down(view.object_mask & (vis < 0.5), shape) == 1.0,
            "background": _down(~view.mask, shape) == 1.0}


def _photo(truth: Path, name: str, shape) -> np.ndarray:
    from PIL import Image

    from mi_shadowgs.io.images import srgb_to_linear

    with Image.open(truth / "photos" / name) as im:
        rgb = im.convert("RGB").resize(shape[::-1], Image.Resampling.BOX)
    return srgb_to_linear(np.asarray(rgb, np.float32) / 255.0)


def score_rule(views, truth: Path, data: Path, dark_max: float, margin: float) -> dict:
    """The share of each region the dark-alpha prior would act on, per support rule."""
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.stages.geometry import background

    train = load_dataset(data, "train")  # the support stage 1 would use
    support = background.support_of(
        background.read_points(data / "points3d.ply"), [v.camera for v in train.views],
        [background.dark_pixels(v.image, dark_max) for v in train.views], margin)
    sums = {}
    for name, view, cam in views:
        shape = (cam.height, cam.width)
        reg = regions(view, shape)
        dark = background.dark_pixels(_photo(truth, name, shape), dark_max)
        rules = {"none": dark, "points": dark & ~background.supported_pixels(cam, support)}
        for rule, px in rules.items():
            for r, m in reg.items():
                s = sums.setdefault(f"{rule}.{r}", [0, 0])
                s[0] += int((px & m).sum())
                s[1] += int(m.sum())
    return {k: a / max(b, 1) for k, (a, b) in sums.items()}


def score_run(views, run: Path) -> dict:
    """A stage-1 model's rendered alpha in each region."""
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.stages.geometry.train import render_view

    surfels = load_ply(run / "model.ply")
    acc = {}
    for _, view, cam in views:
        alpha = render_view(surfels, cam)["alpha"]
        for r, m in regions(view, alpha.shape).items():
            acc.setdefault(r, []).append(alpha[m])
    out = {}
    for r, parts in acc.items():
        a = np.concatenate(parts)
        out[f"{r}.alpha"] = float(a.mean())
        out[f"{r}.{'open' if r != 'background' else 'covered'}"] = float(
            np.mean(a < 0.5) if r != "background" else np.mean(a > 0.5))
    metrics = run / "metrics.json"
    if metrics.is_file():
        out["test_psnr"] = json.loads(metrics.read_text()).get("psnr")
    return out


def main(argv=None) -> int:
    from mi_shadowgs import backend

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--truth", required=True, help="the generated dataset (with photos/)")
    ap.add_argument("--data", required=True, help="its import (mi-shadowgs import)")
    ap.add_argument("--run", action="append", default=[], metavar="NAME=FOLDER",
                    help="a stage-1 folder trained on DATA (repeatable)")
    ap.add_argument("--scale", type=float, default=0.5, help="of the truth's image size")
    ap.add_argument("--dark-max", type=float, default=1.0 / 255.0)
    ap.add_argument("--margin", type=float, default=0.05, help="dark_alpha_margin")
    ap.add_argument("--views", type=int, default=None, help="only every K-th view")
    ap.add_argument("--out", default=None, help="write the figures as JSON here")
    args = ap.parse_args(argv)
    backend.set_variant()
    truth, data = Path(args.truth), Path(args.data)
    for p, what in ((truth / "photos", "--truth"), (data / "points3d.ply", "--data")):
        if not p.exists():
            fail(f"{what}: {p} not found")
    views, frame = _views(truth, data, args.scale)
    views = views[:: args.views or 1]
    rec = {"views": len(views), "frame": frame, "dark_max": args.dark_max,
           "rule": score_rule(views, truth, data, args.dark_max, args.margin), "runs": {}}
    for item in args.run:
        name, _, folder = item.partition("=")
        rec["runs"][name] = score_run(views, Path(folder))
    text = json.dumps(rec, indent=1)
    if args.out:
        Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
