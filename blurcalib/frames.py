"""Reading input frames: listing image files and decoding them to grey levels.

Frames are returned as ``(H, W)`` float32 grey levels on the 8-bit scale (0 black .. 255 white,
see ``docs/conventions.md``): 8-bit images as they are, 16-bit images scaled by ``255 / 65535``,
colour images (BGR or BGRA; alpha is ignored) converted to grey with OpenCV's standard weights
``0.299 R + 0.587 G + 0.114 B``, computed in floating point (no rounding to integers).
Pixel ``[i, j]`` is the pixel centred at ``(x, y) = (j, i)`` (OpenCV's pixel-centre convention).
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

IMAGE_EXTENSIONS: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
"""Extensions (lower case) recognised as frames; matched case-insensitively."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOI = b"\xff\xd8"


MIN_FRAME_SIDE = 32
"""Smallest frame width and height (px) worth searching for the target; smaller images are
refused as unreadable."""

MAX_FRAME_PIXELS = 50_000_000
"""Largest frame (width x height) processed; larger frames are refused (as unreadable, from the
file header where possible, before decoding). Extraction's memory grows with the frame: an
8000 x 6000 colour JPEG peaked at 1.8 GB resident in one process (0.3 GB of it the interpreter
and torch; loading 0.4 GB, tag detection 0.4 GB, block growth the rest), so a frame at the
limit stays under 2 GB per worker."""

_HEADER_BYTES = 1 << 18
"""Bytes read to find a PNG's or JPEG's size (a JPEG's EXIF block may precede its frame header)."""

_CONVERT_ROWS = 256
"""Rows converted to grey at a time, so that no full-size float copy of a colour image exists."""


class FrameError(ValueError):
    """A frame or frame input cannot be used; the message names the file and the problem."""


class FrameSizeError(FrameError):
    """A readable frame has another size than the frames it is processed with."""


def _natural_key(path: Path) -> tuple:
    """Sort key putting ``2.png`` before ``10.png``: digit runs compare as numbers.

    ``re.split`` with a capturing group alternates text and digit runs starting with text, so
    the parts at each position always have the same type; the full name breaks ties.
    """
    parts = re.split(r"(\d+)", path.name)
    key = tuple(int(p) if i % 2 else p.casefold() for i, p in enumerate(parts))
    return (key, path.name)


def _is_image_name(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_EXTENSIONS


def list_frames(inputs: Sequence[str | os.PathLike]) -> list[Path]:
    """Expand files and folders into the list of frame files, in order.

    A file input is taken as it is (it must have an image extension). A folder contributes its
    image files (not recursively; hidden files starting with ``.`` are skipped), in natural
    order, so ``2.png`` comes before ``10.png``. Inputs keep their order; a file reached twice
    is listed once, at its first place.

    Args:
        inputs: files and folders.
    Returns:
        Paths of the frame files.
    Raises:
        FrameError: no inputs, a missing input, a file without an image extension, or a folder
            without image files (the message names it).
    """
    if len(inputs) == 0:
        raise FrameError("no frames given: name image files or folders of images")
    wanted = ", ".join(e.lstrip(".") for e in IMAGE_EXTENSIONS)
    out: list[Path] = []
    seen: set[Path] = set()
    for item in inputs:
        path = Path(item)
        if path.is_dir():
            found = sorted((p for p in path.iterdir()
                            if p.is_file() and _is_image_name(p) and not p.name.startswith(".")),
                           key=_natural_key)
            if not found:
                raise FrameError(f"{path}: folder contains no image files ({wanted})")
        elif path.is_file():
            if not _is_image_name(path):
                raise FrameError(f"{path}: not an image file (expected extension {wanted})")
            found = [path]
        elif path.exists():
            raise FrameError(f"{path}: neither a file nor a folder")
        else:
            raise FrameError(f"{path}: no such file or folder")
        for p in found:
            key = p.resolve()
            if key not in seen:
                seen.add(key)
                out.append(p)
    return out


def _truncation(data: bytes) -> str | None:
    """Describe how PNG or JPEG bytes are cut short, or None if they look complete."""
    if data.startswith(_PNG_SIGNATURE) and b"IEND" not in data[-64:]:
        return "truncated PNG (no IEND chunk at the end)"
    if data.startswith(_JPEG_SOI) and data.rfind(b"\xff\xd9") < data.rfind(b"\xff\xda"):
        # Entropy-coded scan data never contains an FFD9 marker, so a file whose last
        # start-of-scan is not followed by an end-of-image marker was cut short.
        return "truncated JPEG (no end-of-image marker after the last scan)"
    return None


def _header_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG's IHDR chunk or a JPEG's start-of-frame marker, read
    without decoding; None for other formats or a header that cannot be parsed."""
    if data.startswith(_PNG_SIGNATURE) and data[12:16] == b"IHDR" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if not data.startswith(_JPEG_SOI):
        return None
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if 0xD0 <= marker <= 0xD9 or marker == 0x01:  # markers without a length
            i += 2
            continue
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
            height = int.from_bytes(data[i + 5:i + 7], "big")
            width = int.from_bytes(data[i + 7:i + 9], "big")
            return width, height
        i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
    return None


def frame_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(width, height)`` of an image file in pixels, or None when it cannot be read.

    PNG and JPEG sizes come from the file header; other formats are decoded.
    """
    try:
        with open(path, "rb") as handle:
            size = _header_size(handle.read(_HEADER_BYTES))
            if size is not None:
                return size
            handle.seek(0)
            data = handle.read()
    except OSError:
        return None
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        return None
    return None if image is None or image.size == 0 else (int(image.shape[1]), int(image.shape[0]))


def frame_size_problem(width: int, height: int) -> str | None:
    """Why a frame of ``width x height`` px cannot be processed, or None: a side below
    :data:`MIN_FRAME_SIDE` (too small to hold the target) or more than
    :data:`MAX_FRAME_PIXELS` pixels (too large for the memory bound)."""
    if min(width, height) < MIN_FRAME_SIDE:
        return (f"is {width}x{height} px, smaller than the {MIN_FRAME_SIDE}x{MIN_FRAME_SIDE} px "
                f"a frame needs")
    if width * height > MAX_FRAME_PIXELS:
        return (f"is {width}x{height} px ({width * height / 1e6:.1f} MP), more than the "
                f"{MAX_FRAME_PIXELS / 1e6:.0f} MP a frame may have")
    return None


def load_frame(path: str | os.PathLike, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Read one frame as grey levels.

    The file's bytes are decoded with ``cv2.imdecode`` (so paths with any characters work),
    keeping the stored depth and channels, then converted as described in the module docstring.

    Args:
        path: image file (png, jpg, tif, bmp, ... anything OpenCV decodes).
        expected_size: ``(width, height)`` in pixels the frame must have, or None.
    Returns:
        ``(H, W)`` float32 grey levels, 0..255.
    Raises:
        FrameError: the file is missing, unreadable, empty, truncated, not an image, of an
            unsupported pixel type, smaller or larger than :func:`frame_size_problem` allows
            (the size is checked from the header before decoding where the format allows).
        FrameSizeError: a readable frame not of ``expected_size``.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FrameError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise FrameError(f"{path}: is a folder, not an image file") from None
    except OSError as exc:
        raise FrameError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not data:
        raise FrameError(f"{path}: empty file")
    header = _header_size(data)
    problem = None if header is None else frame_size_problem(*header)
    if problem is not None:
        raise FrameError(f"{path}: {problem}")
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    problem = _truncation(data)
    if problem is not None and (image is None or data.startswith(_JPEG_SOI)):
        # Some decoder builds return a partly grey image for a cut-short JPEG: refuse it too.
        raise FrameError(f"{path}: {problem}")
    if image is None or image.size == 0:
        raise FrameError(f"{path}: cannot decode image (not an image, or corrupt or truncated)")
    problem = frame_size_problem(int(image.shape[1]), int(image.shape[0]))
    if problem is not None:
        raise FrameError(f"{path}: {problem}")
    if image.dtype == np.uint8:
        scale = np.float32(1.0)
    elif image.dtype == np.uint16:
        scale = np.float32(255.0 / 65535.0)
    else:
        raise FrameError(f"{path}: unsupported pixel type {image.dtype} (expected 8 or 16 bit)")
    channels = 1 if image.ndim == 2 else image.shape[2]
    codes = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}
    if channels == 1:
        grey = image.reshape(image.shape[:2]).astype(np.float32)
    elif channels in codes:
        grey = np.empty(image.shape[:2], dtype=np.float32)
        for r0 in range(0, grey.shape[0], _CONVERT_ROWS):
            rows = image[r0:r0 + _CONVERT_ROWS].astype(np.float32)
            grey[r0:r0 + _CONVERT_ROWS] = cv2.cvtColor(rows, codes[channels])
    else:
        raise FrameError(f"{path}: unsupported number of channels {channels} (expected 1, 3 or 4)")
    del image
    if scale != 1.0:
        grey *= scale
    if expected_size is not None:
        h, w = grey.shape
        ew, eh = expected_size
        if (w, h) != (ew, eh):
            raise FrameSizeError(f"{path}: is {w}x{h}, expected {ew}x{eh}")
    return grey
