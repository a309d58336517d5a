"""Bundle adjustment of the generic camera on synthetic observations with a known answer."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from blurcalib.calib.bundle import BundleSettings, bundle_adjust, reduce_frames
from blurcalib.calib.coverage import coverage_warnings
from blurcalib.calib.normal_equations import leave_out_models
from blurcalib.camera.generic import CentralGeneric, fit_to_rays
from blurcalib.geometry.pose import Pose
from tests.bundle_scene import TARGET, TRUE_CAM, bumped_truth, observed_scene

START_CAM = TRUE_CAM.with_params(fx=303.0, fy=296.0, cx=162.0, k1=-0.10, k2=0.0)


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(b.T @ a)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def _scene(truth: CentralGeneric, frames: int, seed: int
           ) -> tuple[list[Pose], np.ndarray, np.ndarray, np.ndarray]:
    """A 12 x 9 planar target (2 cm) seen from ``frames`` poses; exact generic projections."""
    poses, _, index, points, observed = observed_scene(
        np.random.default_rng(seed), frames, (40, 30), (280, 210),
        lambda pose, _k: (*truth.project(pose.transform(TARGET)), None))
    return poses, index, points, observed


@pytest.fixture(scope="module")
def truth() -> CentralGeneric:
    return bumped_truth()


@pytest.mark.slow
def test_recovers_grid_and_poses(truth: CentralGeneric) -> None:
    poses, index, points, observed = _scene(truth, 10, seed=1)
    start = fit_to_rays(START_CAM.pixel_to_ray, 320, 240, cell_px=40.0)
    rng = np.random.default_rng(3)
    noisy = [Pose.from_rvec_tvec(p.rvec + rng.normal(size=3) * 0.01, p.t + rng.normal(size=3) * 0.003)
             for p in poses]
    settings = BundleSettings(smoothness_px=1e4, outlier_iteration=0, max_iterations=30, tol=1e-14)
    res = bundle_adjust(start, noisy, index, points, observed, settings=settings)
    assert res.median_error < 1e-5
    px = np.random.default_rng(4).uniform([0, 0], [319, 239], (2000, 2))
    true_rays = truth.pixel_to_ray(px)
    est_rays = res.model.pixel_to_ray(px)
    Q = _kabsch(true_rays, est_rays)
    u, inside = res.model.project(true_rays @ Q.T)
    covered = res.coverage.sum() > 0
    assert covered and inside.mean() > 0.99
    assert np.median(np.linalg.norm(u - px, axis=1)[inside]) < 1e-3
    for est, true in zip(res.poses, poses, strict=True):
        R = est.R @ (Q @ true.R).T
        assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 0.01
        assert np.linalg.norm(est.t - Q @ true.t) < 1e-4


def test_shift_is_estimated(truth: CentralGeneric) -> None:
    poses, index, points, observed = _scene(truth, 10, seed=2)
    shift = np.array([1.5, -0.8])
    moved = observed + np.where((index == 9)[:, None], shift, 0.0)
    free = np.zeros(10, bool)
    free[9] = True
    settings = BundleSettings(smoothness_px=100.0, outlier_iteration=0, shift_sigma_px=1e3,
                              max_iterations=12, tol=1e-14)
    res = bundle_adjust(truth, poses, index, points, moved, shift_free=free, settings=settings)
    np.testing.assert_allclose(res.shifts[9], shift, atol=0.05)
    assert np.all(res.shifts[:9] == 0)
    assert res.median_error < 1e-4


def test_outliers_are_removed_and_inputs_checked(truth: CentralGeneric) -> None:
    poses, index, points, observed = _scene(truth, 8, seed=5)
    bad = observed.copy()
    bad[::50] += 25.0
    res = bundle_adjust(truth, poses, index, points, bad, settings=BundleSettings(max_iterations=8))
    assert not res.inlier[::50].any()
    assert res.inlier.sum() >= len(bad) - len(bad[::50])
    with pytest.raises(ValueError, match="frames without observations"):
        bundle_adjust(truth, [*poses, poses[0]], index, points, observed)


def test_coverage_warnings_name_regions(truth: CentralGeneric) -> None:
    coverage = np.ones((truth.grid_height - 3, truth.grid_width - 3), int)
    coverage[:2, :2] = 0
    lines = coverage_warnings(truth, coverage)
    assert len(lines) == 1 and "top-left" in lines[0] and "4 grid cells" in lines[0]
    assert "degrees off the axis" in lines[0]  # the corner of a wide lens, also in angle


def test_reduce_frames_is_the_schur_complement() -> None:
    """The reduced camera system against the dense formula, frames touching row spans only."""
    rng = np.random.default_rng(0)
    G, F = 700, 150
    Hgp = np.zeros((G, F, 8))
    for f in range(F):
        a = rng.integers(0, G - 100)
        Hgp[a:a + rng.integers(20, 600), f] = rng.normal(size=8)
    M = rng.normal(size=(F, 8, 8))
    Hpp_inv = np.linalg.inv(M @ M.transpose(0, 2, 1) + 8 * np.eye(8))
    B = rng.normal(size=(G, G))
    Hgg, bg, bp = B @ B.T, rng.normal(size=G), rng.normal(size=(F, 8))
    Y = np.einsum("gfi,fij->gfj", Hgp, Hpp_inv).reshape(G, -1)
    expected = Hgg - Y @ Hgp.reshape(G, -1).T
    S, c = reduce_frames(*(torch.as_tensor(x) for x in (Hgg, Hgp, Hpp_inv, bg, bp)))
    np.testing.assert_allclose(S.numpy(), expected, atol=1e-9)
    np.testing.assert_allclose(c.numpy(), bg - Y @ bp.reshape(-1), atol=1e-9)
    low, _ = reduce_frames(*(torch.as_tensor(x) for x in (Hgg, Hgp, Hpp_inv)), lower=True)
    np.testing.assert_allclose(np.tril(low.numpy()), np.tril(expected), atol=1e-9)


def test_leave_out_step_is_the_refit_without_those_frames(truth: CentralGeneric) -> None:
    """Each left-out camera, one step from the full fit, is near the converged bundle adjustment
    of the other frames (warm started from the full fit); leaving nothing out keeps the full
    fit's camera."""
    poses, index, points, observed = _scene(truth, 12, seed=6)
    observed = observed + np.random.default_rng(1).normal(0, 0.05, observed.shape)
    free = np.arange(12) % 3 == 0
    observed[free[index]] += [0.7, -0.4]
    start = fit_to_rays(START_CAM.pixel_to_ray, 320, 240, cell_px=40.0)
    settings = BundleSettings(max_iterations=20, tol=1e-12)
    full = bundle_adjust(start, poses, index, points, observed, shift_free=free, settings=settings)
    masks = [np.arange(12) < 4, np.arange(12) % 2 == 1, np.zeros(12, bool)]
    models = leave_out_models(full, masks, [start, truth, start])
    px = np.random.default_rng(2).uniform([20, 20], [300, 220], (500, 2))

    def moved(a: CentralGeneric, b: CentralGeneric) -> float:
        ra, rb = a.pixel_to_ray(px), b.pixel_to_ray(px)
        u, _ = b.project(ra @ _kabsch(ra, rb).T)
        return float(np.abs(u - px).max())

    for mask, prior, model in zip(masks[:2], [start, truth], models[:2], strict=True):
        keep = ~mask[index]
        frame = np.cumsum(~mask)[index[keep]] - 1
        refit = bundle_adjust(full.model, [p for p, m in zip(full.poses, mask, strict=True) if not m], frame,
                              points[keep], observed[keep], weights=full.inlier[keep].astype(float),
                              shift_free=free[~mask], settings=replace(settings, outlier_iteration=0),
                              prior=prior)
        assert moved(model, full.model) > 0.05
        assert moved(model, refit.model) < 0.1 * moved(model, full.model)
    assert moved(models[2], full.model) < 0.005
    # Folds that partition the frames give all frames' terms as their sums: the same cameras.
    folds = [np.arange(12) % 3 == k for k in range(3)]
    summed = leave_out_models(full, [*folds, masks[1]], [start, truth, start, truth])
    passed = leave_out_models(full, [masks[1], *folds], [truth, start, truth, start])
    for a, b in zip(summed, [*passed[1:], passed[0]], strict=True):
        np.testing.assert_allclose(a.grid, b.grid, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="one prior"):
        leave_out_models(full, masks, [start])
