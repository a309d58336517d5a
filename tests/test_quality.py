"""Quality filtering from saved block figures."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from blurcalib.camera import translation
from blurcalib.quality import QualitySettings, connected_blocks, filter_frame
from blurcalib.results import BlockStatus, BlockTable


def _grid(n: int = 7) -> BlockTable:
    """``n x n`` accepted blocks 30 px apart, loss 10, boundary energy 0.05, sigma_major 5 px."""
    fy, fx = np.mgrid[0:n, 0:n]
    fx, fy = fx.ravel(), fy.ravel()
    b = len(fx)
    centre = np.stack([100.0 + 30 * fx, 60.0 + 30 * fy], axis=1)
    return BlockTable(["f"] * b, np.arange(b), fx, fy, [BlockStatus.ACCEPTED.value] * b, np.full(b, 10.0),
                      np.full(b, 0.05), np.full(b, 5.0), np.full(b, 1.0), np.zeros(b), np.zeros(b),
                      np.zeros((b, 2)), translation(centre), np.zeros((b, 6)), np.zeros((b, 3, 3)))


def test_thresholds_then_connectivity() -> None:
    t = _grid()
    fx, fy = t.fx, t.fy
    size = (2 * 100 + 30 * 6, 2 * 60 + 30 * 6)
    # A wall of high-BE blocks in column 5 cuts off column 6; one high-loss block elsewhere.
    t.boundary_energy[fx == 5] = 0.2
    t.loss[(fx == 1) & (fy == 1)] = 50.0
    status = t.status.astype(object)
    status[(fx == 0) & (fy == 0)] = BlockStatus.HIGH_LOSS.value
    t = replace(t, status=status)
    res = filter_frame(t, size)
    def at(x, y):
        return res.status[np.flatnonzero((fx == x) & (fy == y))[0]]
    assert at(5, 3) == BlockStatus.FILTERED_BOUNDARY_ENERGY.value
    assert at(1, 1) == BlockStatus.FILTERED_LOSS.value
    assert at(6, 3) == BlockStatus.DISCONNECTED.value
    assert at(0, 0) == BlockStatus.HIGH_LOSS.value
    assert at(3, 3) == BlockStatus.ACCEPTED.value
    assert res.kept.sum() == 7 * 5 - 2  # columns 0..4 minus (0,0) and (1,1)
    assert np.array_equal(res.kept, res.status == BlockStatus.ACCEPTED.value)
    # Looser thresholds keep more.
    loose = filter_frame(t, size, QualitySettings(tau_be=0.3, tau_loss=100.0))
    assert loose.kept.sum() == 7 * 7 - 1


def test_frame_prefilter_on_blur() -> None:
    t = _grid()
    size = (380, 300)
    paper = QualitySettings(min_sigma_major=3.8)
    assert filter_frame(t, size, paper).frame_ok
    little_blur = replace(t, sigma_major=np.full(len(t), 2.0))
    low = filter_frame(little_blur, size, paper)
    assert not low.frame_ok and low.centre_sigma_major == 2.0
    default = filter_frame(little_blur, size)
    assert default.frame_ok and default.kept.sum() == low.kept.sum()


def test_nothing_survives() -> None:
    t = _grid(3)
    res = filter_frame(replace(t, loss=np.full(9, 99.0)), (200, 200))
    assert res.seed == -1 and not res.kept.any()
    assert res.counts() == {BlockStatus.FILTERED_LOSS.value: 9}


def test_degenerate_homography_has_no_centre() -> None:
    t = _grid(2)
    t.H[1, 2, 2] = 0.0
    assert np.isnan(t.centre[1]).all() and np.array_equal(t.centre[0], [100.0, 60.0])


def test_connected_blocks_from_several_seeds() -> None:
    """Two islands of allowed blocks on a row: each seed reaches its own island only, a block
    that is not allowed is never reached, and two seeds reach both islands."""
    fx = np.array([0, 1, 2, 3, 4, 5])
    fy = np.zeros(6, dtype=int)
    allowed = np.array([True, True, False, True, True, True])
    np.testing.assert_array_equal(connected_blocks(fx, fy, allowed, [0]), [1, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(connected_blocks(fx, fy, allowed, [5]), [0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(connected_blocks(fx, fy, allowed, [0, 4]), [1, 1, 0, 1, 1, 1])
