"""Env-map relighting: the generator's procedural sky and its scoring.

The sky is checked against its own definition through Mitsuba's ``envmap`` emitter (so the
lat-long convention is Mitsuba's, not ours), and a generated dataset's env-map relit views
are scored by ``run`` like the directional ones.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowgs.core.directions import direction_from_angles, light_grid, solid_angle
from mi_shadowgs.core.envmap import load_envmap
from mi_shadowgs.dataset import layout
from mi_shadowgs.dataset.generate import SkyConfig, sky_envmap_image
from mi_shadowgs.io.images import write_exr
from mi_shadowgs.stages.relight.render import envmap_grid_radiance

ROOT = Path(__file__).resolve().parents[1]


def _emitter(tmp_path: Path, sky: SkyConfig):
    path = tmp_path / "sky.exr"
    write_exr(path, sky_envmap_image(sky))
    return load_envmap(str(path))  # on two threads at least (core.envmap)


@pytest.mark.parametrize("az, el", [(250.0, 45.0), (30.0, 20.0), (140.0, 70.0)])
def test_sun_sits_where_it_is_configured(tmp_path, az, el):
    sky = SkyConfig(sun_azimuth_deg=az, sun_elevation_deg=el)
    em = _emitter(tmp_path, sky)
    sun = direction_from_angles(az, el)
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(*(float(-x) for x in sun))  # looking up the sun's direction
    sun_radiance = float(np.asarray(em.eval(si)[0])[0])
    disc = 2 * np.pi * (1 - np.cos(np.radians(sky.sun_radius_deg)))
    # The disc's centre lies pixels inside the 6-pixel disc, where the bilinear lookup reads
    # the disc's own radiance: measured within 0.07%; 1% is the margin.
    assert sun_radiance == pytest.approx(sky.sun_irradiance / disc + sky.zenith[0], rel=0.01)
    # The brightest of the 128 grid cells is the one nearest the sun (cells are ~12.7 deg).
    rad = envmap_grid_radiance(em).mean(1)
    grid = light_grid(128)
    assert np.argmax(rad) == np.argmax(grid @ sun)


def test_sun_irradiance_matches_its_setting(tmp_path):
    # Sun alone (black sky): the light set carries sun_irradiance. Within 10%: the 4-degree
    # disc is drawn in 1.4-degree pixels (+6% here). Near the zenith Mitsuba's bilinear
    # lookup shrinks the disc (-28% at 90 degrees): the generator's sun sits at 45.
    sky = SkyConfig(zenith=(0, 0, 0), horizon=(0, 0, 0), ground=(0, 0, 0))
    rad = envmap_grid_radiance(_emitter(tmp_path, sky)).mean(1)  # [128]
    assert float(np.sum(rad * solid_angle(128))) == pytest.approx(sky.sun_irradiance, rel=0.1)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("env")
    cli = [sys.executable, "-m", "tests.tiny_cli", "--threads", "1"]
    for args in (["generate", "default", "--out", str(work / "data")],
                 ["run", str(work / "data"), "--out", str(work / "run")]):
        out = subprocess.run(cli + args + ["--preset", "test-tiny", "--no-progress"],
                             cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr
    return work


def test_generate_writes_sky_relit_views_and_run_scores_them(tiny_run):
    data, run = tiny_run / "data", tiny_run / "run"
    assert (data / layout.SKY_ENVMAP).is_file()
    entry = [e for e in json.loads((data / "lights.json").read_text())["relightings"]
             if e["type"] == "envmap"]
    assert [e["path"] for e in entry] == [layout.SKY_ENVMAP]  # relative: the folder moves
    name = entry[0]["name"]
    assert sorted((data / "test").glob(f"r_*_relit_{name}.exr"))
    metrics = json.loads((run / "material" / "full" / "metrics.json").read_text())
    scored = metrics["relighting"][name]
    assert scored["type"] == "envmap" and scored["light_directions"] > 2
    assert np.isfinite(scored["psnr"]) and scored["views"] >= 1 and scored["render_s"] > 0


def test_a_missing_env_map_is_named_before_any_work(tiny_run, tmp_path):
    data = tmp_path / "data"
    subprocess.run(["cp", "-r", str(tiny_run / "data"), str(data)], check=True)
    (data / layout.SKY_ENVMAP).unlink()
    out = subprocess.run([sys.executable, "-m", "tests.tiny_cli", "run", str(data), "--out",
                          str(tmp_path / "run"), "--preset", "test-tiny", "--no-progress"],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 2
    assert f"{data / layout.SKY_ENVMAP}: env map of relighting" in out.stderr
    assert not (tmp_path / "run").exists()
