"""Hostile and accidental input: every case is generated here, small, and must end in a one-line
message (exit status 2 from the command line), a per-frame status, or a bounded refusal before any
large allocation; never a traceback, a hang or a silently wrong camera."""

from __future__ import annotations

import dataclasses
import errno
import json
import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from blurcalib.camera.generic import MAX_GRID_NODES, check_grid_size
from blurcalib.cli import build_parser, main
from blurcalib.cli.calibrate import pipeline_settings
from blurcalib.extract.duplicates import find_duplicates, mark_duplicates
from blurcalib.io import atomic
from blurcalib.io.atomic import (
    OutputError,
    atomic_write_json,
    atomic_write_text,
    claim_output_dir,
    output_lock,
)
from blurcalib.io.frame_files import read_frame_status, write_frame_results
from blurcalib.io.frames import FrameError, frame_size, list_frames, load_frame
from blurcalib.io.record import FrameRecord, FrameStatus
from blurcalib.io.results import BlockTable, FeatureTable
from blurcalib.runs.cluster import ClusterError, check_address, run_on_cluster
from blurcalib.runs.runtime import available_cores, capped_count
from blurcalib.target.pattern import MAX_STAR_SEGMENTS, PatternFileError, load_pattern
from tests.conftest import FIXTURE_YAML

ROOT = Path(__file__).resolve().parents[1]


def _png(path: Path, width: int = 64, height: int = 64, value: int = 128) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, data = cv2.imencode(".png", np.full((height, width), value, np.uint8))
    assert ok
    path.write_bytes(data.tobytes())  # cv2.imwrite cannot take a name that is not UTF-8
    return path


def _run(capsys: pytest.CaptureFixture, argv: list[str]) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


# ----------------------------------------------------------------------------- pattern YAMLs
def _pattern_with(tmp_path: Path, name: str, prefix: str, field: str, value: str) -> Path:
    text = FIXTURE_YAML.read_text()
    line = next(x for x in text.splitlines() if x.startswith(f"{field}:"))
    path = tmp_path / name
    path.write_text(prefix + text.replace(line, f"{field}: {value}"))
    return path


def test_alias_bomb_is_refused_in_one_short_line(tmp_path: Path) -> None:
    """1 kB of YAML aliases expanding to 10^9 leaves: the message names the field and the value's
    shape, never its repr (2.5 GB and a MemoryError before)."""
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 10)]
    bomb = _pattern_with(tmp_path, "bomb.yaml", "\n".join(lines) + "\n", "num_star_segments", "*a9")
    assert bomb.stat().st_size < 1200
    with pytest.raises(PatternFileError) as info:
        load_pattern(bomb)
    message = str(info.value)
    assert "field 'num_star_segments' must be int, got a list of 9 item(s)" in message
    assert len(message) < 200 + len(str(bomb))


def test_alias_bomb_upload_gives_a_notice_in_the_app(tmp_path: Path) -> None:
    from state import AppState

    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 10)]
    bomb = _pattern_with(tmp_path, "bomb.yaml", "\n".join(lines) + "\n", "squares_x", "*a9")
    state = AppState()
    assert not state.set_pattern(bomb)
    notice = state.notices[-1]
    assert notice.level == "error" and notice.title == "Pattern refused" and "squares_x" in notice.text
    deep = tmp_path / "deep.yaml"
    deep.write_text("a: " + "[" * 20000 + "]" * 20000 + "\n")
    assert not state.set_pattern(deep)
    assert state.notices[-1].title == "Pattern refused" and "nested more than 16" in state.notices[-1].text


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("a: " + "[" * 20000 + "]" * 20000 + "\n", "nested more than 16 levels deep at line 1"),
        ("a:\n" + "".join("  " * i + f"k{i}:\n" for i in range(1, 40)), "nested more than 16 levels deep"),
        ("num_star_segments: " + "9" * 5000 + "\n", "unreadable value"),
        ("# padding\n" * 200_000, "more than 1048576 bytes"),
    ],
)
def test_deep_huge_and_oversized_yaml_refused(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "p.yaml"
    path.write_text(text)
    with pytest.raises(PatternFileError, match=needle):
        load_pattern(path)


@pytest.mark.parametrize("segments", ["400000000", str(MAX_STAR_SEGMENTS + 4)])
def test_star_segment_count_is_bounded(tmp_path: Path, segments: str) -> None:
    path = _pattern_with(tmp_path, "p.yaml", "", "num_star_segments", segments)
    with pytest.raises(
        PatternFileError, match=rf"multiple of 4 from 4 to {MAX_STAR_SEGMENTS}, got {segments}"
    ):
        load_pattern(path)


# ----------------------------------------------------------------------------- frame files
def _tiff_header(width: int, height: int, order: str = "<", big: bool = False) -> bytes:
    """A TIFF (or BigTIFF) of one strip whose directory claims ``width x height`` RGBA 16-bit
    pixels, deflate-compressed; the strip itself is a few bytes."""
    mark = b"II" if order == "<" else b"MM"
    entries = [
        (256, 4, width),
        (257, 4, height),
        (258, 3, 16),
        (259, 3, 8),
        (262, 3, 2),
        (277, 3, 4),
        (278, 4, height),
        (279, 4, 16),
        (273, 4, 0),
    ]
    if big:
        head = mark + struct.pack(order + "HHHQ", 43, 8, 0, 16)
        ifd_at = 16
        size = 8 + len(entries) * 20 + 8
        strip = ifd_at + size
        body = struct.pack(order + "Q", len(entries))
        for tag, kind, value in entries:
            value = strip if tag == 273 else value
            body += struct.pack(order + "HHQ", tag, kind, 1) + struct.pack(
                order + ("H6x" if kind == 3 else "I4x"), value
            )
        body += struct.pack(order + "Q", 0)
    else:
        head = mark + struct.pack(order + "HI", 42, 8)
        ifd_at = 8
        size = 2 + len(entries) * 12 + 4
        strip = ifd_at + size
        body = struct.pack(order + "H", len(entries))
        for tag, kind, value in entries:
            value = strip if tag == 273 else value
            body += struct.pack(order + "HHI", tag, kind, 1) + struct.pack(
                order + ("H2x" if kind == 3 else "I"), value
            )
        body += struct.pack(order + "I", 0)
    return head + body + bytes(16)


@pytest.mark.parametrize(("order", "big"), [("<", False), (">", False), ("<", True)])
def test_tiff_bomb_refused_from_its_header_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, order: str, big: bool
) -> None:
    """A 16000 x 16000 RGBA 16-bit TIFF (2 GB decoded, 4.4 GB peak before): the size comes from
    the directory, and the decoder is never called."""
    path = tmp_path / "bomb.tif"
    path.write_bytes(_tiff_header(16000, 16000, order, big))
    assert frame_size(path) == (16000, 16000)

    def no_decode(*args: object) -> None:
        raise AssertionError("decoded a frame whose header is over the limit")

    monkeypatch.setattr(cv2, "imdecode", no_decode)
    with pytest.raises(FrameError, match=r"bomb\.tif: is 16000x16000 px \(256\.0 MP\), more than the 50 MP"):
        load_frame(path)


def test_bmp_bomb_and_unknown_formats_refused_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bmp = tmp_path / "bomb.bmp"
    bmp.write_bytes(b"BM" + bytes(12) + struct.pack("<Iii", 40, 20000, -20000) + bytes(64))
    webp = tmp_path / "disguised.png"
    webp.write_bytes(b"RIFF\x00\x00\x00\x00WEBPVP8 " + bytes(64))
    monkeypatch.setattr(cv2, "imdecode", lambda *a: pytest.fail("decoded"))
    assert frame_size(bmp) == (20000, 20000) and frame_size(webp) is None
    with pytest.raises(FrameError, match="is 20000x20000 px"):
        load_frame(bmp)
    with pytest.raises(FrameError, match="not a PNG, JPEG, TIFF or BMP file"):
        load_frame(webp)


def test_tiff_size_from_a_directory_after_the_pixels(tmp_path: Path) -> None:
    """libtiff writes the directory after the image data: the header is read where it lies."""
    image = np.random.default_rng(0).integers(0, 256, (900, 1100), dtype=np.uint8)
    path = tmp_path / "big.tif"
    assert cv2.imwrite(str(path), image)
    assert frame_size(path) == (1100, 900) and load_frame(path).shape == (900, 1100)


def _jpeg(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    return data.tobytes()


def test_corrupted_jpeg_is_unreadable_and_padded_jpeg_is_kept(tmp_path: Path) -> None:
    """2,000 damaged bytes in the scan: the decoder warns and invents pixels; the frame is marked
    (it came out ok, 0.23 px off, before). Padding before the end marker is harmless."""
    rng = np.random.default_rng(1)
    image = cv2.GaussianBlur(rng.integers(0, 256, (240, 320), dtype=np.uint8), (0, 0), 2)
    data = bytearray(_jpeg(image))
    scan = data.find(b"\xff\xda") + 20
    for j in rng.integers(scan, len(data) - 4, 2000):
        data[j] = int(rng.integers(0, 255))
    (tmp_path / "damaged.jpg").write_bytes(bytes(data))
    with pytest.raises(
        FrameError, match=r"damaged\.jpg: corrupt image data \(the decoder says: Corrupt JPEG"
    ):
        load_frame(tmp_path / "damaged.jpg")
    clean = _jpeg(image)
    (tmp_path / "padded.jpg").write_bytes(clean[:-2] + b"\x00\x00" + clean[-2:])
    assert np.array_equal(load_frame(tmp_path / "padded.jpg"), load_frame_bytes(tmp_path, clean))


def load_frame_bytes(tmp_path: Path, data: bytes) -> np.ndarray:
    path = tmp_path / "clean.jpg"
    path.write_bytes(data)
    return load_frame(path)


def test_broken_links_loops_and_non_utf8_names_get_rows(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """Broken symbolic links and link loops get an unreadable row (they vanished before); a name
    that is not UTF-8 is processed and written escaped (the batch stopped on every re-run before)."""
    frames = tmp_path / "f"
    _png(frames / "ok.png")
    _png(Path(os.fsdecode(bytes(frames) + b"/caf\xe9.png")))
    (frames / "broken.png").symlink_to("nowhere.png")
    (frames / "loop1.png").symlink_to("loop2.png")
    (frames / "loop2.png").symlink_to("loop1.png")
    assert len(list_frames([frames])) == 5
    for _ in range(2):  # the re-run too
        code, _err = _run(
            capsys, ["extract", frames, "--pattern", FIXTURE_YAML, "--out", tmp_path / "o", "--workers", "1"]
        )
        assert code == 1  # no frame holds the target, and nothing stopped the batch
    rows = {r.split(",")[0]: r for r in (tmp_path / "o" / "frames.csv").read_text().splitlines()[1:]}
    assert set(rows) == {"broken.png", "caf\\xe9.png", "loop1.png", "loop2.png", "ok.png"}
    assert "unreadable" in rows["broken.png"] and "broken symbolic link (to nowhere.png" in rows["broken.png"]
    assert "Too many levels of symbolic links" in rows["loop1.png"]
    assert rows["caf\\xe9.png"].split(",")[1] == "not_seeded"


NEEDS_DEVICES = pytest.mark.skipif(
    not Path("/dev/zero").exists() or not hasattr(os, "mkfifo"), reason="needs /dev/zero and FIFOs (POSIX)"
)


@NEEDS_DEVICES
def test_devices_and_fifos_behind_frame_names_get_unreadable_rows(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``/dev/zero`` behind ``zero.png`` read 2 GB in seconds; a FIFO behind a name blocked the run."""
    frames = tmp_path / "f"
    _png(frames / "ok.png")
    (frames / "zero.png").symlink_to("/dev/zero")
    os.mkfifo(tmp_path / "pipe")
    (frames / "pipe.png").symlink_to(tmp_path / "pipe")
    code, _err = _run(capsys, ["extract", frames, "--pattern", FIXTURE_YAML, "--out", tmp_path / "o",
                               "--workers", "1"])
    assert code == 1
    rows = (tmp_path / "o" / "frames.csv").read_text().splitlines()[1:]  # named by the files they lead to
    for needle in ("zero.png: is a character device, not a regular file",
                   "pipe.png: is a FIFO (named pipe), not a regular file"):
        assert any(",unreadable," in r and needle in r for r in rows), rows


# ----------------------------------------------------------------------------- feature files and videos
def _features_csv(tmp_path: Path, first_row: dict[str, str] | None = None) -> Path:
    """A features.csv of two sharp frames of 12 features; ``first_row`` replaces fields of row 1."""
    from blurcalib.io.results import FEATURE_COLUMNS, write_features
    from blurcalib.target.pattern import layout_pattern

    pattern = layout_pattern()
    ids = np.tile(np.arange(12), 2)
    fx, fy = pattern.features[ids].T
    table = FeatureTable(np.repeat(["a.png", "b.png"], 12), ids, fx, fy, fx * 0.01, fy * 0.01,
                         100.0 + 30 * fx, 100.0 + 30 * fy, np.ones(24), np.full(24, 3))
    path = write_features(tmp_path / "features.csv", table)
    lines = path.read_text().splitlines()
    row = lines[1].split(",")
    for name, value in (first_row or {}).items():
        row[FEATURE_COLUMNS.index(name)] = value
    path.write_text("\n".join([lines[0], ",".join(row), *lines[2:]]) + "\n")
    return path


@pytest.mark.parametrize(("first_row", "needle"), [
    ({"x": "nan"}, "features.csv: row 1: x is nan; positions must be finite numbers"),
    ({"feature_id": "1" + "0" * 30}, "features.csv: column 'feature_id', row 1: cannot parse"),
    ({"flags": "1" + "0" * 30}, "features.csv: column 'flags', row 1: cannot parse"),
    ({"frame": "n" * 200_000}, "features.csv: row 1: a field longer than the 131072 characters"),
    ({"weight": "1e300"}, "features.csv: row 1: weight 1e+300 is outside 0 to 1e+06"),
    ({"feature_id": "-1"}, "features.csv: row 1: feature id -1 is not one of the pattern's ids"),
])
def test_bad_feature_rows_exit_2_before_any_calibration(
    tmp_path: Path, capsys: pytest.CaptureFixture, first_row: dict[str, str], needle: str
) -> None:
    """A NaN position ran the whole calibration, then failed writing features.bin; 10^30 and a 200 kB
    field were tracebacks; a weight of 1e300 failed after 5.6 minutes."""
    path = _features_csv(tmp_path, first_row)
    code, err = _run(capsys, ["calibrate", "--features", path, "--image-size", "1280x720", "--pattern",
                              FIXTURE_YAML, "--out", tmp_path / "out"])
    assert code == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()


@NEEDS_DEVICES
def test_feature_files_behind_devices_and_fifos_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    (tmp_path / "zero.bin").symlink_to("/dev/zero")
    os.mkfifo(tmp_path / "pipe.bin")
    for name, what in (("zero.bin", "a character device"), ("pipe.bin", "a FIFO (named pipe)")):
        code, err = _run(capsys, ["calibrate", "--features", tmp_path / name, "--pattern", FIXTURE_YAML,
                                  "--out", tmp_path / "out"])
        assert code == 2 and f"{tmp_path / name}: is {what}, not a regular file" in err
    assert not (tmp_path / "out").exists()


def test_cell_px_1_with_features_is_refused_before_the_file_is_read(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """Refused only after the 49 s parametric stage before; now from the .bin's header, before its
    rows are read (this file's rows are refused too, later)."""
    from blurcalib.io.refformat import encode_ref_dataset, to_ref_dataset
    from blurcalib.target.pattern import layout_pattern

    dataset = to_ref_dataset((1280, 720), ["a.png", "b.png"], np.array([0, 1]), np.array([0, 0]),
                             np.array([10.0, 20.0]), np.array([10.0, 20.0]), layout_pattern())
    dataset.images[1].name = "a.png"
    path = tmp_path / "features.bin"
    path.write_bytes(encode_ref_dataset(dataset))
    argv = ["calibrate", "--features", path, "--pattern", FIXTURE_YAML, "--out", tmp_path / "out"]
    code, err = _run(capsys, [*argv, "--cell-px", "1"])
    assert code == 2 and "--cell-px 1: cells of 1 px make a 1282 x 722 grid" in err
    code, err = _run(capsys, argv)
    assert code == 2 and "images 0 and 1 are both named 'a.png'" in err
    code, err = _run(capsys, ["calibrate", "--features", _features_csv(tmp_path), "--image-size", "1280x720",
                              "--pattern", FIXTURE_YAML, "--out", tmp_path / "out", "--cell-px", "1"])
    assert code == 2 and "--cell-px 1: cells of 1 px make a 1282 x 722 grid" in err
    assert not (tmp_path / "out").exists()


def test_two_videos_of_one_name_exit_2_naming_both(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``clip.mp4`` and ``clip.mkv``: a ValueError traceback in extract and calibrate before."""
    for name, fourcc in (("clip.mp4", "mp4v"), ("clip.mkv", "MJPG")):
        writer = cv2.VideoWriter(str(tmp_path / name), cv2.VideoWriter_fourcc(*fourcc), 10, (64, 48))
        for _ in range(2):
            writer.write(np.zeros((48, 64, 3), np.uint8))
        writer.release()
    for command in ("extract", "calibrate"):
        code, err = _run(capsys, [command, tmp_path / "clip.mp4", tmp_path / "clip.mkv", "--pattern",
                                  FIXTURE_YAML, "--out", tmp_path / "out"])
        assert code == 2 and (f"{tmp_path / 'clip.mp4'} and {tmp_path / 'clip.mkv'}: both give frames the "
                              f"name clip#000000") in err
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- output folders
def test_full_disk_is_one_line_and_keeps_old_files(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    old = atomic_write_text(tmp_path / "kept.txt", "old")

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic.os, "fsync", full)
    with pytest.raises(OutputError, match=r"kept\.txt: cannot write \(No space left on device\)"):
        atomic_write_text(old, "new")
    assert old.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["kept.txt"]
    _png(tmp_path / "f" / "a.png")
    code, err = _run(capsys, ["extract", tmp_path / "f", "--pattern", FIXTURE_YAML, "--out", tmp_path / "o"])
    assert code == 2 and err.startswith("blurcalib: error: ") and "No space left on device" in err
    assert len(err.strip().splitlines()) == 1


def test_second_run_into_a_locked_folder_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    _png(tmp_path / "f" / "a.png")
    out = tmp_path / "o"
    argv = ["extract", tmp_path / "f", "--pattern", FIXTURE_YAML, "--out", out, "--workers", "1"]
    with output_lock(out):
        code, err = _run(capsys, argv)
        assert code == 2 and "another blurcalib run is writing into this folder" in err
        assert list(out.iterdir()) == []  # nothing written, no lock file added
    assert _run(capsys, argv)[0] == 1 and (out / "frames.csv").is_file()
    assert not (tmp_path / "never").exists()
    with output_lock(tmp_path / "never"):
        pass
    assert not (tmp_path / "never").exists()  # a folder made for the lock and left empty is removed


def test_a_run_inside_or_around_a_locked_folder_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """An ``extract`` into ``OUT/frames`` during a ``calibrate`` into ``OUT`` was accepted and mixed
    the two runs' frames; a run into the folder around a locked one would replace its files."""
    _png(tmp_path / "f" / "a.png")
    out = tmp_path / "o"
    inside = ["extract", tmp_path / "f", "--pattern", FIXTURE_YAML, "--out", out / "frames", "--workers", "1"]
    with output_lock(out):
        code, err = _run(capsys, inside)
        assert code == 2 and f"it is inside {out.resolve()}, the output folder of another" in err
        assert len(err.strip().splitlines()) == 1 and list(out.iterdir()) == []  # OUT/frames not made
    with output_lock(out / "frames"):
        with pytest.raises(OutputError, match="into this folder or into one inside it"):
            with output_lock(out):
                pass
        with output_lock(tmp_path / "beside"):  # a folder beside it is free
            pass
    assert _run(capsys, inside)[0] == 1 and (out / "frames" / "frames.csv").is_file()


def test_a_failed_rerun_leaves_the_manifest_of_the_kept_outputs(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After a re-run with other settings failed on a full disk, the run manifest named the new
    settings while the kept outputs were made with the old ones."""
    _png(tmp_path / "f" / "a.png")
    out = tmp_path / "o"
    argv = ["extract", tmp_path / "f", "--pattern", FIXTURE_YAML, "--out", out, "--workers", "1"]
    assert _run(capsys, argv)[0] == 1
    before = json.loads((out / atomic.RUN_MANIFEST).read_text())
    tables = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}

    real, calls = os.fsync, []

    def fills_up(fd: int) -> None:  # the disk fills after the run's first file
        calls.append(fd)
        if len(calls) > 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd)

    with monkeypatch.context() as m:
        m.setattr(atomic.os, "fsync", fills_up)
        code, err = _run(capsys, [*argv, "--psf-size", "21"])
    assert code == 2 and "No space left on device" in err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == tables
    assert _run(capsys, [*argv, "--psf-size", "21"])[0] == 1
    after = json.loads((out / atomic.RUN_MANIFEST).read_text())
    # the new settings are named once the outputs made with them are published
    assert before["settings"]["window"]["start"] == 17 and after["settings"]["window"]["start"] == 21


def test_unwritable_subfolder_refused_before_the_manifest_changes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run that would fail on a read-only ``frames/`` must not first rewrite the manifest (its
    tables would then not match it). Simulated through ``os.access``: the tests may run as root."""
    out = claim_output_dir(tmp_path / "o", "extract", {"kernel": 17})
    (out / "frames").mkdir()
    before = (out / atomic.RUN_MANIFEST).read_text()
    real = os.access
    monkeypatch.setattr(atomic.os, "access", lambda p, mode: Path(p).name != "frames" and real(p, mode))
    with pytest.raises(OutputError, match=r"frames: output folder is not writable"):
        claim_output_dir(out, "extract", {"kernel": 7})
    assert (out / atomic.RUN_MANIFEST).read_text() == before


def test_extract_refuses_another_datasets_frames_of_the_same_names(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    _png(tmp_path / "a" / "0.png", value=100)
    _png(tmp_path / "b" / "0.png", value=200)
    out = tmp_path / "o"
    base = ["--pattern", FIXTURE_YAML, "--out", out, "--workers", "1"]
    assert _run(capsys, ["extract", tmp_path / "a", *base])[0] == 1
    code, err = _run(capsys, ["extract", tmp_path / "b", *base])
    assert code == 2 and f"its frame 0.png was extracted from {tmp_path / 'a' / '0.png'}" in err
    assert read_frame_status(out, "0.png").source == str(tmp_path / "a" / "0.png")
    assert _run(capsys, ["extract", tmp_path / "b", *base, "--overwrite"])[0] == 1
    assert read_frame_status(out, "0.png").source == str(tmp_path / "b" / "0.png")
    assert _run(capsys, ["extract", tmp_path / "b", *base])[0] == 1  # the same dataset resumes


def test_strict_json_for_reports_and_frame_statuses(tmp_path: Path) -> None:
    """``NaN`` is not JSON (a sharp-only run's blurry median is NaN): ``null`` is written."""

    def strict(text: str) -> object:
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))

    doc = {"median": float("nan"), "rms": [1.0, float("inf"), np.float64("nan")], "n": 3}
    assert strict(atomic_write_json(tmp_path / "r.json", doc).read_text()) == {
        "median": None,
        "rms": [1.0, None, None],
        "n": 3,
    }
    write_frame_results(
        tmp_path,
        "a.png",
        FeatureTable.empty(),
        BlockTable.empty(),
        [],
        FrameRecord("a.png", FrameStatus.OK, seconds=float("nan")),
    )
    status = next((tmp_path / "frames").glob("*.status.json"))
    assert strict(status.read_text())["seconds"] is None


# ----------------------------------------------------------------------------- command line
@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["pattern", "--out", "{tmp}/x", "--dpi", "100000"], "more than the 150 MP limit"),
        (["pattern", "--out", "{tmp}/x", "--dpi", "3000"], "24803 x 35079 px (870 MP)"),
        (["pattern", "--out", "{tmp}/x", "--dpi", "nan"], "--dpi: must be a finite number > 0, got 'nan'"),
        (
            ["pattern", "--out", "{tmp}/x", "--segments", "100000000"],
            "multiple of 4 from 4 to 128, got 100000000",
        ),
        (["pattern", "--out", "{tmp}/x", "--formats", ","], "no format to write"),
        (
            ["synth", "--out", "{tmp}/ds", "--noise", "nan"],
            "noise (noise_sigma) must be a finite number >= 0",
        ),
        (["synth", "--out", "{tmp}/ds", "--noise", "-3"], "got -3.0"),
        (["synth", "--out", "{tmp}/ds", "--blur-max", "inf"], "blur_max_px"),
        (
            ["extract", "{tmp}/f", "--pattern", str(FIXTURE_YAML), "--out", "{tmp}/ds", "--threads", "abc"],
            "--threads: must be a whole number >= 1, got 'abc'",
        ),
        (
            [
                "extract",
                "{tmp}/f",
                "--pattern",
                str(FIXTURE_YAML),
                "--out",
                "{tmp}/ds",
                "--cluster",
                "tcp://h:port",
            ],
            "not a scheduler address, the port must be a number from 1 to 65535",
        ),
        (
            [
                "extract",
                "{tmp}/f",
                "--pattern",
                str(FIXTURE_YAML),
                "--out",
                "{tmp}/ds",
                "--cluster",
                "tcp://:8786",
            ],
            "no host",
        ),
        (
            [
                "calibrate",
                "--sharp",
                "{tmp}/f",
                "--pattern",
                str(FIXTURE_YAML),
                "--out",
                "{tmp}/ds",
                "--cell-px",
                "inf",
            ],
            "--cell-px: must be a finite number > 0, got 'inf'",
        ),
        (
            [
                "calibrate",
                "--sharp",
                "{tmp}/f",
                "--pattern",
                str(FIXTURE_YAML),
                "--out",
                "{tmp}/ds",
                "--cell-px",
                "1",
            ],
            "1282 x 722 grid (925604 nodes)",
        ),
        (
            ["calibrate", "{tmp}/f", "--pattern", str(FIXTURE_YAML), "--out", "{tmp}/ds",
             "--sharp-below", "-3"],
            "--sharp-below: must be a finite number > 0, got '-3'",
        ),
        (
            ["calibrate", "{tmp}/f", "--pattern", str(FIXTURE_YAML), "--out", "{tmp}/ds", "--tau-be", "nan"],
            "--tau-be: must be a finite number >= 0, got 'nan'",
        ),
        (
            ["calibrate", "{tmp}/f", "--pattern", str(FIXTURE_YAML), "--out", "{tmp}/ds",
             "--min-sigma-major", "-1"],
            "--min-sigma-major: must be a finite number >= 0, got '-1'",
        ),
        (
            ["calibrate", "{tmp}/f", "--pattern", str(FIXTURE_YAML), "--out", "{tmp}/ds", "--folds", "1"],
            "--folds: must be >= 2",
        ),
        (
            ["extract", "{tmp}/f", "--pattern", str(FIXTURE_YAML), "--out", "{tmp}/ds", "--psf-size", "4"],
            "--psf-size: must be odd, from 3 to 255 px, got 4",
        ),
        (
            ["calibrate", "--features", "{tmp}/f.csv", "--image-size", "4294967295x4294967295", "--pattern",
             str(FIXTURE_YAML), "--out", "{tmp}/ds"],
            "--image-size: 4294967295x4294967295 px (18446744065119.6 MP), more than the 50 MP a frame may",
        ),
    ],
)
def test_bad_arguments_exit_2_before_anything_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture, argv: list[str], needle: str
) -> None:
    _png(tmp_path / "f" / "0.png", 1280, 720)
    try:
        code = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    except SystemExit as exc:  # argparse's refusal of an option value
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2 and needle in err and "Traceback" not in err, err
    assert not (tmp_path / "ds").exists() and not list(tmp_path.glob("x.*"))


def test_pattern_needs_overwrite_to_replace_files(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "t" / "star"
    argv = ["pattern", "--out", out, "--formats", "yaml"]
    assert _run(capsys, argv)[0] == 0
    (tmp_path / "t" / "star.yaml").write_text("edited")
    code, err = _run(capsys, argv)
    assert code == 2 and "star.yaml: already exists; use --overwrite" in err
    assert (tmp_path / "t" / "star.yaml").read_text() == "edited"
    assert _run(capsys, [*argv, "--overwrite"])[0] == 0
    assert (tmp_path / "t" / "star.yaml").read_text() == FIXTURE_YAML.read_text()


def test_threads_and_workers_are_capped_at_the_cores(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cores = available_cores()
    assert capped_count(cores, "--threads") == (cores, None)
    value, note = capped_count(1000, "--threads")
    assert (
        value == cores and note == f"--threads 1000 is more than the {cores} cores available: using {cores}"
    )
    _png(tmp_path / "f" / "0.png")
    try:
        code, err = _run(
            capsys,
            [
                "extract",
                tmp_path / "f",
                "--pattern",
                FIXTURE_YAML,
                "--out",
                tmp_path / "o",
                "--threads",
                "1000",
                "--workers",
                "999",
            ],
        )
        assert code == 1 and torch.get_num_threads() == cores
        assert f"blurcalib: note: --threads 1000 is more than the {cores} cores available" in err
        assert f"blurcalib: note: --workers 999 is more than the {cores} cores available" in err
    finally:
        torch.set_num_threads(1)
        cv2.setNumThreads(1)


def test_malformed_cluster_address_fails_fast(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Refused when the options are read, before anything is written, with or without Dask."""
    assert check_address("tcp://10.0.0.5:8786") == "tcp://10.0.0.5:8786"
    assert check_address("localhost:8786") == "localhost:8786"
    for bad in ("foo", "http://h:1", "tcp://h:99999", "tls://h:1/x"):
        with pytest.raises(ClusterError, match="not a scheduler address"):
            check_address(bad)
    _png(tmp_path / "f" / "0.png")
    with pytest.raises(SystemExit) as info:
        main(["extract", str(tmp_path / "f"), "--pattern", str(FIXTURE_YAML), "--out", str(tmp_path / "o"),
              "--cluster", "tcp://h:port"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "argument --cluster: not a scheduler address, the port must be" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.cluster
def test_malformed_cluster_address_is_refused_before_connecting() -> None:
    """No wait for a scheduler that cannot exist."""
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'blurcalib[cluster]'")
    with pytest.raises(ClusterError, match="'tcp://h:port': not a scheduler address"):
        next(iter(run_on_cluster("tcp://h:port", print, [(1,)])))


def test_generic_grid_limit_names_the_cell_that_fits() -> None:
    assert check_grid_size(1280, 720, 25.0) == (31, 53)
    with pytest.raises(ValueError) as info:
        check_grid_size(1280, 720, 1.0)
    assert f"the limit is {MAX_GRID_NODES} nodes: use cells of 14 px or more" in str(info.value)
    assert check_grid_size(1280, 720, 14.0)[0] * check_grid_size(1280, 720, 14.0)[1] <= MAX_GRID_NODES
    with pytest.raises(ValueError, match="finite positive"):
        check_grid_size(1280, 720, math.inf)


# ----------------------------------------------------------------------------- duplicate views
def _views(rng: np.random.Generator, n: int, shift: float) -> tuple[np.ndarray, np.ndarray]:
    ids = np.arange(n)
    xy = np.stack([100 + 30 * (ids % 15), 80 + 30 * (ids // 15)], axis=1).astype(float)
    return ids, xy + shift + rng.normal(0, 0.02, xy.shape)


def _table(frames: dict[str, tuple[np.ndarray, np.ndarray]]) -> FeatureTable:
    rows = [(name, i, x, y) for name, (ids, xy) in frames.items() for i, (x, y) in zip(ids, xy, strict=True)]
    name, fid, x, y = zip(*rows, strict=True)
    zeros = np.zeros(len(rows))
    return FeatureTable(
        np.array(name),
        np.array(fid),
        zeros,
        zeros,
        zeros,
        zeros,
        np.array(x),
        np.array(y),
        np.ones(len(rows)),
        zeros.astype(np.int64),
    )


def test_copies_of_one_frame_are_duplicates_and_distinct_views_are_not() -> None:
    rng = np.random.default_rng(2)
    ids, xy = _views(rng, 245, 0.0)
    frames = {f"sharp/{k}.png": (ids, xy + rng.normal(0, 0.01, xy.shape)) for k in range(5)}
    frames["sharp/damaged.png"] = (ids[::2][:136], xy[::2][:136] + 0.1)  # 136 of 245, 0.1 px off
    frames["sharp/moved.png"] = _views(rng, 245, 2.0)  # a distinct view, 2 px away
    frames["blurry/other.png"] = (ids[:100], xy[:100] * 1.01)  # another distance to the target
    order = list(frames)
    found = find_duplicates(_table(frames), order)
    assert [(d.frame, d.original) for d in found] == [
        (f"sharp/{k}.png", "sharp/0.png") for k in range(1, 5)
    ] + [("sharp/damaged.png", "sharp/0.png")]
    rows = mark_duplicates([FrameRecord(n, FrameStatus.OK) for n in order], _table(frames))
    assert {r.frame for r in rows if r.status is FrameStatus.DUPLICATE} == {d.frame for d in found}
    assert rows[1].status is FrameStatus.DUPLICATE
    assert rows[1].message.startswith("same view as sharp/0.png: 245")
    assert [r.status for r in rows[-2:]] == [FrameStatus.OK, FrameStatus.OK]


@pytest.mark.slow
def test_five_copies_of_one_frame_do_not_calibrate(tmp_path: Path) -> None:
    """Five copies of one sharp frame gave a "calibrated" camera (fx 836 against 900): they are
    one view, and a calibration needs 5 distinct ones."""
    from blurcalib.pipeline.run import PipelineError, run_pipeline
    from blurcalib.sim.synth import SynthConfig, write_dataset
    from blurcalib.sim.truth import TrueCamera
    from tests.state.test_app_state import SMALL_CAMERA

    data = write_dataset(
        tmp_path / "ds",
        SynthConfig(sharp=1, blurry=0, square_px=(36.0, 42.0), seed=3),
        camera=TrueCamera(SMALL_CAMERA),
        workers=1,
    )
    source = tmp_path / "ds" / data.frames[0].name
    copies = []
    for k in range(5):
        copies.append(tmp_path / "copies" / f"{k}.png")
        copies[-1].parent.mkdir(exist_ok=True)
        shutil.copy(source, copies[-1])
    pattern = load_pattern(tmp_path / "ds" / "pattern.yaml")
    with pytest.raises(PipelineError) as info:
        run_pipeline(copies, [], pattern, tmp_path / "out")
    message = str(info.value)
    assert "only 1 of 1 frame(s) are usable" in message
    assert "sharp/1.png (duplicate)" in message and "sharp/4.png (duplicate)" in message


def _capture_csv(tmp_path: Path, table: FeatureTable) -> Path:
    from blurcalib.io.results import FeatureFlags, write_features

    table.flags[:] = int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME)
    return write_features(tmp_path / "features.csv", table)


def test_a_face_on_features_csv_is_refused_before_any_calibration(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """Fronto-parallel frames calibrated for 15 minutes to fx 17,505 px (true 645) with a held-out
    error of 0.026 px."""
    from tests.calib.test_capture import capture_features, sampled

    path = _capture_csv(tmp_path, capture_features(sampled(12, 1.0, 7)))
    code, err = _run(capsys, ["calibrate", "--features", path, "--image-size", "1280x720", "--pattern",
                              FIXTURE_YAML, "--out", tmp_path / "out"])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{path}: degenerate capture: the 12 sharp frames all see the target nearly face-on" in err
    assert not (tmp_path / "out").exists()
    argv = ["calibrate", "--features", str(path), "--pattern", str(FIXTURE_YAML), "--out", "o"]
    assert pipeline_settings(build_parser().parse_args(argv)).capture.refuse
    assert not pipeline_settings(build_parser().parse_args([*argv, "--allow-degenerate"])).capture.refuse


def test_copies_of_one_frame_in_a_features_csv_are_duplicates(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """Six copies of one frame in a feature file were all used (fx 874 against 900)."""
    from tests.calib.test_capture import capture_features, sampled

    one = capture_features(sampled(1, 40.0, 8))
    copies = FeatureTable.concat([dataclasses.replace(one, frame=np.full(len(one), f"{k}.png"))
                                  for k in range(6)])
    path = _capture_csv(tmp_path, copies)
    code, err = _run(capsys, ["calibrate", "--features", path, "--image-size", "1280x720", "--pattern",
                              FIXTURE_YAML, "--out", tmp_path / "out"])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "only 1 of 1 frame(s)" in err and "1.png (duplicate)" in err and "5.png (duplicate)" in err


# ----------------------------------------------------------------------------- worker processes
def test_workers_exit_when_their_parent_is_killed(tmp_path: Path) -> None:
    script = textwrap.dedent("""
        import multiprocessing, os, time
        from concurrent.futures import ProcessPoolExecutor
        from blurcalib.runs.runtime import exit_with_parent

        if __name__ == "__main__":
            ctx = multiprocessing.get_context("spawn")
            pool = ProcessPoolExecutor(2, mp_context=ctx, initializer=exit_with_parent, initargs=(0.2,))
            pids = {f.result() for f in [pool.submit(os.getpid) for _ in range(8)]}
            print(" ".join(map(str, sorted(pids))), flush=True)
            time.sleep(600)
    """)
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        pids = [int(p) for p in parent.stdout.readline().split()]
        assert pids and all(_alive(p) for p in pids)
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait()
    deadline = time.monotonic() + 20
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(p) for p in pids)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as handle:
            return handle.read().split(") ")[-1][0] != "Z"
    except FileNotFoundError:
        return False


# ----------------------------------------------------------------------------- the app
def test_app_refuses_addresses_it_cannot_use(capsys: pytest.CaptureFixture) -> None:
    import app
    from views.security import ServeError, check_listen

    check_listen("127.0.0.1", 0)
    for host, port, needle in (
        ("127.0.0.1", 70000, "not a TCP port"),
        ("192.0.2.1", 8080, "cannot listen on"),
        ("no-such-host.invalid", 8080, "not a host name"),
    ):
        with pytest.raises(ServeError, match=needle):
            check_listen(host, port)
    handler = signal.getsignal(signal.SIGTERM)
    assert app.main(["--host", "192.0.2.1"]) == 2
    assert signal.getsignal(signal.SIGTERM) == handler
    err = capsys.readouterr().err
    assert err.strip() == "app.py: error: cannot listen on 192.0.2.1:8080 (Cannot assign requested address)"
    for argv, needle in (
        (["--port", "70000"], "must be a TCP port number (0 to 65535), got 70000"),
        (["--port", "-1"], "got -1"),
        (["--threads", "-1"], "--threads: must be >= 1, got -1"),
        (["--threads", "abc"], "must be a whole number >= 1, got 'abc'"),
    ):
        with pytest.raises(SystemExit) as info:
            app.main(argv)
        assert info.value.code == 2 and needle in capsys.readouterr().err


def test_a_host_other_machines_reach_needs_allow_remote(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``--host 0.0.0.0`` let any network client browse, probe and export as the app's user, with no
    warning: now it is refused without ``--allow-remote``, and warned about with it."""
    import app
    from views.security import ServeError, check_host, is_local_host

    assert all(is_local_host(h) for h in ("127.0.0.1", "::1", "localhost"))
    assert not any(is_local_host(h) for h in ("0.0.0.0", "::", "192.0.2.1", "no-such-host.invalid"))
    assert check_host("127.0.0.1", False) is None
    assert app.main(["--host", "0.0.0.0", "--port", "0"]) == 2
    assert capsys.readouterr().err.strip() == (
        "app.py: error: --host 0.0.0.0 exposes the app to the network: any client that reaches it can browse "
        "and read files, export into any folder and run jobs as this user; add --allow-remote to do so on a "
        "network you trust")
    assert check_host("0.0.0.0", True).endswith("run jobs as this user (--allow-remote)")
    with pytest.raises(ServeError, match="--allow-remote"):
        app.serve(tmp_path, port=0, host="0.0.0.0")
    server, running = app.serve(tmp_path, port=0, host="0.0.0.0", allow_remote=True)
    running.close()
    server.stop()


def test_a_typed_pattern_file_is_not_quoted_in_the_app(tmp_path: Path) -> None:
    """A pattern path typed in the app named any file the app's user can read, and the notice
    quoted a field's value or the offending line: now it names the field or the line number only."""
    from state import AppState

    _png(tmp_path / "f" / "0.png")
    secret = "SECRET-TOKEN-1234"
    files = {
        "value.yaml": (f"num_star_segments: {secret}\n", "field 'num_star_segments' must be int"),
        "line.yaml": (f"a: [b\n{secret}: x: y\n", "not valid YAML (line 2)"),
        "segments.yaml": ("num_star_segments: 424242\n", "must be a multiple of 4 from 4 to 128"),
        "squares.yaml": (FIXTURE_YAML.read_text().replace("squares_x: 17", "squares_x: 1"),
                         "squares_x: not a valid star target"),
        "binary.yaml": (None, "not a pattern file (not UTF-8 text)"),
    }
    state = AppState()
    for name, (text, needle) in files.items():
        path = tmp_path / name
        if text is None:
            path.write_bytes(b"\x89" + secret.encode())
        else:
            path.write_text(text)
        assert not state.load_folder(tmp_path / "f", path)
        notice = state.notices[-1].text
        assert notice.startswith(f"{path}: ") and needle in notice, notice
        assert secret not in notice and "424242" not in notice and "0x89" not in notice, notice
    with pytest.raises(PatternFileError, match=secret):  # the command line's own user sees the value
        load_pattern(tmp_path / "value.yaml")


def test_a_very_long_folder_path_is_a_notice(tmp_path: Path) -> None:
    """A 5,000-character folder path was an OSError traceback in the server log and no notice."""
    from state import AppState

    state = AppState()
    for folder, pattern in ((tmp_path / ("a" * 5000), None), (tmp_path / ("a/" * 2500), None),
                            (tmp_path, tmp_path / ("p" * 5000 + ".yaml"))):
        assert not state.load_folder(folder, pattern)
        notice = state.notices[-1]
        assert notice.title == "Cannot open the folder" and "(File name too long)" in notice.text
        assert len(notice.text) < 250 and "..." in notice.text, notice.text


def test_upload_names_are_made_safe() -> None:
    from views.security import MAX_UPLOAD_NAME, safe_upload_name

    assert safe_upload_name("a\x00b.png") == "a_b.png"
    assert safe_upload_name("../../etc/passwd") == "passwd"
    assert safe_upload_name("C:\\x\\frame.png") == "frame.png"
    long = safe_upload_name("x" * 300 + ".png")
    assert len(long) == MAX_UPLOAD_NAME and long.endswith(".png")
    assert safe_upload_name("\x00") == "_" and safe_upload_name("..") == "upload"


def test_oversized_and_overflowing_uploads_are_dropped() -> None:
    from viser import _messages

    from views.security import MAX_UPLOAD_BYTES, secure_viser_server

    server = secure_viser_server("127.0.0.1", 0, "test")
    try:
        button = server.gui.add_upload_button("Upload")
        handlers = server._websock_server._incoming_handlers
        start, part = handlers[_messages.FileTransferStartUpload][0], handlers[_messages.FileTransferPart][0]
        transfers = server.gui._current_file_upload_states

        def begin(uuid: str, size: int) -> None:
            start(
                0, _messages.FileTransferStartUpload(button._impl.uuid, uuid, "f.png", "image/png", 2, size)
            )

        begin("big", MAX_UPLOAD_BYTES + 1)
        assert "big" not in transfers  # refused before any part is buffered
        begin("small", 10)
        assert "small" in transfers
        part(0, _messages.FileTransferPart(button._impl.uuid, "small", 0, b"x" * 11))
        assert "small" not in transfers  # a part beyond the declared size drops the upload
    finally:
        server.stop()


def test_builtin_dataset_goes_to_the_user_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import app
    from state.folder import builtin_dataset_folder

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert builtin_dataset_folder() == tmp_path / "cache" / "blurcalib" / "app_dataset"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert builtin_dataset_folder() == tmp_path / "home" / ".cache" / "blurcalib" / "app_dataset"
    asked: list[Path] = []
    monkeypatch.setattr(app, "default_dataset",
                        lambda root, progress, workers: asked.append(Path(root)) or tmp_path)
    server, running = app.serve(None, port=0)
    running.close()
    server.stop()
    assert asked == [tmp_path / "home" / ".cache" / "blurcalib" / "app_dataset"]
    assert ROOT not in asked[0].parents


@pytest.mark.slow
@pytest.mark.parametrize("signals", [(signal.SIGTERM,), (signal.SIGTERM, signal.SIGINT, signal.SIGTERM)],
                         ids=["once", "again-during-clean-up"])
def test_sigterm_stops_the_app_and_deletes_its_uploads(tmp_path: Path, signals: tuple[int, ...]) -> None:
    """After SIGTERM the app ends as after Ctrl+C: its upload folder is gone from the temp folder
    (203 MB were left behind). Signals that follow while it cleans up (``timeout`` and a process
    group's kill each send one) are ignored: no traceback, exit 0, the uploads deleted."""
    folder = tmp_path / "data"
    _png(folder / "0.png")
    shutil.copy(FIXTURE_YAML, folder / "pattern.yaml")
    temp = tmp_path / "tmp"
    temp.mkdir()
    env = {**os.environ, "TMPDIR": str(temp), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "app.py"), str(folder), "--port", "0"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        lines = []
        while not any("blurcalib app: http://" in line for line in lines):
            line = proc.stdout.readline()
            assert line, "".join(lines)
            lines.append(line)
        assert [p.name for p in temp.glob("blurcalib-uploads-*")]
        for sig in signals:
            proc.send_signal(sig)
            time.sleep(0.02)
        rest = proc.communicate(timeout=60)[0]
        assert proc.returncode == 0 and "Traceback" not in rest, rest
    finally:
        proc.kill()
    assert not list(temp.glob("blurcalib-uploads-*"))
