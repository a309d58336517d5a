"""Shared fixtures: paths to the reference fixtures in ``../shared`` beside the checkout."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared" / "fixtures"
SCHOPS = SHARED / "schops"
REAL = SHARED / "real_star16"
FIXTURE_YAML = SCHOPS / "pattern_resolution_17x24_segments_16_apriltag_0.yaml"
FIXTURE_PNG = SCHOPS / "pattern_resolution_17x24_segments_16_apriltag_0.png"


@pytest.fixture(scope="session")
def shared_fixtures() -> Path:
    """The ``shared/fixtures`` folder; tests that need it are skipped loudly if it is absent."""
    if not SHARED.is_dir():
        pytest.fail(f"shared fixtures not found at {SHARED}: clone with ../shared beside it")
    return SHARED
