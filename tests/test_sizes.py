"""The code stays readable in pieces: no module of ``blurcalib``, the app's ``state`` and ``views`` or
``app.py`` over 600 lines, no function over 100.

A function's length counts from its ``def`` (decorators excluded) to its last line, docstring and
nested functions included; a nested function is also checked on its own.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENGINE = ROOT / "blurcalib"
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 100


def oversized(path: Path) -> list[str]:
    """``file: N lines`` and ``file:line name: N lines`` for the module and each function of
    ``path`` over the limits."""
    source = path.read_text(encoding="utf-8")
    found = []
    lines = len(source.splitlines())
    if lines > MAX_MODULE_LINES:
        found.append(f"{path.name}: {lines} lines")
    for node in ast.walk(ast.parse(source, str(path))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = (node.end_lineno or node.lineno) - node.lineno + 1
            if length > MAX_FUNCTION_LINES:
                found.append(f"{path.name}:{node.lineno} {node.name}: {length} lines")
    return found


def test_no_engine_module_or_function_is_over_the_limit() -> None:
    paths = sorted(ENGINE.rglob("*.py"))
    found = {str(p.relative_to(ENGINE)): oversized(p) for p in paths}
    assert len(paths) > 100
    assert not any(found.values()), {k: v for k, v in found.items() if v}


def test_no_app_module_or_function_is_over_the_limit() -> None:
    paths = sorted([*(ROOT / "state").glob("*.py"), *(ROOT / "views").glob("*.py"), ROOT / "app.py"])
    found = {str(p.relative_to(ROOT)): oversized(p) for p in paths}
    assert len(paths) > 15
    assert not any(found.values()), {k: v for k, v in found.items() if v}


def test_the_check_sees_a_long_module_and_a_long_function(tmp_path: Path) -> None:
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES))
    long_function = tmp_path / "f.py"
    long_function.write_text(f"def f():\n{body}    return 0\n")
    assert oversized(long_function) == [f"f.py:1 f: {MAX_FUNCTION_LINES + 2} lines"]
    fits = tmp_path / "g.py"
    fits.write_text("def g():\n" + "".join(body.splitlines(keepends=True)[:MAX_FUNCTION_LINES - 1]))
    assert oversized(fits) == []
    long_module = tmp_path / "m.py"
    long_module.write_text("x = 0\n" * (MAX_MODULE_LINES + 1))
    assert oversized(long_module) == [f"m.py: {MAX_MODULE_LINES + 1} lines"]
