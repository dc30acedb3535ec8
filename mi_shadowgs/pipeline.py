"""The whole method end to end (``mi-shadowgs run``): stage 1 (geometry), stage 2
(segmentation), then stages 3-5 per variant (visibility and the material/light
decomposition, evaluation and relighting), the summary and the report.

``run_pipeline`` takes the run's settings as one ``RunConfig`` tree (``mi_shadowgs.presets``)
and hands each stage's runner its config object; each stage is resumable, and a stage whose
outputs are complete and were made from the same inputs is not run again.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from mi_shadowgs.backend import ensure_variant
from mi_shadowgs.config import slow_preset_warning
from mi_shadowgs.io.atomic import write_json
from mi_shadowgs.presets import CONFIG_NAME, RunConfig
from mi_shadowgs.stages import geometry, segmentation
from mi_shadowgs.stages.common import warn
from mi_shadowgs.stages.evaluation.evaluate import check_evaluation_inputs
from mi_shadowgs.stages.evaluation.runner import evaluate_variant
from mi_shadowgs.stages.geometry.background import PastTheGround
from mi_shadowgs.stages.geometry.gains import GAINS_FILE, read_gains
from mi_shadowgs.stages.geometry.runner import BACKDROP_FILE, read_backdrop
from mi_shadowgs.stages.material.config import MaterialConfig, label_source_overrides
from mi_shadowgs.stages.material.runner import fit_or_reuse, occluder_bounds
from mi_shadowgs.stages.visibility import shadow_maps
from mi_shadowgs.summary import build_summary, write_report_figures


def material_stage(top, name: str, material: MaterialConfig, labels: str, dataset: dict,
                   data: Path, surfels, train, test, bounds: shadow_maps.SceneBounds,
                   config: RunConfig, overwrite: bool, progress: bool, past=None
                   ) -> tuple[dict, float | None]:
    """Stages 3-5 of one variant, fitted with ``material``, into ``material/<name>`` of the
    run ``top`` (an Output); ``labels``: where stage 2's segments came from; ``dataset``: the
    dataset's fingerprint; ``past``: the run's ``PastTheGround`` (None: none), used where
    ``material.backdrop_surfels`` is "skip". Returns (metrics, fit seconds), the seconds None
    when a finished output of the same provenance is reused."""
    from mi_shadowgs.io.provenance import Output, Provenance, input_ref
    from mi_shadowgs.stages.common import warn_other_backend

    folder = top.folder / "material" / name
    seg_model = top.folder / "segmentation" / "model.ply"
    settings = {"variant": name, "material": dataclasses.asdict(material), "labels": labels,
                "visibility": dataclasses.asdict(config.visibility),
                "relight": dataclasses.asdict(config.relight),
                "bounds_quantile": config.bounds_quantile, "figure_views": config.figure_views}
    if name == "full" and config.preview_envmaps:  # the previews of the full fit use them
        settings["preview_envmaps"] = list(config.preview_envmaps)
    inputs = {"model": input_ref(seg_model)}
    gains_file = top.folder / "geometry" / GAINS_FILE
    gains = read_gains(gains_file, [v.name for v in train.views]) if gains_file.is_file() else None
    if gains is not None:  # stage 1's gains, held: each training photo divided by its own
        inputs["view_gains"] = input_ref(gains_file)
    past = past if material.backdrop_surfels == "skip" else None
    if past is not None:  # the pixels left out follow stage 1's backdrop colour
        inputs["backdrop"] = input_ref(top.folder / "geometry" / BACKDROP_FILE)
        keep = ~past.surfels(surfels)  # neither fitted nor relit nor exported
        if not keep.all():
            warn(f"{seg_model}: {int((~keep).sum())} of {len(keep)} surfels lie past the "
                 "ground in the room's colour; stage 4 leaves them and their pixels out "
                 "(--set material.backdrop_surfels=fit keeps them)")
            surfels = surfels.subset(keep)
    if "preview_envmaps" in settings:  # by content: a file edited, or one added to a folder,
        # makes the previews again (the dataset's own env maps are in its fingerprint)
        inputs.update({f"preview_envmap_{i}": input_ref(f)
                       for i, f in enumerate(_user_envmap_files(config))})
    provenance = Provenance(dataset=dataset, inputs=inputs, settings=settings)
    top.add_part(f"material/{name}")
    with Output.open(folder, "run", provenance, overwrite=overwrite, reuse=True,
                     inputs=[data, seg_model], part_of=top.folder) as out:
        if out.complete:
            return json.loads((folder / "metrics.json").read_text()), None
        warn_other_backend(out, made_from=seg_model)
        res, fit_s = fit_or_reuse(out, surfels, train, material, config.visibility, bounds,
                                  progress, gains, past)
        metrics = evaluate_variant(
            out, res, train, test, bounds, config.visibility, config.relight,
            config.figure_views, _segment_maps(top.folder / "segmentation" / "segments", test),
            fit_s, _preview_envmaps(config, train) if name == "full" else None)
        out.finish()
    return metrics, fit_s


def _segment_maps(folder: Path, test) -> dict:
    """Stage 2's segment maps of the test views (view stem -> sRGB uint8 [H, W, 3])."""
    from mi_shadowgs.io.images import read_png

    out = {}
    for v in test.views:
        stem = Path(v.name).name
        if (folder / f"{stem}.png").is_file():
            out[stem] = read_png(folder / f"{stem}.png")
    return out


def _preview_envmaps(config: RunConfig, train) -> list[tuple[str, Path, float]]:
    """(name, file, scale) of the env maps the report's previews relight with: the
    dataset's env-map relightings, then ``config.preview_envmaps`` (files, or folders of
    .exr files) where they exist."""
    from mi_shadowgs.stages.evaluation.evaluate import envmap_file

    out = [(e["name"], envmap_file(e, train.root), float(e.get("scale", 1.0)))
           for e in (train.lights or {}).get("relightings", []) if e.get("type") == "envmap"]
    return out + [(f.stem, f, 1.0) for f in _user_envmap_files(config)]


def check_preview_envmaps(entries, source: str = "preview_envmaps") -> tuple[str, ...]:
    """``entries`` (env map files, or folders of .exr files) as absolute paths, for
    ``RunConfig.preview_envmaps``. A bare path is a TypeError (it would be read letter by
    letter) and a missing entry a FileNotFoundError, both naming ``source``; an integer
    (clipped) env map file gets a warning."""
    import os

    from mi_shadowgs.core.envmap import low_dynamic_range_warning

    if isinstance(entries, str | os.PathLike) or not isinstance(entries, list | tuple):
        raise TypeError(f"{source} takes a list of env map files or folders, got {entries!r}")
    for e in entries:
        if not os.path.exists(e):
            raise FileNotFoundError(f"{source}: {e}: not found")
        if os.path.isfile(e) and (note := low_dynamic_range_warning(e, source)) is not None:
            warn(note)
    return tuple(str(Path(e).resolve()) for e in entries)


def _user_envmap_files(config: RunConfig) -> list[Path]:
    """The files of ``config.preview_envmaps`` (files, or folders of .exr files), in order."""
    files = []
    for entry in config.preview_envmaps:
        path = Path(entry)
        files += (sorted(path.glob("*.exr")) if path.is_dir()
                  else [path] if path.is_file() else [])
    return files


def run_pipeline(data: str | Path, out: str | Path, config: RunConfig, progress: bool = True,
                 overwrite: bool = False, log=print) -> dict:
    """Stages 1-5 on dataset ``data`` into run folder ``out``; returns the summary.

    Every input (both splits, ground truth, lights.json) is read and checked first. Each
    stage's output is reused when it is finished and was made from the same dataset, input
    model and settings; stages 1, 2 and 4 continue from their last checkpoints after an
    interruption (a kill loses at most their ``checkpoint_seconds``);
    anything else exits with a ProvenanceError naming what differs, unless ``overwrite``
    removes the run's files first. ``log`` takes the stages' one-line summaries.
    """
    from mi_shadowgs.dataset.fingerprint import dataset_ref
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.io.provenance import Output, Provenance
    from mi_shadowgs.io.report import write_report
    from mi_shadowgs.stages.common import load_training_views

    data, run = Path(data), Path(out)
    t_start = time.perf_counter()
    settings = config.to_dict()  # as asked; the stages' manifests record what they ran with
    slow = slow_preset_warning(config.preset, ensure_variant())
    if slow:
        warn(slow)
    train = load_training_views(data)
    test = load_dataset(data, "test")
    available = check_evaluation_inputs(train, test)
    labels = config.masks
    if labels == "auto":
        labels = ("material" if all(v.material is not None for v in train.views)
                  else "chromaticity")
    elif labels == "material":  # checked before stage 1 trains, not when stage 2 starts
        from mi_shadowgs.stages.segmentation.masks import material_masks

        material_masks(train)
    changed = label_source_overrides(config.material, labels)
    if changed:  # stage 4's settings for segments from colour labels, resolved once here
        config = dataclasses.replace(config, material=dataclasses.replace(config.material,
                                                                          **changed))
        if log:
            log(f"stage 4 on segments from {labels}: " + ", ".join(
                f"{k} {v}" for k, v in changed.items()) + " (MaterialConfig.chromaticity_*)")
    dataset = dataset_ref(data)  # fingerprinted once; every stage's manifest records it
    provenance = Provenance(dataset=dataset, settings=settings)
    stages, reused = [], []  # (name, seconds) of the stages this call ran; names of the rest

    def done(name: str, stage) -> None:
        if stage.ran:
            stages.append((name, stage.seconds))
            if stage.summary and log:
                log(stage.summary)
        else:
            reused.append(name)

    with Output.open(run, "run", provenance, overwrite=overwrite, reuse=True,
                     compare=("dataset",), inputs=[data],
                     parts=("geometry", "segmentation", "material")) as top:
        top.add_part("geometry")
        geo = geometry.run_geometry(data, run / "geometry", config.geometry,
                                    preset=config.preset, dataset=dataset, reuse=True,
                                    overwrite=overwrite, progress=progress, train=train,
                                    test=test)
        done("geometry", geo)
        top.add_part("segmentation")
        seg = segmentation.run_segmentation(
            run / "geometry" / "model.ply", data, run / "segmentation", config.segmentation,
            masks=labels, chromaticity=config.chromaticity, preset=config.preset,
            dataset=dataset, overwrite=overwrite, reuse=True, progress=progress, train=train,
            views=test)
        done("segmentation", seg)
        surfels = load_ply(run / "segmentation" / "model.ply")
        bounds = occluder_bounds(surfels, train.cameras, config.bounds_quantile)
        past = (PastTheGround.of(train, config.geometry, read_backdrop(run / "geometry"))
                if any(m.backdrop_surfels == "skip" for m in config.variants().values())
                else None)  # once for every variant: it carves the views' support

        # Stages 3-5 per variant: visibility + decomposition, then evaluation and relighting.
        results = {}
        for name, material in config.variants().items():
            results[name], fit_s = material_stage(top, name, material, labels, dataset, data,
                                                  surfels, train, test, bounds, config,
                                                  overwrite, progress, past)
            if fit_s is not None:
                stages.append((f"material ({name})", fit_s))
            else:
                reused.append(f"material ({name})")
        with top.staged("report") as tmp:  # beside any file of the user's there
            write_report_figures(tmp, run, data, earlier=run / "report")
        summary = build_summary(run, data, config, results, stages,
                                time.perf_counter() - t_start, available, reused)
        write_json(top.path("summary.json"), summary)
        write_json(top.path(CONFIG_NAME), settings)  # the tree it ran with (--config reads it)
        top.claim("report.html")
        write_report(run)
        top.finish()
    return summary
