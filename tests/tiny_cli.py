"""``python -m tests.tiny_cli [--threads N] COMMAND ...``: the ``mi-shadowgs`` command line
with one more preset, ``test-tiny``, in every stage: 24 px views, seconds per command, and
checkpoints every few steps and every half second, so that a kill at any moment finds some.

The kill tests run commands in a subprocess so that they can SIGKILL them; a subprocess
cannot see a test's monkeypatched presets, so it registers them here. ``--threads 1`` runs
Dr.Jit's LLVM backend on one thread: with more, float atomics add in a varying order and
two runs of the same command differ in the last bits (see tests/test_kill.py).
"""

from __future__ import annotations

import dataclasses
import sys

TINY = "test-tiny"


def presets() -> list[tuple[dict, object]]:
    """(a preset table, its test-tiny settings) for every stage, and last the run's tree
    (``mi_shadowgs.presets.PRESETS``) made of them."""
    from mi_shadowgs import presets as run_presets

    stages = stage_presets()
    return [*stages, (run_presets.PRESETS, run_tree(stages))]


def stage_presets() -> list[tuple[dict, object]]:
    """(a stage's PRESETS dict, its test-tiny settings) for every stage."""
    from mi_shadowgs.dataset import generate
    from mi_shadowgs.stages.export import export
    from mi_shadowgs.stages.geometry import train as geometry_train
    from mi_shadowgs.stages.geometry.densify import DensifyConfig
    from mi_shadowgs.stages.material import config as material_config
    from mi_shadowgs.stages.relight import render as relight
    from mi_shadowgs.stages.segmentation import features as segmentation
    from mi_shadowgs.stages.segmentation import masks
    from mi_shadowgs.stages.visibility import shadow_maps as visibility

    return [
        (generate.PRESETS, dataclasses.replace(
            generate.get_config("cpu-small"), width=24, height=24, n_train=8, n_test=2, spp=4,
            relight=generate.DEFAULT_RELIGHT[:1], envmaps="sky")),
        (geometry_train.PRESETS, dataclasses.replace(
            geometry_train.get_config("cpu-small"), iterations=80, sh_degree=0, init_points=600,
            hull_resolution=16, normal_from=40, dist_from=60, lambda_dist=100.0, log_every=10,
            preview_every=40, checkpoint_every=25, checkpoint_seconds=0.5,
            densify=DensifyConfig(start=20, stop=60, interval=20, opacity_reset_interval=0,
                                  max_surfels=2000))),
        (segmentation.PRESETS, dataclasses.replace(
            segmentation.get_config("cpu-small"), iterations=40, n_samples=256, feature_dim=8,
            log_every=10, checkpoint_every=15, checkpoint_seconds=0.5)),
        (material_config.PRESETS, dataclasses.replace(
            material_config.get_config("cpu-small"), iterations=60, warmup=20, prune_every=10,
            warmup_map_resolution=32, refine_passes=((4.0, 2.0),), refine_views=4,
            refine_global=128, refine_global_map_resolution=32, refine_global_views=2,
            normal_steps=30, log_every=10, checkpoint_every=15, checkpoint_seconds=0.5)),
        (visibility.PRESETS, dataclasses.replace(visibility.get_config("cpu-small"),
                                                 resolution=64)),
        (relight.PRESETS, relight.get_config("cpu-small")),
        (export.PRESETS, export.get_config("cpu-small")),
        (masks.PRESETS, masks.get_config("cpu-small")),
    ]


def run_tree(stages: list[tuple[dict, object]]):
    """The test-tiny ``RunConfig``: every stage's test-tiny settings in one tree."""
    from mi_shadowgs.presets import RunConfig

    configs = {type(config).__name__: config for _, config in stages}
    return RunConfig(geometry=configs["GeometryConfig"],
                     segmentation=configs["SegmentationConfig"],
                     chromaticity=configs["ChromaticityConfig"],
                     visibility=configs["VisibilityConfig"], material=configs["MaterialConfig"],
                     relight=configs["RelightConfig"], export=configs["ExportConfig"],
                     preset=TINY, figure_views=1)


def main(argv: list[str]) -> int:
    from mi_shadowgs import cli

    for table, config in presets():
        table[TINY] = config
    if argv[:1] == ["--threads"]:
        import drjit as dr

        dr.set_thread_count(int(argv[1]))
        argv = argv[2:]
    return cli.main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
