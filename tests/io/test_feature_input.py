"""Calibrating from a feature file (``calibrate --features``): the reference tool's dataset and
blurcalib's own features.csv, with the held-out validation and the uncertainty outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from blurcalib.calib.joint import JointSettings
from blurcalib.calib.sequence import SequenceSettings
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.validation import ValidationSettings
from blurcalib.cli import main
from blurcalib.io.feature_input import FeatureInputError, read_feature_input
from blurcalib.io.results import FeatureFlags, FeatureTable, write_features
from blurcalib.pipeline.run import PipelineSettings, run_from_features
from blurcalib.target.pattern import layout_pattern, load_pattern
from tests.calib.test_joint import simulated_features
from tests.conftest import FIXTURE_YAML

SHARP = int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME)
BLURRY = int(FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME)


@pytest.fixture(scope="module")
def features_csv(tmp_path_factory):
    """A features.csv of 8 sharp and 4 blurry simulated frames (blurry ones shifted by up to 2 px),
    with 0.03 px noise."""
    sharp = simulated_features(8, 1, SHARP, "sharp/s")
    blurry = simulated_features(4, 2, BLURRY, "blurry/b", shift=2.0)
    table = FeatureTable.concat([sharp, blurry])
    rng = np.random.default_rng(0)
    table.x += rng.normal(0, 0.03, len(table))
    table.y += rng.normal(0, 0.03, len(table))
    path = tmp_path_factory.mktemp("features") / "features.csv"
    write_features(path, table)
    return path


@pytest.mark.slow
def test_features_csv_calibrates_with_shifts_and_trust(features_csv, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    code = main(["calibrate", "--features", str(features_csv), "--image-size", "1280x720",
                 "--pattern", str(FIXTURE_YAML), "--out", str(out), "--cell-px", "80"])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert report["counts"]["blurry"] == {"used": 4} and report["counts"]["sharp"] == {"used": 8}
    assert report["generic"]["blurry_frames"] == 4 and report["generic"]["median_error_px"] < 0.06
    shifts = [r["shift"] for r in report["frames"] if r["kind"] == "blurry"]
    assert all(np.hypot(*s) < 2.9 for s in shifts)
    v = report["validation"]
    assert v["method"] == "kfold" and v["folds"] == 5 and report["validation_skipped"] is None
    assert v["generic"]["frames"] == 12 and 0.02 < v["generic"]["median_px"] < 0.08
    assert set(v) >= {"generic", "generic_sharp", "parametric"}
    unc = np.load(out / "calibration" / "uncertainty.npz")
    assert unc["sigma_px"].shape == unc["x"].shape == unc["sigma_px_sharp"].shape
    assert 0.01 < float(unc["noise_px"]) < 0.05  # 0.03 px per axis simulated
    assert (out / "calibration" / "uncertainty.png").is_file()
    assert (out / "calibration" / "sharp_only" / "intrinsics0.yaml").is_file()
    gain = report["blurry_frames_gain"]
    assert gain["uncertainty_median_px"][1] < gain["uncertainty_median_px"][0]
    printed = capsys.readouterr().out
    assert "held-out reprojection error (5-fold" in printed and "what the blurry frames bought" in printed
    me = report["model_error"]
    assert me["cells"] == [8, 6] and isinstance(me["systematic"], bool) and "noise_ratio" in me
    assert f"model error: {me['verdict']}" in printed


def test_features_csv_needs_the_image_size(features_csv) -> None:
    with pytest.raises(FeatureInputError, match="--image-size"):
        read_feature_input(features_csv, layout_pattern())
    table, size = read_feature_input(features_csv, layout_pattern(), (1280, 720))
    assert size == (1280, 720) and int(((table.flags & BLURRY) == BLURRY).sum()) > 0


def test_features_outside_the_image_size(features_csv, tmp_path) -> None:
    """A wrong --image-size is named before any calibration runs, and nothing is written."""
    with pytest.raises(FeatureInputError, match="outside the 640 x 480 image"):
        read_feature_input(features_csv, layout_pattern(), (640, 480))
    out = tmp_path / "out"
    code = main(["calibrate", "--features", str(features_csv), "--image-size", "640x480",
                 "--pattern", str(FIXTURE_YAML), "--out", str(out)])
    assert code == 2 and not (out / "report.json").exists()


def test_unknown_feature_file(tmp_path) -> None:
    path = tmp_path / "f.txt"
    path.write_text("x")
    with pytest.raises(FeatureInputError, match="reference dataset"):
        read_feature_input(path, layout_pattern())


@pytest.mark.slow
def test_reference_dataset_through_features(shared_fixtures, tmp_path, capsys) -> None:
    """The reference tool's own features of the real camera: generic median reprojection and
    held-out error printed, the generic camera below the parametric one held out too."""
    real = shared_fixtures / "real_star16"
    trust = TrustSettings(validation=ValidationSettings(folds=3), cross_validation=False)
    settings = PipelineSettings(calibration=SequenceSettings(trust=trust))
    report = run_from_features(real / "features_10px.bin", load_pattern(real / "pattern.yaml"),
                               tmp_path / "out", settings)
    assert report.counts["sharp"].get("used", 0) >= 20
    assert report.generic["median_error_px"] < 0.06
    v = report.to_dict()["validation"]
    assert v["generic"]["median_px"] < v["parametric"]["median_px"]
    assert v["generic"]["median_px"] < 0.08


@pytest.mark.slow
def test_a_full_disk_leaves_the_earlier_outputs_and_no_staging(features_csv, tmp_path, monkeypatch) -> None:
    """A write that fails while the output set is staged (no space left) removes the staging
    folder; the earlier run's outputs stay as they were."""
    import errno

    import blurcalib.pipeline.run as pipeline

    trust = TrustSettings(validation=ValidationSettings(method="none"), cross_validation=False)
    calibration = SequenceSettings(generic=JointSettings(cell_px=80.0), trust=trust)
    settings = PipelineSettings(calibration=calibration)
    out = tmp_path / "out"
    run_from_features(features_csv, layout_pattern(), out, settings, (1280, 720))
    before = (out / "report.json").read_bytes()

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pipeline, "save_trust", full)
    with pytest.raises(OSError, match="No space left"):
        run_from_features(features_csv, layout_pattern(), out, settings, (1280, 720))
    assert not (out / pipeline.STAGING_DIR).exists()
    assert (out / "report.json").read_bytes() == before
