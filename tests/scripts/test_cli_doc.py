"""docs/cli.md is what scripts/cli_doc.py makes from the command-line parsers."""

from __future__ import annotations

import importlib.util

from tests.conftest import ROOT


def _cli_doc():
    spec = importlib.util.spec_from_file_location("cli_doc", ROOT / "scripts" / "cli_doc.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cli_page_matches_the_parsers() -> None:
    page = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert page == _cli_doc().render(), "docs/cli.md is out of date: run python scripts/cli_doc.py"


def test_every_option_of_calibrate_is_on_the_page() -> None:
    from blurcalib.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    page = _cli_doc().render()
    section = page.split("## `blurcalib calibrate`")[1].split("\n## ")[0]
    flags = [s for a in sub.choices["calibrate"]._actions for s in a.option_strings if s.startswith("--")]
    missing = [f for f in flags if f != "--help" and f"`{f}" not in section]
    assert not missing and len(flags) > 20, missing
