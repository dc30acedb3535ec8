"""Capture conditions of a generated dataset: a lamp, room light and a camera's jitter.

Scene parameters that every scene takes (``-D NAME=VALUE``), read here rather than in the
XML, so that datasets without them keep their fingerprints (docs/capture.md):

- ``capture``: a preset of the others (``CAPTURES``: ``lab``, ``none``); a parameter set
  beside it wins.
- ``lamp_distance``: a lamp at this distance from the object's centre, in object radii
  (> 1 + ``lamp_radius``). It replaces the scene's directional lights.
  ``lamp_azimuth`` / ``lamp_elevation`` (degrees, as the directional lights': from the
  object's centre), ``lamp_radius`` (object radii; a Mitsuba ``sphere`` area emitter, or a
  ``point`` emitter for 0) and ``lamp_irradiance`` (1 or 3 numbers: the irradiance, W/m^2 at
  normal incidence, that the lamp gives at the object's centre; its radiant intensity is
  ``lamp_irradiance * distance^2`` W/sr with the distance in world units).
- ``room_radiance``: a dim ``constant`` emitter of this radiance (1 or 3 numbers; 0: none).
- ``relight_lamp``: a relit test set under a new point lamp (lights.json's relighting
  ``RELIGHT_LAMP_NAME``, of type "point"): ``AZ,EL,DISTANCE`` (degrees from the object's
  centre, object radii, > 1), with the training lamp's irradiance at the object's centre
  (else ``LAMP_DEFAULTS``'); ``none``: no such set. A capture with a lamp gets one by
  default, ``RELIGHT_LAMP_TURN`` degrees of azimuth from its lamp, at
  ``RELIGHT_LAMP_ELEVATION`` and the same distance (recorded among the parameters, so that
  the dataset's fingerprint says it); a scene without a lamp only when it is set.
- ``photo_ev``, ``photo_wb``, ``photo_noise``, ``photo_jpeg`` (``generate --photos`` only):
  each photo's exposure is multiplied by ``2^u`` with ``u`` uniform in +-``photo_ev``, and
  each channel by ``1 + w`` with ``w`` uniform in +-``photo_wb``; Gaussian sensor noise of
  standard deviation ``photo_noise * sqrt(x + 0.01)`` on the linear value ``x`` after the
  gains; saved as JPEG of quality ``photo_jpeg``. Each photo's gains go to
  ``photos/gains.json`` (``photos.py``).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from mi_shadowgs.core.directions import direction_from_angles

LAMP_PARAMS = ("lamp_azimuth", "lamp_elevation", "lamp_distance", "lamp_radius",
               "lamp_irradiance")
PHOTO_PARAMS = ("photo_ev", "photo_wb", "photo_noise", "photo_jpeg")
CAPTURE_PARAMS = ("capture", *LAMP_PARAMS, "room_radiance", "relight_lamp", *PHOTO_PARAMS)
# A lamp capture's relighting: a point lamp turned this far in azimuth from its lamp and at
# this elevation (a shadow the training views never showed), named so in lights.json.
RELIGHT_LAMP_NAME = "lamp_moved"
RELIGHT_LAMP_TURN = 150.0
RELIGHT_LAMP_ELEVATION = 35.0
LAMP_DEFAULTS = {"lamp_azimuth": "35", "lamp_elevation": "50", "lamp_radius": "0",
                 "lamp_irradiance": "3"}
# A lab capture as the paper's real scenes were taken: one white lamp near the object in a
# dim room, photographed hand-held by a camera that sets its own exposure and white balance.
CAPTURES = {
    "lab": {"lamp_azimuth": "35", "lamp_elevation": "50", "lamp_distance": "6",
            "lamp_radius": "0.15", "lamp_irradiance": "3", "room_radiance": "0.03",
            "photo_ev": "0.35", "photo_wb": "0.04", "photo_noise": "0.01", "photo_jpeg": "90"},
    "none": {},
}
PHOTO_JPEG_DEFAULT = 95  # write_jpeg's quality: the photos of a capture without jitter


@dataclasses.dataclass(frozen=True)
class LampSpec:
    azimuth_deg: float
    elevation_deg: float
    distance: float  # object radii from the object's centre
    radius: float  # object radii (0: a point light)
    irradiance: tuple  # RGB at the object's centre, W/m^2 at normal incidence


@dataclasses.dataclass(frozen=True)
class Capture:
    """The capture parameters of a scene, checked (see the module doc)."""

    lamp: LampSpec | None = None
    room_radiance: tuple = (0.0, 0.0, 0.0)
    photo_ev: float = 0.0
    photo_wb: float = 0.0
    photo_noise: float = 0.0
    photo_jpeg: int = PHOTO_JPEG_DEFAULT
    params: dict = dataclasses.field(default_factory=dict)  # as recorded (strings)
    relight_lamp: LampSpec | None = None  # the point lamp of the lamp relighting

    @property
    def has_room(self) -> bool:
        return max(self.room_radiance) > 0

    @property
    def jitters_photos(self) -> bool:
        """Whether photos differ from plain sRGB JPEGs of the views (and get gains.json)."""
        return any(k in self.params for k in PHOTO_PARAMS)


def _numbers(path: Path, name: str, value: str, counts=(1,)) -> list[float]:
    from mi_shadowgs.dataset.scene import SceneError

    try:
        vals = [float(v) for v in str(value).replace(",", " ").split()]
    except ValueError:
        vals = []
    if len(vals) not in counts or not all(map(math.isfinite, vals)):
        want = " or ".join(map(str, counts))
        raise SceneError(f"{path}: scene parameter {name!r} must be {want} finite number(s), "
                         f"got {value!r}")
    return vals


def _in_range(path: Path, name: str, value: float, lo: float, hi: float, what: str) -> float:
    from mi_shadowgs.dataset.scene import SceneError

    if not lo <= value <= hi:
        raise SceneError(f"{path}: scene parameter {name!r} must be {what}, got {value:g}")
    return value


def _rgb(path: Path, name: str, value: str, positive: bool) -> tuple:
    from mi_shadowgs.dataset.scene import SceneError

    vals = _numbers(path, name, value, (1, 3))
    vals = vals * 3 if len(vals) == 1 else vals
    if min(vals) < 0 or (positive and max(vals) <= 0):
        need = "non-negative, not all 0" if positive else "non-negative"
        raise SceneError(f"{path}: scene parameter {name!r} must be {need}, got {value!r}")
    return tuple(vals)


def split_capture(path: Path, overrides: dict) -> tuple[Capture, dict]:
    """(the checked capture of ``overrides``, the other overrides); ``SceneError`` names a
    bad parameter."""
    from mi_shadowgs.dataset.scene import SceneError

    rest = {k: v for k, v in overrides.items() if k not in CAPTURE_PARAMS}
    given = {k: str(v).strip() for k, v in overrides.items() if k in CAPTURE_PARAMS}
    params = {}
    if "capture" in given:
        name = given["capture"].lower()
        if name not in CAPTURES:
            raise SceneError(f"{path}: scene parameter 'capture' must be one of "
                             f"{sorted(CAPTURES)}, got {given['capture']!r}")
        params = {"capture": name, **CAPTURES[name]}
    params.update({k: v for k, v in given.items() if k != "capture"})
    lamp = None
    stray = [k for k in LAMP_PARAMS if k in params and k != "lamp_distance"]
    if "lamp_distance" in params:
        lp = {**LAMP_DEFAULTS, **{k: params[k] for k in LAMP_PARAMS if k in params}}
        az = _numbers(path, "lamp_azimuth", lp["lamp_azimuth"])[0]
        el = _in_range(path, "lamp_elevation", _numbers(path, "lamp_elevation",
                       lp["lamp_elevation"])[0], -90.0, 90.0, "in [-90, 90] degrees")
        radius = _in_range(path, "lamp_radius", _numbers(path, "lamp_radius",
                           lp["lamp_radius"])[0], 0.0, math.inf, ">= 0 (object radii)")
        dist = _numbers(path, "lamp_distance", lp["lamp_distance"])[0]
        if dist <= 1.0 + radius:
            raise SceneError(f"{path}: scene parameter 'lamp_distance' {dist:g} puts the lamp "
                             f"inside the object: it must be > 1 + lamp_radius = "
                             f"{1.0 + radius:g} object radii from the object's centre")
        lamp = LampSpec(az, el, dist, radius,
                        _rgb(path, "lamp_irradiance", lp["lamp_irradiance"], positive=True))
    elif stray:
        raise SceneError(f"{path}: scene parameter(s) {', '.join(stray)} need "
                         "'lamp_distance' (object radii), which places the lamp")
    room = (_rgb(path, "room_radiance", params["room_radiance"], positive=False)
            if "room_radiance" in params else (0.0, 0.0, 0.0))
    relight = _relight_lamp(path, params, lamp)
    ev = _in_range(path, "photo_ev", _numbers(path, "photo_ev", params.get("photo_ev", "0"))[0],
                   0.0, 3.0, "in [0, 3] EV")
    wb = _in_range(path, "photo_wb", _numbers(path, "photo_wb", params.get("photo_wb", "0"))[0],
                   0.0, 0.5, "in [0, 0.5] (a share of each channel)")
    noise = _in_range(path, "photo_noise", _numbers(path, "photo_noise",
                      params.get("photo_noise", "0"))[0], 0.0, 0.5, "in [0, 0.5]")
    jpeg = _numbers(path, "photo_jpeg", params.get("photo_jpeg", str(PHOTO_JPEG_DEFAULT)))[0]
    if jpeg != int(jpeg) or not 1 <= jpeg <= 100:
        raise SceneError(f"{path}: scene parameter 'photo_jpeg' must be a whole number in "
                         f"[1, 100], got {params['photo_jpeg']!r}")
    return Capture(lamp, room, ev, wb, noise, int(jpeg), params, relight), rest


def _relight_lamp(path: Path, params: dict, lamp: LampSpec | None) -> LampSpec | None:
    """The point lamp of ``relight_lamp`` (module doc), derived from ``lamp`` and written
    into ``params`` where it is not set; None for none."""
    from mi_shadowgs.dataset.scene import SceneError

    if "relight_lamp" not in params and lamp is not None:
        params["relight_lamp"] = (f"{(lamp.azimuth_deg + RELIGHT_LAMP_TURN) % 360.0:g},"
                                  f"{RELIGHT_LAMP_ELEVATION:g},{lamp.distance:g}")
    text = params.get("relight_lamp")
    if text is None or text.strip().lower() == "none":
        return None
    az, el, dist = _numbers(path, "relight_lamp", text, (3,))
    _in_range(path, "relight_lamp", el, -90.0, 90.0, "AZ,EL,DISTANCE with EL in [-90, 90] "
              "degrees")
    if dist <= 1.0:
        raise SceneError(f"{path}: scene parameter 'relight_lamp' {text!r} puts the lamp "
                         "inside the object: its DISTANCE must be > 1 object radius")
    irr = (lamp.irradiance if lamp is not None else
           _rgb(path, "lamp_irradiance", LAMP_DEFAULTS["lamp_irradiance"], positive=True))
    return LampSpec(az, el, dist, 0.0, irr)


def lamp_light(spec: LampSpec, centre: np.ndarray, object_radius: float, path: Path,
               name: str = "lamp", param: str = "lamp"):
    """The lamp as a ``scene.Light`` named ``name`` in the world: its position, radius and
    irradiance at the object's centre; ``SceneError`` naming the ``param`` parameters when
    any of its sphere lies at or below the base."""
    from mi_shadowgs.dataset.scene import Light, SceneError

    l_dir = direction_from_angles(spec.azimuth_deg, spec.elevation_deg)
    distance = spec.distance * object_radius
    position = np.asarray(centre, np.float64) + distance * l_dir
    radius = spec.radius * object_radius
    if position[1] - radius <= 0.0:
        given = (f"scene parameters 'lamp_elevation' {spec.elevation_deg:g}, 'lamp_distance' "
                 f"{spec.distance:g}, 'lamp_radius' {spec.radius:g}" if param == "lamp" else
                 f"scene parameter '{param}'")
        raise SceneError(f"{path}: the lamp ({given}) is at or below the base (y = 0): "
                         f"its lowest point is at y = {position[1] - radius:.4g}")
    return Light(name, tuple(l_dir.tolist()), spec.irradiance, spec.azimuth_deg,
                 spec.elevation_deg, position=tuple(position.tolist()), radius=radius,
                 distance=distance)


def lamp_emitter(light, area: bool) -> dict:
    """Mitsuba's description of a lamp ``Light``: a ``point`` emitter of its intensity, or
    (``area`` and a radius) a ``sphere`` whose uniform radiance ``I / (pi R^2)`` gives the
    same intensity ``I`` (a sphere's projected area is pi R^2 from every side)."""
    intensity = [e * light.distance**2 for e in light.irradiance]
    if not area or light.radius <= 0:
        return {"type": "point", "position": list(light.position),
                "intensity": {"type": "rgb", "value": intensity}}
    radiance = [i / (math.pi * light.radius**2) for i in intensity]
    return {"type": "sphere", "center": list(light.position), "radius": light.radius,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": radiance}}}


def captured_scenes(scene, capture: Capture, lamp) -> tuple[object, object | None]:
    """(the scene with the capture's lights, for ray tracing: a lamp as a ``point`` emitter,
    which no ray hits; the scene to path-trace, with the lamp as its sphere, or None when it
    is the first). The lamp replaces the scene's directional lights; the room light is a
    ``constant`` emitter."""
    import mitsuba as mi

    def build(area: bool):
        desc = {"type": "scene"}
        for sh in scene.shapes():
            desc[sh.id() or f"shape{len(desc)}"] = sh
        if lamp is None:
            for em in scene.emitters():
                desc[em.id()] = em
        else:
            desc["lamp"] = lamp_emitter(lamp, area)
        if capture.has_room:
            desc["room"] = {"type": "constant",
                            "radiance": {"type": "rgb", "value": list(capture.room_radiance)}}
        return mi.load_dict(desc, optimize=False)

    traced = build(area=False)
    return traced, (build(area=True) if lamp is not None and lamp.radius > 0 else None)


def room_json(capture: Capture) -> dict:
    """lights.json's record of the room light."""
    return {"type": "constant", "radiance": list(capture.room_radiance),
            "irradiance_unoccluded": [math.pi * r for r in capture.room_radiance],
            "note": "uniform radiance from every direction (W/m^2/sr); not in the "
                    "irradiance ground truth, which holds the direct light of each lamp "
                    "or directional light"}
