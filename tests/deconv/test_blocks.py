"""Local deconvolution of star blocks: recovery of known blocks, the translational ambiguity,
PSF re-centring, PSF figures, batching, and per-block flags for invalid input."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
import torch
from scipy.ndimage import convolve

from blurcalib.deconv import blocks, lm
from blurcalib.deconv.blocks import fit_blocks, fit_blocks_fixed, fit_blocks_hinted, render_model
from blurcalib.deconv.convolution import DIRECT_PER_FFT_POINT, fft_size, flushing_denormals
from blurcalib.deconv.latent import latent_pattern, update_homography
from blurcalib.deconv.problem import BlockProblem
from blurcalib.deconv.result import BlockFit
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.geometry.homography import translation
from blurcalib.io.results import BlockStatus
from blurcalib.psf.kernel import (
    boundary_energy,
    psf_centroid,
    psf_moments,
    recentre,
    resize_kernels,
    shift_pair,
)
from blurcalib.sim.blocks import SimulatedBlocks, simulate_blocks
from blurcalib.target.pattern import layout_pattern, star_signed_distance, star_signed_distance_normal

SEGMENTS = 16
K = 13
SETTINGS = DeconvSettings()


def _simulate(num: int, seed: int, **kw) -> SimulatedBlocks:
    opts = {"supersample": 4, "tile_px": 80, "blur_px": (3.0, 7.0)}
    opts.update(kw)
    return simulate_blocks(layout_pattern(), num, np.random.default_rng(seed), **opts)


def _centre_error(fit: BlockFit, sim: SimulatedBlocks) -> np.ndarray:
    return np.linalg.norm(fit.centre - sim.centre_true, axis=1)


def _centred_truth(psf_true: np.ndarray, K: int) -> np.ndarray:
    """The true kernels moved so that their centroids sit at the centre, cropped to ``K x K``."""
    _, centred, _ = recentre(np.broadcast_to(np.eye(3), (len(psf_true), 3, 3)), psf_true)
    c = (psf_true.shape[-1] - K) // 2
    return centred[:, c:c + K, c:c + K]


@pytest.fixture(scope="module")
def sim() -> SimulatedBlocks:
    return _simulate(6, seed=3)


@pytest.fixture(scope="module")
def fit(sim: SimulatedBlocks) -> BlockFit:
    return fit_blocks(sim.image, sim.H0, SEGMENTS, K, SETTINGS)


# ----------------------------------------------------------------------------------- recovery
def test_known_blocks_are_recovered(sim: SimulatedBlocks, fit: BlockFit) -> None:
    # H0 is off by up to 1.5 px and 3 % scale; blur 3-7 px, noise 2 grey levels
    err = _centre_error(fit, sim)
    assert err.max() < 0.05, err
    assert all(st is BlockStatus.ACCEPTED for st in fit.status)
    assert fit.converged.all()
    # noise is 2; sharp edges leave up to ~3.5 (the soft-edge model, tau = 0.25 px)
    assert np.all((fit.residual_rms > 1.8) & (fit.residual_rms < 4.0)), fit.residual_rms
    truth = _centred_truth(sim.psf_true, K)
    a = fit.psf - fit.psf.mean(axis=(1, 2), keepdims=True)
    b = truth - truth.mean(axis=(1, 2), keepdims=True)
    ncc = (a * b).sum(axis=(1, 2)) / np.sqrt((a * a).sum(axis=(1, 2)) * (b * b).sum(axis=(1, 2)))
    assert ncc.min() > 0.9, ncc
    # gain ~170 and offset ~30 grey levels (after the blur, the default order)
    assert np.all(np.abs(fit.coeffs[:, 2] - 170.0) < 20.0) and np.all(np.abs(fit.coeffs[:, 5] - 30.0) < 10.0)


def test_result_arrays_are_consistent(fit: BlockFit) -> None:
    assert fit.H.shape == (6, 3, 3) and fit.psf.shape == (6, K, K) and fit.coeffs.shape == (6, 6)
    np.testing.assert_allclose(fit.H[:, 2, 2], 1.0)
    np.testing.assert_allclose(fit.psf.sum(axis=(1, 2)), 1.0, atol=1e-9)
    np.testing.assert_allclose(fit.psf_fit.sum(axis=(1, 2)), 1.0, atol=1e-9)
    assert fit.psf.min() >= 0.0 and fit.psf_fit.min() >= 0.0
    np.testing.assert_allclose(fit.H, translation(fit.centroid) @ fit.H_fit, atol=1e-9)
    np.testing.assert_allclose(fit.centroid, psf_centroid(fit.psf_fit), atol=1e-9)
    np.testing.assert_allclose(fit.residual_rms ** 2, fit.loss)
    assert np.all(fit.num_pixels == [m.sum() for m in fit.masks])


def test_render_model_reproduces_the_loss(sim: SimulatedBlocks) -> None:
    fit = fit_blocks(sim.image, sim.H0[:2], SEGMENTS, K, SETTINGS)
    for i in range(2):
        shown = render_model(fit, sim.image, i)
        shape = tuple(fit.window_size[i][::-1])
        assert shown.model.shape == shown.observed.shape == shown.mask.shape == shape
        x0, y0 = shown.origin
        h, w = shown.observed.shape
        np.testing.assert_array_equal(shown.observed, sim.image[y0:y0 + h, x0:x0 + w])
        assert np.mean(shown.residual[shown.mask] ** 2) == pytest.approx(fit.loss[i], rel=1e-4)
    assert _centre_error(fit, dataclasses.replace(sim, centre_true=sim.centre_true[:2])).max() < 0.05


@pytest.mark.parametrize("kernel_size", [3, 7])
def test_small_kernels_for_nearly_sharp_frames(kernel_size: int) -> None:
    sim = _simulate(3, seed=9, blur_px=(0.5, 2.0))
    fit = fit_blocks(sim.image, sim.H0, SEGMENTS, kernel_size)
    assert fit.psf.shape == (3, kernel_size, kernel_size)
    assert all(st is BlockStatus.ACCEPTED for st in fit.status)
    assert _centre_error(fit, sim).max() < 0.05


# ---------------------------------------------------------------------- translational ambiguity
def test_shift_pair_leaves_the_blurred_image_unchanged() -> None:
    rng = np.random.default_rng(0)
    latent = rng.uniform(size=(40, 50))
    kernel = np.zeros((9, 9))
    kernel[3:6, 2:7] = rng.uniform(size=(3, 5))
    for delta in [(1, 0), (-2, 1), (2, -3)]:
        shifted_latent, shifted_kernel = shift_pair(latent, kernel, delta)
        np.testing.assert_allclose(convolve(shifted_latent, shifted_kernel, mode="wrap"),
                                   convolve(latent, kernel, mode="wrap"), atol=1e-12)
        # the kernel's centroid moved by -delta, the latent by +delta
        np.testing.assert_allclose(psf_centroid(shifted_kernel), psf_centroid(kernel) - np.array(delta))
    with pytest.raises(ValueError, match="out of the 9 x 9 window"):
        shift_pair(latent, kernel, (4, 0))


def test_shifted_start_gives_the_same_recentred_centre(sim: SimulatedBlocks, fit: BlockFit) -> None:
    # a shift of the initial H by (2, -1) px is absorbed by the kernel, and the re-centring brings
    # both fits to the same star centre and PSF; what differs is the optimisation path (kernel
    # support, LM steps), measured at <= 0.025 px over three seeds
    H0 = translation(np.array([2.0, -1.0])) @ sim.H0[:3]
    moved = fit_blocks(sim.image, H0, SEGMENTS, K, SETTINGS)
    assert np.abs(moved.centre - fit.centre[:3]).max() < 0.03
    assert np.abs(moved.psf - fit.psf[:3]).max() < 0.1 * fit.psf[:3].max()
    assert _centre_error(moved, dataclasses.replace(sim, centre_true=sim.centre_true[:3])).max() < 0.05


# ------------------------------------------------------------------------------------ recentring
def test_recentre_moves_centroid_and_homography_by_the_same_amount() -> None:
    psf = np.zeros((2, 15, 15))
    psf[0, 7, 3:9] = 1.0  # horizontal line, centroid (-1.5, 0)
    psf[1, 2:6, 9:11] = [[1.0, 2.0], [1.0, 2.0], [3.0, 1.0], [1.0, 1.0]]
    psf /= psf.sum(axis=(1, 2), keepdims=True)
    rng = np.random.default_rng(1)
    H = np.eye(3) + 0.01 * rng.normal(size=(2, 3, 3))
    H[:, :2, 2] = [[40.0, 30.0], [12.0, 55.0]]
    c = psf_centroid(psf)
    H2, psf2, c2 = recentre(H, psf)
    np.testing.assert_allclose(c2, c)
    np.testing.assert_allclose(psf_centroid(psf2), 0.0, atol=1e-12)
    np.testing.assert_allclose(psf2.sum(axis=(1, 2)), 1.0)
    assert psf2.min() >= 0.0
    np.testing.assert_allclose(H2, translation(c) @ H)
    # H(0, 0) moves by exactly the centroid
    np.testing.assert_allclose(H2[:, :2, 2] / H2[:, 2:, 2] - H[:, :2, 2] / H[:, 2:, 2], c, atol=1e-12)
    # single kernels work too
    H1, psf1, c1 = recentre(H[0], psf[0])
    np.testing.assert_allclose(H1, H2[0])
    np.testing.assert_allclose(psf1, psf2[0])
    np.testing.assert_allclose(c1, c[0])


# --------------------------------------------------------------------------------- PSF figures
def test_psf_figures_of_a_known_line_blur() -> None:
    length = 7
    line = np.zeros((21, 21))
    line[10, 10 - length // 2:10 + length // 2 + 1] = 1.0  # horizontal, 7 px
    sim = _simulate(3, seed=5, psf=line)
    fit = fit_blocks(sim.image, sim.H0, SEGMENTS, K, SETTINGS)
    assert _centre_error(fit, sim).max() < 0.05
    # a 7-px box has sigma sqrt((7^2 - 1) / 12) = 2 px; the fit also absorbs the pixel area
    assert np.all(np.abs(fit.sigma_major - 2.0) < 0.25), fit.sigma_major
    assert np.all(fit.sigma_minor < 0.7), fit.sigma_minor
    assert np.all(np.abs(np.sin(fit.orientation)) < 0.1), fit.orientation
    assert np.all(fit.eccentricity > 0.9)
    assert np.all(fit.boundary_energy < 0.02)
    mom = psf_moments(fit.psf_fit)
    np.testing.assert_allclose(fit.sigma_major, mom.sigma_major)
    np.testing.assert_allclose(fit.boundary_energy, boundary_energy(fit.psf_fit))


def test_boundary_energy_flags_a_kernel_reaching_the_border() -> None:
    long_line = np.zeros((21, 21))
    long_line[10, 1:20] = 1.0  # 19 px: longer than the 13 x 13 window
    sim = _simulate(2, seed=6, psf=long_line)
    fit = fit_blocks(sim.image, sim.H0, SEGMENTS, K, SETTINGS)
    assert np.all(fit.boundary_energy > 0.15), fit.boundary_energy


# ------------------------------------------------------------------------------------- batching
def test_batch_equals_one_by_one(sim: SimulatedBlocks, fit: BlockFit) -> None:
    for i in (0, 4):
        single = fit_blocks(sim.image, sim.H0[i:i + 1], SEGMENTS, K, SETTINGS)
        assert np.abs(single.centre[0] - fit.centre[i]).max() < 2e-3
        assert np.abs(single.psf[0] - fit.psf[i]).max() < 2e-3
        assert single.loss[0] == pytest.approx(fit.loss[i], rel=1e-2)
    small_batches = fit_blocks(sim.image, sim.H0, SEGMENTS, K, dataclasses.replace(SETTINGS, batch_size=4))
    assert np.abs(small_batches.centre - fit.centre).max() < 2e-3
    for groups in (1, 64):  # stage groups of one block each, and the whole batch as one group
        grouped = fit_blocks(sim.image, sim.H0, SEGMENTS, K,
                             dataclasses.replace(SETTINGS, stage_batch_size=groups))
        assert np.abs(grouped.centre - fit.centre).max() < 2e-3
        assert [m.shape for m in grouped.masks] == [m.shape for m in fit.masks]


def _in_thread(work):
    """``work()``'s result, run in a new thread that keeps denormal floats, and whether the
    thread still keeps them afterwards."""
    out = {}

    def run() -> None:
        torch.set_flush_denormal(False)
        out["fit"] = work()
        out["kept_after"] = not flushing_denormals()

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    return out


def test_denormals_are_flushed_during_a_fit_alone_and_change_nothing(sim: SimulatedBlocks, fit: BlockFit,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush denormal floats")
    during = []
    batch = blocks.fit_free_batch

    def recorded(*args, **kwargs):
        during.append(flushing_denormals())
        return batch(*args, **kwargs)

    monkeypatch.setattr(blocks, "fit_free_batch", recorded)
    solved = _in_thread(lambda: fit_blocks(sim.image, sim.H0, SEGMENTS, K, SETTINGS))
    assert during and all(during) and solved["kept_after"]  # flushed inside, the thread's own after
    monkeypatch.setattr(blocks, "_fit", blocks._fit.__wrapped__)  # the solver without flushing
    kept = _in_thread(lambda: fit_blocks(sim.image, sim.H0, SEGMENTS, K, SETTINGS))
    assert not during[-1]
    for other in (solved["fit"], kept["fit"]):
        assert np.abs(other.centre - fit.centre).max() < 1e-4
        assert np.abs(other.psf - fit.psf).max() < 1e-5


def test_float64_agrees_with_float32(sim: SimulatedBlocks, fit: BlockFit) -> None:
    fit64 = fit_blocks(sim.image, sim.H0[:2], SEGMENTS, K, dataclasses.replace(SETTINGS, dtype="float64"))
    assert np.abs(fit64.centre - fit.centre[:2]).max() < 2e-3


@pytest.mark.parametrize("kernel_size", [K, 41])  # direct and FFT convolutions
def test_fixed_fit_chord_steps_land_where_full_steps_do(sim: SimulatedBlocks, kernel_size: int,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """With given PSFs the later LM steps are chord steps (the Jacobian of the last full
    evaluation, within ``CHORD_WITHIN_PX`` of it): chord steps are taken, some blocks that move
    farther have their Jacobian evaluated again, and the fit lands where the one that evaluates
    every accepted step's Jacobian does (blocks started 1.5 px off: within 0.0006 px). Without the
    distance limit it ends 10 x farther from it (0.006 px) after the same 6 steps."""
    psfs = resize_kernels(_centred_truth(sim.psf_true, K), kernel_size)
    counts = {"chord": 0, "fresh": 0}
    chord = lm._chord

    def counted(prob, cur, best, accept, fresh, *args):
        counts["chord"] += int((accept & ~fresh).sum())
        counts["fresh"] += int(fresh.sum())
        return chord(prob, cur, best, accept, fresh, *args)

    monkeypatch.setattr(lm, "_chord", counted)
    fast = fit_blocks_fixed(sim.image, sim.H0, SEGMENTS, psfs, SETTINGS)
    assert counts["chord"] > 0 and counts["fresh"] > 0, counts
    monkeypatch.setattr(lm, "CHORD_FROM_STEP", SETTINGS.fixed_steps)
    every = fit_blocks_fixed(sim.image, sim.H0, SEGMENTS, psfs, SETTINGS)
    assert fast.status == every.status
    np.testing.assert_allclose(fast.centre, every.centre, atol=0.002)
    np.testing.assert_allclose(fast.loss, every.loss, rtol=1e-3)
    assert _centre_error(fast, sim).max() < 0.05
    monkeypatch.setattr(lm, "CHORD_FROM_STEP", 1)
    monkeypatch.setattr(lm, "CHORD_WITHIN_PX", np.inf)
    unlimited = fit_blocks_fixed(sim.image, sim.H0, SEGMENTS, psfs, SETTINGS)
    assert np.abs(unlimited.centre - every.centre).max() > 0.004


@pytest.mark.parametrize(("kernel_size", "side", "by_fft"),
                         [(7, 20, False), (29, 20, False), (41, 100, True)])
def test_block_convolution_is_the_valid_convolution(kernel_size: int, side: int, by_fft: bool) -> None:
    """Both paths of the solver's convolution (direct for small windows and kernels, FFT for
    large ones) give ``k * L`` on the observed grid, as an independent ``scipy.ndimage.convolve``
    does."""
    rng = np.random.default_rng(5)
    size = np.array([[side + 3, side - 1], [side - 3, side + 1]])
    s = DeconvSettings(dtype="float64")
    prob = BlockProblem(torch.zeros((side + 60, side + 60), dtype=torch.float64), None,
                        np.array([[3, 4], [9, 2]]), size, SEGMENTS, kernel_size, s)
    direct_cost = prob.h * prob.w * kernel_size**2
    assert (direct_cost > DIRECT_PER_FFT_POINT * fft_size(prob.Hl) * fft_size(prob.Wl)) == by_fft
    L = torch.as_tensor(rng.random((2, 3, prob.Hl, prob.Wl)))
    k = torch.as_tensor(rng.random((2, kernel_size, kernel_size)))
    out = prob.conv(L, k).numpy()
    r = prob.r
    for b in range(2):
        for c in range(3):
            ref = convolve(L[b, c].numpy(), k[b].numpy(), mode="constant")[r:r + prob.h, r:r + prob.w]
            np.testing.assert_allclose(out[b, c], ref, rtol=1e-10, atol=1e-10)


# ------------------------------------------------------------------------------- invalid input
def test_invalid_blocks_are_flagged_per_block(sim: SimulatedBlocks, fit: BlockFit) -> None:
    good = sim.H0[0]
    nan_h = np.full((3, 3), np.nan)
    flat = good.copy()
    flat[:, 1] = 0.0  # the square collapses to a segment
    behind = good.copy()
    behind[2] = [2.0, 0.0, 1.0]  # the horizon crosses the square
    outside = translation(np.array([-60.0, 0.0])) @ good  # the window leaves the image
    H0 = np.stack([good, nan_h, flat, behind, outside, np.zeros((3, 3))])
    out = fit_blocks(sim.image, H0, SEGMENTS, K, SETTINGS)
    assert out.status == (BlockStatus.ACCEPTED, BlockStatus.DEGENERATE_HOMOGRAPHY,
                          BlockStatus.DEGENERATE_HOMOGRAPHY, BlockStatus.DEGENERATE_HOMOGRAPHY,
                          BlockStatus.OUTSIDE_IMAGE, BlockStatus.DEGENERATE_HOMOGRAPHY)
    assert out.converged.tolist() == [True, False, False, False, False, False]
    assert np.abs(out.centre[0] - fit.centre[0]).max() < 2e-3
    assert np.all(np.isnan(out.loss[1:])) and np.all(np.isnan(out.psf[1:]))
    np.testing.assert_array_equal(out.H[4], outside)  # unfitted blocks keep their H0
    with pytest.raises(ValueError, match="not fitted"):
        render_model(out, sim.image, 4)


def test_a_window_without_a_star_fails_alone(sim: SimulatedBlocks, fit: BlockFit) -> None:
    image = sim.image.astype(np.float64)
    x0, y0 = fit.origin[1]
    w, h = fit.window_size[1]
    image[y0:y0 + h, x0:x0 + w] = 120.0  # block 1: a blank window
    cx, cy = np.round(fit.centre[2]).astype(int)
    image[cy + 3, cx] = np.nan  # block 2: one non-finite pixel in the square, ignored
    out = fit_blocks(image, sim.H0[:3], SEGMENTS, K, SETTINGS)
    assert out.status == (BlockStatus.ACCEPTED, BlockStatus.NOT_CONVERGED, BlockStatus.ACCEPTED)
    assert np.abs(out.centre[[0, 2]] - fit.centre[[0, 2]]).max() < 0.01
    assert out.num_pixels[2] == fit.num_pixels[2] - 1


def test_pixel_mask_removes_pixels_from_the_loss(sim: SimulatedBlocks, fit: BlockFit) -> None:
    mask = np.ones(sim.image.shape, dtype=bool)
    x0, y0 = fit.origin[0]
    w, h = fit.window_size[0]
    mask[y0:y0 + h // 4, x0:x0 + w] = False  # the top quarter of block 0's window
    out = fit_blocks(sim.image, sim.H0[:2], SEGMENTS, K, SETTINGS, pixel_mask=mask)
    assert out.num_pixels[0] < fit.num_pixels[0] and out.num_pixels[1] == fit.num_pixels[1]
    assert not out.masks[0][: h // 4].any()
    assert _centre_error(out, dataclasses.replace(sim, centre_true=sim.centre_true[:2])).max() < 0.05


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError, match="odd"):
        fit_blocks(np.zeros((40, 40)), np.eye(3)[None], SEGMENTS, 12)
    with pytest.raises(ValueError, match="dtype"):
        DeconvSettings(dtype="float16")
    with pytest.raises(ValueError, match="stop_rejections"):
        DeconvSettings(stop_rejections=0)
    with pytest.raises(ValueError, match="stop_decrease"):
        DeconvSettings(stop_decrease=-1.0)
    with pytest.raises(ValueError, match=r"\(height, width\)"):
        fit_blocks(np.zeros((4, 4, 3)), np.eye(3)[None], SEGMENTS, K)
    with pytest.raises(ValueError, match="pixel_mask"):
        fit_blocks(np.zeros((40, 40)), np.eye(3)[None], SEGMENTS, K, pixel_mask=np.ones((4, 4), dtype=bool))
    with pytest.raises(ValueError, match="psfs"):
        fit_blocks_fixed(np.zeros((40, 40)), np.eye(3)[None], SEGMENTS, -np.ones((1, K, K)))


@pytest.mark.parametrize("segments", [8, 16])
def test_closed_form_edge_normal_matches_autograd(segments: int) -> None:
    q = torch.as_tensor(np.random.default_rng(3).uniform(-3.0, 3.0, (20000, 2)), dtype=torch.float64)
    q.requires_grad_(True)
    dist = star_signed_distance(q, segments)
    (grad,) = torch.autograd.grad(dist.sum(), q)
    d2, nx, ny = star_signed_distance_normal(q[:, 0].detach(), q[:, 1].detach(), segments)
    normal = torch.stack([nx, ny], dim=1)
    assert torch.allclose(d2, dist.detach(), rtol=0.0, atol=1e-12)
    assert torch.allclose(normal, grad, atol=1e-12)
    assert torch.allclose(normal.norm(dim=-1), torch.ones(len(q), dtype=torch.float64))


def test_latent_jacobian_matches_finite_differences() -> None:
    """``dS / d delta`` of :func:`latent_pattern` (the edge normaliser's change included) is the
    central difference of ``S(H (I + Delta))`` in all 8 directions, for blocks under perspective,
    away from the pixels where the nearest edge switches."""
    rng = np.random.default_rng(8)
    H = np.stack([translation(np.array([20.0, 19.0])) @ np.array(
        [[14.0 + rng.normal(), rng.normal(), 0.0], [rng.normal(), 13.0 + rng.normal(), 0.0],
         [rng.normal(0, 0.01), rng.normal(0, 0.01), 1.0]]) for _ in range(3)])
    H_t = torch.as_tensor(H)
    grid = (40, 40)
    _, dS = latent_pattern(H_t, grid, SEGMENTS, 0.25, 1, torch.float64, with_jac=True)
    eps = 1e-6

    def pattern_at(step: torch.Tensor) -> torch.Tensor:
        return latent_pattern(update_homography(H_t, step), grid, SEGMENTS, 0.25, 1, torch.float64, False)[0]

    for k in range(8):
        step = torch.zeros((3, 8), dtype=torch.float64)
        step[:, k] = eps
        numeric = (pattern_at(step) - pattern_at(-step)) / (2 * eps)
        err = (numeric - dS[:, k]).abs()
        smooth = err < 1e-3 * numeric.abs().max()  # the rest: pixels across an edge switch
        assert smooth.double().mean() > 0.99
        assert torch.median((numeric - dS[:, k]).abs()[numeric.abs() > 1e-3]) < 1e-6


def test_lm_stop_rules_keep_the_fit_and_solve_fewer_blocks(sim: SimulatedBlocks,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """With given PSFs, a block whose step is a small fraction of its own noise, or that rejected
    two steps in a row, stops: the fit lands where the one taking every step does (within a
    hundredth of a px) and solves fewer blocks."""
    psfs = _centred_truth(sim.psf_true, K)
    solved: list[int] = []
    evaluate = BlockProblem.evaluate

    def counted(self, H_loc, *args, **kwargs):
        solved.append(H_loc.shape[0])
        return evaluate(self, H_loc, *args, **kwargs)

    monkeypatch.setattr(BlockProblem, "evaluate", counted)
    every_step = dataclasses.replace(SETTINGS, stop_decrease=0.0, stop_rejections=SETTINGS.fixed_steps)
    full = fit_blocks_fixed(sim.image, sim.H0, SEGMENTS, psfs, every_step)
    full_rows, solved[:] = sum(solved), []
    stopped = fit_blocks_fixed(sim.image, sim.H0, SEGMENTS, psfs, SETTINGS)
    assert sum(solved) < full_rows
    assert np.nanmax(np.linalg.norm(stopped.centre - full.centre, axis=1)) < 0.01
    assert np.nanmedian(_centre_error(stopped, sim)) < 1.1 * np.nanmedian(_centre_error(full, sim)) + 1e-3


def test_psf_hint_replaces_the_coarse_kernel() -> None:
    """Given the expected PSFs (here the true ones, relative to ``H0``), blocks start from their
    support in one stage and land as close to the truth as the full schedule."""
    sim = _simulate(10, 21, blur_px=(5.0, 9.0), init_shift_px=0.4, truth_kernel_size=13)
    image = sim.image.astype(np.float32)
    full = fit_blocks(image, sim.H0, SEGMENTS, K, SETTINGS)
    hinted = fit_blocks_hinted(image, sim.H0, SEGMENTS, sim.psf_true, SETTINGS)
    ok = np.array([s is BlockStatus.ACCEPTED for s in hinted.status])
    assert ok.sum() >= 9
    err_full, err_hinted = _centre_error(full, sim), _centre_error(hinted, sim)
    assert np.median(err_hinted[ok]) < 1.3 * np.median(err_full) + 0.005
    assert np.median(err_hinted[ok]) < 0.05
    # A block without a usable hint starts from the whole window (measured 0.17 px off).
    blank = sim.psf_true.copy()
    blank[0] = 0.0
    rough = fit_blocks_hinted(image, sim.H0, SEGMENTS, blank, SETTINGS)
    assert rough.status[0] is BlockStatus.ACCEPTED and _centre_error(rough, sim)[0] < 0.5
    with pytest.raises(ValueError, match="hints"):
        fit_blocks_hinted(image, sim.H0, SEGMENTS, sim.psf_true[:3], SETTINGS)


def test_a_larger_loss_area_sees_more_pixels_and_lands_closer() -> None:
    """``loss_extent`` 1.5 fits each block over its square and a band of its neighbours' squares:
    2.25 x the pixels, and the star centre lands closer to the truth (measured 0.025 -> 0.015 px
    and 0.037 -> 0.025 px median on these two sets of 15-18 px blur)."""
    errors = {1.0: [], 1.5: []}
    pixels = {1.0: [], 1.5: []}
    for seed in (5, 6):
        sim = _simulate(12, seed, blur_px=(14.0, 18.0), square_px=(26.0, 30.0), tile_px=112,
                        truth_kernel_size=29, init_shift_px=0.3)
        for extent in errors:
            fit = fit_blocks_hinted(sim.image.astype(np.float32), sim.H0, SEGMENTS, sim.psf_true,
                                    DeconvSettings(loss_extent=extent))
            assert all(s is BlockStatus.ACCEPTED for s in fit.status)
            errors[extent].append(_centre_error(fit, sim))
            pixels[extent].append(fit.num_pixels)
    ratio = np.concatenate(pixels[1.5]) / np.concatenate(pixels[1.0])
    assert np.all((ratio > 2.0) & (ratio < 2.5))
    small, large = np.concatenate(errors[1.0]), np.concatenate(errors[1.5])
    assert np.median(large) < 0.75 * np.median(small) and large.max() < small.max()
    with pytest.raises(ValueError, match="loss_extent"):
        DeconvSettings(loss_extent=0.0)


def test_concatenated_fits_share_the_largest_window(sim: SimulatedBlocks, fit: BlockFit) -> None:
    """A fit reports its window from its PSFs; rows of several fits are zero-padded (centred) to
    the largest, and a replaced row carries the other fit's values."""
    big = fit_blocks(sim.image, sim.H0[:2], SEGMENTS, 17, SETTINGS)
    both = BlockFit.concat([fit, big])
    assert (fit.kernel_size, big.kernel_size, both.kernel_size) == (K, 17, 17) and len(both) == len(fit) + 2
    np.testing.assert_array_equal(both.psf[:len(fit), 2:-2, 2:-2], fit.psf)
    assert np.all(both.psf[:len(fit), :2] == 0) and np.all(both.psf[:len(fit), :, -2:] == 0)
    swapped = fit.with_rows(np.array([1]), big, np.array([0]))
    np.testing.assert_array_equal(swapped.H[1], big.H[0])
    np.testing.assert_array_equal(swapped.H[[0, 2]], fit.H[[0, 2]])
    assert swapped.kernel_size == 17 and swapped.status[1] is big.status[0]
