"""Opening a user's input file: a regular file only, of bounded size, checked before it is read.

A path that names a device (``/dev/zero`` behind a ``frame.png`` or ``features.bin`` link), a
FIFO (which blocks its reader until a writer comes), a socket or a folder is refused before a
byte is read; so is a file larger than its reader accepts. The file is opened without blocking
and checked on the open descriptor, so that what is checked is what is read.
"""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Iterator
from typing import BinaryIO

__all__ = ["InputFileError", "byte_size", "open_input", "read_input"]


class InputFileError(ValueError):
    """An input file that is not a regular file, or is too large; the message names the file."""


def byte_size(n: int) -> str:
    """A size in bytes for a message: ``"812 bytes"``, ``"3.2 MB"``, ``"1.5 GB"`` (powers of 1000)."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} bytes"


def _kind(mode: int) -> str:
    """What a file that is not a regular file is, for a message."""
    kinds = ((stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device"),
             (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
             (stat.S_ISSOCK, "a socket"))
    return next((name for test, name in kinds if test(mode)), "not a regular file")


@contextlib.contextmanager
def open_input(path: str | os.PathLike[str], max_bytes: int | None = None,
               what: str = "file") -> Iterator[BinaryIO]:
    """Open ``path`` for reading when it is a regular file of at most ``max_bytes`` bytes.

    Symbolic links are followed; the checks apply to the file they lead to.

    Args:
        path: the file.
        max_bytes: the largest size accepted (None: any).
        what: what the file is, for the message about its size (``"frame"``, ``"results file"``).
    Yields:
        The open binary file.
    Raises:
        InputFileError: not a regular file (a folder, a device, a FIFO, a socket), or larger than
            ``max_bytes``.
        OSError: the file cannot be opened (missing, no permission), as ``os.open`` raises it.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise InputFileError(f"{os.fspath(path)}: is {_kind(info.st_mode)}, not a regular file")
        if max_bytes is not None and info.st_size > max_bytes:
            raise InputFileError(f"{os.fspath(path)}: {byte_size(info.st_size)}, more than the "
                                 f"{byte_size(max_bytes)} a {what} may have")
        os.set_blocking(fd, True)
        handle = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    with handle:
        yield handle


def read_input(path: str | os.PathLike[str], max_bytes: int | None = None, what: str = "file") -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (:func:`open_input`; None: any size);
    a file that grows past the limit while it is read is refused too.

    Raises:
        InputFileError: see :func:`open_input`.
        OSError: the file cannot be opened or read.
    """
    with open_input(path, max_bytes, what) as handle:
        data = handle.read() if max_bytes is None else handle.read(max_bytes + 1)
    if max_bytes is not None and len(data) > max_bytes:
        raise InputFileError(f"{os.fspath(path)}: more than the {byte_size(max_bytes)} a {what} may have")
    return data
