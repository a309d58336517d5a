"""Quality filtering from saved block figures."""

from __future__ import annotations

import numpy as np

from blurcalib.quality import QualitySettings, filter_frame
from blurcalib.results import BlockStatus


def _grid(n: int = 7):
    fy, fx = np.mgrid[0:n, 0:n]
    fx, fy = fx.ravel(), fy.ravel()
    centre = np.stack([100.0 + 30 * fx, 60.0 + 30 * fy], axis=1)
    status = np.array([BlockStatus.ACCEPTED.value] * len(fx), dtype=object)
    loss = np.full(len(fx), 10.0)
    be = np.full(len(fx), 0.05)
    sigma = np.full(len(fx), 5.0)
    return fx, fy, centre, status, loss, be, sigma


def test_thresholds_then_connectivity() -> None:
    fx, fy, centre, status, loss, be, sigma = _grid()
    size = (2 * 100 + 30 * 6, 2 * 60 + 30 * 6)
    # A wall of high-BE blocks in column 5 cuts off column 6; one high-loss block elsewhere.
    be[fx == 5] = 0.2
    loss[(fx == 1) & (fy == 1)] = 50.0
    status[(fx == 0) & (fy == 0)] = BlockStatus.HIGH_LOSS.value
    res = filter_frame(fx, fy, centre, status, loss, be, sigma, size)
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
    loose = filter_frame(fx, fy, centre, status, loss, be, sigma, size,
                         QualitySettings(tau_be=0.3, tau_loss=100.0))
    assert loose.kept.sum() == 7 * 7 - 1


def test_frame_prefilter_on_blur() -> None:
    fx, fy, centre, status, loss, be, sigma = _grid()
    size = (380, 300)
    paper = QualitySettings(min_sigma_major=3.8)
    assert filter_frame(fx, fy, centre, status, loss, be, sigma, size, paper).frame_ok
    low = filter_frame(fx, fy, centre, status, loss, be, np.full(len(fx), 2.0), size, paper)
    assert not low.frame_ok and low.centre_sigma_major == 2.0
    default = filter_frame(fx, fy, centre, status, loss, be, np.full(len(fx), 2.0), size)
    assert default.frame_ok and default.kept.sum() == low.kept.sum()


def test_nothing_survives() -> None:
    fx, fy, centre, status, _, be, sigma = _grid(3)
    res = filter_frame(fx, fy, centre, status, np.full(9, 99.0), be, sigma, (200, 200))
    assert res.seed == -1 and not res.kept.any()
    assert res.counts() == {BlockStatus.FILTERED_LOSS.value: 9}
