"""Parametric cameras of the family in OpenCV's FileStorage YAML, the form ``cv2.FileStorage``
users read.

Keys: ``camera_model`` (the family's model name), ``distortion_model`` (ROS ``camera_info``'s name:
``plumb_bob``, ``rational_polynomial`` or ``equidistant``), ``fisheye_model`` (1 for the
``cv::fisheye`` convention, as OpenCV's calibration sample writes it), ``camera_matrix`` (3x3)
``distortion_coefficients`` (1xN in OpenCV's order: 5 for Brown-Conrady, 8 for the rational model,
4 ``k1..k4`` for ``cv::fisheye``), ``image_width``, ``image_height`` (px, OpenCV convention).

A file without ``camera_model`` (one written by OpenCV's tools) is read by its other keys: a
fisheye flag or ``equidistant`` is Kannala-Brandt, 4 or 5 coefficients Brown-Conrady, 8 (or 12 and
14 whose thin-prism and tilt entries are 0) the rational model. The thin-prism fisheye has no
OpenCV form (its file is the reference tool's, :mod:`blurcalib.camera.files`).
"""

from __future__ import annotations

import os

import numpy as np

from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.family import model_class
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.rational import RationalCamera
from blurcalib.camera.storage import CameraFileError, StorageReader, write_storage

__all__ = ["read_opencv_camera", "write_opencv_camera"]

ROS_NAMES = {BrownConradyCamera.MODEL: "plumb_bob", RationalCamera.MODEL: "rational_polynomial",
             KannalaBrandtCamera.MODEL: "equidistant"}
"""ROS ``camera_info.distortion_model`` of each model OpenCV has."""


def write_opencv_camera(path: str | os.PathLike[str], camera: ParametricCamera) -> None:
    """Write ``camera`` as OpenCV FileStorage YAML (module docstring), atomically and exactly.

    Raises:
        ValueError: the model has no OpenCV form (the thin-prism fisheye).
    """
    names = camera.OPENCV_DISTORTION
    if names is None:
        raise ValueError(f"OpenCV has no {camera.MODEL} model; write it as the reference tool's file")
    values = camera.named()
    write_storage(path, {
        "camera_model": camera.MODEL, "distortion_model": ROS_NAMES[camera.MODEL],
        "fisheye_model": int(camera.MODEL == KannalaBrandtCamera.MODEL), "camera_matrix": camera.K,
        "distortion_coefficients": np.array([[values[n] for n in names]]),
        "image_width": camera.width, "image_height": camera.height})


def _model_of(file: StorageReader, count: int) -> type[ParametricCamera]:
    """The model a file holds: its ``camera_model``, else from its OpenCV keys."""
    if file.has("camera_model"):
        return model_class(file.text("camera_model"))
    fisheye = file.has("fisheye_model") and file.number("fisheye_model") != 0
    if fisheye or (file.has("distortion_model") and file.text("distortion_model") == "equidistant"):
        return KannalaBrandtCamera
    return BrownConradyCamera if count in (4, 5) else RationalCamera


def read_opencv_camera(path: str | os.PathLike[str]) -> ParametricCamera:
    """Read a camera of the family from OpenCV FileStorage YAML (module docstring).

    Raises:
        CameraFileError: missing, unreadable or malformed file, or coefficients the model cannot
            hold; the message names the file and the problem.
    """
    with StorageReader(path) as file:
        file.require("camera_matrix", "distortion_coefficients", "image_width", "image_height")
        K = file.matrix("camera_matrix")
        dist = file.matrix("distortion_coefficients").reshape(-1)
        cls = _model_of(file, dist.size)
        if cls.OPENCV_DISTORTION is None:
            raise CameraFileError(f"camera file {file.name!r}: OpenCV has no {cls.MODEL} model")
        names = cls.OPENCV_DISTORTION
        if dist.size > len(names) and np.any(dist[len(names):] != 0):
            raise CameraFileError(f"camera file {file.name!r}: distortion_coefficients has non-zero entries "
                                  f"beyond the {len(names)} of the {cls.MODEL} model")
        if dist.size < len(names) and not (cls is BrownConradyCamera and dist.size == 4):
            raise CameraFileError(f"camera file {file.name!r}: distortion_coefficients has {dist.size} "
                                  f"entries, the {cls.MODEL} model {len(names)}")
        if K.shape != (3, 3) or K[0, 1] != 0 or K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
            raise CameraFileError(f"camera file {file.name!r}: camera_matrix must be "
                                  "[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
        values = dict(zip(names, dist, strict=False))
        width, height = file.number("image_width"), file.number("image_height")
        if width != int(width) or height != int(height):
            raise CameraFileError(f"camera file {file.name!r}: image_width and image_height must be integers")
        return cls.from_values(int(width), int(height), fx=K[0, 0],
                               fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], **values)
