"""Held-out validation (validation.py): the frame fit, the k-fold split and what it measures."""

from __future__ import annotations

import numpy as np
import pytest

from blurcalib.calib import validation
from blurcalib.calib.joint import JointSettings, calibrate_generic
from blurcalib.calib.sharp import calibrate_sharp
from blurcalib.calib.uncertainty import cross_validation_diff
from blurcalib.calib.validation import (
    ValidationSettings,
    assign_folds,
    fit_frames,
    generic_projector,
    kfold_validation,
    parametric_projector,
)
from blurcalib.camera.generic import fit_to_rays
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureFlags
from blurcalib.sim.truth import d435i_like_camera
from blurcalib.target.pattern import layout_pattern
from tests.calib.test_joint import simulated_features

SIZE = (1280, 720)
SHARP = int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME)
BLURRY = int(FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME)


def test_folds_deal_both_kinds_evenly() -> None:
    blurry = np.array([False] * 7 + [True] * 13)
    fold = assign_folds([f"f{i}" for i in range(20)], blurry, 5)
    for k in range(5):
        assert (fold == k).sum() == 4
        assert (fold[~blurry] == k).any() and (fold[blurry] == k).any()


def test_frame_fit_recovers_pose_and_shift() -> None:
    """A frame seen by the true camera, moved by a known shift, is fitted back from a wrong start."""
    truth = d435i_like_camera(0, 0.3).model
    model = fit_to_rays(truth.pixel_to_ray, *SIZE, cell_px=40.0)
    pattern = layout_pattern()
    P = pattern.points_3d()
    R = Pose.from_rvec_tvec([0.2, -0.3, 0.05], [0, 0, 0]).R
    pose = Pose(R, np.array([-0.1, -0.08, 0.45]))
    px = truth.project(pose.transform(P))
    ok = np.all((px > 5) & (px < np.array(SIZE) - 5), axis=1)
    shift = np.array([1.5, -0.7])
    R0 = Pose.from_rvec_tvec([0.21, -0.28, 0.06], [0, 0, 0]).R
    start = Pose(R0, pose.t + np.array([0.005, -0.004, 0.01]))
    frame = np.zeros(int(ok.sum()), np.int64)
    fit = fit_frames(generic_projector(model), [start], frame, P[ok], px[ok] + shift, np.array([True]),
                     shift_sigma_px=1e6)
    assert np.nanmax(np.linalg.norm(fit.residuals, axis=1)) < 2e-3
    np.testing.assert_allclose(fit.shifts[0], shift, atol=5e-3)
    fixed = fit_frames(parametric_projector(truth), [start], frame, P[ok], px[ok], np.array([False]))
    assert np.nanmax(np.linalg.norm(fixed.residuals, axis=1)) < 2e-3
    assert np.all(fixed.shifts == 0)


def _fits(cell_px: float, noise: float = 0.05):
    pattern = layout_pattern()
    sharp = simulated_features(8, 1, SHARP, "s")
    blurry = simulated_features(6, 2, BLURRY, "b", shift=2.0)
    rng = np.random.default_rng(3)
    for t in (sharp, blurry):
        t.x += rng.normal(0, noise, len(t))
        t.y += rng.normal(0, noise, len(t))
    parametric = calibrate_sharp(sharp, pattern, SIZE)
    settings = JointSettings(cell_px=cell_px)
    joint = calibrate_generic(sharp, blurry, parametric, pattern, SIZE, settings)
    alone = calibrate_generic(sharp, None, parametric, pattern, SIZE, settings)
    return pattern, sharp, parametric, joint, alone


@pytest.fixture(scope="module")
def coarse():
    return _fits(80.0)


def test_no_frame_is_scored_by_a_camera_that_saw_it(coarse, monkeypatch) -> None:
    pattern, sharp, parametric, joint, alone = coarse
    seen: list[set[str]] = []
    scored: list[tuple[int, set[str]]] = []
    leave_out, score = validation.leave_out_generic, validation._score_frames
    project = validation.generic_projector

    trained: dict[int, int] = {}
    alive: list[object] = []  # no id is reused while the spies look them up

    def spy_leave_out(fit, left_out, *args, **kwargs):
        models = leave_out(fit, left_out, *args, **kwargs)
        for mask, model in zip(left_out, models, strict=True):
            seen.append(set(np.array(fit.frames)[~np.asarray(mask)].tolist()))
            trained[id(model)] = len(seen) - 1
            alive.append(model)
        return models

    def spy_projector(model):
        projector = project(model)
        trained[id(projector)] = trained.get(id(model), -1)
        alive.append(projector)
        return projector

    def spy_score(projector, poses, fit, held, settings):
        scored.append((trained.get(id(projector), -1), set(np.array(fit.frames)[held].tolist())))
        return score(projector, poses, fit, held, settings)

    monkeypatch.setattr(validation, "leave_out_generic", spy_leave_out)
    monkeypatch.setattr(validation, "_score_frames", spy_score)
    monkeypatch.setattr(validation, "generic_projector", spy_projector)
    result = kfold_validation(joint, alone, parametric, sharp, pattern, SIZE, ValidationSettings(folds=4))
    assert result is not None and result.folds == 4
    assert len(seen) == 8  # two generic cameras per fold
    held_all: set[str] = set()
    for trained_on, held in scored:
        if trained_on >= 0:
            assert not (held & seen[trained_on])
        held_all |= held
    assert held_all == set(joint.frames)
    assert {result.fold_of[f] for f in joint.frames} == {0, 1, 2, 3}


def test_held_out_error_tells_the_cameras_apart(coarse) -> None:
    """Each camera scored on unseen frames: the generic camera near its training error (noise
    0.05 px per axis), the parametric one well above it (the lens is not Brown-Conrady)."""
    pattern, sharp, parametric, joint, alone = coarse
    v = kfold_validation(joint, alone, parametric, sharp, pattern, SIZE, halves=True)
    assert v is not None and set(v.scores) == {"generic", "generic_sharp", "parametric"}
    assert v.halves is None  # 4 sharp frames in a half: too few for its parametric camera
    g = v.scores["generic"]
    assert g.frames == 14 and g.observations > 1000
    assert joint.median_error < g.median_px < 1.6 * joint.median_error
    assert v.scores["parametric"].median_px > 1.4 * g.median_px
    assert g.sharp_median_px > 0 and g.blurry_median_px > 0
    assert v.to_dict()["generic"]["frames"] == 14


def test_too_few_frames_or_none() -> None:
    pattern, sharp, parametric, joint, alone = _fits(80.0)
    assert kfold_validation(joint, alone, parametric, sharp, pattern, SIZE,
                            ValidationSettings(method="none")) is None
    assert kfold_validation(joint, alone, parametric, sharp, pattern, SIZE,
                            ValidationSettings(min_frames=15)) is None
    with pytest.raises(ValueError, match="folds"):
        ValidationSettings(folds=1)


@pytest.mark.slow
def test_blurry_frames_widening_the_calibrated_area(coarse) -> None:
    """The sharp-only camera's area and grid are smaller than the joint camera's when blurry
    frames reach further; each refit keeps a prior on its own grid."""
    pattern = layout_pattern()
    sharp = simulated_features(8, 1, SHARP, "s")
    sharp = sharp.select((sharp.x > 200) & (sharp.x < 1080))
    blurry = simulated_features(6, 2, BLURRY, "b", shift=2.0)
    parametric = calibrate_sharp(sharp, pattern, SIZE)
    settings = JointSettings(cell_px=80.0)
    joint = calibrate_generic(sharp, blurry, parametric, pattern, SIZE, settings)
    alone = calibrate_generic(sharp, None, parametric, pattern, SIZE, settings)
    assert alone.model.grid.shape != joint.model.grid.shape
    v = kfold_validation(joint, alone, parametric, sharp, pattern, SIZE)
    assert v is not None and v.scores["generic_sharp"].frames == v.scores["generic"].frames == 14
    assert v.scores["generic"].median_px < 0.1 and v.scores["generic_sharp"].median_px < 0.1


@pytest.mark.slow
def test_halves_from_the_same_pass() -> None:
    """With enough sharp frames in each half, the validation also gives the cameras of two
    halves of the frames."""
    pattern = layout_pattern()
    sharp = simulated_features(12, 4, SHARP, "s")
    blurry = simulated_features(4, 5, BLURRY, "b", shift=2.0)
    rng = np.random.default_rng(6)
    for t in (sharp, blurry):
        t.x += rng.normal(0, 0.05, len(t))
        t.y += rng.normal(0, 0.05, len(t))
    parametric = calibrate_sharp(sharp, pattern, SIZE)
    joint = calibrate_generic(sharp, blurry, parametric, pattern, SIZE, JointSettings(cell_px=80.0))
    v = kfold_validation(joint, None, parametric, sharp, pattern, SIZE, halves=True)
    assert v is not None and v.halves is not None
    diff = cross_validation_diff(*v.halves)
    assert 0 < diff.median_px < 0.3  # 8 frames a half on a 80 px grid: 0.21 px (two refits: 0.22 px)
