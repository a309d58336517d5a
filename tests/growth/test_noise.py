"""The frame noise estimate (blurcalib.growth.noise) against the simulator's true Poisson-Gaussian noise."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from blurcalib.growth.noise import NoiseModel, estimate_noise, frame_noise, highpass_residual
from blurcalib.sim import render, synth
from blurcalib.sim.truth import FrameTruth


@pytest.fixture(scope="module")
def rendered() -> tuple[np.ndarray, FrameTruth]:
    """One blurry frame's irradiance (before the sensor) and its truth."""
    sim = synth.Simulator(synth.SynthConfig(sharp=0, blurry=1, blur_min_px=4.0, blur_max_px=10.0, seed=3))
    cfg = sim.config
    rng = np.random.default_rng([cfg.seed, 0])
    pose = synth.sample_pose(sim.pattern, sim.camera, rng, cfg.max_tilt_deg, cfg.square_px)
    motion = synth.sample_motion(sim.renderer, pose, sim.pattern, rng, 6.0, curved=True)
    truth = synth.frame_truth("blurry/0000.png", "blurry", sim.pattern, sim.camera, pose, motion, 0.6, rng,
                              cfg.noise_sigma)
    levels = [sim.texture(render.MIP_TEXELS_PER_SQUARE[k])
              for k in render.mip_levels_for(sim.camera, pose, sim.pattern, cfg.supersample)]
    return sim.renderer.irradiance(levels, pose, motion), truth


@pytest.mark.parametrize(("white", "electrons", "read"), [(150.0, 20.0, 0.5), (200.0, 10.0, 1.0),
                                                           (245.0, 5.0, 0.7)])
def test_the_estimate_tracks_the_simulated_noise(rendered, white: float, electrons: float,
                                                 read: float) -> None:
    """The estimated variance ``a + b mu`` is within 25% of the sensor's true one (shot noise,
    read noise, quantisation) at the ink's, mid grey and the paper's level."""
    irradiance, truth = rendered
    black = 0.15 * white
    truth = dataclasses.replace(truth, levels=(black, white), noise=(1.0 / electrons, read))
    image = render.sensor_image(irradiance, truth, np.random.default_rng(1)).astype(np.float32)
    model = estimate_noise(image)
    for mu in (black, (black + white) / 2, 0.9 * white):
        true = read**2 + 1.0 / 12.0 + mu / electrons
        assert abs(float(model.variance(mu)) / true - 1.0) < 0.25, (mu, float(model.variance(mu)), true)
    mid = (black + white) / 2
    assert 0.8 < model.sigma / np.sqrt(read**2 + 1 / 12 + model.level / electrons) < 1.2
    assert black < model.level < white and abs(model.level - mid) < 0.3 * (white - black)


@pytest.mark.parametrize(("electrons", "read"), [(2000.0, 0.1), (1e6, 0.05)])
def test_a_frame_of_whole_grey_levels_below_a_grey_level_of_noise_reads_its_quantisation(
        rendered, electrons: float, read: float) -> None:
    """A clean camera (0.29-0.38 grey levels of noise with the rounding to whole levels): its flat
    areas quantise to one level, and the estimate is still the noise at the frame's level (within
    25 %), not 0; the same through the float colour conversion of a video's frames."""
    irradiance, truth = rendered
    truth = dataclasses.replace(truth, levels=(30.0, 200.0), noise=(1.0 / electrons, read))
    image = render.sensor_image(irradiance, truth, np.random.default_rng(1)).astype(np.float32)
    assert np.array_equal(image, np.round(image))
    true = np.sqrt(read**2 + 1.0 / 12.0 + estimate_noise(image).level / electrons)
    colour = cv2.cvtColor(np.repeat(image[:, :, None], 3, axis=2), cv2.COLOR_BGR2GRAY)
    for frame in (image, colour):
        model = estimate_noise(frame)
        assert 0.75 < model.sigma / true < 1.25, (model, true)


def test_highpass_residual_has_unit_gain_on_white_noise_and_cancels_planes() -> None:
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 3.0, (300, 300))
    assert np.std(highpass_residual(noise)[2:-2, 2:-2]) == pytest.approx(3.0, rel=0.03)
    y, x = np.mgrid[0:50, 0:60]
    plane = 20.0 + 0.7 * x - 0.4 * y + 0.01 * x * y
    assert np.abs(highpass_residual(plane)[1:-1, 1:-1]).max() < 1e-9


def test_block_variance_is_taken_at_the_block_mean_level() -> None:
    model = NoiseModel(a=0.5, b=0.1, level=100.0)
    coeffs = np.array([[0.0, 0.0, 160.0, 0.0, 0.0, 20.0], [np.nan] * 6])
    var = model.block_variance(coeffs)
    assert var[0] == pytest.approx(0.5 + 0.1 * 100.0) and np.isnan(var[1])
    assert model.sigma == pytest.approx(np.sqrt(10.5))


def test_a_frame_without_enough_unclipped_pixels_has_no_estimate() -> None:
    saturated = np.full((200, 300), 255.0)
    with pytest.raises(ValueError, match="too few unclipped pixels"):
        estimate_noise(saturated)
    assert frame_noise(saturated) is None
    with pytest.raises(ValueError, match="height, width"):
        estimate_noise(np.zeros((4, 4, 3)))
