"""Parametric calibration of the sharp set on simulated ground truth (no rendering: exact geometry)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from blurcalib.calib import parametric_adjustment
from blurcalib.calib.joint import JointSettings
from blurcalib.calib.sequence import (
    BLURRY_FLAGS,
    BlurryFrame,
    SequenceCancelledError,
    SequenceSettings,
    Stage,
    calibrate_features,
)
from blurcalib.calib.sharp import (
    Calibration,
    CalibrationError,
    CalibrationFileError,
    calibrate_sharp,
    load_calibration,
    reprojection_errors,
    save_calibration,
    solve_pose,
)
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.validation import ValidationSettings
from blurcalib.camera.parametric import BrownConrady, load_camera_yaml, project_points
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureFlags, FeatureTable
from blurcalib.sim.synth import sample_pose
from blurcalib.sim.truth import TrueCamera, d435i_like_camera
from blurcalib.target.pattern import StarPattern, layout_pattern

NOISE_PX = 0.05
IMAGE_SIZE = (1280, 720)


@pytest.fixture(scope="module")
def pattern() -> StarPattern:
    return layout_pattern()


@pytest.fixture(scope="module")
def true_camera() -> BrownConrady:
    return d435i_like_camera().model


def simulate(pattern: StarPattern, camera: BrownConrady, num_frames: int, seed: int,
             points: np.ndarray | None = None) -> tuple[FeatureTable, dict[str, Pose]]:
    """Observations of ``num_frames`` random poses: exact projections plus N(0, 0.05 px) noise."""
    rng = np.random.default_rng(seed)
    true_points = pattern.points_3d() if points is None else points
    tables, poses = [], {}
    for f in range(num_frames):
        pose = sample_pose(pattern, TrueCamera(camera), rng, 50.0, (24.0, 42.0))
        px = project_points(camera, pose, true_points) + rng.normal(0.0, NOISE_PX, (len(true_points), 2))
        inside = ((pose.transform(true_points)[:, 2] > 0) & (px[:, 0] >= 0) & (px[:, 0] <= camera.width - 1)
                  & (px[:, 1] >= 0) & (px[:, 1] <= camera.height - 1))
        ids = np.flatnonzero(inside)
        nominal = pattern.points_3d(ids)
        name = f"sharp/{f:04d}.png"
        poses[name] = pose
        tables.append(FeatureTable(
            [name] * len(ids), ids, pattern.features[ids, 0], pattern.features[ids, 1], nominal[:, 0],
            nominal[:, 1], px[ids, 0], px[ids, 1], np.ones(len(ids)),
            np.full(len(ids), FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME)))
    return FeatureTable.concat(tables), poses


def assert_intrinsics_match(camera: BrownConrady, truth: BrownConrady) -> None:
    assert camera.fx == pytest.approx(truth.fx, rel=1e-3)
    assert camera.fy == pytest.approx(truth.fy, rel=1e-3)
    assert abs(camera.cx - truth.cx) < 0.5 and abs(camera.cy - truth.cy) < 0.5
    # the lens mapping itself: ideal pixels of the central 90 % of the image map alike
    u, v = np.meshgrid(np.linspace(64, 1216, 17), np.linspace(36, 684, 11))
    rays = np.column_stack([(u.ravel() - truth.cx) / truth.fx, (v.ravel() - truth.cy) / truth.fy,
                            np.ones(u.size)])
    assert np.abs(camera.project(rays) - truth.project(rays)).max() < 0.25


@pytest.fixture(scope="module")
def clean(pattern: StarPattern, true_camera: BrownConrady
          ) -> tuple[FeatureTable, dict[str, Pose], Calibration]:
    table, poses = simulate(pattern, true_camera, 12, seed=0)
    return table, poses, calibrate_sharp(table, pattern, IMAGE_SIZE)


def test_clean_data_recovers_the_camera(clean, true_camera: BrownConrady, pattern: StarPattern) -> None:
    table, poses, calib = clean
    assert_intrinsics_match(calib.camera, true_camera)
    assert (calib.camera.width, calib.camera.height) == IMAGE_SIZE
    # error norms of 2-D N(0, s^2) noise: median 1.18 s, RMS 1.41 s (a little less after the fit)
    assert 0.9 * NOISE_PX < calib.median_error < 1.3 * NOISE_PX
    assert 1.2 * NOISE_PX < calib.rms_error < 1.5 * NOISE_PX
    assert calib.num_frames == 12 and calib.num_observations == len(table)
    assert (~calib.inlier).sum() <= 1
    # clean data converge like Gauss-Newton: a few Jacobians (4 measured) in one or two rounds
    assert calib.rounds <= 2 and calib.iterations <= 12
    for name, pose in poses.items():
        rel = calib.poses[name].compose(pose.inverse())
        assert np.linalg.norm(rel.rvec) < 1e-3 and np.linalg.norm(pose.t - calib.poses[name].t) < 1e-3
    observed = calib.point_ids
    assert set(observed.tolist()) == set(table.feature_id.tolist())
    assert np.abs(calib.points[observed] - pattern.points_3d(observed)).max() < 1e-4
    assert np.isnan(calib.points[np.setdiff1d(np.arange(pattern.num_features), observed)]).all()
    report = json.loads(json.dumps(calib.to_dict()))
    assert report["median_error_px"] == calib.median_error and set(report["frames"]) == set(poses)


def test_robust_fit_flags_gross_outliers(pattern: StarPattern, true_camera: BrownConrady) -> None:
    table, _ = simulate(pattern, true_camera, 12, seed=1)
    rng = np.random.default_rng(5)
    bad = rng.choice(len(table), 15, replace=False)
    angle = rng.uniform(0.0, 2 * np.pi, len(bad))
    table.x[bad] += 5.0 * np.cos(angle)
    table.y[bad] += 5.0 * np.sin(angle)
    junk = table.select(np.arange(30))  # repeats of real observations, filtered out: ignored
    junk.x += 40.0
    junk.flags[:] = FeatureFlags.FILTERED_OUT
    calib = calibrate_sharp(FeatureTable.concat([table, junk]), pattern, IMAGE_SIZE)
    assert_intrinsics_match(calib.camera, true_camera)
    assert calib.num_observations == len(table)
    out = ~calib.inlier
    flagged = set(zip(calib.frame[out].tolist(), calib.feature_id[out].tolist(), strict=True))
    injected = set(zip(table.frame[bad].tolist(), table.feature_id[bad].tolist(), strict=True))
    assert injected <= flagged and len(flagged - injected) <= 1
    assert np.all(np.sort(calib.errors[~calib.inlier])[-len(bad):] > 4.5)
    assert calib.rms_error < 1.5 * NOISE_PX


def test_outlier_rounds_end_at_flips_at_the_margin(pattern: StarPattern, true_camera: BrownConrady,
                                                   monkeypatch) -> None:
    """Over 10,000 observations the outlier rounds end once at most 1e-4 of them change side, each
    near the threshold: the camera is the one of rounds run until the inlier set is stable, in
    fewer rounds; a flip far from the threshold (a gross error) never ends them."""
    # the rule itself: threshold 0.2 px over 20,000 observations (at most 2 may change side)
    assert parametric_adjustment.settled(np.empty(0), 0.2, 100)
    assert parametric_adjustment.settled(np.array([0.25, 0.15]), 0.2, 20_000)
    assert not parametric_adjustment.settled(np.array([0.25, 0.15, 0.21]), 0.2, 20_000)
    assert not parametric_adjustment.settled(np.array([2.0]), 0.2, 20_000)
    assert not parametric_adjustment.settled(np.array([0.25]), 0.2, 9_999)
    table, _ = simulate(pattern, true_camera, 40, seed=1)
    assert len(table) > 10_000
    rng = np.random.default_rng(9)
    bad = rng.choice(len(table), 15, replace=False)
    table.x[bad] += 5.0
    settled = calibrate_sharp(table, pattern, IMAGE_SIZE)
    monkeypatch.setattr(parametric_adjustment, "SETTLED_SHARE", 0.0)
    stable = calibrate_sharp(table, pattern, IMAGE_SIZE)
    assert settled.rounds < stable.rounds
    assert (settled.inlier != stable.inlier).sum() <= 1e-4 * len(table)
    assert not settled.inlier[bad].any() and not stable.inlier[bad].any()
    u, v = np.meshgrid(np.linspace(0, 1279, 17), np.linspace(0, 719, 11))
    rays = np.column_stack([(u.ravel() - true_camera.cx) / true_camera.fx,
                            (v.ravel() - true_camera.cy) / true_camera.fy, np.ones(u.size)])
    truth = true_camera.project(rays)
    moved = np.abs(settled.camera.project(rays) - stable.camera.project(rays)).max()
    # far less than the calibration's own error (noise 0.05 px): 0.0008 against 0.09 px measured
    assert moved < 0.1 * np.abs(stable.camera.project(rays) - truth).max()


def test_warm_start_from_a_calibration_of_more_frames(pattern: StarPattern,
                                                     true_camera: BrownConrady) -> None:
    """A fit of some frames started from the calibration of all of them (as the held-out folds
    are) reaches the cold start's camera and keeps the same gross outliers out; a frame the start
    has not seen makes it start cold."""
    table, _ = simulate(pattern, true_camera, 12, seed=3)
    rng = np.random.default_rng(7)
    bad = rng.choice(len(table), 10, replace=False)
    table.x[bad] += 6.0
    full = calibrate_sharp(table, pattern, IMAGE_SIZE)
    part = table.select(~np.isin(table.frame, ["sharp/0000.png", "sharp/0001.png", "sharp/0002.png"]))
    cold = calibrate_sharp(part, pattern, IMAGE_SIZE, refine_points=False)
    warm = calibrate_sharp(part, pattern, IMAGE_SIZE, refine_points=False, start=full)
    u, v = np.meshgrid(np.linspace(0, 1279, 9), np.linspace(0, 719, 6))
    px = np.column_stack([u.ravel(), v.ravel()])
    assert np.abs(warm.camera.pixel_to_ray(px) - cold.camera.pixel_to_ray(px)).max() < 1e-7
    assert np.array_equal(warm.inlier, cold.inlier) and (~warm.inlier).sum() >= 9
    other, _ = simulate(pattern, true_camera, 1, seed=4)
    unseen = FeatureTable.concat([part, replace(other, frame=np.full(len(other), "sharp/new.png"))])
    assert calibrate_sharp(unseen, pattern, IMAGE_SIZE, start=full).num_frames == 10


def test_refining_points_absorbs_a_bent_target(pattern: StarPattern, true_camera: BrownConrady) -> None:
    nominal = pattern.points_3d()
    centre = nominal[:, :2].mean(axis=0)
    u = (nominal[:, :2] - centre) / np.abs(nominal[:, :2] - centre).max(axis=0)
    bent = nominal.copy()
    bent[:, 2] = 0.2e-3 * (1.0 - u[:, 0] ** 2) * (1.0 - 0.5 * u[:, 1] ** 2)
    table, _ = simulate(pattern, true_camera, 12, seed=2, points=bent)
    rigid = calibrate_sharp(table, pattern, IMAGE_SIZE, refine_points=False)
    free = calibrate_sharp(table, pattern, IMAGE_SIZE, refine_points=True)
    assert not rigid.point_refined.any() and free.point_refined[free.point_ids].all()
    assert free.rms_error < 0.75 * rigid.rms_error
    assert free.rms_error < 1.5 * NOISE_PX
    assert_intrinsics_match(free.camera, true_camera)

    def off_plane(p: np.ndarray) -> np.ndarray:
        design = np.column_stack([p[:, :2], np.ones(len(p))])
        return p[:, 2] - design @ np.linalg.lstsq(design, p[:, 2], rcond=None)[0]

    ids = free.point_ids
    assert np.abs(off_plane(free.points[ids]) - off_plane(bent[ids])).max() < 0.06e-3
    assert free.flatness()[1] > 0.08e-3
    # gauge: the refined points keep the nominal grid's centroid and scale
    assert np.abs(free.points[ids].mean(axis=0) - nominal[ids].mean(axis=0)).max() < 1e-9
    spread = np.linalg.norm(free.points[ids] - free.points[ids].mean(axis=0), axis=1).mean()
    assert spread == pytest.approx(np.linalg.norm(nominal[ids] - nominal[ids].mean(axis=0), axis=1).mean(),
                                   rel=1e-4)


def test_too_few_usable_frames_names_them(pattern: StarPattern, true_camera: BrownConrady) -> None:
    table, _ = simulate(pattern, true_camera, 5, seed=3)
    thin = table.frame == "sharp/0004.png"
    keep = ~thin | (np.cumsum(thin) <= 12)
    observations = table.select(keep).to_observations()
    with pytest.raises(CalibrationError, match=r"only 4 of 5 frame\(s\) are usable.*sharp/0004\.png \(12\)"):
        calibrate_sharp(observations, pattern, IMAGE_SIZE)
    with pytest.raises(CalibrationError, match="at least 5 sharp frames"):
        calibrate_sharp(FeatureTable.empty(), pattern, IMAGE_SIZE)


def test_bad_arguments_are_rejected(pattern: StarPattern, clean) -> None:
    table = clean[0]
    with pytest.raises(ValueError, match="loss"):
        calibrate_sharp(table, pattern, IMAGE_SIZE, loss="cauchy")
    twice = FeatureTable.concat([table, table.select(np.arange(1))])
    with pytest.raises(ValueError, match="observed twice"):
        calibrate_sharp(twice, pattern, IMAGE_SIZE)


def test_save_load_round_trip(clean, tmp_path) -> None:
    calib = clean[2]
    paths = save_calibration(tmp_path / "calib", calib)
    assert {p.name for p in paths.values()} == {"camera.yaml", "camera.json", "points.csv", "residuals.csv",
                                                "calibration.json", "parametric_intrinsics0.yaml"}
    assert load_camera_yaml(paths["camera_yaml"]) == calib.camera
    loaded = load_calibration(tmp_path / "calib")
    assert loaded.camera == calib.camera
    assert loaded.poses.keys() == calib.poses.keys()
    for name, pose in calib.poses.items():
        np.testing.assert_allclose(loaded.poses[name].R, pose.R, atol=1e-14)
        np.testing.assert_array_equal(loaded.poses[name].t, pose.t)
    np.testing.assert_array_equal(loaded.points, calib.points)
    for name in ("point_ids", "point_refined", "frame", "feature_id", "observed", "residuals", "inlier"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(calib, name))
    assert loaded.to_dict()["frames"].keys() == calib.to_dict()["frames"].keys()
    assert (loaded.median_error, loaded.rms_error, loaded.iterations) == (calib.median_error, calib.rms_error,
                                                                          calib.iterations)
    (tmp_path / "calib" / "points.csv").unlink()
    with pytest.raises(CalibrationFileError, match=r"points\.csv"):
        load_calibration(tmp_path / "calib")


def test_reprojection_errors_and_solve_pose(clean) -> None:
    table, _, calib = clean
    order = np.lexsort((table.feature_id, table.frame))
    errors = reprojection_errors(calib, table.select(order))
    np.testing.assert_allclose(errors, calib.residuals, atol=1e-9)
    stranger = table.select(np.arange(3))
    stranger.frame[:] = "unknown.png"
    assert np.isnan(reprojection_errors(calib, stranger)).all()

    name = "sharp/0003.png"
    rows = calib.frame == name
    xy = calib.observed[rows].copy()
    xy[:5] += 20.0
    pose = solve_pose(calib.camera, calib.points[calib.feature_id[rows]], xy)
    assert np.linalg.norm(pose.compose(calib.poses[name].inverse()).rvec) < 1e-4
    assert np.linalg.norm(pose.t - calib.poses[name].t) < 1e-4
    with pytest.raises(ValueError, match="at least 4"):
        solve_pose(calib.camera, np.zeros((3, 3)), np.zeros((3, 2)))


def test_calibration_sequence_fits_blurry_shifts_and_stops_when_asked(
        clean, pattern: StarPattern, true_camera: BrownConrady) -> None:
    """The in-memory sequence on 12 sharp frames and 3 blurry frames known by their features,
    each moved by a whole-image shift: every blurry frame enters the generic fit with its shift,
    its written features are its centres less that shift, and ``on_stage`` announces the stages
    in order and stops the sequence when it says so."""
    sharp = clean[0]
    moved, _ = simulate(pattern, true_camera, 3, seed=7)
    frames = []
    for i, name in enumerate(sorted(set(moved.frame.tolist()))):
        t = moved.select(moved.frame == name)
        frames.append(BlurryFrame(f"blurry/{i}", features=replace(
            t, frame=np.full(len(t), f"blurry/{i}"), x=t.x + 1.5, y=t.y - 1.0,
            flags=np.full(len(t), int(BLURRY_FLAGS)))))
    settings = SequenceSettings(generic=JointSettings(cell_px=160.0),
                                trust=TrustSettings(validation=ValidationSettings(method="none"),
                                                    cross_validation=False))
    stages: list[Stage] = []
    run = calibrate_features(sharp, None, frames, pattern, IMAGE_SIZE, settings,
                             on_stage=lambda s: stages.append(s) or True)
    assert stages == [Stage.PARAMETRIC, Stage.GENERIC, Stage.ASSESSMENT]
    assert sorted(run.generic.blurry_frames) == [f.name for f in frames]
    assert run.generic.median_error < 2 * NOISE_PX and run.generic_sharp is not None
    assert run.trust is not None and not run.trust_failure and not run.sharp_failure
    for o in run.blurry:
        assert o.entered and o.skipped_features is None and np.all(np.isfinite(o.shift))
        np.testing.assert_allclose(o.aligned.x, o.raw.x - o.shift[0])
        assert np.all(o.aligned.flags & int(FeatureFlags.GLOBALLY_ALIGNED))
    with pytest.raises(SequenceCancelledError):
        calibrate_features(sharp, None, frames, pattern, IMAGE_SIZE, settings,
                           on_stage=lambda s: s is not Stage.GENERIC)
    parametric = calibrate_features(sharp, None, frames, pattern, IMAGE_SIZE,
                                    replace(settings, model="parametric"))
    assert parametric.generic is None and parametric.trust is None
    assert parametric.calibration.median_error == pytest.approx(run.calibration.median_error)
