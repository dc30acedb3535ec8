"""Named presets for the hyperparameter dataclasses of every stage.

Each stage module defines a frozen dataclass whose field defaults are the paper's values,
and a ``PRESETS`` dict name -> instance for each of ``PRESET_NAMES``: ``paper``,
``cpu-small`` (128^2, 64 views, minutes on 2 cores), ``cpu-medium`` (256^2, 96 views:
cpu-small's settings where the resolution does not change them; issue 18) and ``gpu-large``
(512^2, 96 views, cpu-medium's schedule: minutes on a GPU, the size at which the thin parts of
the table's scenes span enough pixels; issue 15).
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

T = TypeVar("T")
PRESET_NAMES = ("cpu-small", "cpu-medium", "gpu-large", "paper")
# Presets sized for a GPU: on the CPU backend their runs take hours. A gpu-large row took
# 4.5-4.8 min on an H100; its stage 1 alone took 30 min on one Xeon thread, and the paper's
# 40k steps at 800^2 take hours on 2 cores (BENCHMARKS.md, "Session 26").
GPU_PRESETS = ("gpu-large", "paper")


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
    for name, value in overrides.items():
        current = getattr(config, name)
        if dataclasses.is_dataclass(current) and not isinstance(current, type):
            if isinstance(value, dict):
                values[name] = with_overrides(current, value, f"{what}.{name}")
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
        elif isinstance(current, (int, float)) and not isinstance(current, bool) and \
                (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise ConfigError(f"{what} setting {name!r} takes a number, got {value!r}")
    return dataclasses.replace(config, **values)


def recorded_config(cls, saved: dict | None, fallback):
    """A stage's settings as its manifest recorded them (``saved``, a dict of ``cls``'s
    fields; fields it lacks keep ``cls``'s defaults, which older runs ran with), else
    ``fallback()`` (the preset's) where nothing usable was recorded."""
    if isinstance(saved, dict):
        names = {f.name for f in dataclasses.fields(cls)}
        try:  # (with_overrides: nested settings such as "raster" are saved as dicts)
            return with_overrides(cls(), {k: tuple(v) if isinstance(v, list) else v
                                          for k, v in saved.items() if k in names},
                                  cls.__name__)
        except (TypeError, ValueError):
            pass  # an older manifest: the preset's settings
    return fallback()


def slow_preset_warning(preset: str, variant: str) -> str | None:
    """The warning for a GPU-sized preset run on another backend, else None."""
    if preset in GPU_PRESETS and not variant.startswith("cuda"):
        return (f"preset {preset!r} is sized for a GPU (--variant cuda_ad_rgb); on {variant} "
                "its run takes hours")
    return None


def to_dict(config: Any) -> dict[str, Any]:
    return dataclasses.asdict(config)
