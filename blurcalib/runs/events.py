"""What a run of frames reports while it runs: typed progress events.

A runner (:func:`blurcalib.runs.folder.run_frames`) passes each event to its ``progress``
callback, from the thread that runs it: :class:`FrameStarted` and :class:`FrameGrew` come from
the in-process executor only (a worker process or a cluster task reports nothing until its frame
is done), :class:`FrameDone` for every frame the run finishes, or stops by a cancel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from blurcalib.extract.frame import FrameResult
from blurcalib.growth.ledger import GrowthEvent
from blurcalib.io.record import FrameRecord


@dataclass(frozen=True)
class FrameStarted:
    """A frame is being extracted in this process, from its own tag or, with ``neighbour``, from
    that neighbour's seed."""

    frame: str
    neighbour: str | None = None


@dataclass(frozen=True)
class FrameGrew:
    """A block of ``frame`` was judged (a growth event, for live display)."""

    frame: str
    event: GrowthEvent


@dataclass(frozen=True)
class FrameDone:
    """A frame is finished (its files are written) or, with status ``cancelled``, stopped by a
    cancel (nothing written; ``result`` holds what was grown).

    Attributes:
        record: its record.
        result: its result (the blocks grown so far for a cancelled frame).
        done: frames of the run finished so far, the skipped ones included.
        total: frames of the run.
    """

    record: FrameRecord
    result: FrameResult
    done: int
    total: int


RunEvent = FrameStarted | FrameGrew | FrameDone
"""An event of a run."""

Progress = Callable[[RunEvent], None]
"""A run's progress callback."""
