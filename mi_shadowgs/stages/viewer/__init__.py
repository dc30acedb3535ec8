"""The browser viewer of a finished run (``mi-shadowgs view``).

``viewer``: the relit frames of a run under the viewer's camera and lights; ``server``: the
viser server that shows them.
"""
