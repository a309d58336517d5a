"""A rig's files (blurcalib.camera.rig_files), the rig itself (blurcalib.camera.rig) and the stereo
rectification (blurcalib.camera.stereo): round trips, the reference tool's pose format, refused
files, OpenCV's rectifying rotations and rectified pairs on one row."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.camera.generic import fit_to_rays
from blurcalib.camera.parametric import BrownConrady
from blurcalib.camera.remap import central_pixel, output_for
from blurcalib.camera.rig import Rig
from blurcalib.camera.rig_files import (
    CAMERA_TR_RIG_FILE,
    RigFileError,
    read_poses,
    read_rig_folder,
    read_stereo_yaml,
    write_poses,
    write_rig_folder,
    write_stereo_pair,
)
from blurcalib.camera.stereo import epipolar_errors, rectifying_rotations, stereo_rectify
from blurcalib.geometry.pose import Pose

LENS = BrownConrady(fx=300.0, fy=299.0, cx=160.2, cy=119.6, k1=-0.05, k2=0.01, p1=0.0, p2=0.0, k3=0.0,
                    width=320, height=240)


def _pose(seed: int) -> Pose:
    rng = np.random.default_rng(seed)
    return Pose.from_rvec_tvec(rng.normal(0, 0.3, 3), rng.normal(0, 0.2, 3))


@pytest.fixture(scope="module")
def rig() -> Rig:
    camera = fit_to_rays(LENS.pixel_to_ray, 320, 240, cell_px=40.0)
    R = Pose.from_rvec_tvec([0.003, -0.008, 0.002], np.zeros(3)).R
    return Rig((camera, camera.rotated(Pose.from_rvec_tvec([0.0, 0.001, 0.0], np.zeros(3)).R)),
               (Pose.identity(), Pose(R, -R @ np.array([0.05, 0.001, 0.0]))))


def test_pose_file_round_trip_in_the_reference_format(tmp_path: Path) -> None:
    poses = [_pose(1), None, _pose(2)]
    path = write_poses(tmp_path / "rig_tr_global.yaml", poses)
    text = path.read_text()
    assert text.startswith("# Each pose gives the B_tr_A transformation")
    assert "pose_count: 3\nposes:\n  - index: 0\n    tx: " in text and "  - index: 2\n" in text
    back = read_poses(path)
    assert back[1] is None
    for a, b in ((poses[0], back[0]), (poses[2], back[2])):
        assert a is not None and b is not None
        assert np.allclose(a.R, b.R, atol=1e-13) and np.allclose(a.t, b.t, atol=1e-13)
    q = Pose.from_quaternion(back[0].quaternion, back[0].t)  # type: ignore[union-attr]
    assert np.allclose(q.R, back[0].R, atol=1e-15)  # type: ignore[union-attr]


def test_rig_folder_round_trip(tmp_path: Path, rig: Rig) -> None:
    sets = [_pose(3), None, _pose(4)]
    points = np.column_stack([np.arange(6) * 0.02, np.zeros(6), np.zeros(6)])
    paths = write_rig_folder(tmp_path, rig, sets, points)
    assert sorted(p.name for p in paths) == ["camera_tr_rig.yaml", "intrinsics0.yaml", "intrinsics1.yaml",
                                             "points.yaml", "rig_tr_global.yaml"]
    folder = read_rig_folder(tmp_path)
    assert folder.rig.size == 2 and folder.rig_tr_global[1] is None
    for a, b in zip(rig.cameras, folder.rig.cameras, strict=True):
        assert np.allclose(a.grid, b.grid, atol=1e-12) and a.area_opencv == b.area_opencv
    for a, b in zip(rig.camera_tr_rig, folder.rig.camera_tr_rig, strict=True):
        assert np.allclose(a.R, b.R, atol=1e-13) and np.allclose(a.t, b.t, atol=1e-13)


def test_refused_rig_files(tmp_path: Path, rig: Rig) -> None:
    with pytest.raises(RigFileError, match=r"intrinsics0\.yaml: no camera file"):
        read_rig_folder(tmp_path)
    write_rig_folder(tmp_path, rig, [_pose(5)])
    write_poses(tmp_path / CAMERA_TR_RIG_FILE, [Pose.identity()])
    with pytest.raises(RigFileError, match=r"camera_tr_rig\.yaml: needs one pose for each of the 2 cameras"):
        read_rig_folder(tmp_path)
    bad = tmp_path / "bad.yaml"
    bad.write_text("pose_count: 1\nposes:\n  - index: 0\n    tx: 1\n")
    with pytest.raises(RigFileError, match=r"bad\.yaml: pose index 0: needs numbers"):
        read_poses(bad)
    bad.write_text("pose_count: 1\nposes:\n  - index: 4\n")
    with pytest.raises(RigFileError, match="outside"):
        read_poses(bad)


def test_rectifying_rotations_are_opencvs() -> None:
    relative = Pose.from_rvec_tvec([0.01, -0.02, 0.005], [-0.05, 0.002, 0.001])
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    R1, R2, *_ = cv2.stereoRectify(K, np.zeros(5), K, np.zeros(5), (320, 240), relative.R,
                                   relative.t.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY)
    ours1, ours2, axis = rectifying_rotations(relative)
    assert axis == 0
    assert np.allclose(ours1, R1, atol=1e-12) and np.allclose(ours2, R2, atol=1e-12)


def test_stereo_pair_rectified_on_one_row(rig: Rig) -> None:
    rect = stereo_rectify(rig.cameras[0], rig.cameras[1], rig.relative(0, 1))
    assert rect.output.kind == "pinhole" and abs(abs(rect.baseline_m) - np.hypot(0.05, 0.001)) < 1e-9
    rng = np.random.default_rng(0)
    X0 = np.column_stack([rng.uniform(-0.3, 0.3, 50), rng.uniform(-0.2, 0.2, 50), rng.uniform(0.8, 2.0, 50)])
    px0, ok0 = rig.cameras[0].project(X0)
    px1, ok1 = rig.cameras[1].project(rig.relative(0, 1).transform(X0))
    ok = ok0 & ok1
    errors = epipolar_errors(rect, rig.cameras[0].pixel_to_ray, rig.cameras[1].pixel_to_ray, px0[ok], px1[ok])
    assert ok.sum() > 30 and np.nanmax(errors) < 1e-6
    Q = rect.projection_matrices()[2]
    q0 = rect.output.project(rig.cameras[0].pixel_to_ray(px0[ok]) @ rect.R1.T)
    q1 = rect.output.project(rig.cameras[1].pixel_to_ray(px1[ok]) @ rect.R2.T)
    h = np.column_stack([q0, q0[:, 0] - q1[:, 0], np.ones(len(q0))]) @ Q.T
    depth_rect = (X0[ok] @ rect.R1.T)[:, 2]
    assert np.allclose(h[:, 2] / h[:, 3], depth_rect, rtol=1e-6)
    wide = stereo_rectify(rig.cameras[0], rig.cameras[1], rig.relative(0, 1), "epipolar")
    assert wide.output.kind == "epipolar"


@pytest.mark.slow
def test_stereo_files_and_maps(tmp_path: Path, rig: Rig) -> None:
    rect, paths = write_stereo_pair(tmp_path, rig, 0, 1)
    assert [p.name for p in paths] == ["stereo_0_1.yaml", "rectify_0_1.npz"]
    back = read_stereo_yaml(paths[0])
    assert np.allclose(back.R1, rect.R1) and np.allclose(back.R2, rect.R2)
    assert np.allclose(back.relative.t, rect.relative.t) and back.output == rect.output
    maps = np.load(paths[1])
    assert maps["map1_x"].shape == (240, 320) and maps["map2_y"].dtype == np.float32
    ray = rect.output.rays(np.array([159.0]), np.array([119.0])) @ rect.R1  # in camera 0's frame
    px, _ = rig.cameras[0].project(ray)
    assert np.allclose([maps["map1_x"][119, 159], maps["map1_y"][119, 159]], px[0], atol=1e-3)


def test_output_projections_invert_their_rays_and_epipolar_rows_are_planes() -> None:
    from blurcalib.camera.remap import OutputProjection

    xs, ys = np.meshgrid(np.linspace(5.0, 95.0, 7), np.linspace(5.0, 75.0, 5))
    for kind in ("pinhole", "latlong", "stereographic", "epipolar"):
        out = OutputProjection(kind, 60.0, 60.0, 50.0, 40.0, 101, 81)
        rays = out.rays(xs.ravel(), ys.ravel())
        assert np.allclose(out.project(rays), np.column_stack([xs.ravel(), ys.ravel()]), atol=1e-9)
    epipolar = OutputProjection("epipolar", 60.0, 60.0, 50.0, 40.0, 101, 81)
    row = epipolar.rays(np.linspace(0.0, 100.0, 9), np.full(9, 20.0))
    normal = np.cross([1.0, 0.0, 0.0], row[4])
    assert np.abs(row @ normal).max() < 1e-12  # one plane through the baseline (x axis)


def test_parametric_frames_keep_what_the_rig_sees(rig: Rig) -> None:
    from blurcalib.camera.brown_conrady import BrownConradyCamera
    from blurcalib.camera.rig import parametric_frames

    turned, cameras, to_new = parametric_frames(rig, [BrownConradyCamera, BrownConradyCamera], step_px=16.0)
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-0.2, 0.2, 20), rng.uniform(-0.15, 0.15, 20), rng.uniform(0.8, 1.5, 20)])
    for c in range(2):
        before, ok = rig.cameras[c].project(rig.camera_tr_rig[c].transform(X))
        seen = turned.camera_tr_rig[c].compose(to_new).transform(X)
        after, ok2 = turned.cameras[c].project(seen)
        assert (ok & ok2).sum() > 10
        assert np.abs(after - before)[ok & ok2].max() < 1e-6
        assert np.abs(cameras[c].project(seen) - after)[ok & ok2].max() < 0.05
    assert np.allclose(turned.camera_tr_rig[0].R, np.eye(3)) and np.allclose(turned.camera_tr_rig[0].t, 0.0)


def test_a_camera_calibrated_away_from_its_image_centre_is_rectified(rig: Rig) -> None:
    """A camera whose frames covered only the left part of its image has no ray at the image
    centre: its focal length comes from the pixel nearest the centre that has rays."""
    left = fit_to_rays(LENS.pixel_to_ray, 320, 240, area=(0, 0, 120, 239), cell_px=40.0)
    assert not np.isfinite(left.pixel_to_ray(np.array([[159.5, 119.5]]))).all()
    assert central_pixel(left)[0] < 120.0 and np.array_equal(central_pixel(rig.cameras[0]), [159.5, 119.5])
    rect = stereo_rectify(rig.cameras[0], left, rig.relative(0, 1))
    assert rect.output.kind == "pinhole"
    outputs = [output_for(left), output_for(rig.cameras[0])]
    assert rect.output.fx == pytest.approx(min(min(o.fx, o.fy) for o in outputs))
    assert 285.0 < output_for(left).fx < 315.0  # the lens's 300 px per radian, off its centre
