"""The parametric camera family: projection and unprojection over the whole valid field, the
analytic Jacobians, agreement with OpenCV, the valid field, descriptions."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.family import MODELS as FAMILY
from blurcalib.camera.family import as_family, camera_from_dict
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.lens import ParametricCamera, project_poses_camera
from blurcalib.camera.parametric import BrownConrady, project_poses
from tests.camera.models import (
    BROWN_CONRADY,
    KANNALA_BRANDT,
    MODELS,
    RATIONAL,
    THIN_PRISM,
    directions,
    field_deg,
)

IDS = [m.MODEL for m in MODELS]


@pytest.mark.parametrize("camera", MODELS, ids=IDS)
def test_unproject_inverts_project_over_the_valid_field(camera: ParametricCamera) -> None:
    rays = directions(field_deg(camera), 4000)
    assert camera.valid_directions(rays * 2.5).all()
    px = camera.project(rays * 2.5)
    back = camera.unproject(px)
    assert np.abs(back - rays).max() < 1e-12
    assert np.abs(camera.project(back) - px).max() < 1e-9
    assert camera.valid_pixels(px).all()


def test_fisheye_models_see_beyond_ninety_degrees() -> None:
    for camera in (KANNALA_BRANDT, THIN_PRISM):
        assert np.degrees(camera.max_angle) > 150
        rays = directions(100.0, 2000, seed=1)
        behind = rays[rays[:, 2] < 0]
        assert len(behind) > 100
        assert np.abs(camera.unproject(camera.project(behind)) - behind).max() < 1e-12


@pytest.mark.parametrize("camera", MODELS, ids=IDS)
def test_jacobians_match_finite_differences(camera: ParametricCamera) -> None:
    rays = directions(field_deg(camera), 60, seed=2) * 1.7
    rays = np.vstack([rays, [[1e-7, -2e-7, 1.0], [3e-4, 1e-4, 0.8]]])  # at and near the axis
    proj = camera.project_with_jacobian(rays)
    assert np.array_equal(proj.pixels, camera.project(rays))
    eps = 1e-6
    d_point = np.stack([(camera.project(rays + eps * e) - camera.project(rays - eps * e)) / (2 * eps)
                        for e in np.eye(3)], axis=-1)
    assert np.abs(proj.d_point - d_point).max() < 1e-6 * np.abs(d_point).max()
    steps = eps * np.maximum(np.abs(camera.params), 1e-3)
    d_intr = np.stack([(camera.with_params(camera.params + h * e).project(rays)
                        - camera.with_params(camera.params - h * e).project(rays)) / (2 * h)
                       for h, e in zip(steps, np.eye(len(steps)), strict=True)], axis=-1)
    assert proj.d_intrinsics.shape == (len(rays), 2, len(camera.PARAM_NAMES))
    assert np.abs(proj.d_intrinsics - d_intr).max() < 1e-6 * np.abs(d_intr).max()


def _forward_points(n: int) -> np.ndarray:
    rng = np.random.default_rng(3)
    return np.column_stack([rng.uniform(-1.0, 1.0, (n, 2)), rng.uniform(0.9, 2.0, n)])


def test_brown_conrady_and_rational_agree_with_cv2_project_points() -> None:
    pts = _forward_points(500)
    for camera in (BROWN_CONRADY, RATIONAL):
        dist = np.array([camera.named()[n] for n in camera.OPENCV_DISTORTION])
        ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), camera.K, dist)
        assert np.abs(camera.project(pts) - ref[:, 0]).max() < 1e-9


def test_kannala_brandt_agrees_with_cv2_fisheye() -> None:
    rays = directions(89.0, 500, seed=4)
    ref, _ = cv2.fisheye.projectPoints(rays[None] * 3.0, np.zeros(3), np.zeros(3), KANNALA_BRANDT.K,
                                       KANNALA_BRANDT.params[4:])
    assert np.abs(KANNALA_BRANDT.project(rays * 3.0) - ref[0]).max() < 1e-9
    px = KANNALA_BRANDT.project(rays)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    undist = cv2.fisheye.undistortPoints(px[None], KANNALA_BRANDT.K, KANNALA_BRANDT.params[4:],
                                         criteria=criteria)[0]
    ours = KANNALA_BRANDT.unproject(px)
    near = rays[:, 2] > 0.2
    assert np.abs(ours[near, :2] / ours[near, 2:] - undist[near]).max() < 1e-8


def test_brown_conrady_is_the_calibration_camera() -> None:
    legacy = BROWN_CONRADY.to_brown_conrady()
    assert isinstance(legacy, BrownConrady)
    assert np.array_equal(BrownConradyCamera.from_brown_conrady(legacy).params, BROWN_CONRADY.params)
    pts = _forward_points(300)
    assert np.abs(BROWN_CONRADY.project(pts) - legacy.project(pts)).max() < 1e-10
    px = legacy.project(pts)
    assert np.abs(BROWN_CONRADY.unproject(px) - legacy.pixel_to_ray(px)).max() < 1e-13
    assert as_family(legacy).MODEL == "Brown_Conrady" and as_family(KANNALA_BRANDT) is KANNALA_BRANDT


def test_project_poses_camera_is_project_poses_for_brown_conrady() -> None:
    rng = np.random.default_rng(5)
    rvecs, tvecs = rng.normal(size=(3, 3)) * 0.2, rng.normal(size=(3, 3)) * 0.05 + [0.0, 0.0, 0.6]
    points = np.column_stack([rng.uniform(-0.1, 0.1, (40, 2)), np.zeros(40)])
    frames = rng.integers(0, 3, 40)
    a = project_poses(BROWN_CONRADY.params, rvecs, tvecs, points, frames, jacobian=True)
    b = project_poses_camera(BROWN_CONRADY, rvecs, tvecs, points, frames, jacobian=True)
    for name in ("pixels", "d_intrinsics", "d_pose", "d_point"):
        assert np.abs(getattr(a, name) - getattr(b, name)).max() < 1e-9, name


def test_project_poses_camera_pose_jacobian_of_a_fisheye() -> None:
    rng = np.random.default_rng(6)
    rvec, tvec = np.array([[0.3, -1.2, 0.2]]), np.array([[0.4, 0.1, -0.05]])  # seen ~100 deg off the axis
    points = np.column_stack([rng.uniform(-0.1, 0.1, (20, 2)), np.zeros(20)])
    proj = project_poses_camera(KANNALA_BRANDT, rvec, tvec, points, jacobian=True)
    eps = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        plus = project_poses_camera(KANNALA_BRANDT, rvec + d[:3], tvec + d[3:], points).pixels
        minus = project_poses_camera(KANNALA_BRANDT, rvec - d[:3], tvec - d[3:], points).pixels
        assert np.abs(proj.d_pose[:, :, k] - (plus - minus) / (2 * eps)).max() < 1e-4


def test_valid_field_ends_where_the_radial_map_folds() -> None:
    folding = BrownConradyCamera.from_values(640, 480, fx=400.0, fy=400.0, cx=320.0, cy=240.0, k1=-0.4)
    # g(r) = r - 0.4 r^3 stops increasing at r = 1 / sqrt(1.2)
    assert np.tan(folding.max_angle) == pytest.approx(1 / np.sqrt(1.2), rel=1e-9)
    rays = directions(60.0, 500, seed=7)
    inside = np.arctan(np.hypot(rays[:, 0], rays[:, 1]) / rays[:, 2]) < folding.max_angle
    assert np.array_equal(folding.valid_directions(rays), inside)
    beyond = folding.project(rays[~inside])
    back = folding.unproject(beyond)  # the folded pixels are the image of rays inside the field
    found = np.all(np.isfinite(back), axis=1)
    assert found.any() and folding.valid_directions(back[found]).all()
    assert np.abs(folding.project(back[found]) - beyond[found]).max() < 1e-9
    assert np.abs(back[found] - rays[~inside][found]).max() > 0.01
    assert not BROWN_CONRADY.valid_directions([[0.0, 0.3, -1.0]]).any()  # behind a perspective camera
    assert np.isnan(folding.unproject([[5000.0, 240.0]])).all()


@pytest.mark.parametrize("camera", MODELS, ids=IDS)
def test_description_round_trip(camera: ParametricCamera) -> None:
    data = camera.to_dict()
    assert list(data["parameters"]) == list(camera.PARAM_NAMES)
    back = camera_from_dict(data)
    assert type(back) is type(camera) and np.array_equal(back.params, camera.params)
    assert (back.width, back.height, back.angular) == (camera.width, camera.height, camera.angular)


def test_description_errors_name_the_problem() -> None:
    data = KANNALA_BRANDT.to_dict()
    del data["parameters"]["k3"]
    with pytest.raises(ValueError, match=r"missing parameters \['k3'\]"):
        camera_from_dict(data)
    with pytest.raises(ValueError, match="unknown camera model 'pinhole'"):
        camera_from_dict({**KANNALA_BRANDT.to_dict(), "model": "pinhole"})
    with pytest.raises(ValueError, match="focal"):
        KANNALA_BRANDT.replace(fx=-1.0)
    with pytest.raises(ValueError, match="no parameters"):
        KannalaBrandtCamera.from_values(10, 10, fx=1.0, fy=1.0, cx=0.0, cy=0.0, p1=0.1)
    legacy = BROWN_CONRADY.to_brown_conrady().to_dict()
    assert np.array_equal(camera_from_dict(legacy).params, BROWN_CONRADY.params)
    assert set(FAMILY) == {"Brown_Conrady", "rational", "Kannala_Brandt", "thin_prism_fisheye"}


def test_scaled_follows_the_pixel_centre_convention() -> None:
    half = KANNALA_BRANDT.scaled(0.5)
    rays = directions(90.0, 200, seed=8)
    assert np.abs(half.project(rays) - (0.5 * (KANNALA_BRANDT.project(rays) + 0.5) - 0.5)).max() < 1e-9
    assert (half.width, half.height) == (640, 360)
