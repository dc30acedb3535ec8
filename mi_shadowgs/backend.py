"""The one place where mi_shadowgs picks its JIT backend and Mitsuba variant.

Dr.Jit 1.5's LLVM backend crashes with libLLVM 14 and 15 ("Cannot select: fminimum") and
works with 19, so before drjit is imported we look for a usable libLLVM and point
``DRJIT_LIBLLVM_PATH`` at it. Variants: ``llvm_ad_rgb`` (CPU, the default, always
available) and ``cuda_ad_rgb`` (asked for explicitly, or through ``MI_SHADOWGS_VARIANT``).
"""

from __future__ import annotations

import glob
import importlib
import os
import pkgutil
import re
import sys

DEFAULT_VARIANT = "llvm_ad_rgb"
SUPPORTED_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
VARIANT_ENV = "MI_SHADOWGS_VARIANT"
LLVM_ENV = "DRJIT_LIBLLVM_PATH"
# Major versions known to crash Dr.Jit 1.5 (measured on these machines).
BROKEN_LLVM_MAJORS = (14, 15)
# Searched in order; the first major version that is not broken wins, newest first.
LLVM_SEARCH_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
)
INSTALL_HINT = (
    "mi_shadowgs: no usable libLLVM found (Dr.Jit 1.5 crashes with LLVM 14/15); "
    "install LLVM 19, e.g. `apt-get install -y libllvm19`, or set DRJIT_LIBLLVM_PATH"
)


class BackendError(RuntimeError):
    """The requested JIT backend cannot run on this machine."""


def _llvm_major(path: str) -> int | None:
    name = os.path.basename(path)
    match = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", name)
    return int(match.group(1)) if match else None


def find_libllvm() -> str | None:
    """Path of the newest libLLVM on this machine that Dr.Jit 1.5 can use, or None."""
    candidates = []
    for pattern in LLVM_SEARCH_GLOBS:
        for path in glob.glob(pattern):
            major = _llvm_major(path)
            if major is None or major in BROKEN_LLVM_MAJORS or major < 11:
                continue
            candidates.append((major, path))
    if not candidates:
        return None
    candidates.sort(key=lambda mp: (-mp[0], len(mp[1])))
    return candidates[0][1]


def configure_llvm() -> str | None:
    """Point DRJIT_LIBLLVM_PATH at a usable libLLVM before drjit loads; returns the path."""
    current = os.environ.get(LLVM_ENV)
    if current:
        return current
    path = find_libllvm()
    if path is None:
        return None
    # Dr.Jit reads the variable when its LLVM backend first initialises (at the first LLVM
    # array or variant), so this also works after a bare `import drjit`.
    os.environ[LLVM_ENV] = path
    return path


def _cuda_available() -> bool:
    import drjit as dr

    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:
        return False


def _llvm_available() -> bool:
    import drjit as dr

    try:
        return bool(dr.has_backend(dr.JitBackend.LLVM))
    except Exception:
        return False


def variant_available(name: str) -> bool:
    """Whether ``name`` can run here (the backend library loads)."""
    configure_llvm()
    if name == "cuda_ad_rgb":
        return _cuda_available()
    if name == "llvm_ad_rgb":
        return _llvm_available()
    return False


def register_plugins() -> list[str]:
    """(Re)import every module of mi_shadowgs.plugins so it registers for the current variant.

    Plugin classes subclass variant-specific Mitsuba types, so after a variant switch
    the modules are reloaded rather than reused.
    """
    from . import plugins

    names = []
    for info in pkgutil.iter_modules(plugins.__path__):
        if info.name.startswith("_"):
            continue
        full = f"{plugins.__name__}.{info.name}"
        if full in sys.modules:
            importlib.reload(sys.modules[full])
        else:
            importlib.import_module(full)
        names.append(info.name)
    return names


_registered_for: str | None = None


def set_variant(name: str | None = None) -> str:
    """Select the Mitsuba variant (default: $MI_SHADOWGS_VARIANT or llvm_ad_rgb).

    Raises BackendError with one clear line when it cannot run here.
    """
    global _registered_for
    name = name or os.environ.get(VARIANT_ENV) or DEFAULT_VARIANT
    if name not in SUPPORTED_VARIANTS:
        raise BackendError(
            f"mi_shadowgs: unsupported variant {name!r}; choose one of {SUPPORTED_VARIANTS}"
        )
    configure_llvm()
    import mitsuba as mi

    if name == "llvm_ad_rgb" and not _llvm_available():
        raise BackendError(INSTALL_HINT)
    if name == "cuda_ad_rgb" and not _cuda_available():
        raise BackendError(
            "mi_shadowgs: variant cuda_ad_rgb needs an NVIDIA GPU with its driver; "
            "none was found (use llvm_ad_rgb)"
        )
    if mi.variant() != name:
        mi.set_variant(name)
    if _registered_for != name:
        register_plugins()
        _registered_for = name
    return name


def ensure_variant() -> str:
    """Make sure a supported variant is active (selecting the default if none is)."""
    import mitsuba as mi

    current = mi.variant()
    if current in SUPPORTED_VARIANTS and _registered_for == current:
        return current
    return set_variant(current if current in SUPPORTED_VARIANTS else None)


def is_cuda() -> bool:
    import mitsuba as mi

    return mi.variant() == "cuda_ad_rgb"
