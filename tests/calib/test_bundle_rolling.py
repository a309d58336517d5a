"""The bundle adjustment with the rolling shutter's per-frame parameters (``RollingRows``) on
synthetic observations with a known answer."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from blurcalib.calib.bundle import BundleSettings, bundle_adjust
from blurcalib.calib.frame_block import RollingRows, rolling_points
from blurcalib.camera.generic import CentralGeneric, fit_to_rays
from blurcalib.camera.shutter import row_time
from blurcalib.geometry.pose import Pose
from tests.bundle_scene import TARGET, TRUE_CAM, bumped_truth, observed_scene

torch.set_num_threads(1)

SETTINGS = BundleSettings(smoothness_px=1e4, outlier_iteration=0, max_iterations=40, tol=1e-14)


def _rolling_projection(truth: CentralGeneric, pose: Pose, theta: np.ndarray, target: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The rolling model's projections of ``target`` (each point at its own row's instant: the row
    iterated from the pose's projection) and whether they are inside."""
    kw = {"dtype": torch.float64}
    R, t = torch.tensor(pose.R[None], **kw), torch.tensor(pose.t[None], **kw)
    fr = torch.zeros(len(target), dtype=torch.int64)
    P, th = torch.as_tensor(target, **kw), torch.as_tensor(theta[None], **kw)
    px, inside = truth.project(pose.transform(target))
    for _ in range(6):
        y = torch.as_tensor(row_time(px[:, 1], 240, 1.0), **kw)
        X, _, _ = rolling_points(R, t, th, fr, P, y)
        px, inside = truth.project(X.numpy(), px)
    return px, inside


def _scene(truth: CentralGeneric, frames: int, moving: int, seed: int):
    """A 12 x 9 planar target (2 cm) seen from ``frames`` poses, the last ``moving`` of them read
    by a rolling shutter with a random twist and curvature; exact projections."""
    rng = np.random.default_rng(seed)

    def view(pose: Pose, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        theta = np.zeros(12)
        if k >= frames - moving:
            theta = np.concatenate([rng.normal(0, 0.04, 3), rng.normal(0, 0.015, 3),
                                    rng.normal(0, 0.02, 3), rng.normal(0, 0.005, 3)])
        return (*_rolling_projection(truth, pose, theta, TARGET), theta)

    poses, thetas, index, points, observed = observed_scene(rng, frames, (60, 50), (260, 190), view)
    return poses, np.array(thetas), index, points, observed


@pytest.fixture(scope="module")
def truth() -> CentralGeneric:
    return bumped_truth()


def _camera_error(truth: CentralGeneric, model: CentralGeneric) -> float:
    """Median distance (px) between the cameras over the image after the best-fit rotation."""
    px = np.random.default_rng(4).uniform([20, 20], [300, 220], (2000, 2))
    a, b = truth.pixel_to_ray(px), model.pixel_to_ray(px)
    U, _, Vt = np.linalg.svd(b.T @ a)
    Q = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    u, inside = model.project(a @ Q.T)
    return float(np.median(np.linalg.norm(u - px, axis=1)[inside]))


def test_rolling_parameters_fitted_with_the_camera(truth: CentralGeneric) -> None:
    """Ten frames, four read by a rolling shutter: with their rolling parameters in the bundle the
    observations fit exactly and the camera is recovered; without, they fit no rigid pose and the
    camera is off by far more."""
    poses, _, index, points, observed = _scene(truth, 10, 4, seed=1)
    start = fit_to_rays(TRUE_CAM.with_params(fx=303.0, k1=-0.10).pixel_to_ray, 320, 240, cell_px=40.0)
    moving = np.arange(10) >= 6
    rows = RollingRows(row_time(observed[:, 1], 240, 1.0), moving, twist_sigma=30.0)
    res = bundle_adjust(start, poses, index, points, observed, settings=SETTINGS, rolling=rows)
    rigid = bundle_adjust(start, poses, index, points, observed, settings=SETTINGS)
    assert res.theta is not None and np.all(res.theta[~moving] == 0.0)
    assert res.median_error < 1e-3
    assert rigid.median_error > 20 * res.median_error
    assert _camera_error(truth, res.model) < 0.005
    assert _camera_error(truth, rigid.model) > 5 * _camera_error(truth, res.model)


def test_rolling_rows_without_moving_frames_change_nothing(truth: CentralGeneric) -> None:
    """Rolling rows with no moving frame give the global-shutter bundle adjustment's camera."""
    poses, _, index, points, observed = _scene(truth, 6, 0, seed=2)
    start = fit_to_rays(TRUE_CAM.with_params(fx=303.0, k1=-0.10).pixel_to_ray, 320, 240, cell_px=40.0)
    rows = RollingRows(row_time(observed[:, 1], 240, 1.0), np.zeros(6, bool))
    a = bundle_adjust(start, poses, index, points, observed, settings=SETTINGS, rolling=rows)
    b = bundle_adjust(start, poses, index, points, observed, settings=SETTINGS)
    assert np.abs(a.model.grid - b.model.grid).max() < 1e-9
    assert np.all(a.theta == 0.0)


def test_rolling_rows_shapes_are_checked(truth: CentralGeneric) -> None:
    poses, _, index, points, observed = _scene(truth, 3, 0, seed=3)
    with pytest.raises(ValueError, match="rolling rows"):
        bundle_adjust(truth, poses, index, points, observed,
                      rolling=RollingRows(np.zeros(len(index) - 1), np.zeros(3, bool)))
