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


class FrameError(ValueError):
    """A frame or frame input cannot be used; the message names the file and the problem."""


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
            unsupported pixel type, or not of ``expected_size`` (the message names the file).
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
    if image.dtype == np.uint8:
        scale = 1.0
    elif image.dtype == np.uint16:
        scale = 255.0 / 65535.0
    else:
        raise FrameError(f"{path}: unsupported pixel type {image.dtype} (expected 8 or 16 bit)")
    grey = image.astype(np.float32)
    channels = 1 if grey.ndim == 2 else grey.shape[2]
    if channels == 1:
        grey = grey.reshape(grey.shape[:2])
    elif channels == 3:
        grey = cv2.cvtColor(grey, cv2.COLOR_BGR2GRAY)
    elif channels == 4:
        grey = cv2.cvtColor(grey, cv2.COLOR_BGRA2GRAY)
    else:
        raise FrameError(f"{path}: unsupported number of channels {channels} (expected 1, 3 or 4)")
    if scale != 1.0:
        grey *= np.float32(scale)
    if expected_size is not None:
        h, w = grey.shape
        ew, eh = expected_size
        if (w, h) != (ew, eh):
            raise FrameError(f"{path}: is {w}x{h}, expected {ew}x{eh}")
    return grey
