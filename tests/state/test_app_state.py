"""The browser app's state and drawing, without a browser: folders, runs, cancel, tuning, errors."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.camera.parametric import BrownConrady
from blurcalib.extract.frame import ExtractSettings
from blurcalib.growth.quality import QualitySettings, noise_scale
from blurcalib.growth.settings import GrowSettings
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import BlockStatus
from blurcalib.sim.synth import SynthConfig
from blurcalib.sim.truth import TrueCamera
from state import AppState, DatasetError, RunSettings, Topic, default_dataset, discover
from state.alignment import AlignmentCache, AlignmentError
from state.blocks import filter_counts
from state.demo import MAX_SHIFT, TILE_PX, alignment_demo, ambiguity_demo
from state.figures import alignment_poses, error_field, feature_poses, truth_poses, used_frame_fields

SMALL_CAMERA = BrownConrady(fx=360.0, fy=360.0, cx=207.5, cy=155.5, k1=0.02, k2=-0.03, p1=0.0003,
                            p2=-0.0002, k3=0.0, width=416, height=312)
SMALL_CONFIG = SynthConfig(sharp=1, blurry=1, square_px=(36.0, 42.0), max_tilt_deg=30.0, blur_min_px=3.0,
                           blur_max_px=4.0, seed=3)
FAST = RunSettings(blurry=ExtractSettings(grow=GrowSettings(max_blocks=25)),
                   sharp=ExtractSettings.sharp(grow=GrowSettings(max_blocks=25)))
"""Grow two fronts (the ring around the tag and the next one, about 45 blocks): the state logic,
not the engine, is under test."""


def make_dataset(root: Path, config: SynthConfig = SMALL_CONFIG) -> Path:
    """A tiny simulated dataset (416 x 312 frames) with ground truth."""
    return default_dataset(root, config, TrueCamera(SMALL_CAMERA))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("app") / "tiny")


@pytest.fixture(scope="module")
def finished(dataset: Path) -> tuple[AppState, list[Topic]]:
    """A state with both frames of the tiny dataset extracted, and the topics it emitted."""
    state = AppState(FAST)
    topics: list[Topic] = []
    state.subscribe(topics.append)
    assert state.load_folder(dataset)
    assert state.view().image.shape == (312, 416) and state.view().result is None
    assert state.run_all()
    assert state.wait(300) and not state.is_running
    return state, topics


def test_discover_orders_frames_and_finds_pattern_and_truth(dataset: Path) -> None:
    d = discover(dataset)
    assert [(f.name, f.kind) for f in d.frames] == [("sharp/0000.png", "sharp"),
                                                    ("blurry/0000.png", "blurry")]
    assert d.pattern_path == dataset / "pattern.yaml" and d.truth is not None
    # The pattern is also found beside a folder of frames.
    assert discover(dataset / "blurry").pattern_path == dataset / "pattern.yaml"


def test_bad_folders_give_an_error_and_keep_the_state(dataset: Path, tmp_path: Path) -> None:
    state = AppState(FAST)
    notices = []
    state.subscribe_notices(notices.append)
    assert state.load_folder(dataset)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "pattern.yaml").write_text((dataset / "pattern.yaml").read_text())
    no_pattern = tmp_path / "no_pattern" / "frames"
    no_pattern.mkdir(parents=True)
    cv2.imwrite(str(no_pattern / "a.png"), np.zeros((20, 20), np.uint8))
    bad_pattern = tmp_path / "bad_pattern.yaml"
    bad_pattern.write_text("num_star_segments: 7\n")
    cases = [(tmp_path / "missing", None, "no such folder"), (empty, None, "no image files"),
             (no_pattern, None, "no pattern.yaml"), (dataset, bad_pattern, "num_star_segments")]
    for folder, pattern, message in cases:
        assert not state.load_folder(folder, pattern)
        assert notices[-1].level == "error" and message in notices[-1].text
        assert state.dataset.folder == dataset and len(state.frames) == 2 and state.current == 0
    with pytest.raises(DatasetError, match="no image files"):
        discover(empty)


@pytest.mark.slow
def test_run_updates_live_then_result_and_refilter_changes_counts(finished: tuple[AppState, list[Topic]]
                                                                   ) -> None:
    state, topics = finished
    state.select_frame(1)
    view = state.view()
    record = view.entry.record
    assert record.status is FrameStatus.OK and record.blocks == len(view.result.blocks) >= 30
    assert len(view.live) == len(view.result.blocks)
    assert topics.count(Topic.LIVE) >= len(view.live) and Topic.RESULT in topics
    progress = state.progress()
    assert progress.frames_done == progress.frames_total == 2 and progress.fraction == 1.0
    kept = filter_counts(view.filter).kept
    assert 0 < kept <= view.entry.record.accepted
    try:
        state.refilter(tau_loss=0.0)
        assert filter_counts(state.view().filter).kept == 0
        assert filter_counts(state.view().filter).removed_loss == view.entry.record.accepted
        state.refilter(tau_loss=1e6, tau_be=1.0)
        assert filter_counts(state.view().filter).kept >= kept
        state.refilter(min_sigma_major=0.0)
        assert state.view().filter.frame_ok
    finally:
        defaults = QualitySettings()
        state.refilter(defaults.tau_be, defaults.tau_loss, defaults.min_sigma_major)
    assert filter_counts(state.view().filter).kept == kept
    assert state.select_block(3) and state.view().selected == 3
    assert not state.select_block(10_000) and state.view().selected == 3
    assert state.select_block(None) and state.view().selected is None


def test_cancel_stops_after_the_first_front(dataset: Path) -> None:
    state = AppState()
    assert state.load_folder(dataset)
    first = threading.Event()

    def on_change(topic: Topic) -> None:
        if topic is Topic.LIVE and state.progress().frame_blocks > 0 and not first.is_set():
            first.set()
            state.cancel()

    state.subscribe(on_change)
    assert state.run_all()
    assert state.wait(300)
    entries = state.entries()
    assert entries[0].record.status is FrameStatus.CANCELLED
    assert entries[1].record.status is FrameStatus.PENDING
    assert {e.front for e in state.view().live} == {0}
    assert state.view().result is not None and entries[0].record.blocks == len(state.view().live)
    assert not state.is_running and not state.progress().cancelling


def test_bad_frames_get_a_status_and_a_notice(dataset: Path, tmp_path: Path) -> None:
    folder = tmp_path / "mixed"
    folder.mkdir()
    (folder / "pattern.yaml").write_text((dataset / "pattern.yaml").read_text())
    good = (dataset / "sharp" / "0000.png").read_bytes()
    (folder / "a_truncated.png").write_bytes(good[: len(good) // 2])
    cv2.imwrite(str(folder / "b_notag.png"), np.full((312, 416), 128, np.uint8))
    (folder / "c_good.png").write_bytes(good)
    state = AppState(FAST)
    notices = []
    state.subscribe_notices(notices.append)
    assert state.load_folder(folder)
    first = state.entries()[0].record
    assert first.status is FrameStatus.UNREADABLE and "truncated" in first.message
    assert notices[-1].level == "error" and state.view().image is None
    assert state.run_all()
    assert state.wait(300)
    status = {e.name: e.record.status.value for e in state.entries()}
    assert status == {"a_truncated.png": "unreadable", "b_notag.png": "not_seeded", "c_good.png": "ok"}
    assert any(n.level == "warning" and "no AprilTag" in n.text for n in notices)
    assert not state.run_all() and notices[-1].title == "Nothing to run"
    # Real data without a calibration folder or five sharp frames: no reference camera, and why.
    with pytest.raises(AlignmentError, match=r"needs ≥5 finished sharp frames, a calibration/ folder, or "
                                             r"ground truth \(0 sharp frames finished\)"):
        AlignmentCache(state).frame("c_good.png")


def test_pattern_that_matches_nothing_leaves_frames_unseeded(dataset: Path, tmp_path: Path) -> None:
    other = tmp_path / "other_tag.yaml"
    other.write_text((dataset / "pattern.yaml").read_text().replace("index: 0", "index: 5"))
    state = AppState(FAST)
    assert state.load_folder(dataset / "sharp", other)
    assert state.run_frame()
    assert state.wait(300)
    entry = state.entries()[0]
    assert entry.record.status is FrameStatus.NOT_SEEDED
    assert "found tag ids [0], the pattern has [5]" in entry.record.message
    assert state.notices[-1].level == "warning" and len(state.view().result.blocks) == 0


def test_current_frame_survives_the_image_cache(dataset: Path) -> None:
    state = AppState(FAST, image_cache=1)
    assert state.load_folder(dataset)
    state.image("blurry/0000.png")
    assert state.view().image is not None and state.view().entry.name == "sharp/0000.png"


def test_uploaded_frame_joins_the_open_dataset(dataset: Path, tmp_path: Path) -> None:
    state = AppState(FAST)
    with pytest.raises(DatasetError, match="open a folder or upload a pattern YAML first"):
        state.add_frame(tmp_path / "x.png", "upload/x.png")
    assert state.load_folder(dataset)
    path = tmp_path / "x.png"
    path.write_bytes((dataset / "sharp" / "0000.png").read_bytes())
    assert state.add_frame(path, "upload/x.png", "sharp") == 2
    assert state.add_frame(path, "upload/x.png") == 3
    assert [e.name for e in state.entries()][2:] == ["upload/x.png", "upload/x-2.png"]
    assert state.current == 3 and state.view().image is not None


@pytest.mark.slow
def test_uploaded_pattern_starts_a_dataset_of_uploads(dataset: Path, tmp_path: Path) -> None:
    state = AppState(FAST)
    notices = []
    state.subscribe_notices(notices.append)
    bad = tmp_path / "bad.yaml"
    bad.write_text("num_star_segments: 7\n")
    assert not state.set_pattern(bad)
    assert state.dataset is None and notices[-1].level == "error" and "bad.yaml" in notices[-1].text
    pattern = tmp_path / "uploaded.yaml"
    pattern.write_text((dataset / "pattern.yaml").read_text())
    assert state.set_pattern(pattern)
    assert state.dataset.pattern_path == pattern and state.entries() == [] and state.dataset.truth is None
    frame = tmp_path / "frame.png"
    frame.write_bytes((dataset / "sharp" / "0000.png").read_bytes())
    assert state.add_frame(frame, "upload/frame.png", "sharp") == 0
    assert state.run_frame() and state.wait(300)
    entry = state.entries()[0]
    assert entry.record.status is FrameStatus.OK and entry.record.accepted > 10


@pytest.mark.slow
def test_replacing_the_pattern_clears_results_and_keeps_truth_only_for_the_same_target(
        dataset: Path, tmp_path: Path) -> None:
    state = AppState(FAST)
    assert state.load_folder(dataset) and state.run_frame() and state.wait(300)
    assert state.results()
    same = tmp_path / "same.yaml"
    same.write_text("# the same target\n" + (dataset / "pattern.yaml").read_text())
    assert state.set_pattern(same)
    assert state.results() == {} and {e.record.status for e in state.entries()} == {FrameStatus.PENDING}
    assert state.dataset.truth is not None and len(state.entries()) == 2
    other = tmp_path / "other.yaml"
    other.write_text((dataset / "pattern.yaml").read_text().replace("index: ", "index: 1"))
    before = state.dataset.pattern
    notices = []
    state.subscribe_notices(notices.append)
    assert state.set_pattern(other)
    tag = state.dataset.pattern.apriltags[0].index
    assert tag == int(f"1{before.apriltags[0].index}") and state.dataset.truth is None
    assert [n.title for n in notices] == ["Ground truth not used", "Pattern in use"]


@pytest.mark.slow
def test_error_field_and_poses(finished: tuple[AppState, list[Topic]]) -> None:
    finished, _ = finished
    results = finished.results()
    assert set(results) == {"sharp/0000.png", "blurry/0000.png"}
    truth = finished.dataset.truth
    for name, (result, flt, _) in results.items():
        field = error_field(result, flt, truth.frame(name))
        assert field.source == "ground truth" and len(field.index) > 10 and field.rms < 0.3
        local = error_field(result, flt, None)
        assert local.source == "local alignment" and local.quad.shape == (len(local.index), 4, 2)
    poses = feature_poses(finished.dataset.pattern, results)
    true = truth_poses(truth)
    assert poses.source == "approximate camera" and set(poses.poses) == set(true.poses)
    for name, pose in poses.poses.items():
        assert np.linalg.norm(pose.camera_center - true.poses[name].camera_center) < 0.01
    assert abs(poses.fov - true.fov) < 0.05


@pytest.mark.slow
def test_alignment_follows_the_thresholds_and_covers_the_used_frames(
        finished: tuple[AppState, list[Topic]]) -> None:
    state, _ = finished
    cache = AlignmentCache(state)
    assert cache.reference().reference.source == "ground-truth camera"
    name = "blurry/0000.png"
    flt = state.results()[name][1]
    a = cache.frame(name)
    assert a.num_blocks == filter_counts(flt).kept >= 12 and a.median_error < 0.1
    assert cache.frame(name) is a
    blocks = state.results()[name][0].blocks
    losses = sorted(blocks.loss[a.index] / noise_scale(blocks.noise_var[a.index]))  # in tau_L's units
    defaults = QualitySettings()
    try:
        state.refilter(tau_loss=losses[-3])
        assert cache.frame(name).num_blocks < a.num_blocks
        state.refilter(tau_loss=0.0)
        with pytest.raises(AlignmentError, match="0 blocks kept"):
            cache.frame(name)
        state.refilter(tau_loss=defaults.tau_loss, min_sigma_major=0.0)
        assert cache.frame(name) is a
        overview = cache.overview()
        assert set(overview.aligned) | set(overview.ill_conditioned) == {"sharp/0000.png", name}
        assert overview.dropped == 0 and 0 < overview.median_error < 0.1
        fields = used_frame_fields(state, cache)
        assert fields.source == "global alignment" and set(fields.fields) == set(overview.aligned)
        assert used_frame_fields(state, cache, "ground truth").source == "ground truth"
    finally:
        state.refilter(defaults.tau_be, defaults.tau_loss, defaults.min_sigma_major)
    poses = alignment_poses({n: cache.frame(n) for n in state.results()}, cache.reference().reference.camera)
    true = truth_poses(state.dataset.truth)
    assert poses.source == "global alignment" and set(poses.poses) == set(true.poses)
    for n, pose in poses.poses.items():
        assert np.linalg.norm(pose.camera_center - true.poses[n].camera_center) < 0.001


def test_ambiguity_demo_keeps_the_image_and_moves_the_star() -> None:
    for delta in ((0, 0), (MAX_SHIFT, -2), (-MAX_SHIFT, MAX_SHIFT)):
        demo = ambiguity_demo(delta)
        assert np.abs(demo.residual).max() < 1e-9
        assert np.allclose(demo.star_centre, np.array([TILE_PX / 2, TILE_PX / 2]) + delta)
        assert np.allclose(demo.centroid, ambiguity_demo((0, 0)).centroid - np.array(delta), atol=1e-9)
    with pytest.raises(ValueError, match="pushes kernel weight"):
        ambiguity_demo((MAX_SHIFT + 5, 0))


def test_alignment_demo_local_then_global_alignment_pins_the_shift_down() -> None:
    exact = alignment_demo((3, -2), scatter_px=1.5, noise_px=0.0)
    deconv, local, aligned = exact.steps
    assert deconv.corner_gap_rms > 0.5 and deconv.rms > 3.0
    # Local alignment removes the per-block shifts up to one common shift of the target (up to
    # the float32 of cv2.getPerspectiveTransform)...
    assert local.corner_gap_rms < 1e-4
    assert np.allclose(local.error, local.error.mean(axis=0), atol=1e-4)
    assert np.linalg.norm(local.error.mean(axis=0) - (3, -2)) < 0.5
    # ...which global alignment, against an exact camera, finds.
    assert np.allclose(exact.x_g, local.error.mean(axis=0), atol=1e-3) and aligned.rms < 1e-3
    noisy = [alignment_demo((3, -2), seed=seed) for seed in range(3)]
    for demo in noisy:
        assert demo.steps[1].corner_gap_rms < 0.1 and demo.steps[2].rms < 0.25 < 3.0 < demo.steps[1].rms


@pytest.mark.slow
def test_views_draw_rgb_images(finished: tuple[AppState, list[Topic]]) -> None:
    pytest.importorskip("viser")
    finished, _ = finished
    from views.ambiguity import alignment_image, demo_image
    from views.errors import colour_wheel, direction_colours, draw_cells, draw_errors, draw_quiver
    from views.frame_view import draw_frame
    from views.frames import stage_line
    from views.inspect import block_images, jump_target, scatter_plots
    from views.psf_field import psf_mosaic
    from views.tuning import alignment_lines

    finished.select_frame(1)
    view = finished.view()
    # where the frame's time went: the growth's stages, in the order they ran
    line = stage_line(view.entry.record, least_s=0.0)
    assert line.startswith("time by stage: seeding ") and line.index("free PSFs") < line.index("alignment")
    assert stage_line(view.entry.record, least_s=1e9) == ""
    worst = jump_target(view, "highest loss")
    loss = view.result.blocks.loss
    assert loss[worst] == loss[np.isfinite(loss)].max()
    longest = jump_target(view, "longest blur for its square")
    ratio = view.result.blocks.blur_per_square
    assert ratio[longest] == ratio[np.isfinite(loss) & np.isfinite(ratio)].max() > 0
    assert finished.select_block(worst)
    view = finished.view()
    images = [draw_frame(view, mode, True, True) for mode in ("kept / removed", "loss", "boundary energy")]
    images += [psf_mosaic(view, 0.9, "kept blocks"), block_images(view, worst), scatter_plots(view),
               demo_image(ambiguity_demo((2, 1))), alignment_image(alignment_demo((1, 0))),
               draw_errors(view.image, error_field(view.result, view.filter, view.truth), 0.2)]
    field = error_field(view.result, view.filter, view.truth, AlignmentCache(finished).frame(view.entry.name))
    assert field.source == "global alignment"
    lines = alignment_lines(AlignmentCache(finished), view.entry.name)
    assert lines[0].startswith("**alignment error** after global alignment: median ")
    assert "(reference: ground-truth camera)" in lines[0]
    # No pre-filter by default: the sharp and the blurry frame are both aligned.
    assert lines[1].startswith("2 aligned frames: alignment median ")
    assert "dropped by the pre-filter" not in lines[1]
    images += [draw_quiver(view.image, (416, 312), field.centre, field.error, 0.02),
               draw_quiver(None, (416, 312), field.centre, field.error, 0.02),
               draw_cells((416, 312), field.centre, field.error, 0.02, 8)]
    for image in images:
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3 and image.std() > 5
    outside = int(np.flatnonzero(view.result.blocks.status == BlockStatus.OUTSIDE_IMAGE.value)[0])
    assert block_images(view, outside).shape[2] == 3
    colours = direction_colours(np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]), 1.0)
    assert colours.tolist() == [[127, 254, 127], [254, 127, 127], [0, 0, 0]]
    assert colour_wheel().shape == (90, 90, 3)


def test_serve_opens_the_folder_without_a_browser(dataset: Path, tmp_path: Path) -> None:
    pytest.importorskip("viser")
    from app import serve

    server, app = serve(dataset, None, 0, settings=FAST)
    try:
        assert server.get_port() > 0 and app.state.dataset.folder == dataset
        assert len(app.panels) == 8
        assert not app.state.load_folder(tmp_path / "missing") and app.state.dataset.folder == dataset
    finally:
        app.close()
        server.stop()
