"""Seeding under heavy blur: a straight motion blur that defeats the plain tag detector at every
scale is undone by the Wiener-deblur search."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from blurcalib.growth.seed import blur_direction, detect_tags, line_kernel, seed_frame
from blurcalib.target.pattern import StarPattern, load_pattern
from tests.conftest import FIXTURE_YAML


def _render(pattern: StarPattern, H: np.ndarray, size: tuple[int, int], blur_px: float,
            angle: float, rng: np.random.Generator) -> np.ndarray:
    """The target seen through ``H`` (feature coordinates -> px), 3 x 3 supersampled, blurred by a
    straight motion of ``blur_px`` along ``angle``, grey levels 40..210 with noise sigma 2."""
    w, h = size
    sub = (np.arange(3) - 1) / 3.0
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    acc = np.zeros((h, w))
    Hinv = np.linalg.inv(H)
    for dy in sub:
        for dx in sub:
            p = np.stack([xs + dx, ys + dy, np.ones_like(xs)], axis=-1) @ Hinv.T
            acc += pattern.intensity(p[..., :2] / p[..., 2:])
    sharp = 40.0 + 170.0 * acc / 9.0
    blurred = cv2.filter2D(sharp, -1, line_kernel(blur_px, angle), borderType=cv2.BORDER_REFLECT)
    return np.clip(blurred + rng.normal(0.0, 2.0, blurred.shape), 0, 255).astype(np.float32)


@pytest.fixture(scope="module")
def pattern() -> StarPattern:
    return load_pattern(FIXTURE_YAML)


def _homography(pattern: StarPattern) -> np.ndarray:
    """Feature coordinates -> px: 28 px squares, rotated by 10 degrees, slightly tilted, the tag
    near the image centre."""
    x0, y0, x1, y1 = pattern.apriltags[0].feature_box
    c, s = np.cos(0.17), np.sin(0.17)
    A = np.array([[28 * c, -28 * s, 0.0], [28 * s, 28 * c, 0.0], [0.0, 0.0, 1.0]])
    A[:2, 2] = np.array([320.0, 240.0]) - A[:2, :2] @ np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2e-4, -1e-4, 1.0]]) @ A


def test_blur_direction_of_a_straight_blur(pattern) -> None:
    rng = np.random.default_rng(1)
    for angle in (0.3, 1.2, 2.5):
        img = _render(pattern, _homography(pattern), (640, 480), 20.0, angle, rng)
        err = abs((blur_direction(img) - angle + np.pi / 2) % np.pi - np.pi / 2)
        assert err < 0.15


def test_heavily_blurred_frame_is_seeded(pattern) -> None:
    H = _homography(pattern)
    img = _render(pattern, H, (640, 480), 22.0, 0.6, np.random.default_rng(0))
    found, _ = detect_tags(img)
    assert not found  # the plain detector fails at every scale
    seed = seed_frame(img, pattern)
    assert seed.source == "tag" and seed.method == "tag_deblurred"
    assert abs(seed.blur[0] - 22.0) <= 6.0
    true = cv2.perspectiveTransform(pattern.tag_corners(pattern.apriltags[0])[None], H)[0]
    assert np.abs(seed.corners_px - true).max() < 3.0
    with pytest.raises(Exception, match="no AprilTag"):
        seed_frame(img, pattern, deblur=False)
