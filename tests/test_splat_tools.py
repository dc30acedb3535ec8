"""The splat PLYs in the splat tools themselves: PlayCanvas's ``splat-transform`` (npm
``@playcanvas/splat-transform``) reads our export and writes it back (dropping our header
comments), which our reader reads back right with ``SPLAT_TOOLS``.

Needs node with ``splat-transform`` (``npm install -g @playcanvas/splat-transform``, or the
path of its CLI in ``SPLAT_TRANSFORM``); skipped with the reason where it is missing.
Nothing is installed here.
"""

from __future__ import annotations

import os
import shutil
import subprocess

import numpy as np
import pytest

from mi_shadowgs import cli
from mi_shadowgs.io import ply
from tests import synthetic_asset as syn

SPLAT_TRANSFORM = os.environ.get("SPLAT_TRANSFORM") or shutil.which("splat-transform")
NO_SPLAT = ("needs node and PlayCanvas's splat-transform (apt-get install -y nodejs npm; "
            "npm install -g @playcanvas/splat-transform, or SPLAT_TRANSFORM=path/to/its "
            "cli); not found")
pytestmark = pytest.mark.skipif(SPLAT_TRANSFORM is None, reason=NO_SPLAT)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("splat")
    run, _ = syn.fake_run(root)
    out = root / "export"
    assert cli.main(["export", str(run), "--format", "3dgs-ply", "--out", str(out),
                     "--no-progress"]) == 0
    return run, out / "point_cloud.ply"


def _splat_transform(*args, timeout=300) -> subprocess.CompletedProcess:
    res = subprocess.run([SPLAT_TRANSFORM, "-w", *map(str, args)], capture_output=True,
                         text=True, timeout=timeout)
    assert res.returncode == 0, res.stdout + res.stderr
    return res


def test_a_round_trip_through_splat_transform_reads_back_with_one_flag(exported, tmp_path):
    run, path = exported
    ours = ply.read_ply_model(run / "material" / "full" / "model.ply")
    assert ply.read_ply_model(path).position.tobytes() == ours.position.tobytes()
    _splat_transform(path, tmp_path / "back.ply")
    assert ply.read_ply_metadata(tmp_path / "back.ply") == {}  # the comments are gone
    back = ply.read_ply_model(tmp_path / "back.ply", **ply.SPLAT_TOOLS)
    order = np.lexsort(back.position.T)  # the tool may reorder the splats
    ref = np.lexsort(ours.position.T)
    np.testing.assert_allclose(back.position[order], ours.position[ref], atol=1e-6)
    q = back.rotation[order] / np.linalg.norm(back.rotation[order], axis=1, keepdims=True)
    r = ours.rotation[ref] / np.linalg.norm(ours.rotation[ref], axis=1, keepdims=True)
    assert np.abs(np.abs(np.sum(q * r, axis=1)) - 1).max() < 1e-5  # the same rotations
    k = ours.channels["sh"].shape[1]
    np.testing.assert_allclose(back.channels["sh"][order, :k], ours.channels["sh"][ref],
                               atol=2e-4)
