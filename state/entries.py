"""The app's frame list: one entry per frame, and the snapshot of the current frame the views draw."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from blurcalib.extract.frame import FrameResult
from blurcalib.growth.ledger import GrowthEvent
from blurcalib.growth.quality import FrameFilter, QualitySettings
from blurcalib.io.record import FrameRecord
from blurcalib.sim.truth import FrameTruth
from blurcalib.target.pattern import StarPattern
from state.folder import FrameFile


@dataclass
class FrameEntry:
    """One frame in the list.

    Attributes:
        name: path relative to the dataset folder (``VIDEO#000123`` for a video's frame).
        path: the file (the video for a video's frame).
        kind: ``blurry`` or ``sharp`` (chooses the extraction settings and output folder).
        record: what is known about it (:class:`blurcalib.io.record.FrameRecord`): its status
            (``pending``, ``queued``, ``running``, ``cancelled`` or its extraction's outcome), the
            message why, its block counts and seconds of the last run.
        index: the frame's index in the video ``path`` (None for an image file).
    """

    name: str
    path: Path
    kind: str
    record: FrameRecord
    index: int | None = None

    @classmethod
    def of(cls, frame: FrameFile) -> FrameEntry:
        """A pending entry for a dataset's frame."""
        return cls(frame.name, frame.path, frame.kind, FrameRecord(frame.name), frame.index)


@dataclass(frozen=True)
class FrameView:
    """A snapshot of the current frame for drawing (arrays are shared, do not modify them).

    Attributes:
        index: the frame's index in the list.
        entry: a copy of its list entry.
        image: ``(H, W)`` grey levels, or None when unreadable.
        result: the last extraction result (None before the first run).
        live: the latest growth event of each block of the run in progress or the last run.
        filter: the quality filter of ``result`` at the current thresholds.
        selected: the selected block (index into ``result.blocks``), or None.
        truth: ground truth of a simulated frame.
        pattern: the target.
        quality: the thresholds.
    """

    index: int
    entry: FrameEntry
    image: np.ndarray | None
    result: FrameResult | None
    live: tuple[GrowthEvent, ...]
    filter: FrameFilter | None
    selected: int | None
    truth: FrameTruth | None
    pattern: StarPattern
    quality: QualitySettings
