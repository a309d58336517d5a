"""``blurcalib calibrate-rig`` (blurcalib.pipeline.rig): a simulated stereo pair's features in, the
rig's files out, with the extrinsics of the truth; refused inputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from blurcalib.calib.rig_residuals import set_epipolar
from blurcalib.camera.rig_files import read_rig_folder, read_stereo_yaml
from blurcalib.cli import main
from blurcalib.io.results import FeatureFlags, write_features
from blurcalib.pipeline.rig_output import read_rig_output
from blurcalib.sim.rig import RigSimulator, d435i_stereo_rig
from blurcalib.sim.rig_eval import extrinsic_error, truth_features
from blurcalib.sim.synth import SynthConfig
from blurcalib.target.pattern import layout_pattern


def test_refused_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pattern = tmp_path / "pattern.yaml"
    layout_pattern().save_yaml(pattern)
    out = tmp_path / "out"
    one = ["calibrate-rig", "--pattern", str(pattern), "--out", str(out), "--image-size", "1280x720"]
    assert main([*one, "--features", str(tmp_path / "a.csv")]) == 2
    assert "two or more cameras" in capsys.readouterr().err
    assert main([*one, "--features", str(tmp_path / "a.csv"), str(tmp_path / "b.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "a.csv" in err
    assert not out.exists()


@pytest.mark.slow
def test_stereo_pair_from_features(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pattern = layout_pattern()
    pattern.save_yaml(tmp_path / "pattern.yaml")
    rig = d435i_stereo_rig(5)
    sim = RigSimulator(SynthConfig(sharp=8, blurry=4, seed=5), rig, pattern)
    sets = [sim.image_set(k) for k in range(12)]
    rng = np.random.default_rng(5)
    files = []
    for c in range(2):
        frames = [s.frames[c] for s in sets if s.frames[c] is not None]
        table = truth_features(frames, pattern, 0.05, 3.0, rng)
        files.append(str(write_features(tmp_path / f"cam{c}.csv", table)))
    out = tmp_path / "rig"
    assert main(["calibrate-rig", "--features", *files, "--image-size", "1280x720", "--cell-px", "50",
                 "--pattern", str(tmp_path / "pattern.yaml"), "--out", str(out), "--no-maps"]) == 0
    printed = capsys.readouterr().out
    assert "camera 1 <- camera 0: T = (" in printed and "image sets used: 12" in printed
    folder = read_rig_folder(out / "calibration")
    assert folder.rig.size == 2 and sum(p is not None for p in folder.rig_tr_global) == 12
    err = extrinsic_error(rig, folder.rig)
    assert err.rotation_deg < 0.01 and err.translation_mm < 0.1
    report = json.loads((out / "report.json").read_text())
    assert abs(report["pairs"][0]["baseline_mm"] - 50.0) < 0.1
    pair = report["pairs"][0]
    assert 0.0 < pair["translation_uncertainty_mm"] < 0.1 and 0.0 < pair["rotation_uncertainty_deg"] < 0.01
    assert 0.04 < pair["holdout_error_px"] < 0.1 and pair["holdout_predictions"] > 1000  # 0.05 px noise
    assert "held-out error" in printed and "uncertainty" in printed
    stereo = read_stereo_yaml(out / "stereo_0_1.yaml")
    assert np.allclose(stereo.relative.t, folder.rig.relative(0, 1).t, atol=1e-12)
    back = read_rig_output(out)  # as the app reads it: the sets named, the features renamed to them
    assert back.set_names == report["set_names"] and len(set(back.set_names)) == 12
    sharp = [n for n in back.set_names if not np.any(back.cameras[0].features.flags[
        back.cameras[0].features.frame == n] & int(FeatureFlags.BLURRY_FRAME))]
    rect = back.pairs[0].rectification
    errors = np.concatenate([set_epipolar(rect, *back.rig.cameras, back.cameras[0].features,
                                          back.cameras[1].features, n).error for n in sharp])
    assert len(sharp) == 8 and len(errors) > 500 and np.median(errors) < 0.1  # 0.05 px noise per axis
