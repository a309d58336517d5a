"""The app's state: the open dataset, per-frame status and results, thresholds, selection, runs.

Everything a view shows is read from :class:`AppState`; every change goes through its methods,
which hold one lock while they change fields and then tell the subscribers which
:class:`~state.events.Topic` changed (:mod:`state.events`, outside the lock, from the thread that
made the change: a viser callback or the run worker). Extraction runs in one worker thread
(:mod:`state.worker`, over the runner of ``blurcalib extract``) and writes every finished frame
into the dataset's output folder (``OUT/sharp/``, ``OUT/blurry/``: ``extract`` outputs, as
``blurcalib calibrate`` lays out its own); opening the dataset again shows the frames finished
with the same pattern, settings and files as done, read back from there.
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Callable, Collection, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from blurcalib.extract.frame import FrameResult
from blurcalib.growth.ledger import GrowthEvent
from blurcalib.growth.quality import FrameFilter, QualitySettings
from blurcalib.io.atomic import output_dir_problem
from blurcalib.io.frames import FrameError
from blurcalib.io.record import EXTRACTION_OUTCOMES, FrameRecord, FrameStatus
from blurcalib.io.sources import FrameInput, in_sequences
from blurcalib.runs.events import FrameDone, FrameGrew, FrameStarted, RunEvent
from blurcalib.runs.folder import RunSummary, finished_frames
from blurcalib.runs.neighbours import neighbours_to_try
from blurcalib.runs.output import frame_sizes
from blurcalib.target.pattern import PatternFileError, load_pattern
from state.blocks import expected_blocks, frame_filter
from state.entries import FrameEntry, FrameView
from state.events import Events, Notice, Topic
from state.folder import Dataset, DatasetError, FrameFile, default_output_folder, discover
from state.worker import Batch, ExtractionWorker, RunProgress, RunSettings

FRAME_KINDS = ("blurry", "sharp")
DONE_STATUSES = EXTRACTION_OUTCOMES - {FrameStatus.FAILED}
"""Frame statuses that ``run_all`` does not redo (a failed frame is retried)."""
KEPT = frozenset({FrameStatus.OK, FrameStatus.NOT_SEEDED, FrameStatus.NO_BLOCKS, FrameStatus.CANCELLED})
"""Frame statuses whose result is kept for the views (the others grew nothing)."""
UPLOADS_OUTPUT = "results"
"""The output folder of a dataset of uploads, inside the folder its pattern was uploaded to."""


class AppState:
    """The state of one app instance (shared by all browser tabs)."""

    def __init__(self, settings: RunSettings | None = None, image_cache: int = 12) -> None:
        self._lock = threading.RLock()
        self.events = Events()
        self._image_cache = image_cache
        self.settings = settings or RunSettings()
        self.dataset: Dataset | None = None
        self.frames: list[FrameEntry] = []
        self.current = -1
        self.selected: int | None = None
        self.quality = QualitySettings()
        self._images: OrderedDict[str, np.ndarray] = OrderedDict()
        self._sizes: dict[str, tuple[int, int]] = {}
        self._results: dict[str, FrameResult] = {}
        self._filters: dict[str, FrameFilter] = {}
        self._live: dict[str, dict[int, GrowthEvent]] = {}  # frame -> feature id -> last event
        self.output: Path | None = None
        self._worker = ExtractionWorker(self, self._lock, self._kind_of)
        self._progress = RunProgress()
        self._done: set[str] = set()  # frames of the run finished so far

    # ----------------------------------------------------------------------------- events
    def subscribe(self, listener: Callable[[Topic], None]) -> None:
        """See :meth:`state.events.Events.subscribe`."""
        self.events.subscribe(listener)

    def subscribe_notices(self, listener: Callable[[Notice], None]) -> None:
        """See :meth:`state.events.Events.subscribe_notices`."""
        self.events.subscribe_notices(listener)

    def notify(self, level: str, title: str, text: str) -> Notice:
        """See :meth:`state.events.Events.notify`."""
        return self.events.notify(level, title, text)

    @property
    def notices(self) -> list[Notice]:
        """The messages sent to the user so far."""
        return self.events.notices

    # ------------------------------------------------------------------------------ folders
    def load_folder(self, folder: str | os.PathLike, pattern: str | os.PathLike | None = None,
                    out: str | os.PathLike | None = None) -> bool:
        """Open a dataset folder, show the frames extracted into its output folder before as
        done (:meth:`resume`) and select its first frame.

        Args:
            folder: the dataset (a folder of frames, or a video file).
            pattern: its pattern YAML (default: ``pattern.yaml`` in the folder or its parent).
            out: the output folder (default: :func:`state.folder.default_output_folder` of the
                dataset): ``OUT/sharp/`` and ``OUT/blurry/`` hold the frames of each kind.

        On any problem (a run in progress, a missing folder, no images, a bad pattern, an
        output folder that holds something else) the previous state is kept and an error notice
        says why.

        Returns:
            Whether the folder was opened.
        """
        if self.is_running:
            self.notify("error", "Cannot open a folder", "a run is in progress: cancel it first")
            return False
        try:
            dataset = discover(folder, pattern)
        except DatasetError as exc:
            self.notify("error", "Cannot open the folder", str(exc))
            return False
        output = Path(out) if out is not None else default_output_folder(dataset.source or dataset.folder)
        problem = output_dir_problem(output, "calibrate", FRAME_KINDS)
        if problem is not None:
            self.notify("error", "Cannot open the folder", f"{problem}: choose another output folder")
            return False
        self._open(dataset, output)
        for warning in dataset.warnings:
            self.notify("warning", "Ground truth not used", warning)
        resumed = self.resume()
        done = f", {resumed} extracted before (in {output})" if resumed else ""
        self.notify("info", "Folder opened",
                    f"{dataset.folder}: {len(dataset.frames)} frames, pattern {dataset.pattern_path.name}"
                    + (", with ground truth" if dataset.truth is not None else "") + done)
        self.events.emit(Topic.FOLDER, Topic.FRAMES, Topic.RUN, Topic.RESULT, Topic.FILTER)
        self.select_frame(0)
        return True

    def _open(self, dataset: Dataset, output: Path) -> None:
        """Make ``dataset`` the open one, every frame pending, results in ``output``."""
        with self._lock:
            self.dataset = dataset
            self.output = output
            self.frames = [FrameEntry.of(f) for f in dataset.frames]
            self.current = -1
            self.selected = None
            self._images.clear()
            self._sizes.clear()
            self._clear_results()

    def _clear_results(self) -> None:
        with self._lock:
            self._results.clear()
            self._filters.clear()
            self._live.clear()
            self._progress = RunProgress()

    def resume(self) -> int:
        """Show the frames finished in the output folder with the current pattern, settings and
        files (:func:`blurcalib.runs.folder.finished_frames`) as done, their results read back
        (no growth ledger: the views draw their blocks, PSFs and features from the files);
        returns how many."""
        with self._lock:
            dataset, output = self.dataset, self.output
            kinds = {kind: self._inputs(kind) for kind in FRAME_KINDS}
        if dataset is None or output is None:
            return 0
        found = [done for kind, frames in kinds.items() if frames for done in
                 finished_frames(frames, dataset.pattern, output / kind, self.settings.for_kind(kind))]
        names = {record.frame for record, _ in found}
        sizes = frame_sizes([f for frames in kinds.values() for f in frames if f.name in names])
        with self._lock:
            for record, result in found:
                entry = self._entry(record.frame)
                entry.record = record
                if (size := sizes[record.frame]) is not None:
                    self._sizes[record.frame] = size
                    self._keep(entry, result)
        return len(found)

    def _inputs(self, kind: str) -> list[FrameInput]:
        """The frames of ``kind`` as the runner takes them: each in the sequence of its folder, or
        of its video (:func:`blurcalib.io.sources.in_sequences`)."""
        with self._lock:
            return in_sequences([FrameInput(e.name, e.path, e.index) for e in self.frames if e.kind == kind])

    def set_pattern(self, path: str | os.PathLike) -> bool:
        """Extract with the pattern YAML ``path`` (an upload) from now on.

        With a dataset open, its pattern is replaced and every frame's result is cleared (the
        results belong to the old target); the ground truth is kept only when the new pattern
        equals the dataset's. With none open, an empty dataset of uploads is started, to which
        :meth:`add_frame` adds frames. A run in progress or a bad YAML gives an error notice and
        keeps the previous state.

        Returns:
            Whether the pattern is now in use.
        """
        if self.is_running:
            self.notify("error", "Cannot change the pattern", "a run is in progress: cancel it first")
            return False
        path = Path(path)
        try:
            pattern = load_pattern(path)
        except PatternFileError as exc:
            self.notify("error", "Pattern refused", str(exc))
            return False
        with self._lock:
            old = self.dataset
            if old is None:
                dataset = Dataset(path.parent, path, pattern, (), None)
            else:
                dataset = replace(old, pattern_path=path, pattern=pattern,
                                  truth=old.truth if pattern == old.pattern else None)
            dropped_truth = old is not None and old.truth is not None and dataset.truth is None
            self.dataset = dataset
            if old is None:
                self.output = path.parent / UPLOADS_OUTPUT
            self.frames = [replace(f, record=FrameRecord(f.name)) for f in self.frames]
            self.selected = None
            self._clear_results()
        if dropped_truth:
            self.notify("warning", "Ground truth not used", f"{path.name} is not the pattern the dataset was "
                                                            "simulated with")
        then = "frames to extract again" if self.frames else "upload frames next"
        self.notify("info", "Pattern in use", f"{path.name}: {pattern.squares_x} x {pattern.squares_y} "
                                              f"squares, {pattern.num_features} features; {then}")
        self.events.emit(Topic.FOLDER, Topic.FRAMES, Topic.RUN, Topic.RESULT, Topic.FILTER, Topic.CURRENT,
                   Topic.SELECTION)
        return True

    def add_frame(self, path: str | os.PathLike, name: str, kind: str = "blurry") -> int:
        """Add a frame file (an upload) to the open dataset and select it; returns its index.

        Raises:
            DatasetError: no dataset is open (there is no pattern to extract with).
        """
        with self._lock:
            if self.dataset is None:
                raise DatasetError("open a folder or upload a pattern YAML first: an uploaded frame "
                                   "needs its pattern")
            taken = {f.name for f in self.frames}
            unique, n = name, 1
            while unique in taken:
                n += 1
                stem = Path(name)
                unique = str(stem.with_name(f"{stem.stem}-{n}{stem.suffix}"))
            self.frames.append(FrameEntry(unique, Path(path), kind, FrameRecord(unique)))
            self.dataset = replace(self.dataset,
                                   frames=(*self.dataset.frames, FrameFile(unique, Path(path), kind)))
            index = len(self.frames) - 1
        self.events.emit(Topic.FRAMES)
        self.select_frame(index)
        return index

    # ------------------------------------------------------------------------------- frames
    def image(self, name: str) -> np.ndarray:
        """A frame's grey levels (cached).

        Raises:
            FrameError: the file cannot be read (the message names it).
            KeyError: no such frame.
        """
        with self._lock:
            cached = self._images.get(name)
            if cached is not None:
                self._images.move_to_end(name)
                return cached
            entry = self._entry(name)
        image = FrameInput(name, entry.path, entry.index).load()
        with self._lock:
            self._images[name] = image
            self._sizes[name] = (image.shape[1], image.shape[0])
            while len(self._images) > self._image_cache:
                self._images.popitem(last=False)
        return image

    def _entry(self, name: str) -> FrameEntry:
        for entry in self.frames:
            if entry.name == name:
                return entry
        raise KeyError(name)

    def _kind_of(self, name: str) -> str:
        with self._lock:
            return self._entry(name).kind

    def _set_status(self, name: str, status: FrameStatus, message: str = "") -> None:
        with self._lock:
            entry = self._entry(name)
            entry.record = replace(entry.record, status=status, message=message)

    def select_frame(self, index: int) -> bool:
        """Make frame ``index`` the current one and load its image.

        An unreadable frame becomes current with status ``unreadable`` and an error notice.
        """
        with self._lock:
            if not 0 <= index < len(self.frames):
                return False
            self.current = index
            self.selected = None
            entry = self.frames[index]
        try:
            self.image(entry.name)
        except FrameError as exc:
            self._set_status(entry.name, FrameStatus.UNREADABLE, str(exc))
            self.notify("error", "Unreadable frame", str(exc))
            self.events.emit(Topic.FRAMES)
        self.events.emit(Topic.CURRENT, Topic.SELECTION)
        return True

    def set_kind(self, index: int, kind: str) -> None:
        """Set whether frame ``index`` is extracted as a ``sharp`` or a ``blurry`` frame."""
        if kind not in FRAME_KINDS:
            raise ValueError(f"kind must be one of {FRAME_KINDS}, got {kind!r}")
        with self._lock:
            entry = self.frames[index]
            entry.kind = kind
            result = self._results.get(entry.name)
            if result is not None:
                self._keep(entry, result)
        self.events.emit(Topic.FRAMES, Topic.FILTER)

    def entries(self) -> list[FrameEntry]:
        """Copies of the frame list's entries."""
        with self._lock:
            return [replace(f) for f in self.frames]

    def view(self) -> FrameView | None:
        """A snapshot of the current frame (None when no frame is open)."""
        with self._lock:
            if self.dataset is None or not 0 <= self.current < len(self.frames):
                return None
            name = self.frames[self.current].name
        try:
            image = self.image(name)
        except (FrameError, KeyError):
            image = None
        with self._lock:
            if self.dataset is None or not 0 <= self.current < len(self.frames):
                return None
            entry = self.frames[self.current]
            if entry.name != name:
                image = self._images.get(entry.name)
            truth = None
            if self.dataset.truth is not None:
                truth = next((f for f in self.dataset.truth.frames if f.name == entry.name), None)
            return FrameView(self.current, replace(entry), image, self._results.get(entry.name),
                             tuple(self._live.get(entry.name, {}).values()), self._filters.get(entry.name),
                             self.selected, truth, self.dataset.pattern, self.quality)

    def results(self) -> dict[str, tuple[FrameResult, FrameFilter | None, tuple[int, int]]]:
        """Every finished frame's result, filter and image size ``(width, height)``."""
        with self._lock:
            return {name: (r, self._filters.get(name), self._sizes[name])
                    for name, r in self._results.items() if name in self._sizes}

    # --------------------------------------------------------------------------------- runs
    @property
    def is_running(self) -> bool:
        """The worker is extracting (or about to)."""
        return self._worker.running

    def progress(self) -> RunProgress:
        """The run's progress."""
        with self._lock:
            return self._progress

    def run_frame(self, index: int | None = None) -> bool:
        """Extract frame ``index`` (default the current one) in the worker thread, again if it
        was extracted before."""
        with self._lock:
            index = self.current if index is None else index
            if not 0 <= index < len(self.frames):
                return False
            name = self.frames[index].name
        return self._start([name], redo=True)

    def run_all(self) -> bool:
        """Extract every frame not extracted yet (failed frames again), in list order, and seed
        a frame whose tag was not found from a neighbour extracted since
        (:func:`blurcalib.runs.neighbours.neighbours_to_try`)."""
        with self._lock:
            names = [f.name for f in self.frames
                     if f.name not in self._results and f.record.status not in DONE_STATUSES]
            records, coming = {f.name: f.record for f in self.frames}, set(names)
            retry = set().union(*(neighbours_to_try(self._inputs(k), records, coming) for k in FRAME_KINDS))
            names = [f.name for f in self.frames if f.name in retry or f.name in coming]
        if not names:
            self.notify("info", "Nothing to run", "every frame has been extracted")
            return False
        return self._start(names, redo=False)

    def _start(self, names: Sequence[str], redo: bool) -> bool:
        with self._lock:
            if self.dataset is None or self.output is None:
                return False
            waiting = set(self._worker.queued())
            new = [n for n in names if n not in waiting and n != self._progress.frame]
            if not new or self._worker.cancelling:
                return False
            if not self._worker.running:
                self._done.clear()
                self._progress = RunProgress(running=True, frames_total=len(new))
            else:
                self._progress = replace(self._progress, frames_total=self._progress.frames_total + len(new))
            for n in new:
                self._set_status(n, FrameStatus.QUEUED)
            self._worker.start(new, redo)
        self.events.emit(Topic.FRAMES, Topic.RUN)
        return True

    def cancel(self) -> None:
        """Stop the run after the current growth front; queued frames go back to pending."""
        with self._lock:
            if not self._worker.running:
                return
            for n in self._worker.cancel():
                self._set_status(n, FrameStatus.PENDING)
            self._progress = replace(self._progress, cancelling=True)
        self.events.emit(Topic.FRAMES, Topic.RUN)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the run to end; returns whether it did within ``timeout`` seconds."""
        return self._worker.wait(timeout)

    # ------------------------------------------------------------------- the worker's reports
    def batch(self, names: Sequence[str], redo: Collection[str]) -> Batch | None:
        """The worker's batch of ``names`` (frames of one kind): see :class:`state.worker.Batch`."""
        with self._lock:
            if self.dataset is None or self.output is None:
                return None
            kind = self._entry(names[0]).kind
            pattern, settings, output = self.dataset.pattern, self.settings.for_kind(kind), self.output
        return Batch(self._inputs(kind), list(names), list(redo), pattern, settings, output / kind)

    def on_run_event(self, event: RunEvent) -> None:
        """A frame of the worker's batch started, grew or finished."""
        if isinstance(event, FrameStarted):
            self._started(event.frame)
        elif isinstance(event, FrameGrew):
            self._grew(event.frame, event.event)
        elif isinstance(event, FrameDone):
            self._finish(event.record, event.result)

    def on_batch_end(self, names: Sequence[str], summary: RunSummary | None, error: str) -> None:
        """The worker's batch ended: frames it skipped as finished before are read back, the
        frames it did not reach are pending again (failed, with ``error``, when it could not run)."""
        if summary is not None and summary.skipped:
            self.resume()
        with self._lock:
            for n in names:
                if self._entry(n).record.status in (FrameStatus.QUEUED, FrameStatus.RUNNING):
                    self._set_status(n, FrameStatus.FAILED if error else FrameStatus.PENDING, error)
        if error:
            self.notify("error", "Cannot extract", error)
        self.events.emit(Topic.FRAMES, Topic.RESULT, Topic.FILTER, Topic.RUN)

    def on_run_end(self) -> None:
        """The worker stops (called with the lock held)."""
        self._progress = replace(self._progress, running=False, cancelling=False, frame="")

    def on_run_ended(self) -> None:
        """The worker stopped."""
        self.events.emit(Topic.RUN)

    def _size(self, name: str) -> tuple[int, int] | None:
        """A frame's ``(width, height)``, read from its file's header when not known yet."""
        with self._lock:
            if name in self._sizes:
                return self._sizes[name]
            entry = self._entry(name)
        size = FrameInput(name, entry.path, entry.index).size()
        if size is not None:
            with self._lock:
                self._sizes[name] = size
        return size

    def _started(self, name: str) -> None:
        self._size(name)
        with self._lock:
            self._set_status(name, FrameStatus.RUNNING)
            self._live[name] = {}
            self._progress = replace(self._progress, frame=name, frame_blocks=0, frame_expected=0)
        self.events.emit(Topic.FRAMES, Topic.RUN, Topic.LIVE)

    def _grew(self, name: str, event: GrowthEvent) -> None:
        with self._lock:
            events = self._live.setdefault(name, {})
            events[event.feature_id] = event  # a block judged again (retried, re-checked) counts once
            expected = self._progress.frame_expected
            if not expected and name in self._sizes:
                expected = expected_blocks(self.dataset.pattern, event, self._sizes[name])
            self._progress = replace(self._progress, frame_blocks=len(events),
                                     frame_expected=max(expected, len(events)))
        self.events.emit(Topic.LIVE, Topic.RUN)

    def _keep(self, entry: FrameEntry, result: FrameResult) -> None:
        """Keep a frame's result and its filter at the current thresholds (under the lock)."""
        self._results[entry.name] = result
        flt = frame_filter(result, self._sizes[entry.name], self.quality, entry.kind)
        if flt is None:
            self._filters.pop(entry.name, None)
        else:
            self._filters[entry.name] = flt

    def _finish(self, record: FrameRecord, result: FrameResult) -> None:
        name, status = record.frame, record.status
        size = self._size(name)
        with self._lock:
            entry = self._entry(name)
            entry.record = record
            if status in KEPT and size is not None:
                self._keep(entry, result)
            if entry.name == self._current_name():
                self.selected = None
            self._done.add(name)
            self._progress = replace(self._progress, frames_done=len(self._done), frame_blocks=0,
                                     frame_expected=0)
        if status not in (FrameStatus.OK, FrameStatus.CANCELLED):
            self.notify("warning" if status is not FrameStatus.FAILED else "error",
                        f"{name}: {status.value.replace('_', ' ')}", record.message)
        self.events.emit(Topic.FRAMES, Topic.RESULT, Topic.FILTER, Topic.SELECTION, Topic.RUN)

    def _current_name(self) -> str | None:
        return self.frames[self.current].name if 0 <= self.current < len(self.frames) else None

    # ----------------------------------------------------------------------- tuning, selection
    def refilter(self, tau_be: float | None = None, tau_loss: float | None = None,
                 min_sigma_major: float | None = None) -> QualitySettings:
        """Set thresholds (None keeps one) and re-filter every finished frame from its figures."""
        with self._lock:
            changes = {k: float(v) for k, v in (("tau_be", tau_be), ("tau_loss", tau_loss),
                                                ("min_sigma_major", min_sigma_major)) if v is not None}
            self.quality = replace(self.quality, **changes)
            for name, result in self._results.items():
                self._keep(self._entry(name), result)
            quality = self.quality
        self.events.emit(Topic.FILTER)
        return quality

    def select_block(self, index: int | None) -> bool:
        """Select block ``index`` of the current frame's result (None clears the selection)."""
        with self._lock:
            name = self._current_name()
            result = self._results.get(name) if name is not None else None
            if index is not None and (result is None or not 0 <= index < len(result.blocks)):
                return False
            if index == self.selected:
                return True
            self.selected = index
        self.events.emit(Topic.SELECTION)
        return True
