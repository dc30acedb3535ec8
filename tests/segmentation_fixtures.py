"""Shared by the segmentation and mask tests: a tiny generated dataset of the default scene
and stand-in surfels on its true surfaces (stage 1 is not needed for stage 2's tests)."""

from __future__ import annotations

import dataclasses

SIZE = 48  # pixels: big enough for the base's shadows to span several pixels


def tiny_dataset(root):
    """A small dataset of the embedded default scene under ``root`` (about 10 s)."""
    from mi_shadowgs.dataset.writer import write_dataset
    from mi_shadowgs.presets import generate_config as get_config
    from mi_shadowgs.scenes import scene_path

    config = dataclasses.replace(get_config("cpu-small"), width=SIZE, height=SIZE, n_train=8,
                                 n_test=3, spp=16, relight=(), envmaps="sky")
    write_dataset(scene_path("default"), root, config, "test-tiny", seed=1, progress=False)
    return root


def standin_surfels(count: int = 3000, seed: int = 0):
    """Surfels sampled on the default scene's true shapes, and the scene set-up."""
    from mi_shadowgs.core.sampling import surfels_on_surface
    from mi_shadowgs.dataset.scene import load_scene
    from mi_shadowgs.scenes import scene_path

    setup = load_scene(scene_path("default"))
    return surfels_on_surface(list(setup.scene.shapes()), count, seed=seed), setup
