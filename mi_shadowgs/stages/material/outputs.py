"""Stage 4's files: the fitted model's PLY metadata, ``light.json``, ``history.csv`` and
``fit.json`` (``save_fit``), and a result read back from them (``fit_from_files``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_shadowgs.core.directions import angles_from_direction
from mi_shadowgs.stages.material.state import LightModel, MaterialResult
from mi_shadowgs.stages.visibility.shadow_maps import VisibilityConfig

# The stage-4 model's PLY records the shadow maps and receivers it was fitted with under
# these keys (the whole ``VisibilityConfig`` as one word of JSON, and its band alone, which
# older models hold without the rest), so that a reader of the bare file (the
# ``surfel_relight`` plugin) shades it as ``relight`` shades the run.
BAND_METADATA_KEY = "receiver_band"
VISIBILITY_METADATA_KEY = "visibility"
# Whether the fit modelled the GGX lobe: a model fitted without it (cpu-*) has roughness and
# metallic channels the fit never moved, so a reader that turns the lobe on draws highlights
# from untrained values.
SPECULAR_METADATA_KEY = "specular"
# What a finished fit leaves in its folder; fit.json, written last, marks it finished.
FIT_FILES = ("model.ply", "light.json", "history.csv", "fit.json")


def model_metadata(vis_config: VisibilityConfig, specular: bool) -> dict[str, str]:
    """What a stage-4 model's PLY records for its readers (``ply.save_ply``'s metadata)."""
    import json

    from mi_shadowgs.config import to_dict

    return {BAND_METADATA_KEY: repr(float(vis_config.receiver_band)),
            VISIBILITY_METADATA_KEY: json.dumps(to_dict(vis_config), separators=(",", ":")),
            SPECULAR_METADATA_KEY: "true" if specular else "false"}


def light_json(result: MaterialResult) -> dict:
    """The fitted light of stage 4 as ``light.json`` holds it: the grid radiance, the active
    directions, their unit vectors and irradiance, their azimuth/elevation (degrees), the
    specular and visibility flags, and the lights after each pruning, refinement and
    settling (``MaterialState.light_log``; "log")."""
    light = result.light
    dirs = np.asarray(light.light_set().directions)
    return {"radiance": light.radiance.tolist(), "active": light.active.tolist(),
            "directions": dirs.tolist(),
            "irradiance": light.weights.tolist() if light.weights is not None else None,
            "angles_deg": [list(angles_from_direction(d)) for d in dirs],
            "specular": result.specular, "use_visibility": result.use_visibility,
            "log": result.light_log, **local_light_json(light)}


def local_light_json(light: LightModel) -> dict:
    """light.json's local-light fields: ``positions`` ([x, y, z], or null for a directional
    light), ``radii`` and ``center`` (where a lamp's irradiance is its weight); none when
    every light is directional."""
    if light.positions is None:
        return {}
    pos = np.asarray(light.positions, np.float64).reshape(-1, 3)
    return {"positions": [p.tolist() if np.all(np.isfinite(p)) else None for p in pos],
            "radii": np.asarray(light.radii if light.radii is not None
                                else np.zeros(len(pos)), np.float64).tolist(),
            "center": np.asarray(light.center, np.float64).tolist()}


def local_lights_from_json(data: dict, count: int) -> tuple:
    """(positions [K, 3] with NaN rows, radii [K], center [3]) from light.json's fields, or
    (None, None, None) without them; raises ValueError naming the field."""
    if data.get("positions") is None:
        return None, None, None
    rows = data["positions"]
    if len(rows) != count:
        raise ValueError(f"'positions' has {len(rows)} entries for {count} lights")
    pos = np.array([[np.nan] * 3 if p is None else p for p in rows], np.float64).reshape(-1, 3)
    radii = np.asarray(data.get("radii") or np.zeros(count), np.float64).reshape(count)
    if np.any(radii < 0) or not np.all(np.isfinite(radii)):
        raise ValueError("'radii' must be finite and >= 0")
    center = np.asarray(data["center"], np.float64).reshape(3)
    return pos, radii, center


def save_fit(out, result: MaterialResult, vis_config: VisibilityConfig, fit_s: float) -> None:
    """``FIT_FILES`` of a finished fit into the open ``Output`` ``out`` (fit.json last)."""
    from mi_shadowgs.io.atomic import write_json, write_text
    from mi_shadowgs.io.ply import save_ply

    save_ply(out.path("model.ply"), result.surfels, model_metadata(vis_config, result.specular))
    write_json(out.path("light.json"), light_json(result))
    write_text(out.path("history.csv"), "step,loss\n" + "".join(
        f"{int(step)},{float(loss)!r}\n" for step, loss in result.history))
    write_json(out.path("fit.json"), {"fit_s": fit_s, "timings": result.timings})


def fit_from_files(model_path: Path, light_path: Path, history_path: Path | None = None,
                   use_visibility: bool = True) -> MaterialResult:
    """A stage-4 result back from its files (``model.ply``, ``light.json``, optionally
    ``history.csv``): what a rerun evaluates instead of fitting again, and what ``relight``
    renders. Errors name the file and field."""
    import json

    from mi_shadowgs.io.ply import load_ply

    model = load_ply(model_path)
    missing = [c for c in ("albedo", "roughness", "metallic") if c not in model.channels]
    if missing:
        raise ValueError(f"{model_path}: the model lacks channel(s) {missing} (not a stage-4 "
                         "model)")
    try:
        data = json.loads(Path(light_path).read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{light_path}: file not found (the fitted light)") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{light_path}: malformed JSON: {exc}") from None
    try:
        radiance = np.asarray(data["radiance"], np.float64).reshape(-1)
        active = np.asarray(data["active"], np.int64).reshape(-1)
        dirs = np.asarray(data["directions"], np.float64).reshape(-1, 3)
        weights = (None if data.get("irradiance") is None
                   else np.asarray(data["irradiance"], np.float64).reshape(len(dirs)))
        specular = bool(data["specular"])
        positions, radii, center = local_lights_from_json(data, len(dirs))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{light_path}: missing or malformed field ({exc})") from None
    history = []
    if history_path is not None and Path(history_path).is_file():
        for line in Path(history_path).read_text().splitlines()[1:]:
            step, loss = line.split(",")
            history.append((int(step), float(loss)))
    light = LightModel(radiance, active, dirs, weights, positions, radii, center)
    return MaterialResult(model, light, specular,
                          bool(data.get("use_visibility", use_visibility)), history, {},
                          list(data.get("log", [])))
