"""Mitsuba XML scenes shipped with mi_shadowgs (``mi_shadowgs.scenes``)."""

from pathlib import Path

SCENE_DIR = Path(__file__).resolve().parent


def scene_path(name: str) -> Path:
    """Path of a shipped scene, e.g. ``scene_path("default")``."""
    path = SCENE_DIR / (name if name.endswith(".xml") else f"{name}.xml")
    if not path.is_file():
        known = sorted(p.stem for p in SCENE_DIR.glob("*.xml"))
        raise FileNotFoundError(f"no shipped scene {name!r} in {SCENE_DIR}; known: {known}")
    return path
