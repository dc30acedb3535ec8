"""What every settings dataclass shares: the preset names, overrides checked by name and
type, field checks, and settings read back from a manifest.

Each stage module defines a frozen dataclass whose field defaults are the paper's values;
the named presets (``PRESET_NAMES``: ``paper``, ``cpu-small``, ``cpu-medium``, ``gpu-large``)
are trees of them in ``mi_shadowgs.presets``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

T = TypeVar("T")
PRESET_NAMES = ("cpu-small", "cpu-medium", "gpu-large", "paper")
# Presets sized for a GPU: on the CPU backend their runs take hours (RESULTS.md).
GPU_PRESETS = ("gpu-large", "paper")
# Where stage 2's label maps come from (segmentation.masks): here, so the CLI names them
# without importing the stages.
LABEL_MAP_SOURCES = ("material", "chromaticity")


class ConfigError(ValueError):
    """A preset name or a config field is unknown or invalid."""


def get_preset(presets: dict[str, T], name: str, what: str) -> T:
    """``presets[name]``, or ConfigError naming the stage and the known presets."""
    try:
        return presets[name]
    except KeyError:
        raise ConfigError(
            f"unknown preset {name!r} for {what}; known presets: {sorted(presets)}"
        ) from None


def with_overrides(config: T, overrides: dict[str, Any] | None, what: str) -> T:
    """A copy of ``config`` with some fields replaced; unknown fields raise ConfigError.

    A field that holds a dataclass takes a dict of its own overrides (e.g. a stage's
    ``{"raster": {"lowpass_inv_var": 8}}``), checked the same way.
    """
    if not overrides:
        return config
    names = {f.name for f in dataclasses.fields(config)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ConfigError(f"unknown {what} setting(s) {unknown}; known: {sorted(names)}")
    values = dict(overrides)
    kinds = _field_kinds(config)
    for name, value in overrides.items():
        current = getattr(config, name)
        if current is None and value is not None:  # an optional field: judged by its type
            current = {"int": 0, "float": 0.0, "bool": False}.get(kinds[name][0])
        if dataclasses.is_dataclass(current) and not isinstance(current, type):
            if isinstance(value, dict):
                # (a run's sections are named alone: "material", not "run.material")
                values[name] = with_overrides(current, value,
                                              name if what == "run" else f"{what}.{name}")
            elif not isinstance(value, type(current)):
                raise ConfigError(f"{what} setting {name!r} takes a dict of its own settings "
                                  f"or a {type(current).__name__}, got {value!r}")
        # A switch or a number given as text (a command line's "false", "128") would pass
        # as a truthy string or fail far from here: refused by name (None stays allowed
        # for the optional ones).
        elif value is None:
            continue
        elif isinstance(current, bool) and not isinstance(value, bool):
            raise ConfigError(f"{what} setting {name!r} takes True or False, got {value!r}")
        elif (isinstance(current, (int, float)) and not isinstance(current, bool)
                and (isinstance(value, bool) or not isinstance(value, (int, float)))):
            raise ConfigError(f"{what} setting {name!r} takes a number, got {value!r}")
    return dataclasses.replace(config, **values)


def parse_settings(cls, items, what: str) -> dict[str, Any]:
    """A command line's ``--set KEY=VALUE`` items -> {field: value} for config class ``cls``,
    each read as its field's annotated type (``parse_value``). A malformed item, an unknown
    key or a value of the wrong type is a ConfigError naming the setting."""
    fields = {f.name: f.type for f in dataclasses.fields(cls)}
    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        if key not in fields:
            raise ConfigError(f"--set: unknown {what} setting {key!r}; known: {sorted(fields)}")
        out[key] = parse_value(key, text, fields[key], what)
    return out


def parse_value(key: str, text: str, annotation, what: str = "") -> Any:
    """Command-line text ``text`` of setting ``key`` (of the settings ``what``) as its
    annotated type (``int``, ``float``, ``bool``, ``str``, ``X | None``; ``none`` for an
    optional one, a comma-separated list for a tuple of numbers); a ConfigError naming
    ``key`` otherwise."""
    options = _type_names(annotation)
    kind = " | ".join(options)
    if text.lower() == "none" and "None" in options:
        return None
    first = options[0]
    readers = {"bool": _read_bool, "int": int, "float": float, "str": str}
    try:
        if first in readers:
            return readers[first](text)
        if first.startswith("tuple[") and ("float" in first or "int" in first):
            cast = float if "float" in first else int
            return tuple(cast(t) for t in text.split(",") if t.strip())
    except ValueError as err:
        name = key.rsplit(".", 1)[-1]
        raise ConfigError(f"--set {key}={text!r}: {what + ' ' if what else ''}setting "
                          f"{name!r} takes {kind}") from err
    raise ConfigError(f"--set {key}: a setting of type {kind} is not set from the command "
                      "line; use --config with a JSON file")


def _field_kinds(cls) -> dict[str, list[str]]:
    """Each field's annotated types by name, in order (``int | None`` -> ["int", "None"]);
    the annotations are text (``from __future__ import annotations``)."""
    return {f.name: _type_names(f.type) for f in dataclasses.fields(cls)}


def _type_names(annotation) -> list[str]:
    """``int | None`` (text, or the type itself once something resolved the annotations)
    -> ["int", "None"]."""
    text = annotation.__name__ if isinstance(annotation, type) else str(annotation)
    return [k.strip().replace("NoneType", "None") for k in text.split("|")]


def _read_bool(text: str) -> bool:
    if text.lower() not in ("true", "false"):
        raise ValueError(text)
    return text.lower() == "true"


def check_fields(config, rules) -> None:
    """ConfigError naming the first field of ``config`` that breaks its rule; ``rules`` are
    (field, holds, rule) triples, e.g. ``("iterations", c.iterations >= 1, ">= 1")``. Called
    from a config's ``__post_init__``: a bad value never reaches a loop that would write the
    untrained model as a result or divide by it."""
    for field, holds, rule in rules:
        if not holds:
            raise ConfigError(f"{type(config).__name__}.{field} must be {rule}, got "
                              f"{getattr(config, field)!r}")


def recorded_config(cls, saved: dict | None, fallback, source: str = "the manifest"):
    """A stage's settings as its manifest recorded them (``saved``, a dict of ``cls``'s
    fields; fields it lacks keep ``cls``'s defaults, which older runs ran with), else
    ``fallback()`` (the preset's) where none were recorded. A record that is there but
    does not read (a field of the wrong type or out of range) is a ConfigError naming
    ``source`` and the field: the fit's settings are never swapped for the preset's."""
    if saved is None:
        return fallback()
    if not isinstance(saved, dict):
        raise ConfigError(f"{source}: the {cls.__name__} record is not a dict of settings: "
                          f"{saved!r}")
    names = {f.name for f in dataclasses.fields(cls)}
    try:  # (with_overrides: nested settings such as "raster" are saved as dicts)
        return with_overrides(cls(), {k: tuple(v) if isinstance(v, list) else v
                                      for k, v in saved.items() if k in names}, cls.__name__)
    except (TypeError, ValueError) as err:  # ConfigError is a ValueError
        raise ConfigError(f"{source}: its recorded {cls.__name__} does not read: {err}") from err


def slow_preset_warning(preset: str, variant: str) -> str | None:
    """The warning for a GPU-sized preset run on another backend, else None."""
    if preset in GPU_PRESETS and not variant.startswith("cuda"):
        return (f"preset {preset!r} is sized for a GPU (--variant cuda_ad_rgb); on {variant} "
                "its run takes hours")
    return None


def to_dict(config: Any) -> dict[str, Any]:
    return dataclasses.asdict(config)
