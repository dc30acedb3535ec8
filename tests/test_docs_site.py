"""The documentation site builds with ``mkdocs build --strict``: a broken link, a missing
anchor, a page missing from the navigation or an API page that cannot be generated fails."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MKDOCS_MISSING = importlib.util.find_spec("mkdocs") is None or \
    importlib.util.find_spec("mkdocstrings") is None


def _build(site: Path, config: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f",
                           str(config), "-d", str(site)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.skipif(MKDOCS_MISSING, reason="mkdocs or mkdocstrings is not installed (the dev "
                    "extra: pip install -e '.[dev]')")
def test_the_site_builds_strict_with_every_page(tmp_path):
    result = _build(tmp_path / "site", ROOT / "mkdocs.yml")
    assert result.returncode == 0, result.stdout + result.stderr
    nav = re.findall(r":\s*(\S+\.md)\s*$", (ROOT / "mkdocs.yml").read_text(), re.M)
    pages = {p.relative_to(ROOT / "docs").as_posix() for p in (ROOT / "docs").rglob("*.md")}
    assert pages == set(nav), "every page under docs/ is in mkdocs.yml's nav, and no other"
    for page in nav:
        html = tmp_path / "site" / ("index.html" if page == "index.md"
                                    else page[:-3] + "/index.html")
        assert html.is_file(), page
        # an image whose markdown did not parse (e.g. alt text over two lines) is no <img>
        built = html.read_text(encoding="utf-8")
        for figure in re.findall(r"!\[[^\]]*\]\((figures/[^)]+)\)",
                                 (ROOT / "docs" / page).read_text(encoding="utf-8")):
            assert re.search(r'<img [^>]*src="[./]*' + re.escape(figure) + '"', built), \
                (page, figure)
    api = (tmp_path / "site" / "api" / "index.html").read_text(encoding="utf-8")
    assert "generate_dataset" in api and "load_model" in api  # generated from docstrings


@pytest.mark.skipif(MKDOCS_MISSING, reason="mkdocs or mkdocstrings is not installed (the dev "
                    "extra: pip install -e '.[dev]')")
def test_a_broken_link_fails_the_build(tmp_path):
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "index.md").write_text("# Home\n\n[gone](gone.md) and [no anchor](#nowhere)\n")
    config = tmp_path / "mkdocs.yml"
    text = (ROOT / "mkdocs.yml").read_text()
    text = re.sub(r"^nav:\n(?:  - .*\n)+", "nav:\n  - Home: index.md\n", text, flags=re.M)
    text = text.replace("docs_dir: docs", f"docs_dir: {docs}")
    config.write_text(text)
    result = _build(tmp_path / "site", config)
    assert result.returncode != 0
    assert "gone.md" in result.stdout + result.stderr
