"""Where a run's frames are computed: in this process, in worker processes, or on a Dask cluster.

An :class:`Executor` takes a list of :class:`blurcalib.runs.task.FrameTask` and yields each
task's result as it finishes (:func:`blurcalib.runs.task.process_frame`); a cancel (a
``threading.Event``) stops it: no task is started after it, and tasks not started are dropped.

* :class:`InProcess`: one frame at a time in this process, the only executor that reports the
  growth as it happens (:class:`blurcalib.runs.events.FrameStarted`,
  :class:`blurcalib.runs.events.FrameGrew`) and stops a frame between its growth fronts;
* :class:`ProcessPool`: worker processes (one torch thread each, started on first use and kept
  for the runs that share the pool);
* :class:`DaskCluster`: one task per frame on a Dask scheduler (:mod:`blurcalib.runs.cluster`).
"""

from __future__ import annotations

import multiprocessing
import threading
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from functools import partial
from typing import Protocol

from blurcalib.extract.frame import FrameResult
from blurcalib.growth.ledger import GrowthEvent
from blurcalib.io.record import FrameStatus
from blurcalib.runs.events import FrameGrew, FrameStarted, Progress
from blurcalib.runs.runtime import exit_with_parent, keep_large_allocations
from blurcalib.runs.task import FrameJob, FrameTask, one_line, process_frame

Results = Iterator[tuple[int, FrameResult]]
"""``(i, result)`` of task ``i``, in the order the tasks finish."""


class Executor(Protocol):
    """Computes the frames of a run."""

    def side_by_side(self, frames: int) -> int:
        """Tasks that run at the same time in a run of ``frames`` frames (0: one after the
        other), for the neighbour rounds (:func:`blurcalib.runs.neighbours.plan_round`)."""
        ...

    def run(self, tasks: Sequence[FrameTask], job: FrameJob, progress: Progress | None = None,
            cancel: threading.Event | None = None) -> Results:
        """Compute ``tasks``, yielding each result as it is done; stop once ``cancel`` is set."""
        ...


def _grew(progress: Progress, frame: str, event: GrowthEvent) -> None:
    progress(FrameGrew(frame, event))


class InProcess:
    """Frames one at a time in this process, with live growth events and a cancel between growth
    fronts (the frame stopped by it is returned with what was grown)."""

    def side_by_side(self, frames: int) -> int:
        return 0

    def run(self, tasks: Sequence[FrameTask], job: FrameJob, progress: Progress | None = None,
            cancel: threading.Event | None = None) -> Results:
        for i, task in enumerate(tasks):
            if cancel is not None and cancel.is_set():
                return
            name = task.frame.name
            if progress is not None:
                progress(FrameStarted(name, None if task.hint is None else task.hint.neighbour))
            yield i, process_frame(task.frame, task.hint, job.pattern, job.settings, job.size,
                                   None if progress is None else partial(_grew, progress, name),
                                   None if cancel is None else cancel.is_set)


def _init_worker() -> None:
    """A worker process of a :class:`ProcessPool`: one torch thread, glibc's allocations kept."""
    import torch

    exit_with_parent()
    keep_large_allocations()  # a spawned worker starts with glibc's defaults
    torch.set_num_threads(1)


class ProcessPool:
    """Worker processes, started on first use and kept for the runs that share the pool (the sharp
    and blurry folders of a calibration: starting ``workers`` processes, each importing torch,
    takes about 2 s of wall time). A run of one task, or a pool of one worker, computes in this
    process instead.

    A context manager: the processes end with it. Tasks carry their pattern and settings, so
    runs with different settings share the processes.
    """

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._executor: ProcessPoolExecutor | None = None

    def __enter__(self) -> ProcessPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def side_by_side(self, frames: int) -> int:
        return self.workers if self.workers > 1 else 0

    def submit(self, task: FrameTask, job: FrameJob) -> Future[FrameResult]:
        """Process a task in a worker; the processes start on the first task."""
        if self._executor is None:
            spawn = multiprocessing.get_context("spawn")
            self._executor = ProcessPoolExecutor(self.workers, mp_context=spawn,
                                                 initializer=_init_worker)
        return self._executor.submit(process_frame, task.frame, task.hint, job.pattern, job.settings,
                                     job.size)

    def close(self) -> None:
        """End the worker processes (a later task starts new ones: after a broken pool, e.g. a
        worker killed for memory)."""
        if self._executor is not None:
            self._executor.shutdown()
            self._executor = None

    def run(self, tasks: Sequence[FrameTask], job: FrameJob, progress: Progress | None = None,
            cancel: threading.Event | None = None) -> Results:
        """A worker that dies (e.g. killed for memory) fails its frame, ``failed`` with the error;
        the next tasks get new processes."""
        if self.workers <= 1 or len(tasks) <= 1:
            yield from InProcess().run(tasks, job, progress, cancel)
            return
        futures = {self.submit(task, job): i for i, task in enumerate(tasks)}
        try:
            for future in as_completed(futures):
                i = futures[future]
                try:
                    result = future.result()
                except Exception as exc:  # a worker died: the frame failed
                    result = FrameResult(tasks[i].frame.name, FrameStatus.FAILED, one_line(exc))
                    if isinstance(exc, BrokenProcessPool):
                        self.close()
                yield i, result
                if cancel is not None and cancel.is_set():
                    return
        finally:
            for future in futures:
                future.cancel()


class DaskCluster:
    """One task per frame on the Dask scheduler at ``address``
    (:func:`blurcalib.runs.cluster.run_on_cluster`)."""

    def __init__(self, address: str) -> None:
        self.address = address

    def side_by_side(self, frames: int) -> int:
        return frames

    def run(self, tasks: Sequence[FrameTask], job: FrameJob, progress: Progress | None = None,
            cancel: threading.Event | None = None) -> Results:
        if not tasks:
            return
        from blurcalib.runs.cluster import run_on_cluster

        results = run_on_cluster(self.address, process_frame, [(t.frame, t.hint) for t in tasks],
                                 (job.pattern, job.settings, job.size), names=[t.frame.name for t in tasks])
        try:
            for i, result in results:
                yield i, result
                if cancel is not None and cancel.is_set():
                    return
        finally:
            results.close()
