"""Surfel models as PLY files, in the layout of the public 2DGS code.

Vertex properties, in this order, all float32 (binary little-endian):
``x, y, z, nx, ny, nz, f_dc_0..2, f_rest_0..(3*(K-1)-1), opacity, scale_0, scale_1,
rot_0..3``, then one property per extra channel column. Values are stored *raw*, as 2DGS
stores them: ``scale_*`` hold log standard deviations, ``opacity`` the logit, ``rot_*`` the
unnormalised quaternion (w, x, y, z). ``f_dc``/``f_rest`` hold the "sh" channel; 3DGS and
2DGS write ``f_rest`` channel-major (``f_rest[c*(K-1) + k-1]``), while our "sh" channel is
coefficient-major (``sh[k*3 + c]``). ``nx, ny, nz`` are written as the surfel normals
(2DGS writes zeros; no reader uses them) and ignored on reading.

Extra channels: a channel ``name`` with C columns becomes properties ``name_0..name_{C-1}``,
or the bare ``name`` when C == 1 (e.g. ``albedo_0..2``, ``roughness``, ``feature_0..15``,
``segment``). Models without an "sh" channel are written without ``f_dc``/``f_rest``.
Channel names must survive that mapping and the 2DGS loader (which gathers properties by
prefix): letters, digits and ``_``, not ending in ``_<digits>``, not starting with ``rot``,
``scale_``, ``f_dc_`` or ``f_rest_``.

Metadata: settings a reader of the model needs (stage 4's ``receiver_band``) are header
comments, ``comment mi_shadowgs KEY VALUE``; other PLY readers skip them
(``read_ply_metadata``).

SH colour space (record ``sh_space``): our models' SH give linear RGB, as our renders are
linear. Splat viewers and 3DGS/2DGS, which train on sRGB photos, take them as sRGB display
values, so ``mi-shadowgs export`` writes display SH and records ``sh_space srgb``.
``read_ply_model`` turns such SH back into linear ones (``sh_from_srgb``): the DC term
exactly, the higher bands to first order. A PLY without the record is read as linear (our
own models); for another tool's PLY, which holds display values, pass ``sh_space="srgb"``.

World frame (record ``world_frame``): "y-up" is our world (docs/conventions.md); "opencv"
is the frame 3DGS, COLMAP, SuperSplat and PlayCanvas take a splat PLY's world to be in (Y
down, Z forward), ours turned 180 degrees about X: ``x, y, z = x, -y, -z``, with the
quaternions, ``shading_normal`` and the SH turned with it (exact: each SH coefficient only
changes sign). ``save_ply`` records "y-up"; ``mi-shadowgs export``'s splat PLYs record the
frame they are written in. ``read_ply_model`` turns an "opencv" PLY back into ours; a PLY
without the record is returned as stored (its frame unknown: ``frame_of``). A PLY that lost
its records (splat-transform drops comments) reads right with ``**SPLAT_TOOLS``.

The reader handles ascii and binary (either byte order) PLY files with scalar vertex
properties of any PLY type; the writer is atomic (``mi_shadowgs.io.atomic``).
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import numpy as np

from mi_shadowgs.core.surfel_checks import (
    check_finite,
    check_log_scale,
    check_nonempty,
    check_quaternion,
)
from mi_shadowgs.io.atomic import atomic_path

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}

# Properties that belong to the 2DGS layout (everything else is an extra channel).
_GEOMETRY = ("x", "y", "z", "nx", "ny", "nz", "opacity", "scale_0", "scale_1",
             "rot_0", "rot_1", "rot_2", "rot_3")
REQUIRED = ("x", "y", "z", "opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3")
# Channel names that clash with 2DGS properties, or with the prefixes its loader collects
# (every property starting with "rot", "scale_" or "f_rest_" is read as part of that group).
_RESERVED = re.compile(r"^(x|y|z|nx|ny|nz|opacity)$|^(rot|scale_|f_dc_|f_rest_)")
_SUFFIX = re.compile(r"^(.+)_(\d+)$")
_CHANNEL_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
MAX_SH_DEGREE = 3
SH_C0 = 0.28209479177387814  # Y_0^0: 3DGS's colour = C0 f_dc + 0.5 for the DC band
SH_SPACE_KEY = "sh_space"  # header record: the colour space of f_dc/f_rest (docstring)
SH_SPACES = ("linear", "srgb")
FRAME_KEY = "world_frame"  # header record: the world frame of the model (docstring)
FRAMES = ("y-up", "opencv")
# What the splat tools assume of a PLY (3DGS, SuperSplat, PlayCanvas): sRGB SH, OpenCV frame.
# read_ply_model(path, **SPLAT_TOOLS) reads one of our exports that lost its header records.
SPLAT_TOOLS = {"sh_space": "srgb", "frame": "opencv"}
# Sign of each SH basis function (3DGS order, degree <= 3) under x, y, z -> x, -y, -z.
_SH_FLIP = np.array([1, -1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float32)
VECTOR_CHANNELS = ("shading_normal",)  # world-frame directions among the channels
METADATA_PREFIX = "mi_shadowgs"  # comment lines of the header that hold metadata
_METADATA_KEY = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


class PlyError(ValueError):
    """A PLY file is malformed or lacks what a surfel model needs; the message names it."""


@dataclasses.dataclass
class PlyModel:
    """Raw (not activated) surfel parameters as float32 numpy arrays, as a PLY stores them."""

    position: np.ndarray  # [N, 3]
    log_scale: np.ndarray  # [N, 2]
    rotation: np.ndarray  # [N, 4] quaternion (w, x, y, z), unnormalised
    opacity_logit: np.ndarray  # [N]
    channels: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # name -> [N, C]

    @property
    def count(self) -> int:
        return int(self.position.shape[0])

    def normals(self) -> np.ndarray:
        """[N, 3] unit normals (third column of the rotation); +Z for a zero quaternion."""
        q = self.rotation.astype(np.float64)
        n = np.linalg.norm(q, axis=1, keepdims=True)
        q = np.where(n > 0, q / np.where(n > 0, n, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
        w, x, y, z = q.T
        return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)

    # -- conversion to and from the Dr.Jit model ----------------------------------------
    @staticmethod
    def from_surfels(surfels) -> PlyModel:
        def arr(v, cols):
            a = np.asarray(v, dtype=np.float32)
            return a.reshape(cols, surfels.count).T if cols > 1 else a.reshape(surfels.count)

        channels = {}
        for name, t in surfels.channels.items():
            c = np.asarray(t.numpy(), dtype=np.float32)
            channels[name] = c[:, None] if c.ndim == 1 else c
        return PlyModel(position=arr(surfels.position, 3), log_scale=arr(surfels.log_scale, 2),
                        rotation=arr(surfels.rotation, 4),
                        opacity_logit=arr(surfels.opacity_logit, 1), channels=channels)

    def to_surfels(self):
        """The ``Surfels`` of these raw parameters (no activation round trip)."""
        import mitsuba as mi

        from mi_shadowgs.core import jit
        from mi_shadowgs.core.surfels import Surfels

        def vec(cls, a):
            a = np.asarray(a, dtype=np.float32)
            return cls(*(jit.host(a[:, i]) for i in range(a.shape[1])))

        channels = {name: jit.tensor(c) for name, c in self.channels.items()}
        return Surfels(position=vec(mi.Point3f, self.position),
                       log_scale=vec(mi.Point2f, self.log_scale),
                       rotation=vec(mi.Vector4f, self.rotation),
                       opacity_logit=jit.host(np.asarray(self.opacity_logit, np.float32)),
                       channels=channels)


# -- world frames --------------------------------------------------------------------------
def _turned(model: PlyModel, sign: float) -> PlyModel:
    """``model`` turned a half turn about X (``x, y, z = x, -y, -z``); ``sign`` picks +180
    or -180 degrees for the quaternions, so that one way then the other gives back the same
    bits. Exact in float32."""
    flip = np.array([1.0, -1.0, -1.0], np.float32)
    w, x, y, z = (model.rotation[:, i] for i in range(4))
    # q' = r q with r = (0, sign, 0, 0): a half turn about X
    rot = np.stack([-sign * x, sign * w, -sign * z, sign * y], axis=-1).astype(np.float32)
    channels = {}
    for name, c in model.channels.items():
        if name == "sh":
            k = c.shape[1] // 3
            c = (c.reshape(len(c), k, 3) * _SH_FLIP[:k, None]).reshape(c.shape)
        elif name in VECTOR_CHANNELS and c.shape[1] == 3:
            c = c * flip
        channels[name] = np.asarray(c, np.float32)
    return dataclasses.replace(model, position=(model.position * flip).astype(np.float32),
                               rotation=rot, channels=channels)


def to_frame(model: PlyModel, frame: str) -> PlyModel:
    """A model in our Y-up world written in ``frame`` (``FRAMES``)."""
    _check_frame(frame, "frame")
    return model if frame == "y-up" else _turned(model, 1.0)


def from_frame(model: PlyModel, frame: str) -> PlyModel:
    """Inverse of ``to_frame``: a model stored in ``frame`` in our Y-up world (bit-exact)."""
    _check_frame(frame, "frame")
    return model if frame == "y-up" else _turned(model, -1.0)


def _check_frame(frame, where) -> None:
    if frame not in FRAMES:
        raise PlyError(f"{where} must be one of {', '.join(FRAMES)}, got {frame!r}")


def frame_of(path: str | os.PathLike, frame: str | None = None) -> str | None:
    """The world frame the PLY at ``path`` is stored in: ``frame`` when given, else its
    ``world_frame`` record, else None (unknown: another tool's, or saved before the record)."""
    if frame is not None:
        _check_frame(frame, f"{path}: frame")
        return frame
    recorded = read_ply_metadata(path).get(FRAME_KEY)
    if recorded is not None:
        _check_frame(recorded, f"{path}: the header record '{FRAME_KEY}'")
    return recorded


# -- SH layout ----------------------------------------------------------------------------
def sh_to_dc_rest(sh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our "sh" channel [N, K*3] (k*3 + c) -> (f_dc [N, 3], f_rest [N, 3*(K-1)] channel-major)."""
    sh = np.asarray(sh)
    n, kc = sh.shape
    k = kc // 3
    coeffs = sh.reshape(n, k, 3)  # [N, K, 3]
    return coeffs[:, 0, :], coeffs[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1))


def dc_rest_to_sh(f_dc: np.ndarray, f_rest: np.ndarray) -> np.ndarray:
    """Inverse of ``sh_to_dc_rest``: f_dc [N, 3], f_rest [N, 3*(K-1)] -> sh [N, K*3]."""
    n = f_dc.shape[0]
    rest = f_rest.reshape(n, 3, f_rest.shape[1] // 3).transpose(0, 2, 1)  # [N, K-1, 3]
    return np.concatenate([f_dc[:, None, :], rest], axis=1).reshape(n, 3 + f_rest.shape[1])


def _srgb_slope(linear: np.ndarray) -> np.ndarray:
    """d sRGB / d linear at ``linear`` (finite at 0: the curve's linear segment, 12.92)."""
    return np.where(linear <= 0.0031308, 12.92,
                    1.055 / 2.4 * np.power(np.maximum(linear, 0.0031308), 1.0 / 2.4 - 1.0))


def sh_to_srgb(sh: np.ndarray) -> np.ndarray:
    """Linear SH [N, K*3] (coefficient-major, colour = SH + 0.5) -> display SH whose colour
    is sRGB: the DC term's view-mean colour through the sRGB curve exactly, the higher bands
    scaled by the curve's slope there (first order)."""
    from mi_shadowgs.io.images import linear_to_srgb

    n, kc = sh.shape
    c = sh.reshape(n, kc // 3, 3).astype(np.float64)  # [N, K, 3]
    linear = np.clip(SH_C0 * c[:, 0] + 0.5, 0.0, 1.0)  # [N, 3] view-mean colour
    out = c * _srgb_slope(linear)[:, None, :]
    out[:, 0] = (linear_to_srgb(linear) - 0.5) / SH_C0
    return out.reshape(n, kc).astype(np.float32)


# The header record of a display-SH PLY whose view-mean colours were clipped into [0, 1]:
# the number of such splats. Display SH hold sRGB values, which end at white; a linear
# colour above 1 (a highlight, a bright albedo under a strong light) comes back as 1, so
# those splats render darker than the run's model (by up to 0.88 on a 64^2 view), and one
# below 0 comes back as 0.
CLIPPED_KEY = "display_clipped_splats"


def display_clipped(sh: np.ndarray) -> int:
    """How many splats of linear SH [N, K*3] ``sh_to_srgb`` clips: view-mean colour outside
    [0, 1] in some channel."""
    linear = SH_C0 * np.asarray(sh, np.float64)[:, :3] + 0.5
    return int(np.count_nonzero(np.any((linear < 0.0) | (linear > 1.0), axis=1)))


def sh_from_srgb(sh: np.ndarray) -> np.ndarray:
    """Inverse of ``sh_to_srgb``: display SH [N, K*3] -> linear SH. Exact on what
    ``sh_to_srgb`` wrote wherever the view-mean colour lies inside [0, 1]."""
    from mi_shadowgs.io.images import srgb_to_linear

    n, kc = sh.shape
    c = sh.reshape(n, kc // 3, 3).astype(np.float64)  # [N, K, 3]
    linear = srgb_to_linear(np.clip(SH_C0 * c[:, 0] + 0.5, 0.0, 1.0))  # [N, 3]
    out = c / _srgb_slope(linear)[:, None, :]
    out[:, 0] = (linear - 0.5) / SH_C0
    return out.reshape(n, kc).astype(np.float32)


def _check_sh_width(kc: int, where: str) -> None:
    k = kc // 3
    deg = round(np.sqrt(k)) - 1
    if kc % 3 or (deg + 1) ** 2 != k or deg > MAX_SH_DEGREE:
        raise PlyError(f"{where}: {kc} SH values are not 3*(degree+1)^2 with degree <= "
                       f"{MAX_SH_DEGREE}")


# -- low-level PLY ------------------------------------------------------------------------
def read_ply_vertices(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The vertex properties of a PLY file: name -> [N] array, in file order."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise PlyError(f"{path}: not a PLY file (no 'ply' magic line)")
        fmt = None
        elements: list[tuple[str, int, list[tuple[str, str]]]] = []
        while True:
            raw = f.readline()
            if not raw:
                raise PlyError(f"{path}: PLY header has no 'end_header'")
            words = raw.decode("ascii", errors="replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                if len(words) < 2 or words[1] not in _FORMATS:
                    raise PlyError(f"{path}: unsupported PLY format line {raw!r}")
                fmt = words[1]
            elif words[0] == "element":
                if len(words) != 3 or not words[2].isdigit():
                    raise PlyError(f"{path}: malformed element line {raw!r}")
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property":
                if not elements:
                    raise PlyError(f"{path}: property before any element")
                if words[1] == "list":
                    if elements[-1][0] == "vertex":
                        raise PlyError(f"{path}: list property {words[-1]!r} in element "
                                       f"{elements[-1][0]!r} is not supported")
                    continue  # only elements after 'vertex' may have lists; never read
                if len(words) != 3 or words[1] not in _PLY_TYPES:
                    raise PlyError(f"{path}: malformed property line {raw!r}")
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise PlyError(f"{path}: unexpected PLY header line {raw!r}")
        if fmt is None:
            raise PlyError(f"{path}: PLY header has no 'format' line")
        if not elements or elements[0][0] != "vertex":
            raise PlyError(f"{path}: the first PLY element must be 'vertex'")
        _, count, props = elements[0]
        names = [p[0] for p in props]
        if len(set(names)) != len(names):
            raise PlyError(f"{path}: duplicate vertex property names")
        order = _FORMATS[fmt]
        if order is None:
            data = _read_ascii(f, path, count, props)
        else:
            dtype = np.dtype([(n, order + t) for n, t in props])
            buf = f.read(dtype.itemsize * count)
            if len(buf) != dtype.itemsize * count:
                raise PlyError(f"{path}: truncated: {count} vertices need "
                               f"{dtype.itemsize * count} bytes, found {len(buf)}")
            rec = np.frombuffer(buf, dtype=dtype, count=count)
            data = {n: rec[n].astype(rec[n].dtype.newbyteorder("=")) for n in names}
    return data


def _read_ascii(f, path: Path, count: int, props) -> dict[str, np.ndarray]:
    rows = []
    for i in range(count):
        line = f.readline()
        if not line:
            raise PlyError(f"{path}: truncated: {count} vertices declared, {i} found")
        vals = line.split()
        if len(vals) != len(props):
            raise PlyError(f"{path}: vertex {i} has {len(vals)} values, expected {len(props)}")
        rows.append(vals)
    table = np.array(rows, dtype=np.float64).reshape(count, len(props))
    return {n: table[:, j].astype(t) for j, (n, t) in enumerate(props)}


def _metadata_lines(path, metadata: dict | None) -> list[str]:
    lines = []
    for key, value in (metadata or {}).items():
        key, value = str(key), str(value)
        if (not _METADATA_KEY.fullmatch(key) or not value
                or any(c.isspace() for c in value) or not value.isascii()):
            raise PlyError(f"{path}: metadata {key!r}: {value!r} cannot be a PLY comment (a "
                           "key of letters, digits and '_', one word of ASCII as its value)")
        lines.append(f"comment {METADATA_PREFIX} {key} {value}")
    return lines


def read_ply_metadata(path: str | os.PathLike) -> dict[str, str]:
    """The ``metadata`` a model was saved with (``comment mi_shadowgs KEY VALUE`` header
    lines): key -> value as text. Empty for a PLY written elsewhere or before it existed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    out = {}
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise PlyError(f"{path}: not a PLY file (no 'ply' magic line)")
        for raw in f:
            words = raw.decode("ascii", errors="replace").split()
            if words[:1] == ["end_header"]:
                return out
            if len(words) == 4 and words[:2] == ["comment", METADATA_PREFIX]:
                out[words[2]] = words[3]
    raise PlyError(f"{path}: PLY header has no 'end_header'")


def write_ply_vertices(path: str | os.PathLike, columns: dict[str, np.ndarray],
                       metadata: dict | None = None) -> None:
    """Write float32 vertex properties (name -> [N], in order) as binary little-endian PLY;
    ``metadata`` (key -> one word) goes into the header as comments other readers skip."""
    names = list(columns)
    n = len(next(iter(columns.values()))) if columns else 0
    dtype = np.dtype([(name, "<f4") for name in names])
    rec = np.empty(n, dtype=dtype)
    for name in names:
        col = np.asarray(columns[name]).reshape(-1)
        if col.shape[0] != n:
            raise PlyError(f"{path}: property {name!r} has {col.shape[0]} values, expected {n}")
        rec[name] = col
    header = ["ply", "format binary_little_endian 1.0", *_metadata_lines(path, metadata),
              f"element vertex {n}"]
    header += [f"property float {name}" for name in names]
    header.append("end_header")
    data = ("\n".join(header) + "\n").encode("ascii") + rec.tobytes()
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


# -- surfel models ------------------------------------------------------------------------
def read_ply_model(path: str | os.PathLike, sh_space: str | None = None,
                   frame: str | None = None) -> PlyModel:
    """Read a 2DGS-layout PLY as raw float32 parameters (PlyError names file and property).

    Refuses (``mi_shadowgs.core.surfel_checks``) an empty model, non-finite values in any
    property, log-scales whose exp is zero in float32 or above 1e12, and zero quaternions,
    naming the property, the first bad vertex and the number of bad vertices.

    The "sh" channel is returned linear: ``sh_space`` ("linear" or "srgb") says what the
    file's SH hold; by default its ``sh_space`` record, else linear (module docstring).
    A model stored in the "opencv" frame (``frame``, else its ``world_frame`` record) is
    returned in our Y-up world; one of unknown frame as stored.
    """
    space = sh_space_of(path, sh_space)
    stored_in = frame_of(path, frame)
    props = read_ply_vertices(path)
    missing = [name for name in REQUIRED if name not in props]
    if missing:
        raise PlyError(f"{path}: missing required vertex propert"
                       f"{'y' if len(missing) == 1 else 'ies'} {', '.join(missing)}")
    check_nonempty(str(path), len(props["x"]), PlyError)
    for name, col in props.items():
        check_finite(str(path), name, col, PlyError)
    for name in ("scale_0", "scale_1"):
        check_log_scale(str(path), name, props[name], PlyError)
    check_quaternion(str(path), "rot_0..rot_3",
                     np.stack([props[f"rot_{i}"] for i in range(4)], axis=-1), PlyError)

    def stack(names):
        return np.stack([props[n].astype(np.float32) for n in names], axis=-1)

    channels: dict[str, np.ndarray] = {}
    dc = [f"f_dc_{i}" for i in range(3)]
    rest = _numbered(props, "f_rest")
    if any(n in props for n in dc):
        if not all(n in props for n in dc):
            raise PlyError(f"{path}: needs all of f_dc_0, f_dc_1, f_dc_2")
        _check_sh_width(3 + len(rest), f"{path}: f_dc/f_rest")
        channels["sh"] = dc_rest_to_sh(stack(dc), stack(rest) if rest else
                                       np.zeros((len(props["x"]), 0), np.float32))
        if space == "srgb":
            channels["sh"] = sh_from_srgb(channels["sh"])
    elif rest:
        raise PlyError(f"{path}: f_rest_* without f_dc_0..2")
    taken = set(_GEOMETRY) | set(dc) | set(rest)
    groups: dict[str, list[str]] = {}
    for name in props:
        if name in taken:
            continue
        m = _SUFFIX.match(name)
        base = m.group(1) if m else name
        groups.setdefault(base, []).append(name)
    for base, names in groups.items():
        numbered = _numbered(props, base)
        if numbered and sorted(numbered) == sorted(names):
            channels[base] = stack(numbered)
        else:  # not a clean base_0..base_{C-1} run: each property is its own channel
            for name in names:
                channels[name] = props[name].astype(np.float32)[:, None]
    model = PlyModel(position=stack(["x", "y", "z"]),
                     log_scale=stack(["scale_0", "scale_1"]),
                     rotation=stack([f"rot_{i}" for i in range(4)]),
                     opacity_logit=props["opacity"].astype(np.float32), channels=channels)
    return model if stored_in is None else from_frame(model, stored_in)


def sh_space_of(path: str | os.PathLike, sh_space: str | None = None) -> str:
    """The colour space of the SH in the PLY at ``path``: ``sh_space`` when given, else the
    file's ``sh_space`` record, else "linear". PlyError names a value that is neither."""
    if sh_space is not None:
        if sh_space not in SH_SPACES:
            raise PlyError(f"{path}: sh_space must be one of {', '.join(SH_SPACES)}, got "
                           f"{sh_space!r}")
        return sh_space
    recorded = read_ply_metadata(path).get(SH_SPACE_KEY, "linear")
    if recorded not in SH_SPACES:
        raise PlyError(f"{path}: the header record '{SH_SPACE_KEY}' is {recorded!r}; expected "
                       f"one of {', '.join(SH_SPACES)}")
    return recorded


def _numbered(props: dict, base: str) -> list[str]:
    """``base_0, base_1, ...`` as long as the run is unbroken."""
    names = []
    while f"{base}_{len(names)}" in props:
        names.append(f"{base}_{len(names)}")
    return names


def write_ply_model(path: str | os.PathLike, model: PlyModel,
                    metadata: dict | None = None) -> None:
    """Write raw parameters in the 2DGS layout (atomic); extra channels follow ``rot_3``;
    ``metadata`` as ``write_ply_vertices``."""
    n = model.count
    cols: dict[str, np.ndarray] = {}
    shapes = {"position": (model.position, 3), "log_scale": (model.log_scale, 2),
              "rotation": (model.rotation, 4)}
    for field, (arr, c) in shapes.items():
        if np.shape(arr) != (n, c):
            raise PlyError(f"{path}: {field} must be [{n}, {c}], got {np.shape(arr)}")
    if np.shape(model.opacity_logit) != (n,):
        raise PlyError(f"{path}: opacity_logit must be [{n}], got {np.shape(model.opacity_logit)}")
    for axis, name in enumerate("xyz"):
        cols[name] = model.position[:, axis]
    for axis, name in enumerate(("nx", "ny", "nz")):
        cols[name] = model.normals()[:, axis]
    channels = {}
    for name, c in model.channels.items():
        c = np.asarray(c)
        c = c[:, None] if c.ndim == 1 else c
        if c.ndim != 2 or c.shape[0] != n:
            raise PlyError(f"{path}: channel {name!r} must be [{n}, C], got {c.shape}")
        channels[name] = c
    if "sh" in channels:
        _check_sh_width(channels["sh"].shape[1], f"{path}: channel 'sh'")
        f_dc, f_rest = sh_to_dc_rest(channels["sh"])
        for i in range(3):
            cols[f"f_dc_{i}"] = f_dc[:, i]
        for i in range(f_rest.shape[1]):
            cols[f"f_rest_{i}"] = f_rest[:, i]
    cols["opacity"] = model.opacity_logit
    for i in range(2):
        cols[f"scale_{i}"] = model.log_scale[:, i]
    for i in range(4):
        cols[f"rot_{i}"] = model.rotation[:, i]
    for name, c in channels.items():
        if name == "sh":
            continue
        if not _CHANNEL_NAME.match(name) or _SUFFIX.match(name) or _RESERVED.match(name):
            raise PlyError(f"{path}: channel name {name!r} cannot round-trip through PLY "
                           "(use letters, digits and '_', not ending in _<digits>, not a 2DGS "
                           "property name, not starting with rot/scale_/f_dc_/f_rest_)")
        if c.shape[1] == 1:
            cols[name] = c[:, 0]
        else:
            for i in range(c.shape[1]):
                cols[f"{name}_{i}"] = c[:, i]
    write_ply_vertices(path, cols, metadata)


def load_ply(path: str | os.PathLike, sh_space: str | None = None,
             frame: str | None = None):
    """Load a PLY surfel model as ``mi_shadowgs.core.surfels.Surfels`` (``sh_space`` and
    ``frame`` as ``read_ply_model``: the SH come out linear, the world ours)."""
    return read_ply_model(path, sh_space, frame).to_surfels()


def save_ply(path: str | os.PathLike, surfels, metadata: dict | None = None) -> None:
    """Save ``Surfels`` (raw parameters, as 2DGS does; our Y-up world, recorded as
    ``world_frame y-up``) to a PLY file, atomically, with ``metadata``
    (``read_ply_metadata``) in its header."""
    write_ply_model(path, PlyModel.from_surfels(surfels), {FRAME_KEY: "y-up", **(metadata or {})})
