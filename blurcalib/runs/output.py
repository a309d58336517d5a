"""The resumable output folder of a run: frame names, result keys, and each frame's files.

A :class:`RunFolder` is an ``extract`` output folder (``docs/results-format.md``): each frame's
results are written under ``frames/`` as soon as it is done, with its record
(:class:`blurcalib.io.record.FrameRecord`) holding the key of what produced it, so that a later
run keeps a finished frame whose key is unchanged (:meth:`RunFolder.resumable`) and redoes the
others; the top-level tables are collected from the per-frame files.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from blurcalib.extract.frame import ExtractSettings, FrameResult
from blurcalib.extract.local_alignment import align_locally
from blurcalib.io.atomic import OutputError, claim_output_dir, remove_temporaries, write_run_manifest
from blurcalib.io.frame_files import (
    collect_results,
    read_frame_results,
    read_frame_status,
    write_frame_results,
)
from blurcalib.io.frames import frame_size_problem
from blurcalib.io.record import FINAL_STATUSES, FRAMES_TABLE, FrameRecord, write_frames_table
from blurcalib.io.results import FRAMES_DIR, FeatureFlags, FeatureTable
from blurcalib.io.sources import FrameInput, in_sequences
from blurcalib.io.text import printable_name
from blurcalib.target.pattern import StarPattern


def _located(path: Path) -> Path:
    """The absolute path a frame is named by: the file it resolves to, or, for a broken symbolic
    link or a link loop, the link itself."""
    return path.resolve() if path.exists() else path.parent.resolve() / path.name


def frame_names(paths: Sequence[Path]) -> list[str]:
    """Names recorded for frames: paths relative to their common folder (``0.png``,
    ``seq1/0.png``), with ``/`` separators, non-UTF-8 bytes escaped (:func:`printable_name`)."""
    if not paths:
        return []
    resolved = [_located(Path(p)) for p in paths]
    common = Path(os.path.commonpath([p.parent for p in resolved]))
    return [printable_name(p.relative_to(common).as_posix()) for p in resolved]


def as_frame_inputs(frames: Sequence[FrameInput | str | os.PathLike[str]]) -> list[FrameInput]:
    """Frames given as :class:`blurcalib.io.sources.FrameInput` or as image paths (named by
    :func:`frame_names`, each in the sequence of its folder, in the order given)."""
    paths = [Path(f) for f in frames if not isinstance(f, FrameInput)]
    named = iter(in_sequences([FrameInput(n, p) for p, n in zip(paths, frame_names(paths), strict=True)]))
    return [f if isinstance(f, FrameInput) else next(named) for f in frames]


def frame_source(frame: FrameInput) -> str:
    """What a frame is extracted from: its file, and a video frame's index (``walk.mp4#12``)."""
    path = printable_name(str(_located(frame.path)))
    return path if frame.index is None else f"{path}#{frame.index}"


def settings_record(settings: ExtractSettings) -> dict[str, Any]:
    """The settings that determine a frame's result, as a JSON-serialisable dict (the torch
    device aside: it changes where, not what, is computed)."""
    record = asdict(settings)
    record["deconv"].pop("device")
    return record


def _digest(doc: object) -> str:
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode("utf-8")).hexdigest()


def run_key(pattern: StarPattern, settings: ExtractSettings) -> str:
    """The part of every frame's key that the run gives: its pattern and settings."""
    return _digest({"pattern": pattern.to_yaml_text(), "settings": settings_record(settings)})


def input_key(run: str, frame: FrameInput) -> str:
    """A frame's result key: the run's key (:func:`run_key`), the input file's size and
    modification time and a video frame's index (a missing file gets a key of its own and is
    redone)."""
    try:
        st = frame.path.stat()
        stamp: object = [st.st_size, st.st_mtime_ns]
    except OSError:
        stamp = None
    return _digest([run, stamp] if frame.index is None else [run, stamp, frame.index])


def frame_sizes(frames: Sequence[FrameInput]) -> dict[str, tuple[int, int] | None]:
    """Each frame's ``(width, height)`` (None when it cannot be read), a video's read once."""
    videos: dict[Path, tuple[int, int] | None] = {}
    for f in frames:
        if f.index is not None and f.path not in videos:
            videos[f.path] = f.size()
    return {f.name: f.size() if f.index is None else videos[f.path] for f in frames}


def common_size(sizes: Sequence[tuple[int, int] | None]) -> tuple[int, int] | None:
    """The most common size of the frames that can be processed (the first seen among
    equally common ones), None if there is none."""
    known = [s for s in sizes if s is not None and frame_size_problem(*s) is None]
    return max(dict.fromkeys(known), key=known.count) if known else None


class RunFolder:
    """An ``extract`` output folder being written by a run (``docs/results-format.md``)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)

    @classmethod
    def claim(cls, path: str | os.PathLike[str], settings: ExtractSettings, sources: Mapping[str, str],
              overwrite: bool = False) -> RunFolder:
        """Take ``path`` as the output folder of a run with ``settings`` over frames named as the
        keys of ``sources`` (:func:`frame_source` of each).

        Raises:
            OutputError: the folder holds something else, or results of frames of the same names
                extracted from other files (without ``overwrite``), or cannot be written
                (:func:`blurcalib.io.atomic.claim_output_dir`).
        """
        if not overwrite:
            cls(path).check_sources(sources)
        out = claim_output_dir(path, "extract", settings_record(settings), overwrite)
        remove_temporaries(out / FRAMES_DIR)
        return cls(out)

    def check_sources(self, sources: Mapping[str, str]) -> None:
        """Refuse to replace a frame's stored result that was extracted from another file
        (another dataset whose frames have the same names): each record keeps its ``source``.

        Raises:
            OutputError: naming the frame and both files.
        """
        for name, source in sources.items():
            record = self.finished(name)
            if record is not None and record.source and record.source != source:
                raise OutputError(f"{self.path}: its frame {name} was extracted from {record.source}, not "
                                  f"{source} (another dataset with the same frame names); use --overwrite "
                                  f"to replace its results, or choose another output folder")

    def finished(self, name: str) -> FrameRecord | None:
        """The record of a finished frame (None: not finished, :func:`read_frame_status`)."""
        return read_frame_status(self.path, name)

    def resumable(self, frame: FrameInput, key: str, size: tuple[int, int] | None,
                  frame_size: tuple[int, int] | None) -> FrameRecord | None:
        """The record of ``frame`` when a run can keep it: finished with the same ``key``, a final
        status (:data:`blurcalib.io.record.FINAL_STATUSES`) and, for a run of frames of ``size``,
        of that size (``frame_size``, None when unreadable now); else None (the frame is redone)."""
        record = self.finished(frame.name)
        if (record is None or record.key != key or record.status not in FINAL_STATUSES
                or (size is not None and frame_size not in (None, size))):
            return None
        return record

    def write(self, record: FrameRecord, result: FrameResult | None = None) -> None:
        """Write a frame's record with the features, blocks and corners of ``result`` (none
        without one)."""
        if result is None:
            result = FrameResult(record.frame, record.status)
        write_frame_results(self.path, record.frame, result.features, result.blocks, result.corners, record)

    def write_table(self, records: Sequence[FrameRecord]) -> Path:
        """``frames.csv``: one row per record, by frame name
        (:data:`blurcalib.io.record.EXTRACT_COLUMNS`)."""
        return write_frames_table(self.path / FRAMES_TABLE, sorted(records, key=lambda r: r.frame))

    def collect(self, names: Sequence[str], settings: ExtractSettings) -> dict[str, Path]:
        """The top-level tables of the finished frames ``names``, in that order
        (:func:`blurcalib.io.frame_files.collect_results`), after the run manifest names the run's
        ``settings`` (:func:`blurcalib.io.atomic.write_run_manifest`)."""
        write_run_manifest(self.path, "extract", settings_record(settings))
        return collect_results(self.path, names)

    def features(self, name: str) -> FeatureTable:
        """A finished frame's features."""
        return read_frame_results(self.path, name).features

    def read_result(self, record: FrameRecord) -> FrameResult:
        """A finished frame's result as read back from its files: its features, blocks (PSFs
        included) and corners, and, when its blocks were not moved by the local alignment, the
        local alignment of its accepted blocks again (:func:`blurcalib.extract.local_alignment.align_locally`,
        from the homographies as fitted). Its seed, growth ledger and noise model are not kept
        (None); its seconds are the record's stages.

        Raises:
            ResultsFileError: the frame's files are missing or malformed.
        """
        files = read_frame_results(self.path, record.frame)
        blocks, features = files.blocks, files.features
        local = None
        aligned = bool(len(features)) and bool(np.any(features.flags & int(FeatureFlags.LOCALLY_ALIGNED)))
        accepted = blocks.accepted
        if accepted.any() and not aligned:
            local = align_locally(blocks.H[accepted], blocks.fx[accepted], blocks.fy[accepted])
        return FrameResult(record.frame, record.status, record.message, blocks, features, files.corners,
                           local=local, seconds=dict(record.stages), kind=record.kind,
                           blur_px=np.nan if record.blur_px is None else record.blur_px)


def keyed(record: FrameRecord, key: str, source: str, tried: Sequence[str] | None) -> FrameRecord:
    """``record`` with its resume ``key``, ``source`` and the neighbours ``tried`` (None: none)."""
    return replace(record, key=key, source=source,
                   neighbours_tried=None if tried is None else tuple(tried))
