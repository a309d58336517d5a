"""The rolling shutter: the simulator's row-time ground truth and renders, the frames' rolling
geometry, the readout ratio, and auto on global-shutter data."""

from __future__ import annotations

import csv
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from blurcalib.calib.joint import JointSettings, calibrate_generic
from blurcalib.calib.rolling_frames import fit_rolling_frames
from blurcalib.calib.rolling_shutter import (
    BlurVelocity,
    RollingShutterResult,
    RollingShutterSettings,
    _message,
    calibrate_rolling_shutter,
    estimate_ratio,
    parse_rolling_shutter,
    rolling_evidence,
)
from blurcalib.calib.sequence import BlurryFrame, BlurryOutcome, SequenceSettings
from blurcalib.calib.sharp import calibrate_sharp
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.validation import ValidationSettings, parametric_projector
from blurcalib.camera.files import read_generic_yaml
from blurcalib.camera.parametric import BrownConrady
from blurcalib.camera.shutter import row_time
from blurcalib.geometry.pose import Pose
from blurcalib.io.record import FrameRecord, FrameStatus
from blurcalib.io.results import FEATURE_COLUMNS, FeatureFlags, FeatureTable
from blurcalib.pipeline.frames import blurry_row, write_frames
from blurcalib.pipeline.run import GLOBAL_SHUTTER_DIR, PipelineSettings, run_pipeline
from blurcalib.sim.evaluate import camera_accuracy
from blurcalib.sim.render import Renderer, dot_texture
from blurcalib.sim.synth import Simulator, SynthConfig, frame_truth, sample_motion, sample_pose, write_dataset
from blurcalib.sim.truth import FrameTruth, Motion, TrueCamera, d435i_like_camera, row_window_track
from blurcalib.target.pattern import layout_pattern

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def pinhole() -> TrueCamera:
    """A distortion-free 320 x 240 camera: a camera translation parallel to a fronto-parallel
    target moves the whole image by one velocity."""
    return TrueCamera(BrownConrady(fx=300.0, fy=300.0, cx=159.5, cy=119.5, k1=0.0, k2=0.0, p1=0.0, p2=0.0,
                                   k3=0.0, width=320, height=240))


def _centroid(img: np.ndarray) -> np.ndarray:
    ys, xs = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    return np.array([(img * xs).sum(), (img * ys).sum()]) / img.sum()


def test_zero_motion_rolling_shutter_equals_global(pinhole: TrueCamera) -> None:
    renderer = Renderer(pinhole)
    tex = dot_texture((0.0, 0.0), radius_m=0.004, texel_m=0.0005, extent_m=0.01)
    pose = Pose(np.eye(3), np.array([0.01, -0.005, 0.2]))
    still = Motion(np.zeros(6), np.zeros(6), 6)
    rolling = renderer.irradiance([tex], pose, still, rolling_shutter=2.0)
    assert rolling.max() > 0.5
    assert np.abs(rolling - renderer.irradiance([tex], pose, still)).max() < 1e-5
    pattern = layout_pattern()
    rng = np.random.default_rng(0)
    truth = frame_truth("f", "blurry", pattern, pinhole, Pose(np.eye(3), np.array([-0.1, -0.08, 0.4])),
                        still, 0.5, rng, 2.0, rolling_shutter=2.0)
    assert np.abs(truth.mean - truth.mid).max() < 1e-9
    assert np.abs(truth.blur_length).max() < 1e-9


def test_horizontal_velocity_shifts_features_linearly_with_row(pinhole: TrueCamera) -> None:
    """Translation along x of a fronto-parallel camera: the image moves by ``u`` px per exposure
    time everywhere, and a feature seen in row ``y`` is shifted by ``c(y) u`` (ground truth),
    which the render's dot centroids show too."""
    ratio, depth, vx = 2.0, 0.2, 0.008
    u = pinhole.model.fx * vx / depth  # px per exposure time (12 px)
    motion = Motion(np.array([0.0, 0.0, 0.0, vx, 0.0, 0.0]), np.zeros(6), 40)
    pattern = layout_pattern()
    truth = frame_truth("f", "blurry", pattern, pinhole, Pose(np.eye(3), np.array([-0.09, -0.07, depth])),
                        motion, 0.5, np.random.default_rng(0), 2.0, rolling_shutter=ratio)
    seen = truth.visible
    assert seen.sum() > 100 and np.ptp(truth.mean[seen, 1]) > 150
    shift = truth.mean[seen] - truth.mid[seen]
    expected = row_time(truth.mean[seen, 1], 240, ratio) * u
    assert np.abs(shift[:, 0] - expected).max() < 1e-6
    assert np.abs(shift[:, 1]).max() < 1e-9
    assert truth.blur_length[seen] == pytest.approx(u, rel=1e-6)
    renderer = Renderer(pinhole)
    tex = dot_texture((0.0, 0.0), radius_m=0.0015, texel_m=0.0002, extent_m=0.004)
    for row in (30.0, 120.0, 210.0):
        y_m = (row - pinhole.model.cy) * depth / pinhole.model.fy
        pose = Pose(np.eye(3), np.array([0.0, y_m, depth]))
        img = renderer.irradiance([tex], pose, motion, rolling_shutter=ratio).astype(np.float64)
        mid = pinhole.project(pose.transform(np.zeros((1, 3))))[0]
        found = _centroid(img)
        assert found[0] - mid[0] == pytest.approx(float(row_time(found[1], 240, ratio)) * u, abs=0.03)
        assert found[1] == pytest.approx(mid[1], abs=0.03)


def _blur_vectors(camera: TrueCamera, truth: FrameTruth, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Blur lengths ``L`` and major axes of each point's true path over its row window (the PSF's
    second moments, as blocks measure them)."""
    tracks, w = row_window_track(camera, truth.pose, truth.motion, points, camera.model.height,
                                 truth.rolling_shutter)
    d = tracks - (w[..., None] * tracks).sum(axis=0)
    cov = np.einsum("nm,nmi,nmj->mij", w, d, d)
    val, vec = np.linalg.eigh(cov)
    return np.sqrt(12.0 * np.clip(val[:, 1] - val[:, 0], 0.0, None)), vec[:, :, 1]


def _frames(ratio: float, count: int, seed: int, camera: TrueCamera, noise_px: float = 0.03,
            prefix: str = "b", blurry: bool = True) -> tuple[FeatureTable, list[FrameTruth], BlurVelocity]:
    """Truth features (time averages over the row windows) of ``count`` frames, with noise."""
    sim = Simulator(SynthConfig(sharp=0, blurry=1, seed=seed, rolling_shutter=ratio), camera=camera)
    pattern = sim.pattern
    rng = np.random.default_rng(seed)
    cols: dict[str, list] = {k: [] for k in ("frame", "feature_id", "fx", "fy", "X", "Y", "x", "y",
                                            "weight", "flags")}
    vel: dict[str, list] = {"frame": [], "feature_id": [], "length": [], "direction": []}
    truths = []
    kind = FeatureFlags.BLURRY_FRAME if blurry else FeatureFlags.SHARP_FRAME
    for i in range(count):
        pose = sample_pose(pattern, camera, rng, 50.0, (24.0, 42.0))
        motion = sample_motion(sim.renderer, pose, pattern, rng, rng.uniform(3.0, 18.0), curved=i % 2 == 0,
                               rolling_shutter=ratio) if blurry else Motion.still()
        truth = frame_truth(f"{prefix}{i}", "blurry", pattern, camera, pose, motion, 0.5, rng, 2.0, ratio)
        ids = np.flatnonzero(truth.block_inside)
        xy = truth.mean[ids] + rng.normal(0.0, noise_px, (len(ids), 2))
        fx, fy = pattern.features[ids].T
        name = f"{prefix}{i}.png"
        cols["frame"] += [name] * len(ids)
        cols["feature_id"] += ids.tolist()
        cols["fx"] += fx.tolist()
        cols["fy"] += fy.tolist()
        cols["X"] += (fx * pattern.square_length_m).tolist()
        cols["Y"] += (fy * pattern.square_length_m).tolist()
        cols["x"] += xy[:, 0].tolist()
        cols["y"] += xy[:, 1].tolist()
        cols["weight"] += [1.0] * len(ids)
        cols["flags"] += [int(FeatureFlags.STAR_CENTRE | kind)] * len(ids)
        length, direction = _blur_vectors(camera, truth, pattern.points_3d(ids))
        vel["frame"] += [name] * len(ids)
        vel["feature_id"] += ids.tolist()
        vel["length"].append(length)
        vel["direction"].append(direction)
        truths.append(truth)
    velocity = BlurVelocity(np.array(vel["frame"]), np.array(vel["feature_id"]),
                            np.concatenate(vel["length"]), np.concatenate(vel["direction"]))
    return FeatureTable(**cols), truths, velocity


@pytest.mark.parametrize("ratio", [2.0, 0.0])
def test_frame_fit_and_ratio(ratio: float) -> None:
    """With the true camera held, the rolling geometry fits the features to their noise, the ratio
    comes out within 5% (readout = 2 exposures) and a global shutter's twists are chi-square
    noise (the test does not fire)."""
    camera = TrueCamera(d435i_like_camera(0).model)
    table, truths, velocity = _frames(ratio, 8, 5, camera)
    names = sorted(set(table.frame.tolist()), key=table.frame.tolist().index)
    frame = np.array([names.index(f) for f in table.frame])
    P = np.column_stack([table.X, table.Y, np.zeros(len(table))])
    fit = fit_rolling_frames(parametric_projector(camera.model), [t.pose for t in truths], frame, P,
                             np.column_stack([table.x, table.y]), np.ones(8, bool), np.ones(8, bool), 720)
    assert fit.sigma_px < 0.04
    ratio_hat, sigma, _ = estimate_ratio(fit, frame, velocity.length, velocity.direction)
    statistic = float(fit.z.sum())
    if ratio > 0:
        assert ratio_hat == pytest.approx(ratio, rel=0.05)
        assert sigma < 0.2
        assert statistic > chi2.isf(1e-4, 12 * 8)
    else:
        assert statistic < chi2.isf(1e-4, 12 * 8)
        assert ratio_hat < 3 * sigma + 0.05


def _structured(table: FeatureTable, amplitude_px: float, seed: int) -> FeatureTable:
    """``table`` with a smooth error field per frame (sine waves of 380 px in x and y, as a
    deconvolution's errors are larger than a sharp frame's noise and correlated)."""
    rng = np.random.default_rng(seed)
    x, y = table.x.copy(), table.y.copy()
    for name in dict.fromkeys(table.frame.tolist()):
        m = table.frame == name
        a, ph = rng.normal(0.0, amplitude_px, 4), rng.uniform(0.0, 2 * np.pi, 4)
        x[m] += a[0] * np.sin(table.x[m] / 60 + ph[0]) + a[1] * np.sin(table.y[m] / 60 + ph[1])
        y[m] += a[2] * np.sin(table.x[m] / 60 + ph[2]) + a[3] * np.sin(table.y[m] / 60 + ph[3])
    return replace(table, x=x, y=y)


@pytest.mark.parametrize("ratio", [2.0, 0.0])
def test_evidence_against_structured_errors(ratio: float) -> None:
    """4 sharp frames (noise 0.03 px) and 8 blurry ones with a structured 0.1 px error field each,
    the true camera held. The chi-square of the rolling parameters against the pooled noise level
    fires on the global shutter too; the evidence (the displacement the rolling parameters explain
    net of a pose change, against the residual they leave) finds the readout of 2 exposure times
    (measured 0.98 px explained against 0.12 px left) and nothing on the global shutter (0.09 against
    0.12 px)."""
    camera = TrueCamera(d435i_like_camera(0).model)
    sharp, sharp_truth, _ = _frames(0.0, 4, 7, camera, prefix="s", blurry=False)
    blurry, blurry_truth, _ = _frames(ratio, 8, 5, camera)
    blurry = _structured(blurry, 0.1, 3)
    table = FeatureTable(**{k: np.concatenate([getattr(sharp, k), getattr(blurry, k)])
                            for k in FEATURE_COLUMNS})
    names = list(dict.fromkeys(table.frame.tolist()))
    frame = np.array([names.index(f) for f in table.frame])
    moving = np.array([n.startswith("b") for n in names])
    P = np.column_stack([table.X, table.Y, np.zeros(len(table))])
    args = (parametric_projector(camera.model), [t.pose for t in sharp_truth + blurry_truth], frame, P,
            np.column_stack([table.x, table.y]), moving)
    fit = fit_rolling_frames(*args, moving, 720)
    rigid = fit_rolling_frames(*args, np.zeros(len(names), bool), 720)
    evidence = rolling_evidence(fit, rigid, frame, moving, 1e-4)
    assert evidence.statistic > evidence.threshold
    assert float(np.nansum(fit.z)) > chi2.isf(1e-4, 12 * 8)
    if ratio > 0:
        assert evidence.found() and evidence.explained_px > 5 * evidence.residual_px
    else:
        assert not evidence.found() and evidence.explained_px < evidence.residual_px


@pytest.mark.slow
@pytest.mark.parametrize("ratio", [2.0, 0.0])
def test_auto_calibration(ratio: float) -> None:
    """Truth features of 8 static sharp and 10 blurry frames: with a rolling shutter ``auto``
    gives a camera far closer to the truth than ``off`` (measured 0.046 against 0.79 px) and the
    ratio within 10% (measured 1.96, with the camera fitted together with the rolling parameters
    held); with a global shutter it finds nothing and returns ``off``'s camera."""
    truth_camera = d435i_like_camera(0, 0.3)
    pattern = layout_pattern()
    sharp, _, _ = _frames(0.0, 8, 11, truth_camera, prefix="s", blurry=False)
    blurry, _, velocity = _frames(ratio, 10, 12, truth_camera)
    parametric = calibrate_sharp(sharp, pattern, (1280, 720), refine_points=False)
    joint = JointSettings(cell_px=80.0)
    off = calibrate_generic(sharp, blurry, parametric, pattern, (1280, 720), joint)
    auto, result = calibrate_rolling_shutter(sharp, blurry, parametric, pattern, (1280, 720),
                                             RollingShutterSettings("auto"), joint, velocity, off)
    err_off = camera_accuracy(truth_camera, off.model, step=16.0).median
    err_auto = camera_accuracy(truth_camera, auto.model, step=16.0).median
    if ratio > 0:
        assert result.applied and result.significant
        assert result.ratio == pytest.approx(ratio, rel=0.1)
        assert err_auto < 0.1 and err_off > 0.5
        assert result.corrected is not None and len(result.corrected) == len(blurry)
    else:
        assert not result.applied and not result.significant
        assert auto is off
        assert "none found" in result.message


def test_parse_rolling_shutter() -> None:
    assert parse_rolling_shutter("off") == "off"
    assert parse_rolling_shutter("auto") == "auto"
    assert parse_rolling_shutter("2") == 2.0
    for bad in ("-1", "nan", "fast", "11"):
        with pytest.raises(ValueError, match="rolling shutter"):
            parse_rolling_shutter(bad)


@pytest.mark.slow
def test_modelled_run_keeps_the_camera_without_the_model(tmp_path) -> None:
    """A run that applies the model writes the generic camera of the same features without it
    (``calibration/global_shutter/``): the camera an ``off`` run of the same extraction publishes;
    an ``off`` run writes none."""
    model = BrownConrady(fx=420.0, fy=420.0, cx=239.6, cy=179.3, k1=0.02, k2=-0.03, p1=0.0003, p2=-0.0002,
                         k3=0.0, width=480, height=360)
    config = SynthConfig(sharp=6, blurry=3, square_px=(24.0, 30.0), max_tilt_deg=45.0, blur_min_px=4.0,
                         blur_max_px=6.0, seed=5, rolling_shutter=2.0)
    write_dataset(tmp_path / "data", config, camera=TrueCamera(model))
    pattern = layout_pattern()
    sharp = sorted((tmp_path / "data" / "sharp").glob("*.png"))
    blurry = sorted((tmp_path / "data" / "blurry").glob("*.png"))
    trust = TrustSettings(validation=ValidationSettings(method="none"), cross_validation=False)
    out = tmp_path / "run"
    off = SequenceSettings(trust=trust)
    report = run_pipeline(sharp, blurry, pattern, out, PipelineSettings(calibration=off))
    assert report.generic["blurry_frames"] >= 1
    assert not (out / "calibration" / GLOBAL_SHUTTER_DIR).exists()
    published_off = read_generic_yaml(out / "calibration" / "intrinsics0.yaml")
    forced = SequenceSettings(trust=trust, rolling_shutter=RollingShutterSettings(2.0))
    report = run_pipeline(sharp, blurry, pattern, out, PipelineSettings(calibration=forced))
    assert report.rolling_shutter["applied"]
    without = read_generic_yaml(out / "calibration" / GLOBAL_SHUTTER_DIR / "intrinsics0.yaml")
    px = np.column_stack([np.linspace(40.0, 440.0, 50), np.linspace(30.0, 330.0, 50)])
    assert np.allclose(without.pixel_to_ray(px), published_off.pixel_to_ray(px), atol=1e-9)
    assert not np.allclose(read_generic_yaml(out / "calibration" / "intrinsics0.yaml").pixel_to_ray(px),
                           without.pixel_to_ray(px), atol=1e-9)


def test_frames_csv_holds_the_blur_velocity(tmp_path) -> None:
    """A blurry frame's row carries the rolling-shutter step's median blur velocity, by the frame's
    name in the calibration; a frame it did not measure has the column empty."""
    outcome = BlurryOutcome(BlurryFrame("blurry/a.png"), entered=True, shift=np.array([0.5, -0.25]))
    other = BlurryOutcome(BlurryFrame("blurry/b.png"), entered=True, shift=np.array([0.0, 0.0]))
    velocity = {"blurry/a.png": 7.2549}
    rows = [blurry_row(FrameRecord(name, FrameStatus.OK), o, SequenceSettings(), velocity)
            for name, o in (("a.png", outcome), ("b.png", other))]
    assert rows[0].used and rows[0].verdict.velocity_px == 7.255 and rows[1].verdict.velocity_px is None
    with open(write_frames(tmp_path / "frames.csv", rows), newline="", encoding="utf-8") as fh:
        table = list(csv.DictReader(fh))
    assert [r["velocity_px"] for r in table] == ["7.255", ""]


def test_a_forced_ratio_the_test_does_not_support_is_a_warning() -> None:
    """``--rolling-shutter 2`` on a global-shutter capture was applied without a word although the
    test found nothing (statistic 18 against 125)."""
    forced = RollingShutterResult(2.0, math.nan, math.nan, True, False, 18.0, 125.0, ["b0.png"])
    message = _message(forced, True)
    assert message.startswith("warning: rolling shutter modelled as asked (ratio 2)")
    assert "test statistic 18, significant above 125" in message and "\n" not in message
    found = replace(forced, significant=True, statistic=300.0)
    assert _message(found, True).startswith("rolling shutter: modelled")
    auto = replace(forced, mode="auto", applied=False)
    assert "none found" in _message(auto, False)
