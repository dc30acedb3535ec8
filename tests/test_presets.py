"""The run's settings tree (``mi_shadowgs.presets``): built once from a preset and nested
overrides, set from the command line by name, recorded by the run and read back."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from tiny_cli import TINY, presets

from mi_shadowgs.config import ConfigError
from mi_shadowgs.presets import (
    PRESETS,
    SECTIONS,
    RunConfig,
    build,
    load_overrides,
    parse_sets,
)


@pytest.fixture
def tiny_presets(monkeypatch):
    for table, config in presets():
        monkeypatch.setitem(table, TINY, config)


def stage_classes() -> dict[str, type]:
    return {name: type(getattr(RunConfig(), name)) for name in SECTIONS}


@pytest.fixture
def constructions(monkeypatch):
    """Counts of each stage config's constructions (``__init__`` calls) from now on."""
    counts = dict.fromkeys(stage_classes(), 0)
    for name, cls in stage_classes().items():
        original = cls.__init__

        def counted(self, *args, _name=name, _original=original, **kwargs):
            counts[_name] += 1
            _original(self, *args, **kwargs)

        monkeypatch.setattr(cls, "__init__", counted)
    return counts


def test_every_preset_is_a_whole_tree():
    for name in ("paper", "cpu-small", "cpu-medium", "gpu-large"):
        tree = PRESETS[name]
        assert tree.preset == name
        for section, cls in stage_classes().items():
            assert isinstance(getattr(tree, section), cls), (name, section)
    assert PRESETS["paper"].ablations and not PRESETS["cpu-small"].ablations
    # cpu-small differs from the paper where its 128^2 views need it
    assert PRESETS["cpu-small"].geometry.iterations < PRESETS["paper"].geometry.iterations


def test_photos_are_imported_at_the_presets_view_size():
    # the size every stage of the preset is tuned for and its studies score at
    # (docs/decisions.md, "Photos imported at the preset's view size")
    from mi_shadowgs import presets

    for name in ("paper", "cpu-small", "cpu-medium", "gpu-large"):
        gen = presets.GENERATE[name]
        assert presets.import_config(name).max_size == max(gen.width, gen.height), name


def test_build_constructs_each_changed_stage_config_once(constructions):
    config = build("cpu-small", {"material": {"iterations": 300, "lr_albedo": 0.02},
                                 "visibility": {"resolution": 256}}, seed=3)
    assert config.material.iterations == 300 and config.material.lr_albedo == 0.02
    assert config.visibility.resolution == 256
    assert config.geometry.seed == config.segmentation.seed == config.material.seed == 3
    assert constructions == {"geometry": 1, "segmentation": 1, "chromaticity": 0,
                             "visibility": 1, "material": 1, "relight": 0, "export": 0}
    # untouched sections are the preset's own objects
    assert config.relight is PRESETS["cpu-small"].relight


def test_a_run_builds_no_stage_config_of_its_own(tiny_presets, constructions, tmp_path):
    """The settings are built once, before the run: the stages receive those objects and
    make none (on a dataset with material ids and masks, where no setting depends on the
    labels)."""
    import mi_shadowgs.api as msg

    data = msg.generate_dataset(msg.scene_path("default"), tmp_path / "data", preset=TINY)
    for name in constructions:
        constructions[name] = 0
    config = build(TINY, {"material": {"iterations": 40}}, seed=1)
    built = dict(constructions)
    msg.run(data, tmp_path / "run", config=config)
    assert built == {"geometry": 1, "segmentation": 1, "chromaticity": 0, "visibility": 0,
                     "material": 1, "relight": 0, "export": 0}
    assert constructions == built, "a stage rebuilt its settings during the run"
    # The run records the tree it ran with, and --config reads it back to the same tree.
    recorded = json.loads((tmp_path / "run" / "config.json").read_text())
    assert recorded == json.loads(json.dumps(config.to_dict()))
    assert build(*load_overrides(tmp_path / "run")) == config
    # Each stage's manifest records the object that stage ran with.
    from mi_shadowgs.io.provenance import MANIFEST_NAME

    manifest = json.loads((tmp_path / "run" / "material" / "full" / MANIFEST_NAME)
                          .read_text())
    assert manifest["settings"]["material"] == json.loads(json.dumps(
        dataclasses.asdict(config.material)))


def test_set_reads_each_value_as_its_fields_type():
    sets = parse_sets(["material.iterations=300", "material.use_visibility=false",
                       "visibility.raster.tile_size=8", "masks=chromaticity",
                       "segmentation.n_segments=none", "geometry.lambda_normal=0.2"])
    assert sets == {"material": {"iterations": 300, "use_visibility": False},
                    "visibility": {"raster": {"tile_size": 8}}, "masks": "chromaticity",
                    "segmentation": {"n_segments": None}, "geometry": {"lambda_normal": 0.2}}
    config = build("cpu-small", sets)
    assert config.visibility.raster.tile_size == 8 and config.masks == "chromaticity"
    # a stage's own command takes its bare field names
    assert parse_sets(["iterations=10"], section="geometry") == {"geometry": {"iterations": 10}}


@pytest.mark.parametrize("item, match", [
    ("material.iterationz=3", "unknown material setting 'iterationz'"),
    ("materal.iterations=3", "unknown run setting 'materal'"),
    ("material.iterations=many", "material.iterations='many': material setting 'iterations' "
                                 "takes int"),
    ("material.use_visibility=yes", "use_visibility"),
    ("visibility.raster=3", "is a group of settings"),
    ("material.iterations", "expected SECTION.FIELD=VALUE"),
])
def test_set_names_a_bad_item(item, match):
    with pytest.raises(ConfigError, match=match):
        parse_sets([item])


def test_values_are_checked_by_the_stage_configs():
    with pytest.raises((ConfigError, ValueError), match="iterations"):
        build("cpu-small", {"material": {"iterations": -1}})
    with pytest.raises(ConfigError, match="unknown preset 'cpu-tiny'"):
        build("cpu-tiny")
    with pytest.raises(ConfigError, match="masks"):
        build("cpu-small", {"masks": "sam"})


def test_config_reads_a_run_back_and_names_a_bad_file(tmp_path):
    config = build("cpu-small", {"material": {"refine_passes": ((3.0, 1.0),)}}, seed=2)
    (tmp_path / "config.json").write_text(json.dumps(config.to_dict()))
    assert build(*load_overrides(tmp_path / "config.json")) == config
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ConfigError, match="bad.json: does not read as JSON"):
        load_overrides(tmp_path / "bad.json")
    with pytest.raises(ConfigError, match="not found"):
        load_overrides(tmp_path / "missing")
    (tmp_path / "other.json").write_text(json.dumps({"x": 1}))
    with pytest.raises(ConfigError, match="no 'preset' field"):
        load_overrides(tmp_path / "other.json")


def test_the_run_command_takes_set_and_config(tmp_path, capsys):
    from mi_shadowgs import cli

    assert cli.main(["run", str(tmp_path / "none"), "--out", str(tmp_path / "run"),
                     "--set", "material.iterationz=3"]) == 2
    assert "iterationz" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
    args = cli.build_parser().parse_args(
        ["run", "d", "--out", "o", "--material-iterations", "5", "--set",
         "visibility.resolution=128", "--seed", "4"])
    from mi_shadowgs.cli.run import run_config

    config = run_config(args)
    assert config.material.iterations == 5 and config.visibility.resolution == 128
    assert config.geometry.seed == 4


def test_pruning_beside_a_lamp_builds_no_config(constructions):
    """Stage 4's pruning keeps a lamp and a light near its direction apart (no merging)
    without a config of its own: the run's MaterialConfig is the one it was given."""
    import mitsuba as mi

    from mi_shadowgs.core.directions import direction_from_angles
    from mi_shadowgs.stages.material import lights

    cfg = PRESETS["cpu-small"].material
    assert cfg.merge_angle_deg > 3.0
    dirs = np.stack([direction_from_angles(0.0, 40.0), direction_from_angles(2.0, 41.0)])
    class Opt(dict):  # the optimiser's face that pruning uses
        def set_learning_rate(self, rates):
            self.rates = rates

    opt = Opt(log_light=mi.Float(np.zeros(2, np.float32)))
    pos = np.array([[3.0, 4.0, 0.0], [np.nan] * 3])
    for name in constructions:
        constructions[name] = 0
    kept, _, kept_pos = lights._prune(opt, dirs, None, cfg, lambda d: None, pos)
    assert len(kept) == 2 and kept_pos.shape == (2, 3)  # not merged
    assert constructions["material"] == 0
    merged, _, _ = lights._prune(opt, dirs, None, cfg, lambda d: None, None)
    assert len(merged) == 1  # without the lamp they are one light
