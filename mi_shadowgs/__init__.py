"""mi_shadowgs: shadow-aware inverse rendering with 2D Gaussian surfels on Mitsuba 3 / Dr.Jit.

Importing the package finds a usable libLLVM (before drjit loads), selects the default
variant when none is active, and registers the Mitsuba plugins for it.
"""

from . import backend as _backend

__version__ = "0.1.0"

if _backend.configure_llvm() is None:
    import sys as _sys

    print(_backend.INSTALL_HINT, file=_sys.stderr)
else:
    _backend.ensure_variant()

set_variant = _backend.set_variant

__all__ = ["set_variant", "__version__"]
