"""Videos as hostile input: a header that claims any frame count (an 8-frame AVI claiming
2,147,483,647 frames made a list of that many frames: 2.6 GB in 120 s, and 5 GB in the app), a
container that cannot seek, two videos whose frames would share names, and a list of frames
too long to keep."""

from __future__ import annotations

import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.io import sources
from blurcalib.io.frames import FrameError
from blurcalib.io.sources import frame_inputs, read_video_frame, video_frame_count
from tests.conftest import FIXTURE_YAML
from tests.io.test_sources import _decoded

ROOT = Path(__file__).resolve().parents[2]


def _avi(path: Path, frames: int, claimed: int | None = None) -> Path:
    """An MJPEG AVI of ``frames`` distinct 64 x 48 frames whose headers (``avih`` total frames and
    ``strh`` length) claim ``claimed`` frames (0: no count, and the container cannot seek)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    for i in range(frames):
        image = np.full((48, 64, 3), 30, np.uint8)
        image[:, 4 * i:4 * i + 4] = 230
        writer.write(image)
    writer.release()
    if claimed is not None:
        data = bytearray(path.read_bytes())
        struct.pack_into("<I", data, data.index(b"avih") + 8 + 16, claimed)
        struct.pack_into("<I", data, data.index(b"strh") + 8 + 32, claimed)
        path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("claimed", [2**31 - 1, 9, 100_000])
def test_a_header_claiming_more_frames_lists_the_frames_that_decode(tmp_path: Path, claimed: int) -> None:
    path = _avi(tmp_path / "clip.avi", 8, claimed)
    assert int(cv2.VideoCapture(str(path)).get(cv2.CAP_PROP_FRAME_COUNT)) == claimed
    assert video_frame_count(path) == 8
    assert [f.name for f in frame_inputs([path])] == [f"clip#{i:06d}" for i in range(8)]


def test_a_lying_header_stays_in_bounded_memory_in_extract_and_the_app(tmp_path: Path) -> None:
    """Under a 1.5 GB address-space limit: the frame list of ``extract`` and the app's dataset."""
    path = _avi(tmp_path / "clip.avi", 8, 2**31 - 1)
    (tmp_path / "pattern.yaml").write_bytes(FIXTURE_YAML.read_bytes())
    script = textwrap.dedent(f"""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (1_500_000_000, 1_500_000_000))
        from blurcalib.io.sources import frame_inputs
        from state.folder import discover
        print(len(frame_inputs([{str(path)!r}])), len(discover({str(path)!r}).frames))
    """)
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["8", "8"]


def test_a_video_that_cannot_seek_is_counted_and_read_frame_by_frame(tmp_path: Path) -> None:
    """Without a frame count the container ignores seeks: frame 5 came back as frame 1."""
    path = _avi(tmp_path / "clip.avi", 13, 0)
    assert video_frame_count(path) == 13
    decoded = _decoded(path)
    for i in (0, 5, 12):
        assert np.array_equal(read_video_frame(path, i), decoded[i])
    with pytest.raises(FrameError, match="frame 13: cannot be read"):
        read_video_frame(path, 13)


def test_two_videos_of_one_name_are_refused_naming_both(tmp_path: Path) -> None:
    mp4 = tmp_path / "clip.mp4"
    writer = cv2.VideoWriter(str(mp4), cv2.VideoWriter_fourcc(*"mp4v"), 10, (64, 48))
    for _ in range(3):
        writer.write(np.zeros((48, 64, 3), np.uint8))
    writer.release()
    mkv = _avi(tmp_path / "clip.mkv", 3)
    with pytest.raises(FrameError) as info:
        frame_inputs([mp4, mkv])
    assert str(info.value) == (f"{mp4} and {mkv}: both give frames the name clip#000000: rename one of them "
                               f"(a video's frames are named by its path without the extension)")


def test_a_list_of_frames_too_long_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sources, "MAX_VIDEO_FRAMES", 5)
    path = _avi(tmp_path / "clip.avi", 8)
    with pytest.raises(FrameError, match=r"clip.avi: 8 frames, more than the 5 of one video processed: keep "
                                         r"fewer with --every N or --max-frames N"):
        frame_inputs([path])
    assert len(frame_inputs([path], every=2)) == 4 and len(frame_inputs([path], max_frames=5)) == 5
