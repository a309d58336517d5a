"""OpenCV ``FileStorage`` YAML files of cameras: writing entries and reading checked nodes.

Every camera file blurcalib writes in OpenCV's format (``camera_matrix``,
``distortion_coefficients``, ``image_width``, ``image_height`` and model keys) goes through
:func:`write_storage`, and every reader through :class:`StorageReader`, so a malformed file
fails with one message that names the file and the problem (:class:`CameraFileError`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType

import cv2
import numpy as np

from blurcalib.io.atomic import atomic_write_text

__all__ = ["CameraFileError", "StorageReader", "read_text", "write_storage"]


class CameraFileError(ValueError):
    """A camera file is missing, unreadable or malformed; the message names the file."""


def read_text(path: str | os.PathLike[str]) -> str:
    """The file's text; :class:`CameraFileError` when it is missing, unreadable or empty."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise CameraFileError(f"camera file {os.fspath(path)!r} does not exist") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise CameraFileError(f"cannot read camera file {os.fspath(path)!r}: {exc}") from exc
    if not text.strip():
        raise CameraFileError(f"camera file {os.fspath(path)!r} is empty")
    return text


def cv_message(exc: BaseException) -> str:
    """OpenCV's own message (the binding wraps cv2.error parse failures in a SystemError)."""
    return str(exc.__cause__ or exc).strip()


def write_storage(path: str | os.PathLike[str],
                  entries: Mapping[str, np.ndarray | int | float | str]) -> None:
    """Write ``entries`` (matrices, numbers, strings, in order) as OpenCV FileStorage YAML,
    atomically. Doubles are written with 17 significant digits, so they read back exactly."""
    flags = cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML
    storage = cv2.FileStorage("", flags)
    for key, value in entries.items():
        storage.write(key, value)
    atomic_write_text(path, storage.releaseAndGetString())


class StorageReader:
    """A camera file opened as OpenCV FileStorage, read key by key (a context manager).

    Raises:
        CameraFileError: missing, unreadable or not OpenCV YAML; the message names the file.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.name = os.fspath(path)
        text = read_text(path)
        try:
            self._storage = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
        except (cv2.error, SystemError) as exc:
            raise CameraFileError(f"camera file {self.name!r} is not valid OpenCV YAML: "
                                  f"{cv_message(exc)}") from exc

    def __enter__(self) -> StorageReader:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._storage.release()
        if isinstance(exc, cv2.error | SystemError):
            raise CameraFileError(f"camera file {self.name!r} is malformed: {cv_message(exc)}") from exc
        if isinstance(exc, ValueError) and not isinstance(exc, CameraFileError):
            raise CameraFileError(f"camera file {self.name!r} is invalid: {exc}") from exc

    def has(self, key: str) -> bool:
        """Whether the file holds ``key``."""
        return not self._storage.getNode(key).isNone()

    def _node(self, key: str) -> cv2.FileNode:
        node = self._storage.getNode(key)
        if node.isNone():
            raise CameraFileError(f"camera file {self.name!r} is missing key {key!r}")
        return node

    def require(self, *keys: str) -> None:
        """:class:`CameraFileError` naming the first of ``keys`` the file lacks."""
        for key in keys:
            self._node(key)

    def matrix(self, key: str) -> np.ndarray:
        """The OpenCV matrix under ``key`` (float64)."""
        node = self._node(key)
        mat = node.mat() if node.isMap() else None
        if mat is None:
            raise CameraFileError(f"camera file {self.name!r}: {key} is not an OpenCV matrix")
        return np.asarray(mat, dtype=np.float64)

    def number(self, key: str) -> float:
        """The number under ``key``."""
        node = self._node(key)
        if not (node.isInt() or node.isReal()):
            raise CameraFileError(f"camera file {self.name!r}: {key} must be a number")
        return float(node.real())

    def text(self, key: str) -> str:
        """The string under ``key``."""
        node = self._node(key)
        if not node.isString():
            raise CameraFileError(f"camera file {self.name!r}: {key} must be a string")
        return str(node.string())
