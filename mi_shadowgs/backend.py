"""The one place where mi_shadowgs picks its JIT backend and Mitsuba variant.

Dr.Jit 1.5's LLVM backend refuses libLLVM 14 and aborts the process on 15 ("Cannot select:
fminimum"); it works with 19. So before drjit initialises its LLVM backend we point
``DRJIT_LIBLLVM_PATH`` at a library that ``mi_shadowgs.libllvm`` has seen run a Dr.Jit
kernel (the same check ``scripts/setup.sh`` makes). Where there is none, drjit is pointed
at no library at all, so that it fails with an error instead of loading a broken LLVM, and
``set_variant`` raises ``BackendError`` saying what to install. Variants: ``llvm_ad_rgb``
(CPU, the default, always available) and ``cuda_ad_rgb`` (asked for explicitly, or through
``MI_SHADOWGS_VARIANT``). The Mitsuba plugins are not this module's business: they register
when asked (``mi_shadowgs.plugins.register``).
"""

from __future__ import annotations

import os
import sys

from mi_shadowgs import libllvm

DEFAULT_VARIANT = "llvm_ad_rgb"
SUPPORTED_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
VARIANT_ENV = "MI_SHADOWGS_VARIANT"
LLVM_ENV = "DRJIT_LIBLLVM_PATH"
# Set beside LLVM_ENV once a library passed the check: child processes trust it.
CHECKED_ENV = "MI_SHADOWGS_LIBLLVM_CHECKED"
# What drjit is pointed at when nothing usable exists: a clean "not found" beats an abort.
NO_LIBRARY = os.path.join(os.sep, "nonexistent", "mi_shadowgs-no-usable-libLLVM.so")


class BackendError(RuntimeError):
    """The requested JIT backend cannot run on this machine."""


# Why the LLVM backend is unusable here, once configure_llvm failed (set_variant raises it).
_llvm_error: BackendError | None = None


def configure_llvm() -> str:
    """Point DRJIT_LIBLLVM_PATH at a libLLVM that Dr.Jit can use; returns its path.

    Must run before drjit first initialises its LLVM backend (``import mi_shadowgs`` does).
    A path the user set is checked like any other. Raises BackendError naming what to do.
    """
    global _llvm_error
    current = os.environ.get(LLVM_ENV)
    if current and os.environ.get(CHECKED_ENV) == current:
        return current
    if current:
        ok, reason = libllvm.judge(current, sys.executable)
        path = current if ok else None
        problem = f"{LLVM_ENV}={current} is not usable: {reason}"
    else:
        path, _ = libllvm.find_usable(python=sys.executable)
        problem = libllvm.INSTALL_HINT
    if path is None:
        os.environ[LLVM_ENV] = NO_LIBRARY
        os.environ[CHECKED_ENV] = NO_LIBRARY
        _llvm_error = BackendError(f"mi_shadowgs: {problem}")
        raise _llvm_error
    os.environ[LLVM_ENV] = path
    os.environ[CHECKED_ENV] = path
    _llvm_error = None
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
    if name == "cuda_ad_rgb":
        return _cuda_available()
    if name == "llvm_ad_rgb":
        return _llvm_available()
    return False


# Called with the new variant's name after each switch (``set_variant``): how the plugins
# layer (``mi_shadowgs.plugins.register``) follows the variant without the backend
# importing it.
_on_switch: list = []


def on_variant_switch(hook) -> None:
    """Call ``hook(name)`` after every later variant switch of ``set_variant`` (once per
    hook, however often it is added)."""
    if hook not in _on_switch:
        _on_switch.append(hook)


def set_variant(name: str | None = None) -> str:
    """Select the Mitsuba variant (default: $MI_SHADOWGS_VARIANT or llvm_ad_rgb).

    Raises BackendError with one clear line when it cannot run here.
    """
    # A variant from the environment is named as such: the user may not know it is set.
    source = "variant"
    if not name and os.environ.get(VARIANT_ENV):
        name, source = os.environ[VARIANT_ENV], f"{VARIANT_ENV}={os.environ[VARIANT_ENV]}:"
    name = name or DEFAULT_VARIANT
    try:
        return _select(name)
    except BackendError as exc:
        if source == "variant":
            raise
        raise BackendError(f"mi_shadowgs: {source} {str(exc).removeprefix('mi_shadowgs: ')} "
                           f"(unset {VARIANT_ENV} or pass --variant)") from None


def _select(name: str) -> str:
    if name not in SUPPORTED_VARIANTS:
        raise BackendError(
            f"mi_shadowgs: unsupported variant {name!r}; choose one of {SUPPORTED_VARIANTS}"
        )
    if name == "llvm_ad_rgb" and _llvm_error is not None:
        raise _llvm_error
    import mitsuba as mi

    if name == "llvm_ad_rgb" and not _llvm_available():
        raise BackendError(f"mi_shadowgs: {libllvm.INSTALL_HINT}")
    if name == "cuda_ad_rgb" and not _cuda_available():
        raise BackendError(
            "mi_shadowgs: variant cuda_ad_rgb needs an NVIDIA GPU with its driver; "
            "none was found (use llvm_ad_rgb)"
        )
    if mi.variant() != name:
        mi.set_variant(name)
        for hook in _on_switch:
            hook(name)
    return name


def ensure_variant() -> str:
    """Make sure a supported variant is active (selecting the default if none is)."""
    import mitsuba as mi

    current = mi.variant()
    if current in SUPPORTED_VARIANTS:
        return current
    return set_variant(current if current in SUPPORTED_VARIANTS else None)
