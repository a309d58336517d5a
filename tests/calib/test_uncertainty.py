"""Projection uncertainty against Monte-Carlo refits, the cross-validation diff, guidance and files."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from blurcalib.calib.bundle import BundleSettings, bundle_adjust
from blurcalib.calib.normal_equations import normal_equations
from blurcalib.calib.uncertainty import (
    ProjectionUncertainty,
    cross_validation_diff,
    guidance,
    projection_uncertainty,
    save_uncertainty_npz,
    save_uncertainty_png,
)
from blurcalib.camera.generic import CentralGeneric, apply_update, best_fit_rotation, fit_to_rays
from tests.calib.test_bundle import TRUE_CAM, _scene

NOISE_PX = 0.1
SETTINGS = BundleSettings(outlier_iteration=0, max_iterations=20, tol=1e-12)


def _errors(truth: CentralGeneric, estimate: CentralGeneric, px: np.ndarray) -> np.ndarray:
    """``(K, 2)`` px: the estimate's projection of each pixel's true ray after the best-fit rotation."""
    true_rays = truth.pixel_to_ray(px)
    Q = best_fit_rotation(true_rays, estimate.pixel_to_ray(px))
    u, inside = estimate.project(true_rays @ Q.T, init=px)
    err = u - px
    err[~inside] = np.nan
    return err


@pytest.fixture(scope="module")
def truth() -> CentralGeneric:
    return fit_to_rays(TRUE_CAM.pixel_to_ray, 320, 240, cell_px=40.0)


def test_matches_monte_carlo_refits(truth: CentralGeneric) -> None:
    """Refits with fresh noise and a fresh prior centre (the initial grid drawn from the smoothness
    prior around the truth): the errors after the best-fit rotation follow the predicted covariance.

    The observations carry weight ``1 / NOISE_PX^2``, so that the bundle adjustment's estimate is
    the posterior's mode and its prior has the weight the covariance gives it.
    """
    poses, index, points, exact = _scene(truth, 12, seed=1)
    weights = np.full(len(index), NOISE_PX ** -2)
    settings = BundleSettings(outlier_iteration=0, max_iterations=30, tol=1e-12, smoothness_px=0.2)
    rng = np.random.default_rng(0)
    first = bundle_adjust(truth, poses, index, points, exact + rng.normal(size=exact.shape) * NOISE_PX,
                          weights=weights, settings=settings)
    unc = projection_uncertainty(first)
    px = np.column_stack([unc.x, unc.y])
    evals, evecs = np.linalg.eigh(normal_equations(first).hgg_prior.numpy())
    rank = evals > 1e-9 * evals.max()
    prior_sqrt = evecs[:, rank] / np.sqrt(evals[rank])
    errors = []
    for _ in range(24):
        prior_centre = apply_update(torch.tensor(truth.grid), torch.as_tensor(
            prior_sqrt @ rng.normal(size=int(rank.sum()))).reshape(*truth.grid.shape[:2], 2))
        observed = exact + rng.normal(size=exact.shape) * NOISE_PX
        res = bundle_adjust(truth.with_grid(prior_centre.numpy()), poses, index, points, observed,
                            weights=weights, settings=settings)
        errors.append(_errors(truth, res.model, px))
    assert unc.noise_px == pytest.approx(1.0, rel=0.08)
    assert np.diff(np.unique(unc.x)).max() <= 16.0 and unc.x.reshape(unc.shape)[0, 0] == unc.x.min()
    e = np.array(errors)
    ok = np.isfinite(e).all(axis=(0, 2))  # the edge's pixels whose true ray left an estimate's area
    assert ok.mean() > 0.95
    e = e[:, ok]
    mse = (e ** 2).sum(-1).mean(0)
    ratio = np.sqrt(mse.mean() / (unc.sigma_px[ok] ** 2).mean())
    assert 0.75 < ratio < 1.33
    assert np.corrcoef(np.sqrt(mse), unc.sigma_px[ok])[0, 1] > 0.9
    np.testing.assert_allclose(np.trace(unc.cov, axis1=1, axis2=2), unc.sigma_px ** 2, rtol=1e-9)
    emp = np.einsum("tki,tkj->kij", e, e) / len(e)
    off = emp[:, 0, 1] / np.sqrt(emp[:, 0, 0] * emp[:, 1, 1])
    cov = unc.cov[ok]
    pred = cov[:, 0, 1] / np.sqrt(cov[:, 0, 0] * cov[:, 1, 1])
    assert np.median(np.abs(off - pred)) < 0.25
    # the focal-scale part of the error field (weakly determined by 12 frames) has the predicted spread
    centre = np.array([159.5, 119.5])
    design = np.column_stack([np.ones(int(ok.sum())), px[ok] - centre])
    coef = np.linalg.lstsq(design, e.transpose(1, 0, 2).reshape(len(design), -1), rcond=None)[0]
    scale = 0.5 * (coef[1, 0::2] + coef[2, 1::2]) * np.linalg.norm(centre)
    assert 0.6 < np.sqrt(np.mean(scale ** 2)) / unc.scale_px < 1.6
    noise_given = projection_uncertainty(first, noise_px=2.0)
    assert noise_given.noise_px == 2.0
    assert 1.0 < noise_given.median() / unc.median() <= 2.0  # what the prior holds does not double


def test_fewer_frames_in_a_region_raise_sigma(truth: CentralGeneric) -> None:
    """Without the frames whose target sits in the left part, sigma rises on the left, not on the
    right, and the guidance names left regions only."""
    poses, index, points, exact = _scene(truth, 24, seed=2)
    observed = exact + np.random.default_rng(1).normal(size=exact.shape) * NOISE_PX
    full = projection_uncertainty(bundle_adjust(truth, poses, index, points, observed, settings=SETTINGS))
    mean_x = np.array([observed[index == f, 0].mean() for f in range(len(poses))])
    keep = np.nonzero(mean_x > 140)[0]
    rows = np.isin(index, keep)
    remap = np.full(len(poses), -1)
    remap[keep] = np.arange(len(keep))
    res = bundle_adjust(truth, [poses[f] for f in keep], remap[index[rows]], points[rows], observed[rows],
                        settings=SETTINGS)
    right_only = projection_uncertainty(res, noise_px=full.noise_px)
    left = full.x < 60
    right = full.x > 260
    trusting = projection_uncertainty(res, noise_px=full.noise_px, prior_scale=0.1)
    assert trusting.sigma_px[left].mean() < 0.7 * right_only.sigma_px[left].mean()
    with pytest.raises(ValueError, match="prior_scale"):
        projection_uncertainty(res, prior_scale=0.0)
    assert right_only.sigma_px[left].mean() > 2 * full.sigma_px[left].mean()
    assert right_only.sigma_px[right].mean() < 1.6 * full.sigma_px[right].mean()
    threshold = 2 * float(np.percentile(full.sigma_px, 90))
    assert guidance(full, 320, 240, threshold) == []
    lines = guidance(right_only, 320, 240, threshold)
    assert lines and all("right" not in line for line in lines)
    assert any("left" in line for line in lines)


def test_cross_validation_diff(truth: CentralGeneric) -> None:
    same = cross_validation_diff(truth, truth)
    assert same.median_px < 1e-6 and np.nanmax(same.diff_px) < 1e-6
    assert same.x.reshape(same.shape)[0, 0] == same.x.min() and np.diff(np.unique(same.x)).max() <= 16
    R, _ = np.linalg.qr(np.eye(3) + 0.02 * np.random.default_rng(0).normal(size=(3, 3)))
    R *= np.sign(np.linalg.det(R))
    turned = cross_validation_diff(truth, truth.rotated(R))
    assert np.nanmax(turned.diff_px) < 1e-4
    wider = TRUE_CAM.with_params(fx=TRUE_CAM.fx * 1.002, fy=TRUE_CAM.fy * 1.002, k1=-0.118)
    other = fit_to_rays(wider.pixel_to_ray, 320, 240, cell_px=40.0)
    diff = cross_validation_diff(truth, other)
    px = np.column_stack([diff.x, diff.y])
    a = TRUE_CAM.pixel_to_ray(px)
    b = wider.pixel_to_ray(px)
    expected = np.linalg.norm(wider.project(a @ best_fit_rotation(a, b).T) - px, axis=1)
    assert diff.median_px > 0.1
    np.testing.assert_allclose(diff.diff_px, expected, atol=5e-3)
    with pytest.raises(ValueError, match="image sizes differ"):
        cross_validation_diff(truth, fit_to_rays(TRUE_CAM.pixel_to_ray, 330, 240, cell_px=40.0))


def _synthetic(sigma_of: callable, area: tuple[float, float, float, float] = (-0.5, -0.5, 319.5, 239.5)
               ) -> ProjectionUncertainty:
    xs = np.arange(area[0] + 0.5, area[2], 8.0)
    ys = np.arange(area[1] + 0.5, area[3], 8.0)
    xx, yy = np.meshgrid(xs, ys)
    sigma = sigma_of(xx.ravel(), yy.ravel())
    cov = np.zeros((len(sigma), 2, 2))
    cov[:, 0, 0] = cov[:, 1, 1] = sigma ** 2 / 2
    return ProjectionUncertainty(xx.ravel(), yy.ravel(), xx.shape, sigma, cov, 0.02, 320, 240, 100.0, 0.01,
                                 0.02)


def test_guidance_names_regions() -> None:
    calm = _synthetic(lambda x, y: np.full(len(x), 0.01))
    assert guidance(calm, 320, 240) == []
    corner = _synthetic(lambda x, y: np.where((x < 100) & (y < 70), 0.12, 0.01))
    lines = guidance(corner, 320, 240)
    assert lines == ["capture more frames with the target in the top-left corner of the image "
                     "(uncertainty up to 0.12 px there)"]
    everywhere = _synthetic(lambda x, y: np.full(len(x), 0.2))
    assert len(guidance(everywhere, 320, 240)) == 1 and "whole image" in guidance(everywhere, 320, 240)[0]
    cropped = _synthetic(lambda x, y: np.full(len(x), 0.01), area=(-0.5, -0.5, 200.0, 239.5))
    lines = guidance(cropped, 320, 240)
    assert len(lines) == 3
    assert all("right" in line and "outside the calibrated area" in line for line in lines)


def test_files(tmp_path) -> None:
    unc = _synthetic(lambda x, y: 0.01 + 1e-4 * x)
    sharp = _synthetic(lambda x, y: 0.02 + 1e-4 * y, area=(19.5, -0.5, 319.5, 239.5))
    maps = [("sharp", sharp), ("sharp + blurry", unc)]
    png = save_uncertainty_png(tmp_path / "uncertainty.png", maps, 320, 240)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    npz = np.load(save_uncertainty_npz(tmp_path / "uncertainty.npz", unc, sharp))
    assert set(npz.files) == {"x", "y", "sigma_px", "noise_px", "sigma_px_sharp", "noise_px_sharp"}
    assert npz["x"].shape == unc.shape and float(npz["noise_px"]) == 0.02
    np.testing.assert_allclose(npz["sigma_px"].ravel(), unc.sigma_px)
    s = npz["sigma_px_sharp"].ravel()
    inside = unc.x >= 20
    np.testing.assert_allclose(s[inside], 0.02 + 1e-4 * unc.y[inside], atol=1e-12)
    assert np.isnan(s[~inside]).all()
    only = np.load(save_uncertainty_npz(tmp_path / "only.npz", unc))
    assert set(only.files) == {"x", "y", "sigma_px", "noise_px"}
    assert unc.border_band(20.0) > unc.median() and unc.rms() > 0
