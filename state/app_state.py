"""The app's state: the open dataset, per-frame status and results, thresholds, selection, runs.

Everything a view shows is read from :class:`AppState`; every change goes through its methods,
which hold one lock while they change fields and then tell the subscribers which
:class:`~state.events.Topic` changed (:mod:`state.events`, outside the lock, from the thread that
made the change: a viser callback or the run worker). Extraction runs in one worker thread, frame
after frame from a queue, and stops between growth fronts when cancelled; the worker stays here
because each of its status changes must be atomic with the store's fields.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np

from blurcalib.extract.frame import ExtractSettings, FrameResult, FrameStatus, extract_frame
from blurcalib.geometry.homography import homography_centre
from blurcalib.growth.ledger import GrowthEvent
from blurcalib.growth.quality import FrameFilter, QualitySettings, filter_frame
from blurcalib.growth.seed import block_homography
from blurcalib.io.frames import FrameError
from blurcalib.io.results import BlockStatus
from blurcalib.io.sources import FrameInput
from blurcalib.sim.truth import FrameTruth
from blurcalib.target.pattern import PatternFileError, StarPattern, load_pattern
from state.events import Events, Notice, Topic
from state.folder import Dataset, DatasetError, FrameFile, discover

log = logging.getLogger(__name__)

FRAME_KINDS = ("blurry", "sharp")
DONE_STATUSES = frozenset(s.value for s in FrameStatus) - {FrameStatus.FAILED.value}
"""Frame statuses that ``run_all`` does not redo (a failed frame is retried)."""


@dataclass
class FrameEntry:
    """One frame in the list.

    Attributes:
        name: path relative to the dataset folder (``VIDEO#000123`` for a video's frame).
        path: the file (the video for a video's frame).
        kind: ``blurry`` or ``sharp`` (chooses the extraction settings).
        status: ``pending``, ``queued``, ``running``, ``cancelled`` or a
            :class:`blurcalib.extract.frame.FrameStatus` value.
        message: why, when the status is not ``ok``.
        blocks, accepted: attempted and accepted blocks of the last run.
        seconds: time of the last run.
        index: the frame's index in the video ``path`` (None for an image file).
    """

    name: str
    path: Path
    kind: str
    status: str = "pending"
    message: str = ""
    blocks: int = 0
    accepted: int = 0
    seconds: float = 0.0
    index: int | None = None


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


@dataclass(frozen=True)
class FilterCounts:
    """Blocks of one frame by outcome of the quality filter."""

    kept: int
    removed_be: int
    removed_loss: int
    disconnected: int
    rejected: int

    @property
    def removed(self) -> int:
        """Blocks the growth accepted and the filter removed."""
        return self.removed_be + self.removed_loss + self.disconnected


def filter_counts(flt: FrameFilter) -> FilterCounts:
    """Counts of a frame's filter result."""
    counts = flt.counts()
    removed_be = counts.get(BlockStatus.FILTERED_BOUNDARY_ENERGY.value, 0)
    removed_loss = counts.get(BlockStatus.FILTERED_LOSS.value, 0)
    disconnected = counts.get(BlockStatus.DISCONNECTED.value, 0)
    kept = int(flt.kept.sum())
    rejected = len(flt.status) - kept - removed_be - removed_loss - disconnected
    return FilterCounts(kept, removed_be, removed_loss, disconnected, rejected)


def frame_filter(result: FrameResult, image_size: tuple[int, int], quality: QualitySettings,
                 kind: str = "blurry") -> FrameFilter | None:
    """The quality filter of a result's blocks (None when it has none).

    The σ_major pre-filter applies to blurry frames only: a sharp frame has little blur by design.
    """
    if not len(result.blocks):
        return None
    if kind == "sharp":
        quality = replace(quality, min_sigma_major=0.0)
    return filter_frame(result.blocks, image_size, quality)


def expected_blocks(pattern: StarPattern, event: GrowthEvent, image_size: tuple[int, int]) -> int:
    """Features whose star centre, predicted from one block's homography, lies in the image."""
    B = block_homography(np.eye(3), np.array([event.fx]), np.array([event.fy]))[0]
    H_feature = event.H @ np.linalg.inv(B)
    f = pattern.features
    centres = homography_centre(block_homography(H_feature, f[:, 0], f[:, 1]))
    w, h = image_size
    inside = (centres[:, 0] >= 0) & (centres[:, 0] <= w - 1) & (centres[:, 1] >= 0) \
        & (centres[:, 1] <= h - 1)
    return int(inside.sum())


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
        self._queue: deque[str] = deque()
        self._cancel = threading.Event()
        self._worker: threading.Thread | None = None
        self._progress = RunProgress()

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
    def load_folder(self, folder: str | os.PathLike, pattern: str | os.PathLike | None = None) -> bool:
        """Open a dataset folder and select its first frame.

        On any problem (a run in progress, a missing folder, no images, a bad pattern) the
        previous state is kept and an error notice says why.

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
        with self._lock:
            self.dataset = dataset
            self.frames = [FrameEntry(f.name, f.path, f.kind, index=f.index) for f in dataset.frames]
            self.current = -1
            self.selected = None
            self._images.clear()
            self._sizes.clear()
            self._results.clear()
            self._filters.clear()
            self._live.clear()
            self._progress = RunProgress()
        for warning in dataset.warnings:
            self.notify("warning", "Ground truth not used", warning)
        self.notify("info", "Folder opened",
                    f"{dataset.folder}: {len(dataset.frames)} frames, pattern {dataset.pattern_path.name}"
                    + (", with ground truth" if dataset.truth is not None else ""))
        self.events.emit(Topic.FOLDER, Topic.FRAMES, Topic.RUN)
        self.select_frame(0)
        return True

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
            self.frames = [FrameEntry(f.name, f.path, f.kind, index=f.index) for f in self.frames]
            self.selected = None
            self._results.clear()
            self._filters.clear()
            self._live.clear()
            self._progress = RunProgress()
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
            self.frames.append(FrameEntry(unique, Path(path), kind))
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

    def _set_status(self, name: str, status: str, message: str = "") -> None:
        with self._lock:
            entry = self._entry(name)
            entry.status, entry.message = status, message

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
            self._set_status(entry.name, FrameStatus.UNREADABLE.value, str(exc))
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
                flt = frame_filter(result, self._sizes[entry.name], self.quality, kind)
                if flt is not None:
                    self._filters[entry.name] = flt
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
        with self._lock:
            return self._worker is not None

    def progress(self) -> RunProgress:
        """The run's progress."""
        with self._lock:
            return self._progress

    def run_frame(self, index: int | None = None) -> bool:
        """Extract frame ``index`` (default the current one) in the worker thread."""
        with self._lock:
            index = self.current if index is None else index
            if not 0 <= index < len(self.frames):
                return False
            name = self.frames[index].name
        return self._start([name])

    def run_all(self) -> bool:
        """Extract every frame not extracted yet (failed frames again), in list order."""
        with self._lock:
            names = [f.name for f in self.frames
                     if f.name not in self._results and f.status not in DONE_STATUSES]
        if not names:
            self.notify("info", "Nothing to run", "every frame has been extracted")
            return False
        return self._start(names)

    def _start(self, names: Sequence[str]) -> bool:
        with self._lock:
            if self.dataset is None:
                return False
            new = [n for n in names if n not in self._queue and n != self._progress.frame]
            if not new or self._progress.cancelling:
                return False
            if self._worker is None:
                self._cancel.clear()
                self._progress = RunProgress(running=True, frames_total=len(new))
            else:
                self._progress = replace(self._progress,
                                         frames_total=self._progress.frames_total + len(new))
            self._queue.extend(new)
            for n in new:
                self._entry(n).status = "queued"
            if self._worker is None:
                self._worker = threading.Thread(target=self._work, name="blurcalib-run", daemon=True)
                self._worker.start()
        self.events.emit(Topic.FRAMES, Topic.RUN)
        return True

    def cancel(self) -> None:
        """Stop the run after the current growth front; queued frames go back to pending."""
        with self._lock:
            if self._worker is None:
                return
            self._cancel.set()
            for n in self._queue:
                self._entry(n).status = "pending"
            self._queue.clear()
            self._progress = replace(self._progress, cancelling=True)
        self.events.emit(Topic.FRAMES, Topic.RUN)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the run to end; returns whether it did within ``timeout`` seconds."""
        with self._lock:
            worker = self._worker
        if worker is None:
            return True
        worker.join(timeout)
        return not worker.is_alive()

    def _work(self) -> None:
        while True:
            with self._lock:
                if not self._queue or self._cancel.is_set():
                    self._worker = None
                    self._progress = replace(self._progress, running=False, cancelling=False, frame="")
                    break
                name = self._queue.popleft()
                self._entry(name).status = "running"
                self._live[name] = {}
                self._progress = replace(self._progress, frame=name, frame_blocks=0, frame_expected=0)
            self.events.emit(Topic.FRAMES, Topic.RUN, Topic.LIVE)
            t0 = time.perf_counter()
            try:
                self._run_one(name, t0)
            except Exception as exc:  # the worker must survive any failure of one frame
                log.exception("extraction of %s failed", name)
                self._finish(name, None, FrameStatus.FAILED.value, f"{type(exc).__name__}: {exc}", t0)
        self.events.emit(Topic.RUN)

    def _run_one(self, name: str, t0: float) -> None:
        with self._lock:
            entry = self._entry(name)
            settings = self.settings.for_kind(entry.kind)
            pattern = self.dataset.pattern
        try:
            image = self.image(name)
        except FrameError as exc:
            self._finish(name, None, FrameStatus.UNREADABLE.value, str(exc), t0)
            return
        result = extract_frame(image, pattern, name, settings, on_event=partial(self._on_event, name),
                               should_stop=self._cancel.is_set)
        if self._cancel.is_set():
            self._finish(name, result, "cancelled", "cancelled: the blocks grown so far are kept", t0)
        else:
            self._finish(name, result, result.status.value, result.message, t0)

    def _on_event(self, name: str, event: GrowthEvent) -> None:
        with self._lock:
            events = self._live.setdefault(name, {})
            events[event.feature_id] = event  # a block judged again (retried, re-checked) counts once
            expected = self._progress.frame_expected
            if not expected and name in self._sizes:
                expected = expected_blocks(self.dataset.pattern, event, self._sizes[name])
            self._progress = replace(self._progress, frame_blocks=len(events),
                                     frame_expected=max(expected, len(events)))
        self.events.emit(Topic.LIVE, Topic.RUN)

    def _finish(self, name: str, result: FrameResult | None, status: str, message: str, t0: float) -> None:
        with self._lock:
            entry = self._entry(name)
            entry.status, entry.message = status, message
            entry.seconds = time.perf_counter() - t0
            if result is not None:
                entry.blocks = len(result.blocks)
                entry.accepted = int(result.blocks.accepted.sum())
                self._results[name] = result
                flt = frame_filter(result, self._sizes[name], self.quality, entry.kind)
                if flt is None:
                    self._filters.pop(name, None)
                else:
                    self._filters[name] = flt
            if entry.name == self._current_name():
                self.selected = None
            self._progress = replace(self._progress, frames_done=self._progress.frames_done + 1,
                                     frame_blocks=0, frame_expected=0)
        if status not in (FrameStatus.OK.value, "cancelled"):
            self.notify("warning" if status != FrameStatus.FAILED.value else "error",
                        f"{name}: {status.replace('_', ' ')}", message)
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
                flt = frame_filter(result, self._sizes[name], self.quality, self._entry(name).kind)
                if flt is not None:
                    self._filters[name] = flt
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
