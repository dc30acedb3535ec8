"""Stage 4's result as files and back: ``light.json`` from a ``MaterialResult``
(``light_json``), and a ``MaterialResult`` from ``model.ply``, ``light.json`` and
``history.csv`` (``fit_from_files``), which a rerun evaluates instead of fitting again and
which relighting, evaluation and export read.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mi_shadowgs.core.directions import angles_from_direction
from mi_shadowgs.stages.material import fit


def light_json(result: fit.MaterialResult) -> dict:
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
            "log": result.light_log}


def fit_from_files(model_path: Path, light_path: Path, history_path: Path | None = None,
                   use_visibility: bool = True) -> fit.MaterialResult:
    """A stage-4 result back from its files (``model.ply``, ``light.json``, optionally
    ``history.csv``): what a rerun evaluates instead of fitting again, and what ``relight``
    renders. Errors name the file and field."""
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
        weights = (None if data.get("irradiance") is None else
                   np.asarray(data["irradiance"], np.float64).reshape(len(dirs)))
        specular = bool(data["specular"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{light_path}: missing or malformed field ({exc})") from None
    history = []
    if history_path is not None and Path(history_path).is_file():
        for line in Path(history_path).read_text().splitlines()[1:]:
            step, loss = line.split(",")
            history.append((int(step), float(loss)))
    light = fit.LightModel(radiance, active, dirs, weights)
    return fit.MaterialResult(model, light, specular,
                              bool(data.get("use_visibility", use_visibility)), history, {},
                              list(data.get("log", [])))
