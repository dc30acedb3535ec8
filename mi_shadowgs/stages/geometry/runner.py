"""Stage 1's library runner: ``run_geometry(data, folder, config, ...)`` trains the 2DGS
geometry on a dataset and writes its files (model, checkpoint, log, previews, metrics).
``mi-shadowgs train`` and ``mi_shadowgs.pipeline.run_pipeline`` call it; the manifest rules
are in ``mi_shadowgs.stages.common``.
"""

from __future__ import annotations

import csv
import io
import json
import time
from pathlib import Path

import numpy as np

from mi_shadowgs.dataset.fingerprint import dataset_ref
from mi_shadowgs.io.atomic import write_json, write_text
from mi_shadowgs.io.provenance import Output, Provenance
from mi_shadowgs.stages.common import (
    StageRun,
    load_training_views,
    settings_dict,
    warn,
    warn_other_backend,
)
from mi_shadowgs.stages.geometry.background import estimate_backdrop
from mi_shadowgs.stages.geometry.gains import GAINS_FILE, enabled, write_gains

LOG_FIELDS = ("iteration", "loss", "l1", "dssim", "mask", "normal", "dist", "dark_alpha", "psnr",
              "surfels", "time")
# With ``hull_prune_views`` on: what the prune removed, beside the model it made, so that an
# evaluation after ``train --no-eval`` reports it as one straight after training does.
PRUNE_RECORD = "prune.json"
BACKDROP_FILE = "backdrop.json"  # the colour behind the surfels in views without masks


class GeometryWriter:
    """The geometry stage's files as the loop produces them: log, previews, checkpoints."""

    def __init__(self, out: Output, config_dict: dict):
        self.out = out
        self.config_dict = config_dict
        self.log_path = out.path("log.csv")

    def start_log(self, from_step: int) -> None:
        """Keep the log rows up to ``from_step`` (a resumed run rewrites what came after). A
        row cut short by a crash while it was appended (no iteration, or not all fields) is
        one the rerun writes again: dropped."""
        rows = []
        if from_step > 0 and self.log_path.is_file():
            with open(self.log_path, newline="") as f:
                rows = [r for r in csv.DictReader(f)
                        if None not in r.values() and (r["iteration"] or "").isdigit()
                        and int(r["iteration"]) <= from_step]
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
        from mi_shadowgs.io.images import linear_to_srgb, write_png
        from mi_shadowgs.stages.geometry.train import render_view

        r = render_view(surfels, view.camera)
        normal = np.where(r["alpha"][..., None] > 0, r["normal"] * 0.5 + 0.5, 0.0)
        row = np.concatenate([np.clip(r["rgb"], 0, 1), np.clip(view.image, 0, 1)], axis=1)
        row2 = np.concatenate([linear_to_srgb(np.clip(normal, 0, 1)),
                               np.repeat(r["alpha"][..., None], 3, -1)], axis=1)
        img = np.concatenate([linear_to_srgb(row), row2], axis=0)
        write_png(self.out.path(f"previews/iter_{step:06d}.png"), img, srgb=False)

    def on_checkpoint(self, state) -> None:
        from mi_shadowgs.io.checkpoint import save_checkpoint

        save_checkpoint(self.out.folder / "checkpoint",
                        *state.to_checkpoint(config=self.config_dict))


def geometry_line(metrics: dict) -> str:
    normal = metrics.get("normal_error_median_deg")  # absent: no ground-truth normals
    normal = f"{normal:.2f} deg" if normal is not None else "n/a (no ground-truth normals)"
    return (f"geometry: {metrics['surfels']} surfels; test PSNR {metrics['psnr']:.2f} dB, SSIM "
            f"{metrics['ssim']:.4f}, median normal error {normal}, mask IoU "
            + ("n/a (no masks)" if metrics.get("mask_iou") is None
               else f"{metrics['mask_iou']:.4f}")
            + (f"; {metrics['hull_pruned']} pruned outside the masks"
               if "hull_pruned" in metrics else "")
            + (f"; view gains within {100 * metrics['view_gain_error_max']:.1f}% of the "
               "truth" if "view_gain_error_max" in metrics else ""))


def _dark_alpha_pixels(config, points) -> str:
    """Which pixels the dark-alpha term acts on, for the no-masks warning."""
    if config.lambda_dark_alpha <= 0:
        return "off"
    if config.dark_alpha_support == "points" and points is not None:
        return "dark pixels whose rays miss the SfM points"
    return ("every dark pixel: no SfM points to tell a shadow from the background"
            if config.dark_alpha_support == "points" else "every dark pixel")


def run_geometry(data: str | Path, folder: str | Path, config, *, preset: str = "",
                 dataset: dict | None = None,
                 resume: bool = False, overwrite: bool = False, reuse: bool = False,
                 evaluate: bool = True, progress: bool = True, train=None,
                 test=None, on_test_view=None) -> StageRun:
    """Stage 1 on dataset ``data`` into ``folder`` (a run's ``geometry/``).

    Writes ``model.ply``, ``checkpoint/checkpoint.npz``, ``log.csv``, ``previews/``,
    ``config.json``, ``BACKDROP_FILE``, with ``hull_prune_views`` ``PRUNE_RECORD``, with
    the view gains on (``gains.enabled``) ``GAINS_FILE`` and, with ``evaluate``,
    ``metrics.json`` (test views). An existing output
    is replaced (``overwrite``), continued from its checkpoint (``resume``), returned as it
    is when finished or else continued (``reuse``, as ``run`` does), or refused; it is
    continued or reused only when its dataset fingerprint and settings match.
    ``train`` / ``test``: the splits, when the caller has loaded them already.
    ``on_test_view(view, render)``: called on each test view the evaluation renders.
    ``dataset``: the dataset's fingerprint (``dataset_ref``), when the caller has it; ``preset``:
    the preset name ``config`` came from, recorded in ``config.json``.
    """
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.io.checkpoint import has_checkpoint, load_checkpoint
    from mi_shadowgs.io.ply import load_ply, save_ply
    from mi_shadowgs.stages.geometry.train import (
        Callbacks,
        TrainState,
        prune_outside_masks,
        prune_warning,
        train_geometry,
    )

    if resume and overwrite:
        raise ValueError("--resume continues the stage's files and --overwrite removes them: "
                         "pass one of them")
    t0 = time.perf_counter()
    folder = Path(folder)
    # Every input is read before the first step: a bad test image fails now, not after.
    train = train if train is not None else load_training_views(data)
    if evaluate and test is None:
        test = load_dataset(data, "test")
    gains_on = enabled(config, data)
    if not getattr(train, "has_masks", True):
        config = _unmasked(config, train, data)
    cfg_dict = settings_dict(config)
    cfg_dict["view_gains"] = "on" if gains_on else "off"  # what "auto" is on this dataset
    provenance = Provenance(dataset=dataset or dataset_ref(data), settings=cfg_dict)
    with Output.open(folder, "train", provenance, overwrite=overwrite, reuse=resume or reuse,
                     inputs=[data], continue_flag="--resume") as out:
        if reuse and out.complete:
            if not evaluate or (folder / "metrics.json").is_file():
                return StageRun(folder, False, 0.0, "")
            warn_other_backend(out)
            # Trained without its evaluation (`train --no-eval`): evaluated now, so that a
            # run's summary and report have stage 1.
            out.claim("metrics.json")
            line = _write_metrics(folder, load_ply(folder / "model.ply"), test, config,
                                  on_test_view, gains_on, read_backdrop(folder))
            out.finish()
            return StageRun(folder, False, 0.0, line)
        warn_other_backend(out)
        state = None
        ckpt_dir = folder / "checkpoint"
        if out.reused and has_checkpoint(ckpt_dir):
            state = TrainState.from_numpy(load_checkpoint(ckpt_dir)[0], config)
        elif resume:  # killed before its first checkpoint: that was < checkpoint_seconds
            warn(f"{ckpt_dir}: no checkpoint yet; starting from step 0")
        write_json(out.path("config.json"), {"stage": "geometry", "preset": preset,
                                             "data": str(Path(data).resolve()),
                                             "config": cfg_dict})
        out.claim("checkpoint/checkpoint.npz", "model.ply", BACKDROP_FILE,
                  *([GAINS_FILE] if gains_on else []),
                  *(["metrics.json"] if evaluate else []))
        writer = GeometryWriter(out, cfg_dict)
        writer.start_log(state.step if state else 0)
        cb = Callbacks(on_log=writer.on_log, on_preview=writer.on_preview,
                       on_checkpoint=writer.on_checkpoint,
                       on_gains=lambda g, psnr: write_gains(folder / GAINS_FILE, g, psnr,
                                                            [v.name for v in train.views],
                                                            data))
        backdrop = estimate_backdrop(train, config)
        write_json(folder / BACKDROP_FILE, {
            "rgb": None if backdrop is None else backdrop.tolist(),
            "meaning": "linear RGB behind the surfels in the training views without masks "
                       "(null: black), before each view's gain"})
        surfels = train_geometry(train, config, state=state, callbacks=cb, progress=progress,
                                 backdrop=backdrop)
        surfels, pruned = prune_outside_masks(surfels, train.views, config)
        if (note := prune_warning(pruned, surfels.count + pruned, config, data)) is not None:
            warn(note)
        if config.hull_prune_views:  # kept for an evaluation after `train --no-eval`
            out.claim(PRUNE_RECORD)
            write_json(folder / PRUNE_RECORD, {"hull_pruned": pruned,
                                               "surfels_before": surfels.count + pruned})
        save_ply(folder / "model.ply", surfels)
        line = (_write_metrics(folder, surfels, test, config, on_test_view, gains_on,
                               backdrop) if evaluate else "")
        out.finish()
    return StageRun(folder, True, time.perf_counter() - t0, line)


def _unmasked(config, train, data):
    """The settings of a dataset without masks, and a warning that says what they do."""
    from mi_shadowgs.stages.geometry.config import unmasked

    config = unmasked(config)
    warn(f"{data}: no masks: stage 1 initialises from "
         + ("the SfM points" if getattr(train, "points", None) else "random points in "
            "the cameras' bounds")
         + f", skips the mask loss and the mask IoU, and trains with lambda_dist "
           f"{config.lambda_dist:g}, lambda_normal {config.lambda_normal:g}, "
           f"lambda_dark_alpha {config.lambda_dark_alpha:g} ("
         + _dark_alpha_pixels(config, getattr(train, "points", None)) + ") and "
         + ("the opacity reset" if config.densify.opacity_reset_interval else
            "no opacity reset" + ("" if config.densify.world_prune_after is None else
                                  " (surfels larger than "
                                  f"{config.densify.world_size_fraction:g} x the cameras' "
                                  "extent pruned from iteration "
                                  f"{config.densify.world_prune_after})"))
         + (f"; hull_prune_views {config.hull_prune_views} (--prune-outside-masks) has "
            "no mask to prune by and removes nothing" if config.hull_prune_views else ""))
    return config


def read_backdrop(folder: Path) -> np.ndarray | None:
    """A stage-1 folder's backdrop colour [3] (``BACKDROP_FILE``), or None (black)."""
    path = Path(folder) / BACKDROP_FILE
    rgb = json.loads(path.read_text()).get("rgb") if path.is_file() else None
    return None if rgb is None else np.asarray(rgb, np.float64)


def _write_metrics(folder: Path, surfels, test, config, on_test_view, gains_on: bool,
                   backdrop: np.ndarray | None = None) -> str:
    """The model's test metrics into ``folder/metrics.json`` (claimed); their summary line.
    With ``hull_prune_views`` on, ``hull_pruned`` is the count of ``PRUNE_RECORD``; with the
    view gains on (``gains_on``), each test render is scaled by its own least-squares gain,
    and the fitted gains' error is there when their truth is known."""
    from mi_shadowgs.stages.geometry.train import evaluate as evaluate_geometry

    m = evaluate_geometry(surfels, test, config.raster, on_view=on_test_view,
                          fit_gains=gains_on, backdrop=backdrop)
    if backdrop is not None:
        m["backdrop"] = [float(c) for c in backdrop]
    m["surfels"] = surfels.count
    truth = (json.loads((folder / GAINS_FILE).read_text()).get("truth")
             if (folder / GAINS_FILE).is_file() else None)
    if truth:  # a lab capture's true gains: the fitted ones' error after one scale per channel
        m["view_gain_error_max"] = truth["max_error"]
        m["view_gain_error_mean"] = truth["mean_error"]
    if config.hull_prune_views and (folder / PRUNE_RECORD).is_file():
        m["hull_pruned"] = json.loads((folder / PRUNE_RECORD).read_text())["hull_pruned"]
    write_json(folder / "metrics.json", m)
    return geometry_line(m)


