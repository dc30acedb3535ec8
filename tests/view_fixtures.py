"""A run folder made in a second for the viewer's tests: a box standing on a plane (its
shadow moves with the light), written as stage 4 writes it (``material/full/model.ply``,
``light.json`` and a manifest holding the visibility settings), plus a geometry-only copy
(``geometry/model.ply`` with segments, no stage 4)."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import mitsuba as mi
import numpy as np
import synthetic_asset

from mi_shadowgs.core.directions import direction_from_angles
from mi_shadowgs.io.ply import save_ply
from mi_shadowgs.io.provenance import FORMAT_VERSION, MANIFEST_NAME

FITTED = (40.0, 50.0, 2.5)  # azimuth, elevation (degrees), irradiance of the fitted light
# Small shadow maps keep the tests fast; the viewer must take them from the manifest.
VISIBILITY = {"resolution": 128, "projection": "orthographic"}


def _surfels(n: int):
    surf = synthetic_asset.box_on_plane_surfels(n, 1.2, 0.3, roughness=0.6)
    pos = surf.to_numpy()["position"]
    on_box = pos[:, 1] > 0.01  # [N] the box (segment 1) or the plane (segment 0)
    albedo = np.where(on_box[:, None], [0.7, 0.3, 0.2], [0.6, 0.6, 0.6]).astype(np.float32)
    surf.channels["albedo"] = mi.TensorXf(albedo)
    surf.channels["segment"] = mi.TensorXf(on_box.astype(np.float32)[:, None])
    return surf


def _manifest(folder: Path, files: list[str], settings: dict, inputs: dict | None = None
              ) -> None:
    (folder / MANIFEST_NAME).write_text(json.dumps(
        {"format": FORMAT_VERSION, "command": "test", "complete": True, "files": files,
         "settings": settings, "inputs": inputs or {}}))


def add_segmentation(run: Path, made_from_digest: str) -> None:
    """``run/segmentation``, a copy of its geometry recorded as made from the geometry
    model of digest ``made_from_digest`` (another one: the run's stages do not belong
    together)."""
    folder = run / "segmentation"
    folder.mkdir()
    shutil.copyfile(run / "geometry" / "model.ply", folder / "model.ply")
    _manifest(folder, ["model.ply"], {}, {"model": {"digest": made_from_digest}})


def make_run(root: Path, n: int = 4000) -> tuple[Path, Path]:
    """(a run with stage 4, a run with geometry and segments only) under ``root``."""
    surf = _surfels(n)
    run = root / "run"
    material = run / "material" / "full"
    material.mkdir(parents=True)
    save_ply(material / "model.ply", surf)
    az, el, e = FITTED
    d = direction_from_angles(az, el)
    (material / "light.json").write_text(json.dumps(
        {"radiance": [0.0] * 128, "active": [0], "directions": [d.tolist()],
         "irradiance": [e], "angles_deg": [[az, el]], "specular": False,
         "use_visibility": True}))
    _manifest(material, ["model.ply", "light.json"], {"visibility": VISIBILITY})
    # The run's own manifest lists its fits, as a run's does (a fit it does not list is
    # none of its own).
    (run / MANIFEST_NAME).write_text(json.dumps(
        {"format": FORMAT_VERSION, "command": "run", "complete": True, "files": [],
         "parts": ["material/full"], "settings": {}, "inputs": {}}))
    geometry_only = root / "geometry_only"
    (geometry_only / "geometry").mkdir(parents=True)
    plain = dataclasses.replace(surf, channels={"segment": surf.channels["segment"]})
    save_ply(geometry_only / "geometry" / "model.ply", plain)
    return run, geometry_only
