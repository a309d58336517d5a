"""Generic calibration of a feature table (joint.py) and its output files."""

from __future__ import annotations

import numpy as np
import pytest

from blurcalib.calib.joint import JointSettings, calibrate_generic, generic_report, save_generic_calibration
from blurcalib.calib.sharp import Calibration, calibrate_sharp
from blurcalib.camera.files import read_generic_yaml
from blurcalib.io.results import FeatureFlags, FeatureTable
from blurcalib.sim.synth import sample_pose
from blurcalib.sim.truth import d435i_like_camera
from blurcalib.target.pattern import StarPattern, layout_pattern


def simulated_features(count: int, seed: int, flags: int, prefix: str, shift: float = 0.0) -> FeatureTable:
    pattern = layout_pattern()
    truth = d435i_like_camera(0, 0.3)
    rng = np.random.default_rng(seed)
    P = pattern.points_3d()
    cols: dict[str, list] = {k: [] for k in ("frame", "feature_id", "fx", "fy", "X", "Y", "x", "y",
                                            "weight", "flags")}
    for i in range(count):
        pose = sample_pose(pattern, truth, rng, 50.0, (24.0, 42.0))
        cam = pose.transform(P)
        px = truth.project(cam) + shift * rng.uniform(-1, 1, 2)
        ok = (cam[:, 2] > 0) & np.all((px >= 0) & (px <= [1279, 719]), axis=1)
        ids = np.nonzero(ok)[0]
        n = len(ids)
        fx, fy = pattern.features[ids].T
        cols["frame"] += [f"{prefix}{i}.png"] * n
        cols["feature_id"] += ids.tolist()
        cols["fx"] += fx.tolist()
        cols["fy"] += fy.tolist()
        cols["X"] += (fx * pattern.square_length_m).tolist()
        cols["Y"] += (fy * pattern.square_length_m).tolist()
        cols["x"] += px[ids, 0].tolist()
        cols["y"] += px[ids, 1].tolist()
        cols["weight"] += [1.0] * n
        cols["flags"] += [flags] * n
    return FeatureTable(**cols)


def joint_inputs() -> tuple[StarPattern, FeatureTable, FeatureTable, Calibration]:
    """The pattern, 8 sharp and 4 blurry simulated frames' features (the blurry ones shifted by up
    to 2 px, no noise) and the sharp frames' parametric camera."""
    pattern = layout_pattern()
    sharp = simulated_features(8, 1, int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME), "s")
    blurry = simulated_features(4, 2, int(FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME), "b",
                                shift=2.0)
    return pattern, sharp, blurry, calibrate_sharp(sharp, pattern, (1280, 720), refine_points=False)


@pytest.fixture(scope="module")
def fitted():
    pattern, sharp, blurry, parametric = joint_inputs()
    settings = JointSettings(cell_px=80.0)
    return parametric, calibrate_generic(sharp, blurry, parametric, pattern, (1280, 720), settings)


def test_generic_beats_parametric(fitted) -> None:
    parametric, result = fitted
    assert len(result.blurry_frames) == 4 and len(result.shifts) == 4
    assert result.median_error < parametric.median_error / 3
    assert result.blurry_median_error < 0.05
    report = generic_report(result)
    assert report["blurry_frames"] == 4 and report["median_error_px"] == result.median_error


@pytest.mark.slow
def test_files(fitted, tmp_path) -> None:
    _, result = fitted
    pinhole = result.parametric.scaled(0.25)
    paths = save_generic_calibration(tmp_path / "calibration", result, pinhole=pinhole)
    assert [p.name for p in paths] == ["intrinsics0.yaml", "generic_poses.csv", "undistortion_map.npz",
                                       "generic_coverage.png", "generic_minus_parametric.png"]
    back = read_generic_yaml(paths[0])
    np.testing.assert_allclose(back.grid, result.model.grid, atol=1e-13)
    maps = np.load(paths[2])
    assert maps["map_x"].shape == (180, 320)
    xx, yy = np.meshgrid(np.arange(320.0), np.arange(180.0))
    rays = np.stack([(xx - pinhole.cx) / pinhole.fx, (yy - pinhole.cy) / pinhole.fy, np.ones_like(xx)], -1)
    u, inside = result.model.project(rays.reshape(-1, 3))
    ok = inside & (maps["map_x"].reshape(-1) >= 0)
    assert ok.mean() > 0.9
    assert np.abs(maps["map_x"].reshape(-1)[ok] - u[ok, 0]).max() < 1e-3
    lines = paths[1].read_text().splitlines()
    assert lines[0] == "frame,tx,ty,tz,qx,qy,qz,qw,shift_x,shift_y" and len(lines) == 13
