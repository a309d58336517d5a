"""Frame sources: folders, image files and videos as one ordered list of frames read on demand.

Each input is a folder (its image files, :func:`blurcalib.io.frames.list_frames`), an image file or a
video file (:data:`VIDEO_EXTENSIONS`, decoded by OpenCV's ``cv2.VideoCapture``). Every frame is a
:class:`FrameInput`: a name, the file and, for a video, the frame's index, so that a worker
process reads just the frame it processes (nothing decodes a whole video into memory). A video
frame is read by seeking to its index (``CAP_PROP_POS_FRAMES``), which returns the same pixels
as a sequential decode and costs a few hundredths of a frame's extraction. A video whose container
cannot seek (one without a frame count or an index) is read by decoding the frames before the one
wanted.

A video's frame count is what decodes, not what its header claims (:func:`video_frame_count`),
and at most :data:`MAX_VIDEO_FRAMES` frames of one video are listed. Every frame of a video is
read at the size its stream header gives: OpenCV's decoder scales a frame stored at another size
(a stream whose size changes part-way) to that size and says nothing, so such frames cannot be
told apart and get no ``wrong_size`` status. They are a different camera: split such a video at
the change, or extract its frames to image files, before calibrating.

Names: an image is named by its path relative to the common folder of all inputs' files
(``0.png``, ``seq1/0.png``); frame ``i`` of a video by the video's relative path without its
extension, ``#`` and ``i`` in six digits (``walk#000123``), in every table.

Frames of one input form a *sequence* (:attr:`FrameInput.sequence`): the frames of a video, or
the images of a folder in natural order. Neighbours in a sequence see the target from nearby
poses (:func:`blurcalib.runs.neighbours.seed_from_neighbour`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from blurcalib.io.frames import (
    IMAGE_EXTENSIONS,
    FrameError,
    FrameSizeError,
    frame_size,
    frame_size_problem,
    list_frames,
    load_frame,
)

VIDEO_EXTENSIONS: tuple[str, ...] = (".mp4", ".avi", ".mkv", ".mov")
"""Extensions (lower case) read as videos; matched case-insensitively."""

MAX_VIDEO_FRAMES = 1_000_000
"""Most frames listed from one video (after ``every`` and ``max_frames``): nine hours at 30 frames
per second. A longer list is refused, so that the list of frames stays small in memory."""


def is_video(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` has a video extension (:data:`VIDEO_EXTENSIONS`)."""
    return Path(path).suffix.lower() in VIDEO_EXTENSIONS


@dataclass(frozen=True)
class FrameInput:
    """One frame to process.

    Attributes:
        name: the name recorded for the frame in every table.
        path: the image file, or the video file.
        index: the frame's index in the video (0 for its first frame); None for an image file.
        sequence: the sequence the frame belongs to (the video, or the image's folder), for
            neighbour seeding; empty for a frame in no sequence.
        order: the frame's position in its sequence (the video index, or the image's rank in
            its folder).
    """

    name: str
    path: Path
    index: int | None = None
    sequence: str = ""
    order: int = 0

    def load(self, expected_size: tuple[int, int] | None = None) -> np.ndarray:
        """The frame's grey levels ``(H, W)`` float32, 0..255 (:func:`blurcalib.io.frames.load_frame`'s
        conventions; a video frame is converted from BGR with the same weights).

        Raises:
            FrameError: unreadable (the message names the file and the frame index).
            FrameSizeError: readable but not of ``expected_size`` ``(width, height)``.
        """
        if self.index is None:
            return load_frame(self.path, expected_size)
        image = read_video_frame(self.path, self.index)
        h, w = image.shape
        if expected_size is not None and (w, h) != tuple(expected_size):
            raise FrameSizeError(f"{self.path} frame {self.index}: is {w}x{h}, expected "
                                 f"{expected_size[0]}x{expected_size[1]}")
        return image

    def size(self) -> tuple[int, int] | None:
        """``(width, height)`` px, or None when it cannot be read (a video's from its header)."""
        if self.index is None:
            return frame_size(self.path)
        return video_size(self.path)


def _open(path: Path) -> cv2.VideoCapture:
    if not path.is_file():
        raise FrameError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    try:
        capture = cv2.VideoCapture(str(path))
    except cv2.error:
        capture = None
    if capture is None or not capture.isOpened():
        raise FrameError(f"{path}: cannot open as a video (not a video, or corrupt or unsupported)")
    return capture


def video_size(path: str | os.PathLike[str]) -> tuple[int, int] | None:
    """``(width, height)`` of a video's frames in pixels, or None when it cannot be opened."""
    try:
        capture = _open(Path(path))
    except FrameError:
        return None
    try:
        w, h = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
    finally:
        capture.release()
    return (w, h) if w > 0 and h > 0 else None


def video_frame_count(path: str | os.PathLike[str]) -> int:
    """Number of frames of a video that decode: the container's count when its last frame
    decodes, else the count found by seeking (:func:`_decodable_count`).

    A header may claim any count (an 8-frame AVI whose header says 2,147,483,647 frames); the
    count is never taken on trust, and a video with a count is never read whole: a few dozen
    seeks at most.

    Raises:
        FrameError: the file is missing or cannot be opened as a video.
    """
    capture = _open(Path(path))
    try:
        claimed = capture.get(cv2.CAP_PROP_FRAME_COUNT)
        return _decodable_count(capture, int(claimed) if math.isfinite(claimed) and claimed >= 1 else 0)
    finally:
        capture.release()


def _at(capture: cv2.VideoCapture, index: int) -> bool:
    """Whether the frame an open video just decoded is frame ``index`` (its position is the next)."""
    return round(capture.get(cv2.CAP_PROP_POS_FRAMES)) == index + 1


def _decodes(capture: cv2.VideoCapture, index: int) -> bool:
    """Whether frame ``index`` of an open video can be sought to and decoded."""
    try:
        capture.set(cv2.CAP_PROP_POS_FRAMES, float(index))
        return bool(capture.grab()) and _at(capture, index)
    except cv2.error:
        return False


def _decodable_count(capture: cv2.VideoCapture, claimed: int) -> int:
    """Frames ``0 .. n - 1`` that decode, taking the frames up to the last that decodes as there:
    the ``claimed`` count when its last frame decodes (one seek), else a bisection between the
    first frame and the claimed end (about ``log2(claimed)`` seeks). Without a claimed count (0)
    the video cannot seek either, and its frames are counted by decoding them one after another
    (nothing is kept)."""
    if not claimed:
        count = 0
        while capture.grab():
            count += 1
        return count
    if _decodes(capture, claimed - 1):
        return claimed
    if not _decodes(capture, 0):
        return 0
    good, bad = 0, claimed - 1
    while bad - good > 1:
        middle = (good + bad) // 2
        good, bad = (middle, bad) if _decodes(capture, middle) else (good, middle)
    return good + 1


def read_video_frame(path: str | os.PathLike[str], index: int) -> np.ndarray:
    """Frame ``index`` of a video as grey levels ``(H, W)`` float32, 0..255 (BGR converted with
    ``0.299 R + 0.587 G + 0.114 B``), read by seeking to it; where the video cannot seek to it (a
    container without an index), by decoding the frames before it.

    Raises:
        FrameError: the video cannot be opened, has no frame ``index``, or its frames are too
            small or too large (:func:`blurcalib.io.frames.frame_size_problem`).
    """
    path = Path(path)
    capture = _open(path)
    try:
        w, h = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        problem = frame_size_problem(w, h) if w > 0 and h > 0 else None
        if problem is not None:
            raise FrameError(f"{path}: {problem}")
        if index > 0:
            capture.set(cv2.CAP_PROP_POS_FRAMES, float(index))
        ok, frame = capture.read()
        if ok and index > 0 and not _at(capture, index):  # the seek went elsewhere: decode up to it
            capture.release()
            capture = _open(path)
            ok = all(capture.grab() for _ in range(index))
            ok, frame = capture.read() if ok else (False, None)  # type: ignore[assignment]  # cv2 reads None on failure
    except cv2.error as exc:
        raise FrameError(f"{path} frame {index}: cannot decode ({' '.join(str(exc).split())})") from None
    finally:
        capture.release()
    if not ok or frame is None or frame.size == 0:
        raise FrameError(f"{path} frame {index}: cannot be read (past the end, or corrupt)")
    if frame.dtype != np.uint8:
        raise FrameError(f"{path} frame {index}: unsupported pixel type {frame.dtype} (expected 8 bit)")
    if frame.ndim == 2:
        return frame.astype(np.float32)
    if frame.shape[2] == 1:
        return frame[:, :, 0].astype(np.float32)
    return cv2.cvtColor(frame.astype(np.float32), cv2.COLOR_BGR2GRAY)


def _located(path: Path) -> Path:
    """The absolute path a file is named by: the file it resolves to, or, for a broken symbolic
    link, the link itself (as :func:`blurcalib.runs.output.frame_names` names plain paths)."""
    return path.resolve() if path.exists() else path.parent.resolve() / path.name


def _text(name: str) -> str:
    """A name as text that can be written as UTF-8 (non-UTF-8 bytes as ``\\xNN`` escapes)."""
    return os.fsencode(name).decode("utf-8", "backslashreplace")


def _keep(count: int, every: int, max_frames: int | None) -> range:
    """Positions kept from ``count`` frames: every ``every``-th from the first, at most ``max_frames``."""
    kept = range(0, count, every)
    return kept if max_frames is None else kept[:max_frames]


def frame_inputs(inputs: Sequence[str | os.PathLike[str]], every: int = 1,
                 max_frames: int | None = None) -> list[FrameInput]:
    """Expand folders, image files and video files into the frames to process, in order.

    A folder contributes its image files in natural order (:func:`blurcalib.io.frames.list_frames`),
    a video its frames, an image file itself. ``every`` and ``max_frames`` apply to each folder
    and each video on its own: its frames ``0, every, 2 every, ...``, at most ``max_frames`` of
    them. A file reached twice is listed once, at its first place.

    Args:
        inputs: folders, image files and video files.
        every: keep every ``every``-th frame of a folder or video (>= 1).
        max_frames: keep at most this many frames of a folder or video (>= 1; None: all).
    Returns:
        The frames, named as the module docstring says; names are unique.
    Raises:
        FrameError: no inputs, a missing input, a file that is neither an image nor a video, a
            video that cannot be opened, has no frames or more than :data:`MAX_VIDEO_FRAMES` to
            list, a folder without image files, or two files whose frames would get one name.
        ValueError: ``every`` or ``max_frames`` below 1.
    """
    if every < 1 or (max_frames is not None and max_frames < 1):
        raise ValueError(f"every and max_frames must be >= 1, got {every} and {max_frames}")
    if len(inputs) == 0:
        raise FrameError("no frames given: name image files, folders of images or video files")
    groups: list[tuple[list[Path], str]] = []  # (files, "video", "folder" or "image") per input
    seen: set[Path] = set()
    for item in inputs:
        path = Path(item)
        if path.is_file() and is_video(path):
            files, kind = [path], "video"
        elif path.is_file() and path.suffix.lower() not in IMAGE_EXTENSIONS:
            wanted = ", ".join(e.lstrip(".") for e in IMAGE_EXTENSIONS + VIDEO_EXTENSIONS)
            raise FrameError(f"{path}: neither an image nor a video file (expected extension {wanted})")
        else:
            files, kind = list_frames([path]), "folder" if path.is_dir() else "image"
        files = [f for f in files if _located(f) not in seen]
        seen.update(_located(f) for f in files)
        if files:
            groups.append((files, kind))
    common = Path(os.path.commonpath([_located(f).parent for files, _ in groups for f in files]))
    out: list[FrameInput] = []
    for files, kind in groups:
        if kind == "video":
            path = files[0]
            count = video_frame_count(path)
            if count == 0:
                raise FrameError(f"{path}: the video has no frames that can be decoded")
            kept = _keep(count, every, max_frames)
            if len(kept) > MAX_VIDEO_FRAMES:
                raise FrameError(f"{path}: {count} frames, more than the {MAX_VIDEO_FRAMES} of one video "
                                 f"processed: keep fewer with --every N or --max-frames N")
            stem = _text(_located(path).relative_to(common).with_suffix("").as_posix())
            out += [FrameInput(f"{stem}#{i:06d}", path, i, str(_located(path)), i) for i in kept]
        else:
            kept = _keep(len(files), every, max_frames) if kind == "folder" else range(len(files))
            out += [FrameInput(_text(_located(files[i]).relative_to(common).as_posix()), files[i])
                    for i in kept]
    _check_unique(out)
    return in_sequences(out)


def _check_unique(frames: list[FrameInput]) -> None:
    """Refuse two files whose frames get one name (``clip.mp4`` and ``clip.mkv`` both name their
    frames ``clip#000000``...), naming both."""
    first: dict[str, Path] = {}
    for f in frames:
        other = first.setdefault(f.name, f.path)
        if other != f.path:
            raise FrameError(f"{other} and {f.path}: both give frames the name {f.name}: rename one of them "
                             f"(a video's frames are named by its path without the extension)")


def in_sequences(frames: list[FrameInput]) -> list[FrameInput]:
    """Image frames placed in the sequence of their folder, ranked in list order; video frames
    keep theirs, or, without one, are placed in their video's at their index."""
    rank: dict[str, int] = {}
    out = []
    for f in frames:
        if f.index is None:
            folder = str(_located(f.path).parent)
            f = FrameInput(f.name, f.path, None, folder, rank.get(folder, 0))
            rank[folder] = f.order + 1
        elif not f.sequence:
            f = FrameInput(f.name, f.path, f.index, str(_located(f.path)), f.index)
        out.append(f)
    return out
