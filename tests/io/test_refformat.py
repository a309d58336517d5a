"""The reference tool's binary feature dataset: the real fixture, round trips, errors, export."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.ndimage as ndi

from blurcalib.io.frames import load_frame
from blurcalib.io.refformat import (
    RefDataset,
    RefFormatError,
    encode_ref_dataset,
    read_ref_dataset,
    to_ref_dataset,
    write_ref_dataset,
)
from blurcalib.target.pattern import StarPattern, load_pattern
from tests.conftest import FIXTURE_YAML, REAL

FEATURES_BIN = REAL / "features_10px.bin"


@pytest.fixture(scope="module")
def real_dataset(shared_fixtures) -> RefDataset:
    return read_ref_dataset(FEATURES_BIN)


@pytest.fixture(scope="module")
def real_pattern(shared_fixtures) -> StarPattern:
    return load_pattern(REAL / "pattern.yaml")


@pytest.fixture(scope="module")
def shipped_pattern() -> StarPattern:
    """The shipped 17x24 pattern (the real frames' geometry, tag #0): for tests of the format alone."""
    return load_pattern(FIXTURE_YAML)


def _symmetry_score(image: np.ndarray, centres: np.ndarray, radius: float = 4.0) -> np.ndarray:
    """``(N,)`` sum over a disc of offsets d of ``(I(c + d) - I(c - d))^2``, bilinear sampling."""
    grid = np.arange(-radius, radius + 1e-9, 0.5)
    dx, dy = np.meshgrid(grid, grid)
    keep = (dx**2 + dy**2 <= radius**2) & (dx**2 + dy**2 > 0)
    d = np.stack([dx[keep], dy[keep]], axis=1)

    def sample(pts: np.ndarray) -> np.ndarray:
        return ndi.map_coordinates(image, [pts[..., 1], pts[..., 0]], order=1, mode="nearest")

    c = np.asarray(centres, dtype=np.float64)[:, None, :]
    return ((sample(c + d) - sample(c - d)) ** 2).sum(axis=1)


def _small_dataset(pattern: StarPattern) -> RefDataset:
    rng = np.random.default_rng(3)
    ids = np.array([5, 0, 17, 3, 5, 100])
    frame_of_obs = np.array([0, 0, 0, 2, 2, 2])
    x = rng.uniform(-0.5, 639.5, len(ids))
    y = rng.uniform(-0.5, 479.5, len(ids))
    return to_ref_dataset((640, 480), ["a.png", "b.png", "c 10.png"], frame_of_obs, ids, x, y,
                          pattern)


def test_fixture_header_and_images(real_dataset: RefDataset) -> None:
    ds = real_dataset
    assert ds.image_size == (1280, 720)
    assert len(ds.images) == 27
    names = [img.name for img in ds.images]
    # The fixture frames 0.png .. 3.png are in the detector's run; its other frames are named
    # 10.png .. 32.png (fixture frames 4.png .. 7.png are not among them).
    assert {"0.png", "1.png", "2.png", "3.png"} <= set(names)
    assert len(set(names)) == 27
    for img in ds.images:
        assert img.features.dtype == np.int64 and img.xy.shape == (len(img.features), 2)
        assert len(np.unique(img.features)) == len(img.features)
    assert len(ds.image("0.png").features) == 257


def test_fixture_geometry_matches_pattern(real_dataset: RefDataset,
                                          real_pattern: StarPattern) -> None:
    geo = real_dataset.geometry
    assert np.float32(geo.square_length_m) == np.float32(real_pattern.square_length_m)
    assert len(geo.ids) == real_pattern.num_features == 343
    np.testing.assert_array_equal(real_pattern.feature_ids(geo.fx, geo.fy), geo.ids)
    np.testing.assert_array_equal(np.sort(geo.ids), np.arange(343))
    for img in real_dataset.images:
        assert img.features.min() >= 0 and img.features.max() < 343


def test_fixture_features_inside_image(real_dataset: RefDataset) -> None:
    xy = real_dataset.image("0.png").xy
    w, h = real_dataset.image_size
    assert np.all((xy >= -0.5) & (xy <= [w - 0.5, h - 0.5]))


def test_fixture_positions_are_star_centres(real_dataset: RefDataset) -> None:
    """After subtracting 0.5 px the positions are point-symmetry centres of the real frame."""
    image = load_frame(REAL / "images" / "0.png", expected_size=real_dataset.image_size)
    xy = real_dataset.image("0.png").xy
    score = _symmetry_score(image, xy)
    median = xy[np.argsort(score)[len(score) // 2]][None]
    at = _symmetry_score(image, median)[0]
    for offset in ([0.5, 0.0], [-0.5, 0.0], [0.0, 0.5], [0.0, -0.5], [0.5, 0.5], [-0.5, -0.5]):
        assert at < _symmetry_score(image, median + offset)[0]
    # Over all features, the file's positions minus 0.5 beat the unconverted ones by far.
    assert np.median(score) < 0.3 * np.median(_symmetry_score(image, xy + 0.5))


def test_fixture_rewrites_byte_for_byte(real_dataset: RefDataset, tmp_path: Path) -> None:
    out = write_ref_dataset(tmp_path / "copy.bin", real_dataset)
    assert out.read_bytes() == FEATURES_BIN.read_bytes()


def test_round_trip(shipped_pattern: StarPattern, tmp_path: Path) -> None:
    ds = _small_dataset(shipped_pattern)
    back = read_ref_dataset(write_ref_dataset(tmp_path / "small.bin", ds))
    assert back.image_size == (640, 480)
    assert [img.name for img in back.images] == ["a.png", "b.png", "c 10.png"]
    for a, b in zip(ds.images, back.images, strict=True):
        np.testing.assert_array_equal(a.features, b.features)
        np.testing.assert_allclose(b.xy, a.xy, rtol=0, atol=640 * 2.0**-23)
        np.testing.assert_array_equal(b.xy + 0.5, (a.xy + 0.5).astype(np.float32))
    geo, geo_back = ds.geometry, back.geometry
    assert geo_back.square_length_m == float(np.float32(geo.square_length_m))
    for field in ("ids", "fx", "fy"):
        np.testing.assert_array_equal(getattr(geo_back, field), getattr(geo, field))


def test_to_ref_dataset_layout(shipped_pattern: StarPattern) -> None:
    ds = _small_dataset(shipped_pattern)
    assert [len(img.features) for img in ds.images] == [3, 0, 3]
    np.testing.assert_array_equal(ds.images[0].features, [0, 5, 17])
    np.testing.assert_array_equal(ds.images[2].features, [3, 5, 100])
    geo = ds.geometry
    np.testing.assert_array_equal(shipped_pattern.feature_ids(geo.fx, geo.fy), geo.ids)
    assert geo.square_length_m == shipped_pattern.square_length_m


def test_to_ref_dataset_errors(shipped_pattern: StarPattern) -> None:
    args = ((640, 480), ["a.png"])
    with pytest.raises(ValueError, match="more than once"):
        to_ref_dataset(*args, [0, 0], [4, 4], [1.0, 2.0], [1.0, 2.0], shipped_pattern)
    with pytest.raises(ValueError, match="feature ids"):
        to_ref_dataset(*args, [0], [343], [1.0], [1.0], shipped_pattern)
    with pytest.raises(ValueError, match="index the 1 frames"):
        to_ref_dataset(*args, [1], [0], [1.0], [1.0], shipped_pattern)
    with pytest.raises(ValueError, match="same length"):
        to_ref_dataset(*args, [0], [0], [1.0, 2.0], [1.0], shipped_pattern)
    with pytest.raises(ValueError, match="finite"):
        to_ref_dataset(*args, [0], [0], [np.nan], [1.0], shipped_pattern)


def test_truncated_files(shipped_pattern: StarPattern, tmp_path: Path) -> None:
    data = encode_ref_dataset(_small_dataset(shipped_pattern))
    path = tmp_path / "cut.bin"
    # In the magic, the image size, a name's length, a name, a feature record, the geometry.
    for cut in (4, 20, 32, 36, 45, len(data) - 7):
        path.write_bytes(data[:cut])
        with pytest.raises(RefFormatError, match=rf"cut\.bin: truncated at byte {cut}"):
            read_ref_dataset(path)


def test_malformed_files(shipped_pattern: StarPattern, tmp_path: Path) -> None:
    data = encode_ref_dataset(_small_dataset(shipped_pattern))
    path = tmp_path / "bad.bin"
    path.write_bytes(b"calib_init" + data[10:])
    with pytest.raises(RefFormatError, match=r"bad\.bin: bad magic"):
        read_ref_dataset(path)
    path.write_bytes(data[:10] + b"\x00\x00\x00\x01" + data[14:])
    with pytest.raises(RefFormatError, match="unsupported format version 1"):
        read_ref_dataset(path)
    path.write_bytes(data[:14] + b"\x00\x00\x00\x02" + data[18:])
    with pytest.raises(RefFormatError, match="has 2 cameras"):
        read_ref_dataset(path)
    path.write_bytes(data + b"\x00\x00")
    with pytest.raises(RefFormatError, match=rf"2 unexpected bytes after .* byte {len(data)}"):
        read_ref_dataset(path)
    path.write_bytes(b"")
    with pytest.raises(RefFormatError, match=r"bad\.bin: empty file"):
        read_ref_dataset(path)
    with pytest.raises(RefFormatError, match=r"missing\.bin: no such file"):
        read_ref_dataset(tmp_path / "missing.bin")
