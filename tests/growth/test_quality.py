"""Quality filtering from saved block figures."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from blurcalib.deconv.blocks import fit_blocks
from blurcalib.geometry.homography import translation
from blurcalib.growth.noise import NoiseModel
from blurcalib.growth.quality import REFERENCE_NOISE_VAR, QualitySettings, connected_blocks, filter_frame
from blurcalib.io.results import BlockStatus, BlockTable
from blurcalib.sim.blocks import simulate_blocks
from blurcalib.target.pattern import layout_pattern


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


def test_the_largest_group_is_kept_not_an_island_at_the_centre() -> None:
    t = _grid()
    fx, fy = t.fx, t.fy
    size = (2 * 100 + 30 * 6, 2 * 60 + 30 * 6)
    # a ring of high-loss blocks around the centre block cuts it off; it has the lowest loss
    ring = (np.abs(fx - 3) <= 1) & (np.abs(fy - 3) <= 1) & ~((fx == 3) & (fy == 3))
    t.loss[ring] = 50.0
    t.loss[(fx == 3) & (fy == 3)] = 1.0
    res = filter_frame(t, size)
    centre = np.flatnonzero((fx == 3) & (fy == 3))[0]
    assert res.status[centre] == BlockStatus.DISCONNECTED.value
    assert res.kept.sum() == 7 * 7 - 9 and res.kept[res.seed] and res.seed != centre


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


def _poisson_frame(paper: float, ink: float, electrons: float, seed: int
                   ) -> tuple[BlockTable, tuple[int, int]]:
    """Nine blurred star blocks (4-8 px of blur) between ``ink`` and ``paper`` grey levels with
    shot noise of ``electrons`` per grey level and 0.5 grey levels of read noise, fitted, with
    the noise variances of that sensor (:class:`NoiseModel`); feature coordinates on a 3 x 3
    grid (the filter's connectivity)."""
    pattern = layout_pattern()
    rng = np.random.default_rng(seed)
    sim = simulate_blocks(pattern, 9, rng, blur_px=(4.0, 8.0), noise_sigma=0.0, supersample=4, tile_px=80,
                          init_shift_px=0.4, ink=ink, paper=paper, truth_kernel_size=13)
    clean = sim.image.astype(np.float64)
    noisy = rng.poisson(clean * electrons) / electrons + rng.normal(0.0, 0.5, clean.shape)
    image = np.clip(np.round(noisy), 0, 255).astype(np.float32)
    fit = fit_blocks(image, sim.H0, pattern.num_star_segments, 17)
    noise = NoiseModel(a=0.5**2 + 1.0 / 12.0, b=1.0 / electrons, level=(ink + paper) / 2)
    b = len(fit)
    fy, fx = np.divmod(np.arange(b), 3)
    table = BlockTable(["f"] * b, np.arange(b), fx, fy, [s.value for s in fit.status], fit.loss,
                       fit.boundary_energy, fit.sigma_major, fit.sigma_minor, fit.eccentricity,
                       fit.orientation, fit.centroid, fit.H, fit.coeffs, fit.psf, fit.loss_extent,
                       noise.block_variance(fit.coeffs))
    return table, (image.shape[1], image.shape[0])


def test_the_noise_relative_loss_threshold_keeps_bright_and_dark_frames_alike() -> None:
    """Blocks that fit (loss about the noise variance) are kept on a dark frame with little shot
    noise and on a bright one with much: the relative threshold keeps all of both, the paper's
    absolute 30 grey levels^2 drops the bright frame's (shot noise about 35 grey levels^2)."""
    dark, dark_size = _poisson_frame(paper=120.0, ink=15.0, electrons=20.0, seed=4)
    bright, bright_size = _poisson_frame(paper=250.0, ink=30.0, electrons=4.0, seed=4)
    assert dark.accepted.all() and bright.accepted.all()
    for t in (dark, bright):  # the losses are the noise's, plus little model error
        assert np.all((t.loss / t.noise_var > 0.8) & (t.loss / t.noise_var < 2.0))
    relative, absolute = QualitySettings(), QualitySettings(loss_mode="absolute")
    assert filter_frame(dark, dark_size, relative).kept.all()
    assert filter_frame(bright, bright_size, relative).kept.all()
    assert filter_frame(dark, dark_size, absolute).kept.all()
    assert filter_frame(bright, bright_size, absolute).kept.sum() <= 2


def test_loss_limit_grows_with_the_noise_above_the_reference() -> None:
    """``tau_L`` up to the reference noise (and where the noise is unknown), in proportion to the
    noise variance above it."""
    s = QualitySettings(tau_loss=30.0)
    limit = s.loss_limit(np.array([0.0, 1.0, REFERENCE_NOISE_VAR, 2 * REFERENCE_NOISE_VAR, np.nan]))
    assert np.allclose(limit, [30.0, 30.0, 30.0, 60.0, 30.0])
    assert np.allclose(QualitySettings(loss_mode="absolute").loss_limit(np.array([1.0, 40.0])), 30.0)
    with pytest.raises(ValueError, match="loss_mode"):
        QualitySettings(loss_mode="noise")  # type: ignore[arg-type]
