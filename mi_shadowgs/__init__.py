"""mi_shadowgs: shadow-aware inverse rendering with 2D Gaussian surfels on Mitsuba 3 / Dr.Jit.

Importing the package finds a libLLVM that Dr.Jit can run (before drjit loads), selects the
default variant when none is active, and registers the Mitsuba plugins for it.
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

__all__ = ["set_variant", "__version__"]
