"""Frames as tasks on a Dask cluster: the same results as a local run, resumable, CLI errors."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.camera.parametric import BrownConrady
from blurcalib.cli import main
from blurcalib.extract.frame import ExtractSettings
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import read_features
from blurcalib.runs.cluster import ClusterError, run_on_cluster
from blurcalib.runs.events import FrameDone, RunEvent
from blurcalib.runs.folder import extract_to_folder
from blurcalib.runs.runtime import configure_threads
from blurcalib.sim.synth import Simulator, SynthConfig
from blurcalib.sim.truth import TrueCamera

pytestmark = [pytest.mark.slow, pytest.mark.cluster]

distributed = pytest.importorskip(
    "dask.distributed", reason="Dask is not installed: pip install 'blurcalib[cluster]'")
dask = pytest.importorskip("dask")

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> tuple[list[Path], Simulator]:
    model = BrownConrady(fx=420.0, fy=420.0, cx=239.6, cy=179.3, k1=0.02, k2=-0.03, p1=0.0003,
                         p2=-0.0002, k3=0.0, width=480, height=360)
    sim = Simulator(SynthConfig(sharp=3, blurry=0, square_px=(24.0, 30.0), max_tilt_deg=30.0, seed=5),
                    camera=TrueCamera(model))
    folder = tmp_path_factory.mktemp("frames")
    paths = []
    for i in range(3):
        path = folder / f"f{i}.png"
        cv2.imwrite(str(path), sim.frame(i).image)
        paths.append(path)
    return paths, sim


@contextlib.contextmanager
def local_cluster(workers: int) -> Iterator[str]:
    """A local Dask cluster of ``workers`` single-threaded worker processes, each under a nanny
    that restarts it when it dies; its scheduler's address."""
    # the workers are new processes: they import this checkout's blurcalib
    old = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), *([old] if old else [])])
    try:
        with distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                      dashboard_address=None) as local:
            yield local.scheduler_address
    finally:
        if old is None:
            os.environ.pop("PYTHONPATH")
        else:
            os.environ["PYTHONPATH"] = old


@pytest.fixture(scope="module")
def cluster():
    with local_cluster(2) as address:
        yield address


@pytest.fixture
def one_thread():
    """The cluster's workers compute with one thread; so does the local run compared with them
    (floating-point sums, hence the last digits, depend on the thread count)."""
    import torch

    before = torch.get_num_threads()
    configure_threads(1)
    yield
    configure_threads(before)


def _features(path: Path) -> dict:
    return {(f.frame, f.feature_id): (f.x, f.y) for f in read_features(path)}


def test_cluster_run_matches_local_run_and_resumes(tmp_path, frames, cluster, one_thread) -> None:
    paths, sim = frames
    settings = ExtractSettings.sharp()
    local = extract_to_folder(paths, sim.pattern, tmp_path / "local", settings)
    assert [r.status for r in local.records] == [FrameStatus.OK] * 3
    # a cluster run that finds one frame already done extracts only the other two
    extract_to_folder(paths[:1], sim.pattern, tmp_path / "dask", settings)
    seen = []

    def progress(event: RunEvent) -> None:
        assert isinstance(event, FrameDone)  # a cluster task reports its frame once done
        seen.append((event.done, event.total, event.record.frame))

    run = extract_to_folder(paths, sim.pattern, tmp_path / "dask", settings, cluster=cluster,
                            progress=progress)
    assert run.skipped == ["f0.png"]
    assert sorted(name for _, _, name in seen) == ["f1.png", "f2.png"]
    assert [(done, total) for done, total, _ in seen] == [(2, 3), (3, 3)]
    ref, got = _features(tmp_path / "local" / "features.csv"), _features(tmp_path / "dask" / "features.csv")
    assert len(ref) > 150 and ref.keys() == got.keys()
    diff = np.array([np.subtract(ref[k], got[k]) for k in ref])
    assert np.abs(diff).max() < 1e-9


def test_cli_extract_on_cluster(tmp_path, frames, cluster) -> None:
    paths, sim = frames
    yaml = tmp_path / "pattern.yaml"
    sim.pattern.save_yaml(yaml)
    out = tmp_path / "out"
    assert main(["extract", str(paths[1]), "--pattern", str(yaml), "--out", str(out), "--sharp",
                 "--cluster", cluster]) == 0
    assert {f.frame for f in read_features(out / "features.csv")} == {"f1.png"}


def test_unreachable_scheduler_is_one_line_error(tmp_path, frames, capsys) -> None:
    with pytest.raises(ClusterError, match="cannot reach the Dask scheduler"):
        list(run_on_cluster("tcp://127.0.0.1:9", len, [("x",)], timeout_s=2.0))
    paths, sim = frames
    yaml = tmp_path / "pattern.yaml"
    sim.pattern.save_yaml(yaml)
    code = main(["extract", str(paths[0]), "--pattern", str(yaml), "--out", str(tmp_path / "o"),
                 "--cluster", "tcp://127.0.0.1:9"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("blurcalib: error: tcp://127.0.0.1:9: cannot reach")


def test_cli_calibrate_on_cluster_matches_local_run(tmp_path, cluster, one_thread) -> None:
    """``calibrate --cluster``: the frames are extracted on the workers, the cameras fitted on the
    client; the cameras, the per-frame statuses and the features are those of a local run."""
    model = BrownConrady(fx=430.0, fy=430.0, cx=239.6, cy=179.3, k1=-0.05, k2=0.02, p1=0.0, p2=0.0,
                         k3=0.0, width=480, height=360)
    sim = Simulator(SynthConfig(sharp=6, blurry=0, square_px=(24.0, 30.0), max_tilt_deg=35.0, seed=11),
                    camera=TrueCamera(model))
    folder = tmp_path / "sharp"
    folder.mkdir()
    for i in range(6):
        cv2.imwrite(str(folder / f"s{i}.png"), sim.frame(i).image)
    yaml = tmp_path / "pattern.yaml"
    sim.pattern.save_yaml(yaml)
    runs = {}
    for name, extra in (("local", ["--workers", "1"]), ("dask", ["--cluster", cluster])):
        out = tmp_path / name
        assert main(["calibrate", "--sharp", str(folder), "--pattern", str(yaml), "--out", str(out),
                     "--model", "parametric", *extra]) == 0
        runs[name] = out
    camera = {name: BrownConrady.from_dict(
        json.loads((out / "report.json").read_text())["calibration"]["camera"]) for name, out in runs.items()}
    assert np.allclose(camera["local"].params, camera["dask"].params, rtol=0, atol=1e-9)
    assert abs(camera["dask"].fx - model.fx) < 1.0
    frames = {name: (out / "frames.csv").read_text() for name, out in runs.items()}
    assert frames["local"] == frames["dask"]
    ref, got = (_features(out / "features.csv") for out in runs.values())
    assert len(ref) > 300 and ref.keys() == got.keys()


def dies_once(i: int, marker: str, shared: str) -> str:
    """Task ``i`` of a run whose task 1 kills its worker process the first time it runs."""
    if i == 1 and not Path(marker).exists():
        Path(marker).write_text("died")
        os.kill(os.getpid(), signal.SIGKILL)
    return f"{shared}{i}"


def always_dies(i: int, shared: str) -> str:
    """Task ``i`` of a run whose task 1 kills its worker process whenever it runs."""
    if i == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    return f"{shared}{i}"


def test_the_only_worker_restarted_mid_run_loses_nothing(tmp_path) -> None:
    """Killing the only worker (its nanny restarts it) ended the client in FutureCancelledError:
    the arguments common to all tasks were scattered data, lost with the worker."""
    with local_cluster(1) as address:
        got = dict(run_on_cluster(address, dies_once, [(i, str(tmp_path / "died")) for i in range(4)],
                                  ("frame",)))
    assert (tmp_path / "died").is_file()  # the worker was killed while running task 1
    assert got == {i: f"frame{i}" for i in range(4)}


def test_a_task_whose_workers_keep_dying_ends_the_run_in_one_line() -> None:
    """The other tasks finish and are yielded (their frames written) before the one-line error."""
    got = []
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), local_cluster(1) as address:
        with pytest.raises(ClusterError) as info:
            for item in run_on_cluster(address, always_dies, [(i,) for i in range(4)], ("frame",),
                                       names=["a.png", "b.png", "c.png", "d.png"]):
                got.append(item)
    message = str(info.value)
    assert "\n" not in message and "tasks did not finish on the Dask cluster (" in message
    assert "b.png" in message and "its workers kept dying while running it" in message
    lost = int(message.split(": ", 1)[1].split(" of ")[0])
    assert f"the {4 - lost} finished are kept; run again to resume" in message
    assert (1, "frame1") not in got and len(got) == 4 - lost >= 1


def sleeps(i: int, shared: str) -> str:
    """Task ``i``: a second's work."""
    time.sleep(1.0)
    return f"{shared}{i}"


def test_a_lost_scheduler_ends_the_run_in_one_line_keeping_what_finished(tmp_path) -> None:
    """Killing the scheduler ended the client in a CommClosedError or FutureCancelledError
    traceback."""
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    quiet = {"env": env, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    python = [sys.executable, "-m"]
    scheduler = subprocess.Popen([*python, "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                  "--port", str(port), "--no-dashboard"], **quiet)
    worker = subprocess.Popen([*python, "distributed.cli.dask_worker", address, "--nthreads", "1",
                               "--no-dashboard", "--no-nanny"], **quiet)
    got = []
    try:
        with dask.config.set({"distributed.comm.timeouts.connect": "5s"}):
            with pytest.raises(ClusterError) as info:
                names = [f"f{i}.png" for i in range(6)]
                for item in run_on_cluster(address, sleeps, [(i,) for i in range(6)], ("frame",),
                                           timeout_s=60.0, names=names):
                    got.append(item)
                    if len(got) == 2:
                        scheduler.kill()
    finally:
        for process in (worker, scheduler):
            process.kill()
            process.wait()
    message = str(info.value)
    assert "\n" not in message and f"{6 - len(got)} of 6 tasks did not finish on the Dask cluster" in message
    assert f"the {len(got)} finished are kept; run again to resume" in message and len(got) >= 2
    assert all(result == f"frame{i}" for i, result in got)
