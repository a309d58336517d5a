"""The app's rig state (state/rig.py over blurcalib.pipeline.rig_output): an exact rig output loads
with the poses written, its reprojection and epipolar errors are ~0, missing frames are said, and a
folder that is not a rig output is refused naming it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from state.rig import RigOutputError, load_rig
from tests.rig_output_scene import SET_NAMES, RigScene, write_rig_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> RigScene:
    return write_rig_scene(tmp_path_factory.mktemp("rig_scene"))


def test_loads_the_poses_written_and_exact_errors_are_zero(scene: RigScene) -> None:
    rig = load_rig(scene.out)
    out = rig.output
    assert rig.camera_labels == ["cam0", "cam1"] and rig.set_labels == SET_NAMES
    assert rig.pair_labels == ["cam0 - cam1"] and out.pairs[0].maps_file is not None
    for want, got in zip(scene.rig.camera_tr_rig, out.rig.camera_tr_rig, strict=True):
        assert np.allclose(want.R, got.R, atol=1e-12) and np.allclose(want.t, got.t, atol=1e-12)
    for want, got in zip(scene.rig_tr_global, out.rig_tr_global, strict=True):
        assert got is not None and np.allclose(want.t, got.t, atol=1e-12)
    assert np.allclose(rig.set_points(1), scene.rig_tr_global[1].transform(out.points))
    for c in range(2):
        res = rig.residuals(c)
        assert len(res.xy) == len(out.cameras[c].features) > 200 and res.stats[2] < 1e-6
    for name in SET_NAMES:
        view = rig.rectified(0, name)
        assert not view.missing and all(image is not None for image in view.images)
        assert len(view.epipolar.error) > 50 and view.epipolar.stats[2] < 0.01  # px
        # the frames' dots land on the features' rectified positions, in both images
        rectified = (view.epipolar.rectified1, view.epipolar.rectified2)
        for image, points in zip(view.images, rectified, strict=True):
            xy = np.round(points).astype(int)
            inside = (xy[:, 0] >= 0) & (xy[:, 0] < 320) & (xy[:, 1] >= 0) & (xy[:, 1] < 240)
            assert image is not None and np.median(image[xy[inside, 1], xy[inside, 0]]) > 180


def test_a_wrong_pose_shows_in_the_errors(scene: RigScene, tmp_path: Path) -> None:
    out = tmp_path / "rig"
    shutil.copytree(scene.out, out)
    poses = (out / "calibration" / "camera_tr_rig.yaml").read_text().splitlines()
    k = max(i for i, line in enumerate(poses) if line.strip().startswith("ty:"))
    poses[k] = "    ty: 0.003"  # camera 1 moved about 4 mm down
    (out / "calibration" / "camera_tr_rig.yaml").write_text("\n".join(poses) + "\n")
    rig = load_rig(out)
    assert rig.residuals(1).stats[0] > 0.5 and rig.residuals(0).stats[2] < 1e-6


def test_missing_frames_are_said_and_maps_computed_without_the_file(scene: RigScene, tmp_path: Path) -> None:
    out = tmp_path / "demo" / "calibration"  # where demo --rig --out demo writes its rig
    shutil.copytree(scene.out, out)
    (out / "rectify_0_1.npz").unlink()
    rig = load_rig(tmp_path / "demo")
    assert rig.output.folder == out and rig.output.pairs[0].maps_file is None
    shown = rig.rectified(0, SET_NAMES[0])
    assert shown.images[0] is not None and shown.epipolar.stats[2] < 0.01
    report = json.loads((out / "report.json").read_text())
    report["cameras"][1]["input"] = "gone/cam1"
    del report["set_names"]  # the sets are then named by the cameras' frames
    (out / "report.json").write_text(json.dumps(report))
    rig = load_rig(out)
    assert rig.set_labels == SET_NAMES
    view = rig.rectified(0, SET_NAMES[0])
    assert view.images[1] is None and view.images[0] is not None
    assert view.missing == "cam1: its input gone/cam1 is not found" and len(view.epipolar.error) > 50


@pytest.mark.parametrize(("make", "said"), [
    (lambda d: None, "not a folder"),
    (lambda d: d.mkdir(), "not a calibrate-rig output (no calibration/"),
    (lambda d: (d / "calibration").mkdir(parents=True), "not a calibrate-rig output (no report.json"),
])
def test_refused_folders(tmp_path: Path, make: object, said: str) -> None:
    folder = tmp_path / "D"
    make(folder)  # type: ignore[operator]
    with pytest.raises(RigOutputError) as err:
        load_rig(folder)
    message = str(err.value)
    assert message.startswith(str(folder)) and said in message and "\n" not in message

