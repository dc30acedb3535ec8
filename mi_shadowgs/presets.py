"""Every setting of a run as one typed tree, and the named presets.

A run's settings are a ``RunConfig``: one frozen config object per stage (``geometry``,
``segmentation``, ``chromaticity``, ``visibility``, ``material``, ``relight``, ``export``)
and the run's own options. ``build(preset, overrides)`` makes it once from a named preset
and nested overrides; the stages receive these objects and never a preset name, and the run
records the tree it ran with in ``RUN/config.json``, which ``load_overrides`` reads back.

Presets: ``paper`` (the paper's settings), ``cpu-small`` (128^2 views, minutes on 2 cores),
``cpu-medium`` (256^2) and ``gpu-large`` (512^2, on a GPU). ``docs/decisions.md`` says why
each non-paper default is what it is.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from mi_shadowgs.config import (
    GPU_PRESETS,
    LABEL_MAP_SOURCES,
    PRESET_NAMES,
    ConfigError,
    check_fields,
    get_preset,
    parse_value,
    with_overrides,
)
from mi_shadowgs.stages.export.export import PRESETS as EXPORT
from mi_shadowgs.stages.export.export import ExportConfig
from mi_shadowgs.stages.geometry.train import PRESETS as GEOMETRY
from mi_shadowgs.stages.geometry.train import GeometryConfig
from mi_shadowgs.stages.material.config import PRESETS as MATERIAL
from mi_shadowgs.stages.material.config import MaterialConfig
from mi_shadowgs.stages.relight.render import PRESETS as RELIGHT
from mi_shadowgs.stages.relight.render import RelightConfig
from mi_shadowgs.stages.segmentation.features import PRESETS as SEGMENTATION
from mi_shadowgs.stages.segmentation.features import SegmentationConfig
from mi_shadowgs.stages.segmentation.masks import PRESETS as CHROMATICITY
from mi_shadowgs.stages.segmentation.masks import ChromaticityConfig
from mi_shadowgs.stages.visibility.shadow_maps import PRESETS as VISIBILITY
from mi_shadowgs.stages.visibility.shadow_maps import VisibilityConfig

MASK_SOURCES = ("auto", *LABEL_MAP_SOURCES)  # "auto": material ids where the views have them
# The stage sections of the tree, in the method's order.
SECTIONS = ("geometry", "segmentation", "chromaticity", "visibility", "material", "relight",
            "export")
CONFIG_NAME = "config.json"  # the tree a run ran with, in the run folder


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Every setting of ``mi-shadowgs run``: each stage's config and the run's options."""

    geometry: GeometryConfig = dataclasses.field(default_factory=GeometryConfig)
    """Stage 1: the 2DGS geometry."""
    segmentation: SegmentationConfig = dataclasses.field(default_factory=SegmentationConfig)
    """Stage 2: contrastive features and K-means."""
    chromaticity: ChromaticityConfig = dataclasses.field(default_factory=ChromaticityConfig)
    """Stage 2's label maps from colour, for views without material ids."""
    visibility: VisibilityConfig = dataclasses.field(default_factory=VisibilityConfig)
    """Stage 3: shadow maps from the surfels' depth."""
    material: MaterialConfig = dataclasses.field(default_factory=MaterialConfig)
    """Stage 4: materials, lights and indirect light."""
    relight: RelightConfig = dataclasses.field(default_factory=RelightConfig)
    """Stage 5: relighting under new lights."""
    export: ExportConfig = dataclasses.field(default_factory=ExportConfig)
    """``mi-shadowgs export``: splat PLYs, meshes and Mitsuba scenes."""
    preset: str = "paper"
    """The named preset the tree was built from (recorded; the values are the fields)."""
    masks: str = "auto"
    """Stage 2's labels: ``material`` ids, ``chromaticity``, or ``auto`` (ids when present)."""
    ablations: bool = False
    """Also fit the paper's Table 3 variants (w/o visibility, w/o segmentation)."""
    bounds_quantile: float = 0.98
    """Shadow-map bounds: this quantile of the surfels' distances from their centroid."""
    figure_views: int = 4
    """Test views shown in the report's figure grid."""
    preview_envmaps: tuple[str, ...] = ()
    """Env maps (files or folders of .exr) of the report's relit previews."""

    def __post_init__(self):
        check_fields(self, (
            ("masks", self.masks in MASK_SOURCES, f"one of {MASK_SOURCES}"),
            ("bounds_quantile", 0 < self.bounds_quantile <= 1, "in (0, 1]"),
            ("figure_views", self.figure_views >= 1, ">= 1"),
            ("preset", isinstance(self.preset, str) and bool(self.preset), "a preset name")))

    def variants(self) -> dict[str, MaterialConfig]:
        """Stage 4's fits: ``full``, and with ``ablations`` the paper's Table 3 variants."""
        out = {"full": self.material}
        if self.ablations:
            out["no_visibility"] = dataclasses.replace(self.material, use_visibility=False)
            out["no_segmentation"] = dataclasses.replace(self.material, segment_average=False)
        return out

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _tree(name: str, **run) -> RunConfig:
    return RunConfig(geometry=GEOMETRY[name], segmentation=SEGMENTATION[name],
                     chromaticity=CHROMATICITY[name], visibility=VISIBILITY[name],
                     material=MATERIAL[name], relight=RELIGHT[name], export=EXPORT[name],
                     preset=name, **run)


PRESETS: dict[str, RunConfig] = {
    "paper": _tree("paper", ablations=True),
    "cpu-small": _tree("cpu-small"),
    "cpu-medium": _tree("cpu-medium"),
    "gpu-large": _tree("gpu-large"),
}


def get_config(name: str) -> RunConfig:
    """The named preset's tree, unchanged."""
    return get_preset(PRESETS, name, "run")


def build(preset: str = "cpu-small", overrides: dict[str, Any] | None = None,
          seed: int | None = None) -> RunConfig:
    """The settings of a run: preset ``preset`` with nested ``overrides`` (``{"material":
    {"iterations": 300}, "masks": "chromaticity"}``; unknown names and wrong types are a
    ConfigError naming the setting). ``seed`` sets every stage's seed. Each stage config
    that changes is constructed exactly once."""
    overrides = {k: dict(v) if isinstance(v, dict) else v for k, v in (overrides or {}).items()}
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError(f"seed must be a whole number >= 0, got {seed!r}")
        for section in ("geometry", "segmentation", "material"):
            overrides.setdefault(section, {}).setdefault("seed", seed)
    if "preview_envmaps" in overrides:
        overrides["preview_envmaps"] = tuple(overrides["preview_envmaps"])
    return with_overrides(get_config(preset), overrides, "run")


def parse_sets(items: list[str], section: str | None = None) -> dict[str, Any]:
    """``--set section.field=value`` items (``material.iterations=300``,
    ``visibility.raster.tile=8``, ``masks=chromaticity``) as nested overrides, each value
    read as its field's type; with ``section`` (a stage's own command) a bare ``field=value``
    names a field of that section. A malformed item, an unknown name or a bad value is a
    ConfigError naming it."""
    base = RunConfig()
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected SECTION.FIELD=VALUE")
        path = key.split(".")
        if section is not None and path[0] not in {f.name for f in dataclasses.fields(base)}:
            path = [section, *path]
        node, target = base, out
        for depth, name in enumerate(path):
            if not dataclasses.is_dataclass(node) or name not in {
                    f.name for f in dataclasses.fields(node)}:
                where = ".".join(path[:depth]) or "run"
                known = sorted(f.name for f in dataclasses.fields(node)) \
                    if dataclasses.is_dataclass(node) else []
                raise ConfigError(f"--set {key}: unknown setting {name!r} in {where}; "
                                  f"known: {known}")
            field = next(f for f in dataclasses.fields(node) if f.name == name)
            child = getattr(node, name)
            if depth == len(path) - 1:
                if dataclasses.is_dataclass(child):
                    raise ConfigError(f"--set {key}: {key} is a group of settings; set one "
                                      f"of its fields, e.g. {key}."
                                      f"{dataclasses.fields(child)[0].name}=...")
                target[name] = parse_value(key, text, field.type)
            else:
                target = target.setdefault(name, {})
                node = child
    return out


def merge(base: dict[str, Any], more: dict[str, Any]) -> dict[str, Any]:
    """Nested overrides ``more`` laid over ``base`` (a new dict)."""
    out = dict(base)
    for k, v in more.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) \
            else v
    return out


def load_overrides(path: str | Path) -> tuple[str, dict[str, Any]]:
    """(preset, overrides) of a run's recorded settings ``path`` (``RUN/config.json``, or
    the run folder): ``build(*load_overrides(p))`` rebuilds the tree that run ran with."""
    path = Path(path)
    if path.is_dir():
        path = path / CONFIG_NAME
    try:
        saved = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"--config {path}: not found (a run folder's {CONFIG_NAME})") \
            from None
    except (OSError, ValueError) as err:
        raise ConfigError(f"--config {path}: does not read as JSON: {err}") from None
    if not isinstance(saved, dict) or not isinstance(saved.get("preset"), str):
        raise ConfigError(f"--config {path}: not a run's settings (no 'preset' field)")
    preset = saved.pop("preset")
    if preset not in PRESETS:
        raise ConfigError(f"--config {path}: unknown preset {preset!r}; known: "
                          f"{sorted(PRESETS)}")
    return preset, _lists_to_tuples(saved)


def _lists_to_tuples(value):
    if isinstance(value, dict):
        return {k: _lists_to_tuples(v) for k, v in value.items()}
    if isinstance(value, list):
        return tuple(_lists_to_tuples(v) for v in value)
    return value


def slow_preset_warning(config: RunConfig, variant: str) -> str | None:
    """The warning for a GPU-sized preset run on another backend, else None."""
    if config.preset in GPU_PRESETS and not variant.startswith("cuda"):
        return (f"preset {config.preset!r} is sized for a GPU (--variant cuda_ad_rgb); on "
                f"{variant} its run takes hours")
    return None


__all__ = ["MASK_SOURCES", "PRESETS", "PRESET_NAMES", "RunConfig", "build", "get_config",
           "load_overrides", "merge", "parse_sets", "slow_preset_warning"]
