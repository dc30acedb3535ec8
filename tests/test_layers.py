"""The import layers of mi_shadowgs go one way (see README "Layout").

Every import in the package (module level or inside a function) is read with ``ast``:
- no module imports a ``mi_shadowgs.cli`` module except the CLI package itself (the entry
  point ``mi_shadowgs.cli:main`` and its ``__main__``); ``validation/`` and ``benchmarks/``
  do not either;
- layers, bottom to top: base (``config``, ``libllvm``, ``backend``) < ``core`` < ``io`` <
  ``dataset`` < ``stages`` < ``pipeline`` < ``api`` / ``plugins`` / ``batch`` < ``cli``; a
  module imports only its own layer or lower ones;
- stages in the method's order (geometry < segmentation < visibility < material < relight):
  a stage imports earlier stages (never a private ``_name`` of theirs) and never a later one.

The checkers (``layer_violations``, ``cli_violations``) read module text, so that planted
bad imports show that they report what they should.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "mi_shadowgs"
LAYERS = ["base", "core", "io", "dataset", "stages", "pipeline", "api", "cli"]
STAGES = ["common", "render", "geometry", "segmentation", "visibility", "material", "relight",
          "evaluation", "export", "viewer"]
# (importer, imported) pairs exempt from the layers: none.
ALLOWED: set[tuple[str, str]] = set()


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(mod: str) -> tuple[int, int]:
    """(layer, stage order) of a mi_shadowgs module."""
    parts = mod.split(".")
    top = parts[1] if len(parts) > 1 else "base"
    if top in ("config", "libllvm", "backend", "scenes"):
        return 0, 0
    if top in ("presets", "summary"):  # the run's settings tree and report: beside pipeline
        return LAYERS.index("pipeline"), 0
    if top in ("plugins", "batch"):  # batch: runs of the whole method, as Ray tasks
        return LAYERS.index("api"), 0
    if top == "stages":
        return LAYERS.index("stages"), STAGES.index(parts[2]) if len(parts) > 2 else 99
    return LAYERS.index(top), 0


def imports(path: Path) -> list[tuple[str, list[str], int]]:
    """(absolute module, imported names, line) of every mi_shadowgs import in ``path``."""
    return imports_in(path.read_text(), module_name(path), path.name == "__init__.py")


def imports_in(source: str, mod: str, is_package: bool = False
               ) -> list[tuple[str, list[str], int]]:
    """The same for the text ``source`` of module ``mod``."""
    pkg = mod if is_package else mod.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = pkg.split(".")[:len(pkg.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            if base.split(".")[0] != "mi_shadowgs":
                continue
            for alias in node.names:  # `from pkg import submodule` names the submodule
                sub = f"{base}.{alias.name}"
                is_mod = ((ROOT / Path(*sub.split("."))).with_suffix(".py").is_file() or
                          (ROOT / Path(*sub.split("."))).is_dir())
                out.append((sub if is_mod else base, [alias.name], node.lineno))
        elif isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names
                    if a.name.split(".")[0] == "mi_shadowgs"]
    return out


def module_level_imports(source: str, mod: str, is_package: bool = False) -> set[str]:
    """The mi_shadowgs modules that ``source`` (module ``mod``) imports when it is imported:
    its imports outside functions and classes (at the top, or under a top-level ``if`` or
    ``try``), ``if TYPE_CHECKING:`` blocks left out."""
    tree = ast.parse(source)
    body, top = list(tree.body), []
    while body:
        node = body.pop(0)
        if isinstance(node, ast.Import | ast.ImportFrom):
            top.append(node)
        elif isinstance(node, ast.If) and not (isinstance(node.test, ast.Name)
                                               and node.test.id == "TYPE_CHECKING"):
            body += node.body + node.orelse
        elif isinstance(node, ast.Try):
            body += node.body + node.orelse + node.finalbody
            for handler in node.handlers:
                body += handler.body
    text = ast.unparse(ast.Module(body=top, type_ignores=[]))
    return {target for target, _, _ in imports_in(text, mod, is_package)} - {mod}


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The cycles of a module import graph (module -> modules it imports): each strongly
    connected component of more than one module, sorted (Tarjan's algorithm)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def cli_violations(mod: str, source: str, is_package: bool = False) -> list[str]:
    """Imports of a ``mi_shadowgs.cli`` module in ``source`` (module ``mod``)."""
    if mod == "mi_shadowgs.cli" or mod.startswith("mi_shadowgs.cli."):
        return []
    return [f"{mod}:{line} imports {target}"
            for target, _, line in imports_in(source, mod, is_package)
            if target == "mi_shadowgs.cli" or target.startswith("mi_shadowgs.cli.")]


def layer_violations(mod: str, source: str, is_package: bool = False) -> list[str]:
    """Imports in ``source`` (module ``mod`` of the package) that climb a layer or a stage."""
    if mod == "mi_shadowgs":
        return []
    bad = []
    s_layer, s_stage = layer(mod)
    for target, names, line in imports_in(source, mod, is_package):
        if (target == "mi_shadowgs" or (mod, target) in ALLOWED or
                any(target.startswith(a + ".") for s, a in ALLOWED if s == mod)):
            continue
        t_layer, t_stage = layer(target)
        where = f"{mod}:{line} ({mod} -> {target})"
        if t_layer > s_layer:
            bad.append(f"{where}: {LAYERS[t_layer]} is above {LAYERS[s_layer]}")
        elif t_layer == s_layer == LAYERS.index("stages") and t_stage != s_stage:
            if t_stage > s_stage:  # mi_shadowgs.stages itself (99) lists them all
                bad.append(f"{where}: a later stage")
            elif any(n.startswith("_") for n in names):
                bad.append(f"{where}: a private name of another stage")
    return bad


def package_files():
    return [p for p in PKG.rglob("*.py") if "__pycache__" not in p.parts]


def _checked(path: Path, check) -> list[str]:
    return check(module_name(path), path.read_text(), path.name == "__init__.py")


def test_only_the_entry_point_imports_a_cli_module():
    files = package_files() + [p for d in ("validation", "benchmarks")
                               for p in (ROOT / d).rglob("*.py")]
    bad = [b for path in files for b in _checked(path, cli_violations)]
    assert not bad, "\n".join(bad)


def test_layers_go_one_way():
    bad = [b for path in package_files() for b in _checked(path, layer_violations)]
    assert not bad, "\n".join(bad)


def test_no_import_cycle():
    """Importing any module of the package imports a tree of modules, not a loop (imports
    inside functions are lazy and left out)."""
    graph = {module_name(p): module_level_imports(p.read_text(), module_name(p),
                                                  p.name == "__init__.py")
             for p in package_files()}
    cycles = import_cycles(graph)
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


def test_the_cycle_checker_finds_a_planted_loop():
    a = module_level_imports("from mi_shadowgs.core import raster_tiles\n",
                             "mi_shadowgs.core.raster")
    b = module_level_imports("import drjit\nfrom mi_shadowgs.core.raster import x\n"
                             "def f():\n    from mi_shadowgs.core import shading\n",
                             "mi_shadowgs.core.raster_tiles")
    assert a == {"mi_shadowgs.core.raster_tiles"} and b == {"mi_shadowgs.core.raster"}
    assert (import_cycles({"mi_shadowgs.core.raster": a, "mi_shadowgs.core.raster_tiles": b})
            == [["mi_shadowgs.core.raster", "mi_shadowgs.core.raster_tiles"]])
    assert import_cycles({"x": {"y"}, "y": {"z"}}) == []


def test_the_layer_order():
    assert layer("mi_shadowgs.core.shading") < layer("mi_shadowgs.stages.visibility.x")
    assert layer("mi_shadowgs.stages.material.fit") > layer("mi_shadowgs.stages.visibility")
    assert layer("mi_shadowgs.stages.geometry.train") < layer("mi_shadowgs.stages.relight.x")
    assert layer("mi_shadowgs.cli.run")[0] == len(LAYERS) - 1


# Planted modules: (module, text, what the checker must report; "" = nothing).
PLANTED = [
    # A later stage, at module level, inside a function, and relative.
    ("mi_shadowgs.stages.geometry.train",
     "from mi_shadowgs.stages.material.fit import fit_material\n", "a later stage"),
    ("mi_shadowgs.stages.segmentation.features",
     "def f():\n    from mi_shadowgs.stages.relight import render\n", "a later stage"),
    ("mi_shadowgs.stages.geometry.train", "from ..material import fit\n", "a later stage"),
    ("mi_shadowgs.stages.material.fit",
     "from mi_shadowgs.stages.geometry.train import _private\n", "a private name"),
    # A higher layer.
    ("mi_shadowgs.core.shading", "import mi_shadowgs.stages.visibility.shadow_maps\n",
     "stages is above core"),
    ("mi_shadowgs.io.ply", "from mi_shadowgs import pipeline\n", "pipeline is above io"),
    ("mi_shadowgs.pipeline", "from mi_shadowgs.cli import run\n", "cli is above pipeline"),
    # The backend does not register the plugins (they register when asked).
    ("mi_shadowgs.backend", "from mi_shadowgs import plugins\n", "api is above base"),
    # Allowed: lower layers, earlier stages' public names.
    ("mi_shadowgs.stages.material.fit",
     "from mi_shadowgs.core import brdf\nfrom mi_shadowgs.stages.visibility import "
     "shadow_maps\nimport numpy\n", ""),
]


def test_the_layer_checker_reports_a_planted_bad_import():
    """A checker that cannot fail is a defect: module texts with a bad import are reported,
    and good ones are not."""
    for mod, text, expected in PLANTED:
        found = layer_violations(mod, text)
        if expected:
            assert len(found) == 1 and expected in found[0], (mod, text, found)
        else:
            assert found == [], (mod, text, found)


def test_the_cli_checker_reports_a_planted_cli_import():
    for mod in ("mi_shadowgs.pipeline", "mi_shadowgs.api", "validation.geometry",
                "benchmarks.bm_raster"):
        for text in ("from mi_shadowgs.cli import train\n", "import mi_shadowgs.cli.run\n",
                     "def f():\n    from mi_shadowgs.cli.run import main\n"):
            assert len(cli_violations(mod, text)) == 1, (mod, text)
        assert cli_violations(mod, "from mi_shadowgs.stages import geometry\n") == []
    # The entry point's package may.
    assert cli_violations("mi_shadowgs.cli.main", "from mi_shadowgs.cli import run\n") == []
