"""The star target: YAML, exact page render against the reference PNG, features, signed distance."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from blurcalib.data import reference_pattern_path
from blurcalib.target.pattern import (
    PatternFileError,
    StarPattern,
    layout_pattern,
    load_pattern,
    star_signed_distance,
)
from tests.conftest import FIXTURE_PNG, FIXTURE_YAML


@pytest.fixture(scope="module")
def fixture_pattern() -> StarPattern:
    return load_pattern(FIXTURE_YAML)


def _assert_same_pattern(a: StarPattern, b: StarPattern) -> None:
    assert (a.num_star_segments, a.squares_x, a.squares_y, a.apriltags) == (
        b.num_star_segments, b.squares_x, b.squares_y, b.apriltags)
    assert a.square_length_m == pytest.approx(b.square_length_m, rel=1e-12)
    for fa, fb in zip(dataclasses.astuple(a.page), dataclasses.astuple(b.page), strict=True):
        assert fa == pytest.approx(fb, abs=1e-9)


def test_fixture_yaml_fields(fixture_pattern: StarPattern) -> None:
    p = fixture_pattern
    assert (p.num_star_segments, p.squares_x, p.squares_y) == (16, 17, 24)
    assert p.square_length_m == pytest.approx(0.011882352941176469)
    assert p.apriltags[0].index == 0 and p.apriltags[0].feature_box == (5, 9, 9, 13)


@pytest.mark.parametrize(("name", "approx_mm", "tag"), [
    ("pattern_resolution_17x24_segments_16_apriltag_0.yaml", 12.0, 0),
    ("pattern_resolution_25x36_segments_16_apriltag_6.yaml", 8.0, 6),
    ("pattern_resolution_50x72_segments_16_apriltag_3.yaml", 4.0, 3),
])
def test_layout_reproduces_reference_generator(name, approx_mm, tag) -> None:
    mine = layout_pattern(approx_square_length_mm=approx_mm, tag_index=tag)
    _assert_same_pattern(mine, load_pattern(reference_pattern_path(name)))
    assert mine.to_yaml_text() == reference_pattern_path(name).read_text()


def test_yaml_round_trip(tmp_path, fixture_pattern: StarPattern) -> None:
    out = fixture_pattern.save_yaml(tmp_path / "p.yaml")
    _assert_same_pattern(load_pattern(out), fixture_pattern)
    assert list(tmp_path.iterdir()) == [out]  # no temporary file left behind


def test_render_matches_reference_png(shared_fixtures, fixture_pattern: StarPattern) -> None:
    ref = cv2.imread(str(FIXTURE_PNG), cv2.IMREAD_UNCHANGED)[..., 0].astype(np.int32)
    h, w = ref.shape
    mine = fixture_pattern.render_page(dpi=136, supersample=3, size_px=(w, h)).astype(np.int32)
    exact = fixture_pattern.render_page(dpi=136, supersample=1, size_px=(w, h))
    kernel = np.ones((3, 3), np.uint8)
    away_from_edges = cv2.erode(exact, kernel) == cv2.dilate(exact, kernel)
    agree = np.abs(mine - ref) <= 32
    assert away_from_edges.mean() > 0.5
    assert agree[away_from_edges].mean() >= 0.99


def test_tag_detected_where_the_layout_puts_it(fixture_pattern: StarPattern) -> None:
    dpi = 136
    page = fixture_pattern.render_page(dpi=dpi, supersample=2)
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
        cv2.aruco.DetectorParameters())
    corners, ids, _ = detector.detectMarkers(page)
    assert ids is not None and ids.ravel().tolist() == [0]
    tag = fixture_pattern.apriltags[0]
    expected_px = fixture_pattern.feature_to_page_mm(fixture_pattern.tag_corners(tag)) / 25.4 * dpi
    expected_px -= 0.5  # pixel-centre convention
    assert np.abs(corners[0][0] - expected_px).max() < 1.5


def test_feature_layout(fixture_pattern: StarPattern) -> None:
    p = fixture_pattern
    # (17 - 1) x (24 - 1) interior corners minus the 5 x 5 corners on and around the tag.
    assert p.num_features == 16 * 23 - 25
    f = p.features
    order = f[:, 1] * 100 + f[:, 0]
    assert np.all(np.diff(order) > 0)  # y-major ids
    assert np.array_equal(p.feature_ids(f[:, 0], f[:, 1]), np.arange(p.num_features))
    assert p.feature_ids(np.array([5, 7, -1, 16]), np.array([9, 11, 0, 0])).tolist() == [-1] * 4
    pts = p.points_3d()
    assert np.allclose(pts[:, :2], f * p.square_length_m) and np.all(pts[:, 2] == 0)
    first = p.neighbours(0)
    assert sorted(first) == sorted([1, int(p.feature_ids(0, 1))])
    assert all(0 in p.neighbours(n) for n in first)


def _random_block_points(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, size=(n, 2))


def test_signed_distance_sign_matches_exact(fixture_pattern: StarPattern) -> None:
    q = _random_block_points(20000, 0)
    feature = np.array([2, 3])  # an ordinary star away from the tag
    exact = fixture_pattern.intensity(feature + q / 2)
    dist = star_signed_distance(torch.from_numpy(q), 16).numpy()
    clear = np.abs(dist) > 0.03
    assert clear.mean() > 0.6
    assert np.array_equal(dist[clear] > 0, exact[clear] > 0.5)


def test_signed_distance_is_a_distance(fixture_pattern: StarPattern) -> None:
    """Moving a point by less than |d| never changes its colour; by a bit more it can."""
    q = _random_block_points(4000, 1) * 0.98
    d = star_signed_distance(torch.from_numpy(q), 16).numpy()
    angles = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    feature = np.array([2, 3])
    base = fixture_pattern.intensity(feature + q / 2)
    inner = q[:, None, :] + 0.97 * np.abs(d)[:, None, None] * ring[None]
    assert np.all(fixture_pattern.intensity(feature + inner / 2) == base[:, None])
    outer = q[:, None, :] + 1.2 * np.abs(d)[:, None, None] * ring[None] + 1e-6
    changed = np.any(fixture_pattern.intensity(feature + outer / 2) != base[:, None], axis=1)
    assert changed.mean() > 0.95


def test_neighbouring_stars_have_opposite_colours_at_their_border(
        fixture_pattern: StarPattern) -> None:
    t = np.linspace(-0.49, 0.49, 101)
    left = fixture_pattern.intensity(np.stack([np.full_like(t, 2.499), 3 + t], axis=1))
    right = fixture_pattern.intensity(np.stack([np.full_like(t, 2.501), 3 + t], axis=1))
    assert np.mean(left != right) > 0.9


@pytest.mark.parametrize(("text", "needle"), [
    ("squares_x: 17\n", "num_star_segments"),
    ("num_star_segments: 16\nsquares_x: 17\nsquares_y: 24\nsquare_length_in_meters: 0.01\n", "'page'"),
    ("num_star_segments: 10\nsquares_x: 17\nsquares_y: 24\nsquare_length_in_meters: 0.01\n"
     "page: {width_mm: 1, height_mm: 1, pattern_start_x_mm: 0, pattern_start_y_mm: 0,"
     " pattern_end_x_mm: 1, pattern_end_y_mm: 1}\n", "multiple of 4"),
    ("num_star_segments: [16\n", "not valid YAML"),
    ("just a string\n", "mapping"),
])
def test_bad_yaml_names_file_and_field(tmp_path, text: str, needle: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(PatternFileError) as err:
        load_pattern(path)
    assert str(path) in str(err.value) and needle in str(err.value)


def test_missing_yaml(tmp_path) -> None:
    with pytest.raises(PatternFileError, match="not found"):
        load_pattern(tmp_path / "nope.yaml")


@pytest.mark.parametrize(("key", "value", "needle"), [
    ("squares_x", "100000000", "field 'squares_x' must be between 3 and 1000"),
    ("squares_y", "2", "field 'squares_y' must be between 3 and 1000"),
    ("squares_x", ".inf", "field 'squares_x' must be int"),
    ("square_length_in_meters", ".inf", "field 'square_length_in_meters' must be a finite positive"),
    ("square_length_in_meters", ".nan", "field 'square_length_in_meters' must be a finite positive"),
    ("square_length_in_meters", "-0.01", "field 'square_length_in_meters' must be a finite positive"),
    ("square_length_in_meters", "0.02", "field 'squares_x' is 17, but the page's pattern area"),
    ("width_mm", ".inf", "field 'page.width_mm' must be a finite positive"),
    ("pattern_end_x_mm", "1e9", "must lie on the page"),
    ("pattern_start_y_mm", "400", "start < end"),
    ("tag_x", "15", "field 'apriltags[0]'"),
])
def test_unsound_geometry_is_refused_before_allocating(tmp_path, shared_fixtures, key: str,
                                                       value: str, needle: str) -> None:
    lines = FIXTURE_YAML.read_text().splitlines()
    changed = [f"{line.split(':')[0]}: {value}" if line.strip().lstrip("- ").startswith(f"{key}:")
               else line for line in lines]
    assert changed != lines
    path = tmp_path / "bad.yaml"
    path.write_text("\n".join(changed) + "\n")
    with pytest.raises(PatternFileError) as err:
        load_pattern(path)
    assert str(err.value).startswith(f"{path}: ") and needle in str(err.value)


def test_consistent_large_target_is_accepted(tmp_path) -> None:
    """A poster of 1000 x 700 squares of 2 mm: the page agrees with the squares."""
    poster = layout_pattern(page_size_mm=(2008.0, 1408.0), approx_square_length_mm=2.0)
    assert (poster.squares_x, poster.squares_y) == (1000, 700)
    back = load_pattern(poster.save_yaml(tmp_path / "poster.yaml"))
    assert back == poster and back.num_features > 690_000
