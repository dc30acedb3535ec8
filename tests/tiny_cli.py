"""``python -m tests.tiny_cli [--threads N] COMMAND ...``: the ``mi-shadowgs`` command line
with one more preset, ``test-tiny`` (in ``mi_shadowgs.presets``): 24 px views, seconds per
command, and checkpoints every few steps and every half second, so that a kill at any moment
finds some. ``-m MODULE ARGS`` runs another module's ``main`` with the preset instead
(``mi_shadowgs.cli``, ``validation.pipeline``: how a batch's workers start their steps).

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
    """(a preset table of ``mi_shadowgs.presets``, its test-tiny entry): the run's tree, the
    generator's and the importer's settings."""
    from mi_shadowgs import presets as run_presets
    from mi_shadowgs.dataset.generate import DEFAULT_RELIGHT
    from mi_shadowgs.stages.geometry.densify import DensifyConfig

    small = run_presets.get_config("cpu-small")
    tree = dataclasses.replace(
        small, preset=TINY, figure_views=1,
        geometry=dataclasses.replace(
            small.geometry, iterations=80, sh_degree=0, init_points=600, hull_resolution=16,
            normal_from=40, dist_from=60, lambda_dist=100.0, log_every=10, preview_every=40,
            checkpoint_every=25, checkpoint_seconds=0.5,
            densify=DensifyConfig(start=20, stop=60, interval=20, opacity_reset_interval=0,
                                  max_surfels=2000)),
        segmentation=dataclasses.replace(
            small.segmentation, iterations=40, n_samples=256, feature_dim=8, log_every=10,
            checkpoint_every=15, checkpoint_seconds=0.5),
        material=dataclasses.replace(
            small.material, iterations=60, warmup=20, prune_every=10,
            warmup_map_resolution=32, refine_passes=((4.0, 2.0),), refine_views=4,
            refine_global=128, refine_global_map_resolution=32, refine_global_views=2,
            normal_steps=30, log_every=10, checkpoint_every=15, checkpoint_seconds=0.5),
        visibility=dataclasses.replace(small.visibility, resolution=64))
    generate = dataclasses.replace(
        run_presets.generate_config("cpu-small"), width=24, height=24, n_train=8, n_test=2,
        spp=4, relight=DEFAULT_RELIGHT[:1], envmaps="sky")
    return [(run_presets.PRESETS, tree), (run_presets.GENERATE, generate),
            (run_presets.IMPORT, run_presets.import_config("cpu-small"))]


def set_sections(mp, name: str, **sections) -> None:
    """Patch (``mp``: a pytest MonkeyPatch) preset ``name``'s tree so that its stage
    ``sections`` are the configs given, e.g. ``set_sections(mp, "cpu-small", geometry=g)``."""
    from mi_shadowgs import presets as run_presets

    mp.setitem(run_presets.PRESETS, name,
               dataclasses.replace(run_presets.PRESETS[name], **sections))


def launcher():
    """How a batch's workers start their steps with the preset: through this module."""
    from pathlib import Path

    from mi_shadowgs.batch.runner import Launcher

    root = str(Path(__file__).resolve().parents[1])
    return Launcher(prefix=(sys.executable, "-m", "tests.tiny_cli", "-m"),
                    env=(("PYTHONPATH", root),), cwd=root)


def main(argv: list[str]) -> int:
    from mi_shadowgs import cli
    from mi_shadowgs.batch import runner

    for table, config in presets():
        table[TINY] = config
    runner.DEFAULT_LAUNCHER = launcher()  # a batch started here: its steps know it too
    if argv[:1] == ["--threads"]:
        import drjit as dr

        dr.set_thread_count(int(argv[1]))
        argv = argv[2:]
    if argv[:1] == ["-m"]:  # how a batch's worker starts its steps (tests/test_batch.py)
        import importlib

        module = importlib.import_module(argv[1])
        if hasattr(module, "TABLE_PRESETS"):
            module.TABLE_PRESETS = (*module.TABLE_PRESETS, TINY)
        return module.main(argv[2:])
    return cli.main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
