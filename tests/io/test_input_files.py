"""Input files that are not regular files, or are too large, are refused before a byte is read:
a device behind a frame's or a feature file's name (``/dev/zero`` read 2 GB in seconds), a FIFO
(its reader waited for a writer for ever), a folder, a file over its reader's limit."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from blurcalib.io import feature_input
from blurcalib.io.feature_input import FeatureInputError, read_feature_input
from blurcalib.io.frames import MAX_FRAME_BYTES, FrameError, frame_size, load_frame
from blurcalib.io.input_file import InputFileError, read_input
from blurcalib.io.results import ResultsFileError, read_feature_table
from blurcalib.target.pattern import PatternFileError, layout_pattern, load_pattern

DEVICE = Path("/dev/zero")


def _link(tmp_path: Path, name: str, target: Path) -> Path:
    link = tmp_path / name
    link.symlink_to(target)
    return link


def _fifo(tmp_path: Path, name: str) -> Path:
    path = tmp_path / name
    os.mkfifo(path)
    return path


def _sparse(tmp_path: Path, name: str, size: int) -> Path:
    """A file of ``size`` bytes that takes no disk space (a hole)."""
    path = tmp_path / name
    with open(path, "wb") as handle:
        handle.truncate(size)
    return path


needs_devices = pytest.mark.skipif(not DEVICE.exists() or not hasattr(os, "mkfifo"),
                                   reason="needs /dev/zero and FIFOs (POSIX)")


@needs_devices
@pytest.mark.parametrize("kind", ["device", "fifo", "folder"])
def test_frames_that_are_not_regular_files_are_unreadable(tmp_path: Path, kind: str) -> None:
    path = {"device": lambda: _link(tmp_path, "zero.png", DEVICE),
            "fifo": lambda: _fifo(tmp_path, "pipe.png"),
            "folder": lambda: (tmp_path / "dir.png").mkdir() or tmp_path / "dir.png"}[kind]()
    what = {"device": "a character device", "fifo": "a FIFO (named pipe)", "folder": "a folder"}[kind]
    assert frame_size(path) is None
    with pytest.raises(FrameError) as info:
        load_frame(path)
    assert str(info.value) == f"{path}: is {what}, not a regular file"


def test_a_frame_file_over_the_limit_is_refused_before_reading(tmp_path: Path) -> None:
    path = _sparse(tmp_path, "huge.png", MAX_FRAME_BYTES + 1)
    with pytest.raises(FrameError, match=r"huge.png: 401.\d MB, more than the 401.\d MB a frame may have"):
        load_frame(path)


def test_a_file_that_grows_past_the_limit_while_read_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "f.bin"
    path.write_bytes(b"x" * 11)
    assert read_input(path, 11) == b"x" * 11
    with pytest.raises(InputFileError, match="more than the 10 bytes a file may have"):
        read_input(path, 10)


@needs_devices
@pytest.mark.parametrize("name", ["zero.bin", "zero.csv"])
def test_feature_files_behind_a_device_are_refused(tmp_path: Path, name: str) -> None:
    path = _link(tmp_path, name, DEVICE)
    with pytest.raises(FeatureInputError) as info:
        read_feature_input(path, layout_pattern(), (1280, 720))
    assert str(info.value) == f"{path}: is a character device, not a regular file"


@needs_devices
@pytest.mark.parametrize("name", ["pipe.bin", "pipe.csv"])
def test_a_fifo_named_as_a_feature_file_does_not_block(tmp_path: Path, name: str) -> None:
    path = _fifo(tmp_path, name)
    with pytest.raises(FeatureInputError) as info:
        read_feature_input(path, layout_pattern(), (1280, 720))
    assert str(info.value) == f"{path}: is a FIFO (named pipe), not a regular file"
    with pytest.raises(ResultsFileError, match="FIFO"):
        read_feature_table(path)


@needs_devices
def test_a_fifo_named_as_a_pattern_does_not_block(tmp_path: Path) -> None:
    path = _fifo(tmp_path, "pattern.yaml")
    with pytest.raises(PatternFileError, match="is a FIFO"):
        load_pattern(path)


@pytest.mark.parametrize(("suffix", "shown"), [(".bin", "64.0 MB"), (".csv", "512.0 MB")])
def test_feature_files_over_the_limit_are_refused_before_reading(tmp_path: Path, suffix: str,
                                                                 shown: str) -> None:
    path = _sparse(tmp_path, f"big{suffix}", feature_input.MAX_FILE_BYTES[suffix] + 1)
    with pytest.raises(FeatureInputError) as info:
        read_feature_input(path, layout_pattern(), (1280, 720))
    assert str(info.value).startswith(f"{path}: ") and f"more than the {shown}" in str(info.value)
