"""The rig simulator (blurcalib.sim.rig): synchronised sets with the rig's extrinsics, the hand
motion seen by each camera, the dataset folders and their truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from blurcalib.camera.generic import fit_to_rays
from blurcalib.camera.rig import Rig
from blurcalib.geometry.pose import Pose
from blurcalib.sim.rig import (
    RIG_TRUTH_FILE,
    RigSimulator,
    chain_rig,
    conjugate_motion,
    d435i_stereo_rig,
    load_rig_truth,
    write_rig_dataset,
)
from blurcalib.sim.rig_eval import extrinsic_error
from blurcalib.sim.synth import SynthConfig
from blurcalib.sim.truth import Motion


def test_conjugated_motion_is_the_same_rigid_motion() -> None:
    rng = np.random.default_rng(0)
    motion = Motion(rng.normal(0, 0.02, 6), rng.normal(0, 0.01, 6), 9)
    between = d435i_stereo_rig().relative(0, 1)
    seen = conjugate_motion(motion, between)
    mid0 = Pose.from_rvec_tvec([0.1, -0.2, 0.05], [0.02, 0.01, 0.5])
    mid1 = between.compose(mid0)
    points = rng.normal(0, 0.1, (5, 3))
    for p0, p1 in zip(motion.poses(mid0), seen.poses(mid1), strict=True):
        assert np.allclose(between.compose(p0).transform(points), p1.transform(points), atol=1e-12)


@pytest.mark.slow  # builds both cameras' renderers
def test_sets_are_seen_through_the_extrinsics() -> None:
    rig = d435i_stereo_rig(3)
    sim = RigSimulator(SynthConfig(sharp=2, blurry=2, seed=3), rig)
    for k in range(4):
        image_set = sim.image_set(k)
        for c, frame in enumerate(image_set.frames):
            assert frame is not None
            want = rig.camera_tr_rig[c].compose(image_set.rig_tr_global)
            assert np.allclose(frame.pose.R, want.R) and np.allclose(frame.pose.t, want.t)
            assert frame.visible.sum() >= 40
        if image_set.kind == "blurry":
            b0, b1 = (f.blur_length[f.visible] for f in image_set.frames)
            assert np.median(b0) > 1.0 and np.median(b1) > 1.0
            assert abs(np.median(b0) - np.median(b1)) > 1e-3  # each camera blurs differently


@pytest.mark.slow  # builds three cameras' renderers
def test_visibility_rule_links_the_third_camera_only_through_the_second() -> None:
    rig = chain_rig(3, seed=0)
    assert np.isclose(np.linalg.norm(rig.relative(0, 2).t), 0.1)
    sim = RigSimulator(SynthConfig(sharp=2, blurry=2, seed=0), rig, groups=[(0, 1), (1, 2)])
    for k in range(4):
        image_set = sim.image_set(k)
        group = (0, 1) if k % 2 == 0 else (1, 2)
        for c, frame in enumerate(image_set.frames):
            if c not in group:
                assert frame is None
                continue
            assert frame is not None and frame.visible.sum() >= 40
            want = rig.camera_tr_rig[c].compose(image_set.rig_tr_global)
            assert np.allclose(frame.pose.R, want.R) and np.allclose(frame.pose.t, want.t)
            if image_set.kind == "blurry":
                assert np.median(frame.blur_length[frame.visible]) > 1.0
    with pytest.raises(ValueError, match="visibility rule"):
        RigSimulator(SynthConfig(sharp=1, blurry=0), rig, groups=[(0, 3)])


@pytest.mark.slow
def test_truth_only_dataset_round_trips(tmp_path: Path) -> None:
    rig, sets = write_rig_dataset(tmp_path, SynthConfig(sharp=2, blurry=0, seed=1), render=False)
    loaded, poses = load_rig_truth(tmp_path)
    assert [s.name for s in sets] == sorted(poses)
    for a, b in zip(rig.camera_tr_rig, loaded.camera_tr_rig, strict=True):
        assert np.allclose(a.R, b.R) and np.allclose(a.t, b.t)
    for c in range(2):
        truth = json.loads((tmp_path / f"cam{c}" / "ground_truth.json").read_text())
        assert len(truth["frames"]) == 2
    assert json.loads((tmp_path / RIG_TRUTH_FILE).read_text())["sets"][0]["cameras"] == [0, 1]


def test_extrinsic_error_is_zero_for_the_truth_in_any_gauge() -> None:
    truth = d435i_stereo_rig(0, deviation_px=0.0)
    models = [fit_to_rays(c.pixel_to_ray, c.width, c.height, cell_px=80.0) for c in truth.cameras]
    turn = [Pose.from_rvec_tvec([0.01, -0.02, 0.005], np.zeros(3)).R, Pose.from_rvec_tvec([0.0, 0.03, 0.0],
                                                                                           np.zeros(3)).R]
    rig = Rig(tuple(models), truth.camera_tr_rig).with_frames(turn)
    err = extrinsic_error(truth, rig)
    assert err.rotation_deg < 1e-3 and err.translation_mm < 1e-3
    assert abs(err.baseline_mm - 50.0) < 1e-9
    second = rig.camera_tr_rig[1]
    moved = Rig(rig.cameras, (rig.camera_tr_rig[0], Pose(second.R, second.t + np.array([0.001, 0.0, 0.0]))))
    assert abs(extrinsic_error(truth, moved).translation_mm - 1.0) < 1e-3


@pytest.mark.slow
def test_rendered_set_has_each_cameras_frame(tmp_path: Path) -> None:
    import cv2

    write_rig_dataset(tmp_path, SynthConfig(sharp=1, blurry=0, seed=2, supersample=1))
    for c in range(2):
        image = cv2.imread(str(tmp_path / f"cam{c}" / "sharp" / "0000.png"), cv2.IMREAD_UNCHANGED)
        assert image.shape == (720, 1280) and image.std() > 10.0
    left = cv2.imread(str(tmp_path / "cam0" / "sharp" / "0000.png"), cv2.IMREAD_UNCHANGED)
    right = cv2.imread(str(tmp_path / "cam1" / "sharp" / "0000.png"), cv2.IMREAD_UNCHANGED)
    assert np.abs(left.astype(int) - right.astype(int)).mean() > 1.0  # seen from 50 mm apart


@pytest.mark.slow
def test_synth_rig_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import cv2

    from blurcalib.cli import main

    out = tmp_path / "pair"
    assert main(["synth", "--rig", "--rig-scale", "0.25", "--sharp", "1", "--blurry", "0",
                 "--out", str(out)]) == 0
    assert "simulated 1 image set (1 sharp, 0 blurry) of a 2-camera rig" in capsys.readouterr().out
    for c in range(2):
        image = cv2.imread(str(out / f"cam{c}" / "sharp" / "0000.png"), cv2.IMREAD_UNCHANGED)
        assert image.shape == (180, 320)
    _, poses = load_rig_truth(out)
    assert list(poses) == ["sharp/0000.png"]
    assert main(["synth", "--rig", "--lens", "fisheye", "--out", str(tmp_path / "no")]) == 2
    assert "--rig simulates a pair of the standard lens" in capsys.readouterr().err
    assert main(["demo", "--rig", "--lens", "fisheye", "--out", str(tmp_path / "no")]) == 2
    assert "--rig simulates a pair of the standard lens" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()
