"""Frames as tasks on a Dask cluster: the same results as a local run, resumable, CLI errors."""

from __future__ import annotations

import json
import os
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

pytestmark = pytest.mark.slow

distributed = pytest.importorskip(
    "distributed", reason="Dask is not installed: pip install 'blurcalib[cluster]'")

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


@pytest.fixture(scope="module")
def cluster():
    # the workers are new processes: they import this checkout's blurcalib
    old = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), *([old] if old else [])])
    try:
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                      dashboard_address=None) as local:
            yield local.scheduler_address
    finally:
        if old is None:
            os.environ.pop("PYTHONPATH")
        else:
            os.environ["PYTHONPATH"] = old


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
