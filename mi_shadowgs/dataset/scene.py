"""Load a scene XML with parameters: lights from angles, the object normalised, parts numbered.

Scene conventions (mi_shadowgs/scenes/default.xml): shapes with ids ``object_<part>`` are
the object's parts, numbered 1.. in XML order (their material ids); ``base`` is the base (id P + 1);
background is 0. Emitters ``light<k>`` are ``directional``; Python turns the parameters
``light<k>_azimuth``/``_elevation`` into ``light<k>_direction`` (the propagation direction,
``-l``). ``object_to_world`` is computed from the object's bounding box so that its bounding
sphere has radius 1, centred on the Y axis, standing on y = 0 (unless ``normalize=false``).
Overriding a computed parameter is an error naming the parameters to set instead.

``mesh.xml`` takes ``-D mesh=PATH``; with ``parts=auto`` and a ``<stem>_parts.json`` beside
the mesh, the object is loaded as one shape per part with the part's material.
Every scene takes ``-D base_texture=mat``: the base's reflectance becomes a procedural
mottled mat (``mat_texture``), so that SfM finds features on photo sets (``--photos``).
Every scene also takes the capture's parameters (``capture.py``: ``-D capture=lab``, a lamp
in place of the directional lights, room light, the photos' jitter).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from mi_shadowgs.core.directions import direction_from_angles
from mi_shadowgs.core.envmap import two_threads
from mi_shadowgs.dataset.capture import (
    RELIGHT_LAMP_NAME,
    Capture,
    captured_scenes,
    lamp_light,
    split_capture,
)

LIGHT_ID = re.compile(r"^light(\d+)$")


class SceneError(ValueError):
    """A scene file, parameter or asset is missing or invalid; the message names it."""


@dataclasses.dataclass(frozen=True)
class Part:
    name: str  # part name (the shape id without "object_")
    shape_id: str
    material_id: int
    bsdf: str  # "diffuse", "principled", ... (after unwrapping twosided)
    albedo: tuple | None = None  # constant linear albedo when known


@dataclasses.dataclass(frozen=True)
class Light:
    name: str
    direction: tuple  # l: unit, toward the light
    irradiance: tuple  # RGB, W/m^2 at normal incidence
    azimuth_deg: float
    elevation_deg: float
    # A lamp (``capture.py``): its centre (world), sphere radius (world units; 0: a point)
    # and distance from the object's centre, where ``direction`` points to it and
    # ``irradiance`` is what it gives. None: a directional light.
    position: tuple | None = None
    radius: float = 0.0
    distance: float = 0.0

    @property
    def is_lamp(self) -> bool:
        return self.position is not None

    def to_json(self) -> dict:
        out = {"name": self.name, "direction": list(self.direction),
               "irradiance": list(self.irradiance), "azimuth_deg": self.azimuth_deg,
               "elevation_deg": self.elevation_deg}
        if self.is_lamp:
            out.update({"type": "lamp", "position": list(self.position),
                        "radius": self.radius, "distance": self.distance,
                        "intensity": [e * self.distance**2 for e in self.irradiance]})
        return out


@dataclasses.dataclass
class SceneSetup:
    path: Path
    params: dict  # every parameter as passed to Mitsuba (strings)
    scene: object  # mi.Scene
    parts: list[Part]
    base_id: int  # material id of the base
    lights: list[Light]
    object_to_world: np.ndarray  # [4, 4]
    object_center: np.ndarray  # [3] centre of the object's bounding sphere
    object_radius: float
    # Every file the load read, by name: "scene" (the XML), "mesh", "parts" (the
    # *_parts.json), "part FILE" / "texture FILE" (relative to it), "file VALUE" (another
    # ``filename`` of the XML). The generator digests them all; ``dataset_scene`` checks them.
    inputs: dict = dataclasses.field(default_factory=dict)  # name -> Path (resolved)
    # lamp, room light and photo jitter (``capture.py``)
    capture: Capture = dataclasses.field(default_factory=Capture)
    # The scene to path-trace where it differs from ``scene`` (a sphere lamp: ``scene``
    # holds it as a point, which rays never hit), else None.
    render_scene: object = None
    # Relit test sets under lamps (``capture.py``'s ``relight_lamp``): (name, [Light]).
    lamp_relights: list = dataclasses.field(default_factory=list)

    @property
    def path_traced(self):
        """The scene the views are path-traced from."""
        return self.scene if self.render_scene is None else self.render_scene

    def shape_material_ids(self) -> dict[str, int]:
        ids = {p.shape_id: p.material_id for p in self.parts}
        ids["base"] = self.base_id
        return ids

    def materials_json(self) -> list[dict]:
        out = [{"id": 0, "name": "background"}]
        for p in self.parts:
            out.append({"id": p.material_id, "name": p.name, "shape": p.shape_id,
                        "bsdf": p.bsdf, "albedo": list(p.albedo) if p.albedo else None})
        out.append({"id": self.base_id, "name": "base", "shape": "base", "bsdf": "diffuse"})
        return out


# -- XML parsing ------------------------------------------------------------------------
def _parse_xml(path: Path) -> ET.Element:
    if not path.is_file():
        raise SceneError(f"scene file not found: {path}")
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SceneError(f"{path}: malformed XML: {exc}") from None


def _bsdf_kind(shape: ET.Element) -> str:
    b = shape.find("bsdf")
    while b is not None and b.get("type") in ("twosided", "mask"):
        b = b.find("bsdf")
    return b.get("type", "unknown") if b is not None else "none"


def _floats(path: Path, name: str, value: str, n: int | None = None) -> list[float]:
    try:
        vals = [float(v) for v in str(value).replace(",", " ").split()]
    except ValueError:
        raise SceneError(f"{path}: parameter {name!r} must be numbers, got {value!r}") from None
    if not vals or (n is not None and len(vals) != n) or not all(map(math.isfinite, vals)):
        want = f"{n} finite number(s)" if n else "finite numbers"
        raise SceneError(f"{path}: parameter {name!r} must be {want}, got {value!r}")
    return vals


def _fmt(v) -> str:
    return ", ".join(f"{float(x):.9g}" for x in np.ravel(v))


def _fmt_matrix(m: np.ndarray) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(m))


# -- normalisation -----------------------------------------------------------------------
def normalizing_transform(bbox_min, bbox_max) -> np.ndarray:
    """[4, 4] that scales the bbox's bounding sphere to radius 1, centres it on the Y axis
    and puts its lowest point on y = 0."""
    lo, hi = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
    half_diag = 0.5 * np.linalg.norm(hi - lo)
    if not np.isfinite(half_diag) or half_diag <= 0:
        raise SceneError(f"the object's bounding box is empty or degenerate: {lo} .. {hi}")
    s = 1.0 / half_diag
    c = 0.5 * (lo + hi)
    m = np.diag([s, s, s, 1.0])
    m[:3, 3] = [-s * c[0], -s * lo[1], -s * c[2]]
    return m


# -- parts (*_parts.json) ----------------------------------------------------------------
def _ply_has_uv(path: Path) -> bool:
    head = path.open("rb").read(2048)
    return b"property float u" in head and b"property float v" in head


def _part_bsdf(json_path: Path, entry: dict, materials: dict
               ) -> tuple[dict, str, tuple | None, str | None]:
    """Mitsuba bsdf dict, kind, constant albedo and texture (as the parts file names it,
    when the part uses one) of one part of a ``*_parts.json``."""
    root = json_path.parent
    part_file = root / entry["file"]
    mat = materials.get(entry.get("material")) if materials else None
    if mat is not None:  # hotdog style: Mitsuba material parameters
        tex = mat.get("base_color_texture")
        if tex and _ply_has_uv(part_file):
            color = {"type": "bitmap", "filename": str(root / tex)}
            albedo = None
        else:
            albedo = tuple(mat.get("base_color", (0.5, 0.5, 0.5)))
            color = {"type": "rgb", "value": list(albedo)}
        if mat.get("bsdf") == "principled":
            inner = {"type": "principled", "base_color": color,
                     "roughness": float(mat.get("roughness", 0.5)),
                     "metallic": float(mat.get("metallic", 0.0))}
            kind = "principled"
        else:
            inner, kind = {"type": "diffuse", "reflectance": color}, "diffuse"
    else:  # MTL style: diffuse, textured where the part has UVs
        tex = entry.get("texture")
        if tex and _ply_has_uv(part_file):
            color, albedo = {"type": "bitmap", "filename": str(root / tex)}, None
        else:
            albedo = tuple(entry.get("mean_linear_albedo") or entry.get("mtl_Kd")
                           or (0.5, 0.5, 0.5))
            color = {"type": "rgb", "value": list(albedo)}
        inner, kind = {"type": "diffuse", "reflectance": color}, "diffuse"
    return {"type": "twosided", "bsdf": inner}, kind, albedo, (tex if albedo is None else None)


def _json_file(path: Path):
    """A JSON file's value, or ``SceneError`` naming the file."""
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: malformed JSON: {exc}") from None


def _read_parts_json(path: Path) -> dict:
    data = _json_file(path)
    parts = data.get("parts") if isinstance(data, dict) else None
    if not isinstance(parts, list) or not parts:
        raise SceneError(f"{path}: field 'parts' must be a non-empty list")
    for i, p in enumerate(parts):
        for key in ("part", "file"):
            if not isinstance(p, dict) or key not in p:
                raise SceneError(f"{path}: missing field 'parts[{i}].{key}'")
        if not (path.parent / p["file"]).is_file():
            raise SceneError(f"{path}: part mesh not found: {path.parent / p['file']} "
                             f"(field 'parts[{i}].file')")
    return data


# -- loading -----------------------------------------------------------------------------
def _resolve_mesh(path: Path, params: dict) -> Path | None:
    value = params.get("mesh", "")
    if "mesh" not in params:
        return None
    if not value:
        raise SceneError(f"{path}: scene needs a mesh: pass -D mesh=PATH (a PLY or OBJ file)")
    mesh = Path(value).expanduser()
    if not mesh.is_absolute() and not mesh.is_file():
        mesh = path.parent / mesh
    if not mesh.is_file():
        raise SceneError(f"mesh file not found: {value} (scene parameter 'mesh' of {path})")
    if mesh.suffix.lower() not in (".ply", ".obj"):
        raise SceneError(f"mesh {mesh}: only .ply and .obj are supported")
    return mesh.resolve()


def _computed_params(root: ET.Element, defaults: dict) -> dict[str, str]:
    """Parameters that ``load_scene`` computes (name -> what to set instead)."""
    out = {"object_to_world": "set 'normalize' instead (true: the object scaled to a unit "
                              "bounding sphere standing on y = 0; false: its own coordinates)"}
    if "mesh" in defaults:
        out["mesh_type"] = "it follows the suffix of 'mesh'; set 'mesh' instead"
    for em in root.findall("emitter"):
        name = em.get("id") or ""
        if LIGHT_ID.match(name):
            out[f"{name}_direction"] = (f"set '{name}_azimuth' and '{name}_elevation' "
                                        f"(degrees) instead")
    return {k: v for k, v in out.items() if k in defaults}


def _scene_params(path: Path, root, overrides: dict | None
                  ) -> tuple[dict[str, str], str, Capture]:
    """(the scene's parameters: its ``<default>`` values with ``overrides``, the base's
    texture, the capture); an unknown or computed parameter is a SceneError naming it."""
    # base_texture and the capture's parameters are Python's, for every scene: kept out of
    # the XML (and of params unless set), so that plain datasets keep their fingerprints.
    capture, overrides = split_capture(path, dict(overrides or {}))
    texture = str(overrides.pop("base_texture", "plain")).strip().lower()
    if texture not in ("plain", "mat"):
        raise SceneError(f"{path}: scene parameter 'base_texture' must be 'plain' or 'mat', "
                         f"got {texture!r}")
    defaults = {d.get("name"): d.get("value") for d in root.iter("default")}
    params = dict(defaults)
    computed = _computed_params(root, defaults)
    for k, v in overrides.items():
        if k not in defaults:
            raise SceneError(f"{path}: unknown scene parameter {k!r}; known: {sorted(defaults)}")
        if k in computed:  # the loader would overwrite it: refuse rather than ignore
            raise SceneError(f"{path}: scene parameter {k!r} is computed, not set; "
                             f"{computed[k]}")
        params[k] = str(v)
    return params, texture, capture


def _scene_lights(path: Path, root, params: dict[str, str]) -> list[Light]:
    """The scene's lights (direction from azimuth/elevation, irradiance as RGB), in their
    number's order; writes each one's direction and irradiance into ``params``."""
    lights = []
    for em in root.findall("emitter"):
        m = LIGHT_ID.match(em.get("id") or "")
        if not m:
            continue
        if em.get("type") != "directional":
            raise SceneError(f"{path}: emitter {em.get('id')!r} must be 'directional'")
        name = em.get("id")
        az = _floats(path, f"{name}_azimuth", params.get(f"{name}_azimuth", ""), 1)[0]
        el = _floats(path, f"{name}_elevation", params.get(f"{name}_elevation", ""), 1)[0]
        irr = _floats(path, f"{name}_irradiance", params.get(f"{name}_irradiance", ""))
        if len(irr) not in (1, 3) or min(irr) < 0:
            raise SceneError(f"{path}: parameter '{name}_irradiance' must be 1 or 3 "
                             f"non-negative numbers, got {params[f'{name}_irradiance']!r}")
        irr = irr * 3 if len(irr) == 1 else irr
        if not 0.0 < el <= 90.0:
            raise SceneError(f"{path}: parameter '{name}_elevation' must be in (0, 90] "
                             f"degrees, got {el}")
        l_dir = direction_from_angles(az, el)
        params[f"{name}_direction"] = _fmt(-l_dir)
        params[f"{name}_irradiance"] = _fmt(irr)
        lights.append(Light(name, tuple(l_dir.tolist()), tuple(irr), az, el))
    lights.sort(key=lambda lt: int(LIGHT_ID.match(lt.name).group(1)))
    return lights


def _mesh_and_parts(path: Path, params: dict[str, str]) -> tuple[Path | None, Path | None]:
    """(the object's mesh file, its parts file), either None; writes the mesh into
    ``params``."""
    mesh = _resolve_mesh(path, params)
    parts_json = None
    if mesh is not None:
        params["mesh"] = str(mesh)
        params["mesh_type"] = mesh.suffix.lower()[1:]
        mode = params.get("parts", "none")
        cand = mesh.with_name(f"{mesh.stem}_parts.json")
        if mode == "auto" and cand.is_file():
            parts_json = cand
        elif mode not in ("auto", "none", ""):
            parts_json = Path(mode)
            if not parts_json.is_file():
                raise SceneError(f"parts file not found: {mode} (scene parameter 'parts')")
    return mesh, parts_json


def load_scene(path: str | Path, overrides: dict[str, str] | None = None) -> SceneSetup:
    """Load a scene XML with ``overrides`` of its ``<default>`` parameters (see module doc)."""
    import mitsuba as mi

    path = Path(path)
    root = _parse_xml(path)
    params, texture, capture = _scene_params(path, root, overrides)
    shapes = [s for s in root.findall("shape")]
    part_elems = [s for s in shapes if (s.get("id") or "").startswith("object_")]
    if not part_elems:
        raise SceneError(f"{path}: no object shape (a <shape id=\"object_<part>\">)")
    if not any(s.get("id") == "base" for s in shapes):
        raise SceneError(f"{path}: no base shape (a <shape id=\"base\">)")
    lights = _scene_lights(path, root, params)
    mesh, parts_json = _mesh_and_parts(path, params)
    normalize = params.get("normalize", "true").strip().lower() not in ("false", "0", "no")
    params["object_to_world"] = _fmt_matrix(np.eye(4))

    # Mitsuba rejects parameters the XML never references (e.g. "normalize", read here).
    used = set(re.findall(r"\$(\w+)", path.read_text()))

    def _load(p):
        try:
            with two_threads():  # an EXR texture or env map in it: see core.envmap
                return mi.load_file(str(path), optimize=False,
                                    **{k: v for k, v in p.items() if k in used})
        except Exception as exc:  # Mitsuba raises RuntimeError with a long trace
            msg = str(exc).strip().splitlines()
            raise SceneError(f"{path}: Mitsuba cannot load the scene: "
                             f"{msg[-1] if msg else exc}") from None

    scene0 = _load(params)
    inputs = _xml_inputs(path, root, params, mesh)
    if parts_json is not None:
        data = _read_parts_json(parts_json)
        inputs["parts"] = parts_json.resolve()
        part_meshes, parts = [], []
        for i, entry in enumerate(data["parts"]):
            bsdf, kind, albedo, texture = _part_bsdf(parts_json, entry,
                                                     data.get("materials") or {})
            inputs[f"part {entry['file']}"] = (parts_json.parent / entry["file"]).resolve()
            if texture is not None:
                inputs[f"texture {texture}"] = (parts_json.parent / texture).resolve()
            sid = f"object_{entry['part']}"
            parts.append(Part(entry["part"], sid, i + 1, kind, albedo))
            part_meshes.append((sid, {"type": "ply", "filename": str(parts_json.parent /
                                                                    entry["file"]),
                                      "bsdf": bsdf}))
        lo, hi = _bbox_of([_load_part(parts_json, sid, d) for sid, d in part_meshes])
    else:
        parts = [Part(e.get("id")[len("object_"):], e.get("id"), i + 1, _bsdf_kind(e))
                 for i, e in enumerate(part_elems)]
        lo, hi = _bbox_of([s for s in scene0.shapes() if s.id().startswith("object_")])
    m = normalizing_transform(lo, hi) if normalize else np.eye(4)
    params["object_to_world"] = _fmt_matrix(m)
    if parts_json is not None:
        desc = {"type": "scene"}
        for s in scene0.shapes():
            if not s.id().startswith("object_"):
                desc[s.id()] = s
        for e in scene0.emitters():
            desc[e.id()] = e
        for sid, d in part_meshes:
            desc[sid] = dict(d, to_world=mi.ScalarTransform4f(m))
        scene = mi.load_dict(desc, optimize=False)  # keep one shape per part
    else:
        scene = _load(params)
    if texture == "mat":
        scene = _with_mat_base(scene)
        params["base_texture"] = texture
    lo_w, hi_w = (m[:3, :3] @ np.stack([lo, hi]).T).T + m[:3, 3]
    centre = 0.5 * (lo_w + hi_w)
    radius = 0.5 * float(np.linalg.norm(hi_w - lo_w))
    render_scene = None
    if capture.lamp is not None or capture.has_room:
        lamp = (lamp_light(capture.lamp, centre, radius, path)
                if capture.lamp is not None else None)
        scene, render_scene = captured_scenes(scene, capture, lamp)
        lights = [lamp] if lamp is not None else lights
    relit = []
    if capture.relight_lamp is not None:
        relit.append((RELIGHT_LAMP_NAME, [lamp_light(capture.relight_lamp, centre, radius,
                                                     path, "lamp", "relight_lamp")]))
    params.update(capture.params)
    return SceneSetup(path=path, params=params, scene=scene, parts=parts,
                      base_id=len(parts) + 1, lights=lights, object_to_world=m,
                      object_center=centre, object_radius=radius, inputs=inputs,
                      capture=capture, render_scene=render_scene, lamp_relights=relit)


def _load_part(parts_json: Path, shape_id: str, desc: dict):
    """One part's shape, or ``SceneError`` naming the part when Mitsuba cannot load it."""
    import mitsuba as mi

    try:
        return mi.load_dict(desc, optimize=False)
    except Exception as exc:  # Mitsuba raises RuntimeError with a long trace
        msg = str(exc).strip().splitlines()
        raise SceneError(f"{parts_json}: part {shape_id[len('object_'):]!r}: Mitsuba cannot "
                         f"load it: {msg[-1] if msg else exc}") from None


def _xml_inputs(path: Path, root: ET.Element, params: dict, mesh: Path | None) -> dict:
    """The XML and the files its ``filename`` strings name (parameters substituted; a
    relative name from the XML's folder, as Mitsuba resolves it). The mesh keeps its name."""
    inputs = {"scene": path.resolve()}
    if mesh is not None:
        inputs["mesh"] = mesh.resolve()
    for el in root.iter("string"):
        if el.get("name") != "filename":
            continue
        value = re.sub(r"\$(\w+)", lambda m: params.get(m.group(1), m.group(0)),
                       el.get("value") or "")
        file = Path(value).expanduser()
        file = (file if file.is_absolute() else path.parent / file).resolve()
        if file.is_file() and file not in inputs.values():
            inputs[f"file {value}"] = file
    return inputs


# -- the textured base ("mat") -------------------------------------------------------------
MAT_SIZE = 1024  # texels per side: ~3 texels per pixel of a 512^2 view of the 3.2-unit base
MAT_SEED = 7  # one fixed mat: datasets differ by their scene parameters, not by chance


def mat_texture(size: int = MAT_SIZE, seed: int = MAT_SEED) -> np.ndarray:
    """A mottled mat texture [size, size, 3] (linear albedo in [0.04, 0.8]): patches of a
    few hues with sharp edges at several sizes, and scattered dots, as photogrammetry mats
    print, so that SIFT finds many distinct, repeatable corners and blobs on the base (a
    plain base gives SfM nothing to match; smooth noise gives it nothing stable)."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    palette = np.array([[0.75, 0.72, 0.62], [0.08, 0.10, 0.14], [0.60, 0.18, 0.10],
                        [0.12, 0.35, 0.55], [0.70, 0.60, 0.15], [0.20, 0.45, 0.20],
                        [0.45, 0.45, 0.45]])

    def field(sigma):
        f = ndimage.gaussian_filter(rng.normal(size=(size, size)), sigma, mode="wrap")
        return (f - f.mean()) / f.std()

    # patches: the palette index follows two coarse fields, with sharp boundaries
    idx = (np.floor(1.6 * field(40.0)) + 3 * np.floor(1.2 * field(22.0))) % len(palette)
    tex = palette[idx.astype(int)]
    # dots of a few radii in random palette colours
    yy, xx = np.mgrid[0:size, 0:size]
    for radius, count in ((18, 90), (11, 220), (7, 400)):
        cy, cx = rng.uniform(0, size, (2, count))
        col = palette[rng.integers(0, len(palette), count)]
        near = np.full((size, size), -1)
        dist = np.full((size, size), np.inf)
        for k in range(count):
            y0, y1 = int(max(cy[k] - radius, 0)), int(min(cy[k] + radius + 1, size))
            x0, x1 = int(max(cx[k] - radius, 0)), int(min(cx[k] + radius + 1, size))
            d = np.hypot(yy[y0:y1, x0:x1] - cy[k], xx[y0:y1, x0:x1] - cx[k])
            hit = (d < radius) & (d < dist[y0:y1, x0:x1])
            dist[y0:y1, x0:x1][hit] = d[hit]
            near[y0:y1, x0:x1][hit] = k
        tex = np.where(near[..., None] >= 0, col[np.maximum(near, 0)], tex)
    tex = ndimage.gaussian_filter(tex, (0.7, 0.7, 0))  # anti-alias the edges a little
    return np.clip(tex, 0.04, 0.8).astype(np.float32)


def _with_mat_base(scene):
    """``scene`` with its base's reflectance replaced by the ``mat_texture`` (same shape)."""
    import mitsuba as mi

    desc = {"type": "scene"}
    for sh in scene.shapes():
        if sh.id() != "base":
            desc[sh.id()] = sh
            continue
        to_world = mi.traverse(sh)["to_world"]
        desc["base"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(
            np.array(to_world.matrix, dtype=np.float64).reshape(4, 4)),
            "bsdf": {"type": "diffuse", "reflectance": {
                "type": "bitmap", "bitmap": mi.Bitmap(mat_texture()), "raw": True,
                "filter_type": "bilinear"}}}
    for em in scene.emitters():
        desc[em.id()] = em
    return mi.load_dict(desc, optimize=False)


def _bbox_of(shapes) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for s in shapes:
        b = s.bbox()
        lo = np.minimum(lo, np.array(b.min, dtype=np.float64))
        hi = np.maximum(hi, np.array(b.max, dtype=np.float64))
    return lo, hi


# -- a generated dataset's scene, reloaded -----------------------------------------------------
# Parameters a dataset records that ``load_scene`` derives from the others.
_DERIVED = re.compile(r"object_to_world|mesh_type|light\d+_direction")


def dataset_scene(data: str | Path) -> SceneSetup:
    """The scene a generated dataset was rendered from, reloaded with its recorded
    parameters: the ground truth that validations trace.

    Only what was rendered is returned. Every file the scene read then (its manifest's
    inputs) must have the same content now, and the object must be placed as recorded;
    otherwise ``SceneError`` names what differs. A shipped scene recorded at a path that is
    gone (another clone) is taken from this install when its content is the same.
    """
    from mi_shadowgs.dataset import layout
    from mi_shadowgs.io.provenance import file_digest, read_manifest
    from mi_shadowgs.scenes import SCENE_DIR

    data = Path(data)
    info_path = data / layout.DATASET_JSON
    if not info_path.is_file():
        raise SceneError(f"{info_path}: not found: only a dataset made by mi-shadowgs "
                         "generate records the scene to reload")
    info = _json_file(info_path)
    recorded = info.get("scene") if isinstance(info, dict) else None
    if not isinstance(recorded, str) or not recorded:
        raise SceneError(f"{info_path}: no field 'scene': only a dataset made by "
                         "mi-shadowgs generate has a scene to reload")
    manifest = read_manifest(data)
    generated = manifest is not None and manifest.get("command") == "generate"
    made = (manifest.get("inputs") or {}) if generated else {}  # name -> {path, digest}
    scene = Path(recorded)
    if not scene.is_file():
        shipped = SCENE_DIR / scene.name
        want = (made.get("scene") or {}).get("digest")
        if not (shipped.is_file() and want and file_digest(shipped) == want):
            why = (f"; the shipped {shipped.name} is not the file it was rendered from"
                   if shipped.is_file() else "")
            raise SceneError(f"{info_path}: the scene file it was rendered from is gone: "
                             f"{recorded} (field 'scene'){why}")
        scene = shipped
    params = {k: str(v) for k, v in (info.get("parameters") or {}).items()
              if not _DERIVED.fullmatch(k)}
    try:
        setup = load_scene(scene, params)
    except SceneError as exc:
        raise SceneError(f"{info_path}: its scene cannot be reloaded: {exc}") from None

    changed = [f"{setup.inputs[name]} ({name})" for name, ref in made.items()
               if name in setup.inputs and file_digest(setup.inputs[name]) != ref.get("digest")]
    changed += [f"{ref.get('path')} ({name}: no longer read)" for name, ref in made.items()
                if name not in setup.inputs and not name.startswith("envmap ")]
    if changed:
        raise SceneError(f"{data}: the files its scene was rendered from have changed: "
                         f"{', '.join(changed)}. Traced now, its ground truth would not match "
                         "its images: restore them or generate the dataset again")
    placed = (info.get("parameters") or {}).get("object_to_world")
    if placed is not None and not np.allclose(
            _floats(info_path, "object_to_world", placed),
            _floats(info_path, "object_to_world", setup.params["object_to_world"]),
            rtol=1e-6, atol=1e-7):
        raise SceneError(f"{info_path}: the reloaded object is not where it was rendered "
                         f"(parameter 'object_to_world' {placed!r}, now "
                         f"{setup.params['object_to_world']!r})")
    unchecked = sorted(set(setup.inputs) - set(made))
    if unchecked:  # datasets made before the manifest recorded these files
        named = ", ".join(unchecked[:3]) + (f" and {len(unchecked) - 3} more"
                                            if len(unchecked) > 3 else "")
        print(f"mi-shadowgs: warning: {data}: its manifest has no digest of {named} "
              "(it predates their record); they are used as they are now", file=sys.stderr)
    return setup
