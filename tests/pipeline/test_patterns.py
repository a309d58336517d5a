"""One camera from two patterns: the joint target keeps each pattern's geometry, the joint camera
is at least as close to the truth as either pattern's alone, and the cross-pattern check names a
systematic difference between the patterns and stays quiet without one."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from blurcalib.calib.cross_pattern import compare_cameras
from blurcalib.calib.joint import JointSettings
from blurcalib.calib.sequence import SequenceSettings, calibrate_features
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.uncertainty import ProjectionUncertainty
from blurcalib.calib.validation import ValidationSettings
from blurcalib.camera.files import read_generic_yaml
from blurcalib.camera.generic import fit_to_rays
from blurcalib.cli import main
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureFlags, FeatureTable, write_features
from blurcalib.pipeline.patterns import run_from_feature_sets
from blurcalib.pipeline.run import PipelineError, PipelineSettings
from blurcalib.sim.evaluate import camera_accuracy
from blurcalib.sim.synth import sample_pose
from blurcalib.sim.truth import TrueCamera, d435i_like_camera
from blurcalib.target.pattern import StarPattern, layout_pattern
from blurcalib.target.pattern_set import pattern_set

SIZE = (1280, 720)
CELL_PX = 80.0
STAR, CHECKER = layout_pattern(num_star_segments=16), layout_pattern(num_star_segments=4, tag_index=8)


def _features(pattern: StarPattern, truth: TrueCamera, poses: list[Pose], seed: int, noise_px: float = 0.05,
              radial_px: float = 0.0, scale: float = 0.0) -> FeatureTable:
    """The star centres each pose shows ``truth``, with noise, then moved radially from the image
    centre by ``radial_px (2 (r / R)^2 - 1)`` (``R`` the half diagonal: inwards near the centre,
    outwards at the border, as the real fixtures' checkerboard against the star) and scaled by
    ``1 + scale`` about the centre (a focal-length-like difference): a pattern-dependent bias."""
    points = pattern.points_3d()
    rng = np.random.default_rng(seed)
    centre = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
    parts = []
    for i, pose in enumerate(poses):
        cam = pose.transform(points)
        px = truth.project(cam) + rng.normal(0.0, noise_px, (len(points), 2))
        d = px - centre
        r = np.linalg.norm(d, axis=1, keepdims=True)
        shift = radial_px * (2.0 * (r / np.linalg.norm(centre)) ** 2 - 1.0)
        px += shift * d / np.maximum(r, 1e-9) + scale * d
        ids = np.flatnonzero((cam[:, 2] > 0) & np.all((px >= 0) & (px <= [SIZE[0] - 1, SIZE[1] - 1]), axis=1))
        fx, fy = pattern.features[ids].T.astype(float)
        n = len(ids)
        parts.append(FeatureTable(frame=np.full(n, f"{i}.png"), feature_id=ids, fx=fx, fy=fy,
                                  X=fx * pattern.square_length_m, Y=fy * pattern.square_length_m,
                                  x=px[ids, 0], y=px[ids, 1], weight=np.ones(n),
                                  flags=np.full(n, int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME))))
    return FeatureTable.concat(parts)


def _poses(frames: int, seed: int) -> tuple[TrueCamera, list[Pose]]:
    truth = d435i_like_camera(0, 0.3)
    rng = np.random.default_rng(seed)
    return truth, [sample_pose(STAR, truth, rng, 50.0, (24.0, 42.0)) for _ in range(frames)]


def test_the_joint_target_keeps_each_patterns_geometry() -> None:
    """Each pattern's features land on ids of their own, at their own target points moved by a
    whole number of rows (a pose absorbs it), and frames stay apart by label."""
    ps = pattern_set([STAR, CHECKER])
    truth, poses = _poses(2, 1)
    a, b = (ps.to_joint(k, _features(p, truth, poses, k)) for k, p in enumerate((STAR, CHECKER)))
    assert not set(a.feature_id.tolist()) & set(b.feature_id.tolist())
    for k, (table, pattern) in enumerate(((a, STAR), (b, CHECKER))):
        own = ps.joint.points_3d(table.feature_id) - [0.0, ps.offsets[k] * pattern.square_length_m, 0.0]
        original = _features(pattern, truth, poses, k)
        np.testing.assert_allclose(own, pattern.points_3d(original.feature_id), atol=1e-12)
        metric = ps.joint.points_3d(table.feature_id)[:, :2]
        np.testing.assert_allclose(np.column_stack([table.X, table.Y]), metric)
    assert set(ps.pattern_of(np.concatenate([a.frame, b.frame])).tolist()) == {0, 1}
    assert ps.frames_of(1, ["pattern1/0.png", "pattern2/0.png"]) == ["pattern2/0.png"]
    bigger = layout_pattern(approx_square_length_mm=20.0)
    with pytest.raises(ValueError, match="one square length"):
        pattern_set([STAR, bigger])


def _uncertainty(model, sigma_px: float) -> ProjectionUncertainty:
    xs, ys = np.meshgrid(np.linspace(8, SIZE[0] - 9, 40), np.linspace(8, SIZE[1] - 9, 24))
    n = xs.size
    return ProjectionUncertainty(x=xs.ravel(), y=ys.ravel(), shape=xs.shape, sigma_px=np.full(n, sigma_px),
                                 cov=np.zeros((n, 2, 2)), noise_px=0.05, width=SIZE[0], height=SIZE[1],
                                 effective_parameters=0.0, scale_px=0.0, noise_free_px=0.05)


def test_camera_comparison_names_a_focal_scale_beyond_the_uncertainty() -> None:
    """A camera and the same camera with focal lengths 0.05 % longer differ by about 0.2 px at the
    border: far beyond an uncertainty of 0.01 px (systematic, the scale recovered), within one of
    0.5 px; a camera against itself differs by nothing."""
    model = d435i_like_camera(0, 0.0).model
    longer = replace(model, fx=model.fx * 1.0005, fy=model.fy * 1.0005)
    a, b = (fit_to_rays(m.pixel_to_ray, SIZE[0], SIZE[1], cell_px=CELL_PX) for m in (model, longer))
    tight = compare_cameras(a, _uncertainty(a, 0.01), b, _uncertainty(b, 0.01))
    assert tight.systematic and tight.ratio > 5.0
    assert tight.scale_pct == pytest.approx(0.05, abs=0.01)
    assert tight.verdict().startswith("systematic difference between patterns")
    loose = compare_cameras(a, _uncertainty(a, 0.5), b, _uncertainty(b, 0.5))
    assert not loose.systematic and "agree within their uncertainty" in loose.verdict()
    same = compare_cameras(a, _uncertainty(a, 0.01), a, _uncertainty(a, 0.01))
    assert same.rms_px < 1e-3 and not same.systematic


def _write(tmp: Path, name: str, table: FeatureTable) -> Path:
    return write_features(tmp / f"{name}.csv", table)


def _settings() -> PipelineSettings:
    """Quick settings: Brown-Conrady, a coarse grid, 3 folds from 8 frames, no halves."""
    trust = TrustSettings(validation=ValidationSettings(folds=3, min_frames=8), cross_validation=False)
    return PipelineSettings(calibration=SequenceSettings(parametric="Brown_Conrady", trust=trust,
                                                         generic=JointSettings(cell_px=CELL_PX)))


@pytest.mark.slow
def test_two_patterns_give_one_camera_at_least_as_good_as_either(tmp_path) -> None:
    """Two unbiased patterns, 8 poses each: the joint camera (16 frames) is at least as close to
    the truth as either pattern's alone, every frame is used, the check finds no systematic
    difference and scores the joint camera on each pattern's frames."""
    truth, poses = _poses(8, 4)
    star, checker = _features(STAR, truth, poses, 10), _features(CHECKER, truth, _poses(8, 6)[1], 11)
    paths = [_write(tmp_path, "star", star), _write(tmp_path, "checker", checker)]
    report = run_from_feature_sets(list(zip(paths, (STAR, CHECKER), strict=True)), tmp_path / "joint",
                                   _settings(), SIZE)
    joint = read_generic_yaml(tmp_path / "joint" / "calibration" / "intrinsics0.yaml")
    errors = {"joint": camera_accuracy(truth, joint).median}
    for name, table, pattern in (("star", star, STAR), ("checker", checker, CHECKER)):
        run = calibrate_features(table, None, [], pattern, SIZE, _settings().calibration, assess=False)
        assert run.generic is not None
        errors[name] = camera_accuracy(truth, run.generic.model).median
    assert errors["joint"] <= min(errors["star"], errors["checker"]) * 1.05, errors
    assert report.generic is not None and report.generic["frames"] == 16
    check = report.patterns
    assert check is not None and check["failure"] == ""
    cameras = check["cameras"]["pattern2 - pattern1"]
    assert not cameras["systematic"] and cameras["ratio"] < 2.0, cameras
    assert not check["features"]["pattern2 - pattern1"]["systematic"]
    assert check["held_out"]["pattern1"]["joint"]["frames"] == 8
    assert check["held_out"]["pattern2"]["alone"]["frames"] == 8
    doc = json.loads((tmp_path / "joint" / "report.json").read_text())
    assert doc["patterns"]["cameras"] == json.loads(json.dumps(check["cameras"]))


@pytest.mark.slow
def test_the_check_names_a_radial_feature_bias_of_one_pattern(tmp_path, capsys) -> None:
    """The checkerboard's features moved radially by -0.04 px at the centre to +0.04 px at the
    border (below the noise of any one feature; the feature-level check) and scaled by 0.05 %, the
    real fixtures' focal-length difference (the camera level): the check calls both systematic
    and says so in print."""
    truth, poses = _poses(8, 5)
    star = _features(STAR, truth, poses, 20)
    checker = _features(CHECKER, truth, poses, 21, radial_px=0.04, scale=5e-4)
    paths = [_write(tmp_path, "star", star), _write(tmp_path, "checker", checker)]
    code = main(["calibrate", "--features", str(paths[0]), "--pattern", _yaml(tmp_path, STAR, "star"),
                 "--features", str(paths[1]), "--pattern", _yaml(tmp_path, CHECKER, "checker"),
                 "--image-size", "1280x720", "--parametric", "Brown_Conrady", "--cell-px", str(CELL_PX),
                 "--validation", "none", "--out", str(tmp_path / "out")])
    assert code == 0
    printed = capsys.readouterr().out
    doc = json.loads((tmp_path / "out" / "report.json").read_text())["patterns"]
    cameras = doc["cameras"]["pattern2 - pattern1"]
    assert cameras["systematic"] and cameras["scale_pct"] > 0.03, cameras  # the profile adds to the scale
    assert doc["features"]["pattern2 - pattern1"]["systematic"]
    assert "systematic difference between patterns" in printed
    assert "held-out error on pattern2's frames" in printed


def _yaml(tmp: Path, pattern: StarPattern, name: str) -> str:
    return str(pattern.save_yaml(tmp / f"{name}.yaml"))


def test_several_patterns_need_one_feature_file_each(tmp_path, capsys) -> None:
    """Two patterns with frames, or with one feature file, are refused in one line; files of
    different image sizes too."""
    star, checker = _yaml(tmp_path, STAR, "star"), _yaml(tmp_path, CHECKER, "checker")
    assert main(["calibrate", "--features", "a.csv", "--pattern", star, "--pattern", checker,
                 "--out", str(tmp_path / "o")]) == 2
    assert "one --features FILE each" in capsys.readouterr().err
    truth, poses = _poses(2, 1)
    path = _write(tmp_path, "star", _features(STAR, truth, poses, 0))
    with pytest.raises(PipelineError, match="at least two feature files"):
        run_from_feature_sets([(path, STAR)], tmp_path / "p", _settings(), SIZE)
