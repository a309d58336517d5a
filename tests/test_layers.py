"""The engine's sub-packages import each other in one direction only: the pipeline's order.

Each sub-package of ``blurcalib`` may import the sub-packages listed before it in
:data:`LAYERS`, never one after it; the engine never imports the app (``state``, ``views``,
``app``). A new sub-package must be placed in the list.
"""

from __future__ import annotations

import ast
from pathlib import Path

ENGINE = Path(__file__).resolve().parents[1] / "blurcalib"

LAYERS: tuple[str, ...] = (
    "geometry", "optim", "psf", "io", "target", "camera", "deconv", "growth", "extract", "runs", "calib",
    "pipeline", "sim", "paper", "data", "argtypes", "cli", "__main__",
)
"""Sub-packages (and top-level modules) of ``blurcalib``, lowest first."""

APP = ("state", "views", "app")


def imports(path: Path) -> set[str]:
    """The absolute modules a source file imports (``from X import ...`` and ``import X``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return found


def package_of(path: Path) -> str:
    """The sub-package (or top-level module) of ``blurcalib`` a file belongs to."""
    parts = path.relative_to(ENGINE).with_suffix("").parts
    return parts[0]


def edges() -> dict[tuple[str, str], list[str]]:
    """``(importer, imported)`` sub-package pairs, each with the files that import across."""
    out: dict[tuple[str, str], list[str]] = {}
    for path in sorted(ENGINE.rglob("*.py")):
        here = package_of(path)
        for module in imports(path):
            parts = module.split(".")
            if parts[0] in APP:
                out.setdefault((here, parts[0]), []).append(str(path.relative_to(ENGINE)))
            elif parts[0] == "blurcalib" and len(parts) > 1 and parts[1] != here:
                out.setdefault((here, parts[1]), []).append(str(path.relative_to(ENGINE)))
    return out


def test_every_sub_package_has_a_layer() -> None:
    found = {package_of(p) for p in ENGINE.rglob("*.py")} - {"__init__"}
    assert found <= set(LAYERS), f"place these in LAYERS: {sorted(found - set(LAYERS))}"


def test_sub_packages_import_only_lower_layers() -> None:
    rank = {name: i for i, name in enumerate(LAYERS)}
    upward = {f"{a} -> {b}": files for (a, b), files in edges().items()
              if b in APP or rank.get(b, -1) >= rank.get(a, len(LAYERS))}
    assert not upward, f"imports against the pipeline's order: {upward}"


def test_the_check_sees_an_upward_import(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text("from blurcalib.calib.sharp import calibrate_sharp\nimport state.app_state\n")
    assert imports(source) == {"blurcalib.calib.sharp", "state.app_state"}
