"""Images out: a surfel model's views rendered to files (``mi-shadowgs render``), and the
one way every command writes a premultiplied RGBA frame (EXR and PNG).

Per view (named after the frame's ``file_path``): ``NAME.exr`` linear RGBA (colour
premultiplied over black, or composited over ``background``), ``NAME.png`` an sRGB preview,
and for each AOV: ``NAME_AOV.exr`` plus a normalised ``NAME_AOV.png`` preview. The output
folder is new, or holds an earlier render: of the same model, cameras and settings it is
continued (a killed render keeps its finished views and renders only the missing ones; a
finished one is reused), of others it is refused unless ``overwrite``, which removes the
files its manifest lists (``mi_shadowgs.io.provenance``) so that old and new renders never
mix. It is never a dataset folder or inside one.

World frames are never guessed: the model's is its PLY's ``world_frame`` record (our PLYs
record it; an "opencv" export is read back into ours), else ``world_up`` ("+y" ours, "+z"
Blender's; ``--world-up``), else that of the cameras when they record theirs (a
``world_up`` field, or our ``dataset.json`` beside them): the model is then taken to be in
its cameras' frame, as given. When neither records a frame the render stops, asking for
``--world-up``. The cameras' frame is their record, else Blender's (NeRF-synthetic's
convention, as the dataset loader reads them). The cameras are turned into the model's
frame, never the model into theirs, so a model and cameras in one frame render as given.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

WORLD_UPS = ("+y", "+z")  # --world-up: ours, Blender's (turned by loader.BLENDER_TO_YUP)


def camera_frame(cameras: Path) -> str | None:
    """The world up axis a transforms file records: its ``world_up`` field, or ours ("+y")
    with our ``dataset.json`` beside it; None when it records none."""
    import json

    from mi_shadowgs.dataset import layout
    from mi_shadowgs.dataset.loader import WORLD_UP_FIELD, world_frame

    meta = json.loads(Path(cameras).read_text())
    if WORLD_UP_FIELD in meta or (Path(cameras).parent / layout.DATASET_JSON).is_file():
        return world_frame(Path(cameras), meta)
    return None


def model_world_up(model: Path, cameras: Path, recorded: str | None,
                   world_up: str | None) -> str:
    """The world up axis the model is rendered in (module docstring): "+y" for a PLY that
    records its frame (read into ours), else ``world_up``, else the cameras' recorded one;
    a ValueError (exit 2) asking for ``--world-up`` when neither input records a frame."""
    from mi_shadowgs.dataset.layout import DATASET_JSON
    from mi_shadowgs.dataset.loader import WORLD_UP_FIELD

    if world_up is not None and world_up not in WORLD_UPS:
        raise ValueError(f"--world-up must be one of {', '.join(WORLD_UPS)}, got {world_up!r}")
    if recorded is not None:
        if world_up not in (None, "+y"):
            raise ValueError(f"{model}: the PLY records its world frame ({recorded!r}, read "
                             f"as our Y-up world); --world-up {world_up} is for a PLY "
                             "without that record")
        return "+y"
    if world_up is not None:
        return world_up
    up = camera_frame(cameras)
    if up is None:
        raise ValueError(
            f"{model}: the PLY records no world frame, and {cameras} none either (no "
            f"'{WORLD_UP_FIELD}' field, no {DATASET_JSON} beside it): pass --world-up +z "
            "when the model was made from these cameras as they are (e.g. 3DGS or 2DGS "
            "trained on NeRF-synthetic; rendered in the cameras' frame as given), or "
            "--world-up +y when it is in our Y-up world (the cameras then read as "
            "Blender's Z-up, as the dataset loader reads them)")
    return up


def cameras_in(cameras: Path, up: str) -> list:
    """(file_path, Camera) per frame of ``cameras``, in the world whose up axis is ``up``:
    the file's own cameras turned from its frame (``camera_frame``, else Blender's)."""
    import dataclasses

    from mi_shadowgs.dataset.loader import BLENDER_TO_YUP, load_frames

    frames = load_frames(cameras, as_stored=True)
    own = camera_frame(cameras) or "+z"
    turn = (np.eye(4) if own == up else BLENDER_TO_YUP if up == "+y" else BLENDER_TO_YUP.T)
    return [(f.file_path, f.camera if own == up else
             dataclasses.replace(f.camera, c2w=turn @ f.camera.c2w)) for f in frames]


# AOVs whose preview is stretched over the covered pixels' range (see ``aov_preview``).
RANGE_AOVS = ("depth", "median_depth")


@dataclasses.dataclass(frozen=True)
class RenderResult:
    folder: Path
    views: int
    surfels: int
    rendered: int  # views this call rendered; the others were written by an earlier call


def write_rgba(folder: Path, name: str, rgb: np.ndarray, alpha: np.ndarray,
               composited: bool = False) -> None:
    """``NAME.exr`` linear RGBA of ``rgb`` [H, W, 3] (premultiplied) and ``alpha`` [H, W, 1],
    and ``NAME.png``: sRGB with straight alpha (PNG's), or the colour alone where it was
    ``composited`` over a background."""
    from mi_shadowgs.io.images import write_exr, write_png

    write_exr(folder / f"{name}.exr", np.concatenate([rgb, alpha], axis=-1))
    if composited:
        write_png(folder / f"{name}.png", rgb)
        return
    straight = np.where(alpha > 0, rgb / np.maximum(alpha, 1e-12), 0.0)
    write_png(folder / f"{name}.png", np.concatenate([straight, alpha], axis=-1))


def exr_channel_names(width: int) -> list[str]:
    if width in (1, 3):
        return ["Y"] if width == 1 else ["R", "G", "B"]
    return [f"C{i:02d}" for i in range(width)]  # zero-padded: EXR sorts channel names


def aov_preview(name: str, img: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """A displayable [H, W, 1 or 3] image in [0, 1] for AOV ``name`` (linear)."""
    covered = alpha[..., 0] > 0
    if name == "normal":
        return np.where(covered[..., None], img * 0.5 + 0.5, 0.0)
    if name == "alpha":
        return img
    if name in RANGE_AOVS:
        # min-max over covered pixels onto [0.1, 1], so the nearest surface is not black
        # like the background.
        vals = img[covered]
        lo, hi = (float(vals.min()), float(vals.max())) if vals.size else (0.0, 1.0)
        out = (img - lo) / max(hi - lo, 1e-12)
        return np.where(covered[..., None], 0.1 + 0.9 * np.clip(out, 0, 1), 0.0)
    if img.shape[-1] == 3 and name not in ("distortion", "count"):
        return img  # a colour-like channel (e.g. albedo): premultiplied linear colour
    img = img[..., :3] if img.shape[-1] >= 3 else img[..., :1]
    lo, hi = float(img.min()), float(img.max())
    return (img - lo) / max(hi - lo, 1e-12)


# A frame's ``file_path`` may name its image with its extension (nerfstudio's datasets
# do) or without (NeRF-synthetic's): the render's own files take the name without it.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")


def view_stems(names) -> list[str]:
    """File stems of the views: each frame's file name (without an image extension),
    numbered where two are equal (frames from different folders) or where a frame has
    none."""
    stems = [(p.stem if p.suffix.lower() in IMAGE_SUFFIXES else p.name) or f"view_{i:03d}"
             for i, p in enumerate(Path(name) for name in names)]
    if len(set(stems)) != len(stems):
        stems = [f"{i:03d}_{s}" for i, s in enumerate(stems)]
    return stems


def render_views(model: str | Path, cameras: str | Path, out: str | Path, aovs=(),
                 background=None, color_channel: str = "sh",
                 memory_budget: str | None = None, overwrite: bool = False,
                 progress: bool = True, sh_space: str | None = None,
                 world_up: str | None = None, frame: str | None = None) -> RenderResult:
    """Render the surfel PLY ``model`` from every view of the NeRF-synthetic ``cameras``
    file into the folder ``out`` (module docstring). Every argument is checked before any
    rendering: a missing file, an unknown AOV or colour channel, a bad background or
    budget raise an error naming it. ``sh_space``: what the PLY's SH hold ("linear" or
    "srgb"; default its header record, else linear: ``mi_shadowgs.io.ply``). ``frame``:
    the frame the PLY is stored in ("y-up", "opencv"; default its record), ``world_up``
    the up axis of a PLY without either (module docstring)."""
    from mi_shadowgs.core.memory import parse_bytes
    from mi_shadowgs.core.raster import RasterConfig
    from mi_shadowgs.core.render import (
        RenderError,
        aov_layout,
        check_color_channel,
        parse_background,
    )
    from mi_shadowgs.io.ply import frame_of, load_ply, sh_space_of
    from mi_shadowgs.io.provenance import Output, Provenance, input_ref
    from mi_shadowgs.stages.common import warn_other_backend

    model = Path(model)
    if not model.is_file():
        raise FileNotFoundError(f"model file not found: {model}")
    if not Path(cameras).is_file():
        raise FileNotFoundError(f"cameras file not found: {cameras}")
    sh_space = sh_space_of(model, sh_space)
    frame = frame_of(model, frame)
    up = model_world_up(model, Path(cameras), frame, world_up)
    views = cameras_in(Path(cameras), up)
    surfels = load_ply(model, sh_space, frame)
    aovs = list(dict.fromkeys(aovs))
    aov_layout(aovs, surfels)  # unknown names fail before any rendering
    background = parse_background(background, "--background")
    raster = (RasterConfig() if memory_budget is None else
              RasterConfig(memory_budget_bytes=parse_bytes(memory_budget, "--memory-budget")))
    try:  # a channel of another width than 1, 3 (sh: 3(d+1)^2) too, not at the first view
        check_color_channel(surfels, color_channel)
    except RenderError as exc:
        raise RenderError(f"{model}: --color-channel: {exc}") from None
    stems = view_stems(name for name, _ in views)
    provenance = Provenance(
        inputs={"model": input_ref(model), "cameras": input_ref(cameras)},
        settings={"aovs": aovs, "background": background, "color_channel": color_channel,
                  "sh_space": sh_space, "world_up": up,
                  "ply_frame": "opencv" if frame == "opencv" else "y-up"})
    suffixes = [".exr", ".png"] + [f"_{a}{ext}" for a in aovs for ext in (".exr", ".png")]
    with Output.open(out, "render", provenance, overwrite=overwrite, reuse=True,
                     inputs=[model, cameras]) as output:
        if output.complete:
            return RenderResult(output.folder, len(views), surfels.count, 0)
        output.claim(*(f"{stem}{suffix}" for stem in stems for suffix in suffixes))
        warn_other_backend(output)  # views of an earlier call on another backend stay
        todo = missing_views(output.folder, stems, suffixes)
        _render(output.folder, surfels, [(stems[i], views[i][1]) for i in todo], len(stems),
                aovs, background, color_channel, raster, progress)
        output.finish()
    return RenderResult(output.folder, len(views), surfels.count, len(todo))


def missing_views(folder: Path, stems, suffixes) -> list[int]:
    """Indices of the views that lack one of their files ``STEM + suffix`` in ``folder``.

    Only a continued output (its provenance matched) holds any: each file is written
    atomically, so one that exists is whole and made from these inputs and settings; a view
    a kill cut short between its files is rendered again, to the same bytes."""
    return [i for i, stem in enumerate(stems)
            if not all((folder / f"{stem}{suffix}").is_file() for suffix in suffixes)]


def _render(folder: Path, surfels, views, total: int, aovs, background, color_channel,
            raster, progress: bool) -> None:
    """Render and write ``views`` ((stem, camera) pairs): the missing ones of the output's
    ``total``."""
    from tqdm import tqdm

    from mi_shadowgs.core.render import render_surfels
    from mi_shadowgs.io.images import write_exr, write_png

    for stem, camera in tqdm(views, desc="render", unit="view", total=total,
                             initial=total - len(views), disable=not progress):
        images = render_surfels(surfels, camera, color_channel=color_channel, aovs=aovs,
                                background=background, config=raster)
        arrays = {k: np.asarray(v.numpy(), dtype=np.float32) for k, v in images.items()}
        alpha = arrays["alpha"]
        write_rgba(folder, stem, arrays["rgb"], alpha, composited=background is not None)
        for name in aovs:
            img = arrays[name]
            write_exr(folder / f"{stem}_{name}.exr", img,
                      channels=exr_channel_names(img.shape[-1]))
            write_png(folder / f"{stem}_{name}.png", aov_preview(name, img, alpha),
                      srgb=name not in ("normal", "alpha") + RANGE_AOVS)
