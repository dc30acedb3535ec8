"""Image files: linear float EXR (OpenEXR) and 8-bit sRGB PNG previews.

Arrays are numpy, [H, W] or [H, W, C], row 0 at the top of the image.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mi_shadowgs.io.atomic import atomic_path

_CHANNEL_NAMES = {1: ["Y"], 2: ["Y", "A"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class ImageReadError(ValueError):
    """An image file is corrupt or not of its kind; the one-line message names the file."""


@contextlib.contextmanager
def _captured_output() -> Iterator[list[str]]:
    """Collect what C libraries print on file descriptors 1 and 2 during the block.

    OpenEXR reports a corrupt file on both before it raises; the caller keeps the first
    line as the reason instead of letting several half-messages reach the terminal.
    """
    lines: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 1)
        os.dup2(sink.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            lines.extend(ln.strip() for ln in sink.read().decode(errors="replace").splitlines()
                         if ln.strip())


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


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
        with _captured_output() as printed:
            with OpenEXR.File(str(path), separate_channels=True) as exr:
                chans = exr.channels()
                names = list(chans)
                order = [c for c in ("R", "G", "B", "A") if c in names]
                order = order if order else names
                if order == ["Y"] or (len(order) < len(names) and "Y" in names and not order):
                    order = ["Y"]
                planes = [np.asarray(chans[c].pixels, dtype=np.float32) for c in order]
    except Exception as exc:  # OpenEXR raises plain exceptions with no file name
        # Its printed diagnosis ("found corrupt leader") says more than the exception.
        reason = printed[0].removeprefix(f"{path}: ") if printed else _first_line(exc)
        raise ImageReadError(f"{path}: corrupt or unreadable EXR: {reason}") from None
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


def write_jpeg(path: str | os.PathLike, image: np.ndarray, quality: int = 95) -> None:
    """Write [H, W, 3] as an 8-bit sRGB JPEG (a photo as a camera saves it); float input is
    taken as linear."""
    import imageio.v3 as iio

    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = to_uint8(img, srgb=True)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, img[..., :3], extension=".jpg", quality=quality)


def read_png(path: str | os.PathLike) -> np.ndarray:
    """Read a PNG as uint8 [H, W, C]."""
    import imageio.v3 as iio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PNG file not found: {path}")
    if path.suffix.lower() == ".png":
        with open(path, "rb") as f:
            if f.read(len(_PNG_SIGNATURE)) != _PNG_SIGNATURE:
                # imageio would answer with advice to install plugins.
                raise ImageReadError(f"{path}: not a PNG file (no PNG signature)")
    try:
        img = iio.imread(path)
    except Exception as exc:  # Pillow: "image file is truncated", zlib errors, ...
        raise ImageReadError(f"{path}: corrupt PNG: {_first_line(exc)}") from None
    return img if img.ndim == 3 else img[..., None]
