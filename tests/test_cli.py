"""The command line: outputs, exit codes and messages for bad input."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

from blurcalib.cli import build_parser, main
from blurcalib.cli.calibrate import pipeline_settings
from blurcalib.target.pattern import layout_pattern
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


@pytest.mark.slow
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


@pytest.mark.slow
def test_view_passes_options_to_the_app(capfd) -> None:
    assert main(["view", "--help"]) == 0
    assert "usage: blurcalib view" in capfd.readouterr().out


def _inputs(tmp_path):
    """A pattern YAML and folders of sharp and blurry frames (flat grey: nothing to find)."""
    pattern = layout_pattern().save_yaml(tmp_path / "pattern.yaml")
    for kind in ("sharp", "blurry"):
        (tmp_path / kind).mkdir()
        for i in range(2):
            cv2.imwrite(str(tmp_path / kind / f"{i}.png"), np.full((48, 64), 128, np.uint8))
    return pattern


def test_unavailable_device_is_one_line(tmp_path, capsys, monkeypatch) -> None:
    pattern = _inputs(tmp_path)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for command, (device, needle) in itertools.product(
            ("extract", "calibrate"), (("cuda", "--device 'cuda': CUDA is not available"),
                                       ("cuda:1", "--device 'cuda:1': CUDA is not available"),
                                       ("gpu", "--device 'gpu': not a torch device"))):
        code = main([command, str(tmp_path / "sharp"), "--pattern", str(pattern), "--out",
                     str(tmp_path / "out"), "--device", device])
        err = capsys.readouterr().err
        assert code == 2 and err.startswith("blurcalib: error: ") and needle in err
        assert err.count("\n") == 1 and not (tmp_path / "out").exists()


def test_device_reaches_the_block_solver_and_the_bundle_adjustment(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    pattern = _inputs(tmp_path)
    for command in ("calibrate", "demo"):
        where = [str(tmp_path / "sharp"), "--pattern", str(pattern)] if command == "calibrate" else []
        args = build_parser().parse_args([command, *where, "--out", str(tmp_path / "o"),
                                          "--device", "cuda:0"])
        s = pipeline_settings(args)
        assert s.extraction.deconv.device == "cuda:0" and s.calibration.generic.bundle.device == "cuda:0"
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
@pytest.mark.parametrize("command", ["extract", "calibrate"])
def test_user_files_are_never_overwritten(tmp_path, capsys, command) -> None:
    pattern = _inputs(tmp_path)
    out = tmp_path / "out"
    (out / "calibration").mkdir(parents=True)
    user = {"features.csv": "mine", "frames.csv": "mine", "psfs.npz": "mine",
            "calibration/camera.yaml": "mine"}
    for name, text in user.items():
        (out / name).write_text(text)
    argv = (["extract", str(tmp_path / "sharp")] if command == "extract" else
            ["calibrate", "--sharp", str(tmp_path / "sharp"), "--blurry", str(tmp_path / "blurry")])
    argv += ["--pattern", str(pattern), "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{out}: output folder is not empty and is not a blurcalib output" in err
    assert "--overwrite" in err and err.count("\n") == 1
    assert {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()} == set(user)
    assert all((out / name).read_text() == "mine" for name in user)
    if command == "extract":  # with --overwrite it runs (the flat frames have no tag: exit 1)
        assert main([*argv, "--overwrite"]) == 1
        assert "not_seeded" in (out / "frames.csv").read_text()
        assert main(argv) == 1  # now an extract output: re-runs need no --overwrite


def test_version_is_the_installed_package_version(capsys) -> None:
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"blurcalib {version('blurcalib')}"


def _compare_inputs(tmp_path) -> tuple[str, str, str]:
    """Two features.csv files of one simulated camera at the same 6 poses (noise 0.05 px), the second
    moved radially by -0.05 px x cos(pi r / 700 px), inwards near the centre and outwards at the
    border, as a pattern-dependent feature definition would."""
    from blurcalib.io.results import write_features
    from blurcalib.sim.truth import d435i_like_camera
    from tests.calib.test_sharp import simulate

    pattern = layout_pattern()
    camera = d435i_like_camera().model
    a, _ = simulate(pattern, camera, 6, seed=3)
    b, _ = simulate(pattern, camera, 6, seed=3)
    d = np.column_stack([b.x - camera.cx, b.y - camera.cy])
    r = np.linalg.norm(d, axis=1)
    shift = -0.05 * np.cos(np.pi * r / 700.0) / r
    b.x[:] += shift * d[:, 0]
    b.y[:] += shift * d[:, 1]
    paths = [str(write_features(tmp_path / f"{n}.csv", t)) for n, t in (("a", a), ("b", b))]
    return paths[0], paths[1], str(pattern.save_yaml(tmp_path / "pattern.yaml"))


@pytest.mark.slow
def test_compare_names_a_pattern_dependent_bias(tmp_path, capsys) -> None:
    a, b, pattern = _compare_inputs(tmp_path)
    assert main(["compare", a, b, "--pattern", pattern, "--image-size", "1280x720"]) == 0
    out = capsys.readouterr().out
    assert "systematic error: the two patterns place the same target points up to" in out
    # the same file twice: the same features, no residual at all
    assert main(["compare", a, a, "--pattern", pattern, pattern, "--image-size", "1280x720"]) == 0
    out = capsys.readouterr().out
    assert "no systematic error found" in out and "median 0.0000 px" in out
    assert "focal lengths +0.000 % / +0.000 %" in out


@pytest.mark.parametrize(("extra", "needle"), [
    ([], "--image-size"),
    (["--image-size", "1280x720", "--pattern", "{p}", "{p}", "{p}"], "one per file"),
])
def test_compare_bad_input_exits_2(tmp_path, capsys, extra, needle) -> None:
    a, b, pattern = _compare_inputs(tmp_path)
    argv = ["compare", a, b] + (["--pattern", pattern] if "--pattern" not in extra else []) + extra
    assert main([x.replace("{p}", pattern) for x in argv]) == 2
    err = capsys.readouterr().err
    assert "blurcalib: error:" in err and needle in err
