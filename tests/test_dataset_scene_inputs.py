"""A dataset's scene inputs: every file the scene reads is digested at generation, and the
validations reload only the scene that was rendered (``dataset.scene.dataset_scene``).

A tiny mesh asset in the ``*_parts.json`` layout of ../shared/data (two boxes, one of them
textured) stands in for the shared assets, so that this runs on a fresh machine.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mi_shadowgs.cli import main as cli_main
from mi_shadowgs.dataset.scene import SceneError, dataset_scene, load_scene
from mi_shadowgs.io.images import write_png
from mi_shadowgs.io.provenance import MANIFEST_NAME
from mi_shadowgs.scenes import scene_path

TINY = ["--width", "24", "--height", "24", "--n-train", "2", "--n-test", "1", "--spp", "2",
        "--envmap", "sky", "--no-progress"]
PARTS_INPUTS = {"scene", "mesh", "parts", "part parts/a.ply", "part parts/b.ply",
                "texture textures/wood.png"}


def _box_ply(path: Path, lo, hi) -> None:
    """A closed box [lo, hi] as a binary PLY with per-vertex UVs (12 triangles)."""
    from plyfile import PlyData, PlyElement

    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])], np.float32)  # [8, 3], index = 4x + 2y + z
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4),
             (1, 5, 7, 3)]  # outward: -x, +x, -y, +y, -z, +z
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    vertex = np.empty(8, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("u", "f4"), ("v", "f4")])
    for k, name in enumerate("xyz"):
        vertex[name] = corners[:, k]
    vertex["u"], vertex["v"] = corners[:, 0] - lo[0], corners[:, 1] - lo[1]
    face = np.empty(len(tris), [("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = tris
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(vertex, "vertex"),
             PlyElement.describe(face, "face")]).write(str(path))


def _parts_asset(root: Path) -> Path:
    """root/toy.ply (the merged mesh), toy_parts.json, parts/{a,b}.ply, textures/wood.png."""
    _box_ply(root / "toy.ply", (-0.6, 0.0, -0.3), (0.6, 0.5, 0.3))
    _box_ply(root / "parts" / "a.ply", (-0.6, 0.0, -0.3), (-0.1, 0.5, 0.3))
    _box_ply(root / "parts" / "b.ply", (0.1, 0.0, -0.3), (0.6, 0.5, 0.3))
    (root / "textures").mkdir()
    write_png(root / "textures" / "wood.png", np.full((4, 4, 3), 0.3, np.float32))
    (root / "toy_parts.json").write_text(json.dumps({"parts": [
        {"part": "a", "file": "parts/a.ply", "mean_linear_albedo": [0.6, 0.2, 0.1]},
        {"part": "b", "file": "parts/b.ply", "texture": "textures/wood.png"}]}))
    return root / "toy.ply"


def _generate(argv, capsys):
    rc = cli_main(["generate", *argv])
    return rc, capsys.readouterr()


def test_load_scene_names_every_file_it_reads(tmp_path):
    mesh = _parts_asset(tmp_path / "toy")
    setup = load_scene(scene_path("mesh"), {"mesh": str(mesh)})
    assert set(setup.inputs) == PARTS_INPUTS
    assert setup.inputs["texture textures/wood.png"] == (tmp_path / "toy" / "textures" /
                                                         "wood.png").resolve()
    assert [p.name for p in setup.parts] == ["a", "b"]
    # A procedural scene reads its XML alone.
    assert load_scene(scene_path("default")).inputs == {"scene": scene_path("default")}


def test_a_changed_part_is_a_new_dataset_and_not_its_ground_truth(tmp_path, capsys):
    mesh = _parts_asset(tmp_path / "toy")
    out = tmp_path / "data"
    argv = ["mesh", "-D", f"mesh={mesh}", "--out", str(out), *TINY]
    assert _generate(argv, capsys)[0] == 0
    made = json.loads((out / MANIFEST_NAME).read_text())["inputs"]
    assert PARTS_INPUTS <= set(made)
    assert dataset_scene(out).inputs.keys() == PARTS_INPUTS

    # A part's material edited after the dataset was made: before, the fingerprint covered
    # only the XML and the merged mesh, so generate answered "nothing to do" and the
    # validations traced the edited scene against the old images.
    parts = tmp_path / "toy" / "toy_parts.json"
    original = parts.read_text()
    parts.write_text(original.replace("[0.6, 0.2, 0.1]", "[0.1, 0.2, 0.6]"))
    rc, cap = _generate(argv, capsys)
    assert rc == 2 and "different dataset" in cap.err, cap.err
    with pytest.raises(SceneError, match=r"have changed: .*toy_parts\.json \(parts\)"):
        dataset_scene(out)
    parts.write_text(original)
    texture = tmp_path / "toy" / "textures" / "wood.png"
    write_png(texture, np.full((4, 4, 3), 0.7, np.float32))
    with pytest.raises(SceneError, match=r"wood\.png \(texture textures/wood\.png\)"):
        dataset_scene(out)
    texture.write_bytes(b"not a PNG")  # Mitsuba's own error, named by the part
    with pytest.raises(SceneError, match=r"toy_parts\.json: part 'b': Mitsuba cannot load"):
        dataset_scene(out)


def test_a_dataset_whose_manifest_predates_the_parts_warns(tmp_path, capsys):
    mesh = _parts_asset(tmp_path / "toy")
    out = tmp_path / "data"
    assert _generate(["mesh", "-D", f"mesh={mesh}", "--out", str(out), *TINY], capsys)[0] == 0
    manifest_path = out / MANIFEST_NAME
    manifest = json.loads(manifest_path.read_text())
    manifest["inputs"] = {k: v for k, v in manifest["inputs"].items()
                          if k in ("scene", "mesh")}  # as the generator recorded them before
    manifest_path.write_text(json.dumps(manifest))
    setup = dataset_scene(out)
    err = capsys.readouterr().err
    assert "no digest of part parts/a.ply, part parts/b.ply, parts and 1 more" in err, err
    assert [p.name for p in setup.parts] == ["a", "b"]


def test_a_dataset_from_another_clone_reloads_the_shipped_scene(tmp_path, capsys):
    out = tmp_path / "data"
    assert _generate(["default", "--out", str(out), *TINY], capsys)[0] == 0
    info_path = out / "dataset.json"
    info = json.loads(info_path.read_text())
    # The recorded parameters include the derived ones (object_to_world, the lights'
    # directions), which load_scene refuses as overrides: validation.decomposition did so.
    assert "object_to_world" in info["parameters"]
    with pytest.raises(SceneError, match="computed"):
        load_scene(info["scene"], info["parameters"])
    setup = dataset_scene(out)
    assert setup.params["object_to_world"] == info["parameters"]["object_to_world"]

    def record(scene: str) -> None:
        info_path.write_text(json.dumps(dict(info, scene=scene)))

    record("/gone/clone/mi_shadowgs/scenes/default.xml")  # the clone it was made in is gone
    assert dataset_scene(out).path == scene_path("default")
    record("/gone/clone/scenes/mine.xml")
    with pytest.raises(SceneError, match=r"gone: /gone/clone/scenes/mine\.xml \(field 'scene'\)"):
        dataset_scene(out)
    # This install's default.xml is not the one the dataset was rendered from.
    manifest_path = out / MANIFEST_NAME
    manifest = manifest_path.read_text()
    digest = json.loads(manifest)["inputs"]["scene"]["digest"]
    manifest_path.write_text(manifest.replace(digest, "0" * 32))
    record("/gone/clone/mi_shadowgs/scenes/default.xml")
    with pytest.raises(SceneError, match="shipped default.xml is not the file it was rendered"):
        dataset_scene(out)
    # An object placed elsewhere than the images have it (normalisation changed since).
    manifest_path.write_text(manifest)
    info["parameters"]["object_to_world"] = "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"
    record(str(scene_path("default")))
    with pytest.raises(SceneError, match="'object_to_world'"):
        dataset_scene(out)


def test_a_folder_without_a_generated_scene_is_named(tmp_path):
    with pytest.raises(SceneError, match=r"dataset\.json: not found: only a dataset made by"):
        dataset_scene(tmp_path)
    (tmp_path / "dataset.json").write_text(json.dumps({"format_version": 1}))
    with pytest.raises(SceneError, match="no field 'scene'"):
        dataset_scene(tmp_path)


def test_a_file_a_users_xml_names_is_an_input(tmp_path, capsys):
    """A user's scene XML whose base reads a texture (a ``filename`` of the XML, relative to
    it): the texture is an input of the dataset, and editing it makes another dataset."""
    xml = scene_path("default").read_text().replace(
        '<bsdf type="diffuse"><rgb name="reflectance" value="$base_albedo"/></bsdf>\n  </shape>\n'
        '</scene>',
        '<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
        '<string name="filename" value="mat.png"/></texture></bsdf>\n  </shape>\n</scene>')
    assert "mat.png" in xml
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "scene.xml").write_text(xml)
    write_png(tmp_path / "mine" / "mat.png", np.full((4, 4, 3), 0.4, np.float32))
    setup = load_scene(tmp_path / "mine" / "scene.xml")
    assert setup.inputs["file mat.png"] == (tmp_path / "mine" / "mat.png").resolve()
    out = tmp_path / "data"
    argv = [str(tmp_path / "mine" / "scene.xml"), "--out", str(out), *TINY]
    assert _generate(argv, capsys)[0] == 0
    assert "file mat.png" in json.loads((out / MANIFEST_NAME).read_text())["inputs"]
    write_png(tmp_path / "mine" / "mat.png", np.full((4, 4, 3), 0.6, np.float32))
    rc, cap = _generate(argv, capsys)
    assert rc == 2 and "different dataset" in cap.err, cap.err
