"""The one dataset reader: our generated layout, NeRF-synthetic, and TensoIR's per-view folders.

- ``load_cameras(transforms_json)``: the cameras of a NeRF-synthetic ``transforms_*.json``.
- ``load_dataset(dir, split)``: every view of a split as numpy arrays (see ``View``), plus
  ``lights.json`` and ``dataset.json`` when present.

Worlds are Y-up (docs/conventions.md). NeRF-synthetic's and TensoIR's folders come from
Blender (Z-up); their cameras (and TensoIR's normals) are turned into our Y-up world
(``x, y, z = x_b, z_b, -y_b``). A transforms file says which frame it is in by its
``world_up`` field; without one, ours is recognised by ``dataset.json`` beside it.
nerfstudio intrinsics (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``k1..k4``, ``p1``, ``p2``) are
honoured: images are undistorted to the pinhole the cameras describe.
Errors name the file and the field at fault.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import sys
from pathlib import Path

import numpy as np

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.distortion import FIELDS, Distortion, undistort
from mi_shadowgs.dataset.poses import (
    PoseError,
    check_intrinsics,
    check_pose,
    duplicate_images,
    scaled_note,
)
from mi_shadowgs.io.images import read_exr, read_png, srgb_to_linear

# Blender Z-up world -> our Y-up world (a rotation of -90 degrees about +X).
BLENDER_TO_YUP = np.array([[1.0, 0.0, 0.0, 0.0],
                           [0.0, 0.0, 1.0, 0.0],
                           [0.0, -1.0, 0.0, 0.0],
                           [0.0, 0.0, 0.0, 1.0]])


class DatasetError(ValueError):
    """A dataset file is missing, malformed or inconsistent; the message names it."""


@dataclasses.dataclass
class View:
    """One view. Arrays are [H, W, ...] with row 0 at the top; None where not in the dataset."""

    name: str
    camera: Camera
    image: np.ndarray  # [H, W, 3] linear RGB
    mask: np.ndarray  # [H, W] bool: covered (object plus base; object only for TensoIR)
    object_mask: np.ndarray | None = None  # [H, W] bool: object parts only
    albedo: np.ndarray | None = None  # [H, W, 3] linear
    normal: np.ndarray | None = None  # [H, W, 3] unit world-space, 0 on background
    depth: np.ndarray | None = None  # [H, W] z-depth, 0 on background
    material: np.ndarray | None = None  # [H, W] int32 material id (0 = background)
    visibility: np.ndarray | None = None  # [H, W, L] per training light, 1 = unoccluded
    irradiance: np.ndarray | None = None  # [H, W, L, 3] direct diffuse irradiance per light
    relit: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # name -> [H, W, 3]
    has_mask: bool = True  # False: no alpha and no mask file; ``mask`` is then all True


@dataclasses.dataclass
class Dataset:
    root: Path
    split: str
    views: list[View]
    lights: dict | None = None  # lights.json
    info: dict | None = None  # dataset.json
    layout: str = "nerf"  # "nerf" (ours and NeRF-synthetic) or "tensoir"
    points: Path | None = None  # SfM points in our frame (``points3d.ply`` of an import)

    @property
    def has_masks(self) -> bool:
        """Every view has a real mask (alpha); else stage 1 works without masks."""
        return all(v.has_mask for v in self.views)

    def __len__(self) -> int:
        return len(self.views)

    @property
    def cameras(self) -> list[Camera]:
        return [v.camera for v in self.views]

    def stack(self, field: str) -> np.ndarray:
        """All views' ``field`` stacked: [N, H, W, ...]."""
        arrays = [getattr(v, field) for v in self.views]
        if any(a is None for a in arrays):
            raise DatasetError(f"{self.root}: split {self.split!r} has no {field!r} for "
                               "every view")
        return np.stack(arrays)


# -- JSON helpers -------------------------------------------------------------------------
def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: malformed JSON: {exc}") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    return data


def _check_fields_read(root: Path, info: dict | None, lights: dict | None) -> None:
    """The kinds of the dataset.json and lights.json fields that the loader and the stages
    read by name (a DatasetError naming the file and field): a number where an object or a
    list belongs failed later with a TypeError, some after training."""
    def kind(path: Path, doc: dict | None, field: str, want: type, items: type | None = None,
             name: str | None = None):
        value = (doc or {}).get(field)
        if value is None:
            return
        if (not isinstance(value, want)
                or (items is not None and not all(isinstance(v, items) for v in value))):
            what = ({dict: "an object", list: "a list"}[want]
                    + ("" if items is None else " of objects"))
            raise DatasetError(f"{path}: field {name or repr(field)} must be {what}, got {value!r}")

    kind(root / layout.DATASET_JSON, info, "materials", list, dict)
    kind(root / layout.LIGHTS_JSON, lights, "training", dict)
    kind(root / layout.LIGHTS_JSON, lights, "relightings", list, dict)
    training = (lights or {}).get("training") or {}
    kind(root / layout.LIGHTS_JSON, training, "lights", list, dict, "'training.lights'")


def _number(path: Path, field: str, value) -> float:
    if (isinstance(value, bool) or not isinstance(value, (int, float))
            or not math.isfinite(float(value))):
        raise DatasetError(f"{path}: field {field!r} must be a finite number, got {value!r}")
    return float(value)


def _matrix(path: Path, field: str, value) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: field {field!r} must be a 4x4 matrix of numbers") from None
    if m.shape == (3, 4):  # some exporters drop the last row
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise DatasetError(f"{path}: field {field!r} must be a 4x4 matrix, got shape {m.shape}")
    return m


def _pose(path: Path, field: str, value, scaled: dict[int, float], frame: int) -> np.ndarray:
    """``_matrix`` checked as a camera pose (``poses.check_pose``); a uniform scale divided
    out of its rotation is recorded in ``scaled`` by frame, for one note per file."""
    try:
        m, scale = check_pose(_matrix(path, field, value))
    except PoseError as exc:
        raise DatasetError(f"{path}: field {field!r} {exc}") from None
    if scale is not None:
        scaled[frame] = scale
    return m


_NOTED: set[str] = set()  # files whose scaled rotations were noted: once per process


def _note_scaled(path: Path, scaled: dict[int, float]) -> None:
    if scaled and str(path.resolve()) not in _NOTED:
        _NOTED.add(str(path.resolve()))
        print(f"mi-shadowgs: note: {scaled_note(path, sorted(scaled), list(scaled.values()))}",
              file=sys.stderr)


def _image_file(root: Path, file_path: str, exts=(".exr", ".png")) -> Path | None:
    """The image a frame's ``file_path`` names (NeRF-synthetic leaves the extension out)."""
    base = root / file_path
    if base.suffix.lower() in (".png", ".exr", ".jpg", ".jpeg") and base.is_file():
        return base
    for ext in exts:
        p = base.with_name(base.name + ext)
        if p.is_file():
            return p
    return None


def _image_size(path: Path) -> tuple[int, int]:
    img = read_exr(path) if path.suffix.lower() == ".exr" else read_png(path)
    return img.shape[1], img.shape[0]


# -- cameras ------------------------------------------------------------------------------
WORLD_UP_FIELD = "world_up"  # "+y": our frame as it is; "+z": Blender's, turned to Y-up
# nerfstudio camera models we honour (distortion undone by dataset.distortion)
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL")


def world_frame(path: Path, meta: dict) -> str:
    """The world's up axis of a transforms file: its ``world_up`` field; else ours ("+y")
    when our ``dataset.json`` lies beside it; else NeRF-synthetic's Blender frame ("+z")."""
    if WORLD_UP_FIELD in meta:
        up = meta[WORLD_UP_FIELD]
        if up not in ("+y", "+z"):
            raise DatasetError(f"{path}: field {WORLD_UP_FIELD!r} must be \"+y\" or \"+z\", "
                               f"got {up!r}")
        return up
    return "+y" if (path.parent / layout.DATASET_JSON).is_file() else "+z"


@dataclasses.dataclass(frozen=True)
class Frame:
    file_path: str
    camera: Camera  # pinhole, in our Y-up world
    distortion: Distortion | None = None  # lens distortion of the stored image, if any
    to_ours: np.ndarray | None = None  # [3, 3] rotation of world vectors (normals) to Y-up


def _intrinsics(path: Path, meta: dict, fr: dict, i: int, width: int, height: int):
    """(fx, fy, cx, cy, Distortion | None) of frame ``i``: per-frame fields win over the
    file's (nerfstudio); else ``camera_angle_x`` (NeRF-synthetic) with a centred pinhole."""
    def get(key):
        if key in fr:
            return _number(path, f"frames[{i}].{key}", fr[key])
        return _number(path, key, meta[key]) if key in meta else None

    model = fr.get("camera_model", meta.get("camera_model"))
    if model is not None and model not in _PINHOLE_MODELS:
        raise DatasetError(f"{path}: field 'camera_model' {model!r} is not supported "
                           f"(only {', '.join(_PINHOLE_MODELS)}); undistort the images first")
    fx, fy = get("fl_x"), get("fl_y")
    fov_x = None
    if fx is None:
        if fy is not None:
            raise DatasetError(f"{path}: field 'fl_y' without 'fl_x'")
        if "camera_angle_x" not in meta:
            raise DatasetError(f"{path}: missing field 'camera_angle_x' (or 'fl_x')")
        fov_x = _number(path, "camera_angle_x", meta["camera_angle_x"])
        if not 0.0 < fov_x < math.pi:
            raise DatasetError(f"{path}: field 'camera_angle_x' must be in (0, pi) radians, "
                               f"got {fov_x}")
        fx = 0.5 * width / math.tan(0.5 * fov_x)
    fy = fx if fy is None else fy
    cx, cy = get("cx"), get("cy")
    cx = 0.5 * width if cx is None else cx
    cy = 0.5 * height if cy is None else cy
    where = "frames[{i}]." if any(k in fr for k in ("fl_x", "fl_y", "cx", "cy")) else ""
    for key, v in (("fl_x", fx), ("fl_y", fy)):
        if v <= 0:
            raise DatasetError(f"{path}: field '{where.format(i=i)}{key}' must be > 0, got {v}")
    try:
        check_intrinsics(width, height, fx, fy)
    except PoseError as exc:
        field = "camera_angle_x" if fov_x is not None else f"{where.format(i=i)}fl_x/fl_y"
        raise DatasetError(f"{path}: field '{field}' (frame {i}): {exc}") from None
    for key, v, size in (("cx", cx, width), ("cy", cy, height)):
        if not 0.0 < v < size:  # a principal point outside the image contradicts its size
            raise DatasetError(f"{path}: field '{where.format(i=i)}{key}' = {v} lies outside "
                               f"the {width}x{height} image")
    values = {k: get(k) for k in FIELDS}
    dist = Distortion(**{k: (v or 0.0) for k, v in values.items()})
    # NeRF-synthetic's angle kept as given (no round trip through fx): same bits as before
    centred = fy == fx and cx == 0.5 * width and cy == 0.5 * height
    return fx, fy, cx, cy, (None if dist.is_identity else dist), (fov_x if centred else None)


def load_frames(path: str | Path, as_stored: bool = False) -> list[Frame]:
    """Every frame of a NeRF-synthetic or nerfstudio-style ``transforms_*.json``.

    The image size comes from ``w``/``h`` when present, else from the first frame's image.
    Matrices are OpenGL camera-to-world (docs/conventions.md); a Blender Z-up world (see
    ``world_frame``) is turned to Y-up. Intrinsics: ``fl_x``, ``fl_y``, ``cx``, ``cy`` and
    distortion ``k1..k4``, ``p1``, ``p2`` (top level or per frame), else ``camera_angle_x``.
    """
    path = Path(path)
    meta = _read_json(path)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: field 'frames' must be a non-empty list")
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise DatasetError(f"{path}: field 'frames[{i}]' must be an object")
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise DatasetError(f"{path}: missing field 'frames[{i}].{key}'")
        if not isinstance(fr["file_path"], str):
            raise DatasetError(f"{path}: field 'frames[{i}].file_path' must be a string")
    if "w" in meta or "h" in meta:
        for key in ("w", "h"):
            if key not in meta:
                raise DatasetError(f"{path}: field 'w' and 'h' go together; {key!r} is missing")
        width = int(_number(path, "w", meta["w"]))
        height = int(_number(path, "h", meta["h"]))
    else:
        first = _image_file(path.parent, frames[0]["file_path"])
        if first is None:
            raise DatasetError(f"{path}: no 'w'/'h' and the image of 'frames[0].file_path' "
                               f"({frames[0]['file_path']!r}) is missing")
        width, height = _image_size(first)
    if width < 1 or height < 1:
        raise DatasetError(f"{path}: image size must be positive, got {width}x{height}")
    # as_stored: the file's own world, whatever it is (the importer places it itself)
    blender = not as_stored and world_frame(path, meta) == "+z"
    to_ours = BLENDER_TO_YUP if blender else np.eye(4)
    out, scaled = [], {}
    if (pair := duplicate_images([_same_image(fr["file_path"]) for fr in frames])) is not None:
        a, b = pair
        raise DatasetError(f"{path}: frames {a} and {b} name one image file "
                           f"({frames[b]['file_path']!r}, field 'frames[{b}].file_path'): "
                           "one photo cannot have two poses")
    for i, fr in enumerate(frames):
        c2w = _pose(path, f"frames[{i}].transform_matrix", fr["transform_matrix"], scaled, i)
        fx, fy, cx, cy, dist, fov_x = _intrinsics(path, meta, fr, i, width, height)
        cam = (Camera(c2w=to_ours @ c2w, width=width, height=height, fov_x=fov_x)
               if fov_x is not None
               else Camera.from_intrinsics(to_ours @ c2w, width, height, fx, fy, cx, cy))
        out.append(Frame(fr["file_path"], cam, dist, BLENDER_TO_YUP[:3, :3] if blender else None))
    _note_scaled(path, scaled)
    return out


def _same_image(file_path: str) -> str:
    """A frame's ``file_path`` as one image file: ``./a/b`` and ``a//b.png`` are ``a/b``
    (NeRF-synthetic leaves the extension out)."""
    p = os.path.normpath(file_path)
    stem, ext = os.path.splitext(p)
    return stem if ext.lower() in (".png", ".exr", ".jpg", ".jpeg") else p


def load_cameras(path: str | Path) -> list[tuple[str, Camera]]:
    """(file_path, Camera) per frame of a ``transforms_*.json`` (see ``load_frames``); the
    cameras are the pinholes of the undistorted images."""
    return [(f.file_path, f.camera) for f in load_frames(path)]


# -- our layout / NeRF-synthetic ----------------------------------------------------------
def _read_image(path: Path) -> np.ndarray:
    """Linear float [H, W, C]: EXR as stored, PNG decoded from sRGB (alpha stays linear)."""
    if path.suffix.lower() == ".exr":
        return _as_rgb(path, read_exr(path).astype(np.float32))
    img = _png_unit(path)
    c = img.shape[-1]
    if c in (2, 4):
        return np.concatenate([srgb_to_linear(img[..., :-1]), img[..., -1:]], axis=-1)
    return srgb_to_linear(img)


def _png_unit(path: Path) -> np.ndarray:
    """A PNG as float [H, W, 3 or 4] in [0, 1]: 8- or 16-bit (scaled by its own maximum, not
    by 255), grey (+ alpha) made RGB (+ alpha)."""
    raw = read_png(path)
    if raw.dtype.kind not in "ui":
        raise DatasetError(f"{path}: PNG samples of type {raw.dtype} are not supported "
                           "(8- or 16-bit integers)")
    return _as_rgb(path, raw.astype(np.float32) / float(np.iinfo(raw.dtype).max))


def _as_rgb(path: Path, img: np.ndarray) -> np.ndarray:
    """Grey [H, W, 1] or grey + alpha [H, W, 2] as RGB (+ alpha); RGB(A) as it is."""
    c = img.shape[-1]
    if c == 1:
        return np.repeat(img, 3, axis=-1)
    if c == 2:
        return np.concatenate([np.repeat(img[..., :1], 3, axis=-1), img[..., 1:]], axis=-1)
    if c not in (3, 4):
        raise DatasetError(f"{path}: an image of {c} channels; grey, grey + alpha, RGB or "
                           "RGBA is expected")
    return img


def _check_size(path: Path, arr: np.ndarray, cam: Camera) -> np.ndarray:
    if arr.shape[:2] != (cam.height, cam.width):
        raise DatasetError(f"{path}: image is {arr.shape[1]}x{arr.shape[0]}, the transforms "
                           f"say {cam.width}x{cam.height}")
    return arr


def _view_stem(file_path: str) -> str:
    """A frame's ``file_path`` without its image's extension: what its buffers' names extend."""
    stem = (str(Path(file_path).with_suffix(""))
            if Path(file_path).suffix.lower() in (".png", ".exr") else file_path)
    return stem[2:] if stem.startswith("./") else stem


def _view_buffers(root: Path, stem: str, n_lights: int, relit_names) -> dict[str, Path]:
    """suffix -> file of each per-view buffer (``layout``'s suffixes) the view has: every
    file besides its image that ``_load_nerf_view`` reads."""
    suffixes = (layout.MASK, layout.ALBEDO, layout.NORMAL, layout.DEPTH, layout.MATERIAL,
                layout.VISIBILITY, *(layout.IRRADIANCE.format(k=k) for k in range(n_lights)),
                *(layout.RELIT.format(name=name) for name in relit_names))
    found = {s: root / (stem + s) for s in suffixes}
    return {s: p for s, p in found.items() if p.is_file()}


def _load_nerf_view(root: Path, file_path: str, cam: Camera, n_lights: int,
                    relit_names: list[str], tpath: Path, index: int,
                    require_mask: bool, distortion: Distortion | None = None,
                    to_ours: np.ndarray | None = None, no_masks: bool = False) -> View:
    img_path = _image_file(root, file_path)
    if img_path is None:
        raise DatasetError(f"{tpath}: the image of frame {index} ({file_path!r}) is missing "
                           f"under {root}")
    stem = _view_stem(file_path)
    buffers = _view_buffers(root, stem, n_lights, relit_names)
    rgba = _check_size(img_path, _read_image(img_path), cam)
    has_mask = rgba.shape[-1] == 4 and not no_masks
    if rgba.shape[-1] != 4:
        rgba = np.concatenate([rgba[..., :3], np.ones_like(rgba[..., :1])], axis=-1)
    if distortion is not None:
        # Pixels that map outside the photo get alpha 0: nothing was seen there.
        rgba, _ = undistort(rgba, cam, distortion)
        extra = [s for s in (layout.ALBEDO, layout.NORMAL, layout.DEPTH, layout.MATERIAL,
                             layout.VISIBILITY) if s in buffers]
        if extra:
            raise DatasetError(f"{tpath}: frame {index} has lens distortion (k1..k4, p1, p2) "
                               f"and ground-truth buffers ({', '.join(extra)}) that cannot be "
                               "undistorted with it")
    image = rgba[..., :3]
    alpha = rgba[..., 3]
    mask = alpha > 0.5
    if require_mask and not mask.any():
        raise DatasetError(f"{img_path}: the mask (alpha) is empty: the view sees nothing")
    view = View(name=stem, camera=cam, image=image, mask=mask, has_mask=has_mask)
    if (p := buffers.get(layout.MASK)) is not None:
        m = _check_size(p, read_png(p), cam)[..., :1].astype(np.float32)
        if distortion is not None:
            m, _ = undistort(m, cam, distortion)
        view.object_mask = m[..., 0] > 127
    if (p := buffers.get(layout.ALBEDO)) is not None:
        view.albedo = _check_size(p, read_exr(p), cam)[..., :3]
    if (p := buffers.get(layout.NORMAL)) is not None:
        view.normal = _check_size(p, read_exr(p), cam)[..., :3]
        if to_ours is not None:  # world-space normals of a Blender-frame dataset
            view.normal = (view.normal @ to_ours.T).astype(np.float32)
    if (p := buffers.get(layout.DEPTH)) is not None:
        view.depth = _check_size(p, read_exr(p), cam)[..., 0]
    if (p := buffers.get(layout.MATERIAL)) is not None:
        view.material = _check_size(p, read_png(p), cam)[..., 0].astype(np.int32)
    if (p := buffers.get(layout.VISIBILITY)) is not None:
        vis = _check_size(p, read_exr(p), cam)
        if n_lights and vis.shape[-1] != n_lights:
            raise DatasetError(f"{p}: {vis.shape[-1]} visibility channels for {n_lights} "
                               "training lights")
        view.visibility = vis
    irr = []
    for k in range(n_lights):
        p = buffers.get(layout.IRRADIANCE.format(k=k))
        if p is not None:
            irr.append(_check_size(p, read_exr(p), cam)[..., :3])
    if irr:
        if len(irr) != n_lights:
            raise DatasetError(f"{root / stem}: irradiance files exist for only {len(irr)} of "
                               f"{n_lights} lights")
        view.irradiance = np.stack(irr, axis=2)
    for name in relit_names:
        p = buffers.get(layout.RELIT.format(name=name))
        if p is not None:
            view.relit[name] = _check_size(p, read_exr(p), cam)[..., :3]
    return view


def _light_buffers(lights: dict | None) -> tuple[int, list[str]]:
    """(number of training lights, names of the relightings) of ``lights.json``: which
    irradiance and relit buffers a view may have."""
    if not lights:
        return 0, []
    names = [r.get("name") for r in lights.get("relightings", [])]
    return len(lights.get("training", {}).get("lights", [])), [n for n in names if n]


def envmap_path(entry: dict, root: Path) -> Path:
    """The env-map file a ``lights.json`` relighting's ``path`` names: absolute, or relative
    to the dataset folder ``root``."""
    path = Path(entry["path"])
    return path if path.is_absolute() else root / path


def files_read(root: str | Path) -> list[Path]:
    """Every file the loader reads from the dataset ``root``, for any split, found by the
    loader's own rules: the JSON files, ``points3d.ply``, each frame's image and buffers and
    each env map of ``lights.json``, wherever they lie (a frame's ``file_path`` may leave the
    folder, ``../images/r_000``, or pass through a linked folder; an env map's path may be
    absolute). Each is ``root`` joined with the path the dataset gives. A JSON file that
    does not parse names nothing here: loading it fails, naming it. The dataset fingerprint
    (``io.provenance``) covers these files."""
    root = Path(root)
    files = [root / n for n in (layout.DATASET_JSON, layout.LIGHTS_JSON, layout.POINTS_PLY)]
    lights = _json_or_none(root / layout.LIGHTS_JSON)
    # A malformed lights.json names nothing more: loading (or its check) names the field.
    try:
        n_lights, relit_names = _light_buffers(lights)
    except (AttributeError, TypeError):
        n_lights, relit_names = 0, []
    try:
        files += [envmap_path(e, root) for e in (lights or {}).get("relightings", [])
                  if e.get("type") == "envmap" and e.get("path")]
    except (AttributeError, TypeError):
        pass
    for tpath in sorted(root.glob(layout.transforms_name("*"))):
        files.append(tpath)
        frames = (_json_or_none(tpath) or {}).get("frames")
        for fr in frames if isinstance(frames, list) else []:
            if isinstance(fr, dict) and isinstance(fr.get("file_path"), str):
                files.append(_image_file(root, fr["file_path"]))
                stem = _view_stem(fr["file_path"])
                files += _view_buffers(root, stem, n_lights, relit_names).values()
    for meta in sorted(root.glob("*_*/metadata.json")):
        files += _tensoir_files(meta.parent)
    return [p for p in files if p is not None and p.is_file()]


def _json_or_none(path: Path) -> dict | None:
    try:
        return _read_json(path)
    except DatasetError:
        return None


def load_dataset(root: str | Path, split: str = "train", require_mask: bool = True) -> Dataset:
    """Every view of ``split`` from ``root``: our layout, NeRF-synthetic, or TensoIR folders.

    With ``require_mask`` an all-empty mask is an error (a view that sees nothing cannot
    supervise anything).
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found")
    tpath = root / layout.transforms_name(split)
    if not tpath.is_file():
        if any(root.glob(f"{split}_*/metadata.json")):
            return load_tensoir(root, split, require_mask=require_mask)
        raise DatasetError(f"{root}: no {tpath.name} and no TensoIR folders {split}_*/")
    info = (_read_json(root / layout.DATASET_JSON)
            if (root / layout.DATASET_JSON).is_file() else None)
    lights = (_read_json(root / layout.LIGHTS_JSON)
              if (root / layout.LIGHTS_JSON).is_file() else None)
    _check_fields_read(root, info, lights)
    n_lights, relit_names = _light_buffers(lights)
    frames = load_frames(tpath)
    _check_png_alpha(root, info, frames)
    # An import without masks says so ("masks": false): its opaque PNGs carry no mask.
    no_masks = _read_json(tpath).get("masks", True) is False
    views = [_load_nerf_view(root, f.file_path, f.camera, n_lights, relit_names, tpath, i,
                             require_mask, f.distortion, f.to_ours, no_masks)
             for i, f in enumerate(frames)]
    points = root / layout.POINTS_PLY
    return Dataset(root=root, split=split, views=views, lights=lights, info=info, layout="nerf",
                   points=points if points.is_file() else None)


def _check_png_alpha(root: Path, info: dict | None, frames: list[Frame]) -> None:
    """A generated dataset (``dataset.json``) whose views would be read from PNGs that an
    older generator wrote premultiplied (no ``png_alpha`` record) is refused, naming them:
    read as straight alpha their edges would be dark. Their EXRs, when present, are read."""
    if info is None or info.get(layout.PNG_ALPHA_FIELD) == "straight":
        return
    old = [p for f in frames if (p := _image_file(root, f.file_path)) is not None
           and p.suffix.lower() == ".png"]
    if old:
        raise DatasetError(
            f"{root / layout.DATASET_JSON}: no '{layout.PNG_ALPHA_FIELD}' record: its PNGs "
            f"({old[0]}{f' and {len(old) - 1} more' if len(old) > 1 else ''}) were written "
            "premultiplied by an older generator and have no EXR beside them; generate the "
            "dataset again")


# -- TensoIR ------------------------------------------------------------------------------
def _tensoir_camera(meta_path: Path, meta: dict) -> Camera:
    for key in ("cam_transform_mat", "cam_angle_x", "imw", "imh"):
        if key not in meta:
            raise DatasetError(f"{meta_path}: missing field {key!r}")
    raw = meta["cam_transform_mat"]
    try:
        values = [float(v) for v in raw.split(",")] if isinstance(raw, str) else raw
    except ValueError:
        raise DatasetError(f"{meta_path}: field 'cam_transform_mat' must be 16 "
                           "comma-separated numbers") from None
    c2w_blender = _pose(meta_path, "cam_transform_mat", np.reshape(values, (4, 4))
                        if np.size(values) == 16 else values, scaled := {}, 0)
    _note_scaled(meta_path, scaled)
    fov_x = _number(meta_path, "cam_angle_x", meta["cam_angle_x"])
    w = int(_number(meta_path, "imw", meta["imw"]))
    h = int(_number(meta_path, "imh", meta["imh"]))
    if not 0.0 < fov_x < math.pi:
        raise DatasetError(f"{meta_path}: field 'cam_angle_x' must be in (0, pi) radians, "
                           f"got {fov_x}")
    try:
        check_intrinsics(w, h, 0.5 * w / math.tan(0.5 * fov_x), 0.5 * w / math.tan(0.5 * fov_x))
    except PoseError as exc:
        raise DatasetError(f"{meta_path}: field 'cam_angle_x': {exc}") from None
    return Camera(c2w=BLENDER_TO_YUP @ c2w_blender, width=w, height=h, fov_x=fov_x)


def _tensoir_index(path: Path) -> int:
    m = re.search(r"(\d+)$", path.name)
    return int(m.group(1)) if m else -1


TENSOIR_FILES = ("metadata.json", "rgba.png", "albedo.png", "normal.png")


def _tensoir_files(folder: Path) -> list[Path]:
    """The files ``load_tensoir`` reads from one view's folder, where present."""
    files = [folder / name for name in TENSOIR_FILES] + sorted(folder.glob("rgba_*.png"))
    return [p for p in files if p.is_file()]


def load_tensoir(root: str | Path, split: str = "train", require_mask: bool = True) -> Dataset:
    """TensoIR's layout: ``<split>_<i>/`` with ``metadata.json``, ``rgba.png``, and where
    present ``albedo.png``, ``normal.png`` (normals as [0, 1] colours, Blender world) and
    ``rgba_<light>.png`` relit images. Cameras and normals are turned to Y-up."""
    root = Path(root)
    folders = sorted((p for p in root.glob(f"{split}_*") if p.is_dir()), key=_tensoir_index)
    if not folders:
        raise DatasetError(f"{root}: no TensoIR folders {split}_*/")
    rot = BLENDER_TO_YUP[:3, :3]
    views = []
    for folder in folders:
        meta_path = folder / "metadata.json"
        cam = _tensoir_camera(meta_path, _read_json(meta_path))
        rgba_path = folder / "rgba.png"
        if not rgba_path.is_file():
            raise DatasetError(f"{rgba_path}: file not found (frame {folder.name})")
        rgba = _check_size(rgba_path, _read_image(rgba_path), cam)
        mask = rgba[..., 3] > 0.5 if rgba.shape[-1] == 4 else np.ones(rgba.shape[:2], bool)
        if require_mask and not mask.any():
            raise DatasetError(f"{rgba_path}: the mask (alpha) is empty: the view sees nothing")
        view = View(name=folder.name, camera=cam, image=rgba[..., :3], mask=mask,
                    object_mask=mask)
        if (folder / "albedo.png").is_file():
            view.albedo = _check_size(folder / "albedo.png",
                                      _read_image(folder / "albedo.png"), cam)[..., :3]
        if (folder / "normal.png").is_file():
            raw = _png_unit(folder / "normal.png")
            n = (_check_size(folder / "normal.png", raw, cam)[..., :3] * 2.0 - 1.0) @ rot.T
            n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)
            view.normal = np.where(mask[..., None], n, 0.0).astype(np.float32)
        for p in sorted(folder.glob("rgba_*.png")):
            view.relit[p.stem[len("rgba_"):]] = _check_size(p, _read_image(p), cam)[..., :3]
        views.append(view)
    return Dataset(root=root, split=split, views=views, layout="tensoir")
