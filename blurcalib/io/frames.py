"""Reading input frames: listing image files and decoding them to grey levels.

Frames are returned as ``(H, W)`` float32 grey levels on the 8-bit scale (0 black .. 255 white,
see ``docs/conventions.md``): 8-bit images as they are, 16-bit images scaled by ``255 / 65535``,
colour images (BGR or BGRA; alpha is ignored) converted to grey with OpenCV's standard weights
``0.299 R + 0.587 G + 0.114 B``, computed in floating point (no rounding to integers).
Pixel ``[i, j]`` is the pixel centred at ``(x, y) = (j, i)`` (OpenCV's pixel-centre convention).
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO, Literal

import cv2
import numpy as np
import numpy.typing as npt

from blurcalib.io.input_file import InputFileError, open_input, read_input

IMAGE_EXTENSIONS: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
"""Extensions (lower case) recognised as frames; matched case-insensitively."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOI = b"\xff\xd8"


MIN_FRAME_SIDE = 32
"""Smallest frame width and height (px) worth searching for the target; smaller images are
refused as unreadable."""

MAX_FRAME_PIXELS = 50_000_000
"""Largest frame (width x height) processed; larger frames are refused (as unreadable, from the
file header, before decoding). Extraction's memory grows with the frame: an
8000 x 6000 colour JPEG peaked at 1.8 GB resident in one process (0.3 GB of it the interpreter
and torch; loading 0.4 GB, tag detection 0.4 GB, block growth the rest), so a frame at the
limit stays under 2 GB per worker."""

MAX_FRAME_BYTES = 8 * MAX_FRAME_PIXELS + (1 << 20)
"""Largest frame file read (bytes): a frame of :data:`MAX_FRAME_PIXELS` pixels stored without
compression in 4 channels of 16 bits, plus 1 MiB of headers. A larger file is refused before it
is read (so is anything that is not a regular file: a device or a FIFO behind a frame's name)."""

_TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
"""The first four bytes of a TIFF or BigTIFF, little- or big-endian."""

_MAX_JPEG_MARKERS = 100_000
"""Marker segments (and fill bytes) walked to find a JPEG's frame header before giving up."""

_JPEG_DAMAGE = re.compile(r"Corrupt JPEG data|Premature end of JPEG|Bogus|Invalid|Huffman|Inconsistent")
"""libjpeg's warnings about damaged data (what else the process writes meanwhile is passed on)."""

_HARMLESS_JPEG_WARNINGS = re.compile(r"Corrupt JPEG data: \d+ extraneous bytes before marker 0xd9")
"""Decoder warnings that leave the image intact: padding before the end-of-image marker, which
some cameras write. Any other warning (bad Huffman code, premature end of a data segment, ...)
marks the frame unreadable: its pixels are partly invented by the decoder."""

_CONVERT_ROWS = 256
"""Rows converted to grey at a time, so that no full-size float copy of a colour image exists."""


class FrameError(ValueError):
    """A frame or frame input cannot be used; the message names the file and the problem."""


class FrameSizeError(FrameError):
    """A readable frame has another size than the frames it is processed with."""


def _natural_key(path: Path) -> tuple[tuple[int | str, ...], str]:
    """Sort key putting ``2.png`` before ``10.png``: digit runs compare as numbers.

    ``re.split`` with a capturing group alternates text and digit runs starting with text, so
    the parts at each position always have the same type; the full name breaks ties.
    """
    parts = re.split(r"(\d+)", path.name)
    key = tuple(int(p) if i % 2 else p.casefold() for i, p in enumerate(parts))
    return (key, path.name)


def _is_image_name(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_EXTENSIONS


def list_frames(inputs: Sequence[str | os.PathLike[str]]) -> list[Path]:
    """Expand files and folders into the list of frame files, in order.

    A file input is taken as it is (it must have an image extension). A folder contributes its
    image files (not recursively; hidden files starting with ``.`` are skipped), in natural
    order, so ``2.png`` comes before ``10.png``. Inputs keep their order; a file reached twice
    is listed once, at its first place. A symbolic link with an image extension is listed even
    when it is broken or part of a loop, so that its frame gets a status (unreadable, naming the
    link) instead of vanishing.

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
                            if (p.is_file() or p.is_symlink()) and _is_image_name(p)
                            and not p.name.startswith(".")),
                           key=_natural_key)
            if not found:
                raise FrameError(f"{path}: folder contains no image files ({wanted})")
        elif path.is_file() or path.is_symlink():
            if not _is_image_name(path):
                raise FrameError(f"{path}: not an image file (expected extension {wanted})")
            found = [path]
        elif path.exists():
            raise FrameError(f"{path}: neither a file nor a folder")
        else:
            raise FrameError(f"{path}: no such file or folder")
        for p in found:
            key = Path(os.path.realpath(p) if p.exists() else os.path.abspath(p))
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


def _image_format(head: bytes) -> str | None:
    """The format of an image file from its first bytes: ``png``, ``jpeg``, ``tiff``, ``bmp`` or
    None (a format blurcalib does not read)."""
    if head.startswith(_PNG_SIGNATURE):
        return "png"
    if head.startswith(_JPEG_SOI):
        return "jpeg"
    if head[:4] in _TIFF_SIGNATURES:
        return "tiff"
    if head.startswith(b"BM"):
        return "bmp"
    return None


def _read_at(handle: BinaryIO, offset: int, size: int) -> bytes:
    handle.seek(offset)
    return handle.read(size)


def _jpeg_size(handle: BinaryIO) -> tuple[int, int] | None:
    """``(width, height)`` from a JPEG's start-of-frame marker, found by walking the marker
    segments (an EXIF block of any length may precede it)."""
    i = 2
    for _ in range(_MAX_JPEG_MARKERS):
        head = _read_at(handle, i, 9)
        if len(head) < 4 or head[0] != 0xFF:
            return None
        marker = head[1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if 0xD0 <= marker <= 0xD9 or marker == 0x01:  # markers without a length
            i += 2
            continue
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
            if len(head) < 9:
                return None
            return int.from_bytes(head[7:9], "big"), int.from_bytes(head[5:7], "big")
        i += 2 + int.from_bytes(head[2:4], "big")
    return None


def _tiff_size(handle: BinaryIO) -> tuple[int, int] | None:
    """``(width, height)`` from the first image file directory of a TIFF or BigTIFF
    (``ImageWidth`` 256, ``ImageLength`` 257), read without decoding."""
    head = _read_at(handle, 0, 16)
    order: Literal["little", "big"] = "little" if head[:2] == b"II" else "big"
    big = int.from_bytes(head[2:4], order) == 43
    offset = int.from_bytes(head[8:16] if big else head[4:8], order)
    count_size, entry_size, value_at = (8, 20, 12) if big else (2, 12, 8)
    count = int.from_bytes(_read_at(handle, offset, count_size), order)
    entries = _read_at(handle, offset + count_size, entry_size * min(count, 4096))
    found: dict[int, int] = {}
    for k in range(len(entries) // entry_size):
        entry = entries[k * entry_size:(k + 1) * entry_size]
        tag, kind = int.from_bytes(entry[0:2], order), int.from_bytes(entry[2:4], order)
        if tag in (256, 257):
            width = {3: 2, 4: 4, 16: 8}.get(kind)  # SHORT, LONG, LONG8
            if width is None:
                return None
            found[tag] = int.from_bytes(entry[value_at:value_at + width], order)
    return (found[256], found[257]) if len(found) == 2 else None


def _bmp_size(handle: BinaryIO) -> tuple[int, int] | None:
    """``(width, height)`` from a BMP's info header (a negative height: rows stored top-down)."""
    head = _read_at(handle, 14, 12)
    if len(head) < 8:
        return None
    if int.from_bytes(head[0:4], "little") == 12:  # OS/2 core header: 16-bit sides
        return int.from_bytes(head[4:6], "little"), int.from_bytes(head[6:8], "little")
    if len(head) < 12:
        return None
    return (abs(int.from_bytes(head[4:8], "little", signed=True)),
            abs(int.from_bytes(head[8:12], "little", signed=True)))


def _header_size(handle: BinaryIO) -> tuple[int, int] | None:
    """``(width, height)`` of a PNG, JPEG, TIFF or BMP read from its header without decoding
    (a few small reads, wherever the header lies in the file); None for another format or a
    header that cannot be parsed."""
    head = _read_at(handle, 0, 24)
    kind = _image_format(head)
    if kind == "png":
        if head[12:16] != b"IHDR" or len(head) < 24:
            return None
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    readers = {"jpeg": _jpeg_size, "tiff": _tiff_size, "bmp": _bmp_size}
    return readers[kind](handle) if kind in readers else None


def frame_size(path: str | os.PathLike[str]) -> tuple[int, int] | None:
    """``(width, height)`` of an image file in pixels, from its header (nothing is decoded), or
    None when it cannot be read, is not a regular file or is not a PNG, JPEG, TIFF or BMP file."""
    try:
        with open_input(path, what="frame") as handle:
            return _header_size(handle)
    except (OSError, InputFileError):
        return None


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


def _missing(path: Path) -> str:
    """Why an existing-looking path has no file: a broken symbolic link, or none at all."""
    if path.is_symlink():
        return f"broken symbolic link (to {os.readlink(path)}, which does not exist)"
    return "no such file"


_STDERR_LOCK = threading.Lock()
"""Serialises the decodes that capture the C library's standard error."""


@contextlib.contextmanager
def _captured_stderr() -> Iterator[list[str]]:
    """Capture what C code writes to file descriptor 2 while the block runs (libjpeg's warnings);
    yields a list that receives its lines when the block ends."""
    lines: list[str] = []
    with _STDERR_LOCK, tempfile.TemporaryFile() as sink:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(sink.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            lines += [line.strip() for line in sink.read().decode("utf-8", "replace").splitlines()
                      if line.strip()]


def _decode(data: bytes) -> tuple[np.ndarray | None, list[str]]:
    """Decode image bytes with ``cv2.imdecode`` (stored depth and channels); for a JPEG also
    return the decoder's warnings that mean damaged data (not :data:`_HARMLESS_JPEG_WARNINGS`)."""
    buffer = np.frombuffer(data, dtype=np.uint8)
    if not data.startswith(_JPEG_SOI):
        try:
            return cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED), []
        except cv2.error:
            return None, []
    with _captured_stderr() as lines:
        try:
            image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
        except cv2.error:
            image = None
    damage = [line for line in lines if _JPEG_DAMAGE.search(line)]
    other = [line for line in lines if not _JPEG_DAMAGE.search(line)]
    if other:  # another thread's output, caught while the decoder's was: pass it on
        print("\n".join(other), file=sys.stderr, flush=True)
    return image, [line for line in damage if not _HARMLESS_JPEG_WARNINGS.fullmatch(line)]


def load_frame(path: str | os.PathLike[str], expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Read one frame as grey levels.

    The file's bytes are decoded with ``cv2.imdecode`` (so paths with any characters work),
    keeping the stored depth and channels, then converted as described in the module docstring.

    Args:
        path: image file (png, jpg, tif, bmp, ... anything OpenCV decodes).
        expected_size: ``(width, height)`` in pixels the frame must have, or None.
    Returns:
        ``(H, W)`` float32 grey levels, 0..255.
    Raises:
        FrameError: the file is missing (or a broken symbolic link), not a regular file (a
            folder, a device, a FIFO), larger than :data:`MAX_FRAME_BYTES`, unreadable, empty, truncated,
            not a PNG, JPEG, TIFF or BMP file, a JPEG whose decoder reports damaged data, of an
            unsupported pixel type, or smaller or larger than :func:`frame_size_problem` allows
            (the size is checked from the file header, before decoding).
        FrameSizeError: a readable frame not of ``expected_size``.
    """
    path = Path(path)
    try:
        data = read_input(path, MAX_FRAME_BYTES, "frame")
    except FileNotFoundError:
        raise FrameError(f"{path}: {_missing(path)}") from None
    except InputFileError as exc:
        raise FrameError(str(exc)) from None
    except OSError as exc:
        raise FrameError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not data:
        raise FrameError(f"{path}: empty file")
    if _image_format(data[:24]) is None:
        raise FrameError(f"{path}: cannot decode image (not a PNG, JPEG, TIFF or BMP file)")
    header = _header_size(io.BytesIO(data))
    if header is None:  # nothing is decoded whose size is unknown
        problem: str | None = _truncation(data) or "cannot decode image (no image size in its header)"
        raise FrameError(f"{path}: {problem}")
    problem = frame_size_problem(*header)
    if problem is not None:
        raise FrameError(f"{path}: {problem}")
    image, warnings = _decode(data)
    problem = _truncation(data)
    if problem is not None and (image is None or data.startswith(_JPEG_SOI)):
        # Some decoder builds return a partly grey image for a cut-short JPEG: refuse it too.
        raise FrameError(f"{path}: {problem}")
    if image is None or image.size == 0:
        raise FrameError(f"{path}: cannot decode image (not an image, or corrupt or truncated)")
    if warnings:
        raise FrameError(f"{path}: corrupt image data (the decoder says: {warnings[0]}"
                         + (f"; {len(warnings) - 1} more warning(s))" if len(warnings) > 1 else ")"))
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
        grey: npt.NDArray[np.float32] = image.reshape(image.shape[:2]).astype(np.float32)
    elif channels in codes:
        grey = np.empty(image.shape[:2], dtype=np.float32)
        for r0 in range(0, grey.shape[0], _CONVERT_ROWS):  # type: ignore[misc]  # numpy stubs: np.empty of shape[:2] as 0-d
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
