"""The cross-pattern residual: two feature sets of the same target points through one homography
per frame, in undistorted pixels."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from blurcalib.calib.cross_pattern import check_patterns, cross_residuals, radial_profile
from blurcalib.camera.parametric import BrownConrady
from blurcalib.io.results import FeatureTable

CAMERA = BrownConrady(fx=900.0, fy=901.0, cx=650.0, cy=370.0, k1=0.16, k2=-0.49, p1=0.0006, p2=0.0027,
                      k3=0.47, width=1280, height=720)


def _table(frames: list[np.ndarray]) -> FeatureTable:
    names = np.concatenate([[f"{i}.png"] * len(xy) for i, xy in enumerate(frames)])
    xy = np.concatenate(frames)
    ids = np.concatenate([np.arange(len(f)) for f in frames])
    n = len(xy)
    return FeatureTable(frame=names, feature_id=ids, fx=ids % 17, fy=ids // 17, X=np.zeros(n), Y=np.zeros(n),
                        x=xy[:, 0], y=xy[:, 1], weight=np.ones(n), flags=np.zeros(n, dtype=np.int64))


def _views(rng: np.random.Generator, count: int) -> list[np.ndarray]:
    """Undistorted-pixel positions of a 17 x 12 grid seen by ``count`` random homographies."""
    g = np.stack(np.meshgrid(np.arange(17.0), np.arange(12.0)), axis=-1).reshape(-1, 2)
    out = []
    for _ in range(count):
        H = np.array([[38.0, rng.normal(0, 3), 330 + rng.normal(0, 40)],
                      [rng.normal(0, 3), 38.0, 150 + rng.normal(0, 40)],
                      [rng.normal(0, 3e-4), rng.normal(0, 3e-4), 1.0]])
        p = g @ H[:, :2].T + H[:, 2]
        out.append(p[:, :2] / p[:, 2:])
    return out


def _distort(u: np.ndarray) -> np.ndarray:
    xn = (u - [CAMERA.cx, CAMERA.cy]) / [CAMERA.fx, CAMERA.fy]
    return CAMERA.distort(xn) * [CAMERA.fx, CAMERA.fy] + [CAMERA.cx, CAMERA.cy]


def test_a_moved_target_leaves_no_residual() -> None:
    rng = np.random.default_rng(0)
    views = _views(rng, 3)
    a = _table([_distort(u) for u in views])
    # the target moved on the screen by 2.5 px and its scale changed: a homography per frame
    moved = [(u - u.mean(axis=0)) * 1.003 + u.mean(axis=0) + [2.5, -1.0] for u in views]
    b = _table([_distort(u) for u in moved])
    res = cross_residuals(a, b, CAMERA)
    assert res.inlier.all() and len(res.frame) == 3 * 204
    assert np.abs(res.residual).max() < 1e-6


def test_a_radial_bias_shows_in_the_profile() -> None:
    rng = np.random.default_rng(1)
    views = _views(rng, 4)
    a = _table([_distort(u) + rng.normal(0, 0.01, u.shape) for u in views])
    centre = np.array([CAMERA.cx, CAMERA.cy])
    biased = []
    for u in views:
        x = _distort(u)
        d = x - centre
        r = np.linalg.norm(d, axis=1, keepdims=True)
        biased.append(x + 0.2 * (r / 400.0) ** 2 * d / r + rng.normal(0, 0.01, u.shape))
    b = _table(biased)
    b.x[5] += 3.0  # one wrong feature
    res = cross_residuals(a, b, CAMERA)
    assert res.inlier.sum() == len(res.inlier) - 1
    prof = radial_profile(res, np.array([0.0, 100.0, 200.0, 300.0, 450.0]))
    # the homography takes the mean and the linear part of r^2: the rest is negative in the
    # middle of the features and positive at their outer edge
    assert prof.radial[0] < -0.01 and prof.radial[-1] > 0.01
    assert np.all(np.abs(prof.tangential[prof.count > 0]) < 0.005)
    assert prof.z[-1] > 5
    assert len(prof.rows()) == 4


def _biased_pair(bias_px: float, seed: int) -> tuple[FeatureTable, FeatureTable]:
    """Two noisy feature sets (0.01 px) of the same views, ``b`` moved radially by ``bias_px``
    times ``(r / 400)^2``."""
    rng = np.random.default_rng(seed)
    views = _views(rng, 4)
    centre = np.array([CAMERA.cx, CAMERA.cy])
    a, b = [], []
    for u in views:
        x = _distort(u)
        d = x - centre
        r = np.linalg.norm(d, axis=1, keepdims=True)
        a.append(x + rng.normal(0, 0.01, u.shape))
        b.append(x + bias_px * (r / 400.0) ** 2 * d / r + rng.normal(0, 0.01, u.shape))
    return _table(a), _table(b)


def test_check_names_a_radial_bias_and_not_noise() -> None:
    edges = np.array([0.0, 100.0, 200.0, 300.0, 450.0])
    longer = replace(CAMERA, fx=CAMERA.fx * 1.0005, fy=CAMERA.fy * 1.0006)
    check = check_patterns(*_biased_pair(0.2, 4), CAMERA, longer, edges=edges)
    assert check.systematic and check.worst_radial_px > 0.01
    assert check.frames == 4 and check.matches == 4 * 204
    np.testing.assert_allclose(check.focal_pct, [0.05, 0.06], atol=1e-9)
    assert check.lines()[0].startswith("systematic error") and len(check.lines()) == 2 + 4
    # noise alone, and a bias below the limit, are not named systematic
    for bias in (0.0, 0.005):
        quiet = check_patterns(*_biased_pair(bias, 5), CAMERA, CAMERA, edges=edges)
        assert not quiet.systematic and quiet.lines()[0].startswith("no systematic error")


def test_check_without_common_frames_says_so() -> None:
    a = _table(_views(np.random.default_rng(2), 1))
    b = _table(_views(np.random.default_rng(3), 1))
    b.frame[:] = "other.png"
    with pytest.raises(ValueError, match="share no frame"):
        check_patterns(a, b, CAMERA, CAMERA)


def test_tables_without_common_frames() -> None:
    a = _table(_views(np.random.default_rng(2), 1))
    b = _table(_views(np.random.default_rng(3), 1))
    b.frame[:] = "other.png"
    res = cross_residuals(a, b, CAMERA)
    assert len(res.frame) == 0
    with pytest.raises(ValueError):
        radial_profile(res)
