"""Several env maps per dataset: ``GenerateConfig.envmaps`` resolves
"auto" to the shipped maps (``$MI_SHADOWGS_SHARED_DATA/envmaps``) or the sky, each map is a
recorded input (copied into the dataset, in its fingerprint), and ``run`` scores every one.

The shipped maps are stood in for by small maps written here, so nothing depends on whether
``../shared`` exists."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mi_shadowgs.cli import main as cli_main
from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.assets import SHARED_DATA_ENV
from mi_shadowgs.dataset.writer import resolve_envmaps
from mi_shadowgs.io.images import write_exr
from mi_shadowgs.io.provenance import MANIFEST_NAME
from mi_shadowgs.presets import generate_config as get_config

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--width", "24", "--height", "24", "--n-train", "2", "--n-test", "1", "--spp", "4",
        "--no-progress"]


def _envmap(path: Path, sky: float, sun_px: tuple[int, int] = (4, 20)) -> Path:
    """A 16 x 32 lat-long map: a uniform grey sky and one bright pixel (a sun)."""
    img = np.full((16, 32, 3), sky, np.float32)
    img[sun_px] = 200.0
    write_exr(path, img)
    return path


@pytest.fixture
def shared(tmp_path, monkeypatch):
    """A stand-in for ../shared/data with two env maps, named by the env var."""
    folder = tmp_path / "shared" / "data" / "envmaps"
    folder.mkdir(parents=True)
    _envmap(folder / "b_dusk.exr", 0.2, (6, 3))
    _envmap(folder / "a_noon.exr", 0.5)
    (folder / "notes.txt").write_text("not an env map")
    monkeypatch.setenv(SHARED_DATA_ENV, str(tmp_path / "shared" / "data"))
    return folder


def _names(envmaps) -> list[str]:
    return [e.name for e in envmaps]


def test_auto_is_the_shipped_maps_when_present_else_the_sky(shared, tmp_path, monkeypatch):
    cfg = get_config("cpu-small")
    assert cfg.envmaps == "auto"
    assert _names(resolve_envmaps(cfg)) == ["env_a_noon", "env_b_dusk"]  # sorted, EXRs only
    assert [e.ref for e in resolve_envmaps(cfg)] == ["envmaps/a_noon.exr", "envmaps/b_dusk.exr"]
    sky = dataclasses.replace(cfg, envmaps="sky")
    assert [(e.name, e.source, e.ref) for e in resolve_envmaps(sky)] == \
        [("env_sky_envmap", None, layout.SKY_ENVMAP)]
    assert resolve_envmaps(dataclasses.replace(cfg, envmaps="none")) == []
    both = dataclasses.replace(cfg, envmaps=("sky", "auto", str(shared / "a_noon.exr")))
    assert _names(resolve_envmaps(both)) == ["env_sky_envmap", "env_a_noon", "env_b_dusk"]
    monkeypatch.setenv(SHARED_DATA_ENV, str(tmp_path / "absent"))
    assert _names(resolve_envmaps(cfg)) == ["env_sky_envmap"]
    assert resolve_envmaps(dataclasses.replace(cfg, sky=None)) == []


def test_bad_envmap_entries_are_named(shared, tmp_path):
    cfg = get_config("cpu-small")
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        resolve_envmaps(dataclasses.replace(cfg, envmaps=(str(tmp_path / "missing.exr"),)))
    with pytest.raises(ValueError, match="'skyy'"):
        resolve_envmaps(dataclasses.replace(cfg, envmaps=("skyy",)))
    other = tmp_path / "other"
    other.mkdir()
    twin = _envmap(other / "a_noon.exr", 0.9)
    with pytest.raises(ValueError, match="env_a_noon"):
        resolve_envmaps(dataclasses.replace(cfg, envmaps=("auto", str(twin))))


def _generate(argv, capsys):
    rc = cli_main(["generate", "default", *argv])
    return rc, capsys.readouterr()


def test_each_envmap_is_rendered_copied_and_fingerprinted(shared, tmp_path, capsys):
    out = tmp_path / "data"
    rc, cap = _generate(["--out", str(out), "--envmap", "sky", "--envmap", "auto", *TINY],
                        capsys)
    assert rc == 0, cap.err
    lights = json.loads((out / "lights.json").read_text())
    env = [e for e in lights["relightings"] if e["type"] == "envmap"]
    assert [(e["name"], e["path"]) for e in env] == [
        ("env_sky_envmap", layout.SKY_ENVMAP), ("env_a_noon", "envmaps/a_noon.exr"),
        ("env_b_dusk", "envmaps/b_dusk.exr")]
    for e in env:  # one relit image per test view and map, and the map itself in the dataset
        assert (out / "test" / f"r_000_relit_{e['name']}.exr").is_file()
        assert (out / e["path"]).is_file()
    assert (out / "envmaps" / "a_noon.exr").read_bytes() == \
        (shared / "a_noon.exr").read_bytes()
    # the maps differ, so their relit views do
    from mi_shadowgs.io.images import read_exr

    a = read_exr(out / "test" / "r_000_relit_env_a_noon.exr")
    b = read_exr(out / "test" / "r_000_relit_env_b_dusk.exr")
    assert np.abs(a - b).mean() > 1e-3
    info = json.loads((out / "dataset.json").read_text())
    assert info["envmaps"] == [e["path"] for e in env]
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    assert "envmaps/a_noon.exr" in manifest["files"]
    assert set(manifest["inputs"]) >= {"envmap env_a_noon", "envmap env_b_dusk"}
    # Same inputs: recognised. An edited shipped map is another dataset: refused, untouched.
    rc, cap = _generate(["--out", str(out), "--envmap", "sky", "--envmap", "auto", *TINY],
                        capsys)
    assert rc == 0 and "nothing to do" in cap.out
    _envmap(shared / "a_noon.exr", 0.6)
    rc, cap = _generate(["--out", str(out), "--envmap", "sky", "--envmap", "auto", *TINY],
                        capsys)
    assert rc == 2 and "different dataset" in cap.err
    assert json.loads((out / "dataset.json").read_text())["fingerprint"] == info["fingerprint"]


def test_run_scores_every_envmap(shared, tmp_path):
    """A test-tiny dataset with the two stand-in maps and the sky: ``run`` scores all
    three, each with its own light set, and the report lists them."""
    env = {**os.environ, SHARED_DATA_ENV: str(shared.parent)}
    cli = [sys.executable, "-m", "tests.tiny_cli", "--threads", "1"]
    data, run = tmp_path / "data", tmp_path / "run"
    for args in (["generate", "default", "--out", str(data), "--envmap", "auto",
                  "--envmap", "sky"],
                 ["run", str(data), "--out", str(run)]):
        proc = subprocess.run(cli + args + ["--preset", "test-tiny", "--no-progress"],
                              cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((run / "material" / "full" / "metrics.json").read_text())
    scored = {k: v for k, v in metrics["relighting"].items() if v["type"] == "envmap"}
    assert sorted(scored) == ["env_a_noon", "env_b_dusk", "env_sky_envmap"]
    for r in scored.values():
        assert np.isfinite(r["psnr"]) and r["views"] == 2 and r["render_s"] > 0
    assert scored["env_a_noon"]["psnr"] != scored["env_b_dusk"]["psnr"]
    summary = json.loads((run / "summary.json").read_text())
    speed = [t for t in summary["tables"] if t["title"].startswith("Render speed")][0]
    assert {"env_a_noon", "env_b_dusk", "env_sky_envmap"} <= {r[0] for r in speed["rows"]}


def test_an_integer_envmap_is_used_with_a_warning_of_its_clipped_highlights(tmp_path, capsys):
    import imageio.v3 as iio

    from mi_shadowgs.core.envmap import low_dynamic_range

    png = tmp_path / "phone_pano.png"
    iio.imwrite(png, np.full((8, 16, 3), 200, np.uint8))
    exr = _envmap(tmp_path / "noon.exr", 0.9)
    assert low_dynamic_range(str(png)) and not low_dynamic_range(str(exr))
    cfg = dataclasses.replace(get_config("cpu-small"), envmaps=(str(png), str(exr)))
    assert _names(resolve_envmaps(cfg)) == ["env_phone_pano", "env_noon"]
    err = capsys.readouterr().err
    assert f"--envmap {png} stores integers (low dynamic range)" in err and "noon" not in err


@pytest.mark.parametrize("value, kind", [(np.nan, "NaN"), (np.inf, "Inf"),
                                         (-0.5, "a negative value")])
def test_envmap_texels_that_are_no_radiance_are_refused_naming_count_and_place(
        tmp_path, value, kind):
    """Mitsuba loads them without a word (one NaN texel: 121 of 128 light directions, the
    map 10% darker); every path that takes a map refuses it: generate, relight, run's
    previews, the emitter itself."""
    from mi_shadowgs.core.envmap import EnvmapError, load_envmap
    from mi_shadowgs.pipeline import check_preview_envmaps
    from mi_shadowgs.stages.relight import runner

    img = np.full((16, 32, 3), 0.5, np.float32)
    img[0, 0, 0] = -0.01  # HDR ringing, 2% of the mean below 0: kept (NEGATIVE_TOLERANCE)
    img[3, 7, 1] = value
    img[9, 2, :] = value
    path = write_exr(tmp_path / "bad.exr", img) or tmp_path / "bad.exr"
    want = re.escape(f"2 hold {kind} (the first at row 3, column 7)")
    with pytest.raises(EnvmapError, match=f"{path}: .*of its 32x16: {want}"):
        load_envmap(str(path))
    with pytest.raises(ValueError, match=f"--envmap {path}: .*{want}"):
        runner.build_lights(envmap=str(path))
    with pytest.raises(EnvmapError, match=want):
        check_preview_envmaps([str(path)])
    cfg = dataclasses.replace(get_config("cpu-small"), envmaps=(str(path),))
    with pytest.raises(EnvmapError, match=want):
        resolve_envmaps(cfg)


def test_an_integer_envmap_is_known_by_its_content_not_its_name(tmp_path, capsys):
    import imageio.v3 as iio

    from mi_shadowgs.core.envmap import low_dynamic_range

    disguised = tmp_path / "pano.exr"
    iio.imwrite(disguised, np.full((8, 16, 3), 200, np.uint8), extension=".png")
    assert low_dynamic_range(str(disguised))
    resolve_envmaps(dataclasses.replace(get_config("cpu-small"), envmaps=(str(disguised),)))
    assert f"--envmap {disguised} stores integers (low dynamic range)" in \
        capsys.readouterr().err


def test_the_shipped_env_maps_pass_the_check():
    """`make demo` generates with the shipped maps ("auto"): each must pass the check that
    every path applies to a map (their HDR ringing below 0 included)."""
    from mi_shadowgs.core.envmap import check_envmap
    from mi_shadowgs.dataset.assets import shipped_envmaps

    maps = shipped_envmaps()
    if not maps:
        pytest.skip("the shared env maps are not beside this checkout (../shared/data)")
    for path in maps:
        check_envmap(path)
