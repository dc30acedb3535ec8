"""Lamps (local lights) for relighting: given as ``--point`` text (``parse_point``), read
from Mitsuba's ``point``, ``spot`` and sphere ``area`` emitters (``mitsuba_lamp``) and from
``lights.json`` (``lamps_from_json``), checked against the scene (``check_lamps``) and made
into a ``shading.LightSet`` (``lamp_light_set``).

A lamp of radiant intensity I (W/sr, RGB) at p is the local light of weight E = I / |p - c|^2:
its irradiance at normal incidence at the reference point c (``shading.LightSet``). A sphere
lamp of radius R and uniform radiance L has I = L pi R^2 toward every side (its projected
area is pi R^2), which gives the irradiance of the whole sphere exactly wherever a receiver
sees all of it above its horizon; its shadows are those of its centre until the lamps'
shadow maps take the radius. A ``spot`` keeps Mitsuba's cone (``shading.spot_falloff``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit, shading
from mi_shadowgs.core.directions import parse_number_fields

POINT_USAGE = ("X,Y,Z,INTENSITY[,RADIUS] or X,Y,Z,R,G,B[,RADIUS] (world units; W/sr; "
               "RADIUS 0: a point)")
_POINT_FIELDS = {4: ("x", "y", "z", "intensity"), 5: ("x", "y", "z", "intensity", "radius"),
                 6: ("x", "y", "z", "intensity R", "intensity G", "intensity B"),
                 7: ("x", "y", "z", "intensity R", "intensity G", "intensity B", "radius")}


@dataclasses.dataclass(frozen=True)
class Lamp:
    """One lamp in the run's world frame."""

    position: tuple  # [3] world
    intensity: tuple  # [3] RGB radiant intensity, W/sr
    radius: float = 0.0  # world units (0: a point)
    # Mitsuba ``spot``: (axis x, y, z: the unit direction it shines along, cutoff and
    # full-beam half-angles in radians); None: it shines every way.
    cone: tuple | None = None
    source: str = "lamp"  # where it was given, for messages (an option, a file's emitter)


def parse_point(text: str, option: str = "--point") -> Lamp:
    """``X,Y,Z,I[,RADIUS]`` or ``X,Y,Z,R,G,B[,RADIUS]`` -> a Lamp (position, intensity in
    W/sr, radius in world units); ValueError naming the option and the field at fault."""
    values, names, shown = parse_number_fields(str(text), option, POINT_USAGE, _POINT_FIELDS)
    radius = values.pop() if names[-1] == "radius" else 0.0
    intensity = values[3:] * (3 if len(values) == 4 else 1)
    lamp = Lamp(tuple(values[:3]), tuple(intensity), radius, source=shown)
    check_lamp_values(lamp)
    return lamp


def check_lamp_values(lamp: Lamp) -> None:
    """A lamp's own numbers: a finite position, a finite radius >= 0, a finite intensity
    >= 0 in every channel and > 0 in one; ValueError naming the field."""
    pos = np.asarray(lamp.position, np.float64)
    inten = np.asarray(lamp.intensity, np.float64)
    if pos.shape != (3,) or not np.all(np.isfinite(pos)):
        raise ValueError(f"{lamp.source}: field position must be 3 finite numbers, got "
                         f"{lamp.position!r}")
    if not (math.isfinite(lamp.radius) and lamp.radius >= 0):
        raise ValueError(f"{lamp.source}: field radius must be finite and >= 0, got "
                         f"{lamp.radius:g}")
    if (inten.shape != (3,) or not np.all(np.isfinite(inten)) or inten.min() < 0
            or inten.max() <= 0):
        raise ValueError(f"{lamp.source}: field intensity must be finite, >= 0 and > 0 in "
                         f"some channel (W/sr), got {', '.join(f'{v:g}' for v in inten)}")


def check_lamps(lamps: Sequence[Lamp], bounds) -> None:
    """Each lamp where the model can be lit by it: wholly above the base plane y = 0 (the
    model holds no underside of its ground), outside the scene's bounds (the bounding sphere
    of the surfels, ``SceneBounds``: a lamp inside the object lights nothing a view saw and
    no shadow map can look at every occluder from there), and a spot's cone reaching them.
    ValueError naming the lamp and its field."""
    c = np.asarray(bounds.center, np.float64)
    r = float(bounds.radius)
    for lamp in lamps:
        check_lamp_values(lamp)
        p = np.asarray(lamp.position, np.float64)
        where = f"{lamp.source}: field position ({', '.join(f'{v:.4g}' for v in p)})"
        if p[1] - lamp.radius <= 0.0:
            raise ValueError(f"{where} puts the lamp at or below the base plane (y = 0): its "
                             f"lowest point is at y = {p[1] - lamp.radius:.4g}; a lamp must "
                             "be above the ground the model stands on")
        dist = float(np.linalg.norm(p - c))
        if dist - lamp.radius <= r:
            raise ValueError(
                f"{where} puts the lamp inside the scene: {dist:.4g} from the centre "
                f"({', '.join(f'{v:.4g}' for v in c)}) of the scene's bounding sphere of "
                f"radius {r:.4g} (lamp radius {lamp.radius:g}); place it outside that sphere")
        if lamp.cone is not None:
            axis = np.asarray(lamp.cone[:3], np.float64)
            cutoff = float(lamp.cone[3])
            to_c = (c - p) / dist
            gamma = math.acos(float(np.clip(axis @ to_c, -1.0, 1.0)))
            half = math.asin(min(1.0, r / dist))  # the sphere's angular radius from p
            if gamma - half >= cutoff:
                raise ValueError(
                    f"{lamp.source}: the spot's cone (cutoff_angle {math.degrees(cutoff):.4g}"
                    f" deg about its axis) misses the scene: the bounding sphere is "
                    f"{math.degrees(gamma):.4g} deg off the axis and {math.degrees(half):.4g}"
                    " deg in radius as the spot sees it; aim the spot at the object")


def lamp_light_set(lamps: Sequence[Lamp], center) -> shading.LightSet:
    """The local lights of ``lamps`` with weights E = I / |p - c|^2 at ``center`` [3]."""
    c = np.asarray(center, np.float64).reshape(3)
    pos = np.array([lp.position for lp in lamps], np.float64).reshape(-1, 3)
    inten = np.array([lp.intensity for lp in lamps], np.float64).reshape(-1, 3)
    w = (inten / np.sum((pos - c) ** 2, axis=1)[:, None]).astype(np.float32)
    ls = shading.local_lights(pos, mi.Color3f(*(jit.array(w[:, k]) for k in range(3))), c,
                              np.array([lp.radius for lp in lamps], np.float64))
    if any(lp.cone is not None for lp in lamps):
        ls.cones = np.array([lp.cone if lp.cone is not None else [np.nan] * 5
                             for lp in lamps], np.float64)
    return ls


def local_rows(lights: shading.LightSet) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions [K, 3] with NaN rows for directional lights, radii [K], cones [K, 5] with
    NaN rows) of any LightSet, as NumPy."""
    k = lights.count
    pos = (np.full((k, 3), np.nan) if lights.positions is None
           else shading._numpy_rows(lights.positions).copy())
    pos[~lights.local] = np.nan
    radii = (np.zeros(k) if lights.radii is None
             else np.asarray(lights.radii, np.float64).reshape(k))
    cones = (np.full((k, 5), np.nan) if lights.cones is None
             else np.asarray(lights.cones, np.float64).reshape(k, 5))
    return pos, radii, cones


def intensities(lights: shading.LightSet) -> np.ndarray:
    """[K, 3] radiant intensity (W/sr) of each local light, NaN rows for directional ones."""
    w = np.stack([np.asarray(lights.weights[k], np.float64) for k in range(3)], -1)
    w = w.reshape(-1, 3) * np.ones((lights.count, 1))
    out = np.full((lights.count, 3), np.nan)
    loc = lights.local
    out[loc] = w[loc] * lights.intensity()[loc, None]
    return out


def lamps_of(lights: shading.LightSet) -> list[Lamp]:
    """The local lights of ``lights`` as Lamps (directional ones left out)."""
    pos, radii, cones = local_rows(lights)
    inten = intensities(lights)
    return [Lamp(_t(pos[k]), _t(inten[k]), float(radii[k]),
                 _t(cones[k]) if np.all(np.isfinite(cones[k])) else None)
            for k in np.flatnonzero(lights.local)]


def cone_at(lights: shading.LightSet, point) -> np.ndarray:
    """[K] each light's spot falloff toward ``point`` [3] (1 for lights without a cone)."""
    pos, _, cones = local_rows(lights)
    out = np.ones(lights.count)
    has = np.all(np.isfinite(cones), axis=1)
    for k in np.flatnonzero(has):
        to = np.asarray(point, np.float64) - pos[k]
        cos_t = float(cones[k, :3] @ to / max(np.linalg.norm(to), 1e-300))
        out[k] = float(shading.spot_falloff(np.array(cos_t), cones[k, 3], cones[k, 4]))
    return out


# -- Mitsuba emitters -----------------------------------------------------------------------
def _rgb(params, key: str, where: str) -> np.ndarray:
    textured = [k for k in params.keys() if k.startswith(key.split(".")[0] + ".")
                and k != key]
    if key not in params.keys() or textured:
        raise ValueError(f"{where}: its '{key.split('.')[0]}' must be one RGB value or "
                         "spectrum (a texture is not supported)")
    return np.asarray(params[key], np.float64).reshape(-1)[:3] * np.ones(3)


def _t(values) -> tuple:
    return tuple(float(v) for v in np.ravel(values))


def _matrix(value) -> np.ndarray:
    return np.asarray(value.matrix, np.float64).reshape(4, 4)


def mitsuba_lamp(emitter, where: str) -> Lamp | None:
    """The Lamp of a Mitsuba ``point``, ``spot`` or ``area`` emitter on a ``sphere``; None
    for another emitter type. ValueError naming it where it is a lamp that is not supported
    (a textured spot, an area light on another shape or on a scaled-unevenly sphere)."""
    name = emitter.class_name()
    src = f"{where}: emitter {emitter.id()!r} ({name})"
    p = mi.traverse(emitter)
    if name == "PointLight":
        pos = np.asarray(p["position"], np.float64).reshape(-1)[:3]
        return Lamp(_t(pos), _t(_rgb(p, "intensity.value", src)), source=src)
    if name == "SpotLight":
        tex = [k for k in p.keys() if k.startswith("texture.") and k != "texture.value"]
        if tex or ("texture.value" in p.keys() and
                   float(np.asarray(p["texture.value"]).reshape(-1)[0]) != 1.0):
            raise ValueError(f"{src}: a spot with a 'texture' is not supported")
        m = _matrix(p["to_world"])
        axis = m[:3, 2] / np.linalg.norm(m[:3, 2])
        cutoff = math.radians(float(np.asarray(p["cutoff_angle"]).reshape(-1)[0]))
        beam = math.radians(float(np.asarray(p["beam_width"]).reshape(-1)[0]))
        return Lamp(_t(m[:3, 3]), _t(_rgb(p, "intensity.value", src)),
                    cone=_t([*axis, cutoff, min(beam, cutoff)]), source=src)
    if mi.has_flag(emitter.flags(), mi.EmitterFlags.Surface):
        shape = emitter.get_shape()
        if shape is None or shape.class_name() != "Sphere":
            kind = shape.class_name() if shape is not None else "no shape"
            raise ValueError(f"{src}: an area light on a {kind} is not supported; use a "
                             "'sphere' shape (or a point or spot emitter)")
        m = _matrix(mi.traverse(shape)["to_world"])
        scales = np.linalg.norm(m[:3, :3], axis=0)
        if not np.allclose(scales, scales[0], rtol=1e-5):
            raise ValueError(f"{src}: its sphere is scaled unevenly ({scales.tolist()}); a "
                             "lamp is a round sphere")
        radius = float(scales[0])
        radiance = _rgb(p, "radiance.value", src)
        return Lamp(_t(m[:3, 3]), _t(radiance * math.pi * radius**2), radius, source=src)
    return None


# -- lights.json ----------------------------------------------------------------------------
def lamps_from_json(entry: dict, where: str) -> list[Lamp]:
    """The lamps of a ``lights.json`` relighting of type "point": each light with a
    ``position`` [3] (world), an ``intensity`` (W/sr, 1 or 3 numbers) and an optional
    ``radius``; ValueError naming the field."""
    lts = entry.get("lights") or []
    if not lts:
        raise ValueError(f"{where}: relighting {entry.get('name')!r} has no lights")
    out = []
    for k, lt in enumerate(lts):
        src = f"{where}: relighting {entry.get('name')!r} light {k}"
        try:
            pos = np.asarray(lt["position"], np.float64).reshape(3)
            inten = np.asarray(lt["intensity"], np.float64).reshape(-1)
            inten = inten * np.ones(3) if inten.size == 1 else inten.reshape(3)
            radius = float(lt.get("radius", 0.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{src}: missing or malformed field 'position', 'intensity' or "
                             f"'radius' ({exc})") from None
        lamp = Lamp(_t(pos), _t(inten), radius, source=src)
        check_lamp_values(lamp)
        out.append(lamp)
    return out
