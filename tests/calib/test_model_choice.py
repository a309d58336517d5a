"""The parametric family in calibration: a fisheye calibrated against its truth, the model chosen
by held-out error, the pose of a frame beyond 90 degrees, and the generic fit's failure message."""

from __future__ import annotations

import numpy as np
import pytest

from blurcalib.calib.model_choice import choose_model
from blurcalib.calib.pnp import solve_pose
from blurcalib.calib.sequence import generic_failure
from blurcalib.calib.sharp import calibrate_sharp, load_calibration, save_calibration
from blurcalib.camera.generic import best_fit_rotation
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.opencv_files import read_opencv_camera
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureTable
from blurcalib.sim.synth import sample_pose
from blurcalib.sim.truth import TrueCamera, fisheye_camera
from blurcalib.target.pattern import StarPattern, layout_pattern

SIZE = (1280, 720)


def _features(camera: TrueCamera, frames: int, seed: int, noise_px: float = 0.02
              ) -> tuple[StarPattern, FeatureTable]:
    """Star centres of ``frames`` simulated poses: the true projections of the visible features
    plus Gaussian noise (px)."""
    pattern = layout_pattern()
    rng = np.random.default_rng(seed)
    P = pattern.points_3d()
    cols: dict[str, list] = {k: [] for k in ("frame", "feature_id", "X", "Y", "x", "y")}
    for f in range(frames):
        cam = sample_pose(pattern, camera, rng, 60.0, (24.0, 42.0)).transform(P)
        px = camera.project(cam)
        ok = camera.in_view(cam) & np.all(np.isfinite(px), axis=1)
        ok &= np.all((px >= 0) & (px <= np.array(SIZE) - 1), axis=1)
        px = px + rng.normal(0.0, noise_px, px.shape)
        ids = np.flatnonzero(ok)
        for key, values in (("frame", [f"sharp/{f:04d}.png"] * len(ids)), ("feature_id", ids),
                            ("X", P[ids, 0]), ("Y", P[ids, 1]), ("x", px[ids, 0]), ("y", px[ids, 1])):
            cols[key].extend(values)
    n = len(cols["x"])
    table = FeatureTable(np.array(cols["frame"]), np.array(cols["feature_id"]), np.zeros(n, np.int64),
                         np.zeros(n, np.int64), np.array(cols["X"]), np.array(cols["Y"]), np.array(cols["x"]),
                         np.array(cols["y"]), np.ones(n), np.zeros(n, np.int64))
    return pattern, table


def _truth_error(camera, truth: TrueCamera) -> np.ndarray:
    """``|pi(Q ray_true(p)) - p|`` (px) over a lattice of the image, the orientation gauge ``Q``
    fitted."""
    xs, ys = np.meshgrid(np.arange(20.0, SIZE[0] - 20, 40.0), np.arange(20.0, SIZE[1] - 20, 40.0))
    px = np.column_stack([xs.ravel(), ys.ravel()])
    true_rays, rays = truth.pixel_to_ray(px), camera.pixel_to_ray(px)
    ok = np.all(np.isfinite(true_rays), axis=1) & np.all(np.isfinite(rays), axis=1)
    Q = best_fit_rotation(true_rays[ok], rays[ok])
    return np.linalg.norm(camera.project(true_rays[ok] @ Q.T) - px[ok], axis=1)


@pytest.fixture(scope="module")
def fisheye() -> tuple[TrueCamera, StarPattern, FeatureTable]:
    truth = fisheye_camera(130.0, seed=2, deviation_px=0.0)
    return (truth, *_features(truth, 8, seed=5))


def test_kannala_brandt_calibration_matches_the_truth(fisheye, tmp_path) -> None:
    truth, pattern, table = fisheye
    calib = calibrate_sharp(table, pattern, SIZE, model="Kannala_Brandt")
    assert isinstance(calib.camera, KannalaBrandtCamera)
    assert calib.median_error < 0.03  # the 0.02 px noise
    error = _truth_error(calib.camera, truth)
    assert np.median(error) < 0.02 and error.max() < 0.3
    # Written in OpenCV's fisheye format and read back; the reference tool's file beside it.
    paths = save_calibration(tmp_path / "calib", calib)
    assert paths["parametric_ref"].exists()
    back = read_opencv_camera(paths["camera_yaml"])
    assert back.MODEL == "Kannala_Brandt" and np.allclose(back.params, calib.camera.params, rtol=1e-9)
    assert np.allclose(load_calibration(tmp_path / "calib").camera.params, calib.camera.params)


@pytest.mark.slow
def test_held_out_error_chooses_the_fisheye_model(fisheye) -> None:
    _, pattern, table = fisheye
    choice = choose_model(table, pattern, SIZE)
    assert choice.model == "Kannala_Brandt", choice.summary()
    assert choice.scores["Kannala_Brandt"] < 0.05
    assert choice.scores["Brown_Conrady"] > 3 * choice.scores["Kannala_Brandt"]
    assert choice.to_dict()["model"] == "Kannala_Brandt"


def test_pose_of_points_beyond_ninety_degrees() -> None:
    camera = fisheye_camera(190.0, seed=0, deviation_px=0.0).model
    pattern = layout_pattern()
    R = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # the target off to the side
    pose = Pose(R, np.array([0.25, -0.1, -0.03]))
    cam = pose.transform(pattern.points_3d())
    angle = np.degrees(np.arctan2(np.hypot(cam[:, 0], cam[:, 1]), cam[:, 2]))
    seen = camera.valid_directions(cam) & camera.in_image(camera.project(cam))
    assert (angle[seen] > 90).sum() >= 40  # points behind the image plane, seen at up to 96 degrees
    px = camera.project(cam[seen]) + np.random.default_rng(0).normal(0, 0.05, (int(seen.sum()), 2))
    solved = solve_pose(camera, pattern.points_3d()[seen], px)
    assert np.allclose(solved.R, pose.R, atol=2e-3) and np.allclose(solved.t, pose.t, atol=2e-3)


def test_generic_failure_says_what_the_capture_lacks(fisheye) -> None:
    _, _, table = fisheye
    corner = table.select((table.x < 400) & (table.y < 300))
    message = generic_failure(np.linalg.LinAlgError("Singular matrix"), corner, [], SIZE, 40.0)
    assert "\n" not in message and "Singular matrix" in message
    assert "grid cells" in message and "corners" in message
