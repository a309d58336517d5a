"""The undistortion map of a calibrated camera, generic or parametric: its projection chosen from
the camera's field, and the written map sending directions where its projection says."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from blurcalib.calib.joint import JointSettings
from blurcalib.calib.undistortion import undistortion_output, undistortion_report, write_undistortion_map
from blurcalib.camera.generic import fit_to_rays
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.remap import OutputProjection
from tests.camera.models import BROWN_CONRADY, KANNALA_BRANDT

FISHEYE = KANNALA_BRANDT.scaled(0.25)
"""190 degrees across the middle row, 222 across the corners (320 x 180 px)."""
MILD = BROWN_CONRADY.scaled(0.25)
"""A 105 degree lens (diagonally; 160 x 120 px)."""


def _calibration(truth: ParametricCamera) -> SimpleNamespace:
    """A generic calibration's cameras: the generic one (fitted to the true rays) and its parametric
    start."""
    model = fit_to_rays(truth.unproject, truth.width, truth.height, cell_px=20.0)
    return SimpleNamespace(model=model, parametric=truth)


@pytest.fixture(scope="module")
def fisheye() -> SimpleNamespace:
    return _calibration(FISHEYE)


@pytest.fixture(scope="module")
def mild() -> SimpleNamespace:
    return _calibration(MILD)


def test_auto_picks_latlong_beyond_120_degrees_and_pinhole_below(fisheye, mild) -> None:
    wide = undistortion_output(fisheye.model, FISHEYE)
    assert wide.kind == "latlong"
    assert undistortion_report(fisheye.model, wide)["field_deg"] == pytest.approx(222.0, abs=2.0)
    narrow = undistortion_output(mild.model, MILD)
    assert narrow == OutputProjection("pinhole", MILD.fx, MILD.fy, MILD.cx, MILD.cy, MILD.width, MILD.height)
    assert undistortion_report(mild.model, narrow)["field_deg"] < 120.0
    assert undistortion_output(fisheye.model, FISHEYE, "stereographic").kind == "stereographic"
    assert undistortion_output(mild.model, MILD, "latlong").kind == "latlong"
    with pytest.raises(ValueError, match="undistort"):
        undistortion_output(mild.model, MILD, "cylindrical")
    with pytest.raises(ValueError, match="undistort"):
        JointSettings(undistort="cylindrical")


def _round_trip(path, truth: ParametricCamera, kind: str) -> tuple[float, float]:
    """Directions the true camera sees at random pixels, through the written map: the share of them
    the map holds and their largest distance (px) from those pixels."""
    maps = np.load(path)
    assert str(maps["projection"]) == kind
    K, width, height = maps["K"], int(maps["width"]), int(maps["height"])
    output = OutputProjection(kind, K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)
    rng = np.random.default_rng(3)
    px = rng.uniform([0.0, 0.0], [truth.width - 1.0, truth.height - 1.0], (3000, 2))
    at = output.project(truth.unproject(px))
    map_x = maps["map_x"]
    x0, y0 = np.floor(at[:, 0]), np.floor(at[:, 1])
    inside = np.isfinite(at).all(axis=1) & (x0 >= 0) & (y0 >= 0) & (x0 < width - 1) & (y0 < height - 1)
    ix, iy = x0[inside].astype(int), y0[inside].astype(int)
    held = np.all([map_x[iy + dy, ix + dx] >= 0 for dy in (0, 1) for dx in (0, 1)], axis=0)
    pts = at[inside][held].astype(np.float32).reshape(-1, 1, 2)
    back = np.column_stack([cv2.remap(maps[k], pts[..., 0], pts[..., 1], cv2.INTER_LINEAR).ravel()
                            for k in ("map_x", "map_y")])
    return float(held.sum()) / len(px), float(np.abs(back - px[inside][held]).max())


@pytest.mark.parametrize("kind", ["latlong", "stereographic"])
def test_a_fisheye_map_sends_directions_where_its_projection_says(fisheye, tmp_path, kind) -> None:
    output = undistortion_output(fisheye.model, FISHEYE, kind)
    path = write_undistortion_map(tmp_path / "undistortion_map.npz", fisheye.model, output)
    share, worst = _round_trip(path, FISHEYE, kind)
    assert share > 0.85 and worst < 0.05


def test_a_parametric_fisheye_camera_has_its_own_wide_map(tmp_path) -> None:
    """Without a generic camera (``--model parametric``) the map is the parametric camera's."""
    output = undistortion_output(FISHEYE, FISHEYE)
    assert output.kind == "latlong"
    path = write_undistortion_map(tmp_path / "undistortion_map.npz", FISHEYE, output)
    share, worst = _round_trip(path, FISHEYE, "latlong")
    assert share > 0.9 and worst < 0.05


def test_a_mild_lens_map_is_the_pinhole_camera(mild, tmp_path) -> None:
    output = undistortion_output(mild.model, MILD)
    path = write_undistortion_map(tmp_path / "undistortion_map.npz", mild.model, output)
    assert np.array_equal(np.load(path)["K"], MILD.K)
    share, worst = _round_trip(path, MILD, "pinhole")
    assert share > 0.6 and worst < 0.05  # the pinhole image of the same K crops the barrel's corners
