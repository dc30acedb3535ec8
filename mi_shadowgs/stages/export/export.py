"""Relightable assets out of a finished run (``mi-shadowgs export``): the stage-4 model
(``RUN/material/full/model.ply``, ``light.json``) as a file other tools load.

Formats (``--out`` is a folder; it gets a provenance manifest like every output):
- ``3dgs-ply`` -> ``point_cloud.ply``: the 3DGS layout that 3DGS's ``load_ply`` and splat
  viewers (SuperSplat, splat-transform, three.js viewers) read: ``x y z nx ny nz f_dc_0..2
  f_rest_0..44 opacity scale_0..2 rot_0..3``. SH padded with zeros to degree 3 (3DGS and
  2DGS load at ``max_sh_degree`` 3 and assert 45 ``f_rest``); ``scale_2`` is the log of
  ``thickness`` times the smaller tangent scale, so each surfel is a flat 3D Gaussian with
  its thin axis along its normal (the quaternion's third column).
- ``2dgs-ply`` -> ``point_cloud.ply``: 2DGS's layout (two scales), SH padded to degree 3,
  then our extra channels (albedo_0..2, roughness, metallic, segment, ...; linear), and the
  stage-4 model's header records (``comment mi_shadowgs ...``: receiver band, shadow maps,
  specular), so that relighting this file gives the run's relit views.
- ``mesh`` -> ``object.ply``/``object.obj`` (+ ``base.ply``/``base.obj`` when the base is
  known), ``asset.glb`` (both meshes, glTF binary), ``scene.xml``, ``export.json``: see
  ``mi_shadowgs.stages.export.mesh``. The object is closed where it stands on the base
  (``mi_shadowgs.stages.export.close``); ``export.json`` says whether it is watertight and,
  if not, why. The PLYs carry the standard uchar ``red green blue alpha`` vertex colours
  (the albedo in sRGB, which mesh tools show) and per-vertex ``albedo_r/g/b``,
  ``roughness_0``, ``metallic_0`` and ``ggxalpha_0`` (roughness^2, clamped as in
  ``core.brdf``; linear; Mitsuba loads them as ``vertex_albedo_color``,
  ``vertex_roughness``, ``vertex_metallic``, ``vertex_ggxalpha``); the OBJs and the glTF
  hold sRGB vertex colours of the albedo for viewers. ``scene.xml`` needs only Mitsuba:
  each mesh with a BSDF driven by ``mesh_attribute`` textures (``ExportConfig.bsdf``, below),
  the fitted lights as ``directional`` emitters (a fitted lamp as a ``point`` emitter of its
  intensity, or with a radius as a ``sphere`` with an ``area`` emitter of radiance
  I / (pi R^2)), one ``perspective`` sensor per test camera
  (``$resx``, ``$resy``, ``$spp``, ``$max_depth`` can be overridden at load).

The BSDF (``ExportConfig.bsdf``):
- ``"model"`` (default): our Cook-Torrance (``core.brdf``) out of Mitsuba's own plugins. It
  is linear in the metallic m: f = (1 - m) [a / pi + spec(F0 = 0.04)] + m spec(F0 = a), so a
  ``blendbsdf`` weighted by ``vertex_metallic`` mixes a dielectric and a metal. The
  dielectric sums a Lambertian lobe and a GGX lobe; Mitsuba has no sum, so it is a 50/50
  ``blendbsdf`` of ``diffuse`` (reflectance 2a) and ``roughconductor`` (reflectance 2, the
  Fresnel of eta 1.5: F0 = 0.04). The metal is a ``roughconductor`` of reflectance a (its
  Fresnel is 1: Schlick's rise toward grazing angles is left out). GGX alpha and the
  separable Smith G are ours; the Fresnel of the dielectric is the exact one rather than
  Schlick's (within 1 % of it below 70 deg).
- ``"principled"``: Mitsuba's Disney ``principled`` (base colour, roughness, metallic), the
  layout other tools map to. Its diffuse lobe is Disney's, not Lambert's: under grazing
  views and lights it differs from the fitted model by up to ~2x (retro-reflection).

Frame of the splat PLYs (``--frame``): by default the splat tools' (OpenCV/COLMAP: Y down,
``x, y, z = x, -y, -z`` of ours, the quaternions and SH turned with it), which SuperSplat,
PlayCanvas and 3DGS's viewers take a PLY's world to be, so the asset stands upright in them;
``--frame y-up`` keeps ours. The header records it (``world_frame``), so our reader turns
the file back; a copy that lost its header (splat-transform drops comments) reads right with
``io.ply.SPLAT_TOOLS`` (``mi-shadowgs render --splat-conventions``).

Colours in the splat PLYs are what splat viewers display: sRGB values (3DGS trains on sRGB
images). ``--color sh`` converts the model's linear SH (``io.ply.sh_to_srgb``): the DC term
exactly (its view-mean colour through the sRGB curve), the higher bands to first order
(scaled by the curve's slope at the DC colour). ``--color albedo`` writes the shadow-free
albedo, in sRGB, as the DC term with the higher bands zero, so a viewer shows the
relightable albedo. Both PLYs record ``sh_space srgb`` in their header, so that our own
reader (``surfel_raster``, ``mi-shadowgs render``, ``api.load_model``) turns the SH back
into linear ones instead of showing them washed out. sRGB values end at white: a splat whose
view-mean colour lies outside [0, 1] is clipped there, said in a warning and recorded in the
header (``display_clipped_splats``); the run's ``model.ply`` keeps it (``clip_record``).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from mi_shadowgs.io.ply import (
    CLIPPED_KEY,
    FRAME_KEY,
    FRAMES,
    SH_C0,
    SH_SPACE_KEY,
    display_clipped,
    sh_to_srgb,
    to_frame,
)
from mi_shadowgs.stages.export import mesh as mesh_mod

FORMATS = ("3dgs-ply", "2dgs-ply", "mesh")
BSDFS = ("model", "principled")
COLORS = ("sh", "albedo")
PLY_SH_DEGREE = 3  # what 3DGS/2DGS's load_ply expect (max_sh_degree default)
# What the splat PLYs hold, a setting of their provenance so that an older export is not
# reused as this one: 2 = with the header records (the fit's, ``sh_space``).
SPLAT_LAYOUT = 2
# The splat PLYs' world: the splat tools' (3DGS, COLMAP, SuperSplat, PlayCanvas: Y down), so
# that viewers show the scene upright; "y-up" keeps ours. Recorded in the header.
DEFAULT_FRAME = "opencv"
MATERIAL_FOLDER = "material/full"


@dataclasses.dataclass(frozen=True)
class ExportConfig:
    mesh: mesh_mod.MeshConfig = mesh_mod.MeshConfig()
    # 3dgs-ply scale_2: thickness x the smaller tangent scale. Thin enough that a surfel
    # seen edge-on stays a line (as in 2DGS), thick enough that viewers' covariance
    # inversions stay well-conditioned in float32.
    thickness: float = 0.05
    spp: int = 64  # scene.xml's default samples per pixel
    max_depth: int = 8  # scene.xml's default path length (enough for inter-reflections)
    bsdf: str = "model"  # "model" (our Cook-Torrance) or "principled" (Disney): see above

    def __post_init__(self):
        if not (0 < self.thickness <= 1 and self.spp >= 1 and self.max_depth >= 1):
            raise ValueError(f"ExportConfig: bad settings {self}")
        if self.bsdf not in BSDFS:
            raise ValueError(f"ExportConfig.bsdf must be one of {BSDFS}, got {self.bsdf!r}")


class ExportError(ValueError):
    """The run cannot be exported as asked; the message names the file or setting."""


# -- splat PLYs --------------------------------------------------------------------------
def _albedo_sh(albedo: np.ndarray, k: int) -> np.ndarray:
    """SH [N, K*3] whose colour is sRGB(albedo) from every direction."""
    from mi_shadowgs.io.images import linear_to_srgb

    sh = np.zeros((len(albedo), k, 3), np.float32)
    sh[:, 0] = (linear_to_srgb(np.clip(albedo.astype(np.float64), 0.0, 1.0)) - 0.5) / SH_C0
    return sh.reshape(len(albedo), 3 * k)


def _pad_sh(sh: np.ndarray, degree: int = PLY_SH_DEGREE) -> np.ndarray:
    k = (degree + 1) ** 2
    out = np.zeros((sh.shape[0], 3 * k), np.float32)
    out[:, : sh.shape[1]] = sh
    return out


def display_sh(model, color: str) -> np.ndarray:
    """The splat PLYs' SH [N, 48] (degree 3, coefficient-major) of a PlyModel."""
    if color == "albedo":
        if "albedo" not in model.channels:
            raise ExportError("--color albedo: the model has no 'albedo' channel (run stage 4)")
        return _albedo_sh(model.channels["albedo"], (PLY_SH_DEGREE + 1) ** 2)
    if "sh" not in model.channels:
        raise ExportError("--color sh: the model has no 'sh' channel; use --color albedo")
    return sh_to_srgb(_pad_sh(model.channels["sh"]))


def clip_record(model, color: str, fmt: str, out) -> dict[str, str]:
    """The header record of the splats whose colours the display SH clip at white (none:
    empty), said once on stderr; ``--color albedo`` is clipped as the albedo is, in [0, 1]."""
    if fmt == "mesh" or color != "sh" or "sh" not in model.channels:
        return {}
    n = display_clipped(model.channels["sh"])
    if n:
        print(f"mi-shadowgs: warning: {out}: {n} of {model.count} splats have colours outside "
              "[0, 1] (brighter than white, or below black): the display SH clip them, so "
              "the PLY renders them unlike the run (a colour above 1 darker); its header "
              f"records {CLIPPED_KEY} {n}, and the run's model.ply keeps them", file=sys.stderr)
    return {CLIPPED_KEY: str(n)} if n else {}


def gs3d_columns(model, color: str, config: ExportConfig) -> dict[str, np.ndarray]:
    """Vertex properties of the 3DGS PLY, in 3DGS's order (name -> [N] float32)."""
    from mi_shadowgs.io.ply import sh_to_dc_rest

    f_dc, f_rest = sh_to_dc_rest(display_sh(model, color))
    cols = {a: model.position[:, i] for i, a in enumerate("xyz")}
    cols.update({a: model.normals()[:, i] for i, a in enumerate(("nx", "ny", "nz"))})
    cols.update({f"f_dc_{i}": f_dc[:, i] for i in range(3)})
    cols.update({f"f_rest_{i}": f_rest[:, i] for i in range(f_rest.shape[1])})
    cols["opacity"] = model.opacity_logit
    cols["scale_0"], cols["scale_1"] = model.log_scale[:, 0], model.log_scale[:, 1]
    cols["scale_2"] = np.min(model.log_scale, axis=1) + np.float32(np.log(config.thickness))
    cols.update({f"rot_{i}": model.rotation[:, i] for i in range(4)})
    return {k: np.asarray(v, np.float32) for k, v in cols.items()}


def gs2d_model(model, color: str):
    """The PlyModel of the 2DGS PLY: display SH of degree 3, every other channel kept."""
    channels = dict(model.channels)
    channels["sh"] = display_sh(model, color)
    return dataclasses.replace(model, channels=channels)


# -- mesh and scene ------------------------------------------------------------------------
def ggx_alpha(roughness: np.ndarray) -> np.ndarray:
    """GGX alpha of ``core.brdf``: roughness^2 with the roughness clamped to its minimum."""
    from mi_shadowgs.core.brdf import ROUGHNESS_MIN

    return np.square(np.maximum(np.asarray(roughness, np.float64), ROUGHNESS_MIN))


def _attribute(parent, name: str, attr: str, scale: float = 1.0):
    import xml.etree.ElementTree as ET

    tex = ET.SubElement(parent, "texture", type="mesh_attribute", name=name)
    ET.SubElement(tex, "string", name="name", value=attr)
    if scale != 1.0:
        ET.SubElement(tex, "float", name="scale", value=f"{scale:g}")
    return tex


def bsdf_xml(parent, kind: str) -> None:
    """The BSDF of an exported mesh (module docstring, "The BSDF") under ``parent``."""
    import xml.etree.ElementTree as ET

    from mi_shadowgs.core.brdf import F0_DIELECTRIC

    if kind == "principled":
        bsdf = ET.SubElement(parent, "bsdf", type="principled")
        for param, attr in (("base_color", "vertex_albedo_color"),
                            ("roughness", "vertex_roughness"), ("metallic", "vertex_metallic")):
            _attribute(bsdf, param, attr)
        return
    # the dielectric's Fresnel: eta with ((eta - 1) / (eta + 1))^2 = F0_DIELECTRIC
    eta = (1.0 + F0_DIELECTRIC ** 0.5) / (1.0 - F0_DIELECTRIC ** 0.5)
    top = ET.SubElement(parent, "bsdf", type="blendbsdf")
    _attribute(top, "weight", "vertex_metallic")
    dielectric = ET.SubElement(top, "bsdf", type="blendbsdf")  # 0.5 (2 a/pi) + 0.5 (2 spec)
    ET.SubElement(dielectric, "float", name="weight", value="0.5")
    lambert = ET.SubElement(dielectric, "bsdf", type="diffuse")
    _attribute(lambert, "reflectance", "vertex_albedo_color", 2.0)
    coat = ET.SubElement(dielectric, "bsdf", type="roughconductor")
    ET.SubElement(coat, "string", name="distribution", value="ggx")
    _attribute(coat, "alpha", "vertex_ggxalpha")
    ET.SubElement(coat, "float", name="eta", value=f"{eta:.9g}")
    ET.SubElement(coat, "float", name="k", value="0")
    ET.SubElement(coat, "float", name="specular_reflectance", value="2")
    metal = ET.SubElement(top, "bsdf", type="roughconductor")
    ET.SubElement(metal, "string", name="distribution", value="ggx")
    ET.SubElement(metal, "string", name="material", value="none")
    _attribute(metal, "alpha", "vertex_ggxalpha")
    _attribute(metal, "specular_reflectance", "vertex_albedo_color")


def vertex_colors(part: mesh_mod.MeshPart) -> np.ndarray:
    """[V, 4] uint8 RGBA: the albedo in sRGB (rounded: within 1/255), opaque."""
    from mi_shadowgs.io.images import linear_to_srgb

    rgb = linear_to_srgb(np.clip(part.albedo.astype(np.float64), 0.0, 1.0))
    rgba = np.full((len(part.vertices), 4), 255, np.uint8)
    rgba[:, :3] = np.round(rgb * 255.0).astype(np.uint8)
    return rgba


def _trimesh(part: mesh_mod.MeshPart):
    import trimesh

    return trimesh.Trimesh(part.vertices, part.faces, vertex_normals=part.normals,
                           vertex_colors=vertex_colors(part), process=False)


def _mesh_ply_bytes(part: mesh_mod.MeshPart) -> bytes:
    """Binary PLY: normals, the standard uchar ``red green blue alpha`` (sRGB albedo) that
    mesh tools show, then the float materials Mitsuba reads (module docstring)."""
    import trimesh

    m = _trimesh(part)
    for c, name in enumerate("rgb"):
        m.vertex_attributes[f"albedo_{name}"] = part.albedo[:, c].astype(np.float32)
    m.vertex_attributes["roughness_0"] = part.roughness.astype(np.float32)
    m.vertex_attributes["metallic_0"] = part.metallic.astype(np.float32)
    m.vertex_attributes["ggxalpha_0"] = ggx_alpha(part.roughness).astype(np.float32)
    return trimesh.exchange.ply.export_ply(m, encoding="binary", vertex_normal=True,
                                           include_attributes=True)


def _glb_bytes(parts: dict[str, mesh_mod.MeshPart]) -> bytes:
    """glTF binary of the meshes (one node each, named by part) with the sRGB albedo as
    vertex colours (``COLOR_0``), written by trimesh. glTF's frame is ours: Y-up,
    right-handed, metres as scene units."""
    import trimesh

    scene = trimesh.Scene()
    for name, part in parts.items():
        scene.add_geometry(_trimesh(part), node_name=name, geom_name=name)
    return scene.export(file_type="glb", include_normals=True)


def _mesh_obj_text(part: mesh_mod.MeshPart) -> str:
    """Wavefront OBJ with normals and "v x y z r g b" vertex colours (the common extension
    MeshLab, Blender and trimesh read): the albedo in sRGB. One %-format over whole arrays:
    trimesh's writer took tens of seconds on a busy machine for a 300k-triangle mesh."""
    from mi_shadowgs.io.images import linear_to_srgb

    rgb = linear_to_srgb(part.albedo.astype(np.float64))
    nv, nf = len(part.vertices), len(part.faces)
    v = np.concatenate([part.vertices.astype(np.float64), rgb], axis=1)
    f = np.repeat(part.faces.astype(np.int64) + 1, 2, axis=1)  # OBJ counts from 1: f a//a ...
    return ("# mi-shadowgs export: vertex colours = albedo (sRGB)\n"
            + "v %.6f %.6f %.6f %.4f %.4f %.4f\n" * nv % tuple(v.ravel())
            + "vn %.5f %.5f %.5f\n" * nv % tuple(part.normals.astype(np.float64).ravel())
            + "f %d//%d %d//%d %d//%d\n" * nf % tuple(f.ravel()))


def _fmt(values) -> str:
    return ", ".join(f"{float(v):.9g}" for v in np.ravel(values))


@dataclasses.dataclass(frozen=True)
class FittedLight:
    """One fitted light of a stage-4 ``light.json``."""

    direction: np.ndarray  # [3] unit, toward the light (a lamp's: from the fit's centre)
    irradiance: np.ndarray  # [3] RGB (a lamp's: at the fit's centre)
    position: np.ndarray | None = None  # [3] a lamp's, world; None: directional
    radius: float = 0.0  # a lamp's sphere radius (0: a point)
    intensity: np.ndarray | None = None  # [3] a lamp's radiant intensity, W/sr


def fitted_lights(light: dict) -> list[FittedLight]:
    """Each fitted light of a stage-4 ``light.json`` (those of zero irradiance left out);
    a lamp's intensity is its irradiance at the fit's ``center`` times the squared distance
    from there."""
    from mi_shadowgs.core.directions import light_grid, solid_angle
    from mi_shadowgs.stages.material.outputs import local_lights_from_json

    dirs = np.asarray(light.get("directions") or [], np.float64).reshape(-1, 3)
    irr = light.get("irradiance")
    if irr is None:  # radiance over the active grid cells times their solid angle
        rad = np.asarray(light["radiance"], np.float64)
        n = len(rad)
        active = np.asarray(light["active"], int)
        irr = rad[active] * solid_angle(n)
        if len(dirs) == 0:
            dirs = light_grid(n)[active]
    irr = np.asarray(irr, np.float64)
    irr = np.repeat(irr.reshape(-1, 1), 3, 1) if irr.ndim == 1 else irr.reshape(-1, 3)
    if len(irr) != len(dirs):
        raise ExportError(f"light.json: {len(dirs)} directions but {len(irr)} irradiances")
    try:
        pos, radii, center = local_lights_from_json(light, len(dirs))
    except (KeyError, TypeError, ValueError) as exc:
        raise ExportError(f"light.json: malformed local lights ({exc})") from None
    out = []
    for k, (d, e) in enumerate(zip(dirs, irr, strict=True)):
        if not np.any(e > 0):
            continue
        if pos is None or not np.all(np.isfinite(pos[k])):
            out.append(FittedLight(d / np.linalg.norm(d), e))
            continue
        r2 = float(np.sum((pos[k] - center) ** 2))
        out.append(FittedLight(d / np.linalg.norm(d), e, pos[k], float(radii[k]), e * r2))
    return out


def emitter_xml(root, k: int, lt: FittedLight) -> None:
    """A fitted light as Mitsuba XML under ``root``: a ``directional`` emitter, a lamp as a
    ``point`` emitter, or (radius > 0) a black ``sphere`` with an ``area`` emitter whose
    uniform radiance I / (pi R^2) has the lamp's intensity I toward every side. A plain
    (direction, irradiance) pair is a directional light."""
    import math
    import xml.etree.ElementTree as ET

    if not isinstance(lt, FittedLight):
        lt = FittedLight(np.asarray(lt[0], np.float64), np.asarray(lt[1], np.float64))
    if lt.position is None:
        em = ET.SubElement(root, "emitter", type="directional", id=f"light_{k}")
        ET.SubElement(em, "vector", name="direction", value=_fmt(-lt.direction))  # -l
        ET.SubElement(em, "rgb", name="irradiance", value=_fmt(lt.irradiance))
    elif lt.radius <= 0:
        em = ET.SubElement(root, "emitter", type="point", id=f"light_{k}")
        ET.SubElement(em, "point", name="position", value=_fmt(lt.position))
        ET.SubElement(em, "rgb", name="intensity", value=_fmt(lt.intensity))
    else:
        shape = ET.SubElement(root, "shape", type="sphere", id=f"light_{k}")
        ET.SubElement(shape, "point", name="center", value=_fmt(lt.position))
        ET.SubElement(shape, "float", name="radius", value=f"{lt.radius:.9g}")
        bsdf = ET.SubElement(shape, "bsdf", type="diffuse")
        ET.SubElement(bsdf, "rgb", name="reflectance", value="0")
        em = ET.SubElement(shape, "emitter", type="area")
        ET.SubElement(em, "rgb", name="radiance",
                      value=_fmt(lt.intensity / (math.pi * lt.radius**2)))


def scene_xml(parts: dict[str, str], lights, cameras, config: ExportConfig,
              source: str) -> str:
    """Mitsuba 3 scene text: ``parts`` maps shape id -> PLY file name (beside the XML)."""
    import xml.etree.ElementTree as ET

    cam0 = cameras[0][1] if cameras else None
    root = ET.Element("scene", version="3.0.0")
    root.append(ET.Comment(f" written by mi-shadowgs export from {source}; linear RGB, "
                           "Y-up, fitted lights (irradiance on the albedo's scale) "))
    for name, value in (("spp", config.spp), ("max_depth", config.max_depth),
                        ("resx", cam0.width if cam0 else 128),
                        ("resy", cam0.height if cam0 else 128)):
        ET.SubElement(root, "default", name=name, value=str(value))
    integ = ET.SubElement(root, "integrator", type="path")
    ET.SubElement(integ, "integer", name="max_depth", value="$max_depth")
    for shape_id, filename in parts.items():
        shape = ET.SubElement(root, "shape", type="ply", id=shape_id)
        ET.SubElement(shape, "string", name="filename", value=filename)
        bsdf_xml(shape, config.bsdf)
    for k, lt in enumerate(lights):
        emitter_xml(root, k, lt)
    for name, cam in cameras:
        if cam.is_ortho:
            raise ExportError(f"camera {name!r} is orthographic; scene.xml takes perspective "
                              "test cameras")
        sensor = ET.SubElement(root, "sensor", type="perspective", id=name)
        ET.SubElement(sensor, "float", name="fov", value=f"{np.degrees(cam.fov_x):.9g}")
        ET.SubElement(sensor, "string", name="fov_axis", value="x")
        ET.SubElement(sensor, "float", name="near_clip", value=f"{cam.near:.9g}")
        ET.SubElement(sensor, "float", name="far_clip", value=f"{cam.far:.9g}")
        tr = ET.SubElement(sensor, "transform", name="to_world")
        ET.SubElement(tr, "matrix", value=" ".join(f"{v:.9g}" for v in
                                                   cam.mitsuba_to_world().ravel()))
        samp = ET.SubElement(sensor, "sampler", type="independent")
        ET.SubElement(samp, "integer", name="sample_count", value="$spp")
        film = ET.SubElement(sensor, "film", type="hdrfilm")
        ET.SubElement(film, "integer", name="width", value="$resx")
        ET.SubElement(film, "integer", name="height", value="$resy")
        ET.SubElement(film, "string", name="pixel_format", value="rgba")
        ET.SubElement(film, "rfilter", type="box")
    ET.indent(root)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, "unicode") + "\n"


# -- the runner -----------------------------------------------------------------------------
def stage4_inputs(run: Path) -> tuple[Path, Path]:
    """(model.ply, light.json) of the run's finished stage 4, or ExportError naming what is
    missing."""
    from mi_shadowgs.io.provenance import MANIFEST_NAME, read_manifest
    from mi_shadowgs.stages.common import check_run_stages

    if not run.is_dir():
        raise FileNotFoundError(f"run folder not found: {run}")
    top = read_manifest(run)
    if top is None or top.get("command") != "run":
        raise ExportError(f"{run}: not a run folder of `mi-shadowgs run` (no {MANIFEST_NAME} "
                          "of a run)")
    folder = run / MATERIAL_FOLDER
    model, light = folder / "model.ply", folder / "light.json"
    for path in (model, light):
        if not path.is_file():
            raise ExportError(f"{run}: has no stage 4 ({path.relative_to(run)} is missing): "
                              "finish the run (`mi-shadowgs run`) first")
    stage = read_manifest(folder)
    if stage is None or not stage.get("complete"):
        raise ExportError(f"{run}: stage 4 ({MATERIAL_FOLDER}) is unfinished (its manifest "
                          "is not complete): finish the run (`mi-shadowgs run`) first")
    check_run_stages(run)
    return model, light


def _check_out(out: Path, run: Path) -> None:
    """``out`` may be a new folder inside the run, never the run itself (one inside the
    run's own files or parts is refused by ``Output.open``, as for every command)."""
    out, run = out.resolve(), run.resolve()
    if out == run:
        raise ExportError(f"{out}: is the run folder; export writes into a folder of its own")
    if out.suffix.lower() in (".ply", ".obj", ".xml"):
        raise ExportError(f"--out {out}: names a {out.suffix} file, but --out is a folder (the "
                          "files get standard names inside): give a folder name")


def _dataset_of(run: Path, data: str | Path | None) -> Path:
    """The run's dataset (``data`` or the manifest's), checked against its fingerprint."""
    from mi_shadowgs.dataset.fingerprint import dataset_fingerprint
    from mi_shadowgs.io.provenance import ProvenanceError, read_manifest

    ref = (read_manifest(run) or {}).get("dataset") or {}
    path = Path(data) if data is not None else Path(ref.get("path") or "")
    if data is None and not ref.get("path"):
        raise ExportError(f"{run}: its manifest names no dataset; pass --data")
    if not (path / "transforms_train.json").is_file():
        raise FileNotFoundError(f"dataset of {run} not found: {path / 'transforms_train.json'}"
                                " is missing (pass --data)")
    if ref.get("fingerprint") and dataset_fingerprint(path) != ref["fingerprint"]:
        raise ProvenanceError(f"{path}: is not the dataset {run} was made from (fingerprint "
                              f"{dataset_fingerprint(path)[:12]}, the run's "
                              f"{str(ref['fingerprint'])[:12]})")
    return path


def base_known(data: Path) -> bool:
    """Whether the dataset's scene has our base (the plane y = 0): its ``dataset.json``
    names a material "base"."""
    info = data / "dataset.json"
    if not info.is_file():
        return False
    try:
        mats = json.loads(info.read_text()).get("materials") or []
    except json.JSONDecodeError:
        return False
    return any(isinstance(m, dict) and m.get("name") == "base" for m in mats)


def export_run(run: str | Path, out: str | Path, fmt: str, color: str = "sh",
               data: str | Path | None = None, config: ExportConfig | None = None,
               overwrite: bool = False, progress: bool = False, frame: str | None = None):
    """Export the run's stage-4 model as ``fmt`` into the folder ``out``; returns a
    ``StageRun`` (``ran`` False when ``out`` already holds this export of these inputs).
    ``config``: the export's settings (the mesh's grid), the run's own by default
    (``mi_shadowgs.presets.recorded(run).export``). ``data`` (the run's dataset, when it
    moved) only for a mesh. ``frame``: the world frame of the splat PLYs (``FRAMES``;
    default ``DEFAULT_FRAME``; module docstring)."""
    from mi_shadowgs.dataset.fingerprint import dataset_ref
    from mi_shadowgs.io.atomic import atomic_path, write_json, write_text
    from mi_shadowgs.io.ply import (
        read_ply_metadata,
        read_ply_model,
        write_ply_model,
        write_ply_vertices,
    )
    from mi_shadowgs.io.provenance import Output, Provenance, input_ref
    from mi_shadowgs.stages.common import StageRun, settings_dict

    t0 = time.perf_counter()
    cpu0 = time.process_time()  # all threads: the load-independent cost on a busy machine
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}: choose from {', '.join(FORMATS)}")
    if color not in COLORS:
        raise ExportError(f"unknown --color {color!r}: choose from {', '.join(COLORS)}")
    if fmt == "mesh" and color != "sh":
        raise ExportError("--color applies to the splat PLYs; a mesh always carries the "
                          "albedo, roughness and metallic")
    if fmt == "mesh" and frame not in (None, "y-up"):
        raise ExportError("--frame applies to the splat PLYs; a mesh (and scene.xml, "
                          "glTF) is in our Y-up world, as Mitsuba and glTF take it")
    frame = DEFAULT_FRAME if frame is None else frame
    if frame not in FRAMES:
        raise ExportError(f"unknown --frame {frame!r}: choose from {', '.join(FRAMES)}")
    if data is not None and fmt != "mesh":
        raise ExportError(f"--data is read by --format mesh only (its training cameras); "
                          f"--format {fmt} takes the model alone")
    config = ExportConfig() if config is None else config
    run, out = Path(run), Path(out)
    model_path, light_path = stage4_inputs(run)
    _check_out(out, run)
    data_path = _dataset_of(run, data) if fmt == "mesh" else None
    inputs = {"model": input_ref(model_path)}
    if fmt == "mesh":
        inputs["light"] = input_ref(light_path)
    settings = {"format": fmt, "color": color, **settings_dict(config)}
    if fmt != "mesh":
        settings["layout"] = SPLAT_LAYOUT
        settings["frame"] = frame
    provenance = Provenance(dataset=dataset_ref(data_path) if data_path else None,
                            inputs=inputs, settings=settings)
    guard = [model_path, light_path] + ([data_path] if data_path else [])
    with Output.open(out, "export", provenance, overwrite=overwrite, reuse=True,
                     inputs=guard) as output:
        if output.complete:
            return StageRun(out, False, 0.0, f"{out}: already holds this export (reused)")
        model = read_ply_model(model_path)
        clipped = clip_record(model, color, fmt, out)
        records = {SH_SPACE_KEY: "srgb", FRAME_KEY: frame, **clipped}
        if fmt == "3dgs-ply":
            write_ply_vertices(output.path("point_cloud.ply"),
                               gs3d_columns(to_frame(model, frame), color, config), records)
            summary = f"wrote {out / 'point_cloud.ply'} (3DGS layout, {model.count} splats)"
        elif fmt == "2dgs-ply":
            # The header's settings of the fit (receiver band, shadow maps, whether the GGX
            # lobe was fitted) travel too: without them a relight of this PLY (api.relight,
            # the surfel_relight plugin) takes another tool's defaults and adds highlights
            # and shadows the fit never had.
            write_ply_model(output.path("point_cloud.ply"),
                            gs2d_model(to_frame(model, frame), color),
                            {**read_ply_metadata(model_path), **records})
            summary = f"wrote {out / 'point_cloud.ply'} (2DGS layout, {model.count} surfels)"
        else:
            summary = _export_mesh(output, model, light_path, data_path, config, progress,
                                   atomic_path, write_text, write_json, t0, cpu0)
        output.finish()
    return StageRun(out, True, time.perf_counter() - t0, summary)


def _export_mesh(output, model, light_path: Path, data: Path, config: ExportConfig,
                 progress: bool, atomic_path, write_text, write_json, t0: float,
                 cpu0: float) -> str:
    from mi_shadowgs.dataset.loader import DatasetError, load_cameras, load_dataset

    missing = [c for c in ("albedo", "roughness", "metallic") if c not in model.channels]
    if missing:
        raise ExportError(f"{output.folder}: the model lacks channel(s) {missing} (run stage 4)")
    train = [cam for _, cam in load_cameras(data / "transforms_train.json")]
    with_base = base_known(data)
    masks, outline = None, "off"
    if with_base and config.mesh.outline:  # the base's outline from the training masks
        try:
            views = load_dataset(data, "train")
        except DatasetError as e:  # cameras without their images: the fused outline stays
            outline = f"skipped: {e}"
        else:
            if views.has_masks:
                train = views.cameras
                masks = [v.mask for v in views.views]
                outline = "training masks"
            else:
                outline = "skipped: the training views have no masks"
    test = []
    if (data / "transforms_test.json").is_file():
        test = [(f"test_{i:03d}", cam) for i, (_, cam) in
                enumerate(load_cameras(data / "transforms_test.json"))]
    obj, base, info = mesh_mod.extract_mesh(model.to_surfels(), train, config.mesh, with_base,
                                            progress, masks)
    parts = {"object": obj} if base is None else {"object": obj, "base": base}
    for name, part in parts.items():
        with atomic_path(output.path(f"{name}.ply")) as tmp:
            tmp.write_bytes(_mesh_ply_bytes(part))
        write_text(output.path(f"{name}.obj"), _mesh_obj_text(part))
    with atomic_path(output.path("asset.glb")) as tmp:
        tmp.write_bytes(_glb_bytes(parts))
    lights = fitted_lights(json.loads(light_path.read_text()))
    write_text(output.path("scene.xml"), scene_xml(
        {name: f"{name}.ply" for name in parts}, lights, test, config,
        str(light_path.parent)))
    info.update({"base_known": with_base, "base_outline": outline, "lights": len(lights),
                 "sensors": len(test),
                 "seconds_total": time.perf_counter() - t0,
                 "cpu_seconds_total": time.process_time() - cpu0,
                 "object_area": obj.area})
    write_json(output.path("export.json"), info)
    return (f"wrote {output.folder / 'scene.xml'}: object {len(obj.faces)} triangles"
            + (f", base {len(base.faces)}" if base is not None else "")
            + f", {len(lights)} light(s), {len(test)} camera(s), "
              f"{time.perf_counter() - t0:.1f} s")
