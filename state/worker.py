"""The app's extraction worker: a thin adapter over the runner of :mod:`blurcalib.runs.folder`.

Frames queued by *Run frame* and *Run all* are extracted by :func:`blurcalib.runs.folder.run_frames`
with the in-process executor, one frame at a time in one worker thread: the runner passes each
block's growth event on (for the live view), stops between growth fronts when cancelled, writes
every finished frame into the app's output folder (resumable, as ``blurcalib extract`` does) and
seeds a frame whose tag is not found from an extracted neighbour in its sequence. The frames of
one kind (``sharp``, ``blurry``: their settings and their folder ``OUT/<kind>/``) run as one batch,
so that their neighbours seed each other. The state (:class:`state.app_state.AppState`) keeps
every status and result; it hands the worker its lock, so that the queue changes with the frames'
statuses at once.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from blurcalib.extract.frame import ExtractSettings
from blurcalib.io.atomic import OutputError
from blurcalib.io.sources import FrameInput
from blurcalib.runs.events import RunEvent
from blurcalib.runs.executors import InProcess
from blurcalib.runs.folder import RunSummary, run_frames
from blurcalib.target.pattern import StarPattern

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Batch:
    """What one batch runs: every frame of one kind (the neighbours), the frames to extract
    (``only``, ``redo`` those to extract again even when finished), the target, the kind's
    settings and output folder."""

    frames: list[FrameInput]
    only: list[str]
    redo: list[str]
    pattern: StarPattern
    settings: ExtractSettings
    out: Path


@dataclass(frozen=True)
class RunSettings:
    """Extraction settings per frame kind."""

    blurry: ExtractSettings = field(default_factory=ExtractSettings)
    sharp: ExtractSettings = field(default_factory=ExtractSettings.sharp)

    def for_kind(self, kind: str) -> ExtractSettings:
        """The settings of frames of ``kind``."""
        return self.sharp if kind == "sharp" else self.blurry


@dataclass(frozen=True)
class RunProgress:
    """Where the run stands.

    Attributes:
        running: the worker is busy.
        frame: the frame being extracted.
        frame_blocks: blocks decided so far in it.
        frame_expected: blocks expected in it (features whose star lies in the image).
        frames_done, frames_total: frames finished and queued in this run.
        cancelling: a cancel was requested and the worker has not stopped yet.
    """

    running: bool = False
    frame: str = ""
    frame_blocks: int = 0
    frame_expected: int = 0
    frames_done: int = 0
    frames_total: int = 0
    cancelling: bool = False

    @property
    def fraction(self) -> float:
        """Share of the run done, 0..1 (within a frame: decided over expected blocks)."""
        if self.frames_total == 0:
            return 0.0
        within = min(self.frame_blocks / self.frame_expected, 0.99) if self.frame_expected else 0.0
        return min((self.frames_done + (within if self.running else 0.0)) / self.frames_total, 1.0)


class RunTarget(Protocol):
    """What the worker asks of the state (:class:`state.app_state.AppState`)."""

    def batch(self, names: Sequence[str], redo: Collection[str]) -> Batch | None:
        """The batch of these frames (one kind), None when no dataset is open."""
        ...

    def on_run_event(self, event: RunEvent) -> None:
        """A frame started, grew or finished."""
        ...

    def on_batch_end(self, names: Sequence[str], summary: RunSummary | None, error: str) -> None:
        """A batch ended (``error``: why it could not run); frames it did not finish are pending again."""
        ...

    def on_run_end(self) -> None:
        """The worker stops (queue empty or cancelled); called with the lock held, to change fields."""
        ...

    def on_run_ended(self) -> None:
        """The worker stopped; called without the lock, to tell the subscribers."""
        ...


class ExtractionWorker:
    """The queue of frames to extract and the thread that runs it (module docstring).

    Args:
        target: the state the worker reports to.
        lock: the state's lock; queue changes are made under it.
        kind_of: a frame's kind (its batch).
    """

    def __init__(self, target: RunTarget, lock: threading.RLock, kind_of: Callable[[str], str]) -> None:
        self._target = target
        self._lock = lock
        self._kind_of = kind_of
        self._queue: deque[str] = deque()
        self._redo: set[str] = set()
        self._cancel = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        """The worker thread is extracting (or about to)."""
        with self._lock:
            return self._thread is not None

    @property
    def cancelling(self) -> bool:
        """A cancel was requested and the worker has not stopped yet."""
        with self._lock:
            return self._thread is not None and self._cancel.is_set()

    def queued(self) -> list[str]:
        """The frames waiting, in order."""
        with self._lock:
            return list(self._queue)

    def start(self, names: Sequence[str], redo: bool) -> None:
        """Queue ``names`` (extracted again when finished if ``redo``) and start the thread if idle."""
        with self._lock:
            if self._thread is None:
                self._cancel.clear()
            self._queue.extend(names)
            if redo:
                self._redo.update(names)
            if self._thread is None:
                self._thread = threading.Thread(target=self._work, name="blurcalib-run", daemon=True)
                self._thread.start()

    def cancel(self) -> list[str]:
        """Stop after the current growth front; returns the frames taken off the queue."""
        with self._lock:
            if self._thread is None:
                return []
            self._cancel.set()
            dropped = list(self._queue)
            self._queue.clear()
            self._redo.clear()
            return dropped

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the worker to stop; whether it did within ``timeout`` seconds."""
        with self._lock:
            thread = self._thread
        if thread is None:
            return True
        thread.join(timeout)
        return not thread.is_alive()

    def _next(self) -> tuple[list[str], list[str]] | None:
        """Take the next batch off the queue: the queued frames of the first one's kind, and
        those of them to redo; None (and the worker stops) when the queue is empty or cancelled."""
        with self._lock:
            if not self._queue or self._cancel.is_set():
                self._thread = None
                self._target.on_run_end()
                return None
            kind = self._kind_of(self._queue[0])
            names = [n for n in self._queue if self._kind_of(n) == kind]
            for n in names:
                self._queue.remove(n)
            redo = [n for n in names if n in self._redo]
            self._redo.difference_update(names)
            return names, redo

    def _work(self) -> None:
        self._run_batches()
        self._target.on_run_ended()

    def _run_batches(self) -> None:
        while (taken := self._next()) is not None:
            names, redo = taken
            summary, error = None, ""
            try:
                batch = self._target.batch(names, redo)
                if batch is not None:
                    summary = run_frames(batch.frames, batch.pattern, batch.out, batch.settings, InProcess(),
                                         self._target.on_run_event, overwrite=True, cancel=self._cancel,
                                         only=batch.only, redo=batch.redo)
            except OutputError as exc:
                error = str(exc)
            except Exception as exc:  # the worker must survive any failure of a batch
                log.exception("extraction of %s failed", ", ".join(names))
                error = f"{type(exc).__name__}: {exc}"
            self._target.on_batch_end(names, summary, error)
