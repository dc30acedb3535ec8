"""File names of the dataset layout, shared by the writer and the loader (one place).

NeRF-synthetic/TensoIR style: ``transforms_<split>.json`` at the top, and per view
``<split>/r_<i>`` with suffixes for each ground-truth buffer.
"""

from __future__ import annotations

SPLITS = ("train", "test")
DATASET_JSON = "dataset.json"
LIGHTS_JSON = "lights.json"
POINTS_PLY = "points3d.ply"  # an import's SfM points, in our frame
SKY_ENVMAP = "sky_envmap.exr"  # the procedural sky of the env-map relit test views
ENVMAP_DIR = "envmaps"  # copies of the other env maps the relit test views were rendered with
FORMAT_VERSION = 1
# dataset.json's record of the PNGs' alpha: "straight" (NeRF-synthetic's). A generated
# dataset without it wrote premultiplied PNGs; the loader refuses to read those.
PNG_ALPHA_FIELD = "png_alpha"
# generate --photos: every view as a user's photo (sRGB JPEG, no cameras, no masks), named
# "<split>_<index>.jpg" so that scoring finds the view's ground truth.
PHOTOS = "photos"
# photos/gains.json: each photo's true exposure and white-balance gains, when the capture
# jitters them (mi_shadowgs.dataset.photos)
PHOTO_GAINS = "gains.json"


def photo_name(split: str, index: int) -> str:
    return f"{split}_{index:03d}.jpg"

# The angle NeRF-synthetic uses (0.6911 rad, ~39.6 degrees).
NERF_CAMERA_ANGLE_X = 0.6911112070083618

# suffix of each per-view buffer: "<stem><suffix>"
IMAGE_EXR = ".exr"             # linear RGBA, alpha = object-plus-base coverage
IMAGE_PNG = ".png"             # sRGB RGBA preview
ALBEDO = "_albedo.exr"         # linear RGB
NORMAL = "_normal.exr"         # unit world-space normals, stored as they are
DEPTH = "_depth.exr"           # z-depth, 0 on background
MASK = "_mask.png"             # object mask (object parts only), 0 / 255
MATERIAL = "_material.png"     # uint8 material id: 0 background, 1..P parts, P + 1 base
VISIBILITY = "_visibility.exr"  # one channel per training light, 1 where unoccluded
# a sphere lamp's visible share per training light (only when a lamp has a radius)
VISIBILITY_SOFT = "_visibility_soft.exr"
IRRADIANCE = "_irradiance_{k}.exr"  # E_k * max(0, n . l_k) * V_k (lamps: soft V), RGB
RELIT = "_relit_{name}.exr"    # test views only: relit linear RGBA


def transforms_name(split: str) -> str:
    return f"transforms_{split}.json"


def view_stem(split: str, index: int) -> str:
    return f"{split}/r_{index:03d}"
