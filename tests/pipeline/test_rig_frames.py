"""``blurcalib calibrate-rig INPUT...`` (blurcalib.pipeline.rig_frames): image sets matched across the
cameras' inputs, refused inputs, and a rendered stereo pair's frames in, its extrinsics out."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.camera.rig_files import read_rig_folder
from blurcalib.cli import main
from blurcalib.pipeline.rig_frames import camera_frames, unlinked_camera
from blurcalib.pipeline.rig_output import read_rig_output
from blurcalib.pipeline.run import PipelineError
from blurcalib.sim.rig import TrueRig, d435i_stereo_rig, load_rig_truth, write_rig_dataset
from blurcalib.sim.rig_eval import rig_accuracy
from blurcalib.sim.synth import SynthConfig
from blurcalib.sim.truth import TrueCamera
from blurcalib.target.pattern import layout_pattern
from tests.rig_output_scene import write_rig_scene


def _images(folder: Path, names: list[str]) -> Path:
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / name), np.full((48, 64), 128, np.uint8))
    return folder


def _video(path: Path, frames: int) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    for i in range(frames):
        writer.write(np.full((48, 64, 3), 20 * i, np.uint8))
    writer.release()
    return path


def test_image_sets_match_by_name_and_by_video_index(tmp_path: Path) -> None:
    flat = camera_frames(_images(tmp_path / "left", ["0001.png", "0002.png"]))
    assert flat.sets == {"0001.png": "0001.png", "0002.png": "0002.png"}
    nested = camera_frames(_images(tmp_path / "cam0", ["sharp/0000.png", "blurry/0000.png"]))
    assert sorted(nested.sets.values()) == ["blurry/0000.png", "sharp/0000.png"]
    video = _video(tmp_path / "right.avi", 4)
    assert sorted(camera_frames(video).sets.values()) == [f"#{i:06d}" for i in range(4)]
    shifted = camera_frames(video, offset=2)
    assert shifted.sets["right#000002"] == "#000000" and shifted.sets["right#000000"] == "#-00002"
    with pytest.raises(PipelineError, match="left: a time offset applies to a video"):
        camera_frames(tmp_path / "left", offset=1)


def test_a_videos_frames_are_read_back_in_the_image_sets_of_its_time_offset(tmp_path: Path) -> None:
    """A rig output names each camera's input and time offset; reading it back matches a video's
    frames to the image sets the calibration used."""
    scene = write_rig_scene(tmp_path)
    report_path = scene.out / "report.json"
    report = json.loads(report_path.read_text())
    report["cameras"][1].update(input=str(_video(tmp_path / "right.avi", 4)), time_offset=2)
    report_path.write_text(json.dumps(report))
    frames = read_rig_output(scene.out).cameras[1].frames
    assert {name: frame.index for name, frame in frames.items()} == {
        "#-00002": 0, "#-00001": 1, "#000000": 2, "#000001": 3}


def test_cameras_link_through_shared_sets() -> None:
    assert unlinked_camera([{"a"}, {"a", "b"}, {"b"}]) is None  # camera 2 through camera 1
    assert unlinked_camera([{"a"}, {"a"}, {"c"}]) == 2
    assert unlinked_camera([{"a"}, {"b"}, {"b"}]) == 1


def test_a_camera_sharing_no_set_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    layout_pattern().save_yaml(tmp_path / "pattern.yaml")
    left = _images(tmp_path / "left", ["0001.png", "0002.png"])
    right = _images(tmp_path / "right", ["0001.png"])
    other = _images(tmp_path / "other", ["a.png", "b.png"])
    out = tmp_path / "out"
    args = ["calibrate-rig", "--pattern", str(tmp_path / "pattern.yaml"), "--out", str(out)]
    assert main([*args, str(left), str(right), str(other)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{other}: camera 2 shares no frame name with camera 0" in err
    assert main([*args, str(left), "--features", str(tmp_path / "a.csv"), str(tmp_path / "b.csv")]) == 2
    assert "one of them" in capsys.readouterr().err
    assert main([*args, str(left), str(right), "--time-offset", "0"]) == 2
    assert "one value per camera (2), got 1" in capsys.readouterr().err
    assert main([*args, str(left)]) == 2
    assert "two or more cameras" in capsys.readouterr().err
    assert main([*args, str(left), str(right), "--route", "aligned"]) == 2
    assert "generic cameras on the joint route" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
def test_stereo_pair_from_rendered_frames(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 640x360 camera and a 512x288 one (the same field of view) 50 mm apart, 8 sharp and 3
    blurry rendered sets, through the whole pipeline: the extrinsics within 0.5 mm and 0.05 deg of
    the truth, each generic camera within 0.15 px (median over the image; few frames of small
    images), each at its own size in the rig's files."""
    config = SynthConfig(sharp=8, blurry=3, square_px=(24.0, 30.0), max_tilt_deg=45.0, blur_min_px=4.0,
                         blur_max_px=8.0, seed=3)
    pair = d435i_stereo_rig(3, scale=0.5)
    smaller = TrueCamera(pair.cameras[1].model.scaled(0.8), pair.cameras[1].waves)
    data = tmp_path / "pair"
    write_rig_dataset(data, config, TrueRig((pair.cameras[0], smaller), pair.camera_tr_rig))
    out = tmp_path / "rig"
    args = ["calibrate-rig", str(data / "cam0"), str(data / "cam1"), "--out", str(out),
            "--pattern", str(data / "cam0" / "pattern.yaml"), "--workers", "1", "--validation", "none",
            "--parametric", "Brown_Conrady", "--no-maps"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "camera 1 <- camera 0: T = (" in printed and "image sets used: 11" in printed
    truth, _ = load_rig_truth(data)
    rig = read_rig_folder(out / "calibration").rig
    assert [(c.width, c.height) for c in rig.cameras] == [(640, 360), (512, 288)]
    acc = rig_accuracy(truth, rig)
    error = acc.pairs[0][2]
    assert error.translation_mm < 0.5 and error.rotation_deg < 0.05
    assert all(a.median < 0.15 for a in acc.cameras)
    report = json.loads((out / "report.json").read_text())
    assert [c["input"] for c in report["cameras"]] == [str(data / "cam0"), str(data / "cam1")]
    # the smaller camera sees two of the blurry sets blurred less than --sharp-below: sharp frames there
    assert [c["blurry_frames"] for c in report["cameras"]] == [3, 1]
    assert report["cameras"][1]["frames"] < report["sets"]  # camera 1 misses the target's tag in some sets
    assert (out / "stereo_0_1.yaml").is_file() and not (out / "rectify_0_1.npz").exists()
    assert report["pairs"][0]["translation_uncertainty_mm"] > 0.0
    assert (out / "cameras" / "cam1" / "report.json").is_file()
