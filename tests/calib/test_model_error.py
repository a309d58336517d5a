"""The model-error check (model_error.py): residual structure over the image and the halves' diff
against what noise predicts."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from blurcalib.calib.calibration import Calibration
from blurcalib.calib.joint import GenericCalibration, JointSettings, calibrate_generic
from blurcalib.calib.model_error import model_error, residual_structure
from blurcalib.calib.sharp import calibrate_sharp
from blurcalib.calib.trust import assess_calibration, summary_lines
from blurcalib.calib.uncertainty import CrossValidationDiff, ProjectionUncertainty
from blurcalib.io.results import FeatureFlags, FeatureTable
from blurcalib.target.pattern import layout_pattern
from tests.calib.test_joint import simulated_features

SIZE = (1280, 720)
NOISE_PX = 0.02


def _positions() -> np.ndarray:
    """Feature positions ``(N, 2)`` px of 40 simulated frames of a known camera."""
    t = simulated_features(40, 7, int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME), "s")
    return np.column_stack([t.x, t.y])


def _radial_offset(xy: np.ndarray) -> np.ndarray:
    """A smooth radial offset, 0.05 px at the image's border (half-diagonal), on the right half
    of the image only (x > 640 px); zero elsewhere."""
    c = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
    d = xy - c
    r = np.linalg.norm(d, axis=1, keepdims=True)
    off = 0.05 * (r / np.linalg.norm(c)) * d / np.maximum(r, 1e-9)
    return off * (xy[:, :1] > 640)


def test_pure_noise_is_not_systematic() -> None:
    xy = _positions()
    res = np.random.default_rng(1).normal(0, NOISE_PX, xy.shape)
    check = model_error(xy, res, SIZE)
    assert check.structure.count.sum() == len(xy)
    assert check.structure.systematic_cells == 0
    assert not check.systematic
    assert check.structure.max_mean_px < 0.015
    doc = check.to_dict()
    assert doc["systematic"] is False and doc["noise_ratio"] is None and doc["halves_rms_px"] is None
    assert doc["verdict"].startswith("no systematic error")


def test_field_dependent_offset_is_found() -> None:
    xy = _positions()
    res = np.random.default_rng(1).normal(0, NOISE_PX, xy.shape) + _radial_offset(xy)
    s = residual_structure(xy, res, SIZE)
    assert s.systematic_cells >= 4
    assert 0.03 < s.max_mean_px < 0.06
    left = s.z[:, : s.cells[0] // 2]
    assert np.nanmax(left) < s.z_limit  # the untouched half stays within noise
    check = model_error(xy, res, SIZE)
    assert check.systematic and check.verdict().startswith("systematic error")


def _maps(diff_px: float, sigma_px: float) -> tuple[CrossValidationDiff, ProjectionUncertainty]:
    xs, ys = np.meshgrid(np.arange(0.0, 1280, 16), np.arange(0.0, 720, 16))
    x, y, shape = xs.ravel(), ys.ravel(), xs.shape
    diff = CrossValidationDiff(x, y, shape, np.full(len(x), diff_px), diff_px)
    unc = ProjectionUncertainty(x, y, shape, np.full(len(x), sigma_px), np.zeros((len(x), 2, 2)), NOISE_PX,
                                1280, 720, 0.0, 0.0, NOISE_PX)
    return diff, unc


@pytest.mark.parametrize(("diff_px", "ratio", "systematic"), [(0.02, 1.0, False), (0.06, 3.0, True)])
def test_halves_against_noise(diff_px: float, ratio: float, systematic: bool) -> None:
    xy = _positions()
    res = np.random.default_rng(2).normal(0, NOISE_PX, xy.shape)
    check = model_error(xy, res, SIZE, *_maps(diff_px, 0.01))
    assert math.isclose(check.noise_ratio, ratio, rel_tol=1e-6)
    assert math.isclose(check.halves_rms_px, diff_px, rel_tol=1e-6)
    assert check.systematic is systematic
    assert ("the halves differ by 3.0 x what random noise predicts" in check.verdict()) is systematic
    line = [ln for ln in summary_lines({"model_error": check.to_dict()}) if ln.startswith("model error: ")]
    assert len(line) == 1


def _generic_fit(cell_px: float, noise_px: float) -> tuple[FeatureTable, Calibration, GenericCalibration]:
    """16 simulated sharp frames with ``noise_px`` of noise, their parametric and generic cameras."""
    f = simulated_features(16, 3, int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME), "s")
    rng = np.random.default_rng(0)
    f = dataclasses.replace(f, x=np.asarray(f.x) + rng.normal(0, noise_px, len(f.x)),
                            y=np.asarray(f.y) + rng.normal(0, noise_px, len(f.y)))
    pattern = layout_pattern()
    cal = calibrate_sharp(f, pattern, SIZE, refine_points=False)
    return f, cal, calibrate_generic(f, None, cal, pattern, SIZE, JointSettings(cell_px=cell_px))


@pytest.mark.slow
def test_fitted_generic_camera() -> None:
    """A generic camera whose grid follows the lens (40 px cells) leaves noise; the same residuals
    with the offset added show it; a grid too coarse for the lens (80 px) leaves structure even
    without noise (model error of the camera itself)."""
    g = _generic_fit(40.0, NOISE_PX)[2]
    xy, res = g.observed[g.inlier], g.residuals[g.inlier]
    assert not model_error(xy, res, SIZE).systematic
    assert model_error(xy, res + _radial_offset(xy), SIZE).structure.systematic_cells >= 4
    coarse = _generic_fit(80.0, 0.0)[2]
    s = residual_structure(coarse.observed[coarse.inlier], coarse.residuals[coarse.inlier], SIZE)
    assert s.systematic_cells >= 4 and s.max_mean_px > 0.02


@pytest.mark.slow
def test_assessment_reports_model_error() -> None:
    """assess_calibration's model-error check on a generic camera of noise-only features: no
    systematic verdict, the halves within what noise predicts, one printed line."""
    f, cal, g = _generic_fit(40.0, NOISE_PX)
    doc = assess_calibration(g, None, cal, f, layout_pattern(), SIZE).to_dict()
    me = doc["model_error"]
    assert me["systematic"] is False and me["systematic_cells"] == 0
    assert me["halves_rms_px"] is not None and 0.2 < me["noise_ratio"] < 1.5
    assert sum(ln.startswith("model error: no systematic error") for ln in summary_lines(doc)) == 1
