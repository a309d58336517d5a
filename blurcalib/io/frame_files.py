"""Per-frame result files of resumable runs (``docs/results-format.md``, "Per-frame files and
resuming").

:func:`write_frame_results` writes one frame's rows of ``features.csv``, ``blocks.csv``,
``psfs.npz`` and ``corners.csv`` under ``frames/``, with its status record (the row of
:meth:`blurcalib.io.record.FrameRecord.to_row`) and, last, a ``done`` marker
(:func:`frame_result_paths` names the files); :func:`read_frame_results` reads them back and
:func:`collect_results` concatenates the frames of a run into the top-level files. Every file is
written atomically.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from blurcalib.io.atomic import (
    atomic_write_csv,
    atomic_write_json,
    atomic_write_text,
    ensure_writable_dir,
    read_csv_columns,
)
from blurcalib.io.record import FrameRecord
from blurcalib.io.results import (
    BLOCKS_FILE,
    CORNER_COLUMNS,
    CORNERS_FILE,
    FEATURES_FILE,
    FRAMES_DIR,
    PSFS_FILE,
    BlockTable,
    FeatureObservation,
    FeatureTable,
    ResultsFileError,
    as_feature_table,
    read_block_files,
    read_feature_table,
    write_blocks,
    write_features,
    write_results,
)

MAX_STEM_CHARS = 100
"""Longest readable part of a per-frame file stem (:func:`frame_stem`)."""


@dataclass(frozen=True)
class FramePaths:
    """The per-frame files of one frame under ``folder/frames/`` (``<stem>`` is
    :func:`frame_stem` of the frame name); the one place that knows their names.

    Attributes:
        features: ``<stem>.features.csv``, the frame's rows of ``features.csv``.
        blocks: ``<stem>.blocks.csv``, its rows of ``blocks.csv``.
        psfs: ``<stem>.psfs.npz``, its rows of ``psfs.npz``.
        corners: ``<stem>.corners.csv``, its rows of ``corners.csv``.
        status: ``<stem>.status.json``, its status record: the row of ``frames.csv`` plus
            the key of what produced the result.
        done: ``<stem>.done``, the marker holding the frame name, written last.
    """

    features: Path
    blocks: Path
    psfs: Path
    corners: Path
    status: Path
    done: Path


def frame_stem(frame_name: str) -> str:
    """File-name stem of a frame's per-frame files; different frame names get different stems.

    The name, extension kept (``0.png`` and ``0.jpg`` differ), with folders joined by ``__``,
    characters outside ``[A-Za-z0-9._-]`` and a leading ``.`` replaced by ``_``. Where that
    changes the name, or the name has upper-case letters (a case-insensitive file system
    would fold them) or more than :data:`MAX_STEM_CHARS` characters, the readable part is cut
    to that length and ``~`` plus 12 hex digits of the name's SHA-256 are appended
    (``seq/img 1.png`` -> ``seq__img_1.png~<hash>``). ``~`` is never kept from a name, so a
    stem without it is the frame name itself and a stem with it is unique to one name.
    """
    parts = [p for p in re.split(r"[\\/]+", frame_name) if p]
    if not parts:
        raise ValueError(f"frame name {frame_name!r} has no file-name part")
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", "__".join(parts))
    if safe.startswith("."):
        safe = "_" + safe[1:]
    if safe == frame_name and safe == safe.lower() and len(safe) <= MAX_STEM_CHARS:
        return safe
    digest = hashlib.sha256(frame_name.encode("utf-8", "surrogatepass")).hexdigest()[:12]
    return f"{safe[:MAX_STEM_CHARS]}~{digest}"


def frame_result_paths(folder: str | os.PathLike[str], frame_name: str) -> FramePaths:
    """Paths of a frame's per-frame files under ``folder/frames/`` (see :class:`FramePaths`)."""
    base = f"{Path(folder) / FRAMES_DIR / frame_stem(frame_name)}."
    return FramePaths(features=Path(base + FEATURES_FILE), blocks=Path(base + BLOCKS_FILE),
                      psfs=Path(base + PSFS_FILE), corners=Path(base + CORNERS_FILE),
                      status=Path(base + "status.json"), done=Path(base + "done"))


def write_frame_results(folder: str | os.PathLike[str], frame_name: str,
                        features: Sequence[FeatureObservation] | FeatureTable,
                        blocks: BlockTable,
                        corners: Sequence[Sequence[object]], record: FrameRecord) -> FramePaths:
    """Write one frame's results under ``folder/frames/`` for resumable runs.

    The ``done`` marker is removed first and written last (holding the frame name), after the
    features, blocks, PSFs, corners (rows of :data:`CORNER_COLUMNS`) and the status record
    (``record``'s row, :meth:`blurcalib.io.record.FrameRecord.to_row`, as JSON); a frame counts
    as finished only once its marker exists, so an interrupted write is redone on resume.

    Raises:
        ValueError: a row or the status record belongs to another frame.
        OutputError: the folder cannot be written.
    """
    ft = as_feature_table(features)
    others = [("feature", str(f)) for f in ft.frame[ft.frame != frame_name][:1]]
    others += [("block", str(f)) for f in blocks.frame[blocks.frame != frame_name][:1]]
    others += [("corner", str(r[0])) for r in corners if r[0] != frame_name][:1]
    if record.frame != frame_name:
        others.append(("status", record.frame))
    if others:
        kind, other = others[0]
        raise ValueError(f"{kind} row of frame {other!r} passed for frame {frame_name!r}")
    ensure_writable_dir(Path(folder) / FRAMES_DIR)
    paths = frame_result_paths(folder, frame_name)
    paths.done.unlink(missing_ok=True)
    write_features(paths.features, ft)
    write_blocks(paths.blocks, paths.psfs, blocks)
    atomic_write_csv(paths.corners, CORNER_COLUMNS, corners)
    atomic_write_json(paths.status, record.to_row())
    atomic_write_text(paths.done, frame_name + "\n")
    return paths


def read_frame_status(folder: str | os.PathLike[str], frame_name: str) -> FrameRecord | None:
    """The record of a finished frame, or None when the frame is not finished: no ``done``
    marker, or a marker or status record that is unreadable, not a record or names another frame
    (such a frame is simply redone)."""
    paths = frame_result_paths(folder, frame_name)
    try:
        marker = paths.done.read_text(encoding="utf-8")
        row = json.loads(paths.status.read_text(encoding="utf-8"))
        record = FrameRecord.from_row(row) if isinstance(row, dict) else None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if marker != frame_name + "\n" or record is None or record.frame != frame_name:
        return None
    return record


@dataclass(frozen=True)
class FrameFiles:
    """One frame's results as read back from its per-frame files: its ``features``, its
    ``blocks`` (PSFs included) and its ``corners`` (rows of :data:`CORNER_COLUMNS`, typed as
    :func:`blurcalib.extract.frame.corner_rows` makes them)."""

    features: FeatureTable
    blocks: BlockTable
    corners: list[list[Any]]


def read_corner_rows(path: Path) -> list[list[Any]]:
    """The rows of a ``corners.csv``: frame, corner ``(cx2, cy2)`` (ints), ``X``, ``Y`` (m), ``x``,
    ``y`` (px) and the blocks sharing it.

    Raises:
        ResultsFileError: a missing or malformed file.
    """
    cols, _ = read_csv_columns(path, CORNER_COLUMNS, ResultsFileError, "results file")
    try:
        return [[f, int(cx), int(cy), float(X), float(Y), float(x), float(y), int(n)]
                for f, cx, cy, X, Y, x, y, n in zip(*(cols[c] for c in CORNER_COLUMNS), strict=True)]
    except ValueError as exc:
        raise ResultsFileError(f"{path}: {exc}") from None


def read_frame_results(folder: str | os.PathLike[str], frame_name: str) -> FrameFiles:
    """A finished frame's features, blocks and corners from its per-frame files.

    Raises:
        ResultsFileError: the frame is not finished, or a per-frame file is missing or malformed.
    """
    p = frame_result_paths(folder, frame_name)
    if not p.done.is_file():
        raise ResultsFileError(f"{p.done}: frame {frame_name!r} has no finished per-frame results")
    return FrameFiles(read_feature_table(p.features), read_block_files(p.blocks, p.psfs),
                      read_corner_rows(p.corners))


def collect_results(folder: str | os.PathLike[str], frame_names: Sequence[str]) -> dict[str, Path]:
    """Concatenate the per-frame files of ``frame_names``, in that order, into the top-level
    ``features.csv``, ``blocks.csv``, ``psfs.npz`` and ``corners.csv`` of ``folder``.

    Exactly these frames are collected: per-frame files of other frames (left by an earlier
    run) stay under ``frames/`` but are not in the tables.

    Returns:
        The paths written by :func:`write_results`, plus ``"corners"``.
    Raises:
        ResultsFileError: a frame is not finished, or a per-frame file is missing or malformed.
    """
    paths = [frame_result_paths(folder, name) for name in frame_names]
    for name, p in zip(frame_names, paths, strict=True):
        if not p.done.is_file():
            raise ResultsFileError(f"{p.done}: frame {name!r} has no finished per-frame results")
    features = FeatureTable.concat([read_feature_table(p.features) for p in paths])
    blocks = BlockTable.concat([read_block_files(p.blocks, p.psfs) for p in paths])
    corners: list[tuple[str, ...]] = []
    for p in paths:
        cols, _ = read_csv_columns(p.corners, CORNER_COLUMNS, ResultsFileError, "results file")
        corners += zip(*(cols[c] for c in CORNER_COLUMNS), strict=True)
    outputs = write_results(folder, features, blocks)
    outputs["corners"] = atomic_write_csv(Path(folder) / CORNERS_FILE, CORNER_COLUMNS, corners)
    return outputs
