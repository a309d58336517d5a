"""Global alignment (``eq:global_align``, ``eq:bilinear_bias``) on synthetic geometry, and the
Table ``tab:exp4`` experiment on a few frames."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.calib.alignment import (
    LOSSES,
    align_global,
    alignment_covariance,
    loss_weights,
    orientation_ok,
)
from blurcalib.calib.bias import bias_basis, bias_field, grid_coordinates
from blurcalib.calib.report import direction_colours
from blurcalib.camera.parametric import BrownConrady, project_points
from blurcalib.geometry.pose import Pose
from blurcalib.paper.alignment import (
    ROWS,
    AlignmentSettings,
    format_table,
    main,
    run_alignment_experiment,
)
from blurcalib.sim.synth import sample_pose
from blurcalib.sim.truth import d435i_like_camera
from blurcalib.target.pattern import StarPattern, layout_pattern

SHIFT = np.array([3.0, -2.0])
NOISE = 0.03


@pytest.fixture(scope="module")
def pattern() -> StarPattern:
    return layout_pattern()


@pytest.fixture(scope="module")
def camera() -> BrownConrady:
    return d435i_like_camera(0).model


def view(pattern: StarPattern, camera: BrownConrady, tilt_deg: float, depth: float = 0.3):
    """A pose looking at the target's centre, tilted by ``tilt_deg`` about an oblique axis, with
    the target points, true projections and grid coordinates of the features inside the image."""
    P = pattern.points_3d()
    axis = np.array([1.0, 0.3, 0.0]) / math.hypot(1.0, 0.3)
    R = cv2.Rodrigues(axis * math.radians(tilt_deg))[0]
    pose = Pose(R, np.array([0.0, 0.0, depth]) - R @ P.mean(axis=0))
    x = project_points(camera, pose, P)
    inside = (x[:, 0] >= 0) & (x[:, 0] <= camera.width - 1) & (x[:, 1] >= 0) & (x[:, 1] <= camera.height - 1)
    return pose, P[inside], x[inside], grid_coordinates(pattern, pattern.features)[inside]


def translation_std(camera: BrownConrady, pose: Pose, P: np.ndarray, sigma: float) -> float:
    return float(np.sqrt(np.trace(alignment_covariance(camera, pose, P, sigma_px=sigma))))


# ------------------------------------------------------------------------------ translation
@pytest.mark.parametrize("loss", LOSSES)
def test_shift_recovered_exactly_without_noise(pattern, camera, loss):
    pose, P, x, _ = view(pattern, camera, 40.0)
    result = align_global(camera, P, x + SHIFT, loss=loss)
    assert np.linalg.norm(result.translation - SHIFT) < 1e-5
    assert np.allclose(result.corrected, x, atol=1e-5)
    assert np.allclose(result.pose.t, pose.t, atol=1e-7)
    assert result.median_error < 1e-5 and result.converged


@pytest.mark.parametrize("loss", LOSSES)
def test_shift_recovered_with_noise_to_the_cramer_rao_bound(pattern, camera, loss):
    """With 0.03 px noise a single 40-degree view determines x_G to ~0.04 px (the pose absorbs
    most of a translation); every loss stays within 3 Cramér-Rao standard deviations, and with
    0.003 px noise within 0.02 px."""
    pose, P, x, _ = view(pattern, camera, 40.0)
    std = translation_std(camera, pose, P, NOISE)
    assert 0.02 < std < 0.06
    rng = np.random.default_rng(1)
    for sigma, bound in ((NOISE, 3.0 * std), (NOISE / 10, 0.02)):
        noise = rng.normal(0.0, sigma, x.shape)
        result = align_global(camera, P, x + SHIFT + noise, loss=loss)
        assert np.linalg.norm(result.translation - SHIFT) < bound
        assert result.median_error == pytest.approx(1.1774 * sigma, rel=0.15)


def test_mean_loss_is_efficient(pattern, camera):
    """Monte Carlo: the least-squares x_G scatters as the Cramér-Rao covariance predicts."""
    pose, P, x, _ = view(pattern, camera, 40.0)
    rng = np.random.default_rng(2)
    errors = [align_global(camera, P, x + SHIFT + rng.normal(0.0, NOISE, x.shape), loss="mean").translation
              - SHIFT for _ in range(12)]
    rms = math.sqrt(np.mean(np.sum(np.square(errors), axis=1)))
    assert 0.6 < rms / translation_std(camera, pose, P, NOISE) < 1.5


def test_outliers_barely_move_huber_but_move_the_mean(pattern, camera):
    _, P, x, _ = view(pattern, camera, 40.0)
    moves: dict[str, list[float]] = {"huber": [], "mean": []}
    for seed in range(5):
        rng = np.random.default_rng(seed)
        clean = x + SHIFT + rng.normal(0.0, NOISE, x.shape)
        bad = clean.copy()
        idx = rng.choice(len(bad), len(bad) // 10, replace=False)
        a = rng.uniform(0.0, 2.0 * np.pi, len(idx))
        bad[idx] += 2.0 * np.stack([np.cos(a), np.sin(a)], axis=1)
        for loss in moves:
            before = align_global(camera, P, clean, loss=loss, huber_px=0.05).translation
            after = align_global(camera, P, bad, loss=loss, huber_px=0.05).translation
            moves[loss].append(float(np.linalg.norm(after - before)))
    huber_rms = math.sqrt(np.mean(np.square(moves["huber"])))
    mean_rms = math.sqrt(np.mean(np.square(moves["mean"])))
    assert max(moves["huber"]) < 0.05  # about one Cramér-Rao std of the clean estimate
    assert mean_rms > 0.2 and mean_rms > 8 * huber_rms


def test_zero_weights_remove_points_exactly(pattern, camera):
    _, P, x, _ = view(pattern, camera, 40.0)
    rng = np.random.default_rng(3)
    obs = x + SHIFT + rng.normal(0.0, NOISE, x.shape)
    bad = obs.copy()
    bad[:20] += 5.0
    w = np.ones(len(P))
    w[:20] = 0.0
    weighted = align_global(camera, P, bad, w, loss="mean")
    subset = align_global(camera, P[20:], obs[20:], loss="mean")
    assert np.allclose(weighted.translation, subset.translation, atol=1e-6)
    assert loss_weights(np.array([0.0, 9.0]), eps=1.0) == pytest.approx([1.0, 0.1])
    with pytest.raises(ValueError):
        loss_weights(np.array([-1.0]))


# ---------------------------------------------------------------------------- orientation
def test_orientation_filter(pattern, camera):
    frontal, P0, x0, _ = view(pattern, camera, 0.0)
    tilted, P1, x1, _ = view(pattern, camera, 40.0)
    assert not orientation_ok(frontal) and orientation_ok(tilted)
    assert orientation_ok(tilted, threshold=math.radians(39.0))
    assert not orientation_ok(tilted, threshold=math.radians(41.0))
    assert align_global(camera, P0, x0 + SHIFT).ill_conditioned
    result = align_global(camera, P1, x1 + SHIFT)
    assert not result.ill_conditioned
    assert result.angle_to_normal == pytest.approx(math.radians(40.0), abs=1e-6)


def test_frontal_shift_is_ill_conditioned(pattern, camera):
    """As the paper reports, a frontal view cannot separate x_G from the pose."""
    rms = {}
    for tilt in (0.0, 40.0):
        pose, P, x, _ = view(pattern, camera, tilt)
        rng = np.random.default_rng(4)
        errors = [align_global(camera, P, x + SHIFT + rng.normal(0.0, NOISE, x.shape)).translation - SHIFT
                  for _ in range(6)]
        rms[tilt] = math.sqrt(np.mean(np.sum(np.square(errors), axis=1)))
        assert rms[tilt] < 4 * translation_std(camera, pose, P, NOISE)
    assert rms[0.0] > 5 * rms[40.0]
    frontal_pose = view(pattern, camera, 0.0)[0]
    tilted_pose = view(pattern, camera, 40.0)[0]
    P = pattern.points_3d()
    assert (translation_std(camera, frontal_pose, P, NOISE)
            > 10 * translation_std(camera, tilted_pose, P, NOISE))


def test_sampled_poses_align_and_flag(pattern):
    """``synth.sample_pose`` frames: tilted ones recover the shift, the flag follows the angle."""
    truth = d435i_like_camera(0)
    camera = truth.model
    rng = np.random.default_rng(5)
    P = pattern.points_3d()
    for _ in range(4):
        pose = sample_pose(pattern, truth, rng, 60.0, (24.0, 42.0))
        x = project_points(camera, pose, P)
        inside = ((x[:, 0] >= 0) & (x[:, 0] <= camera.width - 1) & (x[:, 1] >= 0)
                  & (x[:, 1] <= camera.height - 1))
        noise = rng.normal(0.0, NOISE, (inside.sum(), 2))
        result = align_global(camera, P[inside], x[inside] + SHIFT + noise)
        angle = pose.optical_axis_angle_to_target_normal()
        assert result.ill_conditioned == (result.angle_to_normal < math.pi / 10)
        assert result.angle_to_normal == pytest.approx(angle, abs=0.05)
        bound = 4 * translation_std(camera, pose, P[inside], NOISE)
        assert np.linalg.norm(result.translation - SHIFT) < bound


# ----------------------------------------------------------------------- spatial bias models
BILINEAR = np.array([[0.5, 0.3, -0.2, 0.15], [-0.4, 0.1, 0.25, -0.2]])


def test_bilinear_field_recovered(pattern, camera):
    """Without noise the joint solve recovers the field exactly; with noise the coefficients are
    within 4 Cramér-Rao standard deviations and the residuals at the noise level. A single
    translation cannot explain the field."""
    pose, P, x, grid = view(pattern, camera, 40.0)
    field = bias_field(grid, "bilinear", BILINEAR)
    exact = align_global(camera, P, x + field, grid=grid, bias="bilinear")
    assert exact.bias_coeffs.shape == (2, 4)
    assert np.allclose(exact.bias_coeffs, BILINEAR, atol=1e-5)
    assert np.allclose(exact.corrected, x, atol=1e-5)
    assert np.allclose(exact.translation, field.mean(axis=0), atol=1e-5)
    translation = align_global(camera, P, x + field, grid=grid, bias="translation")
    assert translation.median_error > 0.03
    assert np.max(np.abs(translation.corrected - x)) > 0.5

    rng = np.random.default_rng(6)
    obs = x + field + rng.normal(0.0, NOISE, x.shape)
    noisy = align_global(camera, P, obs, grid=grid, bias="bilinear", loss="mean")
    std = np.sqrt(np.diag(alignment_covariance(camera, pose, P, grid, "bilinear", NOISE))).reshape(2, 4)
    assert np.all(np.abs(noisy.bias_coeffs - BILINEAR) < 4 * std)
    assert noisy.median_error < 1.3 * 1.1774 * NOISE
    assert align_global(camera, P, obs, grid=grid, bias="translation").median_error > 1.5 * noisy.median_error


def test_quadrant_field_recovered(pattern, camera):
    _, P, x, grid = view(pattern, camera, 40.0)
    quadrants = np.array([[0.4, -0.1], [0.1, 0.3], [-0.2, 0.2], [0.3, 0.0]]) + SHIFT
    result = align_global(camera, P, x + bias_field(grid, "quadrants", quadrants), grid=grid,
                          bias="quadrants", loss="huber")
    assert result.bias_coeffs.shape == (4, 2)
    assert np.allclose(result.bias_coeffs, quadrants, atol=1e-5)
    phi = bias_basis(grid, "quadrants", len(grid))
    assert np.all(phi.sum(axis=1) == 1)
    top_left = (grid[:, 0] < 0) & (grid[:, 1] < 0)
    assert np.all(phi[top_left, 0] == 1)
    cov = alignment_covariance(camera, view(pattern, camera, 40.0)[0], P, grid, "quadrants")
    assert cov.shape == (8, 8) and np.allclose(cov, cov.T)


def test_none_bias_is_plain_pnp(pattern, camera):
    pose, P, x, _ = view(pattern, camera, 30.0)
    result = align_global(camera, P, x, bias="none")
    assert result.bias_coeffs.shape == (0,)
    assert np.allclose(result.translation, 0.0)
    assert np.allclose(result.pose.R, pose.R, atol=1e-9)


def test_alternating_converges_slowly(pattern, camera):
    """Supplement B's alternation has the joint solution as fixed point but crawls towards it:
    the pose keeps most of the translation after 100 alternations."""
    _, P, x, _ = view(pattern, camera, 40.0)
    joint = align_global(camera, P, x + SHIFT, loss="mean")
    alternating = align_global(camera, P, x + SHIFT, loss="mean", method="alternating", iterations=100)
    error = np.linalg.norm(alternating.translation - SHIFT)
    assert error < np.linalg.norm(SHIFT)
    assert error > 1e3 * np.linalg.norm(joint.translation - SHIFT)
    assert alternating.method == "alternating" and not alternating.converged


def test_grid_coordinates_span_unit_square(pattern):
    grid = grid_coordinates(pattern, pattern.features)
    assert grid.min(axis=0) == pytest.approx([-1.0, -1.0])
    assert grid.max(axis=0) == pytest.approx([1.0, 1.0])


def test_invalid_options(pattern, camera):
    _, P, x, _ = view(pattern, camera, 40.0)
    with pytest.raises(ValueError, match="loss"):
        align_global(camera, P, x, loss="l2")
    with pytest.raises(ValueError, match="bias"):
        align_global(camera, P, x, bias="affine")
    with pytest.raises(ValueError, match="grid"):
        align_global(camera, P, x, bias="bilinear")
    with pytest.raises(ValueError, match="observed"):
        align_global(camera, P, x[:-1])
    with pytest.raises(ValueError, match="weights"):
        align_global(camera, P, x, np.ones(3))


@pytest.mark.parametrize(("bias", "loss", "max_steps"), [
    ("translation", "huber", 16), ("bilinear", "huber", 16), ("translation", "median", 40)])
def test_joint_alignment_converges_in_a_few_steps(pattern, camera, bias, loss, max_steps):
    """The joint solve's cost is its step count (each step one small linear solve): a handful of
    LM steps (12 measured with the default Huber width of 0.035 px, which reweights the noise's
    tail; 4 and 5 at the former 0.1 px, where Huber was least squares), more for the median's
    reweighting (24), and the fit reaches the noise. Wall-clock time is not asserted (a loaded
    machine would make that flaky)."""
    _, P, x, grid = view(pattern, camera, 40.0)
    P, x, grid = P[:300], x[:300], grid[:300]
    rng = np.random.default_rng(7)
    obs = x + SHIFT + rng.normal(0.0, NOISE, x.shape)
    result = align_global(camera, P, obs, grid=grid, bias=bias, loss=loss)
    assert result.converged and result.iterations <= max_steps
    assert result.median_error < 1.5 * 1.1774 * NOISE


# ------------------------------------------------------------------------------- experiment
SMALL = AlignmentSettings(frames=6, calibration_frames=6)


def test_experiment_runs_and_is_deterministic():
    first = run_alignment_experiment(SMALL, seed=1)
    second = run_alignment_experiment(SMALL, seed=1)
    assert first.table == second.table
    assert set(first.table) == set(ROWS)
    assert first.calibration_rms < 0.1
    for key, (med, mean, n) in first.table["Global Aligned (reproj.)"].items():
        assert med < 0.05 and mean < 0.06 and n >= 1, key
    for key, (med, _, _) in first.table["Random Shifted"].items():
        assert med > first.table["Raw"][key][0], key
    assert "Global Aligned" in format_table(first)


def test_experiment_main_writes_outputs(tmp_path: Path, capsys):
    assert main(["--out", str(tmp_path), "--frames", "4", "--calibration-frames", "5"]) == 0
    doc = json.loads((tmp_path / "alignment.json").read_text())
    assert doc["experiment"] == "alignment" and len(doc["frames"]) == 4
    assert {r["row"] for r in doc["table"]} == set(ROWS)
    for name in ("fig_exp41.png", "fig_exp42.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "tab:exp4" in capsys.readouterr().out


def test_experiment_main_errors(tmp_path: Path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["--out", str(blocker), "--frames", "2"]) == 2
    assert main(["--out", str(tmp_path), "--frames", "0"]) == 2
    assert "blurcalib: error" in capsys.readouterr().err


def test_direction_colours_follow_the_reference_tool():
    colours = direction_colours(np.array([[1.0, 0.0], [0.0, 1.0]]))
    assert colours[0] == pytest.approx(np.array([127, 254, 127]))
    assert colours[1] == pytest.approx(np.array([254, 127, 127]))
    scaled = direction_colours(np.array([[0.25, 0.0], [0.0, 2.0], [0.0, 0.0]]), full_px=0.5)
    assert scaled[0] == pytest.approx(np.array([127, 254, 127]) / 2)
    assert scaled[1] == pytest.approx(np.array([254, 127, 127]))
    assert scaled[2] == pytest.approx(np.zeros(3))
