"""``generate --photos``: every view as a user's photo, as a camera in auto mode takes it.

A photo is the view's path-traced image with the room light behind the scene (the render
hides emitters; a constant emitter seen through a pixel's uncovered part is its radiance),
times the photo's exposure and white-balance gains, with sensor noise, saved as an sRGB
JPEG. Without the capture's photo parameters (``capture.py``) a photo is the plain sRGB JPEG
of the view and no gains are written. The gains are drawn from the dataset's seed, all
before any photo, so that a generate cut short and run again gives the same photos.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.capture import Capture

NOISE_FLOOR = 0.01  # sensor noise std is photo_noise * sqrt(x + NOISE_FLOOR): shot + read


def _names(folder: Path) -> list[tuple[str, int]]:
    out = []
    for split in layout.SPLITS:
        meta = json.loads((folder / layout.transforms_name(split)).read_text())
        out += [(split, i) for i in range(len(meta["frames"]))]
    return out


def photo_gains(capture: Capture, seed: int, count: int) -> list[dict]:
    """Each of ``count`` photos' exposure (EV), white balance and their product (RGB)."""
    rng = np.random.default_rng([seed, 0x9407])
    ev = rng.uniform(-capture.photo_ev, capture.photo_ev, count)
    wb = 1.0 + rng.uniform(-capture.photo_wb, capture.photo_wb, (count, 3))
    return [{"ev": float(ev[k]), "white_balance": wb[k].tolist(),
             "gain": (2.0 ** ev[k] * wb[k]).tolist()} for k in range(count)]


def develop(rgba: np.ndarray, capture: Capture, gain, rng: np.random.Generator
            ) -> np.ndarray:
    """The linear photo [H, W, 3] of a view's render ``rgba`` [H, W, 4]: the room light
    behind it, ``gain`` [3], then noise (``rng``); not clipped."""
    rgb = rgba[..., :3].astype(np.float64)
    rgb = rgb + (1.0 - rgba[..., 3:4]) * np.asarray(capture.room_radiance)
    x = rgb * np.asarray(gain, np.float64)
    if capture.photo_noise > 0:
        sigma = capture.photo_noise * np.sqrt(np.maximum(x, 0.0) + NOISE_FLOOR)
        x = x + sigma * rng.standard_normal(x.shape)
    return x


def write_photos(folder: Path, capture: Capture, seed: int) -> None:
    """Every view of ``folder`` as a photo under ``photos/`` (see the module doc); with the
    capture's photo parameters, their gains in ``photos/gains.json``."""
    from mi_shadowgs.io.atomic import write_json
    from mi_shadowgs.io.images import read_exr, write_jpeg

    (folder / layout.PHOTOS).mkdir(exist_ok=True)
    names = _names(folder)
    jitter = capture.jitters_photos
    gains = photo_gains(capture, seed, len(names)) if jitter else None
    if jitter:
        write_json(folder / layout.PHOTOS / layout.PHOTO_GAINS, {
            "convention": "linear photo = gain * (the view's EXR rgb + (1 - alpha) * "
                          "room_radiance), then noise of std photo_noise * sqrt(x + "
                          f"{NOISE_FLOOR}), then sRGB and JPEG; gain = 2^ev * white_balance",
            "photo_ev": capture.photo_ev, "photo_wb": capture.photo_wb,
            "photo_noise": capture.photo_noise, "jpeg_quality": capture.photo_jpeg,
            "room_radiance": list(capture.room_radiance),
            "photos": {layout.photo_name(split, i): g
                       for (split, i), g in zip(names, gains, strict=True)}})
    for k, (split, i) in enumerate(names):
        path = folder / layout.PHOTOS / layout.photo_name(split, i)
        if path.is_file():  # a kill may have come after some of them
            continue
        rgba = read_exr(folder / (layout.view_stem(split, i) + layout.IMAGE_EXR))
        if not jitter and not capture.has_room:
            write_jpeg(path, rgba[..., :3])
            continue
        rng = np.random.default_rng([seed, 0x9408, k])
        gain = gains[k]["gain"] if jitter else (1.0, 1.0, 1.0)
        write_jpeg(path, develop(rgba, capture, gain, rng), quality=capture.photo_jpeg)
