"""The rig bundle (blurcalib.calib.rig_bundle) and its initialisation (blurcalib.calib.rig_calibration):
extrinsics recovered from exact and noisy projections, a camera that misses sets, a camera linked
only through another, and refused inputs."""

from __future__ import annotations

import numpy as np
import pytest

from blurcalib.calib.rig_bundle import RigObservations, rig_bundle_adjust
from blurcalib.calib.rig_calibration import RigError, initial_rig
from blurcalib.camera.generic import CentralGeneric
from blurcalib.geometry.pose import Pose
from tests.bundle_scene import TARGET, bumped_truth, random_pose


def _rotation_deg(a: Pose, b: Pose) -> float:
    c = (np.trace(a.R @ b.R.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _rig_truth(cameras: int) -> list[Pose]:
    """Camera c sits 50 mm right of camera c-1, turned 1 degree about y."""
    out = []
    for c in range(cameras):
        R = Pose.from_rvec_tvec([0.0, np.radians(1.0) * c, 0.01 * c], [0.0, 0.0, 0.0]).R
        out.append(Pose(R, -R @ np.array([0.05 * c, 0.0, 0.0])))
    return out


def _scene(model: CentralGeneric, extrinsics: list[Pose], sets: int, seed: int, noise_px: float,
           seen: np.ndarray | None = None, blurry: np.ndarray | None = None
           ) -> tuple[list[Pose], list[RigObservations], list[list[Pose | None]], np.ndarray]:
    """``sets`` target poses seen by camera 0 (and, where ``seen[c, s]``, camera c); the
    observations (with a shift of up to 3 px on ``blurry[c, s]`` frames), each camera's own
    slightly wrong target poses and the true shifts ``(C, S, 2)``."""
    rng = np.random.default_rng(seed)
    C = len(extrinsics)
    seen = np.ones((C, sets), bool) if seen is None else seen
    blurry = np.zeros((C, sets), bool) if blurry is None else blurry
    truth_shift = np.where(blurry[..., None], rng.uniform(-3, 3, (C, sets, 2)), 0.0)
    poses: list[Pose] = []
    while len(poses) < sets:
        pose = random_pose(rng, (100.0, 80.0), (220.0, 160.0))
        counts = [model.project(e.compose(pose).transform(TARGET))[1].sum() for e in extrinsics]
        if min(counts) >= 30:
            poses.append(pose)
    obs, own = [], []
    for c, e in enumerate(extrinsics):
        idx, pts, px, mine = [], [], [], []
        for s, pose in enumerate(poses):
            if not seen[c, s]:
                mine.append(None)
                continue
            u, inside = model.project(e.compose(pose).transform(TARGET))
            idx.append(np.full(int(inside.sum()), s))
            pts.append(TARGET[inside])
            px.append(u[inside] + truth_shift[c, s] + rng.normal(0, noise_px, (int(inside.sum()), 2)))
            wrong = Pose.from_rvec_tvec(rng.normal(0, 0.01, 3), rng.normal(0, 0.003, 3))
            mine.append(wrong.compose(e.compose(pose)))
        n = sum(len(i) for i in idx)
        obs.append(RigObservations(np.concatenate(idx), np.concatenate(pts), np.concatenate(px), np.ones(n),
                                   blurry[c]))
        own.append(mine)
    return poses, obs, own, truth_shift


@pytest.fixture(scope="module")
def model() -> CentralGeneric:
    return bumped_truth()


def test_exact_two_camera_rig_recovers_extrinsics(model: CentralGeneric) -> None:
    truth = _rig_truth(2)
    poses, obs, own, _ = _scene(model, truth, 5, seed=1, noise_px=0.0)
    camera_tr_rig, sets = initial_rig(own)
    assert _rotation_deg(camera_tr_rig[1], truth[1]) < 2.0
    res = rig_bundle_adjust([model, model], camera_tr_rig, sets, obs)
    rel = res.rig.relative(0, 1)
    assert _rotation_deg(rel, truth[1]) < 1e-5
    assert np.linalg.norm(rel.t - truth[1].t) < 1e-7
    assert np.all(res.median_error < 1e-5)
    for got, want in zip(res.rig_tr_global, poses, strict=True):
        assert np.linalg.norm(got.t - want.t) < 1e-7


@pytest.mark.slow
def test_noisy_rig_with_missed_sets_and_blurry_shifts(model: CentralGeneric) -> None:
    truth = _rig_truth(2)
    seen = np.ones((2, 12), bool)
    seen[1, :4] = False  # camera 1 misses four sets
    blurry = np.zeros((2, 12), bool)
    blurry[:, 6:] = True
    blurry[0, 6] = False  # set 6: camera 0 sharp anchors camera 1's blurry frame
    _, obs, own, truth_shift = _scene(model, truth, 12, seed=2, noise_px=0.05, seen=seen, blurry=blurry)
    camera_tr_rig, sets = initial_rig(own)
    res = rig_bundle_adjust([model, model], camera_tr_rig, sets, obs)
    rel = res.rig.relative(0, 1)
    assert _rotation_deg(rel, truth[1]) < 0.01
    assert np.linalg.norm(rel.t - truth[1].t) < 1e-4  # 0.1 mm
    assert np.all((res.median_error > 0.02) & (res.median_error < 0.1))
    assert np.abs(res.shifts[1, 6] - truth_shift[1, 6]).max() < 0.1
    assert np.all(res.shifts[~blurry] == 0.0)


@pytest.mark.slow
def test_camera_linked_through_another(model: CentralGeneric) -> None:
    truth = _rig_truth(3)
    seen = np.ones((3, 9), bool)
    seen[2, :5] = False
    seen[0, 5:] = False  # cameras 0 and 2 share no set: linked through camera 1
    _, obs, own, _ = _scene(model, truth, 9, seed=3, noise_px=0.0, seen=seen)
    camera_tr_rig, sets = initial_rig(own)
    res = rig_bundle_adjust([model] * 3, camera_tr_rig, sets, obs)
    assert _rotation_deg(res.rig.relative(0, 2), truth[2]) < 1e-5
    assert np.linalg.norm(res.rig.relative(0, 2).t - truth[2].t) < 1e-7


def test_refused_inputs(model: CentralGeneric) -> None:
    truth = _rig_truth(2)
    seen = np.ones((3, 6), bool)
    seen[2, :] = [False, False, False, True, True, True]
    seen[:2, 3:] = False
    _, _, own, _ = _scene(model, [*truth, truth[1]], 6, seed=4, noise_px=0.0, seen=seen)
    with pytest.raises(RigError, match="camera 2 shares no image set"):
        initial_rig(own)
    _, obs, own, _ = _scene(model, truth, 3, seed=5, noise_px=0.0)
    camera_tr_rig, sets = initial_rig(own)
    with pytest.raises(ValueError, match="two or more cameras"):
        rig_bundle_adjust([model], camera_tr_rig[:1], sets, obs[:1])
    padded = [RigObservations(o.set_index, o.points, o.observed, o.weights, np.zeros(4, bool)) for o in obs]
    with pytest.raises(ValueError, match="without observations"):
        rig_bundle_adjust([model, model], camera_tr_rig, [*sets, sets[0]], padded)
