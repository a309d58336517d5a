"""The runner of many frames through each executor: resume, neighbour seeding, cancel, progress.

The per-frame engine is a fast stand-in (:mod:`tests.runs.stand_in`), so that the runner's logic,
not the engine, is under test (the engine's own neighbour seeding: ``tests/extract/test_frame.py``).
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

import blurcalib.runs.executors as executors_module
import blurcalib.runs.task as task_module
from blurcalib.extract.frame import ExtractSettings, FrameResult
from blurcalib.io.frame_files import read_frame_status
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import read_features
from blurcalib.runs.events import FrameDone, FrameStarted, RunEvent
from blurcalib.runs.executors import DaskCluster, InProcess, ProcessPool
from blurcalib.runs.folder import finished_frames, run_frames
from blurcalib.target.pattern import layout_pattern
from tests.runs import stand_in


@pytest.fixture()
def engine(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The stand-in engine (:mod:`tests.runs.stand_in`); returns its calls."""
    return stand_in.install(monkeypatch)


def _sequence(folder: Path, values: list[int]) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, value in enumerate(values):
        paths.append(folder / f"{i}.png")
        assert cv2.imwrite(str(paths[-1]), np.full((48, 64), value, np.uint8))
    return paths


@pytest.fixture(params=["in_process", "process_pool", "dask"])
def executor(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch):
    """Each executor, its frames computed in this process so that the stand-in engine holds: the
    pool's processes replaced by threads, the Dask cluster's workers threads of this process."""
    if request.param == "in_process":
        yield InProcess(), ()
    elif request.param == "process_pool":
        monkeypatch.setattr(executors_module, "ProcessPoolExecutor",
                            lambda workers, mp_context, initializer: ThreadPoolExecutor(workers))
        with ProcessPool(2) as pool:
            yield pool, ("2.png",)
    else:
        distributed = pytest.importorskip("distributed", reason="Dask is not installed")
        import torch

        threads = torch.get_num_threads()
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp://",
                                      dashboard_address=None) as cluster:
            yield DaskCluster(cluster.scheduler_address), ("2.png",)
        torch.set_num_threads(threads)


def test_each_executor_seeds_from_neighbours_and_resumes(tmp_path: Path, engine: list[str], executor) -> None:
    """Frame 1 of a sequence has no tag: it is seeded from frame 0, the nearest neighbour, after
    every frame was tried from its own tag; where frames run side by side it tries frame 2 in the
    same round. A second run finds everything done and computes nothing."""
    runner, more = executor
    paths = _sequence(tmp_path / "seq", [10, stand_in.NO_TAG, 12])
    out = tmp_path / "out"
    done: list[FrameDone] = []

    def progress(event: RunEvent) -> None:
        if isinstance(event, FrameDone):
            done.append(event)

    summary = run_frames(paths, layout_pattern(), out, ExtractSettings(), runner, progress)
    records = {r.frame: r for r in summary.records}
    assert sorted(engine[:3]) == ["0.png", "1.png", "2.png"]
    assert sorted(engine[3:]) == sorted(["1.png<-0.png", *(f"1.png<-{n}" for n in more)])
    assert records["1.png"].status is FrameStatus.OK and records["1.png"].seeded_by == "neighbour"
    assert records["1.png"].message == "seeded from neighbour 0.png"  # the nearest one's seed is kept
    assert records["1.png"].neighbours_tried == ("0.png", *more)
    assert read_frame_status(out, "1.png") == records["1.png"]
    assert [(e.done, e.total) for e in done] == [(1, 3), (2, 3), (3, 3), (3, 3)]
    names = [f.frame for f in read_features(out / "features.csv")]
    assert names == ["0.png"] * 20 + ["1.png"] * 20 + ["2.png"] * 20
    engine.clear()
    again = run_frames(paths, layout_pattern(), out, ExtractSettings(), runner, progress)
    assert engine == [] and again.skipped == ["0.png", "1.png", "2.png"]
    assert again.records == summary.records


def test_only_some_frames_and_redo(tmp_path: Path, engine: list[str]) -> None:
    """A run of some frames of a sequence extracts those, seeds them from the finished ones of the
    others, and lists the finished frames of the whole sequence; ``redo`` extracts a finished
    frame again."""
    paths = _sequence(tmp_path / "seq", [10, 11, stand_in.NO_TAG, 13])
    out = tmp_path / "out"
    first = run_frames(paths, layout_pattern(), out, only=["0.png", "3.png"])
    assert engine == ["0.png", "3.png"] and [r.frame for r in first.records] == ["0.png", "3.png"]
    engine.clear()
    second = run_frames(paths, layout_pattern(), out, only=["2.png"])
    assert engine == ["2.png", "2.png<-3.png"]  # 3.png, extracted before, is its nearest neighbour
    assert second.records[0].neighbours_tried == ("3.png",)
    listed = [line.split(",")[0] for line in (out / "frames.csv").read_text().splitlines()[1:]]
    assert listed == ["0.png", "2.png", "3.png"]  # the finished frames of the sequence
    assert {f.frame for f in read_features(out / "features.csv")} == {"0.png", "2.png", "3.png"}
    engine.clear()
    run_frames(paths, layout_pattern(), out, only=["0.png", "1.png"], redo=["0.png"])
    assert engine == ["0.png", "1.png"]


def test_a_cancelled_run_keeps_the_finished_frames_and_resumes(tmp_path: Path, engine: list[str],
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A cancel while a frame grows: that frame is reported cancelled with what it grew and not
    written, no later frame starts, the finished ones are kept; the next run does the rest."""
    paths = _sequence(tmp_path / "seq", [10, 11, 12])
    out = tmp_path / "out"
    cancel = threading.Event()
    events: list[RunEvent] = []
    grow = task_module.extract_frame

    def cancelled_in_frame_1(image, pattern, frame, settings=None, *args, **kwargs) -> FrameResult:
        result = grow(image, pattern, frame, settings)
        if frame == "1.png":
            cancel.set()  # the user cancels while frame 1 grows
            assert kwargs["should_stop"]()
        return result

    monkeypatch.setattr(task_module, "extract_frame", cancelled_in_frame_1)
    summary = run_frames(paths, layout_pattern(), out, progress=events.append, cancel=cancel)
    assert [e.frame for e in events if isinstance(e, FrameStarted)] == ["0.png", "1.png"]
    finished = [(e.record.frame, e.record.status) for e in events if isinstance(e, FrameDone)]
    assert finished == [("0.png", FrameStatus.OK), ("1.png", FrameStatus.CANCELLED)]
    assert [r.frame for r in summary.records] == ["0.png"] and read_frame_status(out, "1.png") is None
    assert [record.frame for record, _ in finished_frames(paths, layout_pattern(), out)] == ["0.png"]
    engine.clear()
    again = run_frames(paths, layout_pattern(), out)
    assert engine == ["1.png", "2.png"] and again.skipped == ["0.png"]
