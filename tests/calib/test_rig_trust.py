"""The rig's trust (blurcalib.calib.rig_trust): the extrinsics' uncertainty from the joint bundle's
normal equations against their true error, the extrinsics' sensitivity to each camera's grid
against finite differences, the uncertainty with the cameras' own errors against the true error of
simulated pairs, and the held-out error of the extrinsics against the simulated feature noise."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from blurcalib.calib.bundle import bundle_adjust
from blurcalib.calib.joint import JointSettings, calibrate_generic
from blurcalib.calib.rig_bundle import RigObservations, camera_sensitivity, rig_bundle_adjust
from blurcalib.calib.rig_calibration import RigCalibration, calibrate_rig, initial_rig
from blurcalib.calib.rig_trust import cameras_covariance, pair_uncertainty, rig_trust
from blurcalib.calib.sharp import calibrate_sharp
from blurcalib.calib.uncertainty import grid_covariance
from blurcalib.camera.generic import CentralGeneric, best_fit_rotation, tangent_basis
from blurcalib.geometry.pose import Pose
from blurcalib.sim.rig import RigSimulator, d435i_stereo_rig
from blurcalib.sim.rig_eval import extrinsic_error, truth_features
from blurcalib.sim.synth import SynthConfig
from blurcalib.target.pattern import layout_pattern
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
    (pair,) = rig_trust(calibration, folds=5, cameras=False)  # exact cameras
    assert (pair.i, pair.j) == (0, 1)
    assert pair.holdout_count > 0.9 * 2 * sum(len(o.set_index) for o in obs) / 2
    assert 0.05 < pair.holdout_px < 0.075  # 1.18 sigma for 0.05 px of noise per axis
    assert pair.translation_mm < 0.1 and pair.rotation_deg < 0.01
    assert set(pair.to_dict()) == {"cameras", "translation_uncertainty_mm", "rotation_uncertainty_deg",
                                   "holdout_error_px", "holdout_predictions"}


def _moved(model: CentralGeneric, dtheta: np.ndarray) -> CentralGeneric:
    """``model`` with its grid moved by the tangent parameters ``dtheta (G,)`` (node ``k``: columns
    ``2 k, 2 k + 1`` along its tangents), each node normalised again."""
    v = model.grid.reshape(-1, 3)
    t = tangent_basis(torch.tensor(v)).numpy()
    d = dtheta.reshape(-1, 2)
    moved = v + d[:, :1] * t[:, 0] + d[:, 1:] * t[:, 1]
    return model.with_grid((moved / np.linalg.norm(moved, axis=1, keepdims=True)).reshape(model.grid.shape))


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    return 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])


def test_sensitivity_to_the_cameras_matches_finite_differences(model: CentralGeneric) -> None:
    """Each camera's grid moved a little: the rig bundle's extrinsics move as ``dE/dtheta``
    predicts (implicit-function theorem), camera 0's (the rig's frame) as well as camera 1's."""
    truth = _rig_truth(2)
    _, obs, own, _ = _scene(model, truth, 6, seed=1, noise_px=0.05)
    camera_tr_rig, poses = initial_rig(own)
    res = rig_bundle_adjust([model, model], camera_tr_rig, poses, obs)
    sensitivity = camera_sensitivity(res, obs)
    assert [d.shape for d in sensitivity] == [(6, model.grid[..., 0].size * 2)] * 2
    rng = np.random.default_rng(0)
    for c in range(2):
        dtheta = rng.normal(size=sensitivity[c].shape[1]) * 1e-5
        models = [model, model]
        models[c] = _moved(model, dtheta)
        moved = rig_bundle_adjust(models, res.rig.camera_tr_rig, res.rig_tr_global, obs).rig.camera_tr_rig[1]
        before = res.rig.camera_tr_rig[1]
        measured = np.concatenate([_rotation_vector(moved.R @ before.R.T), moved.t - before.t])
        predicted = sensitivity[c] @ dtheta
        assert np.linalg.norm(measured - predicted) < 0.05 * np.linalg.norm(predicted)
    # a rotation of a camera's grid is its gauge, which the extrinsics take up: the grid
    # perturbations of the covariance folded into them turn the camera's rays by no rotation
    cam = bundle_adjust(model, [p for p in own[0] if p is not None], obs[0].set_index, obs[0].points,
                        obs[0].observed)
    draw = rng.multivariate_normal(np.zeros(len(sensitivity[0][0])), grid_covariance(cam).numpy(),
                                   method="eigh") * 0.1
    grid = torch.as_tensor(cam.model.grid.reshape(-1, 3).copy())
    g = torch.linalg.cross(grid[:, None, :].expand(-1, 2, -1), tangent_basis(grid), dim=-1).reshape(-1, 3)
    omega = np.array([2e-6, -1e-6, 3e-6])
    xx, yy = np.meshgrid(np.linspace(0.0, 319.0, 21), np.linspace(0.0, 239.0, 16))  # grid_covariance's
    px = np.column_stack([xx.ravel(), yy.ravel()])
    rays = cam.model.pixel_to_ray(px)
    for extra, turn in ((np.zeros(3), 0.0), (omega, float(np.linalg.norm(omega)))):
        moved = _moved(cam.model, draw + g.numpy() @ extra).pixel_to_ray(px)
        Q = best_fit_rotation(rays, moved)
        spread = np.sqrt(np.mean(np.sum((moved - rays) ** 2, axis=1)))
        assert spread > 10 * np.linalg.norm(omega)
        assert abs(np.linalg.norm(_rotation_vector(Q)) - turn) < 0.02 * np.linalg.norm(omega)

@pytest.mark.slow  # three simulated pairs, each camera calibrated
def test_uncertainty_with_the_cameras_matches_the_true_error() -> None:
    """Simulated 640 x 360 pairs, 6 sharp sets each, the features the truth's with 0.05 px of noise;
    each camera calibrated as ``calibrate`` does (its lens deviation is not Brown-Conrady), then the
    rig. The joint bundle alone (cameras held fixed) predicts the translation error some 10 times too
    small; with the cameras' own errors folded in the true error is 0.5-2 times the prediction (RMS
    of the ratio over the seeds)."""
    pattern = layout_pattern()
    size = (640, 360)
    ratios = []
    for seed in range(3):
        rig = d435i_stereo_rig(seed, scale=0.5)
        sim = RigSimulator(SynthConfig(sharp=6, blurry=0, seed=seed, square_px=(24.0, 30.0)), rig, pattern)
        sets = [sim.image_set(k) for k in range(6)]
        rng = np.random.default_rng(seed)
        cams = []
        for c in range(2):
            table = truth_features([s.frames[c] for s in sets if s.frames[c] is not None], pattern, 0.05, 0.0,
                                   rng, size)
            cams.append(calibrate_generic(table, None, calibrate_sharp(table, pattern, size), pattern, size,
                                          JointSettings(cell_px=25.0)))
        result = calibrate_rig(cams)
        bundle = result.bundle
        err = extrinsic_error(rig, bundle.rig)
        alone = pair_uncertainty(bundle.rig, bundle.covariance, 0, 1)
        both = pair_uncertainty(bundle.rig, bundle.covariance + cameras_covariance(result), 0, 1)
        assert both[0] > alone[0] and both[1] > alone[1]
        ratios.append([err.translation_mm / alone[0], err.rotation_deg / alone[1],
                       err.translation_mm / both[0], err.rotation_deg / both[1]])
    rms = np.sqrt(np.mean(np.square(ratios), axis=0))
    assert rms[0] > 4.0 and rms[1] > 2.0  # the features' noise alone: far too small
    assert 0.5 < rms[2] < 2.0 and 0.5 < rms[3] < 2.0
    (pair,) = rig_trust(result, folds=0)
    assert (pair.translation_mm, pair.rotation_deg) == pytest.approx(both, rel=1e-9)
