"""The app's global alignment (state/alignment.py) on synthetic features: no images, no browser."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from blurcalib.calib.sharp import calibrate_sharp, save_calibration
from blurcalib.camera.parametric import BrownConrady, project_points
from blurcalib.extract.frame import FrameResult
from blurcalib.geometry.pose import Pose
from blurcalib.growth.quality import QualitySettings
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import BlockStatus, BlockTable, FeatureFlags, FeatureObservation, FeatureTable
from blurcalib.sim.truth import DatasetTruth, TrueCamera
from blurcalib.target.pattern import layout_pattern
from state.alignment import (
    AlignmentError,
    Reference,
    align_frame,
    calibration_folders,
    find_reference,
)
from state.blocks import frame_filter
from state.figures import cell_means, error_field
from state.folder import Dataset

PATTERN = layout_pattern()
CAMERA = BrownConrady(fx=645.2, fy=644.6, cx=637.8, cy=361.4, k1=0.041, k2=-0.058, p1=0.0007, p2=-0.0004,
                      k3=0.019, width=1280, height=720)
SIZE = (CAMERA.width, CAMERA.height)
SHIFT = np.array([1.5, -0.7])


def view_pose(rvec: tuple[float, float, float], distance: float = 0.4) -> Pose:
    """A pose looking at the target's centre from ``distance`` m, turned by ``rvec`` (rad)."""
    R = Pose.from_rvec_tvec(np.asarray(rvec, float), np.zeros(3)).R
    centre = PATTERN.points_3d().mean(axis=0)
    return Pose(R, np.array([0.0, 0.0, distance]) - R @ centre)


def visible(pose: Pose, camera: BrownConrady = CAMERA) -> tuple[np.ndarray, np.ndarray]:
    """Feature ids whose projection lies 20 px inside the image, and their projections (px)."""
    px = project_points(camera, pose, PATTERN.points_3d())
    inside = np.all((px >= 20) & (px <= np.array(SIZE) - 21), axis=1)
    return np.flatnonzero(inside), px[inside]


def sharp_result(name: str, pose: Pose, camera: BrownConrady = CAMERA) -> FrameResult:
    """A finished sharp frame whose accepted star centres are exact projections."""
    ids, px = visible(pose, camera)
    L = PATTERN.square_length_m
    features = [FeatureObservation(name, int(i), int(PATTERN.features[i, 0]), int(PATTERN.features[i, 1]),
                                   PATTERN.features[i, 0] * L, PATTERN.features[i, 1] * L, float(x), float(y),
                                   1.0, int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME))
                for i, (x, y) in zip(ids, px, strict=True)]
    return FrameResult(name, FrameStatus.OK, features=FeatureTable.from_observations(features))


SHARP_POSES = [view_pose(r) for r in ((0.5, 0.1, 0.0), (-0.5, 0.2, 0.1), (0.1, 0.55, -0.1),
                                      (0.2, -0.5, 0.05), (0.45, 0.4, 0.2), (-0.3, -0.35, -0.1))]


def sharp_frames(count: int) -> dict[str, tuple[FrameResult, tuple[int, int]]]:
    return {f"sharp/{k:04d}.png": (sharp_result(f"sharp/{k:04d}.png", pose), SIZE)
            for k, pose in enumerate(SHARP_POSES[:count])}


def blurry_result(pose: Pose, shift: np.ndarray = SHIFT) -> FrameResult:
    """Blocks whose star centres are projections shifted by ``shift`` px; the loss grows with
    ``fx`` (5 at the left edge, 55 at the right), so tau_L cuts the target into a left part."""
    ids, px = visible(pose)
    n = len(ids)
    fx, fy = PATTERN.features[ids].T
    H = np.broadcast_to([[12.0, 1.0, 0.0], [-1.0, 12.0, 0.0], [0.0, 0.0, 1.0]], (n, 3, 3)).copy()
    H[:, :2, 2] = px + shift
    blocks = BlockTable(["blurry/0000.png"] * n, ids, fx, fy, [BlockStatus.ACCEPTED] * n,
                        5.0 + 50.0 * fx / (PATTERN.squares_x - 2), np.full(n, 0.05), np.full(n, 5.0),
                        np.full(n, 2.0), np.full(n, 0.9), np.zeros(n), np.zeros((n, 2)), H, np.zeros((n, 6)),
                        np.zeros((n, 17, 17)))
    return FrameResult("blurry/0000.png", FrameStatus.OK, blocks=blocks)


def make_dataset(folder: Path, truth: bool) -> Dataset:
    folder.mkdir(parents=True, exist_ok=True)
    true = DatasetTruth(TrueCamera(CAMERA), "pattern.yaml", [], {}) if truth else None
    return Dataset(folder, folder / "pattern.yaml", PATTERN, (), true)


def save_sharp_calibration(folder: Path) -> None:
    table = FeatureTable.concat([r.features for r, _ in sharp_frames(6).values()])
    save_calibration(folder, calibrate_sharp(table, PATTERN, SIZE))


def test_aligned_residuals_vanish_and_x_g_is_the_shift() -> None:
    pose = view_pose((0.6, 0.2, 0.05))
    result = blurry_result(pose)
    flt = frame_filter(result, SIZE, QualitySettings(tau_loss=100.0))
    reference = Reference(CAMERA, PATTERN.points_3d(), "test")
    a = align_frame(reference, PATTERN, result, flt, SIZE)
    assert a.num_blocks == len(result.blocks) == int(flt.kept.sum()) > 150
    assert np.allclose(a.translation, SHIFT, atol=1e-6)
    assert a.median_error < 1e-6 and a.rms_error < 1e-6 and a.orientation_ok and a.converged
    assert np.allclose(a.pose.R, pose.R, atol=1e-8) and np.allclose(a.pose.t, pose.t, atol=1e-9)
    assert np.allclose(a.observed, result.blocks.H[a.index, :2, 2])
    # The error field of the global alignment shows these residuals, block by block.
    field = error_field(result, flt, None, a)
    assert field.source == "global alignment" and np.array_equal(field.index, a.index)
    assert field.rms < 1e-6 and field.quad.shape == (a.num_blocks, 4, 2)


def test_a_wrong_camera_leaves_a_residual_and_frontal_views_are_flagged() -> None:
    pose = view_pose((0.6, 0.2, 0.05))
    result = blurry_result(pose)
    flt = frame_filter(result, SIZE, QualitySettings(tau_loss=100.0))
    wrong = Reference(CAMERA.with_params(k1=0.2), PATTERN.points_3d(), "test")
    assert align_frame(wrong, PATTERN, result, flt, SIZE).median_error > 0.05
    frontal = blurry_result(view_pose((0.05, 0.05, 0.0)))
    a = align_frame(Reference(CAMERA, PATTERN.points_3d(), "test"), PATTERN, frontal,
                    frame_filter(frontal, SIZE, QualitySettings(tau_loss=100.0)), SIZE)
    assert not a.orientation_ok and a.angle_to_normal < np.pi / 10


def test_tau_loss_changes_the_aligned_blocks() -> None:
    result = blurry_result(view_pose((0.6, 0.2, 0.05)))
    reference = Reference(CAMERA, PATTERN.points_3d(), "test")
    counts = []
    for tau in (100.0, 30.0, 15.0):
        flt = frame_filter(result, SIZE, QualitySettings(tau_loss=tau))
        a = align_frame(reference, PATTERN, result, flt, SIZE)
        assert np.array_equal(a.index, np.flatnonzero(flt.kept))
        assert np.allclose(a.translation, SHIFT, atol=1e-5)
        counts.append(a.num_blocks)
    assert counts[0] > counts[1] > counts[2] >= 12
    with pytest.raises(AlignmentError, match="0 blocks kept by the filter, alignment needs 12"):
        align_frame(reference, PATTERN, result, frame_filter(result, SIZE, QualitySettings(tau_loss=1.0)),
                    SIZE)
    with pytest.raises(AlignmentError, match="the reference camera 1280 x 720 px"):
        align_frame(reference, PATTERN, result, frame_filter(result, SIZE, QualitySettings(tau_loss=100.0)),
                    (640, 360))


def test_reference_order_calibration_folder_then_truth_then_sharp_frames(tmp_path: Path) -> None:
    sharp = sharp_frames(6)
    with_folder = make_dataset(tmp_path / "with_folder", truth=True)
    save_sharp_calibration(with_folder.folder / "calibration")
    choice = find_reference(with_folder, sharp)
    assert choice.reference.source == f"calibration folder {with_folder.folder / 'calibration'}"
    assert choice.reference.points.shape == (PATTERN.num_features, 3)
    assert abs(choice.reference.camera.fx - CAMERA.fx) < 0.1

    truth = find_reference(make_dataset(tmp_path / "truth", truth=True), sharp)
    assert truth.reference.source == "ground-truth camera" and truth.reference.camera is CAMERA

    calibrated = find_reference(make_dataset(tmp_path / "real", truth=False), sharp)
    assert calibrated.reference.source.startswith("calibration of 6 sharp frames")
    assert abs(calibrated.reference.camera.cx - CAMERA.cx) < 0.1

    missing = find_reference(make_dataset(tmp_path / "few", truth=False), sharp_frames(4))
    assert missing.reference is None
    assert missing.reason == ("no reference camera: needs ≥5 finished sharp frames, a calibration/ folder, "
                              "or ground truth (4 sharp frames finished)")


def test_a_pipeline_output_beside_the_frames_is_found_and_a_broken_one_is_named(tmp_path: Path) -> None:
    # blurcalib demo: the frames in out/demo/data, the pipeline's output in out/demo/calibration.
    data = make_dataset(tmp_path / "demo" / "data", truth=False)
    save_sharp_calibration(tmp_path / "demo" / "calibration" / "calibration")
    assert calibration_folders(data.folder) == [tmp_path / "demo" / "calibration" / "calibration"]
    assert find_reference(data, {}).reference.source.startswith("calibration folder")

    broken = make_dataset(tmp_path / "broken", truth=False)
    save_sharp_calibration(broken.folder / "calibration")
    (broken.folder / "calibration" / "camera.json").write_text("{")
    choice = find_reference(broken, sharp_frames(2))
    assert choice.reference is None and "(2 sharp frames finished)" in choice.reason
    assert "skipped" in choice.reason and "camera.json" in choice.reason


def test_cell_means_average_errors_per_cell() -> None:
    xy = np.array([[0.0, 0.0], [5.0, 3.0], [25.0, 12.0], [np.nan, 1.0]])
    error = np.array([[1.0, 0.0], [0.0, 1.0], [2.0, 2.0], [9.0, 9.0]])
    corner, mean, count = cell_means(xy, error, (40, 20), 10)
    assert corner.tolist() == [[0.0, 0.0], [20.0, 10.0]]
    assert mean.tolist() == [[0.5, 0.5], [2.0, 2.0]] and count.tolist() == [2, 1]
