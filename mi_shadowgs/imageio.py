"""Image files: linear float EXR (OpenEXR) and 8-bit sRGB PNG previews.

Arrays are numpy, [H, W] or [H, W, C], row 0 at the top of the image.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .atomic import atomic_path

_CHANNEL_NAMES = {1: ["Y"], 2: ["Y", "A"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function on linear values in [0, 1] (clamped)."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


def write_exr(path: str | os.PathLike, image: np.ndarray, channels: list[str] | None = None,
              half: bool = False) -> None:
    """Write a float image as EXR (float32 by default); atomic."""
    import OpenEXR

    image = np.asarray(image, dtype=np.float16 if half else np.float32)
    if image.ndim == 2:
        image = image[..., None]
    n = image.shape[-1]
    names = channels or _CHANNEL_NAMES.get(n) or [f"C{i}" for i in range(n)]
    if len(names) != n:
        raise ValueError(f"{path}: {n} channels but {len(names)} channel names")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {name: np.ascontiguousarray(image[..., i]) for i, name in enumerate(names)}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, data) as exr:
            exr.write(str(tmp))


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an EXR as float32 [H, W, C] (RGB/RGBA order when present, else file order)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"EXR file not found: {path}")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            chans = exr.channels()
            names = list(chans)
            order = [c for c in ("R", "G", "B", "A") if c in names]
            order = order if order else names
            if order == ["Y"] or (len(order) < len(names) and "Y" in names and not order):
                order = ["Y"]
            planes = [np.asarray(chans[c].pixels, dtype=np.float32) for c in order]
    except Exception as exc:  # OpenEXR raises plain exceptions with no file name
        raise OSError(f"cannot read EXR {path}: {exc}") from exc
    return np.stack(planes, axis=-1)


def to_uint8(image: np.ndarray, srgb: bool = True) -> np.ndarray:
    """Linear float [0, 1] image to uint8, sRGB-encoded unless ``srgb`` is False."""
    img = np.asarray(image, dtype=np.float64)
    if srgb:
        if img.ndim == 3 and img.shape[-1] in (2, 4):  # alpha stays linear
            img = np.concatenate([linear_to_srgb(img[..., :-1]), np.clip(img[..., -1:], 0, 1)],
                                 axis=-1)
        else:
            img = linear_to_srgb(img)
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def write_png(path: str | os.PathLike, image: np.ndarray, srgb: bool = True) -> None:
    """Write [H, W], [H, W, 3] or [H, W, 4] as 8-bit PNG; float input is taken as linear."""
    import imageio.v3 as iio

    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = to_uint8(img, srgb=srgb)
    if img.ndim == 3 and img.shape[-1] == 1:
        img = img[..., 0]
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, img, extension=".png")


def read_png(path: str | os.PathLike) -> np.ndarray:
    """Read a PNG as uint8 [H, W, C]."""
    import imageio.v3 as iio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PNG file not found: {path}")
    img = iio.imread(path)
    return img if img.ndim == 3 else img[..., None]
