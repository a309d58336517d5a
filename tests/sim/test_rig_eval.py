"""The stereo rig calibrated end to end on simulated sharp image sets (each camera as
``calibrate`` does, then the rig bundle), against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from blurcalib.calib.joint import JointSettings, calibrate_generic
from blurcalib.calib.rig_calibration import calibrate_rig
from blurcalib.calib.sharp import calibrate_sharp
from blurcalib.sim.rig import RigSimulator, d435i_stereo_rig
from blurcalib.sim.rig_eval import extrinsic_error, truth_features
from blurcalib.sim.synth import SynthConfig
from blurcalib.target.pattern import layout_pattern


@pytest.mark.slow
def test_stereo_pair_extrinsics_from_sharp_sets() -> None:
    pattern = layout_pattern()
    rig = d435i_stereo_rig(2)
    sim = RigSimulator(SynthConfig(sharp=8, blurry=0, seed=2), rig, pattern)
    sets = [sim.image_set(k) for k in range(8)]
    rng = np.random.default_rng(2)
    calibrations = []
    for c in range(2):
        frames = [s.frames[c] for s in sets if s.frames[c] is not None]
        table = truth_features(frames, pattern, 0.05, 0.0, rng)
        param = calibrate_sharp(table, pattern, (1280, 720))
        settings = JointSettings(cell_px=50.0)
        calibrations.append(calibrate_generic(table, None, param, pattern, (1280, 720), settings))
    result = calibrate_rig(calibrations)
    err = extrinsic_error(rig, result.bundle.rig)
    assert err.rotation_deg < 0.01 and err.translation_mm < 0.1
    assert len(result.sets) == 8
    assert np.all(result.bundle.median_error < 0.1)
