"""Write a generated dataset in the NeRF-synthetic/TensoIR layout (see ``layout.py``).

``write_dataset`` checks every input first (scene, mesh, env map, output folder), then
renders into a hidden sibling ``.NAME.<fingerprint>.partial`` that is renamed into place at
the end: a half-written dataset never looks complete, and a failure before any rendering
writes nothing. Each file is written atomically and a view's image EXR last, so a view whose
EXR exists is finished: a killed run leaves the partial folder, and the same command again
renders only the views (and relit images) it lacks. The folder's name holds the
fingerprint of the settings, so only a run with the same settings reuses it; partial
folders of other settings are removed. ``dataset.json`` holds the fingerprint, so a re-run
with the same inputs is recognised, and the manifest (``mi_shadowgs.io.provenance``) lists the
files written: ``overwrite`` replaces a dataset only when the folder holds nothing else.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
import sys
from pathlib import Path

import numpy as np

from mi_shadowgs.core.directions import N_LIGHT_DIRECTIONS, directional_lights_to_map
from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.assets import ENVMAP_SUFFIXES, shipped_envmaps
from mi_shadowgs.dataset.cameras import test_cameras, train_cameras
from mi_shadowgs.dataset.capture import room_json
from mi_shadowgs.dataset.generate import (
    GenerateConfig,
    ViewRenderer,
    check_sampler,
    lit_scene,
    relight_lights,
    sky_envmap_image,
    trace_ground_truth,
)
from mi_shadowgs.dataset.photos import write_photos
from mi_shadowgs.dataset.scene import SceneSetup, load_scene
from mi_shadowgs.io.atomic import remove_stale, write_bytes, write_json
from mi_shadowgs.io.images import write_exr, write_png
from mi_shadowgs.io.provenance import (
    MANIFEST_NAME,
    Output,
    Provenance,
    check_output_location,
    clear,
    input_ref,
    read_manifest,
)


class OutputExistsError(FileExistsError):
    """The output folder already holds something other than this dataset."""


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fingerprint(setup: SceneSetup, config: GenerateConfig, seed: int,
                envmaps: list[EnvMap], photos: bool = False) -> str:
    """sha256 of everything that determines the dataset's content."""
    import mitsuba as mi

    digests = {name: _file_digest(path) for name, path in setup.inputs.items()}
    files = {name: digests.pop(name) for name in ("scene", "mesh") if name in digests}
    # The other files the scene read (parts, their meshes and textures): a key of its own,
    # only where there are any, so that datasets of scenes without them keep their prints.
    if digests:
        files["assets"] = digests
    # the env maps as resolved ("auto" depends on which shared files exist), by content
    files["envmaps"] = [[e.name, None if e.source is None else _file_digest(e.source)]
                        for e in envmaps]
    content = {"format": layout.FORMAT_VERSION, "files": files, "params": setup.params,
               "config": dataclasses.asdict(config), "seed": seed, "mitsuba": mi.__version__}
    if photos:  # only when asked: datasets without photos keep their fingerprints
        content["photos"] = True
    blob = json.dumps(content, sort_keys=True)
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
    if not any(out.iterdir()):  # an empty folder is free to use
        out.rmdir()
        return False
    # Files generate did not write are refused, with or without --overwrite: naming the flag
    # there sent the user to a second refusal.
    _check_only_ours(out)
    if overwrite:
        return False
    raise OutputExistsError(f"output folder {out} already holds a different dataset; pass "
                            "--overwrite to replace it")


# -- the manifest: what --overwrite may remove ------------------------------------------------
def _check_only_ours(out: Path) -> None:
    """OutputExistsError naming the first file or folder in ``out`` that generate did not
    write (not in its manifest)."""
    manifest = read_manifest(out)
    files = (set(manifest["files"]) if manifest and manifest.get("command") == "generate"
             else set())
    files.add(MANIFEST_NAME)
    folders = {str(Path(f).parent) for f in files}
    for p in sorted(out.rglob("*")):
        rel = p.relative_to(out).as_posix()
        if rel not in (folders if p.is_dir() and not p.is_symlink() else files):
            raise OutputExistsError(
                f"{p} was not written by mi-shadowgs generate (not in {out / MANIFEST_NAME}); "
                "--overwrite removes only files it wrote: move it away or choose another --out")


def _write_manifest(folder: Path, provenance: Provenance) -> None:
    out = Output(folder, "generate", provenance, None)
    out.claim(*sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                      if p.is_file()))
    out.finish()


def _remove_ours(folder: Path) -> None:
    """Delete what the manifest of ``folder`` lists and, when nothing else is left, it."""
    clear(folder)
    if not any(folder.iterdir()):
        folder.rmdir()


# -- the partial folder ---------------------------------------------------------------------------
def _partial_dir(out: Path, fp: str) -> Path:
    return out.with_name(f".{out.name}.{fp[:16]}.partial")


def _prepare_partial(out: Path, fp: str) -> Path:
    """The partial folder of these settings, created or kept; the partial folders of other
    settings (and of ``atomic_dir``, which wrote datasets before) are removed, and so are the
    temporaries of a file write that a kill cut short (hidden files: the layout has none)."""
    partial = _partial_dir(out, fp)
    remove_stale(out)  # what atomic_dir, which wrote datasets before, left
    pattern = re.compile(re.escape(f".{out.name}.") + r"[0-9a-f]{16}\.partial")
    for p in out.parent.iterdir() if out.parent.is_dir() else ():
        if p != partial and pattern.fullmatch(p.name) and p.is_dir():
            shutil.rmtree(p)
    partial.mkdir(parents=True, exist_ok=True)
    for p in partial.rglob(".*"):
        if p.is_file():
            p.unlink()
    return partial


def _swap_in(partial: Path, out: Path) -> None:
    """Move ``partial`` to ``out``; a dataset already there (``overwrite``, checked to hold
    only our files) goes aside to ``.NAME.old`` first and is then removed by its manifest."""
    old = out.with_name(f".{out.name}.old")
    if out.exists():
        os.replace(out, old)
    os.replace(partial, out)
    if old.exists():
        _remove_ours(old)


def _finish_swap(out: Path) -> None:
    """Complete a ``_swap_in`` that a kill cut short: between its two renames the previous
    dataset comes back; after them only its removal is left to do."""
    old = out.with_name(f".{out.name}.old")
    if old.is_dir():
        if out.exists():
            _remove_ours(old)
        else:
            os.replace(old, out)


def scene_box(setup: SceneSetup) -> list[list[float]]:
    """[[x, y, z] min, max] of every shape of the scene (object and base) in our world:
    the box NeRF tools should sample (nerfstudio's Blender reader assumes +-1.5)."""
    bbox = setup.scene.bbox()
    return [[round(float(v), 6) for v in bbox.min], [round(float(v), 6) for v in bbox.max]]


def _seed(seed: int, stream: int, index: int) -> int:
    """Per-render sampler seed, distinct per (stream, view), deterministic per dataset seed."""
    return (seed * 1_000_003 + stream * 100_003 + index) % (1 << 32)


def _write_view(root: Path, stem: str, rgba: np.ndarray, gt: dict, i: int,
                soft: bool = False) -> None:
    """The files of one view; its image EXR last, which marks the view finished."""
    # Straight alpha, as NeRF-synthetic's PNGs (the EXR stays premultiplied over black):
    # a premultiplied PNG read by NeRF tools gives silhouettes a dark fringe.
    alpha = rgba[..., 3:]
    straight = np.where(alpha > 0, rgba[..., :3] / np.maximum(alpha, 1e-12), 0.0)
    write_png(root / (stem + layout.IMAGE_PNG), np.concatenate([straight, alpha], axis=-1))
    write_exr(root / (stem + layout.ALBEDO), gt["albedo"][i])
    write_exr(root / (stem + layout.NORMAL), gt["normal"][i])
    write_exr(root / (stem + layout.DEPTH), gt["depth"][i])
    write_png(root / (stem + layout.MASK), (gt["object"][i] * 255).astype(np.uint8))
    write_png(root / (stem + layout.MATERIAL), gt["material"][i].astype(np.uint8))
    vis = gt["visibility"][i]
    if vis.shape[-1]:
        write_exr(root / (stem + layout.VISIBILITY), vis,
                  channels=[f"V{k:02d}" for k in range(vis.shape[-1])])
    if soft:  # a sphere lamp: its visible share beside the hard test of its centre
        write_exr(root / (stem + layout.VISIBILITY_SOFT), gt["visibility_soft"][i],
                  channels=[f"V{k:02d}" for k in range(vis.shape[-1])])
    for k in range(gt["irradiance"].shape[-2]):
        write_exr(root / (stem + layout.IRRADIANCE.format(k=k)), gt["irradiance"][i, :, :, k])
    write_exr(root / (stem + layout.IMAGE_EXR), rgba)


def envmap_relight_name(envmap: Path) -> str:
    return f"env_{Path(envmap).stem}"


@dataclasses.dataclass(frozen=True)
class EnvMap:
    """One env-map relit test set: its relighting name, the file it is copied from (None:
    the procedural sky, written from ``GenerateConfig.sky``) and its path in the dataset."""

    name: str
    source: Path | None
    ref: str  # relative to the dataset folder (lights.json's "path")


ENVMAP_KEYWORDS = ("auto", "sky", "none")


def resolve_envmaps(config: GenerateConfig) -> list[EnvMap]:
    """The env maps of ``config.envmaps`` (see ``GenerateConfig``), in order, checked:
    FileNotFoundError naming a missing file, ValueError for an unknown keyword or two maps
    of the same relighting name."""
    entries = ((config.envmaps,) if isinstance(config.envmaps, str)
               else tuple(config.envmaps))
    sources: list[Path | None] = []
    for entry in entries:
        entry = str(entry)
        if entry == "none":
            continue
        if entry == "auto":
            sources += shipped_envmaps() or [None]
        elif entry == "sky":
            sources.append(None)
        elif (Path(entry).suffix.lower() in ENVMAP_SUFFIXES or Path(entry).exists()
                or "/" in entry):
            path = Path(entry).resolve()
            if not path.is_file():
                raise FileNotFoundError(f"environment map not found: {path} (--envmap)")
            from mi_shadowgs.core.envmap import low_dynamic_range_warning

            if (note := low_dynamic_range_warning(path, "--envmap")) is not None:
                print(f"mi-shadowgs: warning: {note}", file=sys.stderr)
            sources.append(path)
        else:
            raise ValueError(f"envmaps entry {entry!r}: expected an env-map file "
                             f"({', '.join(ENVMAP_SUFFIXES)}) or one of {ENVMAP_KEYWORDS}")
    out: dict[str, EnvMap] = {}
    for src in sources:
        if src is None:
            if config.sky is None:
                continue  # no procedural sky configured: "sky" renders nothing
            env = EnvMap(envmap_relight_name(Path(layout.SKY_ENVMAP)), None, layout.SKY_ENVMAP)
        else:
            env = EnvMap(envmap_relight_name(src), src,
                         f"{layout.ENVMAP_DIR}/{src.stem}{src.suffix.lower()}")
        if env.name in out:
            if out[env.name] == env:
                continue  # the same map named twice ("auto" and its path)
            what = [str(e.source or "the procedural sky") for e in (out[env.name], env)]
            raise ValueError(f"env maps {what[0]} and {what[1]} would both be relighting "
                             f"{env.name!r}: rename one (--envmap)")
        out[env.name] = env
    return list(out.values())


def lights_json(setup: SceneSetup, config: GenerateConfig, envmaps: list[EnvMap]) -> dict:
    """``lights.json``: the training lights and light map, and every relighting (env maps
    named by their path inside the dataset)."""
    train = [lt.to_json() for lt in setup.lights]
    light_map = directional_lights_to_map(np.array([lt.direction for lt in setup.lights]),
                                          np.array([lt.irradiance for lt in setup.lights]))
    relit = [{"name": name, "type": "directional", "lights": [lt.to_json() for lt in lts]}
             for name, lts in relight_lights(config)]
    for env in envmaps:
        relit.append({"name": env.name, "type": "envmap", "path": env.ref,
                      "source": "procedural sky (GenerateConfig.sky)" if env.source is None
                      else str(env.source),
                      "scale": config.envmap_scale,
                      "convention": "Mitsuba lat-long envmap, Y-up, identity to_world"})
    for name, lts in setup.lamp_relights:  # after the env maps: their seeds stay
        relit.append({"name": name, "type": "point", "lights": [lt.to_json() for lt in lts]})
    training = {"lights": train,
                "light_map": {"grid": f"mi_shadowgs.core.directions.light_grid"
                                      f"({N_LIGHT_DIRECTIONS})",
                              "radiance": light_map.tolist()}}
    if setup.capture.has_room:
        training["room"] = room_json(setup.capture)
    convention = ("direction = unit vector toward the light (Y-up world); irradiance in "
                  "W/m^2 at normal incidence, linear RGB")
    if any(lt.is_lamp for lt in setup.lights) or setup.lamp_relights:
        convention += ("; a lamp's direction and irradiance are those at the object's "
                       "centre, its intensity (W/sr) = irradiance * distance^2, and "
                       "position, radius and distance are in world units")
    return {"convention": convention, "training": training, "relightings": relit}


def _cameras(setup, config: GenerateConfig, seed: int) -> dict[str, list]:
    """The training cameras (random on a sphere band, ``seed``) and the test ones (a spiral),
    looking at the object's centre."""
    rng = np.random.default_rng(seed)
    target = setup.object_center
    kw = dict(distance=config.camera_distance, fov_x=config.camera_angle_x,
              width=config.width, height=config.height)
    lo, hi = config.train_elevation_deg
    test_lo, test_hi = config.test_elevation_deg
    return {"train": train_cameras(config.n_train, rng, target, min_elevation_deg=lo,
                                   max_elevation_deg=hi, **kw),
            "test": test_cameras(config.n_test, target, min_elevation_deg=test_lo,
                                 max_elevation_deg=test_hi, **kw)}


def _envmap_relights(setup, config: GenerateConfig, envmaps, partial: Path) -> list:
    """(name, scene) of the env-map relightings, each map copied (or, for the sky, written)
    into the dataset, so that the evaluation reads what was rendered; named relative to it,
    since the partial folder is renamed."""
    out = []
    for env in envmaps:
        if env.source is None:
            write_exr(partial / env.ref, sky_envmap_image(config.sky))
        else:
            (partial / env.ref).parent.mkdir(parents=True, exist_ok=True)
            write_bytes(partial / env.ref, env.source.read_bytes())
        out.append((env.name, lit_scene(setup, envmap=str(partial / env.ref),
                                        envmap_scale=config.envmap_scale)))
    return out


def write_dataset(scene_path: str | Path, out: str | Path, config: GenerateConfig,
                  preset: str, seed: int = 0, overrides: dict[str, str] | None = None,
                  overwrite: bool = False, progress: bool = True,
                  photos: bool = False) -> tuple[Path, bool]:
    """Generate the dataset into ``out``. Returns (out, written); ``written`` is False when
    ``out`` already held this exact dataset. The env maps (``config.envmaps``) are copied
    into it, so that the evaluation reads what was rendered and the dataset's fingerprint
    covers them. ``photos`` also writes every view as a user's photo under ``photos/`` (see
    ``layout.PHOTOS``), the input of ``mi-shadowgs import``."""
    from tqdm import tqdm

    out = Path(out)
    check_sampler(config.sampler, config.samples_per_pass)  # before any folder is made
    envmaps = resolve_envmaps(config)
    setup = load_scene(scene_path, overrides)
    if not setup.lights:
        raise ValueError(f"{scene_path}: no light: neither a directional light (emitters "
                         "light0, light1, ...) nor a lamp (-D lamp_distance=...)")
    fp = fingerprint(setup, config, seed, envmaps, photos)
    inputs = {name: input_ref(path) for name, path in setup.inputs.items()}
    for env in envmaps:
        if env.source is not None:
            inputs[f"envmap {env.name}"] = input_ref(env.source)
    check_output_location(out, [i["path"] for i in inputs.values()], writes_dataset=True,
                          command="generate")
    _finish_swap(out)
    if _check_output(out, fp, overwrite):
        return out, False

    cams = _cameras(setup, config, seed)
    relights = [(name, lit_scene(setup, lights=lts)) for name, lts in relight_lights(config)]
    partial = _prepare_partial(out, fp)
    box = scene_box(setup)
    relights += _envmap_relights(setup, config, envmaps, partial)
    relights += [(name, lit_scene(setup, lights=lts)) for name, lts in setup.lamp_relights]
    renderer = ViewRenderer(cams["train"][0], config.spp, config.max_depth,
                            sampler=config.sampler, pass_spp=config.pass_spp)
    total = config.n_train + config.n_test * (1 + len(relights))
    # Ground truth for this many views at a time: what a kill loses beside one render.
    per_chunk = max(1, config.gt_chunk_rays // (config.width * config.height))
    soft = any(lt.is_lamp and lt.radius > 0 for lt in setup.lights)
    with tqdm(total=total, desc=f"generate {out.name}", unit="view",
              disable=not progress) as bar:
        for split_no, split in enumerate(layout.SPLITS):
            (partial / split).mkdir(exist_ok=True)
            views = cams[split]
            renders = 1 + (len(relights) if split == "test" else 0)
            todo = [i for i, _ in enumerate(views)
                    if not (partial / (layout.view_stem(split, i) + layout.IMAGE_EXR)).is_file()]
            bar.update((len(views) - len(todo)) * renders)
            for c0 in range(0, len(todo), per_chunk):
                chunk = todo[c0:c0 + per_chunk]
                gt = trace_ground_truth(setup, [views[i] for i in chunk],
                                        chunk_rays=config.gt_chunk_rays)
                for j, i in enumerate(chunk):
                    stem = layout.view_stem(split, i)
                    rgba = renderer.render(setup.path_traced, views[i],
                                           _seed(seed, split_no, i))
                    for k, (name, sc) in enumerate(relights if split == "test" else []):
                        path = partial / (stem + layout.RELIT.format(name=name))
                        if not path.is_file():  # a kill may have come after some of them
                            img = renderer.render(sc, views[i], _seed(seed, 2 + k, i))
                            img[..., 3] = rgba[..., 3]  # coverage does not depend on the light
                            write_exr(path, img)
                    _write_view(partial, stem, rgba, gt, j, soft)
                    bar.update(renders)
            frames = [cam.to_frame_json("./" + layout.view_stem(split, i))
                      for i, cam in enumerate(views)]
            meta = {"camera_angle_x": config.camera_angle_x, "w": config.width,
                    "h": config.height, "world_up": "+y", "scene_box": box, "frames": frames}
            write_json(partial / layout.transforms_name(split), meta)
            if split == "test":  # NeRF tools (nerfstudio) also load a val split: the test one
                write_json(partial / layout.transforms_name("val"), meta)
    if photos:
        write_photos(partial, setup.capture, seed)
    write_json(partial / layout.LIGHTS_JSON, lights_json(setup, config, envmaps))
    import mitsuba as mi

    write_json(partial / layout.DATASET_JSON, {
        "format_version": layout.FORMAT_VERSION,
        "scene": str(Path(scene_path).resolve()),
        "parameters": setup.params,
        "preset": preset,
        "config": dataclasses.asdict(config),
        "seed": seed,
        "envmaps": [env.ref for env in envmaps],
        "fingerprint": fp,
        "materials": setup.materials_json(),
        "object": {"center": setup.object_center.tolist(), "radius": setup.object_radius,
                   "to_world": setup.object_to_world.tolist()},
        "scene_box": box,
        layout.PNG_ALPHA_FIELD: "straight",
        "mitsuba_version": mi.__version__,
        "variant": mi.variant(),
    })
    _write_manifest(partial, Provenance(inputs=inputs, settings={"fingerprint": fp}))
    if out.exists():  # --overwrite: check again, files may have come while we rendered
        _check_only_ours(out)
    _swap_in(partial, out)
    return out, True
