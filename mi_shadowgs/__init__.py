"""mi_shadowgs: shadow-aware inverse rendering with 2D Gaussian surfels on Mitsuba 3 / Dr.Jit.

Importing the package finds a libLLVM that Dr.Jit can run (before drjit loads) and selects the
default variant when none is active. The Mitsuba plugins (``surfel_raster``,
``surfel_relight``) register when asked: ``register_plugins()``.
"""

from mi_shadowgs import backend as _backend

__version__ = "0.1.0"

try:
    _backend.configure_llvm()
except _backend.BackendError:
    pass  # set_variant raises it, naming what to install; drjit cannot load a broken LLVM
else:
    try:
        _backend.ensure_variant()
    except _backend.BackendError:
        pass  # e.g. a bad MI_SHADOWGS_VARIANT: set_variant raises it, naming the variable,
        # so that `--help` works and `--variant` overrides it

set_variant = _backend.set_variant


def register_plugins() -> list[str]:
    """Register mi_shadowgs's Mitsuba plugins for the active variant (and, from then on, for
    each variant ``set_variant`` switches to); returns their names."""
    from mi_shadowgs.plugins import register

    return register()


__all__ = ["register_plugins", "set_variant", "__version__"]
