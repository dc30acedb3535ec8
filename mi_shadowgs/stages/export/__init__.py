"""Export of a finished run's stage-4 model (``mi-shadowgs export``): splat PLYs in the
3DGS and 2DGS layouts, or a mesh with per-vertex materials and a Mitsuba scene.

``export``: the formats and ``export_run``; ``mesh``: TSDF fusion of the surfels to a mesh.
"""

from __future__ import annotations

from mi_shadowgs.stages.export.export import FORMATS, ExportConfig, ExportError, export_run

__all__ = ["FORMATS", "ExportConfig", "ExportError", "export_run"]
