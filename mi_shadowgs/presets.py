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
    LABEL_MAP_SOURCES,
    PRESET_NAMES,
    ConfigError,
    check_fields,
    get_preset,
    parse_value,
    with_overrides,
)
from mi_shadowgs.dataset.generate import GenerateConfig
from mi_shadowgs.dataset.importer import ImportConfig
from mi_shadowgs.stages.export.export import ExportConfig
from mi_shadowgs.stages.export.mesh import MeshConfig
from mi_shadowgs.stages.geometry.config import GeometryConfig
from mi_shadowgs.stages.geometry.densify import DensifyConfig
from mi_shadowgs.stages.material.config import MaterialConfig
from mi_shadowgs.stages.relight.render import RelightConfig
from mi_shadowgs.stages.segmentation.features import SegmentationConfig
from mi_shadowgs.stages.segmentation.masks import ChromaticityConfig
from mi_shadowgs.stages.segmentation.planes import PlaneConfig
from mi_shadowgs.stages.visibility.baselines import GaussianTraceConfig, VoxelConfig
from mi_shadowgs.stages.visibility.shadow_maps import VisibilityConfig

MASK_SOURCES = ("auto", *LABEL_MAP_SOURCES)  # "auto": material ids where the views have them
# The stage sections of the tree, in the method's order.
SECTIONS = ("geometry", "segmentation", "chromaticity", "visibility", "material", "relight",
            "export")
CONFIG_NAME = "config.json"  # the tree a run ran with, in the run folder
# Stage 4's fits: the method, and the paper's Table 3 ablations (settings changed from it).
VARIANTS = {
    "full": {},
    "no_visibility": {"use_visibility": False},  # "w/o visibility"
    "no_segmentation": {"segment_average": False},  # "w/o segmentation"
}


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
        if self.material.iterations < 1:  # its albedo would be scored unfitted
            raise ConfigError(f"material.iterations must be >= 1 for a run, got "
                              f"{self.material.iterations}")

    def variants(self) -> dict[str, MaterialConfig]:
        """Stage 4's fits: ``full``, and with ``ablations`` the paper's Table 3 variants."""
        names = VARIANTS if self.ablations else ("full",)
        return {name: dataclasses.replace(self.material, **VARIANTS[name]) if VARIANTS[name]
                else self.material for name in names}

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# -- the named presets ---------------------------------------------------------------------
# paper: the paper's settings (its defaults are each config's field defaults). cpu-small:
# 128^2 views on 2 CPU cores; cpu-medium: 256^2; gpu-large: 512^2 on a GPU. The reason for
# every value that departs from the paper is in docs/decisions.md.

_GEOMETRY_CPU_SMALL = GeometryConfig(
    iterations=2000, sh_degree=0, sh_degree_interval=500,
    lr_position_init=0.0016, lr_position_final=0.000016, lr_sh_dc=0.01, lr_sh_rest=0.0005,
    lr_scale=0.01, lr_rotation=0.004,
    lambda_normal=0.1, lambda_dist=3e4, normal_from=800, dist_from=1200,
    normal_depth_differences="same_plane",
    init_points=8000, hull_resolution=48, hull_extent=1.2, init_scale_factor=0.4,
    init_consistent_fraction=0.5,
    densify=DensifyConfig(start=200, stop=1800, interval=100, opacity_reset_interval=1000,
                          grad_threshold=0.0002, max_surfels=30000),
    unmasked_max_surfels=80000, log_every=25, preview_every=500, checkpoint_every=500)
_GEOMETRY_CPU_MEDIUM = dataclasses.replace(
    _GEOMETRY_CPU_SMALL, iterations=2500, sh_degree=1, unmasked_max_surfels=None,
    densify=dataclasses.replace(_GEOMETRY_CPU_SMALL.densify, max_surfels=80000))
GEOMETRY = {
    # no screen-space prune: at 800^2 it removes the flat surfaces' surfels at each reset
    "paper": GeometryConfig(densify=DensifyConfig(screen_size_threshold=None)),
    "cpu-small": _GEOMETRY_CPU_SMALL,
    "cpu-medium": _GEOMETRY_CPU_MEDIUM,
    "gpu-large": dataclasses.replace(
        _GEOMETRY_CPU_MEDIUM, densify=dataclasses.replace(
            _GEOMETRY_CPU_MEDIUM.densify, max_surfels=200000, screen_size_threshold=None)),
}
_SEGMENTATION_CPU = SegmentationConfig(iterations=300, lr=0.02, n_samples=2048,
                                       prototype_iterations=1,
                                       planes=PlaneConfig(enabled=True))
SEGMENTATION = {"paper": SegmentationConfig(), "cpu-small": _SEGMENTATION_CPU,
                "cpu-medium": _SEGMENTATION_CPU, "gpu-large": _SEGMENTATION_CPU}
CHROMATICITY = dict.fromkeys(PRESET_NAMES, ChromaticityConfig())
_VISIBILITY_CPU = VisibilityConfig(resolution=512, projection="orthographic", bias_texels=1.0,
                                   layer_bias=1.0, layer_cap_texels=3.0, layer_window=1,
                                   receiver_band=0.5)
VISIBILITY = {"paper": VisibilityConfig(), "cpu-small": _VISIBILITY_CPU,
              "cpu-medium": _VISIBILITY_CPU,
              "gpu-large": dataclasses.replace(_VISIBILITY_CPU, resolution=1024)}
_MATERIAL_CPU = MaterialConfig(iterations=600, warmup=200, lr_albedo=0.03, lr_light=0.1,
                               lambda_ind2=1.0, log_every=50, refine_global=128,
                               refine_again_global=True, specular="off",
                               albedo_tv_with_segments=False, albedo_scale=0.9,
                               refine_score="albedo", normal_steps=750, lamps="auto",
                               refine_passes=((8.0, 2.0, 256), (2.0, 0.5)))
MATERIAL = {"paper": MaterialConfig(), "cpu-small": _MATERIAL_CPU, "cpu-medium": _MATERIAL_CPU,
            "gpu-large": _MATERIAL_CPU}
RELIGHT = dict.fromkeys(PRESET_NAMES, RelightConfig())
EXPORT = {"paper": ExportConfig(mesh=MeshConfig(resolution=320)), "cpu-small": ExportConfig(),
          "cpu-medium": ExportConfig(), "gpu-large": ExportConfig()}


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

# The dataset generator (``mi-shadowgs generate``): views and samples per preset.
_GENERATE_CPU = {"n_test": 32, "spp": 128, "max_depth": 4}
GENERATE = {
    "paper": GenerateConfig(),
    "cpu-small": GenerateConfig(width=128, height=128, n_train=64, **_GENERATE_CPU),
    "cpu-medium": GenerateConfig(width=256, height=256, n_train=96, **_GENERATE_CPU),
    "gpu-large": GenerateConfig(width=512, height=512, n_train=96, **_GENERATE_CPU),
}
# The photo importer (``mi-shadowgs import``): the longest side of the imported views, the
# preset's own view size (the paper's 800: ``ImportConfig``'s default).
IMPORT = {"paper": ImportConfig(), "cpu-small": ImportConfig(max_size=128),
          "cpu-medium": ImportConfig(max_size=256), "gpu-large": ImportConfig(max_size=512)}
# The visibility baselines of the paper's Table 2 (``validation.visibility``).
GAUSSIAN_TRACE = {"paper": GaussianTraceConfig(), "cpu-small": GaussianTraceConfig(max_hits=16),
                  "cpu-medium": GaussianTraceConfig(max_hits=16),
                  "gpu-large": GaussianTraceConfig(max_hits=16)}
VOXEL = {"paper": VoxelConfig(), "cpu-small": VoxelConfig(resolution=48),
         "cpu-medium": VoxelConfig(resolution=48), "gpu-large": VoxelConfig(resolution=48)}


def get_config(name: str) -> RunConfig:
    """The named preset's tree, unchanged."""
    return get_preset(PRESETS, name, "run")


def geometry_config(name: str) -> GeometryConfig:
    """The named preset's stage-1 settings."""
    return get_config(name).geometry


def segmentation_config(name: str) -> SegmentationConfig:
    """The named preset's stage-2 settings."""
    return get_config(name).segmentation


def chromaticity_config(name: str) -> ChromaticityConfig:
    """The named preset's settings of stage 2's colour label maps."""
    return get_config(name).chromaticity


def visibility_config(name: str) -> VisibilityConfig:
    """The named preset's shadow-map settings (stage 3)."""
    return get_config(name).visibility


def material_config(name: str) -> MaterialConfig:
    """The named preset's stage-4 settings."""
    return get_config(name).material


def relight_config(name: str) -> RelightConfig:
    """The named preset's relighting settings (stage 5)."""
    return get_config(name).relight


def export_config(name: str) -> ExportConfig:
    """The named preset's export settings."""
    return get_config(name).export


def generate_config(name: str) -> GenerateConfig:
    """The named preset's dataset generation settings."""
    return get_preset(GENERATE, name, "dataset generation")


def import_config(name: str) -> ImportConfig:
    """The named preset's photo import settings."""
    return get_preset(IMPORT, name, "import")


def baseline_configs(name: str) -> tuple[GaussianTraceConfig, VoxelConfig]:
    """The named preset's settings of the Table 2 visibility baselines."""
    return (get_preset(GAUSSIAN_TRACE, name, "Gaussian-based visibility"),
            get_preset(VOXEL, name, "voxel-based visibility"))


def build(preset: str = "cpu-small", overrides: dict[str, Any] | None = None,
          seed: int | None = None) -> RunConfig:
    """The settings of a run: preset ``preset`` with nested ``overrides`` (``{"material":
    {"iterations": 300}, "masks": "chromaticity"}``; unknown names and wrong types are a
    ConfigError naming the setting). ``seed`` sets every stage's seed. Each stage config
    that changes is constructed exactly once."""
    overrides = {k: dict(v) if isinstance(v, dict) else v for k, v in (overrides or {}).items()}
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError(f"seed must be >= 0 (a whole number), got {seed!r}")
        for section in ("geometry", "segmentation", "material"):
            overrides.setdefault(section, {}).setdefault("seed", seed)
    if "preview_envmaps" in overrides:
        overrides["preview_envmaps"] = tuple(overrides["preview_envmaps"])
    if preset not in PRESETS and _whole_tree(overrides):
        # a whole recorded tree (a run's config.json) stands on its own, whatever preset it
        # was built from: a preset made for a study, or one this version no longer has
        return with_overrides(RunConfig(preset=preset), overrides, "run")
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
                known = (sorted(f.name for f in dataclasses.fields(node))
                         if dataclasses.is_dataclass(node) else [])
                raise ConfigError(f"--set {key}: unknown {where} setting {name!r}; "
                                  f"known: {known}")
            field = next(f for f in dataclasses.fields(node) if f.name == name)
            child = getattr(node, name)
            if depth == len(path) - 1:
                if dataclasses.is_dataclass(child):
                    raise ConfigError(f"--set {key}: {key} is a group of settings; set one "
                                      f"of its fields, e.g. {key}."
                                      f"{dataclasses.fields(child)[0].name}=...")
                target[name] = parse_value(key, text, field.type,
                                           ".".join(path[:-1]) or "run")
            else:
                target = target.setdefault(name, {})
                node = child
    return out


def merge(base: dict[str, Any], more: dict[str, Any]) -> dict[str, Any]:
    """Nested overrides ``more`` laid over ``base`` (a new dict)."""
    out = dict(base)
    for k, v in more.items():
        out[k] = (merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict)
                  else v)
    return out


def recorded(run: str | Path) -> RunConfig:
    """The settings tree a run folder recorded (``RUN/config.json`` when it finished, its
    manifest before); for a run that predates the record, the tree of the preset its
    manifest names. A ConfigError naming the folder where there is neither."""
    from mi_shadowgs.io.provenance import read_manifest

    run = Path(run)
    if (run / CONFIG_NAME).is_file():
        return build(*load_overrides(run / CONFIG_NAME))
    saved = (read_manifest(run) or {}).get("settings") or {}
    preset = saved.get("preset")
    if isinstance(preset, str) and _whole_tree(saved):
        # an unfinished run: its manifest holds the same tree
        return build(preset, _lists_to_tuples({k: v for k, v in saved.items()
                                               if k != "preset"}))
    if not isinstance(preset, str):
        raise ConfigError(f"{run}: no record of a run's settings ({CONFIG_NAME}, or a preset "
                          "in its manifest); is it a `mi-shadowgs run` folder?")
    return get_config(preset)


def load_overrides(path: str | Path) -> tuple[str, dict[str, Any]]:
    """(preset, overrides) of a run's recorded settings ``path`` (``RUN/config.json``, or
    the run folder): ``build(*load_overrides(p))`` rebuilds the tree that run ran with."""
    path = Path(path)
    if path.is_dir():
        path = path / CONFIG_NAME
    try:
        saved = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(
            f"--config {path}: not found (a run folder's {CONFIG_NAME})") from None
    except (OSError, ValueError) as err:
        raise ConfigError(f"--config {path}: does not read as JSON: {err}") from None
    if not isinstance(saved, dict) or not isinstance(saved.get("preset"), str):
        raise ConfigError(f"--config {path}: not a run's settings (no 'preset' field)")
    preset = saved.pop("preset")
    if preset not in PRESETS and not _whole_tree(saved):
        raise ConfigError(f"--config {path}: unknown preset {preset!r}; known: "
                          f"{sorted(PRESETS)}")
    return preset, _lists_to_tuples(saved)


def _whole_tree(saved: dict) -> bool:
    """Whether ``saved`` holds a section for every stage (a run's recorded tree)."""
    return all(isinstance(saved.get(k), dict) for k in SECTIONS)


def _lists_to_tuples(value):
    if isinstance(value, dict):
        return {k: _lists_to_tuples(v) for k, v in value.items()}
    if isinstance(value, list):
        return tuple(_lists_to_tuples(v) for v in value)
    return value


__all__ = ["MASK_SOURCES", "PRESETS", "PRESET_NAMES", "RunConfig", "baseline_configs", "build",
           "chromaticity_config", "export_config", "generate_config", "geometry_config",
           "get_config", "import_config", "load_overrides", "material_config", "merge",
           "parse_sets", "recorded", "relight_config", "segmentation_config",
           "visibility_config"]
