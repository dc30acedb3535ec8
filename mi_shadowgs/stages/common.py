"""What every stage runner shares: the training views (with the too-few-views warning),
the resolved settings a manifest records, the ``StageRun`` a runner returns, and the
checkpoint hooks of a resumable loop.

A runner checks its inputs, claims its output folder (``mi_shadowgs.io.provenance``: a
manifest of the dataset's fingerprint, the input model's digest and the resolved settings;
an output is continued or reused only when they all match), runs the stage and writes its
files. The CLIs, ``mi_shadowgs.pipeline`` and ``validation/`` all call the runners.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

from mi_shadowgs.config import to_dict
from mi_shadowgs.io.provenance import Output

# Below this many training views the method is under-determined: each surface point must be
# seen from several sides for its geometry, its segment features and its shadows to be told
# apart from its albedo. `python -m validation.view_count` measures it: at 8 views the
# default scene's test PSNR is 22.6 dB and its shadow IoU 0.70; from 16 on its figures are
# within 0.02 of the 64-view run's.
MIN_TRAIN_VIEWS = 16


# A run's stage folders and the earlier stage's file each was made from (`mi-shadowgs run`'s
# layout; each records the file's digest as its input "model").
RUN_STAGE_INPUTS = (("segmentation", "geometry/model.ply"),
                    ("material/*", "segmentation/model.ply"))


def check_run_stages(run: str | Path) -> None:
    """ProvenanceError when a stage of the run folder ``run`` was made from another file of
    an earlier stage than the one there now: a stage made again in a finished run (``train
    --overwrite`` or ``segment --overwrite`` into it) leaves the later stages, its summary
    and its report made from the old one. Readers of a run (``report``, ``relight``,
    ``view``, ``export``) refuse such a mix instead of using it."""
    from mi_shadowgs.io.provenance import (
        MANIFEST_NAME,
        ProvenanceError,
        file_digest,
        read_manifest,
    )

    run = Path(run)
    for pattern, source in RUN_STAGE_INPUTS:
        for folder in sorted(run.glob(pattern)):
            manifest = read_manifest(folder) if folder.is_dir() else None
            made_from = ((manifest or {}).get("inputs") or {}).get("model") or {}
            if "digest" not in made_from:  # not a stage of the run, or from before the record
                continue
            current = run / source
            if not current.is_file() or file_digest(current) != made_from["digest"]:
                stage = folder.relative_to(run).as_posix()
                raise ProvenanceError(
                    f"{run}: its stages do not belong together: {stage} was made from "
                    f"another {source} than the one there now (made again after it, e.g. by "
                    f"`train` or `segment --overwrite`; see {folder / MANIFEST_NAME}). Make "
                    f"the later stages again: `mi-shadowgs run DATA --out {run}` "
                    "(`--overwrite` where it asks)")


def warn(message: str) -> None:
    """One line on stderr."""
    print(f"mi-shadowgs: warning: {message}", file=sys.stderr)


def warn_other_backend(out: Output, made_from: str | Path | None = None) -> None:
    """One warning line when ``out`` is made now on another Mitsuba variant than what it
    goes on from: its own files so far (a stage resumed from a checkpoint made on
    ``cuda_ad_rgb``, now on ``llvm_ad_rgb``), or the earlier stage's file ``made_from`` (a
    run's stage 2 made on another backend than its stage 1). The backends' results differ at
    round-off level, as two Dr.Jit thread counts do, so the work goes on; the manifests
    record each backend (``made_with``) and the run's report names them. Outputs from before
    the record say nothing. Call it once the output is to be written, not when reused."""
    import mitsuba as mi

    from mi_shadowgs.io.provenance import read_manifest, recorded_variants, variants_of

    now = mi.variant()
    said = []
    before = variants_of(out.made_before)
    if before and before[-1] != now:
        said.append(f"continued on {now} from work that {before[-1]} made (its checkpoint "
                    "and files so far); its manifest records both")
    if made_from is not None:
        made_from = Path(made_from)
        try:
            earlier = read_manifest(made_from.parent)
        except (OSError, ValueError):
            earlier = None  # not ours to judge here; the stage's own checks say so
        if earlier and made_from.name in earlier["files"]:
            variants = recorded_variants(earlier)
            if variants and now not in variants:
                said.append(f"made on {now} from {made_from}, which {' and '.join(variants)} "
                            "made")
    if said:
        warn(f"{out.folder}: " + "; ".join(said) + " (results of the two backends differ at "
             "round-off level)")


def load_training_views(data: str | Path):
    """The training split, with a warning when it has fewer views than the method needs."""
    from mi_shadowgs.dataset.loader import load_dataset

    train = load_dataset(data, "train")
    if len(train.views) < MIN_TRAIN_VIEWS:
        warn(f"{data}: {len(train.views)} training view(s); the method needs at least "
             f"{MIN_TRAIN_VIEWS} spread around the object (geometry, segments and shadows "
             "are poorly determined with fewer)")
    return train


def settings_dict(config) -> dict:
    """A config as plain JSON (what a manifest and ``config.json`` record)."""
    return json.loads(json.dumps(to_dict(config)))


@dataclasses.dataclass(frozen=True)
class StageRun:
    """What a runner did."""

    folder: Path
    ran: bool  # False: a finished output of the same provenance was reused
    seconds: float
    summary: str  # one line for the terminal ("" when there is nothing to say)



def checkpoint_hooks(out: Output, from_checkpoint) -> dict:
    """``state`` and ``on_checkpoint`` of a loop whose state has ``to_checkpoint`` (stages 1,
    2 and 4), saved in ``out``'s ``checkpoint/``: the state is the checkpoint's when ``out``
    is a reused output that has one."""
    from mi_shadowgs.io.checkpoint import has_checkpoint, load_checkpoint, save_checkpoint

    folder = out.folder / "checkpoint"

    def on_checkpoint(state) -> None:
        out.claim("checkpoint/checkpoint.npz")
        save_checkpoint(folder, *state.to_checkpoint())

    state = (from_checkpoint(*load_checkpoint(folder))
             if out.reused and has_checkpoint(folder) else None)
    return {"state": state, "on_checkpoint": on_checkpoint}
