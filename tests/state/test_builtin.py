"""The app's built-in dataset does the app's jobs: at the default thresholds the loss filter
removes the blocks on the glare's edge and τ_L raised keeps them; the frame whose tag is hidden
is not seeded alone, its tag search is shown, and it is seeded from its neighbours in a run of
the pass; the sliders span the frames' own figures."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from blurcalib.io.record import FrameStatus
from blurcalib.io.results import BlockStatus
from state import AppState
from state.blocks import effective_loss, filter_counts, filter_ranges
from state.folder import default_dataset
from state.seeding import TagSearchCache

pytestmark = pytest.mark.slow

GLARE, HIDDEN = "blurry/01-glare.png", "blurry/04-tag-hidden.png"


@pytest.fixture(scope="module")
def builtin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The built-in dataset, rendered once (about 40 s of CPU)."""
    return default_dataset(tmp_path_factory.mktemp("builtin") / "data", workers=2)


def _open(folder: Path, out: Path) -> AppState:
    state = AppState()
    assert state.load_folder(folder, None, out)
    return state


def _run(state: AppState, name: str) -> None:
    index = [e.name for e in state.entries()].index(name)
    assert state.select_frame(index) and state.run_frame(index) and state.wait(900)


def test_the_loss_filter_removes_the_glare_edge(builtin: Path, tmp_path: Path) -> None:
    state = _open(builtin, tmp_path / "out")
    assert len(state.entries()) >= 12 and state.dataset.faults[GLARE].what.startswith("glare")
    _run(state, GLARE)
    view = state.view()
    blocks, flt = view.result.blocks, view.filter
    glare = np.isin(blocks.feature_id, state.dataset.faults[GLARE].features[0])
    removed = glare & (flt.status.astype(str) == BlockStatus.FILTERED_LOSS.value)
    assert removed.sum() >= 3  # on the glare's edge: loss above τ_L, below the growth's limit
    clean = ~glare & blocks.accepted
    assert flt.kept[clean].mean() > 0.95  # elsewhere nearly every accepted block stays
    state.refilter(tau_loss=400.0)
    assert state.view().filter.kept[removed].all()
    state.refilter(tau_loss=30.0)
    counts = filter_counts(state.view().filter, blocks.status)
    assert counts.removed_loss == int(removed.sum()) and counts.not_fitted > 0
    ranges = filter_ranges([(blocks, flt)], state.quality)
    assert ranges.tau_loss.log and ranges.tau_loss.lo < 5.0  # the slider moves τ_L on the filter's scale:
    assert ranges.tau_loss.hi >= float(np.max(effective_loss(blocks, state.quality)[removed]))


def test_the_hidden_tag_frame_is_seeded_from_its_neighbours(builtin: Path, tmp_path: Path) -> None:
    state = _open(builtin, tmp_path / "out")
    _run(state, HIDDEN)  # alone: no neighbour extracted yet
    entry = next(e for e in state.entries() if e.name == HIDDEN)
    assert entry.record.status is FrameStatus.NOT_SEEDED
    search = TagSearchCache(state).search(HIDDEN)
    pattern_tags = {t.index for t in state.dataset.pattern.apriltags}
    assert search is not None and not pattern_tags & search.found.keys() and len(search.rejected) > 0
    assert state.run_all() and state.wait(3600)
    entry = next(e for e in state.entries() if e.name == HIDDEN)
    assert entry.record.status is FrameStatus.OK and entry.record.seeded_by == "neighbour"
    sigma = [f.centre_sigma_major for _, f, _ in state.results().values()
             if f is not None and math.isfinite(f.centre_sigma_major)]
    ranges = filter_ranges([(r.blocks, f) for r, f, _ in state.results().values()], state.quality)
    assert ranges.sigma.hi >= max(sigma) > 3.0  # the heavy blur's frame stands out on the slider
