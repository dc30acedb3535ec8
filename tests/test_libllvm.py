"""The libLLVM discovery (mi_shadowgs.libllvm) and the backend's use of it.

The fake library folders hold symlinks to this machine's real LLVM 14 and 15 under names
that lie (an unversioned ``libLLVM.so``, a ``libLLVM-19.so``): the verdict must come from
the library, never from its name. Debian's llvm-14/15 are part of this project's machine
image; where one is absent its cases are skipped and say so.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from mi_shadowgs import backend, libllvm

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "mi_shadowgs" / "libllvm.py"
LLVM14 = next((p for p in ("/usr/lib/llvm-14/lib/libLLVM.so",
                           "/usr/lib/x86_64-linux-gnu/libLLVM-14.so.1") if os.path.isfile(p)),
              None)
LLVM15 = next((p for p in ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1",
                           "/usr/lib/llvm-15/lib/libLLVM.so") if os.path.isfile(p)), None)
needs_old = pytest.mark.skipif(
    LLVM14 is None or LLVM15 is None,
    reason="needs Debian's libllvm14 and libllvm15 (in this project's machine image) to "
           "build folders of broken libraries")
# The system Python, without the venv's site-packages: the script must need only the stdlib.
SYSTEM_PYTHON = os.path.join(sys.base_prefix, "bin", f"python{sys.version_info[0]}")


@pytest.fixture(scope="module")
def usable_lib() -> str:
    path = os.environ[backend.LLVM_ENV]
    assert libllvm.judge(path, sys.executable)[0], path
    return path


@pytest.fixture
def only_old(tmp_path: Path) -> Path:
    """A folder whose only libLLVMs are 14 and 15, under misleading names."""
    folder = tmp_path / "old"
    folder.mkdir()
    (folder / "libLLVM.so").symlink_to(LLVM14)  # llvm-14's unversioned name
    (folder / "libLLVM-14.so.1").symlink_to(LLVM14)
    (folder / "libLLVM-15.so").symlink_to(LLVM15)
    (folder / "libLLVM-19.so").symlink_to(LLVM15)  # a name that lies
    (folder / "libLLVM-20.so").write_text("not a library")
    return folder


def _script(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([SYSTEM_PYTHON, "-I", str(SCRIPT), *args], capture_output=True,
                          text=True, timeout=300, env=env)


@needs_old
def test_only_14_and_15_says_install(only_old, tmp_path):
    path, tried = libllvm.find_usable([str(only_old)], python=sys.executable, use_cache=False)
    assert path is None
    assert len(tried) == 3  # libLLVM.so, libLLVM-14.so.1 (same file), 15 and 19 (same), 20
    out = _script("--dir", str(only_old), "--no-cache",
                  env={**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")})
    assert out.returncode == 1
    assert out.stdout.startswith("install: ") and "libllvm19" in out.stdout


@needs_old
def test_usable_library_is_found_whatever_its_name(only_old, usable_lib, tmp_path):
    (only_old / "libLLVM-9.so").symlink_to(usable_lib)  # the working one, named as old
    path, _ = libllvm.find_usable([str(only_old)], python=sys.executable, use_cache=False)
    assert path == str(only_old / "libLLVM-9.so")
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    out = _script("--dir", str(only_old), "--python", sys.executable, env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.strip() == f"usable {only_old / 'libLLVM-9.so'}"
    # The verdict is cached, and a second call agrees.
    assert (tmp_path / "cache" / "mi_shadowgs" / "libllvm.json").is_file()
    again = _script("--dir", str(only_old), "--python", sys.executable, env=env)
    assert again.stdout == out.stdout


@needs_old
def test_drjit_kernel_separates_15_from_a_working_library(usable_lib):
    # LLVM 15 aborts Dr.Jit's process ("Cannot select: fminimum"); the child dies, we don't.
    assert not libllvm.runs_drjit_kernel(LLVM15, sys.executable)
    assert libllvm.runs_drjit_kernel(usable_lib, sys.executable)


def test_version_comes_from_the_library(usable_lib, tmp_path):
    assert libllvm.library_version(usable_lib)[0] >= libllvm.MIN_MAJOR
    fake = tmp_path / "libLLVM-99.so"
    fake.write_text("not a library")
    assert libllvm.library_version(str(fake)) is None
    assert libllvm.library_version(str(tmp_path / "missing.so")) is None
    assert not libllvm.judge(str(tmp_path / "missing.so"))[0]


@needs_old
def test_backend_refuses_without_a_usable_library(only_old, monkeypatch):
    # Everything configure_llvm touches is restored by monkeypatch afterwards.
    monkeypatch.delenv(backend.LLVM_ENV)
    monkeypatch.delenv(backend.CHECKED_ENV, raising=False)
    monkeypatch.setattr(libllvm, "SEARCH_DIRS", (str(only_old),))
    monkeypatch.setattr(backend, "_llvm_error", None)
    with pytest.raises(backend.BackendError, match="libllvm19"):
        backend.configure_llvm()
    # drjit is pointed at no library: a clean "not found" instead of an abort in LLVM 15.
    assert os.environ[backend.LLVM_ENV] == backend.NO_LIBRARY
    with pytest.raises(backend.BackendError, match="libllvm19"):
        backend.set_variant("llvm_ad_rgb")


@needs_old
def test_cli_names_a_broken_user_library_and_exits_2(tmp_path):
    env = {**os.environ, backend.LLVM_ENV: LLVM15, "XDG_CACHE_HOME": str(tmp_path)}
    env.pop(backend.CHECKED_ENV, None)
    out = subprocess.run([sys.executable, "-m", "mi_shadowgs.cli", "render", "m.ply",
                          "--cameras", "c.json", "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and f"DRJIT_LIBLLVM_PATH={LLVM15} is not usable" in lines[0]
