"""Your own captures in: photos (SfM with pycolmap on the CPU) or an existing COLMAP model,
written as this project's dataset layout in one world frame.

``import_capture(source, out, config)``:
1. photos: a folder of JPEG/PNG (EXIF orientation honoured); every bad input is refused
   before anything is written (``ImportError_`` names the file or images);
2. SfM (``--colmap`` skips it): SIFT features, exhaustive matching (sequential for large
   sets), incremental mapping, all with ``pycolmap.Device.cpu``;
3. undistortion to pinhole (``pycolmap.undistort_images``; masks by the same camera maps);
4. the world frame (``world_frame``): Y-up, support plane at y = 0, object centred, radius 1;
5. the layout: ``transforms_{train,test}.json`` (nerfstudio intrinsics, ``world_up: +y``),
   ``<split>/r_<i>.png`` (sRGB, alpha = mask or opaque) at ``max_size``, the SfM points in
   our frame (``points3d.ply``), the full-resolution undistorted photos and both COLMAP
   models under ``colmap/``, and ``import.json`` (similarity, registered/rejected images,
   points, reprojection error, timings, settings).

The dataset is built in a hidden sibling folder and moved into place at the end
(``mi_shadowgs.io.atomic.atomic_dir``): a failure or a kill leaves no half dataset.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from mi_shadowgs.config import check_fields
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.poses import PoseError, check_intrinsics, check_pose
from mi_shadowgs.dataset.sfm import (
    open_sfm_work,
    registration_advice,
    run_sfm,
    sfm_key,
    sfm_work_folder,
)
from mi_shadowgs.dataset.world_frame import FrameConfig, world_frame

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
IMPORT_JSON = "import.json"
COLMAP_DIR = "colmap"  # sparse/0 (SfM as found), undistorted/{images,sparse}
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


class CaptureError(ValueError):
    """A capture cannot be imported as given; the message names the file or images."""


@dataclasses.dataclass(frozen=True)
class ImportConfig:
    """Import settings (``mi-shadowgs import``; presets: ``mi_shadowgs.presets.IMPORT``)."""

    test_every: int = 8  # every K-th registered view (by name) is held out for testing
    max_size: int = 800  # training images' longest side in pixels (full size kept beside)
    min_registered: float = 0.9  # fewer registered photos than this fraction: refuse
    exhaustive_max: int = 150  # exhaustive matching up to this many photos, else sequential
    sequential_overlap: int = 20
    max_features: int = 8192  # SIFT features per photo
    camera_model: str = "SIMPLE_RADIAL"  # one camera shared by all photos
    focal_px: float | None = None  # known focal length (pixels of the photos), else EXIF
    frame: FrameConfig = FrameConfig()
    threads: int = -1  # pycolmap threads (-1: all cores)
    # SfM runs in pieces recorded as they finish (``run_sfm``): a kill loses at most one
    # piece. Features of this many photos at a time (~0.1 s a photo at 256^2 on 2 cores)...
    sfm_chunk_photos: int = 8
    # ... and matches of this many photo pairs (~8 ms a pair there).
    sfm_chunk_pairs: int = 500
    # The mapping's models so far are written within this many seconds of the last write
    # (between two photo registrations; ``incremental_mapping``).
    checkpoint_seconds: float = 60.0

    def __post_init__(self):
        check_fields(self, (("sfm_chunk_photos", self.sfm_chunk_photos >= 1, ">= 1"),
                            ("sfm_chunk_pairs", self.sfm_chunk_pairs >= 1, ">= 1"),
                            ("checkpoint_seconds", self.checkpoint_seconds > 0, "> 0")))


# -- inputs -------------------------------------------------------------------------------------
def _read_photo(path: Path):
    """The photo as PIL RGB(A), turned upright by its EXIF orientation."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.load()
            return ImageOps.exif_transpose(im), im.getexif().get(0x0112, 1) not in (None, 1)
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise CaptureError(f"{path}: unreadable image ({exc})") from None


def list_photos(folder: Path) -> list[Path]:
    if folder.is_file():
        raise CaptureError(f"{folder}: a file; import takes a folder of photos (or a "
                           "transforms .json)")
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: photo folder not found")
    photos = sorted(p for p in folder.iterdir()
                    if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if len(photos) < 3:
        raise CaptureError(f"{folder}: {len(photos)} photos (JPEG/PNG); SfM needs at least 3")
    return photos


def check_photos(photos: list[Path]) -> tuple[tuple[int, int], list[Path]]:
    """Every photo readable and of one size: ((width, height), photos turned by EXIF)."""
    sizes, turned = {}, []
    for p in photos:
        im, rotated = _read_photo(p)
        sizes.setdefault(im.size, []).append(p.name)
        if rotated:
            turned.append(p)
    if len(sizes) > 1:
        common = max(sizes, key=lambda s: len(sizes[s]))
        odd = [f"{n} ({w}x{h})" for (w, h), names in sizes.items() if (w, h) != common
               for n in names]
        raise CaptureError(f"{photos[0].parent}: photos of mixed sizes: most are "
                           f"{common[0]}x{common[1]}, but {', '.join(odd[:8])}"
                           f"{' ...' if len(odd) > 8 else ''}; resize or remove them")
    return next(iter(sizes)), turned


def read_mask(path: Path) -> np.ndarray:
    """A mask image as [h, w] in [0, 1], upright by its EXIF orientation: its alpha where it
    has one that is not opaque, else its grey value (a palette's colours, not its indices;
    16-bit grey scaled by its own maximum)."""
    im, _ = _read_photo(path)
    if im.mode == "P":  # palette indices are no grey values: their colours (and alpha)
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
    if "A" in im.getbands():
        alpha = np.asarray(im.getchannel("A"))
        if alpha.min() < 255:
            return alpha / 255.0
    if im.mode.startswith("I;16") or im.mode == "I":  # 16-bit grey (PIL's "I" for PNG too)
        return np.clip(np.asarray(im, np.float64) / 65535.0, 0.0, 1.0)
    if im.mode == "F":
        return np.clip(np.asarray(im, np.float64), 0.0, 1.0)
    return np.asarray(im.convert("L")) / 255.0


def check_mask_size(mask: Path, photo: str, size: tuple[int, int], where: str = "") -> None:
    """The mask (upright) is the size of its photo ``photo`` (upright ``size``); ``where``
    says which input named the mask, before the message."""
    im, _ = _read_photo(mask)
    if im.size != size:
        raise CaptureError(f"{where}{mask}: mask is {im.size[0]}x{im.size[1]}, its photo "
                           f"{photo} is {size[0]}x{size[1]}")


def check_masks(masks: Path, photos: list[Path], size: tuple[int, int]) -> dict[str, Path]:
    """The mask of each photo (same stem, PNG/JPEG) in ``masks``, of the photo's size."""
    if not masks.is_dir():
        raise FileNotFoundError(f"{masks}: mask folder not found (--masks)")
    found, missing = {}, []
    for p in photos:
        cands = [masks / (p.stem + s) for s in (".png", ".jpg", ".jpeg")] + [masks / p.name]
        m = next((c for c in cands if c.is_file()), None)
        if m is None:
            missing.append(p.name)
            continue
        check_mask_size(m, p.name, size)
        found[p.name] = m
    if missing:
        raise CaptureError(f"{masks}: no mask for {', '.join(missing[:8])}"
                           f"{' ...' if len(missing) > 8 else ''} (--masks)")
    return found


_MODEL_FILES = ("cameras", "images", "points3D")


def check_colmap(model: Path) -> str:
    """The model folder holds cameras, images and points3D, all binary or all text, none
    empty (pycolmap reads an empty points3D.bin without end, growing its memory); returns
    their extension (".bin" or ".txt")."""
    if model.is_file():
        raise CaptureError(f"{model}: a file; --colmap takes the model's folder (e.g. sparse/0)")
    if not model.is_dir():
        raise FileNotFoundError(f"{model}: COLMAP model folder not found (--colmap)")
    kinds = {name: [ext for ext in (".bin", ".txt") if (model / f"{name}{ext}").is_file()]
             for name in _MODEL_FILES}
    for name, exts in kinds.items():
        if not exts:
            raise CaptureError(f"{model}: the COLMAP model has no {name}.bin or {name}.txt")
    ext = next((e for e in (".bin", ".txt") if all(e in x for x in kinds.values())), None)
    if ext is None:  # COLMAP reads one kind only: it would say the files do not exist
        found = ", ".join(f"{name}{x[0]}" for name, x in kinds.items())
        raise CaptureError(f"{model}: the COLMAP model mixes binary and text files ({found}); "
                           "it must be all .bin or all .txt (colmap model_converter)")
    empty = [name + ext for name in _MODEL_FILES if (model / f"{name}{ext}").stat().st_size == 0]
    if empty:
        raise CaptureError(f"{model}: the COLMAP model's {', '.join(empty)} "
                           f"{'is' if len(empty) == 1 else 'are'} empty (0 bytes)")
    return ext


def read_colmap(model: Path, photos: list[Path]):
    """The user's COLMAP model of ``photos``, checked (``check_colmap``) and checked against
    them: every image of the model is a photo, every posed image's camera is its photo's size
    as stored (COLMAP reads pixels as stored, whatever their EXIF orientation)."""
    import pycolmap
    from PIL import Image

    cameras = model / f"cameras{check_colmap(model)}"
    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as exc:  # pycolmap's: IndexError, RuntimeError, ValueError, ...
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CaptureError(f"{model}: unreadable COLMAP model ({first})") from None
    by_name = {p.name: p for p in photos}
    unknown = [im.name for im in rec.images.values() if im.name not in by_name]
    if unknown:
        raise CaptureError(f"{model}: the model's images {', '.join(unknown[:8])} are not in "
                           f"{photos[0].parent}")
    posed = [im for im in rec.images.values() if im.has_pose]
    if len(posed) < 3:
        what = "no images" if not rec.images else f"{len(posed)} posed images"
        raise CaptureError(f"{model}: the COLMAP model has {what}; import needs at least 3")
    for im in sorted(posed, key=lambda im: im.name):
        cam = rec.cameras[im.camera_id]
        with Image.open(by_name[im.name]) as photo:
            stored = photo.size
        if (cam.width, cam.height) != stored:  # pycolmap's undistortion would abort
            raise CaptureError(f"{cameras}: camera {im.camera_id} is {cam.width}x{cam.height}, "
                               f"but its image {im.name} is {stored[0]}x{stored[1]} (photos "
                               "resized after COLMAP?)")
        focal = (float(cam.focal_length_x), float(cam.focal_length_y))
        if not all(math.isfinite(f) and f > 0 for f in focal):
            raise CaptureError(f"{cameras}: camera {im.camera_id} (of {im.name}) has focal "
                               f"length {focal[0]:g} x {focal[1]:g} px; it must be > 0")
        try:
            check_intrinsics(int(cam.width), int(cam.height), *focal)
        except PoseError as exc:
            raise CaptureError(f"{cameras}: camera {im.camera_id} (of {im.name}): {exc}") from None
        try:
            check_pose(np.vstack([im.cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]]))
        except PoseError as exc:
            raise CaptureError(f"{model}: the pose of image {im.name} {exc}") from None
    return rec


def _as_stored(upright: np.ndarray, photo: Path) -> np.ndarray:
    """An image [h, w] of the upright ``photo`` turned back to how its pixels are stored
    (undoing ``ImageOps.exif_transpose``)."""
    from PIL import Image

    with Image.open(photo) as im:
        orientation = im.getexif().get(0x0112, 1)
    turn = Image.Transpose
    # exif_transpose's turn per orientation, inverted (the flips are their own inverses)
    undo = {2: turn.FLIP_LEFT_RIGHT, 3: turn.ROTATE_180, 4: turn.FLIP_TOP_BOTTOM,
            5: turn.TRANSPOSE, 6: turn.ROTATE_90, 7: turn.TRANSVERSE,
            8: turn.ROTATE_270}.get(orientation)
    if undo is None:
        return upright
    return np.asarray(Image.fromarray(upright.astype(np.float32), "F").transpose(undo))


# -- from a reconstruction to our cameras ----------------------------------------------------------
def ground_outside_masks(views: list[dict], points: np.ndarray, tolerance: float,
                         reach: float = 2.0) -> float | None:
    """The share of the SfM points on the ground near the object that the masks leave out:
    points [M, 3] in our frame within ``tolerance`` of y = 0 and ``reach`` object radii of
    the Y axis, each counted as out when more than half of the masked views that see it
    have it outside their mask. None when fewer than 20 such points are seen.

    The masks should cover the ground the shadows fall on (the loader's masks are object
    plus base); object-only masks pull against it in stage 1 (median normal error 1.43 ->
    4.68 deg on the default scene)."""
    near = ((np.abs(points[:, 1]) < tolerance)
            & (np.hypot(points[:, 0], points[:, 2]) < reach))
    pts = points[near]
    seen = np.zeros(len(pts), np.int64)
    out = np.zeros(len(pts), np.int64)
    for v in views:
        if v.get("mask") is None:
            continue
        covered, inside = v["camera"].lookup(v["mask"] >= 0.5, pts)
        seen += inside
        out += inside & ~covered
    counted = seen > 0
    if counted.sum() < 20:
        return None
    return float(np.mean(out[counted] > 0.5 * seen[counted]))


# Above this share of the ground's SfM points left out, the masks are taken for the object's
# alone: 0.99 for those on the tests' capture, 0.007 for masks of the object and its ground.
GROUND_OUTSIDE_MASKS_MAX = 0.5


def ground_outside_masks_warning(record: dict) -> str | None:
    """The warning for an import ``record`` whose masks leave out most of the ground near the
    object (``ground_outside_masks`` over ``GROUND_OUTSIDE_MASKS_MAX``), or None."""
    share = record.get("ground_outside_masks")
    if share is None or share <= GROUND_OUTSIDE_MASKS_MAX:
        return None
    return (f"{record['masks']}: the masks leave out {share:.0%} of the SfM points on the "
            "ground near the object; masks should cover the object and the ground its shadows "
            "fall on (the shadows' receiver): with the object's alone stage 1's normals were "
            "3x worse")


def _pinhole(camera, c2w_src: np.ndarray) -> Camera:
    fx, fy = float(camera.focal_length_x), float(camera.focal_length_y)
    cx, cy = float(camera.principal_point_x), float(camera.principal_point_y)
    return Camera.from_intrinsics(c2w_src, int(camera.width), int(camera.height), fx, fy, cx,
                                  cy)


def reconstruction_views(rec) -> list[tuple[str, np.ndarray, object]]:
    """(name, OpenGL c2w [4, 4] in the source frame, pycolmap camera) per registered image,
    by name."""
    out = []
    for image in rec.images.values():
        if not image.has_pose:
            continue
        w2c = np.eye(4)
        w2c[:3, :4] = image.cam_from_world().matrix()  # OpenCV world -> camera
        out.append((image.name, np.linalg.inv(w2c) @ _GL_FROM_CV, rec.cameras[image.camera_id]))
    return sorted(out, key=lambda v: v[0])


def _undistort_mask(mask: np.ndarray, src_cam, dst_cam) -> np.ndarray:
    """A mask [h, w] of the distorted photo -> [H, W] of the undistorted pinhole view (the
    same maps pycolmap's undistortion uses: through normalised camera coordinates)."""
    from scipy import ndimage

    w, h = int(dst_cam.width), int(dst_cam.height)
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    cam = dst_cam.cam_from_img(np.stack([xs.ravel(), ys.ravel()], -1).astype(np.float64))
    src = src_cam.img_from_cam(np.column_stack([cam, np.ones(len(cam))]),
                               check_cheirality=False)
    coords = np.stack([src[:, 1] - 0.5, src[:, 0] - 0.5])
    out = ndimage.map_coordinates(mask.astype(np.float32), coords, order=1, mode="constant",
                                  cval=0.0)
    return out.reshape(h, w)


# -- the dataset ----------------------------------------------------------------------------------
def _resize(img, size: tuple[int, int]):
    from PIL import Image

    return img if img.size == size else img.resize(size, Image.Resampling.LANCZOS)


def _train_size(w: int, h: int, max_size: int) -> tuple[int, int]:
    s = min(1.0, max_size / max(w, h))
    return max(1, round(w * s)), max(1, round(h * s))


def write_views(tmp: Path, views: list[dict], config: ImportConfig) -> dict:
    """``transforms_*.json`` and ``<split>/r_<i>.png`` from the undistorted views."""
    from PIL import Image

    splits = {"train": [], "test": []}
    for i, v in enumerate(views):
        split = "test" if config.test_every > 0 and i % config.test_every == 0 else "train"
        splits[split].append(v)
    if not splits["train"] or not splits["test"]:
        raise CaptureError(f"--test-every {config.test_every} leaves an empty split for "
                           f"{len(views)} registered views")
    for split, vs in splits.items():
        (tmp / split).mkdir()
        frames = []
        for i, v in enumerate(vs):
            cam: Camera = v["camera"]
            size = _train_size(cam.width, cam.height, config.max_size)
            small = cam.with_size(*size)
            with Image.open(v["image"]) as im:
                rgb = _resize(im.convert("RGB"), size)
            alpha = v.get("mask")
            rgba = np.concatenate([np.asarray(rgb), np.full((*size[::-1], 1), 255, np.uint8)],
                                  axis=-1)
            if alpha is not None:
                a = Image.fromarray(np.round(np.clip(alpha, 0, 1) * 255).astype(np.uint8))
                rgba[..., 3] = np.asarray(_resize(a, size))
            stem = layout.view_stem(split, i)
            Image.fromarray(rgba).save(tmp / (stem + ".png"))
            fx, fy = small.focal_xy
            cx, cy = small.principal_point
            frames.append({"file_path": f"./{stem}.png", "source_image": v["name"],
                           "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
                           "transform_matrix": small.c2w.tolist()})
        w, h = _train_size(vs[0]["camera"].width, vs[0]["camera"].height, config.max_size)
        meta = {"camera_model": "PINHOLE", "w": w, "h": h, "world_up": "+y",
                "masks": any(v.get("mask") is not None for v in vs), "frames": frames}
        (tmp / layout.transforms_name(split)).write_text(json.dumps(meta, indent=1))
    return {k: [v["name"] for v in vs] for k, vs in splits.items()}


def _write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """SfM points [M, 3] in our frame with their colours [M, 3] in [0, 1] (float PLY)."""
    from mi_shadowgs.io.ply import write_ply_vertices

    c = rgb.astype(np.float32) / 255.0
    write_ply_vertices(path, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                              "red": c[:, 0], "green": c[:, 1], "blue": c[:, 2]})


def import_capture(source: str | Path, out: str | Path, config: ImportConfig,
                   colmap: str | Path | None = None, masks: str | Path | None = None,
                   progress: bool = True) -> dict:
    """Import photos (SfM) or a COLMAP model of them into the dataset ``out``; returns the
    ``import.json`` record. Every input is checked before anything is written."""
    import pycolmap

    from mi_shadowgs.io.provenance import check_output_location

    t_start, cpu_start = time.perf_counter(), time.process_time()
    # fatal only: its per-step log (and its own "failed" lines) would drown our one line
    pycolmap.logging.minloglevel = 3
    source, out = Path(source), Path(out)
    if source.suffix.lower() == ".json":
        if colmap is not None or masks is not None:
            raise CaptureError(f"{source}: --colmap and --masks are for photo folders; a "
                               "transforms file names its own images (and mask_path)")
        return import_transforms(source, out, config)
    photos = list_photos(source)
    size, turned = check_photos(photos)
    mask_files = check_masks(Path(masks), photos, size) if masks is not None else {}
    model = None
    if colmap is not None:
        model = read_colmap(Path(colmap), photos)
    if config.test_every < 2:
        raise CaptureError(f"--test-every must be >= 2, got {config.test_every}")
    if out.exists():
        raise FileExistsError(f"{out} already exists; import writes a new dataset folder")
    check_output_location(out, [source] + ([Path(colmap)] if colmap else []),
                          command="import")
    timings = {}
    # Our SfM's work (features, matches, models) outlives a kill, beside OUT; a COLMAP model
    # given needs none.
    sfm_work = sfm_work_folder(out) if colmap is None else None
    sfm_state = open_sfm_work(sfm_work, sfm_key(photos, config)) if sfm_work else None
    try:
        record = _import_photos(source, out, photos, size, turned, mask_files, colmap, model,
                                masks, config, sfm_work, sfm_state, timings, t_start, cpu_start,
                                progress)
    except KeyboardInterrupt:  # (io.interrupt.Interrupted too: SIGTERM)
        raise  # the SfM work stays for the rerun to continue
    except BaseException:
        if sfm_work is not None:  # a failure a rerun would meet again: no work left behind
            shutil.rmtree(sfm_work, ignore_errors=True)
        raise
    if sfm_work is not None:
        shutil.rmtree(sfm_work, ignore_errors=True)  # the dataset is written
    return record


def _import_photos(source: Path, out: Path, photos, size, turned, mask_files, colmap, model,
                   masks, config: ImportConfig, sfm_work: Path | None, sfm_state: dict | None,
                   timings: dict, t_start: float, cpu_start: float, progress: bool) -> dict:
    """``import_capture``'s work once every input is checked (its docstring)."""
    import pycolmap
    from tqdm import tqdm

    from mi_shadowgs.io.atomic import atomic_dir

    steps = tqdm(total=5, desc=f"import {out.name}", unit="step", disable=not progress)
    with (tempfile.TemporaryDirectory(prefix=".mi_shadowgs_import_") as work_s,
          atomic_dir(out) as tmp):
        image_dir = source
        names = [p.name for p in photos]
        # SfM reads pixels as stored: give ours upright copies. A user's model describes the
        # pixels as stored: undistorted as they are (their masks turned back to them).
        if turned and colmap is None:
            image_dir = (sfm_work or Path(work_s)) / "upright"
            image_dir.mkdir(exist_ok=True)
            for p in photos:
                im, _ = _read_photo(p)
                (im.save(image_dir / p.name, quality=98) if p in turned
                 else shutil.copy2(p, image_dir / p.name))
        if colmap is None:
            rec = run_sfm(image_dir, names, sfm_work, config, size, timings, sfm_state,
                          progress)
            mode = "photos"
        else:
            rec, mode = model, "colmap"  # read and checked by read_colmap
        steps.update(1)
        registered = sorted(im.name for im in rec.images.values() if im.has_pose)
        rejected = sorted(set(names) - set(registered))
        # A user's own COLMAP model is taken as it is; our SfM must register enough.
        few = mode == "photos" and len(registered) < config.min_registered * len(names)
        if few or len(registered) < 3:
            raise CaptureError(
                f"{source}: SfM registered {len(registered)} of {len(names)} photos (below "
                f"{config.min_registered:.0%}); dropped: {', '.join(rejected[:12])}"
                f"{' ...' if len(rejected) > 12 else ''}. "
                f"{registration_advice(sfm_work / 'database.db' if sfm_work else None)}")
        sparse = tmp / COLMAP_DIR / "sparse" / "0"
        sparse.mkdir(parents=True)
        rec.write(str(sparse))
        t = time.perf_counter()
        undist = tmp / COLMAP_DIR / "undistorted"
        pycolmap.undistort_images(str(undist), str(sparse), str(image_dir),
                                  image_names=registered)
        urec = pycolmap.Reconstruction(str(undist / "sparse"))
        timings["undistort_s"] = time.perf_counter() - t
        steps.update(1)
        t = time.perf_counter()
        views_src = reconstruction_views(urec)
        xyz = np.array([p.xyz for p in urec.points3D.values()], np.float64).reshape(-1, 3)
        rgb = np.array([p.color for p in urec.points3D.values()], np.uint8).reshape(-1, 3)
        sim, frame_report = world_frame(xyz, np.stack([c for _, c, _ in views_src]),
                                        config.frame)
        timings["world_frame_s"] = time.perf_counter() - t
        steps.update(1)
        t = time.perf_counter()
        views = _undistorted_views(rec, views_src, sim, undist, mask_files,
                                   image_dir == source, source)
        ground = None
        if mask_files and frame_report.get("up_from") == "plane":
            ground = ground_outside_masks(views, sim.points(xyz),
                                          frame_report["plane_threshold"] * sim.scale)
        split = write_views(tmp, views, config)
        _write_points_ply(tmp / layout.POINTS_PLY, sim.points(xyz), rgb)
        timings["write_s"] = time.perf_counter() - t
        steps.update(1)
        timings["total_s"] = time.perf_counter() - t_start
        # CPU seconds of all threads: what the import costs whatever else runs beside it
        timings["cpu_s"] = time.process_time() - cpu_start
        record = {
            "format_version": 1, "source": str(source.resolve()), "mode": mode,
            "colmap": str(Path(colmap).resolve()) if colmap else None,
            "masks": str(Path(masks).resolve()) if masks else None,
            "similarity": sim.to_json(), "world_frame": frame_report,
            "registered": registered, "rejected": rejected, "splits": split,
            "points": int(len(xyz)),
            "ground_outside_masks": ground,
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
            "timings": timings, "settings": dataclasses.asdict(config),
            "pycolmap_version": pycolmap.__version__,
        }
        (tmp / IMPORT_JSON).write_text(json.dumps(record, indent=1))
        _write_manifest(tmp, source, names, config)
        steps.update(1)
    steps.close()
    return record


def _undistorted_views(rec, views_src, sim, undist: Path, mask_files: dict, as_stored: bool,
                       source: Path) -> list[dict]:
    """The registered views in the world frame ``sim``: name, pinhole camera, undistorted
    image and, where the user gave one, its mask undistorted alike (``as_stored``: the
    photos were undistorted as stored, so their upright masks are turned back first)."""
    src_cams = {im.name: rec.cameras[im.camera_id] for im in rec.images.values()}
    views = []
    for name, c2w, cam in views_src:
        v = {"name": name, "camera": _pinhole(cam, sim.c2w(c2w)),
             "image": undist / "images" / name}
        if name in mask_files:
            mask = read_mask(mask_files[name])  # upright, as its photo is shown
            if as_stored:
                mask = _as_stored(mask, source / name)
            v["mask"] = _undistort_mask(mask, src_cams[name], cam)
        views.append(v)
    return views


def _write_manifest(folder: Path, source: Path, names: list[str], config: ImportConfig
                    ) -> None:
    """The import's provenance manifest in ``folder``, listing every file there."""
    from mi_shadowgs.io.provenance import Output, Provenance

    prov = Provenance(inputs={"photos": {"path": str(source.resolve()), "files": names}},
                      settings=dataclasses.asdict(config))
    manifest = Output(folder, "import", prov, None)
    manifest.claim(*sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                           if p.is_file()))
    manifest.finish()


# -- nerfstudio transforms.json --------------------------------------------------------------------
def import_transforms(path: Path, out: Path, config: ImportConfig) -> dict:
    """A nerfstudio ``transforms.json`` (intrinsics, distortion, per-frame ``mask_path``, an
    optional ``ply_file_path`` point cloud) into our layout and world frame: images
    undistorted, the frame placed from the points (else from the cameras)."""
    from PIL import Image

    from mi_shadowgs.dataset.distortion import undistort
    from mi_shadowgs.dataset.loader import _read_json, load_frames
    from mi_shadowgs.io.atomic import atomic_dir
    from mi_shadowgs.io.ply import PlyError, read_ply_vertices
    from mi_shadowgs.io.provenance import Output, Provenance, check_output_location

    t_start = time.perf_counter()
    meta = _read_json(path)
    frames = load_frames(path, as_stored=True)
    raw_frames = meta["frames"]
    # the fields only import reads (load_frames checks the rest), in the loader's words
    ply = meta.get("ply_file_path")
    if ply is not None and not isinstance(ply, str):
        raise CaptureError(f"{path}: field 'ply_file_path' must be a string, got {ply!r}")
    for i, fr in enumerate(raw_frames):
        mp = fr.get("mask_path")
        if mp is not None and not isinstance(mp, str):
            raise CaptureError(f"{path}: field 'frames[{i}].mask_path' must be a string, got "
                               f"{mp!r}")
    for i, f in enumerate(frames):
        img_path = path.parent / f.file_path
        if not img_path.is_file():
            raise CaptureError(f"{path}: the image of frame {i} ({f.file_path!r}) is missing")
        im, _ = _read_photo(img_path)
        if im.size != (f.camera.width, f.camera.height):
            raise CaptureError(f"{path}: fields 'w'/'h' say {f.camera.width}x"
                               f"{f.camera.height}, but {img_path.name} is {im.size[0]}x"
                               f"{im.size[1]}")
        mp = raw_frames[i].get("mask_path")
        if mp is not None:
            if not (path.parent / mp).is_file():
                raise CaptureError(f"{path}: the mask of frame {i} ({mp!r}, field "
                                   "'mask_path') is missing")
            # write_views would stretch it to the photo's size
            check_mask_size(path.parent / mp, img_path.name, im.size,
                            where=f"{path}: frame {i} (field 'frames[{i}].mask_path'): ")
    points = np.zeros((0, 3))
    if ply:
        where = f"{path}: the point cloud {ply!r} (field 'ply_file_path')"
        if not (path.parent / ply).is_file():
            raise CaptureError(f"{where} is missing")
        try:
            v = read_ply_vertices(path.parent / ply)
            points = np.stack([v["x"], v["y"], v["z"]], axis=-1)
        except (PlyError, KeyError, ValueError) as exc:
            raise CaptureError(f"{where} is not a point cloud PLY: {exc}") from None
    if out.exists():
        raise FileExistsError(f"{out} already exists; import writes a new dataset folder")
    check_output_location(out, [path.parent], command="import")
    sim, frame_report = world_frame(points, np.stack([f.camera.c2w for f in frames]),
                                    config.frame)
    with (tempfile.TemporaryDirectory(prefix=".mi_shadowgs_import_") as work_s,
          atomic_dir(out) as tmp):
        work = Path(work_s)
        views = []
        for i, f in enumerate(frames):
            name = Path(f.file_path).name
            im, _ = _read_photo(path.parent / f.file_path)
            rgb = np.asarray(im.convert("RGB"), np.float32)
            mask = None
            if raw_frames[i].get("mask_path"):
                mask = read_mask(path.parent / raw_frames[i]["mask_path"])
                mask = mask.astype(np.float32)[..., None]
            if f.distortion is not None:
                rgb, _ = undistort(rgb, f.camera, f.distortion)
                if mask is not None:
                    mask, _ = undistort(mask, f.camera, f.distortion)
            undist = work / f"{i:05d}_{Path(name).stem}.png"
            Image.fromarray(np.clip(np.round(rgb), 0, 255).astype(np.uint8)).save(undist)
            cam = dataclasses.replace(f.camera, c2w=sim.c2w(f.camera.c2w))
            views.append({"name": name, "camera": cam, "image": undist,
                          "mask": None if mask is None else mask[..., 0]})
        split = write_views(tmp, views, config)
        if len(points):
            _write_points_ply(tmp / layout.POINTS_PLY, sim.points(points),
                              np.full((len(points), 3), 128, np.uint8))
        record = {"format_version": 1, "source": str(path.resolve()), "mode": "nerfstudio",
                  "similarity": sim.to_json(), "world_frame": frame_report,
                  "registered": [v["name"] for v in views], "rejected": [], "splits": split,
                  "points": int(len(points)), "mean_reprojection_error_px": None,
                  "timings": {"total_s": time.perf_counter() - t_start},
                  "settings": dataclasses.asdict(config)}
        (tmp / IMPORT_JSON).write_text(json.dumps(record, indent=1))
        manifest = Output(tmp, "import", Provenance(inputs={"transforms": {
            "path": str(path.resolve())}}, settings=dataclasses.asdict(config)), None)
        manifest.claim(*sorted(p.relative_to(tmp).as_posix() for p in tmp.rglob("*")
                               if p.is_file()))
        manifest.finish()
    return record
