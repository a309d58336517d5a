"""Shared fixtures: the shipped reference pattern, and the reference fixtures (real frames, the
reference tool's PNG and features) found through ``BLURCALIB_FIXTURES``.

``BLURCALIB_FIXTURES`` defaults to ``../shared/fixtures`` beside the checkout. Tests that need
those files take the ``shared_fixtures`` fixture: they are skipped, with the reason, when the
folder is absent (a plain clone), and fail instead when ``BLURCALIB_REQUIRE_FIXTURES=1`` (CI).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from blurcalib.data import DEFAULT_PATTERN, reference_pattern_path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("BLURCALIB_FIXTURES") or ROOT.parent / "shared" / "fixtures")
SCHOPS = SHARED / "schops"
REAL = SHARED / "real_star16"
FIXTURE_YAML = reference_pattern_path(DEFAULT_PATTERN)
FIXTURE_PNG = SCHOPS / "pattern_resolution_17x24_segments_16_apriltag_0.png"


@pytest.fixture(scope="session")
def shared_fixtures() -> Path:
    """The reference fixtures folder; skips the test (fails it under CI's
    ``BLURCALIB_REQUIRE_FIXTURES=1``) when it is absent."""
    if not SHARED.is_dir():
        reason = f"reference fixtures not found at {SHARED} (set BLURCALIB_FIXTURES to their folder)"
        if os.environ.get("BLURCALIB_REQUIRE_FIXTURES") == "1":
            pytest.fail(reason)
        pytest.skip(reason)
    return SHARED


@pytest.fixture(scope="session", autouse=True)
def user_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The user's cache folder (``XDG_CACHE_HOME``) of the whole session: a temporary one, so that
    the app's results (:func:`state.folder.default_output_folder`) and built-in dataset never land
    in the real cache, nor come from an earlier session's."""
    with pytest.MonkeyPatch.context() as patch:
        cache = tmp_path_factory.mktemp("cache")
        patch.setenv("XDG_CACHE_HOME", str(cache))
        yield cache
