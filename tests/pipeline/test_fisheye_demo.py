"""``blurcalib demo --lens fisheye`` end to end: a 130 degree fisheye simulated, calibrated and
compared with its truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from blurcalib.cli import main


@pytest.mark.slow
def test_fisheye_demo_runs_end_to_end(tmp_path, capsys) -> None:
    """The smallest capture the pipeline takes (5 sharp frames, 2 blurry) of the 1280 x 720
    fisheye, with the Kannala-Brandt start named (the held-out choice of the model is
    ``tests/calib/test_model_choice.py``'s): over a minute of CPU, rendering and extracting 7
    full-size frames."""
    out = tmp_path / "demo"
    code = main(["demo", "--lens", "fisheye", "--parametric", "Kannala_Brandt", "--sharp", "5",
                 "--blurry", "2", "--workers", "1", "--validation", "none", "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0
    report = json.loads((out / "calibration" / "report.json").read_text())
    assert report["calibration"]["model"] == "Kannala_Brandt"
    assert report["generic"]["blurry_frames"] == 2 and not report["generic_failure"]
    assert report["undistortion"]["projection"] == "latlong" and report["undistortion"]["field_deg"] > 130
    maps = np.load(out / "calibration" / "calibration" / "undistortion_map.npz")
    assert str(maps["projection"]) == "latlong" and (maps["map_x"] >= 0).mean() > 0.5
    lines = printed.splitlines()
    start = next(i for i, line in enumerate(lines) if "each camera against the true camera" in line)
    errors = {line.split(" median ")[0].strip(): float(line.split(" median ")[1].split(",")[0])
              for line in lines[start + 1:start + 4]}
    assert list(errors) == ["parametric, sharp frames", "generic, sharp frames",
                            "generic, sharp + blurry frames"]
    assert errors["generic, sharp + blurry frames"] < min(0.15, errors["parametric, sharp frames"])
    assert "Brown-Conrady camera, from" not in printed  # the Result names the chosen model
    assert "undistortion map (undistortion_map.npz): latlong image of 1280x720 px" in printed
