"""Write a generated dataset in the NeRF-synthetic/TensoIR layout (see ``layout.py``), atomically.

``write_dataset`` checks every input first (scene, mesh, env map, output folder), then
builds the whole dataset in a temporary sibling folder that is renamed into place at the
end (``mi_shadowgs.atomic.atomic_dir``): a half-written dataset never looks complete, and a
failure writes nothing. ``dataset.json`` holds a fingerprint of the inputs, so a re-run with
the same inputs is recognised, and a folder holding a different dataset is an error unless
``overwrite``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np

from ..atomic import atomic_dir, write_json
from ..directions import N_LIGHT_DIRECTIONS, directional_lights_to_map
from ..imageio import write_exr, write_png
from . import layout
from .cameras import test_cameras, train_cameras
from .generate import (
    GenerateConfig,
    ViewRenderer,
    lit_scene,
    relight_lights,
    trace_ground_truth,
)
from .scene import SceneSetup, load_scene


class OutputExistsError(FileExistsError):
    """The output folder already holds something other than this dataset."""


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fingerprint(setup: SceneSetup, config: GenerateConfig, seed: int,
                envmap: Path | None) -> str:
    """sha256 of everything that determines the dataset's content."""
    import mitsuba as mi

    files = {"scene": _file_digest(setup.path)}
    for key in ("mesh",):
        if setup.params.get(key):
            files[key] = _file_digest(Path(setup.params[key]))
    if envmap is not None:
        files["envmap"] = _file_digest(envmap)
    blob = json.dumps({"format": layout.FORMAT_VERSION, "files": files,
                       "params": setup.params, "config": dataclasses.asdict(config),
                       "seed": seed, "mitsuba": mi.__version__}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def _check_output(out: Path, fp: str, overwrite: bool) -> bool:
    """True when ``out`` already holds exactly this dataset (nothing to do)."""
    if not out.exists():
        return False
    if not out.is_dir():
        raise OutputExistsError(f"output {out} exists and is not a folder")
    info_path = out / layout.DATASET_JSON
    if info_path.is_file():
        try:
            old = json.loads(info_path.read_text()).get("fingerprint")
        except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
            old = None
        if old == fp and not overwrite:
            return True
    if overwrite:
        return False
    if not any(out.iterdir()):  # an empty folder is free to use
        out.rmdir()
        return False
    what = "a different dataset" if info_path.is_file() else "other files"
    raise OutputExistsError(f"output folder {out} already holds {what}; pass --overwrite to "
                            "replace it")


def _seed(seed: int, stream: int, index: int) -> int:
    """Per-render sampler seed, distinct per (stream, view), deterministic per dataset seed."""
    return (seed * 1_000_003 + stream * 100_003 + index) % (1 << 32)


def _write_view(root: Path, stem: str, rgba: np.ndarray, gt: dict, i: int) -> None:
    write_exr(root / (stem + layout.IMAGE_EXR), rgba)
    write_png(root / (stem + layout.IMAGE_PNG), rgba)
    write_exr(root / (stem + layout.ALBEDO), gt["albedo"][i])
    write_exr(root / (stem + layout.NORMAL), gt["normal"][i])
    write_exr(root / (stem + layout.DEPTH), gt["depth"][i])
    write_png(root / (stem + layout.MASK), (gt["object"][i] * 255).astype(np.uint8))
    write_png(root / (stem + layout.MATERIAL), gt["material"][i].astype(np.uint8))
    vis = gt["visibility"][i]
    if vis.shape[-1]:
        write_exr(root / (stem + layout.VISIBILITY), vis,
                  channels=[f"V{k:02d}" for k in range(vis.shape[-1])])
    for k in range(gt["irradiance"].shape[-2]):
        write_exr(root / (stem + layout.IRRADIANCE.format(k=k)), gt["irradiance"][i, :, :, k])


def lights_json(setup: SceneSetup, config: GenerateConfig, envmap: Path | None) -> dict:
    train = [lt.to_json() for lt in setup.lights]
    light_map = directional_lights_to_map(np.array([lt.direction for lt in setup.lights]),
                                          np.array([lt.irradiance for lt in setup.lights]))
    relit = [{"name": name, "type": "directional", "lights": [lt.to_json() for lt in lts]}
             for name, lts in relight_lights(config)]
    if envmap is not None:
        relit.append({"name": f"env_{envmap.stem}", "type": "envmap", "path": str(envmap),
                      "scale": config.envmap_scale,
                      "convention": "Mitsuba lat-long envmap, Y-up, identity to_world"})
    return {
        "convention": "direction = unit vector toward the light (Y-up world); irradiance in "
                      "W/m^2 at normal incidence, linear RGB",
        "training": {"lights": train,
                     "light_map": {"grid": f"mi_shadowgs.directions.light_grid"
                                           f"({N_LIGHT_DIRECTIONS})",
                                   "radiance": light_map.tolist()}},
        "relightings": relit,
    }


def write_dataset(scene_path: str | Path, out: str | Path, config: GenerateConfig,
                  preset: str, seed: int = 0, overrides: dict[str, str] | None = None,
                  envmap: str | Path | None = None, overwrite: bool = False,
                  progress: bool = True) -> tuple[Path, bool]:
    """Generate the dataset into ``out``. Returns (out, written); ``written`` is False when
    ``out`` already held this exact dataset."""
    from tqdm import tqdm

    out = Path(out)
    envmap = Path(envmap).resolve() if envmap is not None else None
    if envmap is not None and not envmap.is_file():
        raise FileNotFoundError(f"environment map not found: {envmap} (--envmap)")
    setup = load_scene(scene_path, overrides)
    if not setup.lights:
        raise ValueError(f"{scene_path}: no directional light (emitters light0, light1, ...)")
    fp = fingerprint(setup, config, seed, envmap)
    if _check_output(out, fp, overwrite):
        return out, False

    rng = np.random.default_rng(seed)
    target = setup.object_center
    kw = dict(distance=config.camera_distance, fov_x=config.camera_angle_x,
              width=config.width, height=config.height)
    lo, hi = config.train_elevation_deg
    cams = {"train": train_cameras(config.n_train, rng, target, min_elevation_deg=lo,
                                   max_elevation_deg=hi, **kw),
            "test": test_cameras(config.n_test, target, min_elevation_deg=config.
                                 test_elevation_deg[0],
                                 max_elevation_deg=config.test_elevation_deg[1], **kw)}
    relights = [(name, lit_scene(setup, lights=lts)) for name, lts in relight_lights(config)]
    if envmap is not None:
        relights.append((f"env_{envmap.stem}", lit_scene(setup, envmap=str(envmap),
                                                          envmap_scale=config.envmap_scale)))
    renderer = ViewRenderer(cams["train"][0], config.spp, config.max_depth)
    total = config.n_train + config.n_test * (1 + len(relights))
    with atomic_dir(out, overwrite=overwrite) as tmp, \
            tqdm(total=total, desc=f"generate {out.name}", unit="view",
                 disable=not progress) as bar:
        for split_no, split in enumerate(layout.SPLITS):
            (tmp / split).mkdir()
            views = cams[split]
            gt = trace_ground_truth(setup, views, chunk_rays=config.gt_chunk_rays)
            frames = []
            for i, cam in enumerate(views):
                stem = layout.view_stem(split, i)
                rgba = renderer.render(setup.scene, cam, _seed(seed, split_no, i))
                _write_view(tmp, stem, rgba, gt, i)
                bar.update()
                if split == "test":
                    for j, (name, sc) in enumerate(relights):
                        img = renderer.render(sc, cam, _seed(seed, 2 + j, i))
                        img[..., 3] = rgba[..., 3]  # coverage does not depend on the light
                        write_exr(tmp / (stem + layout.RELIT.format(name=name)), img)
                        bar.update()
                frames.append(cam.to_frame_json("./" + stem))
            write_json(tmp / layout.transforms_name(split),
                       {"camera_angle_x": config.camera_angle_x, "w": config.width,
                        "h": config.height, "frames": frames})
        write_json(tmp / layout.LIGHTS_JSON, lights_json(setup, config, envmap))
        import mitsuba as mi

        write_json(tmp / layout.DATASET_JSON, {
            "format_version": layout.FORMAT_VERSION,
            "scene": str(Path(scene_path).resolve()),
            "parameters": setup.params,
            "preset": preset,
            "config": dataclasses.asdict(config),
            "seed": seed,
            "envmap": str(envmap) if envmap else None,
            "fingerprint": fp,
            "materials": setup.materials_json(),
            "object": {"center": setup.object_center.tolist(), "radius": setup.object_radius,
                       "to_world": setup.object_to_world.tolist()},
            "mitsuba_version": mi.__version__,
            "variant": mi.variant(),
        })
    return out, True
