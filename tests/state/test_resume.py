"""The app's extraction through the runner: an interrupted extraction resumes when the dataset is
opened again (the finished frames read back, not redone), and a frame whose tag is not found is
seeded from an extracted neighbour, as ``blurcalib extract`` does."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

import blurcalib.extract.frame as extract_module
from blurcalib.camera.parametric import BrownConrady
from blurcalib.extract.frame import ExtractSettings
from blurcalib.growth.seed import SeedError, seed_frame
from blurcalib.growth.settings import GrowSettings
from blurcalib.io.record import FrameStatus
from blurcalib.sim.synth import Simulator, SynthConfig
from blurcalib.sim.truth import TrueCamera
from blurcalib.target.pattern import layout_pattern
from state import AppState, RunSettings, Topic
from state.folder import default_output_folder
from tests.runs import stand_in


@pytest.fixture()
def engine(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The runner's stand-in engine (:mod:`tests.runs.stand_in`); returns its calls."""
    return stand_in.install(monkeypatch)


def _dataset(root: Path, values: list[int]) -> Path:
    (root / "sharp").mkdir(parents=True)
    layout_pattern().save_yaml(root / "pattern.yaml")
    for i, value in enumerate(values):
        assert cv2.imwrite(str(root / "sharp" / f"{i}.png"), np.full((48, 64), value, np.uint8))
    return root


def test_an_interrupted_extraction_resumes_when_the_folder_is_opened_again(
        tmp_path: Path, engine: list[str], user_cache: Path) -> None:
    folder = _dataset(tmp_path / "data", [10, 11, 12])
    state = AppState()
    assert state.load_folder(folder)
    assert state.output == default_output_folder(folder) and state.output.is_relative_to(user_cache)

    def cancel_after_the_first(topic: Topic) -> None:
        if topic is Topic.RESULT and state.entries()[0].record.status is FrameStatus.OK:
            state.cancel()

    state.subscribe(cancel_after_the_first)
    assert state.run_all() and state.wait(60)
    pending = [FrameStatus.OK, FrameStatus.PENDING, FrameStatus.PENDING]
    assert [e.record.status for e in state.entries()] == pending and engine == ["sharp/0.png"]
    # opened again (another app): the finished frame is done, read back from the output folder
    reopened = AppState()
    assert reopened.load_folder(folder)
    entries = reopened.entries()
    assert [e.record.status for e in entries] == pending
    assert entries[0].record == state.entries()[0].record
    result = reopened.results()["sharp/0.png"][0]
    assert result.growth is None
    assert np.array_equal(result.features.x, stand_in.grid_features("sharp/0.png", 10.0).x)
    assert "1 extracted before" in reopened.notices[-1].text
    assert reopened.run_all() and reopened.wait(60)
    assert engine == ["sharp/0.png", "sharp/1.png", "sharp/2.png"]  # the finished frame was not redone
    # Run frame extracts a finished frame again
    assert reopened.run_frame(0) and reopened.wait(60)
    assert engine[-1] == "sharp/0.png"


def test_a_frame_without_its_tag_is_seeded_from_its_neighbour(tmp_path: Path, engine: list[str]) -> None:
    folder = _dataset(tmp_path / "data", [10, stand_in.NO_TAG, 12])
    state = AppState()
    assert state.load_folder(folder, out=tmp_path / "out")
    assert state.run_all() and state.wait(60)
    record = state.entries()[1].record
    assert record.status is FrameStatus.OK and record.seeded_by == "neighbour"
    assert record.neighbours_tried == ("sharp/0.png",) and engine[-1] == "sharp/1.png<-sharp/0.png"
    # the app's folder is laid out as calibrate's: an extract output per kind
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["sharp"]
    assert (tmp_path / "out" / "sharp" / "frames.csv").read_text().count("\n") == 4


def test_an_output_folder_that_holds_something_else_is_refused(tmp_path: Path) -> None:
    folder = _dataset(tmp_path / "data", [10])
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    state = AppState()
    assert not state.load_folder(folder, out=mine)
    assert state.notices[-1].level == "error" and "is not a blurcalib output" in state.notices[-1].text
    assert state.dataset is None and (mine / "notes.txt").read_text() == "mine"


# ---------------------------------------------------------------------------- the real engine
FAST = RunSettings(blurry=ExtractSettings(grow=GrowSettings(max_blocks=25)),
                   sharp=ExtractSettings.sharp(grow=GrowSettings(max_blocks=40)))


def _shifted(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    M = np.float32([[1, 0, dx], [0, 1, dy]])
    moved = cv2.warpAffine(image.astype(np.float32), M, image.shape[::-1], borderMode=cv2.BORDER_REPLICATE)
    return np.clip(np.round(moved), 0, 255).astype(np.uint8)


@pytest.mark.slow
def test_the_real_engine_seeds_from_a_neighbour_and_the_views_draw_frames_read_back(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A sequence of a frame and the same view moved by a few pixels whose tag is not found: the
    app seeds the second from the first; opened again, both are read back and every view draws
    their blocks, PSFs, features and filter."""
    pytest.importorskip("viser")
    from state.figures import error_field
    from views.frame_view import draw_frame
    from views.inspect import block_images, scatter_plots
    from views.psf_field import psf_mosaic

    model = BrownConrady(fx=420.0, fy=420.0, cx=239.6, cy=179.3, k1=0.02, k2=-0.03, p1=0.0003, p2=-0.0002,
                         k3=0.0, width=480, height=360)
    sim = Simulator(SynthConfig(sharp=1, blurry=0, square_px=(24.0, 30.0), max_tilt_deg=30.0, seed=11),
                    camera=TrueCamera(model))
    folder = tmp_path / "data"
    (folder / "sharp").mkdir(parents=True)
    sim.pattern.save_yaml(folder / "pattern.yaml")
    image = sim.frame(0).image
    moved = _shifted(image, -5.0, 3.0)
    cv2.imwrite(str(folder / "sharp" / "0.png"), image)
    cv2.imwrite(str(folder / "sharp" / "1.png"), moved)

    def no_tag_in_moved(frame, pattern, H_feature=None, *args, **kwargs):
        if H_feature is None and np.array_equal(frame, moved.astype(np.float32)):
            raise SeedError("no AprilTag of the pattern found (test)")
        return seed_frame(frame, pattern, H_feature, *args, **kwargs)

    monkeypatch.setattr(extract_module, "seed_frame", no_tag_in_moved)
    state = AppState(FAST)
    assert state.load_folder(folder, out=tmp_path / "out")
    done = threading.Event()
    state.subscribe(lambda topic: topic is Topic.RUN and not state.progress().running and done.set())
    assert state.run_all() and state.wait(600) and done.is_set()
    first, second = (e.record for e in state.entries())
    assert first.status is FrameStatus.OK and second.status is FrameStatus.OK
    assert second.seeded_by == "neighbour" and "sharp/0.png" in second.message
    grown = state.results()
    reopened = AppState(FAST)
    assert reopened.load_folder(folder, out=tmp_path / "out")
    assert [e.record for e in reopened.entries()] == [first, second]
    for index, name in enumerate(("sharp/0.png", "sharp/1.png")):
        result, flt, size = reopened.results()[name]
        assert result.growth is None and size == (480, 360) and flt is not None
        assert np.array_equal(result.blocks.H, grown[name][0].blocks.H)
        assert np.array_equal(result.features.x, grown[name][0].features.x)
        assert np.array_equal(flt.kept, grown[name][1].kept)
        local = error_field(result, flt, None)
        assert local is not None and local.source == "local alignment"
        assert np.allclose(local.error, error_field(*grown[name][:2], None).error, atol=1e-9)
        reopened.select_frame(index)
        view = reopened.view()
        block = int(np.flatnonzero(result.blocks.accepted)[0])
        for drawn in (draw_frame(view, "kept / removed", True, True), psf_mosaic(view, 0.9, "kept blocks"),
                      block_images(view, block), scatter_plots(view)):
            assert drawn.dtype == np.uint8 and drawn.ndim == 3 and drawn.std() > 5
