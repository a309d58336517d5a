"""The command line: outputs, exit codes and messages for bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from blurcalib.cli import main
from tests.conftest import FIXTURE_YAML


def test_pattern_command_reproduces_fixture(tmp_path, capsys) -> None:
    assert main(["pattern", "--out", str(tmp_path / "t" / "star"), "--dpi", "50"]) == 0
    assert (tmp_path / "t" / "star.yaml").read_text() == FIXTURE_YAML.read_text()
    assert (tmp_path / "t" / "star.pdf").read_bytes().startswith(b"%PDF")
    assert (tmp_path / "t" / "star.png").stat().st_size > 1000
    assert "343 features" in capsys.readouterr().out


@pytest.mark.parametrize(("argv", "needle"), [
    (["pattern", "--out", "{tmp}/x", "--segments", "10"], "multiple of 4"),
    (["pattern", "--out", "{tmp}/x", "--page", "20x20"], "too few"),
    (["synth", "--out", "{tmp}/ds", "--pattern", "{tmp}/missing.yaml"], "missing.yaml"),
    (["synth", "--out", "{tmp}/file"], "not a folder"),
    (["synth", "--out", "{tmp}/ds", "--blur-min", "9", "--blur-max", "3"], "blur_min_px"),
])
def test_bad_input_exits_2_with_message(tmp_path, capsys, argv, needle) -> None:
    (tmp_path / "file").write_text("x")
    code = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and "blurcalib: error:" in err and needle in err
    assert not (tmp_path / "ds").exists() and not (tmp_path / "x.pdf").exists()


def test_non_empty_output_needs_overwrite(tmp_path, capsys) -> None:
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "keep.txt").write_text("user data")
    assert main(["synth", "--out", str(tmp_path / "ds"), "--sharp", "1", "--blurry", "0"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (tmp_path / "ds" / "keep.txt").read_text() == "user data"


def test_synth_command_writes_dataset(tmp_path) -> None:
    out = tmp_path / "ds"
    proc = subprocess.run(
        [sys.executable, "-m", "blurcalib", "synth", "--out", str(out), "--sharp", "1",
         "--blurry", "1", "--blur-min", "3", "--blur-max", "4", "--workers", "1"],
        capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    truth = json.loads((out / "ground_truth.json").read_text())
    assert [f["name"] for f in truth["frames"]] == ["sharp/0000.png", "blurry/0000.png"]
    assert (out / "sharp" / "0000.png").is_file() and (out / "blurry" / "0000.png").is_file()
    assert "simulated 2 frames" in proc.stdout


def test_view_passes_options_to_the_app(capfd) -> None:
    assert main(["view", "--help"]) == 0
    assert "usage: app.py" in capfd.readouterr().out
