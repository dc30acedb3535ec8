"""The import layers of mi_shadowgs go one way (see README "Layout").

Every import in the package (module level or inside a function) is read with ``ast``:
- no module imports a ``mi_shadowgs.cli`` module except the CLI package itself (the entry
  point ``mi_shadowgs.cli:main`` and its ``__main__``); ``validation/`` and ``benchmarks/``
  do not either;
- layers, bottom to top: base (``config``, ``libllvm``, ``backend``) < ``core`` < ``io`` <
  ``dataset`` < ``stages`` < ``pipeline`` < ``api`` / ``plugins`` < ``cli``; a module imports
  only its own layer or lower ones;
- stages in the method's order (geometry < segmentation < visibility < material < relight):
  a stage imports earlier stages (never a private ``_name`` of theirs) and never a later one.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "mi_shadowgs"
LAYERS = ["base", "core", "io", "dataset", "stages", "pipeline", "api", "cli"]
STAGES = ["common", "geometry", "segmentation", "visibility", "material", "relight"]
# backend.register_plugins (re)imports the plugins after a variant switch: Mitsuba needs them
# registered for the active variant, and the plugins are thin (they call the library).
ALLOWED = {("mi_shadowgs.backend", "mi_shadowgs.plugins")}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(mod: str) -> tuple[int, int]:
    """(layer, stage order) of a mi_shadowgs module."""
    parts = mod.split(".")
    top = parts[1] if len(parts) > 1 else "base"
    if top in ("config", "libllvm", "backend", "scenes"):
        return 0, 0
    if top == "plugins":
        return LAYERS.index("api"), 0
    if top == "stages":
        return LAYERS.index("stages"), STAGES.index(parts[2]) if len(parts) > 2 else 99
    return LAYERS.index(top), 0


def imports(path: Path) -> list[tuple[str, list[str], int]]:
    """(absolute module, imported names, line) of every mi_shadowgs import in ``path``."""
    mod = module_name(path)
    pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = pkg.split(".")[:len(pkg.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            if base.split(".")[0] != "mi_shadowgs":
                continue
            for alias in node.names:  # `from pkg import submodule` names the submodule
                sub = f"{base}.{alias.name}"
                is_mod = (ROOT / Path(*sub.split("."))).with_suffix(".py").is_file() or \
                    (ROOT / Path(*sub.split("."))).is_dir()
                out.append((sub if is_mod else base, [alias.name], node.lineno))
        elif isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names
                    if a.name.split(".")[0] == "mi_shadowgs"]
    return out


def package_files():
    return [p for p in PKG.rglob("*.py") if "__pycache__" not in p.parts]


def test_only_the_entry_point_imports_a_cli_module():
    bad = []
    files = package_files() + [p for d in ("validation", "benchmarks")
                               for p in (ROOT / d).rglob("*.py")]
    for path in files:
        if path.is_relative_to(PKG / "cli"):
            continue
        for target, _, line in imports(path):
            if target == "mi_shadowgs.cli" or target.startswith("mi_shadowgs.cli."):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {target}")
    assert not bad, "\n".join(bad)


def test_layers_go_one_way():
    bad = []
    for path in package_files():
        src = module_name(path)
        if src == "mi_shadowgs":
            continue
        s_layer, s_stage = layer(src)
        for target, names, line in imports(path):
            if target == "mi_shadowgs" or (src, target) in ALLOWED or \
                    any(target.startswith(a + ".") for s, a in ALLOWED if s == src):
                continue
            t_layer, t_stage = layer(target)
            where = f"{path.relative_to(ROOT)}:{line} ({src} -> {target})"
            if t_layer > s_layer:
                bad.append(f"{where}: {LAYERS[t_layer]} is above {LAYERS[s_layer]}")
            elif t_layer == s_layer == LAYERS.index("stages") and t_stage != s_stage:
                if t_stage > s_stage:  # mi_shadowgs.stages itself (99) lists them all
                    bad.append(f"{where}: a later stage")
                elif any(n.startswith("_") for n in names):
                    bad.append(f"{where}: a private name of another stage")
    assert not bad, "\n".join(bad)


def test_the_checker_sees_a_violation(tmp_path):
    """A test that cannot fail is a defect: the rules flag a planted bad import."""
    assert layer("mi_shadowgs.core.shading") < layer("mi_shadowgs.stages.visibility.x")
    assert layer("mi_shadowgs.stages.material.fit") > layer("mi_shadowgs.stages.visibility")
    assert layer("mi_shadowgs.stages.geometry.train") < layer("mi_shadowgs.stages.relight.x")
    assert layer("mi_shadowgs.cli.run")[0] == len(LAYERS) - 1
