"""The frame's path-PSF field: the path PSF and its derivatives, the field's files, blocks fitted
with known PSFs where free ones fail (blur as long as the square), and the joint field fit, free
and tied to one homography."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from blurcalib.deconv import field as field_fit
from blurcalib.deconv.blocks import fit_blocks, fit_blocks_fixed
from blurcalib.deconv.field import fit_path_field
from blurcalib.deconv.problem import BlockProblem
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.geometry.homography import homography_centre, translation
from blurcalib.growth.seed import block_homography
from blurcalib.io.results import BlockStatus
from blurcalib.psf.kernel import psf_centroid
from blurcalib.psf.path import PathField, constant_field, path_kernels
from blurcalib.sim.blocks import simulate_blocks
from blurcalib.target.pattern import StarPattern, layout_pattern

SEGMENTS = 16


def test_path_kernels_are_the_sampled_path_with_zero_centroid_and_exact_derivatives() -> None:
    theta = torch.tensor([[10.0, -4.0, 3.0, 5.0, math.log(0.8)], [0.5, 0.2, 0.0, 0.0, math.log(1.2)]],
                         dtype=torch.float64)
    k, dk = path_kernels(theta, 31, with_jac=True)
    T = 48
    tau = (np.arange(T) + 0.5) / T - 0.5
    d = np.arange(31) - 15.0
    for b in range(2):
        a, bb, s = theta[b, :2].numpy(), theta[b, 2:4].numpy(), math.exp(float(theta[b, 4]))
        p = tau[:, None] * a + (tau[:, None] ** 2 - np.mean(tau**2)) * bb
        direct = sum(np.exp(-((d[None, :] - px) ** 2 + (d[:, None] - py) ** 2) / (2 * s * s)) for px, py in p)
        np.testing.assert_allclose(k[b].numpy(), direct / (2 * np.pi * s * s * T), atol=1e-12)
        assert abs(float(k[b].sum()) - 1.0) < 1e-6
        np.testing.assert_allclose(psf_centroid(k[b].numpy()), 0.0, atol=1e-5)
    for j in range(5):
        step = torch.zeros_like(theta)
        step[:, j] = 1e-6
        numeric = (path_kernels(theta + step, 31)[0] - path_kernels(theta - step, 31)[0]) / 2e-6
        assert float((numeric - dk[:, j]).abs().max()) < 1e-6 * float(dk[:, j].abs().max())
    # the direction of time is not seen: (a, b) and (-a, b) give the same kernel
    flipped = theta.clone()
    flipped[:, :2] *= -1
    np.testing.assert_allclose(path_kernels(flipped, 31)[0].numpy(), k.numpy(), atol=1e-12)


def test_field_files_round_trip_and_degrees_extend() -> None:
    field = PathField(np.arange(12, dtype=float).reshape(3, 4) - 5, math.log(0.7), (1280, 720))
    again = PathField.from_dict(field.to_dict())
    xy = np.array([[0.0, 0.0], [640.0, 360.0], [1279.0, 719.0]])
    np.testing.assert_allclose(again.theta(xy), field.theta(xy), atol=1e-5)
    assert field.with_degree(2).degree == 2 and field.with_degree(0).degree == 0
    np.testing.assert_allclose(field.with_degree(2).theta(xy), field.theta(xy))
    np.testing.assert_allclose(field.with_degree(0).theta(xy)[:, :4], np.tile(field.coeffs[0], (3, 1)))
    with pytest.raises(ValueError, match="not a path field"):
        PathField.from_dict({"coeffs": [[1, 2, 3, 4]] * 2, "sigma_px": 1.0, "image_size": [10, 10]})
    # a straight start from PSFs: their length and orientation
    k = field.with_degree(0).kernels(xy[:1], 41)
    start = constant_field(np.repeat(k, 3, axis=0), (1280, 720), 1)
    a = field.coeffs[0, :2]
    got = start.coeffs[0, :2] * np.sign(start.coeffs[0, :2] @ a)
    assert start.degree == 1 and np.linalg.norm(got - a) < 0.2 * np.linalg.norm(a)


def test_path_change_is_the_largest_distance_between_the_sampled_paths() -> None:
    field = PathField(np.array([[8.0, -3.0, 2.0, 1.0], [1.0, 0.5, 0.0, 0.0], [0.0, 0.0, -1.0, 0.5]]),
                      math.log(0.7), (1280, 720))
    xy = np.array([[100.0, 50.0], [640.0, 360.0], [1200.0, 700.0]])
    np.testing.assert_allclose(field.path_change(field, xy), 0.0, atol=1e-12)
    # the same kernels with the direction of time reversed: no change
    reversed_time = PathField(field.coeffs * np.array([-1.0, -1.0, 1.0, 1.0]), field.log_sigma,
                              field.image_size)
    np.testing.assert_allclose(field.path_change(reversed_time, xy), 0.0, atol=1e-12)
    # the curvature moved by (0.3, 0) px everywhere, the spread from 0.7 to 0.9 px
    moved = field.coeffs.copy()
    moved[0, 2] += 0.3
    other = PathField(moved, math.log(0.9), field.image_size)
    tau = (np.arange(48) + 0.5) / 48 - 0.5
    expected = 0.3 * np.abs(tau**2 - np.mean(tau**2)).max() + 0.2
    np.testing.assert_allclose(field.path_change(other, xy), expected, rtol=1e-9)
    np.testing.assert_allclose(other.path_change(field, xy), expected, rtol=1e-9)


def _long_blur_blocks(seed: int, field: PathField, count: int = 16, shift_px: float = 0.4):
    """Blocks of 24-28 px squares blurred by the field's PSF at their tiles' centres."""
    tile = 112
    cols = math.ceil(math.sqrt(count))
    centres = np.array([[(b % cols + 0.5) * tile, (b // cols + 0.5) * tile] for b in range(count)])
    kernels = field.kernels(centres, 45)
    return simulate_blocks(layout_pattern(), count, np.random.default_rng(seed), square_px=(24.0, 28.0),
                           tile_px=tile, supersample=4, init_shift_px=shift_px, psf=kernels), kernels


FIELD = PathField(np.array([[22.0, 9.0, 3.0, -4.0], [2.0, -1.5, 0.0, 0.0], [-1.0, 2.0, 0.0, 0.0]]),
                  math.log(0.8), (448, 448))
"""A degree-1 field of 24 px paths, slightly curved, on a 448 x 448 image of 16 tiles."""


def test_known_psfs_locate_stars_whose_blur_is_as_long_as_their_squares() -> None:
    """Blur 24 px on 24-28 px squares: free PSFs trade their shape against the star's position,
    the true PSFs held do not."""
    sim, kernels = _long_blur_blocks(3, FIELD)
    settings = DeconvSettings(loss_extent=1.5)
    image = sim.image.astype(np.float32)
    held = fit_blocks_fixed(image, sim.H0, SEGMENTS, kernels, settings)
    free = fit_blocks(image, sim.H0, SEGMENTS, 45, settings)
    err_held = np.linalg.norm(held.centre - sim.centre_true, axis=1)
    err_free = np.linalg.norm(free.centre - sim.centre_true, axis=1)
    assert sum(s is BlockStatus.ACCEPTED for s in held.status) >= 14
    assert np.median(err_held) < 0.06 and err_held.max() < 0.15, err_held
    assert err_free.max() > 0.4 and np.sum(err_free > 0.15) >= 3, err_free
    np.testing.assert_allclose(held.psf_fit, kernels / kernels.sum(axis=(1, 2), keepdims=True), atol=1e-6)
    with pytest.raises(ValueError, match="psfs"):
        fit_blocks_fixed(image, sim.H0, SEGMENTS, kernels[:2], settings)


def test_field_fit_recovers_the_field_and_the_blocks() -> None:
    """From a straight path the same everywhere, the joint fit finds the degree-1 field (the path
    at each block within a few tenths of a px) and puts the blocks on their stars."""
    sim, _ = _long_blur_blocks(5, FIELD)
    centres = homography_centre(sim.H_true)
    k0 = FIELD.with_degree(0).kernels(centres[:1], 45)
    start = constant_field(k0, FIELD.image_size, 1)
    fit = fit_path_field(sim.image.astype(np.float32), sim.H0, SEGMENTS, start)
    got, true = fit.field.theta(centres), FIELD.theta(centres)
    sign = np.sign(np.sum(got[:, :2] * true[:, :2], axis=1))[:, None]
    assert np.abs(got[:, :2] * sign - true[:, :2]).max() < 0.5
    assert np.abs(got[:, 2:4] - true[:, 2:4]).max() < 1.5
    assert abs(math.exp(fit.field.log_sigma) - 0.8) < 0.3
    err = np.linalg.norm(homography_centre(fit.H) - sim.centre_true, axis=1)
    assert np.median(err) < 0.06 and err.max() < 0.3, err
    assert fit.objective[-1] < 0.5 * fit.objective[0]


def test_field_fit_keeps_its_latent_while_the_blocks_are_held_and_lands_where_recomputing_does(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """While the blocks' homographies are held the fit reuses their latent pattern and its
    transform (one latent per held phase); the fit that recomputes them at every evaluation
    takes the same steps to the same field and blocks."""
    sim, _ = _long_blur_blocks(5, FIELD)
    centres = homography_centre(sim.H_true)
    start = constant_field(FIELD.with_degree(0).kernels(centres[:1], 45), FIELD.image_size, 1)
    computed = []  # (homographies, with their derivatives) of each latent computed
    latent = BlockProblem.latent

    def counted(self, H_loc, with_jac):
        computed.append((H_loc, with_jac))
        return latent(self, H_loc, with_jac)

    monkeypatch.setattr(BlockProblem, "latent", counted)
    kept = fit_path_field(sim.image.astype(np.float32), sim.H0, SEGMENTS, start)
    held = [with_jac for H_loc, with_jac in computed if H_loc is computed[0][0]]
    assert held == [False, True]  # the held phase's one latent, then its derivatives for the next
    kept_computed = len(computed)
    computed.clear()
    keep = field_fit._FieldProblem.latent

    def fresh(self, H_loc, with_jac):
        self._latent = None
        return keep(self, H_loc, with_jac)

    monkeypatch.setattr(field_fit._FieldProblem, "latent", fresh)
    again = fit_path_field(sim.image.astype(np.float32), sim.H0, SEGMENTS, start)
    assert len(computed) > kept_computed
    assert kept.iterations == again.iterations
    np.testing.assert_allclose(kept.objective, again.objective, rtol=1e-6)
    np.testing.assert_allclose(kept.field.coeffs, again.field.coeffs, atol=1e-6)
    np.testing.assert_allclose(kept.H, again.H, atol=1e-6)


def _render_plane(pattern: StarPattern, H: np.ndarray, size: tuple[int, int], kernel: np.ndarray,
                  rng: np.random.Generator) -> np.ndarray:
    """The target through ``H`` (feature coordinates -> px), 3 x 3 supersampled, blurred by
    ``kernel``, grey levels 40..210 with noise sigma 2."""
    w, h = size
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    acc = np.zeros((h, w))
    for dy in (np.arange(3) - 1) / 3.0:
        for dx in (np.arange(3) - 1) / 3.0:
            p = np.stack([xs + dx, ys + dy, np.ones_like(xs)], axis=-1) @ np.linalg.inv(H).T
            acc += pattern.intensity(p[..., :2] / p[..., 2:])
    blurred = cv2.filter2D(40.0 + 170.0 * acc / 9.0, -1, kernel, borderType=cv2.BORDER_REFLECT)
    return np.clip(blurred + rng.normal(0.0, 2.0, blurred.shape), 0, 255).astype(np.float32)


def test_tied_fit_brings_blocks_started_px_off_onto_their_stars() -> None:
    """Twelve blocks of one plane under a 26 px blur on 24 px squares, each started 3 px off in
    its own direction (as under heavy blur a tag ring's predictions are): tied to one feature
    homography they land on their stars (measured over 5 draws: medians 0.026-0.05 px); fitted
    each on its own they do not (medians 2-4.4 px)."""
    pattern = layout_pattern()
    H = np.array([[24.0, 2.0, 40.0], [-1.5, 24.0, 30.0], [1e-4, 5e-5, 1.0]])
    field = PathField(np.array([[24.0, 9.0, 2.0, -3.0]]), math.log(0.8), (360, 300))
    image = _render_plane(pattern, H, (360, 300), field.kernels(np.zeros((1, 2)), 45)[0],
                          np.random.default_rng(2))
    fx, fy = np.meshgrid(np.arange(4, 8), np.arange(3, 6))
    f = np.stack([fx.ravel(), fy.ravel()], axis=1).astype(float)
    true = homography_centre(block_homography(H, f[:, 0], f[:, 1]))
    off = np.random.default_rng(4).normal(size=(len(f), 2))
    off *= 3.0 / np.linalg.norm(off, axis=1, keepdims=True)
    H0 = translation(off) @ block_homography(H, f[:, 0], f[:, 1])
    start = PathField(np.array([[20.0, 5.0, 0.0, 0.0]]), math.log(0.8), field.image_size)
    tied = fit_path_field(image, H0, SEGMENTS, start, features=f)
    err = np.linalg.norm(homography_centre(tied.H) - true, axis=1)
    assert np.median(err) < 0.1 and err.max() < 0.3, err
    free = fit_path_field(image, H0, SEGMENTS, start)
    assert np.median(np.linalg.norm(homography_centre(free.H) - true, axis=1)) > 1.0
    with pytest.raises(ValueError, match="at least 4"):
        fit_path_field(image, H0[:3], SEGMENTS, start, features=f[:3])


@pytest.mark.slow
def test_extract_records_the_field_and_the_option_turns_it_off(tmp_path) -> None:
    """A frame with 22 px of straight blur on 28 px squares is fitted with its path-PSF field by
    default (``frames.csv``'s ``psf`` column says ``field``, its status record holds the field,
    whose path is as long as the blur); ``--no-psf-field`` fits it with free PSFs."""
    import csv

    from blurcalib.cli import main
    from blurcalib.io.frame_files import read_frame_status
    from blurcalib.target.pattern import load_pattern
    from tests.conftest import FIXTURE_YAML
    from tests.growth.test_seed import _homography, _render

    pattern = load_pattern(FIXTURE_YAML)
    image = _render(pattern, _homography(pattern), (640, 480), 22.0, 0.6, np.random.default_rng(0))
    frame = tmp_path / "blurry.png"
    cv2.imwrite(str(frame), np.clip(np.round(image), 0, 255).astype(np.uint8))
    rows = {}
    for name, extra in (("field", []), ("free", ["--no-psf-field"])):
        out = tmp_path / name
        assert main(["extract", str(frame), "--pattern", str(FIXTURE_YAML), "--out", str(out),
                     "--workers", "1", *extra]) == 0
        with open(out / "frames.csv", newline="") as handle:
            rows[name] = next(csv.DictReader(handle))
        status = read_frame_status(out, "blurry.png")
        assert status is not None and (status.psf_field is not None) == (name == "field")
        if name == "field":
            field = PathField.from_dict(status.psf_field)
            length = np.linalg.norm(field.theta(np.array([[320.0, 240.0]]))[0, :2])
            assert abs(length - 22.0) < 2.0, length
    assert rows["field"]["psf"] == "field" and rows["free"]["psf"] == "free"
    assert rows["field"]["status"] == rows["free"]["status"] == "ok"
