"""The app's calibration without a browser: inputs and frame statuses at the thresholds, the run
(extracting what is missing first), its figures against the engine's, its assessment without ground
truth, cancel, export and the σ_major pre-filter of sharp frames."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from blurcalib.calib.joint import JointSettings, calibrate_generic
from blurcalib.calib.lens_bias import correct_features
from blurcalib.calib.sequence import MIN_PARAMETRIC_FRAMES, SequenceSettings
from blurcalib.calib.sharp import calibrate_sharp
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.uncertainty import cross_validation_diff
from blurcalib.calib.validation import ValidationSettings
from blurcalib.camera.files import read_generic_yaml
from blurcalib.camera.parametric import load_camera_yaml
from blurcalib.growth.quality import QualitySettings
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import FeatureTable
from blurcalib.paper.generic import projection_errors
from blurcalib.sim.synth import SynthConfig
from state import AppState, Topic, discover
from state.calibration import (
    EXPORT_DIR,
    OPENCV_CAMERA_FILE,
    STAGES,
    USED,
    CalibrationRunner,
    CalibrationSettings,
    collect_inputs,
    input_coverage,
)
from state.figures import generic_poses
from tests.state.test_app_state import FAST, make_dataset
from views.calibration import (
    cross_validation_image,
    difference_image,
    draw_coverage,
    residual_image,
    summary,
    trust_summary,
    uncertainty_image,
)

pytestmark = pytest.mark.slow

CONFIG = SynthConfig(sharp=2, blurry=2, square_px=(36.0, 42.0), max_tilt_deg=30.0, blur_min_px=3.0,
                     blur_max_px=4.0, seed=5)
"""2 sharp and 2 little-blurred 416 x 312 frames: the blurry ones fail the 3.8 px pre-filter."""
SETTINGS = CalibrationSettings(SequenceSettings(generic=JointSettings(cell_px=40.0),
                                                blurry_in_parametric=True))

PAPER = QualitySettings(min_sigma_major=3.8)
"""The paper's thresholds: its 3.8 px pre-filter drops the small dataset's blurry frames (about 0.5 px
of blur), which the tests use to see what the pre-filter does (blurcalib's default is no pre-filter)."""


@pytest.fixture(scope="module")
def state(tmp_path_factory: pytest.TempPathFactory) -> AppState:
    """The four frames extracted (two growth fronts each)."""
    s = AppState(FAST)
    assert s.load_folder(make_dataset(tmp_path_factory.mktemp("appcal") / "data", CONFIG))
    assert s.run_all() and s.wait(600)
    s.refilter(PAPER.tau_be, PAPER.tau_loss, PAPER.min_sigma_major)
    return s


@pytest.fixture
def defaults(state: AppState):
    yield state
    state.refilter(PAPER.tau_be, PAPER.tau_loss, PAPER.min_sigma_major)


def test_the_pre_filter_applies_to_blurry_frames_only(defaults: AppState) -> None:
    state = defaults
    results = state.results()
    kinds = {e.name: e.kind for e in state.entries()}
    for name, (_, flt, _) in results.items():
        assert flt.centre_sigma_major < PAPER.min_sigma_major
        assert flt.frame_ok == (kinds[name] == "sharp"), name
    sharp = next(i for i, e in enumerate(state.entries()) if e.kind == "sharp")
    name = state.entries()[sharp].name
    try:
        state.set_kind(sharp, "blurry")
        assert not state.results()[name][1].frame_ok
    finally:
        state.set_kind(sharp, "sharp")
    assert state.results()[name][1].frame_ok


def test_inputs_coverage_and_statuses_follow_the_thresholds(defaults: AppState) -> None:
    state = defaults
    runner = CalibrationRunner(state, SETTINGS)
    inputs = collect_inputs(state, SETTINGS)
    assert set(inputs.sharp.frame) == {"sharp/0000.png", "sharp/0001.png"} and len(inputs.blurry) == 0
    status = runner.statuses()
    for name in ("blurry/0000.png", "blurry/0001.png"):
        assert status[name].startswith("dropped by the pre-filter (centre σ_major "), status[name]
        assert status[name].endswith(" px < 3.8 px)")
    assert status["sharp/0000.png"] == status["sharp/0001.png"] == "usable: run the calibration"
    accepted = sum(len(r.features) for n, (r, _, _) in state.results().items() if n.startswith("sharp"))
    assert len(inputs.sharp) == accepted
    cov = input_coverage(inputs, SETTINGS.cell_px)
    assert cov.sharp.sum() == accepted and cov.blurry.sum() == 0 and cov.sharp.shape == (8, 11)

    state.refilter(min_sigma_major=0.0)
    inputs = collect_inputs(state, SETTINGS)
    kept = {n: int(f.kept.sum()) for n, (_, f, _) in state.results().items() if n.startswith("blurry")}
    assert all(k >= SETTINGS.sequence.alignment.min_blocks for k in kept.values())
    assert len(inputs.blurry) == sum(kept.values())
    cov = input_coverage(inputs, SETTINGS.cell_px)
    assert cov.blurry.sum() == sum(kept.values()) and cov.total == len(inputs.sharp) + len(inputs.blurry)
    assert set(runner.statuses().values()) == {"usable: run the calibration"}

    state.refilter(tau_loss=0.0)
    status = runner.statuses()
    assert status["blurry/0000.png"] == "too few kept blocks (0 < 12)"
    assert status["sharp/0000.png"] == "usable: run the calibration"


def _engine(state: AppState):
    """The engine's calibration of the app's inputs, called directly (with the lens-bias correction)."""
    inputs = collect_inputs(state, SETTINGS)
    table = FeatureTable.concat([inputs.sharp, inputs.blurry])
    first = calibrate_sharp(table, state.dataset.pattern, inputs.image_size, min_frames=MIN_PARAMETRIC_FRAMES,
                            min_features=SETTINGS.sequence.alignment.min_blocks)
    sharp, blurry = (correct_features(t, inputs.blocks, first.camera) for t in (inputs.sharp, inputs.blurry))
    parametric = calibrate_sharp(FeatureTable.concat([sharp, blurry]), state.dataset.pattern,
                                 inputs.image_size, min_frames=MIN_PARAMETRIC_FRAMES,
                                 min_features=SETTINGS.sequence.alignment.min_blocks)
    blurry = correct_features(inputs.blurry, inputs.blocks, parametric.camera)  # under the final camera
    generic = calibrate_generic(sharp, blurry, parametric, state.dataset.pattern,
                                inputs.image_size, JointSettings(cell_px=SETTINGS.cell_px, route="joint"))
    return parametric, generic


def test_calibration_run_cancel_and_export(defaults: AppState, tmp_path: Path) -> None:
    state = defaults
    state.refilter(min_sigma_major=0.0)
    runner = CalibrationRunner(state, SETTINGS)
    topics: list[Topic] = []
    state.subscribe(topics.append)
    notices = len(state.notices)
    assert runner.run() and not runner.run()  # one run at a time
    assert runner.wait(600) and not runner.is_running
    result = runner.result
    assert result is not None and Topic.CALIBRATION in topics
    assert result.parametric_with_blurry  # 2 sharp frames < 5
    # every frame was extracted: the run went straight to the calibration, without a notice
    assert [n.title for n in state.notices[notices:]] == ["Calibration done"]

    # The figures the app shows are the engine's (two runs of its least squares agree to ~1e-9 px).
    parametric, generic = _engine(state)
    assert result.parametric.median_error == pytest.approx(parametric.median_error, abs=1e-7)
    assert result.generic.median_error == pytest.approx(generic.median_error, abs=1e-7)
    assert result.generic.rms_error == pytest.approx(generic.rms_error, abs=1e-7)
    assert set(result.generic.poses) == {e.name for e in state.entries()}
    # Coverage counts every used observation once, sharp and blurry apart.
    blurry_rows = np.isin(result.generic.frame, result.generic.blurry_frames)
    assert result.coverage.total == len(result.generic.observed)
    assert result.coverage.blurry.sum() == blurry_rows.sum() == len(result.inputs.blurry)
    assert result.coverage.sharp.sum() == len(result.inputs.sharp)
    assert set(runner.statuses().values()) == {USED}
    # Error against the true camera, as the experiment measures it.
    x0, y0, x1, y1 = result.generic.model.area_opencv
    xx, yy = np.meshgrid(np.arange(np.ceil(x0), x1, SETTINGS.lattice_px),
                         np.arange(np.ceil(y0), y1, SETTINGS.lattice_px))
    err = projection_errors(state.dataset.truth.camera, result.generic.model,
                            np.column_stack([xx.ravel(), yy.ravel()]))
    assert result.truth.generic_median == pytest.approx(np.nanmedian(err), abs=1e-12)
    assert result.truth.pixels == np.isfinite(err).sum() > 100
    assert 0 < result.truth.generic_median < 1.0 and 0 < result.truth.parametric_median < 1.0
    diff = result.difference[2]
    assert np.isfinite(diff).any() and np.nanmax(np.linalg.norm(diff, axis=2)) < 2.0
    poses = generic_poses(result.generic)
    assert poses.source == "generic bundle adjustment" and set(poses.poses) == set(result.generic.poses)
    observed, residuals = result.frame_residuals("blurry/0000.png")
    assert len(observed) == len(residuals) == (result.generic.frame == "blurry/0000.png").sum() > 0
    # The assessment: both generic cameras' uncertainty maps; 4 frames are too few to hold any out.
    trust = result.trust
    assert trust is not None and result.trust_failure == ""
    assert result.generic_sharp is not None and set(result.generic_sharp.frames) == {"sharp/0000.png",
                                                                                     "sharp/0001.png"}
    for unc in (trust.uncertainty, trust.uncertainty_sharp):
        ny, nx = unc.shape
        assert ny > 1 and nx > 1 and unc.x.shape == unc.y.shape == unc.sigma_px.shape == (ny * nx,)
        assert np.all(np.diff(unc.x.reshape(unc.shape), axis=1) > 0) and np.all(unc.sigma_px[
            np.isfinite(unc.sigma_px)] > 0) and unc.noise_px > 0
    # the blurry frames widen the calibrated area and lower the uncertainty where both cameras see
    assert trust.uncertainty.x.max() - trust.uncertainty.x.min() > \
        trust.uncertainty_sharp.x.max() - trust.uncertainty_sharp.x.min()
    assert trust.uncertainty.median() < trust.uncertainty_sharp.median()
    assert trust.validation is None and isinstance(trust.guidance, list)
    assert all(isinstance(g, str) and g.startswith("capture ") for g in trust.guidance)
    assert result.trust.to_dict()["blurry_frames_gain"]["uncertainty_median_px"][1] == pytest.approx(
        trust.uncertainty.median(), abs=1e-5)
    text = trust_summary(result, 0.05)
    assert "**Held-out reprojection error**: not measured: 4 frames in the generic fit, the k-fold " \
           "validation needs at least 10." in text
    assert f"| generic, sharp + blurry frames | {trust.uncertainty.median():.4f} |" in text
    assert f"| generic, sharp frames | {trust.uncertainty_sharp.median():.4f} |" in text
    assert "**What the blurry frames bought** (sharp only → sharp + blurry)" in text
    assert all(g.replace("_", "\\_") in text for g in trust.guidance)
    # The view's figures and summary.
    text = summary(result, runner.statuses())
    assert f"generic median error: **{result.generic.median_error:.4f} px**" in text
    assert "At the current thresholds: 4 of 4 frames used." in text
    assert f"{result.truth.generic_median:.4f}" in text
    maps = uncertainty_image(result)
    assert maps.shape[1] > 2 * maps.shape[0]  # two maps side by side
    diff = cross_validation_diff(result.generic_sharp.model, result.generic.model)
    images = [draw_coverage(result.coverage), residual_image(result, None, None),
              residual_image(result, "blurry/0000.png", state.image("blurry/0000.png")),
              difference_image(result), maps, cross_validation_image(diff, result.inputs.image_size)]
    for image in images:
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3 and image.max() > 0
        assert image.std() > 10  # not blank
    # Another fit's field (the global-shutter camera's when the rolling shutter was modelled) on the
    # result's colour scale: the sharp-only fit has fewer observations, so other cells are lit.
    other = residual_image(result, None, None, result.generic_sharp)
    assert other.shape == images[1].shape and np.abs(other.astype(int) - images[1]).max() > 50

    # A threshold change shows in the statuses at once; the result stays until the next run.
    state.refilter(min_sigma_major=3.8)
    status = runner.statuses()
    assert status["blurry/0000.png"].startswith("dropped by the pre-filter")
    assert status["sharp/0000.png"] == USED
    state.refilter(min_sigma_major=0.0)

    # Cancel during the generic stage, then during the assessment: the previous result is kept.
    cancel_at: list[str] = []

    def cancel(topic: Topic) -> None:
        progress = runner.progress()
        if topic is Topic.CALIBRATION and progress.running and STAGES[progress.stage] in cancel_at:
            runner.cancel()

    state.subscribe(cancel)
    for stage in ("generic calibration", "assessment (held-out error, uncertainty)"):
        cancel_at[:] = [stage]
        notices = len(state.notices)
        assert runner.run() and runner.wait(600)
        assert runner.result is result
        assert [n.title for n in state.notices[notices:]] == ["Calibration cancelled"]
    cancel_at.clear()

    # Export and read back.
    paths = runner.export(tmp_path / "export")
    names = {p.name for p in paths}
    assert {"intrinsics0.yaml", "undistortion_map.npz", OPENCV_CAMERA_FILE} <= names
    model = read_generic_yaml(tmp_path / "export" / "intrinsics0.yaml")
    px = np.array([[200.0, 150.0], [120.0, 100.0]])
    assert np.allclose(model.pixel_to_ray(px), result.generic.model.pixel_to_ray(px), atol=1e-9)
    camera = load_camera_yaml(tmp_path / "export" / OPENCV_CAMERA_FILE)
    assert camera.fx == pytest.approx(result.parametric.camera.fx, rel=1e-12)
    assert camera.k1 == pytest.approx(result.parametric.camera.k1, rel=1e-9, abs=1e-15)
    maps = np.load(tmp_path / "export" / "undistortion_map.npz")
    assert maps["map_x"].shape == (312, 416) and np.isfinite(maps["map_x"]).any()
    assert state.notices[-1].title == "Calibration exported" and "intrinsics0.yaml" in state.notices[-1].text
    default = runner.export()
    assert default[0].parent == state.dataset.folder / EXPORT_DIR and default[0].is_file()
    # Its images are not frames of the dataset.
    assert [f.name for f in discover(state.dataset.folder).frames] == [e.name for e in state.entries()]

    # Opening a folder drops the result.
    assert state.load_folder(state.dataset.folder)
    assert runner.result is None


def test_sharp_frames_only_label_and_held_out_table(defaults: AppState) -> None:
    """At the paper's pre-filter no blurry frame is an input: the parametric camera is labelled as
    the sharp frames' and the generic camera is assessed alone (validation lowered to 2 frames)."""
    trust = TrustSettings(validation=ValidationSettings(min_frames=2, folds=2))
    settings = replace(SETTINGS, sequence=replace(SETTINGS.sequence, trust=trust))
    runner = CalibrationRunner(defaults, settings)
    assert runner.run() and runner.wait(600)
    result = runner.result
    assert result is not None and not result.parametric_with_blurry
    assert not result.generic.blurry_frames and result.generic_sharp is None
    text = summary(result, runner.statuses())
    assert "| parametric (Brown-Conrady, sharp frames) |" in text and "sharp and blurry" not in text
    trust = result.trust
    assert trust is not None and trust.uncertainty_sharp is None and trust.cross_validation is None
    scores = trust.validation.scores
    # one sharp frame per fold is too few for a parametric camera: it is not scored (never by a
    # camera that saw the frame)
    assert set(scores) == {"generic"} and trust.validation.folds == 2
    assert set(trust.validation.fold_of) == {"sharp/0000.png", "sharp/0001.png"}
    g = scores["generic"]
    assert g.frames == 2 and 0 < g.median_px < 0.1 and g.rms_px >= g.median_px / 2
    text = trust_summary(result, 0.05)
    assert f"| generic | {g.median_px:.4f} | {g.rms_px:.4f} | 2 |" in text
    assert "| parametric (Brown-Conrady) |" not in text
    assert "no blurry frame entered the generic fit" in text and "not measured (a half" in text
    assert uncertainty_image(result).shape[1] < 2 * uncertainty_image(result).shape[0]  # one map


def test_coverage_fills_in_frame_by_frame_and_a_failed_run_says_why(state: AppState, tmp_path: Path) -> None:
    fresh = AppState(FAST)
    assert fresh.load_folder(state.dataset.folder, out=tmp_path / "fresh")  # not the extracted frames
    runner = CalibrationRunner(fresh, SETTINGS)
    assert runner.inputs().image_size == (0, 0)
    assert set(runner.statuses().values()) == {"not extracted"}
    assert runner.run(extract=False) and runner.wait(60)
    assert runner.result is None
    assert fresh.notices[-1].title == "Calibration failed" and "no usable frame" in fresh.notices[-1].text
    fresh.refilter(min_sigma_major=0.0)
    totals = []
    for index in (0, 2):  # sharp/0000.png, then blurry/0000.png
        assert fresh.run_frame(index) and fresh.wait(600)
        totals.append(input_coverage(runner.inputs(), SETTINGS.cell_px))
    name = fresh.entries()[2].name
    kept = int(fresh.results()[name][1].kept.sum())
    assert totals[0].sharp.sum() == len(fresh.results()["sharp/0000.png"][0].features) > 0
    assert totals[0].blurry.sum() == 0 and totals[1].blurry.sum() == kept > 0
    assert np.array_equal(totals[1].sharp, totals[0].sharp)
    assert runner.statuses()["sharp/0001.png"] == "not extracted"
    # Run calibration extracts the rest first: every frame is used.
    assert runner.run() and runner.wait(900)
    assert {e.record.status for e in fresh.entries()} == {FrameStatus.OK}
    assert runner.result is not None and set(runner.statuses().values()) == {USED}
