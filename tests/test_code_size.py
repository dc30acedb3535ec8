"""Files a reader can hold in mind: no module of the package over ``MAX_MODULE_LINES``
lines and no function over ``MAX_FUNCTION_LINES`` (its ``def`` to its last line), and no
backslash line continuation."""

from __future__ import annotations

import ast
import io
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "mi_shadowgs"
MAX_MODULE_LINES = 700
MAX_FUNCTION_LINES = 100


def modules() -> list[Path]:
    return sorted(p for p in PKG.rglob("*.py") if "__pycache__" not in p.parts)


def long_functions(source: str, name: str) -> list[str]:
    """``name:line def f (N lines)`` for each function of ``source`` over the limit."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            lines = node.end_lineno - node.lineno + 1
            if lines > MAX_FUNCTION_LINES:
                out.append(f"{name}:{node.lineno} def {node.name} ({lines} lines)")
    return out


def continuations(source: str, name: str) -> list[str]:
    """``name:line`` of each backslash continuation outside strings and comments."""
    lines = source.splitlines()
    inside = set()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.STRING:
            inside.update(range(tok.start[0], tok.end[0]))
    return [f"{name}:{i}" for i, line in enumerate(lines, 1)
            if line.rstrip().endswith("\\") and i not in inside
            and not line.lstrip().startswith("#")]


def test_no_module_is_too_long():
    long = [f"{p.relative_to(ROOT)} ({n} lines)" for p in modules()
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES]
    assert not long, "split by job: " + ", ".join(long)


def test_no_function_is_too_long():
    long = [f for p in modules() for f in long_functions(p.read_text(),
                                                         str(p.relative_to(ROOT)))]
    assert not long, "\n".join(long)


def test_no_backslash_continuations():
    found = [c for p in modules() for c in continuations(p.read_text(),
                                                         str(p.relative_to(ROOT)))]
    assert not found, "use parentheses: " + ", ".join(found)


def test_the_checks_report_a_planted_case():
    body = "\n".join(f"    x = {i}" for i in range(MAX_FUNCTION_LINES))
    assert long_functions(f"def f():\n{body}\n", "m.py") == [
        f"m.py:1 def f ({MAX_FUNCTION_LINES + 1} lines)"]
    assert long_functions("def f():\n    return 1\n", "m.py") == []
    assert continuations("x = 1 + \\\n    2\n", "m.py") == ["m.py:1"]
    assert continuations('s = """a \\\nb"""\n', "m.py") == []
