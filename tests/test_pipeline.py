"""The whole pipeline on a small simulated dataset, and its errors for unusable input."""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest

from blurcalib.camera import BrownConrady
from blurcalib.cli import main
from blurcalib.evaluate import evaluate_features
from blurcalib.pattern import layout_pattern
from blurcalib.pipeline import PipelineError, PipelineSettings, run_pipeline
from blurcalib.quality import QualitySettings
from blurcalib.report import error_direction_image
from blurcalib.results import FeatureFlags, read_feature_table
from blurcalib.synth import SynthConfig, TrueCamera, load_ground_truth, write_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    model = BrownConrady(fx=420.0, fy=420.0, cx=239.6, cy=179.3, k1=0.02, k2=-0.03, p1=0.0003,
                         p2=-0.0002, k3=0.0, width=480, height=360)
    cfg = SynthConfig(sharp=6, blurry=2, square_px=(24.0, 30.0), max_tilt_deg=45.0,
                      blur_min_px=4.0, blur_max_px=6.0, seed=5)
    folder = tmp_path_factory.mktemp("ds")
    write_dataset(folder, cfg, camera=TrueCamera(model))
    return folder


def _settings() -> PipelineSettings:
    return PipelineSettings(quality=QualitySettings(min_sigma_major=0.0))


def test_pipeline_end_to_end(tmp_path, dataset) -> None:
    sharp = sorted((dataset / "sharp").glob("*.png"))
    blurry = sorted((dataset / "blurry").glob("*.png"))
    pattern = layout_pattern()
    report = run_pipeline(sharp, blurry, pattern, tmp_path / "out", _settings())
    assert report.calibration["num_frames"] == 6
    assert report.calibration["median_error_px"] < 0.1
    statuses = {r["frame"]: r["status"] for r in report.frames}
    assert set(statuses) == {f"sharp/{i:04d}.png" for i in range(6)} | {"blurry/0000.png",
                                                                        "blurry/0001.png"}
    assert "used" in statuses.values() or "ill_conditioned" in statuses.values()
    for key in ("features", "reference_features", "frames", "error_directions_sharp",
                "frame_errors"):
        assert (tmp_path / "out" / report.outputs[key].split("/")[-1]).is_file()
    saved = json.loads((tmp_path / "out" / "report.json").read_text())
    assert saved["counts"] == report.counts
    table = read_feature_table(tmp_path / "out" / "features.csv")
    assert np.any(table.flags & int(FeatureFlags.SHARP_FRAME))
    acc = evaluate_features(table, load_ground_truth(dataset), pattern, skip_flags=0)
    assert acc and max(a.median for a in acc) < 0.1


def test_mixed_resolution_is_refused(tmp_path, dataset) -> None:
    sharp = sorted((dataset / "sharp").glob("*.png"))
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 120), np.uint8))
    with pytest.raises(PipelineError, match=r"small.png \(120x100\)"):
        run_pipeline(sharp, [small], layout_pattern(), tmp_path / "out", _settings())


def test_too_few_sharp_frames_and_wrong_pattern(tmp_path, dataset) -> None:
    sharp = sorted((dataset / "sharp").glob("*.png"))[:3]
    with pytest.raises(PipelineError, match="sharp-set calibration"):
        run_pipeline(sharp, [], layout_pattern(), tmp_path / "a", _settings())
    assert (tmp_path / "a" / "sharp" / "features.csv").is_file()  # partial results kept
    with pytest.raises(PipelineError, match="no AprilTag"):
        run_pipeline(sharp, [], layout_pattern(tag_index=5), tmp_path / "b", _settings())


def test_error_direction_colours() -> None:
    xy = np.array([[4.0, 4.0], [12.0, 4.0], [20.0, 4.0]])
    res = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, 0.0]])  # down, right, none
    img = error_direction_image(xy, res, (24, 8), cell_px=8, saturate_px=0.5)
    # a = atan2(dy, dx): down is a = pi/2 -> RGB (254, 127, 127); right a = 0 -> (127, 254, 127).
    assert img[4, 4].tolist() == [127, 127, 254]
    assert img[4, 12].tolist() == [127, 254, 127]
    assert img[4, 20].tolist() == [0, 0, 0]


def test_default_calibrate_uses_little_blur_and_gives_reasons(tmp_path, dataset, capsys) -> None:
    out = tmp_path / "out"
    assert main(["calibrate", "--sharp", str(dataset / "sharp"), "--blurry",
                 str(dataset / "blurry"), "--pattern", str(dataset / "pattern.yaml"),
                 "--out", str(out), "--workers", "1"]) == 0
    with open(out / "frames.csv", newline="", encoding="utf-8") as handle:
        table = list(csv.DictReader(handle))
    frames = [r["frame"] for r in table]
    assert sorted(frames) == sorted([f"sharp/{i:04d}.png" for i in range(6)]
                                    + ["blurry/0000.png", "blurry/0001.png"])
    status = {r["frame"]: r["status"] for r in table}
    reason = {r["frame"]: r["reason"] for r in table}
    # 4-6 px of blur: the paper's 3.8 px pre-filter would drop both blurry frames; the defaults
    # keep them and they reach the global alignment.
    blurry = [f for f in frames if f.startswith("blurry/")]
    assert "low_blur" not in status.values()
    assert all(status[f] in ("used", "ill_conditioned") for f in blurry)
    assert any(status[f] == "used" for f in blurry)
    for f in frames:
        assert (status[f] == "used") == (reason[f] == ""), (f, status[f], reason[f])
    # "used" is exactly the set of frames whose features are written unflagged.
    features = read_feature_table(out / "features.csv")
    unflagged = set(features.frame[(features.flags & int(FeatureFlags.FILTERED_OUT)) == 0])
    assert unflagged == {f for f in frames if status[f] == "used"}
    assert "blurry frames:" in capsys.readouterr().out
