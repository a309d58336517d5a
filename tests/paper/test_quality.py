"""The real-world-evaluation experiments on a small simulated camera: PSF quality
(fig:exp_real1, fig:exp_real2) and the loss-threshold sweep (fig:exp_real3)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from blurcalib.calib.sharp import Calibration
from blurcalib.camera.parametric import BrownConrady
from blurcalib.paper import common, psf_field, psf_quality, threshold_sweep
from blurcalib.paper.common import ExtractedFrame
from blurcalib.paper.psf_quality import PsfQualitySettings
from blurcalib.paper.threshold_sweep import BIASES, CONFIGS, SweepExperiment, SweepSettings
from blurcalib.sim.synth import Simulator, SynthConfig
from blurcalib.sim.truth import TrueCamera

SHARP = 6
BLURRY = 3


@pytest.fixture(scope="module")
def sim() -> Simulator:
    model = BrownConrady(fx=420.0, fy=420.0, cx=239.6, cy=179.3, k1=0.02, k2=-0.03, p1=0.0003,
                         p2=-0.0002, k3=0.0, width=480, height=360)
    cfg = SynthConfig(sharp=SHARP, blurry=BLURRY, square_px=(24.0, 30.0), max_tilt_deg=45.0,
                      blur_min_px=4.0, blur_max_px=7.0, seed=3)
    return Simulator(cfg, camera=TrueCamera(model))


@pytest.fixture(scope="module")
def frames(sim: Simulator) -> list[ExtractedFrame]:
    """The blurry frames, extracted once (13 x 13 window, growth capped for speed)."""
    return common.extract_frames(sim, range(SHARP, SHARP + BLURRY),
                                 common.extract_settings(kernel_size=13, max_blocks=40))


@pytest.fixture(scope="module")
def sweep_settings() -> SweepSettings:
    return SweepSettings(sharp=SHARP, blurry=BLURRY, kernel_size=13, max_blocks=40)


@pytest.fixture(scope="module")
def calibration(sim: Simulator, sweep_settings: SweepSettings) -> Calibration:
    return threshold_sweep.calibrate(sim, sweep_settings, seed=3)


@pytest.fixture(scope="module")
def quality(sim: Simulator, frames: list[ExtractedFrame]) -> psf_quality.PsfQualityExperiment:
    settings = PsfQualitySettings(kernel_size=13)
    return psf_quality.analyse_psf_quality(frames, sim.camera, sim.pattern, settings)


@pytest.fixture(scope="module")
def sweep(sim: Simulator, frames: list[ExtractedFrame], calibration: Calibration,
          sweep_settings: SweepSettings) -> SweepExperiment:
    return threshold_sweep.analyse_sweep(frames, calibration, sim.camera, sim.pattern, sweep_settings)


# ------------------------------------------------------------------------------ PSF quality
@pytest.mark.slow
def test_frames_are_extracted(frames: list[ExtractedFrame]) -> None:
    assert len(frames) == BLURRY and all(f.ok for f in frames)
    assert all(f.result.growth.accepted.sum() >= 12 for f in frames)
    assert "blocks accepted" in frames[0].summary()


@pytest.mark.slow
def test_recentring_moves_star_centres_to_the_time_averaged_positions(quality) -> None:
    rc = quality.statistics["recentring"]
    # The fitted PSFs sit off the window centre by a fraction of a pixel; re-centring on their
    # centroids moves the star centre onto the true time-averaged (blurred) position.
    assert 0.02 < rc["median_centroid_px"] < 1.0
    assert rc["median_error_after_px"] < 0.1
    assert rc["median_error_after_px"] < 0.5 * rc["median_error_before_px"]
    blocks = quality.blocks
    assert np.allclose(blocks.centre - blocks.centre_fit, blocks.centroid, atol=1e-6)


@pytest.mark.slow
def test_statistics_and_figures(quality, tmp_path) -> None:
    stats = quality.statistics
    assert stats["blocks"] == len(quality.blocks) > 0 and stats["frames"] == BLURRY
    assert sum(b["count"] for b in stats["be_bins"]) == stats["blocks"]
    split = stats["be_split"]
    assert split["below"]["count"] + split["above"]["count"] == stats["blocks"]
    assert stats["spearman"]["sigma_major_true_blur"] > 0.5  # sigma_major follows the true blur
    assert quality.field is not None and len(quality.field.region) == PsfQualitySettings().magnified
    paths = psf_quality.write_outputs(quality, tmp_path / "out", seed=3)
    assert sorted(p.name for p in paths) == ["fig_exp_real1.png", "fig_exp_real2.png", "psf_quality.json"]
    for p in paths[1:]:
        image = cv2.imread(str(p))
        assert image is not None and image.shape[0] > 300 and image.shape[1] > 600
    doc = json.loads((tmp_path / "out" / "psf_quality.json").read_text())
    assert {"experiment", "paper", "seed", "settings", "camera", "statistics", "frames", "field_frame",
            "blocks", "paper_claims"} <= set(doc)
    assert len(doc["frames"]) == BLURRY and len(doc["blocks"]["loss"]) == stats["blocks"]
    assert doc["settings"]["be_bins"][-1] == "inf"
    assert "median loss BE <= 0.15" in psf_quality.format_table(quality)


@pytest.mark.slow
def test_psf_mosaic_draws_each_accepted_block_at_its_place(frames: list[ExtractedFrame]) -> None:
    frame = frames[0]
    fit = frame.result.growth.fit
    mosaic = psf_field.psf_mosaic(frame, fit.psf, zoom=2)
    w, h = frame.image_size
    assert mosaic.shape == (2 * h, 2 * w) and mosaic.min() >= 0.0 and mosaic.max() == pytest.approx(1.0)
    acc = np.flatnonzero(frame.result.growth.accepted)
    centre = np.round((fit.centre[acc] + 0.5) * 2 - 0.5).astype(int)
    # A re-centred PSF's centroid is the kernel centre, where the blur has mass.
    assert np.mean(mosaic[centre[:, 1], centre[:, 0]] > 0.05) > 0.8


# ------------------------------------------------------------------------------ threshold sweep
def test_sharp_features_from_truth_use_the_simulators_poses(sim: Simulator) -> None:
    obs = threshold_sweep.sharp_observations_from_truth(sim, [0], noise_px=0.0, seed=3)
    truth = sim.frame(0).truth
    ids = np.array([o.feature_id for o in obs])
    xy = np.array([[o.x, o.y] for o in obs])
    assert len(obs) == int(truth.visible.sum())
    assert np.abs(xy - truth.mid[ids]).max() < 1e-9


@pytest.mark.slow
def test_kept_blocks_grow_with_the_loss_threshold(sweep: SweepExperiment) -> None:
    taus = sweep.settings.tau_losses
    for config in CONFIGS:
        kept = [sweep.kept_blocks(config, t) for t in taus]
        assert kept == sorted(kept) and kept[-1] > 0
    # Without the BE filter the raw configuration keeps at least as many blocks.
    assert sweep.kept_blocks("raw", math.inf) >= sweep.kept_blocks("be_filtered", math.inf)


@pytest.mark.slow
def test_un_recentred_centres_are_worse_than_recentred_ones(sweep: SweepExperiment) -> None:
    for bias in BIASES:
        raw = sweep.summary("raw", 30.0, bias)
        recentred = sweep.summary("be_filtered", 30.0, bias)
        assert raw["frames_aligned"] == recentred["frames_aligned"] == BLURRY
        assert raw["true_px_median"] > 2.0 * recentred["true_px_median"]
        assert raw["alignment_px_median"] > recentred["alignment_px_median"]
        assert recentred["true_px_median"] < 0.1


@pytest.mark.slow
def test_sweep_outputs(sweep: SweepExperiment, tmp_path) -> None:
    paths = threshold_sweep.write_outputs(sweep, tmp_path, seed=3)
    image = cv2.imread(str(tmp_path / "fig_exp_real3.png"))
    assert image is not None and image.shape[1] > 600
    doc = json.loads(paths[0].read_text())
    assert {"experiment", "paper", "seed", "settings", "true_camera", "calibration", "frames", "table",
            "per_frame", "paper_full_pipeline_px"} <= set(doc)
    taus = sweep.settings.tau_losses
    assert len(doc["table"]) == len(BIASES) * len(CONFIGS) * len(taus)
    assert doc["settings"]["tau_losses"][-1] == "inf"
    row = doc["table"][0]
    assert {"config", "tau_loss", "bias", "frames_aligned", "kept_blocks", "alignment_px_median",
            "alignment_px_q25", "alignment_px_q75", "true_px_median", "true_px_q25",
            "true_px_q75"} <= set(row)
    assert all(len(cell["frames"]) == BLURRY for cell in doc["per_frame"])
    assert "tau_L" in threshold_sweep.format_table(sweep)


# ------------------------------------------------------------------------------------ commands
@pytest.mark.parametrize(("main", "argv"), [
    (psf_quality.main, ["--frames", "0"]),
    (psf_quality.main, ["--kernel", "16"]),
    (psf_quality.main, ["--blur-min", "5", "--blur-max", "2"]),
    (psf_quality.main, ["--device", "no-such-device"]),
    (threshold_sweep.main, ["--sharp", "2"]),
    (threshold_sweep.main, ["--blurry", "0"]),
    (threshold_sweep.main, ["--tau-be", "0"]),
])
def test_bad_options_return_2(main, argv, tmp_path, capsys) -> None:
    assert main([*argv, "--out", str(tmp_path)]) == 2
    assert "blurcalib: error:" in capsys.readouterr().err


@pytest.mark.parametrize("main", [psf_quality.main, threshold_sweep.main])
def test_unwritable_output_returns_2(main, tmp_path, capsys) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["--out", str(blocker / "sub")]) == 2
    assert "blurcalib: error:" in capsys.readouterr().err


@pytest.mark.slow
def test_commands_write_their_outputs(tmp_path, capsys) -> None:
    small = ["--scale", "0.375", "--kernel", "9", "--max-blocks", "12", "--blur-min", "2", "--blur-max", "3",
             "--out", str(tmp_path)]
    assert psf_quality.main(["--frames", "1", *small]) == 0
    assert threshold_sweep.main(["--sharp", "5", "--blurry", "1", *small]) == 0
    assert {"psf_quality.json", "fig_exp_real1.png", "fig_exp_real2.png", "threshold_sweep.json",
            "fig_exp_real3.png"} <= {p.name for p in tmp_path.iterdir()}
    out = capsys.readouterr().out
    assert "PSF quality" in out and "Threshold sweep" in out and "outputs:" in out
