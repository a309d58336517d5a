"""Extraction of many frames into an output folder, resumable: the one way to run frames.

:func:`run_frames` is what ``blurcalib extract``, ``blurcalib calibrate`` and the app run. It
writes each frame's results as soon as it is done (``frames/<stem>.*``, see
``docs/results-format.md``, :class:`blurcalib.runs.output.RunFolder`), so an interrupted run
loses at most the frames in progress and a re-run skips frames finished with the same pattern,
settings and input file; the per-frame files of the run's finished frames are collected into
``features.csv``, ``blocks.csv``, ``psfs.npz``, ``corners.csv`` (the square corners shared by
neighbouring blocks, after local alignment) and ``frames.csv`` (per-frame status). Frames come
from folders, image files and videos (:mod:`blurcalib.io.sources`) and are computed by an
executor (:mod:`blurcalib.runs.executors`: this process, worker processes or a Dask cluster); in
a sequence, a frame whose tag is not found is seeded from its nearest extracted neighbour,
verified against its own pixels (:mod:`blurcalib.runs.neighbours`). :func:`extract_to_folder`
runs frames with the executor that ``workers`` and ``cluster`` name.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Collection, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path

from blurcalib.extract.frame import ExtractSettings, FrameResult
from blurcalib.io.record import FrameRecord, FrameStatus
from blurcalib.io.results import ResultsFileError
from blurcalib.io.sources import FrameInput
from blurcalib.runs.events import FrameDone, Progress
from blurcalib.runs.executors import DaskCluster, Executor, InProcess, ProcessPool
from blurcalib.runs.neighbours import NeighbourSeed, Poses, moving_message, plan_round
from blurcalib.runs.output import (
    RunFolder,
    as_frame_inputs,
    common_size,
    frame_sizes,
    frame_source,
    input_key,
    keyed,
    run_key,
)
from blurcalib.runs.task import FrameJob, FrameTask
from blurcalib.target.pattern import StarPattern


@dataclass(frozen=True)
class RunSummary:
    """Outcome of a run: the records of its frames (those it was asked to extract, in order; a
    frame stopped by a cancel has none), the frames skipped as already done, and the output files."""

    records: list[FrameRecord]
    skipped: list[str]
    outputs: dict[str, Path]


class _RoundResults:
    """A neighbour round's results: a frame is decided once all its attempts are in, as its first
    verified one (nearest neighbour first), else its last refusal."""

    def __init__(self, attempts: Sequence[tuple[FrameInput, list[NeighbourSeed]]]) -> None:
        self._expected = {f.name: len(hints) for f, hints in attempts}
        self._got: dict[str, dict[int, FrameResult]] = {name: {} for name in self._expected}

    def add(self, i: int, result: FrameResult) -> FrameResult | None:
        """Task ``i``'s result; the frame's decided result once its attempts are all in, else None."""
        mine = self._got[result.frame]
        mine[i] = result
        if len(mine) < self._expected[result.frame]:
            return None
        ordered = [mine[k] for k in sorted(mine)]
        return next((r for r in ordered if r.status is FrameStatus.OK), ordered[-1])


class _Run:
    """One run's state: the frames, their keys and sources, and the records finished so far."""

    def __init__(self, frames: list[FrameInput], folder: RunFolder, job: FrameJob, executor: Executor,
                 todo: list[str], progress: Progress | None, cancel: threading.Event | None) -> None:
        self.frames, self.folder, self.job, self.executor = frames, folder, job, executor
        self.todo, self.progress, self.cancel = todo, progress, cancel
        key = run_key(job.pattern, job.settings)
        self.keys = {f.name: input_key(key, f) for f in frames}
        self.sources = {f.name: frame_source(f) for f in frames}
        self.records: dict[str, FrameRecord] = {}
        self.tried: dict[str, list[str]] = {}

    @property
    def cancelled(self) -> bool:
        return self.cancel is not None and self.cancel.is_set()

    def resume(self, sizes: dict[str, tuple[int, int] | None], redo: Collection[str]) -> None:
        """Take the finished frames an earlier run left that need no redoing."""
        for f in self.frames:
            record = None if f.name in redo else self.folder.resumable(f, self.keys[f.name], self.job.size,
                                                                       sizes[f.name])
            if record is not None:
                self.records[f.name] = record

    def finish(self, result: FrameResult) -> None:
        """Write a finished frame, or report one stopped by a cancel (not written)."""
        name = result.frame
        record = keyed(result.record(), self.keys[name], self.sources[name], self.tried.get(name))
        if self.cancelled:
            record = replace(record, status=FrameStatus.CANCELLED, message="cancelled: the blocks grown so "
                                                                           "far are kept")
        else:
            self.folder.write(record, result)
            self.records[name] = record
            self.folder.write_table([self.records[f.name] for f in self.frames if f.name in self.records])
        if self.progress is not None:
            done = sum(1 for n in self.todo if n in self.records)
            self.progress(FrameDone(record, result, done, len(self.todo)))

    def own_tags(self) -> None:
        """Extract the frames to do from their own tags."""
        todo = set(self.todo)
        tasks = [FrameTask(f) for f in self.frames if f.name in todo and f.name not in self.records]
        for _, result in self.executor.run(tasks, self.job, self.progress, self.cancel):
            self.finish(result)

    def neighbour_rounds(self) -> dict[str, float]:
        """Seed the frames whose tag was not found from their neighbours, round after round;
        returns the frames passed over for their sequence's motion (squares per frame)."""
        side_by_side = self.executor.side_by_side(len(self.frames))
        poses = Poses(self.folder.features)
        while not self.cancelled:
            planned = plan_round(self.frames, self.records, poses, side_by_side, set(self.todo))
            if not planned.attempts:
                return planned.moving
            for f, hints in planned.attempts:
                before = self.records[f.name].neighbours_tried or ()
                self.tried[f.name] = [*before, *(h.neighbour for h in hints)]
            decided = _RoundResults(planned.attempts)
            tasks = [FrameTask(f, hint) for f, hints in planned.attempts for hint in hints]
            for i, result in self.executor.run(tasks, self.job, self.progress, self.cancel):
                chosen = decided.add(i, result)
                if chosen is not None:
                    self.finish(chosen)
        return {}

    def note_moving(self, moving: dict[str, float]) -> None:
        """Say in each frame's message why it was not seeded from its neighbours."""
        for name, motion in moving.items():
            record = self.records[name]
            message = moving_message(record.message, motion)
            if message != record.message:
                self.records[name] = replace(record, message=message)
                self.folder.write(self.records[name])

    def publish(self) -> dict[str, Path]:
        """The top-level tables of the finished frames, in the run's order."""
        names = [f.name for f in self.frames if f.name in self.records]
        outputs = self.folder.collect(names, self.job.settings)
        outputs["frames"] = self.folder.write_table([self.records[n] for n in names])
        return outputs


def run_frames(frames: Sequence[FrameInput | Path], pattern: StarPattern, out_dir: str | os.PathLike[str],
               settings: ExtractSettings | None = None, executor: Executor | None = None,
               progress: Progress | None = None, expected_size: tuple[int, int] | None = None,
               overwrite: bool = False, cancel: threading.Event | None = None,
               only: Collection[str] | None = None, redo: Collection[str] = ()) -> RunSummary:
    """Extract the frames of ``frames`` (those named in ``only``, by default all) into ``out_dir``,
    resumably.

    Every frame ends with a status: an unreadable frame, one of another size, one that cannot
    be seeded or fails is recorded with its status and message, and the others go on. A frame
    finished by an earlier run is skipped when its result key (the pattern, the settings, the
    input file's size and modification time and a video frame's index) is unchanged, its status
    is final (:data:`blurcalib.io.record.FINAL_STATUSES`) and it is not named in ``redo``;
    otherwise it is redone. The top-level tables list the finished frames of ``frames``, in
    order: at the end of an uncancelled run, every frame asked for.

    Once every frame has been tried from its own tag, the frames of a sequence (a video, a
    folder) whose tag was not found are seeded from their nearest extracted neighbour (any
    finished frame of ``frames``) and verified (:func:`blurcalib.runs.neighbours.seed_from_neighbour`),
    in rounds, so that a seeded frame can seed the next. Where the executor runs frames side by
    side, while a round has fewer than :data:`blurcalib.runs.neighbours.NEIGHBOUR_TRIES`
    attempts per worker, its frames try their next neighbours in it too, and the nearest verified
    seed is kept: the round takes about as long as the rounds one neighbour at a time would, and
    ends with the same result. Where the sequence moves the target by more than
    :data:`blurcalib.runs.neighbours.NEIGHBOUR_MOTION_SQUARES` squares per frame around a frame
    (frames of unrelated poses), no neighbour's seed can be right and none is tried; the frame's
    message says so.

    Args:
        frames: :class:`blurcalib.io.sources.FrameInput` (:func:`blurcalib.io.sources.frame_inputs`),
            or image paths (:func:`blurcalib.runs.output.as_frame_inputs`).
        executor: where frames are computed (default: this process, :class:`InProcess`).
        progress: called with each :mod:`blurcalib.runs.events` event.
        expected_size: ``(width, height)`` every frame must have; None takes the most common
            size of the readable frames. Frames of another size get the status ``wrong_size``.
        overwrite: write into a non-empty folder that is not an ``extract`` output
            (:func:`blurcalib.io.atomic.claim_output_dir`), or replace results of frames of the
            same name extracted from other files (each frame's record keeps its ``source``).
        cancel: once set, no frame is started, the frame in this process stops after its growth
            front (reported ``cancelled``, not written) and the run ends with the frames finished.
    Raises:
        OutputError: the folder holds something else, or results of another dataset's frames
            of the same names (without ``overwrite``), or cannot be written.
    """
    inputs = as_frame_inputs(frames)
    names = [f.name for f in inputs]
    if len(set(names)) != len(names):
        raise ValueError("frame names must be unique, one per frame")
    settings = settings or ExtractSettings()
    folder = RunFolder.claim(out_dir, settings, {f.name: frame_source(f) for f in inputs}, overwrite)
    sizes = frame_sizes(inputs)
    job = FrameJob(pattern, settings, expected_size or common_size(list(sizes.values())))
    wanted = set(names if only is None else only)
    todo = [n for n in names if n in wanted]
    run = _Run(inputs, folder, job, executor or InProcess(), todo, progress, cancel)
    run.resume(sizes, redo)
    skipped = [n for n in todo if n in run.records]
    run.own_tags()
    run.note_moving(run.neighbour_rounds())
    outputs = run.publish()
    return RunSummary([run.records[n] for n in todo if n in run.records], skipped, outputs)


def extract_to_folder(frames: Sequence[FrameInput | Path], pattern: StarPattern,
                      out_dir: str | os.PathLike[str], settings: ExtractSettings | None = None,
                      workers: int = 1,
                      progress: Progress | None = None, expected_size: tuple[int, int] | None = None,
                      overwrite: bool = False, cluster: str | None = None,
                      pool: ProcessPool | None = None) -> RunSummary:
    """:func:`run_frames` of every frame with ``cluster`` (a Dask scheduler address) as tasks
    there (:class:`blurcalib.runs.executors.DaskCluster`), else in the worker processes of
    ``pool`` (shared between calls), or of ``workers`` processes started for this call (one:
    this process)."""
    with ExitStack() as stack:
        executor: Executor
        if cluster is not None:
            executor = DaskCluster(cluster)
        elif pool is not None:
            executor = pool
        elif workers > 1:
            executor = stack.enter_context(ProcessPool(workers))
        else:
            executor = InProcess()
        return run_frames(frames, pattern, out_dir, settings, executor, progress, expected_size, overwrite)


def finished_frames(frames: Sequence[FrameInput | Path], pattern: StarPattern,
                    out_dir: str | os.PathLike[str], settings: ExtractSettings | None = None,
                    expected_size: tuple[int, int] | None = None
                    ) -> list[tuple[FrameRecord, FrameResult]]:
    """The frames of ``frames`` that :func:`run_frames` with these arguments would skip (finished
    in ``out_dir`` with the same key), extracted from the same files, each with its record and its
    result read back (:meth:`blurcalib.runs.output.RunFolder.read_result`); nothing is written.
    A frame whose files cannot be read is left out (a run redoes it)."""
    folder = RunFolder(out_dir)
    if not folder.path.is_dir():
        return []
    inputs = as_frame_inputs(frames)
    sizes = frame_sizes(inputs)
    size = expected_size or common_size(list(sizes.values()))
    key = run_key(pattern, settings or ExtractSettings())
    out = []
    for f in inputs:
        record = folder.resumable(f, input_key(key, f), size, sizes[f.name])
        if record is None or record.source != frame_source(f):
            continue
        try:
            out.append((record, folder.read_result(record)))
        except ResultsFileError:
            continue
    return out
