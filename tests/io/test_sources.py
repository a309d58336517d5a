"""Frame sources: folders, image files and videos as one list of frames read on demand."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.io.frames import FrameError, FrameSizeError
from blurcalib.io.sources import FrameInput, frame_inputs, read_video_frame, video_frame_count


def _write_video(path: Path, frames: list[np.ndarray]) -> Path:
    h, w = frames[0].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (w, h), isColor=False)
    for f in frames:
        writer.write(f)
    writer.release()
    return path


@pytest.fixture
def clip(tmp_path: Path) -> tuple[Path, list[np.ndarray]]:
    """A 7-frame mp4v video of distinct 96 x 64 frames (a bright bar moving right)."""
    frames = []
    for i in range(7):
        f = np.full((64, 96), 40, np.uint8)
        f[:, 8 + 10 * i:16 + 10 * i] = 220
        frames.append(f)
    return _write_video(tmp_path / "clip.mp4", frames), frames


def _decoded(path: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, frame = capture.read()
        if not ok:
            return out
        out.append(cv2.cvtColor(frame.astype(np.float32), cv2.COLOR_BGR2GRAY))


def test_video_frames_are_named_and_read_by_index(clip) -> None:
    path, written = clip
    frames = frame_inputs([path])
    assert [f.name for f in frames] == [f"clip#{i:06d}" for i in range(7)]
    assert [f.index for f in frames] == list(range(7)) and video_frame_count(path) == 7
    decoded = _decoded(path)
    for f in (frames[5], frames[0], frames[3]):  # out of order: each read seeks
        image = f.load()
        assert image.dtype == np.float32 and image.shape == (64, 96)
        assert np.array_equal(image, decoded[f.index])
        # mp4v keeps the frame's content: the bar is where it was written
        assert np.abs(image - written[f.index]).mean() < 6
    assert frames[2].size() == (96, 64)
    assert len({f.sequence for f in frames}) == 1 and [f.order for f in frames] == list(range(7))


def test_every_and_max_frames(clip, tmp_path: Path) -> None:
    path, _ = clip
    assert [f.index for f in frame_inputs([path], every=3)] == [0, 3, 6]
    assert [f.index for f in frame_inputs([path], every=2, max_frames=2)] == [0, 2]
    folder = tmp_path / "seq"
    folder.mkdir()
    for i in range(5):
        cv2.imwrite(str(folder / f"{i}.png"), np.full((40, 40), 10 * i, np.uint8))
    # each folder and each video on its own; an image file is itself
    frames = frame_inputs([folder, path], every=2, max_frames=2)
    assert [f.name for f in frames] == ["seq/0.png", "seq/2.png", "clip#000000", "clip#000002"]
    assert [f.order for f in frames] == [0, 1, 0, 2]
    with pytest.raises(ValueError, match="must be >= 1"):
        frame_inputs([path], every=0)


def test_mixed_inputs_share_one_naming(clip, tmp_path: Path) -> None:
    path, _ = clip
    sub = tmp_path / "more"
    sub.mkdir()
    image = sub / "x.png"
    cv2.imwrite(str(image), np.full((40, 50), 99, np.uint8))
    frames = frame_inputs([image, path, sub])  # the image reached twice is listed once
    assert [f.name for f in frames[:2]] == ["more/x.png", "clip#000000"] and len(frames) == 8
    assert frames[0].index is None and frames[0].load().shape == (40, 50)
    with pytest.raises(FrameSizeError, match="expected 50x40"):
        frames[1].load(expected_size=(50, 40))


def test_bad_video_inputs(tmp_path: Path, clip) -> None:
    path, _ = clip
    fake = tmp_path / "fake.mov"
    fake.write_bytes(b"not a video at all" * 100)
    with pytest.raises(FrameError, match=r"fake\.mov: cannot open as a video"):
        frame_inputs([fake])
    other = tmp_path / "notes.txt"
    other.write_text("x")
    with pytest.raises(FrameError, match=r"notes\.txt: neither an image nor a video"):
        frame_inputs([other])
    with pytest.raises(FrameError, match="frame 99: cannot be read"):
        read_video_frame(path, 99)
    with pytest.raises(FrameError, match="no such file"):
        FrameInput("gone#000000", tmp_path / "gone.mp4", 0).load()


def test_app_opens_a_video_as_a_dataset(clip, tmp_path: Path) -> None:
    from blurcalib.target.pattern import layout_pattern
    from state.app_state import AppState
    from state.folder import DatasetError, discover

    path, _ = clip
    layout_pattern().save_yaml(tmp_path / "pattern.yaml")
    dataset = discover(path)
    assert dataset.source == path and dataset.folder == tmp_path
    assert [f.name for f in dataset.frames] == [f"clip#{i:06d}" for i in range(7)]
    assert [f.index for f in dataset.frames] == list(range(7))
    state = AppState()
    assert state.load_folder(path)
    assert np.array_equal(state.image("clip#000004"), read_video_frame(path, 4))
    with pytest.raises(DatasetError, match="neither a folder nor a video file"):
        discover(tmp_path / "pattern.yaml")
