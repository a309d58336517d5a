"""Tests for blurcalib.camera.parametric: projection with its Jacobian, undistortion, homographies, files."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.camera.parametric import (
    BrownConrady,
    CameraFileError,
    load_camera_json,
    load_camera_yaml,
    project_points,
    project_poses,
    save_camera_json,
    save_camera_yaml,
)
from blurcalib.geometry.homography import apply_homography, homography_scale, plane_homography
from blurcalib.geometry.pose import Pose

CV_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-16)


def random_camera(rng: np.random.Generator) -> BrownConrady:
    """Realistic camera: distortion invertible over the whole image."""
    width, height = 640, 480
    fx = rng.uniform(800.0, 1500.0)
    return BrownConrady(
        fx=fx,
        fy=fx * rng.uniform(0.98, 1.02),
        cx=width / 2 + rng.uniform(-20.0, 20.0),
        cy=height / 2 + rng.uniform(-20.0, 20.0),
        k1=rng.uniform(-0.4, 0.2),
        k2=rng.uniform(0.0, 0.2),
        p1=rng.uniform(-2e-3, 2e-3),
        p2=rng.uniform(-2e-3, 2e-3),
        k3=rng.uniform(-0.02, 0.02),
        width=width,
        height=height,
    )


def random_pose(rng: np.random.Generator) -> Pose:
    return Pose.from_rvec_tvec(
        rng.uniform(-0.5, 0.5, 3), [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0.6, 1.5)]
    )


def target_points(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)), np.zeros(n)])


def normalised(pose: Pose, points_world: np.ndarray) -> np.ndarray:
    cam = pose.transform(points_world)
    return cam[:, :2] / cam[:, 2:]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


# ---------------------------------------------------------------------------
# NumPy model vs OpenCV
# ---------------------------------------------------------------------------


def test_project_matches_cv2_project_points(rng: np.random.Generator) -> None:
    for _ in range(20):
        camera, pose = random_camera(rng), random_pose(rng)
        pts = np.vstack([target_points(rng, 40), rng.uniform(-0.3, 0.3, (10, 3))])
        expected, _ = cv2.projectPoints(pts, pose.rvec, pose.t, camera.K, camera.dist)
        np.testing.assert_allclose(project_points(camera, pose, pts), expected[:, 0], rtol=0, atol=1e-9)


def test_unproject_matches_cv2_undistort_points_and_round_trips(rng: np.random.Generator) -> None:
    for _ in range(20):
        camera, pose = random_camera(rng), random_pose(rng)
        pts = target_points(rng, 50)
        px = project_points(camera, pose, pts)
        xn = camera.unproject(px)
        expected = cv2.undistortPoints(px[:, None, :], camera.K, camera.dist, criteria=CV_UNDISTORT_CRITERIA)[
            :, 0
        ]
        np.testing.assert_allclose(xn, expected, rtol=0, atol=1e-9)
        np.testing.assert_allclose(xn, normalised(pose, pts), rtol=0, atol=1e-9)


def test_undistort_inverts_strong_distortion_over_whole_image() -> None:
    camera = BrownConrady(500.0, 500.0, 319.5, 239.5, -0.35, 0.12, 1e-3, -1e-3, -0.01, 640, 480)
    u, v = np.meshgrid(np.linspace(0, 639, 41), np.linspace(0, 479, 31))
    px = np.column_stack([u.ravel(), v.ravel()])
    xd = (px - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
    x = camera.undistort(xd)
    np.testing.assert_allclose(camera.distort(x), xd, rtol=0, atol=1e-13)
    np.testing.assert_allclose(camera.undistort(camera.distort(x)), x, rtol=0, atol=1e-10)
    assert np.max(np.linalg.norm(x - xd, axis=1)) > 0.05  # distortion is far from negligible


def test_pixel_to_ray_is_unit_and_reprojects(rng: np.random.Generator) -> None:
    camera = random_camera(rng)
    px = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], (30, 2))
    rays = camera.pixel_to_ray(px)
    assert rays.shape == (30, 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, rtol=0, atol=1e-14)
    assert np.all(rays[:, 2] > 0)
    np.testing.assert_allclose(camera.project(2.5 * rays), px, rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------
# Torch versions
# ---------------------------------------------------------------------------


def batch_case(
    rng: np.random.Generator, batch: int, n: int
) -> tuple[list[BrownConrady], list[Pose], np.ndarray]:
    cameras = [random_camera(rng) for _ in range(batch)]
    poses = [random_pose(rng) for _ in range(batch)]
    return cameras, poses, np.stack([target_points(rng, n) for _ in range(batch)])


# ---------------------------------------------------------------------------
# Homographies
# ---------------------------------------------------------------------------


def test_plane_homography_maps_to_undistorted_pixels(rng: np.random.Generator) -> None:
    camera, pose = random_camera(rng), random_pose(rng)
    pts = target_points(rng, 30)
    H = plane_homography(camera.K, pose)
    mapped = apply_homography(H, pts[:, :2])
    pinhole = camera.with_params(k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0)
    np.testing.assert_allclose(mapped, project_points(pinhole, pose, pts), rtol=0, atol=1e-9)
    # The distorted observations, undistorted and re-expressed in pixels, land on the same spots.
    xn = camera.unproject(project_points(camera, pose, pts))
    np.testing.assert_allclose(mapped, xn * [camera.fx, camera.fy] + [camera.cx, camera.cy], atol=1e-8)


def test_apply_homography_batched(rng: np.random.Generator) -> None:
    H = np.eye(3) + rng.normal(scale=[[0.1, 0.1, 5.0], [0.1, 0.1, 5.0], [1e-4, 1e-4, 0.0]], size=(3, 3, 3))
    pts = rng.uniform(0, 100, (3, 7, 2))
    batched = apply_homography(H, pts)
    assert batched.shape == (3, 7, 2)
    for b in range(3):
        homog = np.column_stack([pts[b], np.ones(7)]) @ H[b].T
        np.testing.assert_allclose(batched[b], homog[:, :2] / homog[:, 2:], rtol=1e-13)
        np.testing.assert_allclose(apply_homography(H[b], pts[b]), batched[b], rtol=0, atol=0)


def test_homography_scale_is_the_local_area_scale_at_the_origin(rng: np.random.Generator) -> None:
    """``sqrt(|det J|)`` of the mapping at the origin, against finite differences, for strongly
    perspective homographies (where ``H[:2, :2]`` alone is far off)."""
    scale = [[0.2, 0.2, 300.0], [0.2, 0.2, 300.0], [0.05, 0.05, 0.0]]
    H = np.eye(3) + rng.normal(scale=scale, size=(5, 3, 3))
    H[:, :2, :2] *= 15.0
    eps = 1e-6
    c = apply_homography(H, np.zeros((5, 1, 2)))[:, 0]
    dx = (apply_homography(H, np.full((5, 1, 2), [eps, 0.0]))[:, 0] - c) / eps
    dy = (apply_homography(H, np.full((5, 1, 2), [0.0, eps]))[:, 0] - c) / eps
    area = np.abs(dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0])
    np.testing.assert_allclose(homography_scale(H), np.sqrt(area), rtol=1e-5)
    np.testing.assert_allclose(homography_scale(3.0 * H[0]), homography_scale(H[0]), rtol=1e-12)
    assert np.isnan(homography_scale(np.zeros((3, 3))))


# ---------------------------------------------------------------------------
# Scaling
# ---------------------------------------------------------------------------


def test_scaled_camera_maps_projections_with_pixel_centre_convention(rng: np.random.Generator) -> None:
    camera, pose = random_camera(rng), random_pose(rng)
    pts = target_points(rng, 20)
    px = project_points(camera, pose, pts)
    for s in (0.5, 0.25, 2.0, 1.7):
        scaled = camera.scaled(s)
        np.testing.assert_allclose(project_points(scaled, pose, pts), s * (px + 0.5) - 0.5, atol=1e-9)
        assert (scaled.width, scaled.height) == (round(s * 640), round(s * 480))
    round_trip = camera.scaled(2.0).scaled(0.5)
    np.testing.assert_allclose(round_trip.K, camera.K, rtol=1e-15, atol=1e-12)


def test_scaled_convention_matches_cv2_resize() -> None:
    """A blob's centroid after an exact 2x box downsample lands where scaled() predicts."""
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float64)
    centre = np.array([20.3, 30.7])
    image = np.exp(-((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (2 * 3.0**2))
    small = cv2.resize(image, (32, 32), interpolation=cv2.INTER_AREA)
    sy, sx = np.mgrid[0:32, 0:32]
    centroid = np.array([(small * sx).sum(), (small * sy).sum()]) / small.sum()
    camera = BrownConrady(100.0, 100.0, centre[0], centre[1], 0, 0, 0, 0, 0, 64, 64).scaled(0.5)
    np.testing.assert_allclose(centroid, [camera.cx, camera.cy], atol=1e-9)


# ---------------------------------------------------------------------------
# Poses and validation
# ---------------------------------------------------------------------------


def test_pose_algebra(rng: np.random.Generator) -> None:
    a, b = random_pose(rng), random_pose(rng)
    pts = rng.normal(size=(10, 3))
    np.testing.assert_allclose(Pose.from_rvec_tvec(a.rvec, a.t).R, a.R, atol=1e-14)
    np.testing.assert_allclose(a.inverse().transform(a.transform(pts)), pts, atol=1e-14)
    np.testing.assert_allclose(a.compose(b).transform(pts), a.transform(b.transform(pts)), atol=1e-14)
    np.testing.assert_allclose(a.transform(a.camera_center[None]), 0.0, atol=1e-14)
    restored = Pose.from_dict(json.loads(json.dumps(a.to_dict())))
    assert np.array_equal(restored.R, a.R) and np.array_equal(restored.t, a.t)
    with pytest.raises(ValueError, match="'t'"):
        Pose.from_dict({"R": np.eye(3).tolist()})
    with pytest.raises(ValueError, match="rotation"):
        Pose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))


def test_optical_axis_angle_to_target_normal() -> None:
    assert Pose.identity().optical_axis_angle_to_target_normal() == 0.0
    # Camera on the other side of the target, still looking straight at it.
    assert Pose.from_rvec_tvec([math.pi, 0, 0], [0, 0, 1]).optical_axis_angle_to_target_normal() == (
        pytest.approx(0.0, abs=1e-15)
    )
    for angle in (0.1, 0.7, 1.2):
        tilted = Pose.from_rvec_tvec([0.0, angle, 0.0], [0, 0, 1])
        assert tilted.optical_axis_angle_to_target_normal() == pytest.approx(angle, abs=1e-14)
        tilted = Pose.from_rvec_tvec([math.pi - angle, 0.0, 0.0], [0, 0, 1])
        assert tilted.optical_axis_angle_to_target_normal() == pytest.approx(angle, abs=1e-14)


def test_camera_dict_round_trip_and_validation(rng: np.random.Generator) -> None:
    camera = random_camera(rng)
    assert BrownConrady.from_dict(camera.to_dict()) == camera
    assert BrownConrady.from_matrix(camera.K, camera.dist, 640, 480) == camera
    data = camera.to_dict()
    del data["k2"]
    with pytest.raises(ValueError, match="'k2'"):
        BrownConrady.from_dict(data)
    with pytest.raises(ValueError, match="focal"):
        camera.with_params(fx=-1.0)
    with pytest.raises(ValueError, match="width"):
        camera.with_params(width=0)
    with pytest.raises(ValueError, match="supported"):
        BrownConrady.from_matrix(camera.K, [0.1, 0, 0, 0, 0, 0.2, 0, 0], 640, 480)


# ---------------------------------------------------------------------------
# Camera files
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("save", "load"), [(save_camera_yaml, load_camera_yaml), (save_camera_json, load_camera_json)]
)
def test_camera_file_round_trip_is_exact_and_atomic(
    tmp_path: Path, rng: np.random.Generator, save, load
) -> None:
    path = tmp_path / "camera.file"
    first, second = random_camera(rng), random_camera(rng).with_params(cx=1 / 3, k3=-1e-17)
    save(path, first)
    save(path, second)  # overwrite in place
    assert load(path) == second
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera.file"]


def test_yaml_file_is_opencv_file_storage(tmp_path: Path, rng: np.random.Generator) -> None:
    camera = random_camera(rng)
    path = tmp_path / "camera.yaml"
    save_camera_yaml(path, camera)
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert np.array_equal(storage.getNode("camera_matrix").mat(), camera.K)
    assert np.array_equal(storage.getNode("distortion_coefficients").mat(), camera.dist[None])
    assert storage.getNode("image_width").real() == 640 and storage.getNode("image_height").real() == 480
    storage.release()


CORRUPT_YAML = {
    "garbage": "this is :: not [ yaml",
    "truncated": (
        "%YAML:1.0\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0."
    ),
    "empty": "",
    "missing_key": "%YAML:1.0\nimage_width: 640\nimage_height: 480\n",
    "not_a_matrix": (
        "%YAML:1.0\ncamera_matrix: 5\ndistortion_coefficients: 1\nimage_width: 1\nimage_height: 1\n"
    ),
}
CORRUPT_JSON = {
    "garbage": "{not json",
    "empty": "",
    "missing_key": json.dumps({"fx": 1.0}),
    "not_a_mapping": "[1, 2, 3]",
    "bad_value": json.dumps({**BrownConrady(1, 1, 0, 0, 0, 0, 0, 0, 0, 1, 1).to_dict(), "fy": "wide"}),
}


@pytest.mark.parametrize(
    ("load", "content"),
    [(load_camera_yaml, c) for c in CORRUPT_YAML.values()]
    + [(load_camera_json, c) for c in CORRUPT_JSON.values()],
    ids=[f"yaml-{k}" for k in CORRUPT_YAML] + [f"json-{k}" for k in CORRUPT_JSON],
)
def test_corrupt_camera_file_raises_naming_the_file(tmp_path: Path, load, content: str) -> None:
    path = tmp_path / "broken_camera.txt"
    path.write_text(content)
    with pytest.raises(CameraFileError, match=re.escape(str(path))):
        load(path)


@pytest.mark.parametrize("load", [load_camera_yaml, load_camera_json])
def test_missing_camera_file_raises(tmp_path: Path, load) -> None:
    with pytest.raises(CameraFileError, match=r"nowhere\.yaml.*does not exist"):
        load(tmp_path / "nowhere.yaml")


def test_camera_file_error_names_the_problem(tmp_path: Path) -> None:
    yaml_path = tmp_path / "cam.yaml"
    yaml_path.write_text(CORRUPT_YAML["missing_key"])
    with pytest.raises(CameraFileError, match="missing key 'camera_matrix'"):
        load_camera_yaml(yaml_path)
    json_path = tmp_path / "cam.json"
    json_path.write_text(CORRUPT_JSON["missing_key"])
    with pytest.raises(CameraFileError, match="missing key 'fy'"):
        load_camera_json(json_path)


def test_project_poses_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(7)
    intr = np.array([645.2, 644.6, 637.8, 361.4, 0.041, -0.058, 0.0007, -0.0004, 0.019])
    rvecs = rng.normal(size=(3, 3)) * 0.5
    tvecs = rng.normal(size=(3, 3)) * 0.05 + [0.0, 0.0, 0.4]
    points = rng.normal(size=(20, 3)) * 0.1
    frames = rng.integers(0, 3, 20)
    proj = project_poses(intr, rvecs, tvecs, points, frames, jacobian=True)
    j_intr, j_pose, j_point = proj.d_intrinsics, proj.d_pose, proj.d_point

    def numeric(fun, x: np.ndarray) -> np.ndarray:
        cols = []
        for k in range(x.size):
            step = np.zeros(x.size)
            step[k] = 1e-6 * max(1.0, abs(x.flat[k]))
            cols.append((fun((x.ravel() + step).reshape(x.shape)) - fun((x.ravel() - step).reshape(x.shape)))
                        / (2 * step[k]))
        return np.stack(cols, axis=-1)

    rows = np.arange(20)
    np.testing.assert_allclose(numeric(lambda p: project_poses(p, rvecs, tvecs, points, frames).pixels, intr),
                               j_intr, atol=1e-5 * np.abs(j_intr).max())
    d_rvec = numeric(lambda r: project_poses(intr, r, tvecs, points, frames).pixels, rvecs)
    d_tvec = numeric(lambda t: project_poses(intr, rvecs, t, points, frames).pixels, tvecs)
    d_point = numeric(lambda p: project_poses(intr, rvecs, tvecs, p, frames).pixels, points)
    d_rvec, d_tvec = d_rvec.reshape(20, 2, 3, 3), d_tvec.reshape(20, 2, 3, 3)
    d_point = d_point.reshape(20, 2, 20, 3)
    np.testing.assert_allclose(d_rvec[rows, :, frames], j_pose[:, :, :3], atol=1e-4)
    np.testing.assert_allclose(d_tvec[rows, :, frames], j_pose[:, :, 3:], atol=1e-4)
    np.testing.assert_allclose(d_point[rows, :, rows], j_point, atol=1e-4)


def test_project_poses_matches_cv2_project_points() -> None:
    rng = np.random.default_rng(3)
    camera = BrownConrady(645.2, 644.6, 637.8, 361.4, 0.041, -0.058, 0.0007, -0.0004, 0.019, 1280, 720)
    rvec, tvec = rng.normal(size=3) * 0.4, np.array([0.02, -0.01, 0.5])
    points = rng.normal(size=(30, 3)) * 0.1
    expected = cv2.projectPoints(points, rvec, tvec, camera.K, camera.dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(project_poses(camera.params, rvec, tvec, points).pixels, expected, atol=1e-9)
