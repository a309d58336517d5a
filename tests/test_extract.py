"""Seeding, growing, local alignment and frame extraction on simulated and real frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from blurcalib.camera import BrownConrady, apply_homography, translation
from blurcalib.extract import ExtractSettings, FrameStatus, extract_frame, extract_to_folder
from blurcalib.frames import load_frame
from blurcalib.local_alignment import align_locally, shared_corners
from blurcalib.pattern import load_pattern
from blurcalib.refformat import read_ref_dataset
from blurcalib.results import BlockStatus, read_features
from blurcalib.seed import SeedError, block_homography, detect_tags, seed_frame
from blurcalib.synth import Simulator, SynthConfig, TrueCamera
from tests.conftest import FIXTURE_YAML, REAL


@pytest.fixture(scope="module")
def sim() -> Simulator:
    model = BrownConrady(fx=420.0, fy=420.0, cx=239.6, cy=179.3, k1=0.02, k2=-0.03, p1=0.0003,
                         p2=-0.0002, k3=0.0, width=480, height=360)
    cfg = SynthConfig(sharp=2, blurry=1, square_px=(24.0, 30.0), max_tilt_deg=30.0,
                      blur_min_px=5.0, blur_max_px=6.0, seed=11)
    return Simulator(cfg, camera=TrueCamera(model))


@pytest.fixture(scope="module")
def sharp_frame(sim: Simulator):
    return sim.frame(0)


def test_seed_from_tag_matches_truth(sim: Simulator, sharp_frame) -> None:
    truth = sharp_frame.truth
    seed = seed_frame(sharp_frame.image, sim.pattern)
    assert seed.source == "tag" and seed.tag_index == 0 and seed.scale == 1.0
    tag = sim.pattern.apriltags[0]
    corners = np.column_stack([sim.pattern.tag_corners(tag) * sim.pattern.square_length_m,
                               np.zeros(4)])
    true_px = sim.camera.project(truth.pose.transform(corners))
    assert np.abs(seed.corners_px - true_px).max() < 0.5
    # The block homographies of the ring around the tag predict star centres to ~1 px.
    ids = np.flatnonzero(truth.block_inside)[:20]
    f = sim.pattern.features[ids]
    pred = apply_homography(block_homography(seed.H_feature, f[:, 0], f[:, 1]),
                            np.zeros((len(f), 1, 2)))[:, 0]
    near_tag = np.abs(f - np.array([7, 11])).max(axis=1) <= 3
    if near_tag.any():
        assert np.abs(pred[near_tag] - truth.mid[ids][near_tag]).max() < 1.5


def test_downscaled_detection_maps_back_to_full_resolution(sharp_frame) -> None:
    full, s_full = detect_tags(sharp_frame.image, scales=(1.0,))
    half, s_half = detect_tags(sharp_frame.image, scales=(0.5,))
    assert s_full == 1.0 and s_half == 0.5
    assert np.abs(full[0] - half[0]).max() < 1.0


def test_unseedable_frame_is_reported() -> None:
    noise = np.random.default_rng(0).uniform(0, 255, (240, 320)).astype(np.float32)
    pattern = load_pattern(FIXTURE_YAML)
    with pytest.raises(SeedError, match="no AprilTag"):
        seed_frame(noise, pattern)
    result = extract_frame(noise, pattern, "noise.png")
    assert result.status is FrameStatus.NOT_SEEDED and "no AprilTag" in result.message
    with pytest.raises(SeedError, match="invertible"):
        seed_frame(noise, pattern, H_feature=np.zeros((3, 3)))


def test_sharp_frame_features_match_truth(sim: Simulator, sharp_frame) -> None:
    truth = sharp_frame.truth
    result = extract_frame(sharp_frame.image.astype(np.float32), sim.pattern, "f.png",
                           ExtractSettings.sharp())
    assert result.status is FrameStatus.OK
    ids = np.array([f.feature_id for f in result.features])
    xy = np.array([[f.x, f.y] for f in result.features])
    assert len(ids) >= 0.8 * truth.block_inside.sum()
    err = np.linalg.norm(xy - truth.mid[ids], axis=1)
    assert np.median(err) < 0.05
    assert err.max() < 0.5
    # Growing never accepts a block outside the pattern or whose square leaves the image.
    for b in result.blocks:
        if b.status is BlockStatus.ACCEPTED:
            assert sim.pattern.is_valid_feature(b.fx, b.fy)
            corners = apply_homography(b.H, np.array([[-1.0, -1], [1, -1], [1, 1], [-1, 1]]))
            assert np.all(corners >= -0.5) and np.all(corners <= np.array([479.5, 359.5]))
    # Square corners shared by neighbouring blocks land on the projected corners.
    corners = np.array([[r[3], r[4], 0.0] for r in result.corners])
    corner_xy = np.array([[r[5], r[6]] for r in result.corners])
    assert len(corners) > 50
    true_xy = sim.camera.project(truth.pose.transform(corners))
    assert np.median(np.linalg.norm(corner_xy - true_xy, axis=1)) < 0.15
    f0 = result.features[0]
    assert (f0.X, f0.Y) == pytest.approx((f0.fx * sim.pattern.square_length_m,
                                          f0.fy * sim.pattern.square_length_m))


def test_local_alignment_recovers_block_translations() -> None:
    rng = np.random.default_rng(0)
    H_feature = np.array([[30.0, 2.0, 200.0], [-1.5, 29.0, 150.0], [1e-4, -2e-4, 1.0]])
    fy, fx = np.mgrid[0:5, 0:6]
    fx, fy = fx.ravel(), fy.ravel()
    H_true = block_homography(H_feature, fx, fy)
    shift = rng.normal(0, 0.3, (len(fx), 2))
    H_noisy = translation(shift) @ H_true
    la = align_locally(H_noisy, fx, fy)
    expected = -(shift - shift.mean(axis=0))
    assert np.allclose(la.translation, expected, atol=1e-6)
    assert la.rms_before > 0.1 and la.rms_after < 1e-6
    corner2, xy, count = shared_corners(la.H, fx, fy)
    assert len(corner2) == 6 * 7 - 4 and count.max() == 4
    truth = apply_homography(H_feature, corner2 / 2.0) + shift.mean(axis=0)
    assert np.abs(xy - truth).max() < 1e-6


def test_folder_run_records_bad_frames_and_resumes(tmp_path, sim: Simulator, sharp_frame) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "a_good.png"), sharp_frame.image)
    (frames / "b_empty.png").write_bytes(b"")
    good = (frames / "a_good.png").read_bytes()
    (frames / "c_truncated.png").write_bytes(good[: len(good) // 2])
    cv2.imwrite(str(frames / "d_small.png"), sharp_frame.image[:100, :100])
    cv2.imwrite(str(frames / "e_notag.png"), np.full((360, 480), 128, np.uint8))
    yaml = tmp_path / "pattern.yaml"
    sim.pattern.save_yaml(yaml)
    paths = sorted(frames.iterdir())
    out = tmp_path / "out"
    summary = extract_to_folder(paths, sim.pattern, out, ExtractSettings.sharp(),
                                expected_size=(480, 360))
    status = {r["frame"]: r["status"] for r in summary.frames}
    assert status == {"a_good.png": "ok", "b_empty.png": "unreadable",
                      "c_truncated.png": "unreadable", "d_small.png": "unreadable",
                      "e_notag.png": "not_seeded"}
    features = read_features(out / "features.csv")
    assert len(features) > 50 and {f.frame for f in features} == {"a_good.png"}
    corner_lines = (out / "corners.csv").read_text().splitlines()
    assert corner_lines[0] == "frame,cx2,cy2,X,Y,x,y,blocks" and len(corner_lines) > 50
    table = (out / "frames.csv").read_text()
    assert "truncated" in table and "expected 480x360" in table
    again = extract_to_folder(paths, sim.pattern, out, ExtractSettings.sharp(),
                              expected_size=(480, 360))
    assert sorted(again.skipped) == sorted(status)
    assert len(read_features(out / "features.csv")) == len(features)


def test_real_frame_agrees_with_reference_detector(shared_fixtures) -> None:
    pattern = load_pattern(REAL / "pattern.yaml")
    reference = read_ref_dataset(REAL / "features_10px.bin").image("2.png")
    result = extract_frame(load_frame(REAL / "images" / "2.png"), pattern, "2.png",
                           ExtractSettings.sharp())
    ref = dict(zip(reference.features.tolist(), reference.xy, strict=True))
    err = np.array([np.hypot(f.x - ref[f.feature_id][0], f.y - ref[f.feature_id][1])
                    for f in result.features if f.feature_id in ref])
    assert len(err) > 150
    assert np.median(err) < 0.05
