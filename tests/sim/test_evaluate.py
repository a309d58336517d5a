"""A calibrated camera against the true one: the total error and its split into the best-fit
focal lengths and principal point (an affine image map) and the shape error that remains; and
extracted star centres against their true ones after the frame's pose."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.homography import apply_homography
from blurcalib.sim.evaluate import camera_accuracy, pose_consistent_errors
from blurcalib.sim.truth import TrueCamera

LENS = BrownConrady(fx=640.0, fy=641.0, cx=639.0, cy=361.0, k1=0.05, k2=-0.06, p1=0.001, p2=-0.0005,
                    k3=0.02, width=1280, height=720)
CORNER = float(np.hypot(1279 / 2, 719 / 2))


def test_a_focal_length_error_is_all_scale_and_no_shape() -> None:
    eps = 1e-4
    estimate = dataclasses.replace(LENS, fx=LENS.fx * (1 + eps), fy=LENS.fy * (1 + eps))
    a = camera_accuracy(TrueCamera(LENS), estimate)
    assert a.median > 0.3 * eps * CORNER
    assert a.scale_px == pytest.approx(eps * CORNER, rel=0.05)
    assert a.shape_median < 0.05 * a.median
    assert a.defined == 1.0


def test_a_deviation_field_is_shape() -> None:
    wave = np.array([[0.2, -0.1, 2.0, 1.0, 0.3]])
    a = camera_accuracy(TrueCamera(LENS, wave), LENS)
    assert 0.05 < a.shape_median < 0.25
    assert abs(a.scale_px) < 0.05


def test_pose_consistent_errors_remove_a_pose_change_and_keep_a_features_own_error() -> None:
    """A homography of the whole frame (the target's pose) is no error; one star centre moved by
    0.3 px is, and moves no other (least median of squares); with fewer than 8 features only the
    mean offset is removed."""
    gy, gx = np.mgrid[0:6, 0:8]
    truth_xy = np.stack([100.0 + 40.0 * gx.ravel(), 80.0 + 40.0 * gy.ravel()], axis=1)
    H = np.array([[1.02, 0.03, 4.0], [-0.02, 0.99, -3.0], [2e-5, -1e-5, 1.0]])
    xy = apply_homography(H, truth_xy)
    xy[7] += np.array([0.18, 0.24])
    err = pose_consistent_errors(xy, truth_xy)
    assert abs(err[7] - 0.3) < 1e-3 and np.delete(err, 7).max() < 1e-3, err
    few = truth_xy[:5] + np.array([2.0, -1.0])
    few[0, 0] += 0.3
    np.testing.assert_allclose(pose_consistent_errors(few, truth_xy[:5])[1:], 0.06, atol=1e-9)
