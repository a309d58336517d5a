"""Files of the parametric family: OpenCV's FileStorage YAML and the reference tool's
``CentralOpenCVModel`` / ``CentralThinPrismFisheyeModel``, written and read back."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.files import (
    RefCameraError,
    read_opencv_yaml,
    read_parametric_yaml,
    write_parametric_yaml,
)
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.opencv_files import read_opencv_camera, write_opencv_camera
from blurcalib.camera.rational import RationalCamera
from blurcalib.camera.storage import CameraFileError
from blurcalib.camera.thin_prism import ThinPrismFisheyeCamera
from tests.camera.models import BROWN_CONRADY, KANNALA_BRANDT, MODELS, RATIONAL, THIN_PRISM

OPENCV_MODELS = (BROWN_CONRADY, RATIONAL, KANNALA_BRANDT)


def _same(a: ParametricCamera, b: ParametricCamera, rel: float = 0.0) -> bool:
    return (type(a) is type(b) and (a.width, a.height, a.angular) == (b.width, b.height, b.angular)
            and np.allclose(a.params, b.params, rtol=rel, atol=0.0))


@pytest.mark.parametrize("camera", OPENCV_MODELS, ids=[m.MODEL for m in OPENCV_MODELS])
def test_opencv_yaml_round_trip_is_exact(tmp_path: Path, camera: ParametricCamera) -> None:
    path = tmp_path / "camera.yaml"
    write_opencv_camera(path, camera)
    assert _same(read_opencv_camera(path), camera)
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert np.array_equal(storage.getNode("camera_matrix").mat(), camera.K)
    dist = storage.getNode("distortion_coefficients").mat().reshape(-1)
    assert np.array_equal(dist, [camera.named()[n] for n in camera.OPENCV_DISTORTION])
    assert storage.getNode("camera_model").string() == camera.MODEL
    assert storage.getNode("fisheye_model").real() == (camera is KANNALA_BRANDT)
    storage.release()


def _opencv_file(path: Path, dist: np.ndarray, **extra: object) -> None:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.array([[500.0, 0, 320], [0, 501, 240], [0, 0, 1]]))
    storage.write("distortion_coefficients", dist)
    storage.write("image_width", 640)
    storage.write("image_height", 480)
    for key, value in extra.items():
        storage.write(key, value)
    storage.release()


def test_opencv_tool_files_are_read_by_their_keys(tmp_path: Path) -> None:
    path = tmp_path / "cam.yaml"
    _opencv_file(path, np.array([[0.1, -0.2, 0.001, 0.002, 0.03]]))
    assert isinstance(read_opencv_camera(path), BrownConradyCamera)
    _opencv_file(path, np.array([[0.1, -0.2, 0.001, 0.002]]))
    assert read_opencv_camera(path).named()["k3"] == 0.0
    _opencv_file(path, np.array([0.1, -0.2, 0.001, 0.002, 0.03, 0.4, 0.05, 0.01, 0, 0, 0, 0]).reshape(-1, 1))
    rational = read_opencv_camera(path)
    assert isinstance(rational, RationalCamera) and rational.named()["k5"] == 0.05
    _opencv_file(path, np.array([[0.01, -0.002, 0.0003, 0.0]]), fisheye_model=1)
    fisheye = read_opencv_camera(path)
    assert isinstance(fisheye, KannalaBrandtCamera) and fisheye.named()["k3"] == 0.0003
    _opencv_file(path, np.array([[0.01, -0.002, 0.0003, 0.0]]), distortion_model="equidistant")
    assert isinstance(read_opencv_camera(path), KannalaBrandtCamera)


@pytest.mark.parametrize(("dist", "extra", "message"), [
    (np.array([[0.1, 0, 0, 0, 0, 0, 0, 0, 0.2, 0, 0, 0]]), {}, "non-zero entries beyond the 8"),
    (np.array([[0.1, 0.2, 0.3]]), {}, "has 3 entries"),
    (np.array([[0.1, 0.2, 0.3, 0.4]]), {"camera_model": "thin_prism_fisheye"}, "no thin_prism_fisheye"),
    (np.array([[0.1, 0.2, 0.3]]), {"camera_model": "Kannala_Brandt"}, "has 3 entries"),
    (np.array([[0.1, 0.2, 0.3, 0.4]]), {"camera_model": "pinhole"}, "unknown camera model"),
])
def test_bad_opencv_files_name_the_file_and_the_problem(tmp_path: Path, dist: np.ndarray, extra: dict,
                                                       message: str) -> None:
    path = tmp_path / "bad_camera.yaml"
    _opencv_file(path, dist, **extra)
    with pytest.raises(CameraFileError, match=f"bad_camera.yaml.*{message}"):
        read_opencv_camera(path)


def test_thin_prism_has_no_opencv_form(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="reference tool"):
        write_opencv_camera(tmp_path / "c.yaml", THIN_PRISM)
    assert not (tmp_path / "c.yaml").exists()


PERSPECTIVE_PRISM = ThinPrismFisheyeCamera(THIN_PRISM.params, 1280, 720, equidistant=False)


@pytest.mark.parametrize("camera", [*MODELS, PERSPECTIVE_PRISM],
                         ids=[m.MODEL for m in MODELS] + ["thin_prism_perspective"])
def test_reference_yaml_round_trip(tmp_path: Path, camera: ParametricCamera) -> None:
    path = tmp_path / "intrinsics0.yaml"
    write_parametric_yaml(path, camera)
    text = path.read_text()
    assert text.splitlines()[0] == ("type : CentralOpenCVModel" if not camera.angular and not isinstance(
        camera, ThinPrismFisheyeCamera) else "type : CentralThinPrismFisheyeModel")
    assert _same(read_parametric_yaml(path), camera, rel=1e-13)


def test_reference_files_use_the_pixel_corner_convention(tmp_path: Path) -> None:
    path = tmp_path / "intrinsics0.yaml"
    write_parametric_yaml(path, KANNALA_BRANDT)
    lines = path.read_text().splitlines()
    assert lines[3] == "use_equidistant_projection : true"
    values = [float(v) for v in lines[4].split("[")[1].rstrip("]").split(",")]
    assert values[2:4] == pytest.approx([KANNALA_BRANDT.cx + 0.5, KANNALA_BRANDT.cy + 0.5], abs=1e-12)
    assert values[4:8] == pytest.approx(list(KANNALA_BRANDT.params[4:]), rel=1e-13)
    assert values[8:] == [0.0, 0.0, 0.0, 0.0]


def test_rational_reference_file_is_not_a_brown_conrady_camera(tmp_path: Path) -> None:
    path = tmp_path / "intrinsics0.yaml"
    write_parametric_yaml(path, RATIONAL)
    with pytest.raises(RefCameraError, match=r"k4\.\.k6"):
        read_opencv_yaml(path)
    write_parametric_yaml(path, BROWN_CONRADY)
    assert read_opencv_yaml(path).fx == pytest.approx(BROWN_CONRADY.fx, rel=1e-14)
    path.write_text(path.read_text().replace("CentralOpenCVModel", "CentralThinPrismFisheyeModel"))
    with pytest.raises(RefCameraError, match="use_equidistant_projection"):
        read_parametric_yaml(path)
