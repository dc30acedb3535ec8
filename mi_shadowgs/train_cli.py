"""``mi-shadowgs train DATA --out RUN --stage geometry [--preset P] [--resume]``.

Writes ``RUN/geometry/``: ``model.ply`` (2DGS layout), ``checkpoint/checkpoint.npz``
(atomic; ``--resume`` continues from it), ``log.csv`` (iteration, loss terms, PSNR, surfel
count, seconds), ``previews/iter_NNNNNN.png`` (render | ground truth of the first training
view), ``metrics.json`` (test-view evaluation) and ``config.json``.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import shutil
from pathlib import Path

import numpy as np

STAGES = ("geometry",)
LOG_FIELDS = ("iteration", "loss", "l1", "dssim", "mask", "normal", "dist", "psnr", "surfels",
              "time")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", help="dataset folder (transforms_train.json, ...)")
    parser.add_argument("--out", required=True, help="run folder; the stage writes a subfolder")
    parser.add_argument("--stage", choices=STAGES, default="geometry")
    parser.add_argument("--preset", default="cpu-small", help="cpu-small (default) or paper")
    parser.add_argument("--iterations", type=int, default=None, help="override the preset")
    parser.add_argument("--resume", action="store_true",
                        help="continue from the stage's last checkpoint")
    parser.add_argument("--overwrite", action="store_true",
                        help="start afresh, replacing an existing stage folder")
    parser.add_argument("--no-eval", action="store_true", help="skip the test-view metrics")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


class RunWriter:
    """The geometry stage's files: log, previews, checkpoints, model, metrics."""

    def __init__(self, folder: Path, config_dict: dict):
        self.folder = folder
        self.config_dict = config_dict
        self.log_path = folder / "log.csv"
        (folder / "previews").mkdir(parents=True, exist_ok=True)

    def start_log(self, from_step: int) -> None:
        """Keep the log rows up to ``from_step`` (a resumed run rewrites what came after)."""
        from .atomic import write_text

        rows = []
        if from_step > 0 and self.log_path.is_file():
            with open(self.log_path, newline="") as f:
                rows = [r for r in csv.DictReader(f) if int(r["iteration"]) <= from_step]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=LOG_FIELDS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
        write_text(self.log_path, buf.getvalue())

    def on_log(self, record: dict) -> None:
        with open(self.log_path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=LOG_FIELDS, extrasaction="ignore").writerow(
                {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in record.items()})

    def on_preview(self, step: int, surfels, view) -> None:
        from .atomic import atomic_path
        from .imageio import linear_to_srgb, write_png
        from .stage_geometry import render_view

        r = render_view(surfels, view.camera)
        normal = np.where(r["alpha"][..., None] > 0, r["normal"] * 0.5 + 0.5, 0.0)
        row = np.concatenate([np.clip(r["rgb"], 0, 1), np.clip(view.image, 0, 1)], axis=1)
        row2 = np.concatenate([linear_to_srgb(np.clip(normal, 0, 1)),
                               np.repeat(r["alpha"][..., None], 3, -1)], axis=1)
        img = np.concatenate([linear_to_srgb(row), row2], axis=0)
        with atomic_path(self.folder / "previews" / f"iter_{step:06d}.png") as tmp:
            write_png(tmp, img, srgb=False)

    def on_checkpoint(self, state) -> None:
        from .checkpoint import save_checkpoint

        save_checkpoint(self.folder / "checkpoint", state.to_numpy(),
                        {"stage": "geometry", "step": state.step, "config": self.config_dict})


def run(args) -> int:
    from .atomic import write_json
    from .checkpoint import has_checkpoint, load_checkpoint
    from .config import to_dict, with_overrides
    from .dataset.loader import load_dataset
    from .ply import save_ply
    from .stage_geometry import Callbacks, TrainState, evaluate, get_config, train_geometry

    config = get_config(args.preset)
    if args.iterations is not None:
        config = with_overrides(config, {"iterations": args.iterations}, "geometry")
    cfg_dict = json.loads(json.dumps(to_dict(config)))
    folder = Path(args.out) / args.stage
    ckpt_dir = folder / "checkpoint"
    state = None
    train = load_dataset(args.data, "train")
    if args.resume:
        if not has_checkpoint(ckpt_dir):
            raise FileNotFoundError(f"{ckpt_dir}: no checkpoint to resume from")
        arrays, meta = load_checkpoint(ckpt_dir)
        if meta.get("config") != cfg_dict:
            diff = sorted(k for k in cfg_dict if meta.get("config", {}).get(k) != cfg_dict[k])
            raise ValueError(f"{ckpt_dir}: the checkpoint was written with other settings "
                             f"(differing: {diff}); resume with the same --preset/--iterations")
        state = TrainState.from_numpy(arrays, config)
    elif folder.exists():
        if not args.overwrite:
            raise FileExistsError(f"{folder} already exists: pass --resume to continue it or "
                                  "--overwrite to start again")
        shutil.rmtree(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "config.json", {"stage": args.stage, "preset": args.preset,
                                         "data": str(Path(args.data).resolve()),
                                         "config": cfg_dict})
    writer = RunWriter(folder, cfg_dict)
    writer.start_log(state.step if state else 0)
    cb = Callbacks(on_log=writer.on_log, on_preview=writer.on_preview,
                   on_checkpoint=writer.on_checkpoint)
    surfels = train_geometry(train, config, state=state, callbacks=cb,
                             progress=not args.no_progress)
    save_ply(folder / "model.ply", surfels)
    if not args.no_eval:
        test = load_dataset(args.data, "test")
        m = evaluate(surfels, test, config.raster)
        m["surfels"] = surfels.count
        write_json(folder / "metrics.json", m)
        print(f"geometry: {surfels.count} surfels; test PSNR {m['psnr']:.2f} dB, SSIM "
              f"{m['ssim']:.4f}, median normal error "
              f"{m.get('normal_error_median_deg', float('nan')):.2f} deg, mask IoU "
              f"{m['mask_iou']:.4f}")
    return 0
