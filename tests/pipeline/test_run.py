"""The whole pipeline on a small simulated dataset, and its errors for unusable input."""

from __future__ import annotations

import csv
import json
import os
import shutil
from functools import partial
from pathlib import Path

import cv2
import numpy as np
import pytest

import blurcalib.pipeline.frames as frame_rows
import blurcalib.pipeline.outputs as outputs
import blurcalib.pipeline.run as pipeline
from blurcalib.calib.alignment import AlignmentSettings
from blurcalib.calib.report import error_direction_image
from blurcalib.calib.sequence import SequenceSettings
from blurcalib.calib.sharp import load_calibration
from blurcalib.camera.files import read_generic_yaml
from blurcalib.camera.parametric import BrownConrady
from blurcalib.cli import main
from blurcalib.growth.quality import QualitySettings
from blurcalib.io.atomic import OutputError
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import FeatureFlags, read_feature_table
from blurcalib.pipeline.run import PUBLISHED, PipelineError, PipelineSettings, run_from_features, run_pipeline
from blurcalib.runs.events import FrameDone, RunEvent
from blurcalib.sim.accuracy import camera_accuracy_lines, true_accuracies
from blurcalib.sim.evaluate import camera_accuracy, evaluate_features
from blurcalib.sim.synth import SynthConfig, write_dataset
from blurcalib.sim.truth import TrueCamera, load_ground_truth
from blurcalib.target.pattern import layout_pattern


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    model = BrownConrady(fx=420.0, fy=420.0, cx=239.6, cy=179.3, k1=0.02, k2=-0.03, p1=0.0003,
                         p2=-0.0002, k3=0.0, width=480, height=360)
    cfg = SynthConfig(sharp=6, blurry=2, square_px=(24.0, 30.0), max_tilt_deg=45.0,
                      blur_min_px=4.0, blur_max_px=6.0, seed=5)
    folder = tmp_path_factory.mktemp("ds")
    write_dataset(folder, cfg, camera=TrueCamera(model))
    cv2.imwrite(str(folder / "blurry" / "0002_1x1.png"), np.zeros((1, 1), np.uint8))  # a bad frame
    return folder


def report_camera(out: Path) -> BrownConrady:
    """The parametric camera a run saved."""
    return load_calibration(out / "calibration").camera


def _settings() -> PipelineSettings:
    return PipelineSettings(calibration=SequenceSettings(quality=QualitySettings(min_sigma_major=0.0)))


def _frames(dataset):
    return sorted((dataset / "sharp").glob("*.png")), sorted((dataset / "blurry").glob("*.png"))


@pytest.fixture(scope="module")
def finished(tmp_path_factory, dataset):
    """One finished pipeline run: its output folder and report."""
    out = tmp_path_factory.mktemp("run") / "out"
    return out, run_pipeline(*_frames(dataset), layout_pattern(), out, _settings())


def _published(out) -> dict[str, bytes]:
    """The top-level outputs of a run folder, by relative path (report.json aside: it names
    its folder)."""
    files = [p for name in PUBLISHED if name != "report.json" for p in
             ((out / name).rglob("*") if (out / name).is_dir() else [out / name])]
    return {str(p.relative_to(out)): p.read_bytes() for p in files if p.is_file()}


def _done(seen: list[tuple[str, str]], stage: str, event: RunEvent) -> None:
    """A pipeline's progress callback: the frames finished, by stage, into ``seen``."""
    if isinstance(event, FrameDone):
        seen.append((stage, event.record.frame))


@pytest.mark.slow
def test_pipeline_end_to_end(finished, dataset) -> None:
    out, report = finished
    pattern = layout_pattern()
    assert report.calibration["num_frames"] == 6
    assert report.calibration["median_error_px"] < 0.1
    statuses = {r.frame: r.status for r in report.frames}
    assert set(statuses) == {f"sharp/{i:04d}.png" for i in range(6)} | {
        "blurry/0000.png", "blurry/0001.png", "blurry/0002_1x1.png"}
    bad = next(r for r in report.frames if r.frame == "blurry/0002_1x1.png")
    assert bad.status is FrameStatus.UNREADABLE and "is 1x1 px, smaller than" in bad.verdict.reason
    assert "used" in statuses.values() or "ill_conditioned" in statuses.values()
    for key in ("features", "reference_features", "frames", "error_directions_sharp",
                "frame_errors"):
        assert Path(report.outputs[key]) == out / Path(report.outputs[key]).name
        assert Path(report.outputs[key]).is_file()
    saved = json.loads((out / "report.json").read_text())
    assert saved["counts"] == report.counts
    assert (out / "calibration" / "camera.yaml").is_file() and not (out / ".staging").exists()
    table = read_feature_table(out / "features.csv")
    assert np.any(table.flags & int(FeatureFlags.SHARP_FRAME))
    assert np.all(table.flags & int(FeatureFlags.LENS_CORRECTED))  # every centre, sharp and blurry
    acc = evaluate_features(table, load_ground_truth(dataset), pattern, skip_flags=0)
    assert acc and max(a.median for a in acc) < 0.1


@pytest.mark.slow
def test_demo_accuracy_lines_name_each_camera(finished, dataset) -> None:
    """The demo's report against the truth: a line per camera of the run with its own median,
    and the generic cameras' true error over their predicted uncertainty."""
    out, _ = finished
    truth = load_ground_truth(dataset)
    found = true_accuracies(out, truth.camera)
    lines = camera_accuracy_lines(found)
    assert [line.split(" median ")[0].strip() for line in lines[1:]] == [
        "parametric, sharp frames", "generic, sharp frames", "generic, sharp + blurry frames"]
    assert f"median {camera_accuracy(truth.camera, report_camera(out)).median:.4f}," in lines[1]
    joint = read_generic_yaml(out / "calibration" / "intrinsics0.yaml")
    assert f"median {camera_accuracy(truth.camera, joint).median:.4f}," in lines[3]
    assert all(0.25 < t.honesty < 4.0 for t in found[1:])
    assert all(f"true error {t.honesty:.2f} x the predicted uncertainty" in line
               for t, line in zip(found[1:], lines[2:], strict=True))


@pytest.mark.slow
def test_pipeline_delivers_the_generic_camera(finished, dataset) -> None:
    """The default model: the generic camera of sharp and blurry frames together, in the reference
    tool's format, more accurate against the true camera than the parametric one."""
    out, report = finished
    truth = load_ground_truth(dataset)
    generic = read_generic_yaml(out / "calibration" / "intrinsics0.yaml")
    assert report.generic["median_error_px"] < 0.1 and report.generic["blurry_frames"] >= 1
    assert report.camera is not None and np.allclose(report.camera.model.grid, generic.grid, atol=1e-9)
    assert len(report.camera.frames) == report.generic["frames"] and "camera" not in report.to_dict()
    assert Path(report.outputs["error_directions_generic"]).is_file()
    for name in ("generic_poses.csv", "undistortion_map.npz", "generic_coverage.png"):
        assert (out / "calibration" / name).is_file()
    assert report.undistortion["projection"] == "pinhole" and report.undistortion["field_deg"] < 120
    assert str(np.load(out / "calibration" / "undistortion_map.npz")["projection"]) == "pinhole"
    rows = {r.frame: r for r in report.frames}
    for r in rows.values():
        assert r.status is FrameStatus.USED or r.verdict.reason, r
    # Joint route: a blurry frame with enough kept blocks is used whatever its orientation.
    assert all(r.status is FrameStatus.USED for r in rows.values()
               if r.kind == "blurry" and r.verdict.alignment in ("ok", "ill_conditioned"))
    parametric = camera_accuracy(truth.camera, report_camera(out))
    assert camera_accuracy(truth.camera, generic).median < parametric.median


@pytest.fixture()
def serial_opencv():
    """OpenCV on one thread: with its default threads the sharp-set calibration differs between
    runs in the last digits (aligned features moved by up to 4e-7 px between two runs)."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    yield
    cv2.setNumThreads(threads)


@pytest.mark.slow
def test_rerun_resumes_and_a_killed_write_never_mixes_runs(tmp_path, finished, dataset,
                                                          monkeypatch, serial_opencv) -> None:
    out = tmp_path / "out"
    shutil.copytree(finished[0], out)
    seen: list[tuple[str, str]] = []
    run_pipeline(*_frames(dataset), layout_pattern(), out, _settings(),
                 progress=partial(_done, seen))
    assert seen == [("blurry", "0002_1x1.png")]  # only the unreadable frame is retried
    reference = _published(out)
    run_pipeline(*_frames(dataset), layout_pattern(), out, _settings())
    assert _published(out) == reference  # bit-identical re-run
    before = {p: (out / p).read_bytes() for p in [*reference, "report.json"]}
    other = PipelineSettings(calibration=SequenceSettings(quality=QualitySettings(min_sigma_major=0.0),
                                                          alignment=AlignmentSettings(bias="bilinear"),
                                                          model="parametric"))

    # killed (as by kill -9, leaving a temporary file) while writing the set of a run with
    # other settings: the folder keeps the previous set whole, report.json included
    def killed(path, *args, **kwargs):
        (Path(path).parent / f".{Path(path).stem}.k1ll3d_x.tmp.png").write_bytes(b"half a PNG")
        raise KeyboardInterrupt

    monkeypatch.setattr(outputs, "save_frame_error_plot", killed)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(*_frames(dataset), layout_pattern(), out, other)
    monkeypatch.undo()
    assert {p: (out / p).read_bytes() for p in before} == before
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [".staging"]

    # killed while moving the new set into place: no report.json, so no reader takes it whole
    real_replace, moved = os.replace, []

    def replace_then_die(src, dst) -> None:
        if Path(src).parent == out / ".staging" and Path(dst).parent == out:
            if len(moved) == 3:
                raise KeyboardInterrupt
            moved.append(dst)
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace_then_die)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(*_frames(dataset), layout_pattern(), out, other)
    monkeypatch.undo()
    assert len(moved) == 3 and not (out / "report.json").exists()

    # the next run cleans up and publishes one whole set
    run_pipeline(*_frames(dataset), layout_pattern(), out, other)
    published = json.loads((out / "report.json").read_text())
    assert published["settings"]["calibration"]["model"] == "parametric" and published["generic"] is None
    assert published["undistortion"]["projection"] == "pinhole"  # the parametric camera's map
    assert np.load(out / "calibration" / "undistortion_map.npz")["map_x"].shape == (360, 480)
    assert (out / "features.csv").read_bytes() != reference["features.csv"]
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]
    run_pipeline(*_frames(dataset), layout_pattern(), out, _settings())
    assert _published(out) == reference


@pytest.mark.slow
def test_calibrate_reuses_an_extract_output(tmp_path, finished, dataset) -> None:
    """``blurcalib extract BLURRY --kind blurry --out OUT/blurry`` before ``calibrate --out OUT``: calibrate
    refits none of its frames (only the unreadable one is retried) and collects each once."""
    out = tmp_path / "out"
    pattern = dataset / "pattern.yaml"
    assert main(["extract", str(dataset / "blurry"), "--kind", "blurry", "--pattern", str(pattern), "--out",
                 str(out / "blurry")]) == 0
    extracted = (out / "blurry" / "features.csv").read_bytes()
    seen: list[tuple[str, str]] = []
    report = run_pipeline(*_frames(dataset), layout_pattern(), out, _settings(),
                          progress=partial(_done, seen))
    assert [name for stage, name in seen if stage == "blurry"] == ["0002_1x1.png"]
    assert sorted(name for stage, name in seen if stage == "sharp") == [f"{i:04d}.png" for i in range(6)]
    assert (out / "blurry" / "features.csv").read_bytes() == extracted
    blurry = read_feature_table(out / "blurry" / "features.csv")
    assert len(set(zip(blurry.frame, blurry.feature_id, strict=True))) == len(blurry)
    assert [r.frame for r in report.frames] == [r.frame for r in finished[1].frames]
    ours, theirs = read_feature_table(out / "features.csv"), read_feature_table(finished[0] / "features.csv")
    assert np.array_equal(ours.frame, theirs.frame) and np.array_equal(ours.feature_id, theirs.feature_id)
    assert np.allclose(ours.x, theirs.x, atol=1e-5) and np.allclose(ours.y, theirs.y, atol=1e-5)


@pytest.mark.slow
def test_foreign_output_folder_is_refused(tmp_path, dataset) -> None:
    out = tmp_path / "mine"
    (out / "calibration").mkdir(parents=True)
    user = {"features.csv": "my features", "frames.csv": "my frames", "psfs.npz": "my psfs",
            "calibration/camera.yaml": "my camera"}
    for name, text in user.items():
        (out / name).write_text(text)
    with pytest.raises(OutputError, match=r"mine: output folder is not empty and is not a blurcalib"):
        run_pipeline(*_frames(dataset), layout_pattern(), out, _settings())
    assert {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()} == set(user)
    assert all((out / name).read_text() == text for name, text in user.items())


@pytest.mark.slow
def test_mixed_resolution_is_refused(tmp_path, dataset) -> None:
    sharp = sorted((dataset / "sharp").glob("*.png"))
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 120), np.uint8))
    with pytest.raises(PipelineError, match=r"small.png \(120x100\)"):
        run_pipeline(sharp, [small], layout_pattern(), tmp_path / "out", _settings())


@pytest.mark.slow
def test_too_few_sharp_frames_and_wrong_pattern(tmp_path, dataset) -> None:
    sharp = sorted((dataset / "sharp").glob("*.png"))[:3]
    with pytest.raises(PipelineError, match="no AprilTag"):
        run_pipeline(sharp, [], layout_pattern(tag_index=5), tmp_path / "a", _settings())
    # with the pattern fixed, the frames are extracted again (not the old error repeated)
    with pytest.raises(PipelineError, match="sharp-set calibration"):
        run_pipeline(sharp, [], layout_pattern(), tmp_path / "a", _settings())
    assert (tmp_path / "a" / "sharp" / "features.csv").is_file()  # partial results kept


def test_error_direction_colours() -> None:
    xy = np.array([[4.0, 4.0], [12.0, 4.0], [20.0, 4.0]])
    res = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, 0.0]])  # down, right, none
    img = error_direction_image(xy, res, (24, 8), cell_px=8, saturate_px=0.5)
    # a = atan2(dy, dx): down is a = pi/2 -> RGB (254, 127, 127); right a = 0 -> (127, 254, 127).
    assert img[4, 4].tolist() == [127, 127, 254]
    assert img[4, 12].tolist() == [127, 254, 127]
    assert img[4, 20].tolist() == [0, 0, 0]


@pytest.mark.slow
def test_default_calibrate_uses_little_blur_and_gives_reasons(tmp_path, dataset, capsys) -> None:
    out = tmp_path / "out"
    assert main(["calibrate", "--sharp", str(dataset / "sharp"), "--blurry",
                 str(dataset / "blurry"), "--pattern", str(dataset / "pattern.yaml"),
                 "--out", str(out), "--workers", "1"]) == 0
    with open(out / "frames.csv", newline="", encoding="utf-8") as handle:
        table = list(csv.DictReader(handle))
    frames = [r["frame"] for r in table]
    assert sorted(frames) == sorted([f"sharp/{i:04d}.png" for i in range(6)]
                                    + ["blurry/0000.png", "blurry/0001.png", "blurry/0002_1x1.png"])
    status = {r["frame"]: r["status"] for r in table}
    reason = {r["frame"]: r["reason"] for r in table}
    assert status["blurry/0002_1x1.png"] == "unreadable"
    # 4-6 px of blur: the paper's 3.8 px pre-filter would drop both blurry frames; the defaults
    # keep them and the generic calibration uses them.
    blurry = ["blurry/0000.png", "blurry/0001.png"]
    assert "low_blur" not in status.values()
    assert all(status[f] == "used" for f in blurry)
    for f in frames:
        assert (status[f] == "used") == (reason[f] == ""), (f, status[f], reason[f])
    # "used" is exactly the set of frames whose features are written unflagged.
    features = read_feature_table(out / "features.csv")
    unflagged = set(features.frame[(features.flags & int(FeatureFlags.FILTERED_OUT)) == 0])
    assert unflagged == {f for f in frames if status[f] == "used"}
    assert "blurry frames:" in capsys.readouterr().out


def test_a_frame_with_blur_as_long_as_its_squares_is_told_so() -> None:
    """The ``too_few_blocks`` reason names the blur over square side when it is from
    ``BLUR_PER_SQUARE_LIMIT`` (1.25, median of the fitted blocks, unfitted ones ignored); below,
    it adds nothing."""
    from blurcalib.growth.seed import block_homography, line_kernel
    from blurcalib.io.results import BlockStatus, BlockTable
    from blurcalib.psf.kernel import psf_moments

    def table(blur_px: float) -> BlockTable:
        n = 4
        psf = np.repeat(line_kernel(blur_px, 0.3)[None], n, axis=0)
        m = psf_moments(psf)
        sigma = m.sigma_major.copy()
        sigma[0] = np.nan  # not fitted
        H = block_homography(np.diag([24.0, 24.0, 1.0]), np.arange(n, dtype=float), np.ones(n))
        return BlockTable(["f"] * n, np.arange(n), np.arange(n), np.ones(n, dtype=int),
                          [BlockStatus.ACCEPTED] * n, np.ones(n), np.zeros(n), sigma, m.sigma_minor,
                          m.eccentricity, m.orientation, m.centroid, H, np.zeros((n, 6)), psf)

    long, short = table(34.0), table(24.0)
    assert np.nanmedian(long.blur_per_square) > 1.3 and np.nanmedian(short.blur_per_square) < 1.05
    ratio = np.nanmedian(long.blur_per_square)
    assert frame_rows._blur_note(long).startswith(f"; its blur is {ratio:.2f} x the star squares' side")
    assert frame_rows._blur_note(short) == ""


@pytest.mark.slow
def test_final_fit_option_reaches_every_blurry_frame(tmp_path, dataset) -> None:
    """``extract --final-fit all`` fits the inner accepted blocks of a little-blurred frame (its
    window does not grow) over 1.5 x their square, and those blocks' centres move; the default
    leaves such a frame as the growth fitted it."""
    from blurcalib.io.results import read_block_table

    frame = str(dataset / "blurry" / "0000.png")
    pattern = str(dataset / "pattern.yaml")
    tables = {}
    for choice in ("adaptive", "all"):
        assert main(["extract", frame, "--kind", "blurry", "--pattern", pattern, "--out",
                     str(tmp_path / choice), "--final-fit", choice, "--workers", "1"]) == 0
        tables[choice] = read_block_table(tmp_path / choice)
    default, every = tables["adaptive"], tables["all"]
    assert np.all(default.loss_extent == 1.0)
    wide = every.loss_extent == 1.5
    assert wide.sum() >= 0.5 * every.accepted.sum() > 20
    assert np.all(every.accepted[wide])
    moved = np.linalg.norm(every.centre[wide] - default.centre[wide], axis=1)
    assert 0.0 < np.median(moved) < 0.1


@pytest.mark.slow
def test_demo_reads_as_a_result(finished, dataset) -> None:
    """The demo's account: the result first (what, how good against the truth, what the blurry
    frames bought), the coverage warnings as one line, the figures written (each with a legend
    strip below the image) and the terms explained."""
    import io

    from blurcalib.pipeline.text import report_lines
    from blurcalib.sim.demo import DemoLog, figure_lines, result_lines, term_lines

    out, report = finished
    truth = load_ground_truth(dataset)
    found = true_accuracies(out, truth.camera)
    doc = report.to_dict()
    lines = result_lines(doc, found, (truth.camera.model.width, truth.camera.model.height))
    assert lines[0] == "Result" and lines[1].startswith("  Calibrated: a simulated")
    both = next(t for t in found if t.label == "generic, sharp + blurry frames")
    assert f"within {both.accuracy.median:.4f} px of the true camera" in lines[2]
    assert lines[3].startswith("  What the blurry frames bought: against the truth")
    printed = report_lines(report)
    capture = [line for line in printed if line.startswith("warning: capture:")]
    assert any("below 10 the projection uncertainty" in line for line in capture)  # 6 sharp frames
    warned = [line for line in printed if line.startswith("warning:") and line not in capture]
    assert len(warned) <= 2 and all("report.json" in line for line in warned)  # one per generic fit
    figures = figure_lines(report.outputs)
    assert any("error_directions_generic" in line for line in figures)
    for line in figures[1:]:
        path = Path(line.split(": ", 1)[1])
        image = cv2.imread(str(path))
        assert image is not None
        if path.name.startswith("error_directions"):  # the image of the sensor, then its legend
            assert image.shape[0] > truth.camera.model.height and image[-30:].mean() > 200
    assert any("cross-validation diff" in line and "upper bound" in line for line in term_lines())
    stream = io.StringIO()
    log = DemoLog(out / "log-test", stream)
    log.stage("2/4 extracting")
    log.detail("sharp 1/6: sharp/0000.png ok, 200 features")
    assert stream.getvalue().endswith("2/4 extracting\n")
    assert log.path is not None and log.path.read_text().count("\n") == 2


def test_the_capture_check_sees_the_frames_the_parametric_camera_uses(tmp_path, monkeypatch) -> None:
    """Two face-on sharp frames are refused; when the blurry frames join the parametric stage
    (``blurry_in_parametric``), their tilts count and the calibration starts."""
    from blurcalib.io.results import FeatureTable, write_features
    from tests.calib.test_capture import capture_features, sampled

    sharp = capture_features(sampled(2, 1.0, 9))
    sharp.flags[:] = int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME)
    blurry = capture_features(sampled(8, 45.0, 10), seed=1)
    blurry.frame = np.char.add("b", blurry.frame)
    blurry.flags[:] = int(FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME)
    path = write_features(tmp_path / "features.csv", FeatureTable.concat([sharp, blurry]))

    class StartedError(Exception):
        pass

    def started(*args, **kwargs):
        raise StartedError

    monkeypatch.setattr(pipeline, "calibrate_features", started)
    with pytest.raises(PipelineError, match=r"degenerate capture: the 2 sharp frames .* nearly face-on"):
        run_from_features(path, layout_pattern(), tmp_path / "a", PipelineSettings(), (1280, 720))
    joined = PipelineSettings(calibration=SequenceSettings(blurry_in_parametric=True))
    with pytest.raises(StartedError):
        run_from_features(path, layout_pattern(), tmp_path / "b", joined, (1280, 720))
