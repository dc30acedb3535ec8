"""Mitsuba plugins of mi_shadowgs, one per module (``surfel_raster``, ``surfel_relight``).

They register when asked, not on import of the package: call ``register()`` (or
``mi_shadowgs.register_plugins()``) before ``mi.load_file``/``mi.load_dict`` of a scene that
names them. Once registered they follow ``mi_shadowgs.set_variant``: a switch registers them
again for the new variant.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys

# The variant the plugins are registered for (None: not registered yet).
_registered_for: str | None = None


def register() -> list[str]:
    """Register every plugin of this package for the active Mitsuba variant (selecting the
    default variant when none is) and keep them registered across later switches of
    ``mi_shadowgs.set_variant``; returns the plugins' names. Cheap when they already are.

    Plugin classes subclass variant-specific Mitsuba types, so for another variant the
    modules are reloaded rather than reused.
    """
    from mi_shadowgs import backend

    backend.on_variant_switch(_register_for)
    return _register_for(backend.ensure_variant())


def _register_for(variant: str) -> list[str]:
    global _registered_for
    names = [info.name for info in pkgutil.iter_modules(__path__)
             if not info.name.startswith("_")]
    if _registered_for == variant:
        return names
    for name in names:
        full = f"{__name__}.{name}"
        if full in sys.modules:
            importlib.reload(sys.modules[full])
        else:
            importlib.import_module(full)
    _registered_for = variant
    return names
