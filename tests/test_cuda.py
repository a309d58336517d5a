"""The CUDA path (``--device cuda``): the block solver and the generic bundle adjustment on the GPU
give what they give on the CPU. Rounding differs (the GPU's float32 sums are ordered
differently), so region growing may take another path: the extraction is held to the truth, the
bundle adjustment (float64) to the CPU's camera. Skipped where torch sees no CUDA device."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from blurcalib.calib.bundle import BundleSettings
from blurcalib.calib.joint import JointSettings, calibrate_generic
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.extract.frame import ExtractSettings, extract_frame
from blurcalib.sim.evaluate import pose_consistent_errors
from blurcalib.sim.synth import Simulator, SynthConfig
from tests.calib.test_joint import joint_inputs

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="torch sees no CUDA device here")


@pytest.mark.slow
@pytest.mark.parametrize(("blur", "square", "index", "min_share", "max_median"), [
    ((4.0, 15.0), (30.0, 47.0), 0, 0.9, 0.05),    # close-up, free PSFs
    ((12.0, 25.0), None, 3, 0.85, 0.1),           # 22 px on 20-24 px squares: tag ring and path field
], ids=["close-up", "heavy"])
def test_a_frame_extracted_on_cuda_is_as_accurate_as_on_the_cpu(blur, square, index, min_share,
                                                                  max_median) -> None:
    extra = {"square_px": square} if square else {}
    sim = Simulator(SynthConfig(sharp=0, blurry=index + 1, blur_min_px=blur[0], blur_max_px=blur[1],
                                noise_sigma=2.0, seed=11, **extra))
    frame = sim.frame(index)
    image = frame.image.astype(np.float32)
    visible = int(frame.truth.block_inside.sum())
    runs = {device: extract_frame(image, sim.pattern, frame.truth.name,
                                  ExtractSettings(deconv=DeconvSettings(device=device)))
            for device in ("cpu", "cuda")}
    cpu, gpu = runs["cpu"], runs["cuda"]
    assert (gpu.growth.psf_field is None) == (cpu.growth.psf_field is None)
    assert len(gpu.features) > min_share * visible, (len(gpu.features), len(cpu.features), visible)
    ids = gpu.features.feature_id
    err = pose_consistent_errors(np.stack([gpu.features.x, gpu.features.y], axis=1), frame.truth.mean[ids])
    assert np.median(err) < max_median and err.max() < 1.0, (np.median(err), err.max())
    assert abs(len(gpu.features) - len(cpu.features)) < 0.05 * visible


def test_the_generic_bundle_adjustment_on_cuda_gives_the_cpus_camera() -> None:
    pattern, sharp, blurry, parametric = joint_inputs()
    fits = {device: calibrate_generic(sharp, blurry, parametric, pattern, (1280, 720),
                                      JointSettings(cell_px=80.0, bundle=BundleSettings(device=device)))
            for device in ("cpu", "cuda")}
    cpu, gpu = fits["cpu"], fits["cuda"]
    assert gpu.frames == cpu.frames and np.array_equal(gpu.inlier, cpu.inlier)
    assert np.abs(gpu.residuals - cpu.residuals).max() < 1e-6
    for name in cpu.shifts:
        assert np.abs(gpu.shifts[name] - cpu.shifts[name]).max() < 1e-6
    assert cpu.median_error < 0.05
