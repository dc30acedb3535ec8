"""Is there a libLLVM on this machine that Dr.Jit's LLVM backend can use? (stdlib only)

The one source of truth for that question, used by ``mi_shadowgs.backend`` before drjit
loads and by ``scripts/setup.sh`` with the system Python before the venv exists::

    python3 mi_shadowgs/libllvm.py [--dir DIR ...] [--python PY]

prints ``usable PATH`` (exit 0) or ``install: ...`` (exit 1).

A candidate is judged by running it, never by its file name: Debian's llvm-14 ships an
unversioned ``libLLVM.so``, and a symlink may be named anything.
1. Its version comes from the library itself: ``LLVMGetVersion`` (in the C API since LLVM
   16), called through ctypes in a child process so that the library never loads here.
   A library without it is older than 16. Dr.Jit 1.5 refuses 14 and aborts the whole
   process on 15 ("Cannot select: fminimum"), so only 16 or newer can pass.
2. Where a Python with drjit is at hand, a tiny Dr.Jit LLVM kernel (min, max, sqrt and a
   reduction: the instructions 15 fails on) runs on the candidate in a child process, and
   the candidate passes only if the child exits cleanly with the right sum.
Verdicts are cached by (path, size, mtime, drjit version) under
``$XDG_CACHE_HOME/mi_shadowgs`` so that a CLI start pays for it once.
"""

from __future__ import annotations

import argparse
import glob
import hashlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

# Dr.Jit 1.5: 14 is refused, 15 crashes, 19 is measured to work (this machine's Debian).
MIN_MAJOR = 16
# Folders searched, in order; the newest working version wins.
SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib/llvm-*/lib",
    "/usr/lib64",
    "/usr/local/lib",
    "/opt/homebrew/opt/llvm/lib",
)
LIB_PATTERNS = ("libLLVM*.so*", "libLLVM*.dylib")
INSTALL_PACKAGE = "libllvm19"
INSTALL_HINT = (
    "no libLLVM that Dr.Jit's LLVM backend can use (it needs LLVM >= 16; 14 is refused and "
    f"15 crashes it): install one, e.g. `sudo apt-get install -y {INSTALL_PACKAGE}`, or set "
    "DRJIT_LIBLLVM_PATH to one"
)
CHILD_TIMEOUT_S = 120.0

_VERSION_CHILD = r"""
import ctypes, sys
lib = ctypes.CDLL(sys.argv[1])
get = getattr(lib, "LLVMGetVersion", None)
if get is None:
    print("none")
else:
    v = [ctypes.c_uint() for _ in range(3)]
    get(*[ctypes.byref(x) for x in v])
    print(".".join(str(x.value) for x in v))
"""

# Sum over x = 0, 0.5, ..., 7.5 of min(x, 3) + max(x, 1) + sqrt(x).
_KERNEL_CHILD = r"""
import drjit as dr
from drjit.llvm import Float
x = dr.arange(Float, 16) * 0.5
s = dr.sum(dr.minimum(x, 3.0) + dr.maximum(x, 1.0) + dr.sqrt(x))
print(repr(float(s[0] if hasattr(s, "__len__") else s)))
"""
_KERNEL_EXPECTED = sum(min(i / 2, 3.0) + max(i / 2, 1.0) + (i / 2) ** 0.5 for i in range(16))


def candidates(dirs: tuple[str, ...] | list[str] | None = None) -> list[str]:
    """Shared-library files named libLLVM* in ``dirs`` (globs allowed; default SEARCH_DIRS),
    one per real file.

    A version number in the name is only used to try likely winners first.
    """
    seen: dict[str, str] = {}
    for d in SEARCH_DIRS if dirs is None else dirs:
        for folder in sorted(glob.glob(d)):
            for pattern in LIB_PATTERNS:
                for path in sorted(glob.glob(os.path.join(folder, pattern))):
                    if not os.path.isfile(path) or path.endswith(".a"):
                        continue
                    seen.setdefault(os.path.realpath(path), path)

    def name_hint(path: str) -> int:
        m = re.findall(r"\d+", os.path.basename(os.path.realpath(path)))
        return int(m[0]) if m else 0

    return sorted(seen.values(), key=lambda p: (-name_hint(p), len(p), p))


def library_version(path: str) -> tuple[int, int, int] | None:
    """(major, minor, patch) reported by the library, or None if it is older than LLVM 16
    (no ``LLVMGetVersion``) or does not load."""
    try:
        out = subprocess.run([sys.executable, "-c", _VERSION_CHILD, path], capture_output=True,
                             text=True, timeout=CHILD_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired):
        return None
    text = out.stdout.strip()
    if out.returncode != 0 or not re.fullmatch(r"\d+\.\d+\.\d+", text):
        return None
    major, minor, patch = (int(x) for x in text.split("."))
    return major, minor, patch


def _cache_file() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(root) / "mi_shadowgs" / "libllvm.json"


def _drjit_version(python: str) -> str | None:
    """drjit's version as installed for ``python``, or None if it has none."""
    if os.path.abspath(python) == os.path.abspath(sys.executable):
        try:  # no child process for our own interpreter
            from importlib.metadata import PackageNotFoundError, version
            return version("drjit")
        except PackageNotFoundError:
            return None
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    try:
        out = subprocess.run([python, "-c", "import drjit; print(drjit.__version__)"],
                             capture_output=True, text=True, timeout=CHILD_TIMEOUT_S, env=env)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else None


def _cache_key(path: str, drjit_version: str) -> str | None:
    try:
        st = os.stat(os.path.realpath(path))
    except OSError:
        return None  # gone or unreadable: judged afresh, and found not to load
    raw = f"{os.path.realpath(path)}|{st.st_size}|{st.st_mtime_ns}|{drjit_version}"
    return hashlib.sha256(raw.encode()).hexdigest()


def _read_cache() -> dict:
    try:
        return json.loads(_cache_file().read_text())
    except (OSError, ValueError):
        return {}


def _write_cache(cache: dict) -> None:
    path = _cache_file()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(cache, indent=1))
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only home only costs the probe again next time


def runs_drjit_kernel(path: str, python: str) -> bool:
    """Whether Dr.Jit (under ``python``) runs a small LLVM kernel correctly on ``path``."""
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": path}
    try:
        out = subprocess.run([python, "-c", _KERNEL_CHILD], capture_output=True, text=True,
                             timeout=CHILD_TIMEOUT_S, env=env)
    except (OSError, subprocess.TimeoutExpired):
        return False
    try:
        return out.returncode == 0 and abs(float(out.stdout.strip()) - _KERNEL_EXPECTED) < 1e-3
    except ValueError:
        return False


def judge(path: str, python: str | None = None, use_cache: bool = True) -> tuple[bool, str]:
    """(usable, reason) for one candidate library."""
    drjit_version = _drjit_version(python) if python else None
    key = _cache_key(path, drjit_version or "-")
    use_cache = use_cache and key is not None
    cache = _read_cache() if use_cache else {}
    if use_cache and key in cache:
        ok, reason = cache[key]
        return bool(ok), str(reason)
    ok, reason = _judge_uncached(path, python, drjit_version)
    if use_cache:
        cache[key] = [ok, reason]
        _write_cache(cache)
    return ok, reason


def _judge_uncached(path: str, python: str | None,
                    drjit_version: str | None) -> tuple[bool, str]:
    version = library_version(path)
    if version is None:
        return False, "older than LLVM 16 (no LLVMGetVersion) or does not load"
    if version[0] < MIN_MAJOR:
        return False, f"LLVM {version[0]} (Dr.Jit needs >= {MIN_MAJOR})"
    tag = f"LLVM {'.'.join(map(str, version))}"
    if python is None or drjit_version is None:
        where = ("no Python with drjit given" if python is None
                 else f"drjit is not importable by {python}")
        return True, f"{tag} (version check only: {where})"
    if runs_drjit_kernel(path, python):
        return True, f"{tag}, runs a Dr.Jit {drjit_version} kernel"
    return False, f"{tag}, but a Dr.Jit {drjit_version} kernel fails on it"


def find_usable(dirs=None, python: str | None = None,
                use_cache: bool = True) -> tuple[str | None, list[tuple[str, str]]]:
    """The first usable libLLVM in ``dirs`` and the verdict on every candidate tried."""
    tried = []
    for path in candidates(dirs):
        ok, reason = judge(path, python, use_cache)
        tried.append((path, reason))
        if ok:
            return path, tried
    return None, tried


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dir", action="append", default=None,
                        help="search this folder instead of the system's (repeatable)")
    parser.add_argument("--python", default=None,
                        help="a Python with drjit: also run a Dr.Jit kernel on the candidate")
    parser.add_argument("--no-cache", action="store_true", help="ignore cached verdicts")
    parser.add_argument("-v", "--verbose", action="store_true", help="list every candidate")
    args = parser.parse_args(argv)
    path, tried = find_usable(args.dir, args.python,
                              use_cache=not args.no_cache)
    if args.verbose:
        for p, reason in tried:
            print(f"  {p}: {reason}", file=sys.stderr)
    if path is None:
        print(f"install: {INSTALL_HINT}")
        return 1
    print(f"usable {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
