"""A feature file's rows are checked when it is read, before any calibration: each problem is one
line naming the file and the row (``features.csv``, rows from 1 after the header) or the image
(``.bin``). Before, a NaN position ran the whole calibration and failed writing ``features.bin``,
an id of 10^30 or a 200 kB field escaped as a traceback, and repeated rows were named by a later
stage."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from blurcalib.io import feature_input
from blurcalib.io.feature_input import FeatureInputError, read_feature_input
from blurcalib.io.refformat import RefDataset, encode_ref_dataset, to_ref_dataset
from blurcalib.io.results import FEATURE_COLUMNS, FeatureFlags, FeatureTable, write_features
from blurcalib.target.pattern import layout_pattern

ROOT = Path(__file__).resolve().parents[2]
PATTERN = layout_pattern()
SHARP = int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME)
BLURRY = int(FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME)


def _table(frames: int = 2, per_frame: int = 12, flags: int = SHARP) -> FeatureTable:
    """``frames`` frames of ``per_frame`` features each, on a grid inside a 1280 x 720 image."""
    ids = np.tile(np.arange(per_frame), frames)
    fx, fy = PATTERN.features[ids].T
    L = PATTERN.square_length_m
    return FeatureTable(np.repeat([f"f{k}.png" for k in range(frames)], per_frame), ids, fx, fy, fx * L,
                        fy * L, 100.0 + 30 * fx, 100.0 + 30 * fy, np.ones(len(ids)), np.full(len(ids), flags))


def _csv(tmp_path: Path, **field: str) -> Path:
    """A features.csv whose first row has the given fields' text."""
    path = write_features(tmp_path / "features.csv", _table())
    lines = path.read_text().splitlines()
    row = lines[1].split(",")
    for name, value in field.items():
        row[FEATURE_COLUMNS.index(name)] = value
    lines[1] = ",".join(row)
    path.write_text("\n".join(lines) + "\n")
    return path


def _read(path: Path, size: tuple[int, int] | None = (1280, 720)) -> str:
    with pytest.raises(FeatureInputError) as info:
        read_feature_input(path, PATTERN, size)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message and len(message) < 300, message
    return message


def test_a_clean_file_reads(tmp_path: Path) -> None:
    path = write_features(tmp_path / "features.csv", _table())
    table, size = read_feature_input(path, PATTERN, (1280, 720))
    assert len(table) == 24 and size == (1280, 720) and np.array_equal(table.x, _table().x)


@pytest.mark.parametrize(("field", "needle"), [
    ({"x": "nan"}, "row 1: x is nan; positions must be finite numbers"),
    ({"y": "inf"}, "row 1: y is inf; positions must be finite numbers"),
    ({"X": "-inf"}, "row 1: X is -inf"),
    ({"feature_id": "1" + "0" * 30},
     "column 'feature_id', row 1: cannot parse '1000000000000000000000000000000' as a 64-bit integer"),
    ({"flags": "1" + "0" * 30}, "column 'flags', row 1: cannot parse"),
    ({"x": "abc"}, "column 'x', row 1: cannot parse 'abc' as a float"),
    ({"frame": "a" * 200_000}, "row 1: a field longer than the 131072 characters a CSV field may have"),
    ({"feature_id": "-1"}, "row 1: feature id -1 is not one of the pattern's ids 0 to 342"),
    ({"feature_id": "343"}, "row 1: feature id 343 is not one of the pattern's ids 0 to 342"),
    ({"fx": "7"}, "row 1: feature 0 is at feature coordinates (0, 0) in the pattern, the file says (7, 0)"),
    ({"weight": "1e300"}, "row 1: weight 1e+300 is outside 0 to 1e+06 (a relative confidence, 1 nominal)"),
    ({"weight": "-1"}, "row 1: weight -1 is outside 0 to 1e+06"),
    ({"weight": "nan"}, "row 1: weight nan is outside"),
    ({"x": "1e300"}, "features span x 100.0 to 1e+300 px, y 100.0 to 100.0 px, outside the 1280 x 720 image"),
])
def test_bad_values_name_the_row(tmp_path: Path, field: dict[str, str], needle: str) -> None:
    assert needle in _read(_csv(tmp_path, **field))


def test_a_repeated_row_names_both_rows(tmp_path: Path) -> None:
    path = write_features(tmp_path / "features.csv", _table())
    lines = path.read_text().splitlines()
    path.write_text("\n".join([*lines[:4], lines[2], *lines[4:]]) + "\n")
    assert "row 4 repeats row 2: feature 1 observed twice in frame 'f0.png'" in _read(path)


def test_a_byte_order_mark_is_read(tmp_path: Path) -> None:
    path = write_features(tmp_path / "features.csv", _table())
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    table, size = read_feature_input(path, PATTERN, (1280, 720))
    assert len(table) == 24 and size == (1280, 720)


@pytest.mark.parametrize(("flags", "needle"), [
    (BLURRY, "every row is flagged BLURRY_FRAME (4): the parametric camera is calibrated on sharp frames"),
    (SHARP | int(FeatureFlags.FILTERED_OUT), "no features to calibrate from"),
])
def test_no_sharp_frame_or_no_feature_is_named(tmp_path: Path, flags: int, needle: str) -> None:
    path = write_features(tmp_path / "features.csv", _table(flags=flags))
    assert needle in _read(path)


@pytest.mark.parametrize(("size", "needle"), [
    ((2**32 - 1, 2**32 - 1), "the image size 4294967295x4294967295 px (18446744065119.6 MP), more than the "
                             "50 MP a frame may have"),
    ((10, 10), "the image size 10x10 px, smaller than the 32x32 px a frame needs"),
])
def test_an_impossible_image_size_is_named(tmp_path: Path, size: tuple[int, int], needle: str) -> None:
    path = tmp_path / "features.bin"
    t = _table()
    ds = to_ref_dataset((1280, 720), ["f0.png", "f1.png"], (t.frame == "f1.png").astype(int), t.feature_id,
                        t.x, t.y, PATTERN)
    ds.image_size = size
    path.write_bytes(encode_ref_dataset(ds))
    assert needle in _read(path, None)


def _bin(tmp_path: Path, change) -> Path:
    t = _table()
    ds = to_ref_dataset((1280, 720), ["f0.png", "f1.png"], (t.frame == "f1.png").astype(int), t.feature_id,
                        t.x, t.y, PATTERN)
    change(ds)
    path = tmp_path / "features.bin"
    path.write_bytes(encode_ref_dataset(ds))
    return path


def _rename(ds: RefDataset) -> None:
    ds.images[1].name = "f0.png"


def _repeat(ds: RefDataset) -> None:
    ds.images[1].features[3] = ds.images[1].features[0]


def _unknown(ds: RefDataset) -> None:
    ds.images[0].features[2] = 10**6


@pytest.mark.parametrize(("change", "needle"), [
    (_rename, "images 0 and 1 are both named 'f0.png': each image of a dataset needs a name of its own"),
    (_repeat, "image 'f1.png' record 3 repeats image 'f1.png' record 0: feature 0 observed twice"),
    (_unknown, "feature 1000000 of image 'f0.png' is not in the dataset's geometry (which lists 343 "
               "feature ids)"),
])
def test_reference_dataset_errors_name_the_image(tmp_path: Path, change, needle: str) -> None:
    assert needle in _read(_bin(tmp_path, change), None)


def test_a_nan_position_in_a_reference_dataset_names_the_image(tmp_path: Path) -> None:
    path = _bin(tmp_path, lambda ds: None)
    data = bytearray(path.read_bytes())
    name = data.index(b"f1.png")
    data[name + 6 + 4 + 12:name + 6 + 4 + 16] = np.array([np.nan], "<f4").tobytes()  # f1's record 1, x
    path.write_bytes(bytes(data))
    assert "image 'f1.png' record 1: x is nan; positions must be finite numbers" in _read(path, None)


def test_too_many_frames_are_refused_and_the_useless_ones_counted(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(feature_input, "MAX_FRAMES", 30)
    table = FeatureTable.concat([_table(2), _table(40, 1)])
    table.frame[24:] = [f"one{k}.png" for k in range(40)]
    path = write_features(tmp_path / "features.csv", table)
    assert ("42 frames, more than the 30 a calibration takes; 40 of them have fewer than 6 features, which "
            "no calibration can use: select the frames to calibrate from") in _read(path)


def test_rows_whose_names_fill_memory_are_refused_while_read(tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(feature_input, "MAX_TABLE_BYTES", 100_000)
    table = _table()
    table = FeatureTable(np.array([n + "x" * 2000 for n in table.frame.tolist()]), *(
        getattr(table, c) for c in FEATURE_COLUMNS[1:]))
    path = write_features(tmp_path / "features.csv", table)
    assert ("too large: its first 24 rows (frame names of up to 2006 characters) take 194.3 kB in memory, "
            "more than the 100.0 kB a features file may fill") in _read(path)


@pytest.mark.slow
def test_a_million_one_feature_frames_are_refused_in_bounded_memory(tmp_path: Path) -> None:
    """The calibration ran 516 s to a 4.2 GB peak and a 339 MB report.json; now the file is refused
    while it is read, under a 1.5 GB address-space limit."""
    path = tmp_path / "features.csv"
    with open(path, "w") as handle:
        handle.write(",".join(FEATURE_COLUMNS) + "\n")
        handle.writelines(f"f/{k:07d}.png,0,0,0,0.0,0.0,100.5,{100 + k % 500}.25,1.0,{SHARP}\n"
                          for k in range(1_000_000))
    script = textwrap.dedent(f"""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (1_500_000_000, 1_500_000_000))
        from blurcalib.io.feature_input import FeatureInputError, read_feature_input
        from blurcalib.target.pattern import layout_pattern
        try:
            read_feature_input({str(path)!r}, layout_pattern(), (1280, 720))
        except FeatureInputError as exc:
            print(exc)
    """)
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == (f"{path}: 1000000 frames, more than the 10000 a calibration takes; "
                                   f"1000000 of them have fewer than 6 features, which no calibration can "
                                   f"use: select the frames to calibrate from")
