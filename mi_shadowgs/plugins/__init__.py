"""Mitsuba plugins of mi_shadowgs, one per module; installed as ``mi_shadowgs.plugins``.

Each module registers its plugin at its bottom for the active variant;
``mi_shadowgs.backend.register_plugins`` (re)imports them after a variant switch.
"""
