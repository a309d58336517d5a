"""The package's shipped data: the reference pattern YAMLs, their licence, and their packaging."""

from __future__ import annotations

import fnmatch
from pathlib import Path

import pytest

from blurcalib.data import PATTERNS_DIR, REFERENCE_PATTERNS, reference_pattern_path
from blurcalib.target.pattern import load_pattern
from tests.conftest import ROOT


@pytest.mark.parametrize("name", REFERENCE_PATTERNS)
def test_reference_patterns_load(name: str) -> None:
    pattern = load_pattern(reference_pattern_path(name))
    assert pattern.num_star_segments == 16 and len(pattern.apriltags) == 1


def test_unknown_pattern_is_refused() -> None:
    with pytest.raises(ValueError, match="not a shipped reference pattern"):
        reference_pattern_path("pattern.yaml")


def test_licence_ships_beside_the_patterns() -> None:
    text = (PATTERNS_DIR / "LICENSE").read_text(encoding="utf-8")
    assert "Copyright 2019 ETH Zürich, Thomas Schöps" in text and "Redistribution and use" in text


def test_pyproject_declares_every_shipped_file() -> None:
    tomllib = pytest.importorskip("tomllib")
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    globs = config["tool"]["setuptools"]["package-data"]["blurcalib.data"]
    shipped = sorted(p.relative_to(PATTERNS_DIR.parent).as_posix() for p in PATTERNS_DIR.iterdir())
    assert len(shipped) == len(REFERENCE_PATTERNS) + 1
    for rel in shipped:
        assert any(fnmatch.fnmatch(rel, g) for g in globs), rel


def test_shipped_patterns_equal_the_reference_fixtures(shared_fixtures: Path) -> None:
    for name in REFERENCE_PATTERNS:
        assert reference_pattern_path(name).read_bytes() == (shared_fixtures / "schops" / name).read_bytes()
