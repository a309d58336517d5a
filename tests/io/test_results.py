"""Results data model: on-disk round-trips, atomicity, validation, PSF moment figures."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from blurcalib.io.frame_files import (
    collect_results,
    frame_result_paths,
    frame_stem,
    read_frame_status,
    write_frame_results,
)
from blurcalib.io.record import FrameRecord, FrameStatus
from blurcalib.io.results import (
    BlockStatus,
    BlockTable,
    FeatureFlags,
    FeatureObservation,
    FeatureTable,
    ResultsFileError,
    read_block_table,
    read_feature_table,
    read_features,
    write_results,
)
from blurcalib.psf.kernel import boundary_energy, psf_moments

AWKWARD_FLOATS = [0.1, 1 / 3, -0.0, 1e-300, 5e-324, 1.7976931348623157e308, math.pi * 1e7, -2.5e-17]


def _features(frame: str, n: int, seed: int) -> list[FeatureObservation]:
    rng = np.random.default_rng(seed)
    flags = FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME | FeatureFlags.LOCALLY_ALIGNED
    return [FeatureObservation(frame, int(i), int(i % 7), int(i // 7), float(rng.random()) * 0.3,
                               AWKWARD_FLOATS[i % len(AWKWARD_FLOATS)], float(rng.random()) * 4000,
                               float(rng.random()) * 3000, float(rng.random()), int(flags))
            for i in range(n)]


def _blocks(frame: str, n: int, seed: int, k: int = 7) -> BlockTable:
    rng = np.random.default_rng(seed)
    statuses = list(BlockStatus)
    psf = rng.random((n, k, k)).astype(np.float32)
    psf /= psf.sum(axis=(1, 2), keepdims=True)
    m = psf_moments(psf)
    H = rng.normal(size=(n, 3, 3))
    H[:, 0, 0] = [AWKWARD_FLOATS[i % len(AWKWARD_FLOATS)] for i in range(n)]
    i = np.arange(n)
    return BlockTable([frame] * n, i, i % 5, i // 5, [statuses[j % len(statuses)] for j in i],
                      rng.random(n) * 50, boundary_energy(psf), m.sigma_major, m.sigma_minor, m.eccentricity,
                      m.orientation, m.centroid, H, rng.normal(size=(n, 6)), psf)


def _assert_blocks_equal(a: BlockTable, b: BlockTable) -> None:
    assert len(a) == len(b)
    for name in BlockTable._FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), name  # bit-exact


def test_round_trip_exact(tmp_path: Path) -> None:
    features = _features("cam0/img 001,a.png", 40, 0) + _features('img"2".png', 5, 1)
    blocks = _blocks("cam0/img 001,a.png", 12, 2)
    paths = write_results(tmp_path / "out", features, blocks)
    assert set(paths) == {"features", "blocks", "psfs"}
    assert paths["features"].read_text().splitlines()[0] == "frame,feature_id,fx,fy,X,Y,x,y,weight,flags"
    back = read_features(paths["features"])
    assert back == features
    assert all(math.copysign(1, a.Y) == math.copysign(1, b.Y) for a, b in zip(back, features, strict=True))
    _assert_blocks_equal(read_block_table(tmp_path / "out"), blocks)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["blocks.csv", "features.csv", "psfs.npz"]


def test_empty_round_trip(tmp_path: Path) -> None:
    write_results(tmp_path, [], BlockTable.empty())
    assert read_features(tmp_path / "features.csv") == []
    assert len(read_block_table(tmp_path)) == 0


@pytest.mark.slow
def test_large_tables_round_trip(tmp_path: Path) -> None:
    n = 100_000
    rng = np.random.default_rng(3)
    table = FeatureTable(np.array([f"frame_{i // 500:04d}.png" for i in range(n)]), np.arange(n) % 300,
                         rng.integers(0, 16, n), rng.integers(0, 23, n), rng.random(n), rng.random(n),
                         rng.random(n) * 4000, rng.random(n) * 3000, rng.random(n), rng.integers(0, 64, n))
    write_results(tmp_path, table, BlockTable.empty(7))
    back = read_feature_table(tmp_path / "features.csv")
    for name in ("frame", "feature_id", "fx", "fy", "X", "Y", "x", "y", "weight", "flags"):
        assert np.array_equal(getattr(back, name), getattr(table, name)), name
    small = table.select(np.arange(50))
    observations = small.to_observations()
    assert FeatureTable.from_observations(observations).to_observations() == observations
    blocks = _blocks("f", 6, 4)
    _assert_blocks_equal(BlockTable.concat([blocks.select(np.arange(2)), blocks.select(np.arange(2, 6))]),
                         blocks)
    assert read_block_table(tmp_path).psf.shape == (0, 7, 7)


def test_atomic_writes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write_results(tmp_path, _features("a", 3, 0), _blocks("a", 2, 0))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    bad = [*_features("b", 2, 1), FeatureObservation("b", 9, 0, 0, 0.0, 0.0, "12px", 0.0, 1.0, 0)]
    with pytest.raises(ValueError, match="12px"):  # invalid input: nothing is written
        write_results(tmp_path, bad, _blocks("b", 1, 0))
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before

    def failing_savez(handle, **arrays) -> None:
        handle.write(b"partial npz")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", failing_savez)
    with pytest.raises(OSError, match="disk full"):
        write_results(tmp_path, _features("b", 3, 1), _blocks("b", 2, 1))
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert set(after) == set(before)  # no temporary file left behind
    assert after["psfs.npz"] == before["psfs.npz"]  # the failed write left the old file intact
    assert read_features(tmp_path / "features.csv") == _features("b", 3, 1)  # written whole before


def test_corrupt_files_raise(tmp_path: Path) -> None:
    write_results(tmp_path, _features("a", 4, 0), _blocks("a", 3, 0))
    path = tmp_path / "features.csv"
    lines = path.read_text().splitlines()
    fields = lines[2].split(",")
    fields[6] = "12.5px"
    path.write_text("\n".join([*lines[:2], ",".join(fields), *lines[3:]]) + "\n")
    with pytest.raises(ResultsFileError, match=r"features\.csv: column 'x', row 2: cannot parse '12\.5px'"):
        read_features(path)
    path.write_text(lines[0].replace(",weight", "") + "\n")
    with pytest.raises(ResultsFileError, match=r"features\.csv: missing column\(s\) 'weight'"):
        read_features(path)
    with pytest.raises(ResultsFileError, match=r"nope\.csv: results file not found"):
        read_features(tmp_path / "nope.csv")
    blocks = tmp_path / "blocks.csv"
    blocks.write_text(blocks.read_text().replace(",accepted,", ",acceptd,"))
    with pytest.raises(ResultsFileError, match=r"blocks\.csv: column 'status', row 1: 'acceptd'"):
        read_block_table(tmp_path)
    (tmp_path / "psfs.npz").unlink()
    with pytest.raises(ResultsFileError, match=r"psfs\.npz: results file not found"):
        read_block_table(tmp_path)


def _write_frame(folder: Path, name: str, n: int, seed: int, blocks: int = 2) -> Path:
    corners = [[name, 1, 3, 0.005, 0.015, 10.5, 20.25, 2]]
    record = FrameRecord(name, FrameStatus.OK, key=f"key-{seed}")
    return write_frame_results(folder, name, _features(name, n, seed), _blocks(name, blocks, seed),
                               corners, record)


def test_per_frame_results_resume_and_collect(tmp_path: Path) -> None:
    _write_frame(tmp_path, "seq/b.png", 4, 1)
    paths = _write_frame(tmp_path, "a.png", 3, 0)
    assert paths.features == tmp_path / "frames" / "a.png.features.csv"
    assert paths.status == tmp_path / "frames" / "a.png.status.json"
    assert read_frame_status(tmp_path, "a.png").key == "key-0"
    # an interrupted frame (no marker) is not finished; its status is not trusted
    interrupted = _write_frame(tmp_path, "c.png", 2, 2, blocks=0)
    interrupted.done.unlink()
    assert read_frame_status(tmp_path, "c.png") is None
    with pytest.raises(ResultsFileError, match=r"frame 'c\.png' has no finished"):
        collect_results(tmp_path, ["a.png", "c.png"])
    with pytest.raises(ValueError, match=r"frame 'a\.png' passed for frame 'c\.png'"):
        write_frame_results(tmp_path, "c.png", _features("a.png", 1, 0), BlockTable.empty(), [],
                            FrameRecord("c.png"))
    with pytest.raises(ValueError, match=r"status row of frame 'a\.png' passed for frame 'c\.png'"):
        write_frame_results(tmp_path, "c.png", [], BlockTable.empty(), [], FrameRecord("a.png"))
    # exactly the frames asked for are collected, in the order asked
    outputs = collect_results(tmp_path, ["a.png", "seq/b.png"])
    assert read_features(tmp_path / "features.csv") == _features("a.png", 3, 0) + _features("seq/b.png", 4, 1)
    _assert_blocks_equal(read_block_table(tmp_path),
                         BlockTable.concat([_blocks("a.png", 2, 0), _blocks("seq/b.png", 2, 1)]))
    assert outputs["corners"].read_text().splitlines() == [
        "frame,cx2,cy2,X,Y,x,y,blocks", "a.png,1,3,0.005,0.015,10.5,20.25,2",
        "seq/b.png,1,3,0.005,0.015,10.5,20.25,2"]
    collect_results(tmp_path, ["seq/b.png"])
    assert {f.frame for f in read_features(tmp_path / "features.csv")} == {"seq/b.png"}


@pytest.mark.parametrize(("a", "b"), [("0.png", "0.jpg"), ("a b.png", "a_b.png"),
                                      ("seq/b.png", "seq__b.png"), ("A.png", "a.png"),
                                      ("x" * 150 + "1.png", "x" * 150 + "2.png"),
                                      (".a.png", "_a.png"), ("a\\b.png", "a/b.png")])
def test_frame_stems_are_unique_per_frame_name(tmp_path: Path, a: str, b: str) -> None:
    sa, sb = frame_stem(a), frame_stem(b)
    assert sa.lower() != sb.lower()  # distinct even on a case-insensitive file system
    assert len(sa) <= 113 and not sa.startswith(".") and "/" not in sa
    assert frame_stem(a) == sa  # stable
    pa, pb = frame_result_paths(tmp_path, a), frame_result_paths(tmp_path, b)
    assert len({*vars(pa).values(), *vars(pb).values()}) == 12  # twelve different files
    # both frames' results survive side by side
    _write_frame(tmp_path, a, 3, 0)
    _write_frame(tmp_path, b, 2, 1)
    collect_results(tmp_path, [a, b])
    assert [f.frame for f in read_features(tmp_path / "features.csv")] == [a] * 3 + [b] * 2
    assert read_frame_status(tmp_path, a).key == "key-0"
    assert read_frame_status(tmp_path, b).key == "key-1"


def test_frame_stem_keeps_plain_names() -> None:
    assert frame_stem("img_001.png") == "img_001.png"
    assert frame_stem("seq/img 1.png").startswith("seq__img_1.png~")


def _gaussian(k: int, sx: float, sy: float, angle: float, shift: tuple[float, float] = (0, 0)) -> np.ndarray:
    c = (k - 1) / 2
    y, x = np.mgrid[0:k, 0:k] - c
    x, y = x - shift[0], y - shift[1]
    ca, sa = math.cos(angle), math.sin(angle)
    u, v = ca * x + sa * y, -sa * x + ca * y
    g = np.exp(-0.5 * ((u / sx) ** 2 + (v / sy) ** 2))
    return (g / g.sum()).astype(np.float32)


def test_psf_moments_gaussian_line_delta() -> None:
    m = psf_moments(_gaussian(41, 3.0, 1.0, math.radians(30)))
    assert m.sigma_major == pytest.approx(3.0, rel=0.01)
    assert m.sigma_minor == pytest.approx(1.0, rel=0.01)
    assert math.degrees(m.orientation) == pytest.approx(30.0, rel=0.01)
    assert m.eccentricity == pytest.approx(math.sqrt(1 - 1 / 9), rel=0.01)
    assert np.allclose(m.centroid, 0, atol=1e-5)

    line = np.zeros((15, 15), np.float32)
    line[7, 3:12] = 1 / 9
    m = psf_moments(line)
    assert m.sigma_major == pytest.approx(math.sqrt((9**2 - 1) / 12), rel=1e-6)  # discrete 9-px line
    assert m.sigma_major == pytest.approx(9 / math.sqrt(12), rel=0.01)
    assert (m.sigma_minor, m.eccentricity, m.orientation) == (0.0, 1.0, 0.0)
    m = psf_moments(line.T)
    assert m.orientation == pytest.approx(math.pi / 2)

    delta = np.zeros((9, 9), np.float32)
    delta[2, 6] = 1.0  # row 2, column 6: offset (+2, -2) px
    m = psf_moments(delta)
    assert np.array_equal(m.centroid, [2.0, -2.0])
    assert (m.sigma_major, m.sigma_minor, m.eccentricity) == (0.0, 0.0, 0.0)

    batch = np.stack([_gaussian(41, 3.0, 1.0, math.radians(30)), _gaussian(41, 2.0, 2.0, 0.0, (1.5, -0.5))])
    mb = psf_moments(batch)
    assert mb.centroid.shape == (2, 2) and mb.sigma_major.shape == (2,)
    assert mb.sigma_major[0] == pytest.approx(3.0, rel=0.01)
    assert np.allclose(mb.centroid[1], [1.5, -0.5], atol=1e-4)


def test_boundary_energy() -> None:
    delta = np.zeros((11, 11), np.float32)
    delta[5, 5] = 1
    assert boundary_energy(delta) == 0.0
    uniform = np.full((11, 11), 1 / 121, np.float32)
    assert boundary_energy(uniform) == pytest.approx((121 - 49) / 121)
    assert boundary_energy(uniform, ring=1) == pytest.approx((121 - 81) / 121)
    assert np.allclose(boundary_energy(np.stack([delta, uniform])), [0.0, 72 / 121])


def test_blur_per_square_is_the_blur_extent_over_the_square_side() -> None:
    """A straight 20 px blur (sigma_major 20 / sqrt(12)) on squares 25 px wide: 0.8."""
    from blurcalib.growth.seed import block_homography

    H_feature = np.array([[25.0, 0.0, 100.0], [0.0, 25.0, 80.0], [0.0, 0.0, 1.0]])
    table = _blocks("f", 3, 0)
    table.H = block_homography(H_feature, np.array([1.0, 2.0, 3.0]), np.array([1.0, 1.0, 1.0]))
    table.sigma_major = np.array([20.0, 10.0, np.nan]) / math.sqrt(12.0)
    np.testing.assert_allclose(table.blur_per_square[:2], [0.8, 0.4], rtol=1e-12)
    assert np.isnan(table.blur_per_square[2])


def test_loss_extent_and_noise_round_trip_and_read_as_defaults_from_older_files(tmp_path: Path) -> None:
    """``blocks.csv`` carries each block's loss extent (the growth's final fit uses 1.5) and noise
    variance; a file written before the columns existed reads with 1 and NaN everywhere."""
    blocks = _blocks("a.png", 6, 4)
    blocks.loss_extent = np.array([1.0, 1.5, 1.5, 1.0, 1.25, 1.0])
    blocks.noise_var = np.array([4.0, 4.5, np.nan, 12.25, 3.0, 3.5])
    write_results(tmp_path / "new", [], blocks)
    _assert_blocks_equal(read_block_table(tmp_path / "new"), blocks)
    picked = read_block_table(tmp_path / "new").select(np.array([1, 4]))
    assert picked.loss_extent.tolist() == [1.5, 1.25] and picked.noise_var.tolist() == [4.5, 3.0]
    old = tmp_path / "old"
    write_results(old, [], blocks)
    lines = (old / "blocks.csv").read_text().splitlines()
    assert lines[0].endswith(",loss_extent,noise_var")
    (old / "blocks.csv").write_text("\n".join(line.rsplit(",", 2)[0] for line in lines) + "\n")
    assert read_block_table(old).loss_extent.tolist() == [1.0] * 6
    assert np.isnan(read_block_table(old).noise_var).all()
