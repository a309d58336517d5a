"""The rig's trust (blurcalib.calib.rig_trust): the extrinsics' uncertainty from the joint bundle's
normal equations against their true error, and the held-out error of the extrinsics against the
simulated feature noise."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from blurcalib.calib.rig_bundle import RigObservations, rig_bundle_adjust
from blurcalib.calib.rig_calibration import RigCalibration, calibrate_rig, initial_rig
from blurcalib.calib.rig_trust import pair_uncertainty, rig_trust
from blurcalib.camera.generic import CentralGeneric
from blurcalib.geometry.pose import Pose
from tests.bundle_scene import bumped_truth
from tests.calib.test_rig_bundle import _rig_truth, _rotation_deg, _scene


@pytest.fixture(scope="module")
def model() -> CentralGeneric:
    return bumped_truth()


def _fit(model: CentralGeneric, truth: list[Pose], sets: int, seed: int, noise_px: float
         ) -> tuple[float, float, float, float]:
    """The uncertainty ``(mm, deg)`` and true error ``(mm, deg)`` of ``camera 1 <- camera 0``."""
    _, obs, own, _ = _scene(model, truth, sets, seed=seed, noise_px=noise_px)
    camera_tr_rig, poses = initial_rig(own)
    res = rig_bundle_adjust([model, model], camera_tr_rig, poses, obs)
    mm, deg = pair_uncertainty(res.rig, res.covariance, 0, 1)
    rel = res.rig.relative(0, 1)
    return mm, deg, float(np.linalg.norm(rel.t - truth[1].t)) * 1000.0, _rotation_deg(rel, truth[1])


def test_uncertainty_of_exact_data_is_nil(model: CentralGeneric) -> None:
    exact_mm, exact_deg, err_mm, _ = _fit(model, _rig_truth(2), 4, seed=1, noise_px=0.0)
    assert exact_mm < 1e-5 and exact_deg < 1e-6 and err_mm < 1e-4


@pytest.mark.slow  # three rig bundles
def test_uncertainty_is_small_and_shrinks_with_more_sets(model: CentralGeneric) -> None:
    truth = _rig_truth(2)
    few_mm, few_deg, err_mm, err_deg = _fit(model, truth, 4, seed=1, noise_px=0.05)
    many_mm, many_deg, _, _ = _fit(model, truth, 16, seed=1, noise_px=0.05)
    assert 0.0 < few_mm < 0.2 and 0.0 < few_deg < 0.03  # a 320 x 240 camera, 4 sets
    assert many_mm < 0.7 * few_mm and many_deg < 0.7 * few_deg  # about 1/2 for 4 times the sets
    assert err_mm < 4.0 * few_mm and err_deg < 4.0 * few_deg


@pytest.mark.slow  # a three-camera bundle and 1500 draws
def test_pair_uncertainty_through_a_third_camera(model: CentralGeneric) -> None:
    truth = _rig_truth(3)
    _, obs, own, _ = _scene(model, truth, 6, seed=3, noise_px=0.05)
    camera_tr_rig, poses = initial_rig(own)
    res = rig_bundle_adjust([model] * 3, camera_tr_rig, poses, obs)
    assert res.covariance.shape == (12, 12)
    # Monte Carlo: the extrinsics drawn from the covariance, each pair's error sizes measured
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(np.zeros(12), res.covariance, 1500)
    for i, j in ((0, 1), (1, 2), (0, 2)):
        mm, deg = pair_uncertainty(res.rig, res.covariance, i, j)
        assert 0.0 < mm < 0.1 and 0.0 < deg < 0.01
        want = res.rig.relative(i, j)
        t_err, r_err = [], []
        for d in draws:
            moved = [res.rig.camera_tr_rig[0]] + [
                Pose(cv2.Rodrigues(d[6 * k:6 * k + 3])[0] @ p.R, p.t + d[6 * k + 3:6 * k + 6])
                for k, p in enumerate(res.rig.camera_tr_rig[1:])]
            got = moved[j].compose(moved[i].inverse())
            t_err.append(np.sum((got.t - want.t) ** 2))
            r_err.append(np.radians(_rotation_deg(got, want)) ** 2)
        assert abs(np.sqrt(np.mean(t_err)) * 1000.0 / mm - 1.0) < 0.08
        assert abs(np.degrees(np.sqrt(np.mean(r_err))) / deg - 1.0) < 0.08
    assert np.isnan(pair_uncertainty(res.rig, np.zeros((6, 6)), 0, 1)[0])


def _calibration(model: CentralGeneric, obs: list[RigObservations], truth: list[Pose], poses: list[Pose],
                 blurry: np.ndarray) -> list[SimpleNamespace]:
    """Each camera as its own calibration would give it: its frames, observations and exact poses."""
    cams = []
    for c, o in enumerate(obs):
        names = np.array([f"{s:04d}" for s in o.set_index])
        frames = sorted(set(names.tolist()))
        cams.append(SimpleNamespace(
            model=model, frames=frames, frame=names, points=o.points, observed=o.observed,
            weight=np.ones(len(names)), inlier=np.ones(len(names), bool),
            poses={n: truth[c].compose(poses[int(n)]) for n in frames},
            blurry_frames=[n for n in frames if blurry[c, int(n)]],
            shifts={n: np.zeros(2) for n in frames if blurry[c, int(n)]}))
    return cams


@pytest.mark.slow  # five folds of the rig bundle
def test_holdout_error_is_close_to_the_feature_noise(model: CentralGeneric) -> None:
    truth = _rig_truth(2)
    blurry = np.zeros((2, 10), bool)
    blurry[1, 5:] = True
    poses, obs, _, _ = _scene(model, truth, 10, seed=6, noise_px=0.05, blurry=blurry)
    cams = _calibration(model, obs, truth, poses, blurry)
    calibration: RigCalibration = calibrate_rig(cams)  # type: ignore[arg-type]
    (pair,) = rig_trust(calibration, folds=5)
    assert (pair.i, pair.j) == (0, 1)
    assert pair.holdout_count > 0.9 * 2 * sum(len(o.set_index) for o in obs) / 2
    assert 0.05 < pair.holdout_px < 0.075  # 1.18 sigma for 0.05 px of noise per axis
    assert pair.translation_mm < 0.1 and pair.rotation_deg < 0.01
    assert set(pair.to_dict()) == {"cameras", "translation_uncertainty_mm", "rotation_uncertainty_deg",
                                   "holdout_error_px", "holdout_predictions"}
