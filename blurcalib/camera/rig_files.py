"""A rig's files: the reference tool's calibration folder, and OpenCV's per-camera and stereo files.

The reference tool's folder (its ``io/calibration_io.cc``, ``SaveBAState``/``LoadBAState``):

* ``intrinsics{N}.yaml``: camera ``N``'s ``CentralGenericModel`` (:mod:`blurcalib.camera.files`);
* ``camera_tr_rig.yaml``: each camera's rig -> camera pose;
* ``rig_tr_global.yaml``: each image set's target -> rig pose (only the sets used);
* ``points.yaml``: the target's points (m) and their feature ids.

A pose file (yaml-cpp reads it)::

    # Each pose gives the B_tr_A transformation ...
    pose_count: N
    poses:
      - index: i
        tx: ..          (ty, tz: metres)
        qx: ..          (qy, qz, qw: the rotation's unit quaternion, Eigen's names)

numbers with 14 significant digits, as the tool writes them; an index missing from ``poses`` is a
pose not used. OpenCV's files (FileStorage YAML, :mod:`blurcalib.camera.storage`): ``camera{N}.yaml``
(a parametric camera, :func:`blurcalib.camera.opencv_files.write_opencv_camera`) and, per pair,
``stereo_{i}_{j}.yaml`` with ``R``, ``T``, ``E``, ``R1``, ``R2``, ``rectified_camera_matrix``,
``rectification_model`` and, for a pinhole rectification, ``P1``, ``P2``, ``Q``
(:mod:`blurcalib.camera.stereo`), beside ``rectify_{i}_{j}.npz`` (``cv2.remap`` maps ``map1_x,
map1_y, map2_x, map2_y`` float32 from each generic camera's image to the rectified images).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike

from blurcalib.camera.files import RefCameraError, read_generic_yaml, write_generic_yaml
from blurcalib.camera.generic import CentralGeneric
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.opencv_files import write_opencv_camera
from blurcalib.camera.remap import OutputProjection
from blurcalib.camera.rig import Rig
from blurcalib.camera.stereo import StereoRectification, rectification_maps, stereo_rectify
from blurcalib.camera.storage import CameraFileError, StorageReader, write_storage
from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import atomic_path, atomic_write_text, ensure_writable_dir

__all__ = ["CAMERA_TR_RIG_FILE", "POINTS_FILE", "RIG_TR_GLOBAL_FILE", "RigFileError", "RigFolder",
           "intrinsics_file", "read_points", "read_poses", "read_rig_folder", "read_stereo_yaml",
           "stereo_names", "write_poses", "write_rig_folder", "write_stereo_pair"]

CAMERA_TR_RIG_FILE = "camera_tr_rig.yaml"
RIG_TR_GLOBAL_FILE = "rig_tr_global.yaml"
POINTS_FILE = "points.yaml"
POSES_COMMENT = ("# Each pose gives the B_tr_A transformation (i.e., A to B with right-multiplication), "
                 "where the spaces A and B are defined by the filename. Quaternions are written as used by "
                 "the Eigen library.")
_POSE_KEYS = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")


class RigFileError(ValueError):
    """A rig file is missing or malformed; the message names the file and the problem."""


def intrinsics_file(camera: int) -> str:
    """The reference tool's name of camera ``camera``'s model file."""
    return f"intrinsics{camera}.yaml"


def _num(value: float) -> str:
    return f"{float(value):.14g}"


def write_poses(path: str | os.PathLike[str], poses: Sequence[Pose | None]) -> Path:
    """Write a pose file (module docstring), atomically; ``None`` entries are poses not used."""
    lines = [POSES_COMMENT, f"pose_count: {len(poses)}", "poses:"]
    for i, pose in enumerate(poses):
        if pose is None:
            continue
        values = (*pose.t, *pose.quaternion)
        lines.append(f"  - index: {i}")
        lines += [f"    {key}: {_num(v)}" for key, v in zip(_POSE_KEYS, values, strict=True)]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def _load_yaml(path: Path) -> Any:
    """The YAML document of ``path``.

    Raises:
        RigFileError: naming the file when it cannot be read or is not YAML.
    """
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise RigFileError(f"{path}: cannot read ({exc})") from None
    except yaml.YAMLError as exc:
        raise RigFileError(f"{path}: not YAML ({str(exc).splitlines()[0]})") from None


def read_poses(path: str | os.PathLike[str]) -> list[Pose | None]:
    """Read a pose file: ``pose_count`` entries, None where no pose is given.

    Raises:
        RigFileError: naming the file and what is missing or malformed.
    """
    path = Path(path)
    doc = _load_yaml(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("pose_count"), int) or doc["pose_count"] < 0:
        raise RigFileError(f"{path}: needs 'pose_count' (an integer >= 0) and 'poses'")
    entries = doc.get("poses") or []
    if not isinstance(entries, list):
        raise RigFileError(f"{path}: 'poses' must be a list")
    poses: list[Pose | None] = [None] * doc["pose_count"]
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict) or not isinstance(entry.get("index"), int):
            raise RigFileError(f"{path}: pose {k} has no integer 'index'")
        index = entry["index"]
        if not 0 <= index < len(poses) or poses[index] is not None:
            raise RigFileError(f"{path}: pose index {index} is outside 0..{len(poses) - 1} or repeated")
        try:
            v = [float(entry[key]) for key in _POSE_KEYS]
            poses[index] = Pose.from_quaternion(v[3:], v[:3])
        except (KeyError, TypeError, ValueError) as exc:
            raise RigFileError(f"{path}: pose index {index}: needs numbers {', '.join(_POSE_KEYS)} "
                               f"({exc})") from None
    return poses


def _write_points(path: Path, points: np.ndarray, feature_ids: np.ndarray) -> Path:
    lines = ["# Each point is stored as x, y, z.",
             "points : [" + ", ".join(_num(v) for v in points.reshape(-1)) + "]",
             "feature_id_to_point_index:"]
    for index, fid in enumerate(feature_ids):
        lines += [f"  - feature_id: {int(fid)}", f"    point_index: {index}"]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_points(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read ``points.yaml``: the target's points ``(M, 3)`` m and their feature ids ``(M,)``.

    Raises:
        RigFileError: naming the file and what is missing or malformed.
    """
    path = Path(path)
    doc = _load_yaml(path)
    try:
        points = np.asarray(doc["points"], dtype=np.float64).reshape(-1, 3)
        ids = np.full(len(points), -1, dtype=np.int64)
        for entry in doc.get("feature_id_to_point_index") or []:
            ids[int(entry["point_index"])] = int(entry["feature_id"])
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise RigFileError(f"{path}: needs 'points' (x, y, z each) and 'feature_id_to_point_index' "
                           f"({exc})") from None
    return points, ids


@dataclass(frozen=True, eq=False)
class RigFolder:
    """A reference-tool calibration folder's contents.

    Attributes:
        rig: the cameras and their rig -> camera poses.
        rig_tr_global: ``(pose_count,)`` target -> rig poses of the image sets, None where unused.
    """

    rig: Rig
    rig_tr_global: list[Pose | None]


def write_rig_folder(folder: str | os.PathLike[str], rig: Rig, rig_tr_global: Sequence[Pose | None],
                     points: ArrayLike | None = None, feature_ids: ArrayLike | None = None) -> list[Path]:
    """Write the reference tool's calibration folder (module docstring); ``points (M, 3)`` m with
    their ``feature_ids (M,)`` add ``points.yaml`` (the tool's loader needs it). Returns the paths."""
    out = ensure_writable_dir(folder)
    paths = [write_generic_yaml(out / intrinsics_file(c), camera) for c, camera in enumerate(rig.cameras)]
    paths.append(write_poses(out / CAMERA_TR_RIG_FILE, rig.camera_tr_rig))
    paths.append(write_poses(out / RIG_TR_GLOBAL_FILE, rig_tr_global))
    if points is not None:
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ids = np.arange(len(pts)) if feature_ids is None else np.asarray(feature_ids).reshape(-1)
        if len(ids) != len(pts):
            raise ValueError(f"need one feature id per point, got {len(ids)} for {len(pts)}")
        paths.append(_write_points(out / POINTS_FILE, pts, ids))
    return paths


def read_rig_folder(folder: str | os.PathLike[str]) -> RigFolder:
    """Read a reference-tool calibration folder: ``intrinsics0.yaml``, ``intrinsics1.yaml``, ... up to
    the first missing one, and the two pose files (one ``camera_tr_rig`` pose per camera).

    Raises:
        RigFileError: a missing or malformed file, or poses that do not match the cameras.
    """
    base = Path(folder)
    cameras: list[CentralGeneric] = []
    while (base / intrinsics_file(len(cameras))).is_file():
        try:
            cameras.append(read_generic_yaml(base / intrinsics_file(len(cameras))))
        except RefCameraError as exc:
            raise RigFileError(str(exc)) from None
    if not cameras:
        raise RigFileError(f"{base / intrinsics_file(0)}: no camera file")
    camera_tr_rig = read_poses(base / CAMERA_TR_RIG_FILE)
    if len(camera_tr_rig) != len(cameras) or any(p is None for p in camera_tr_rig):
        given = sum(p is not None for p in camera_tr_rig)
        raise RigFileError(f"{base / CAMERA_TR_RIG_FILE}: needs one pose for each of the {len(cameras)} "
                           f"cameras, has {given} of pose_count {len(camera_tr_rig)}")
    rig = Rig(tuple(cameras), tuple(p for p in camera_tr_rig if p is not None))
    return RigFolder(rig, read_poses(base / RIG_TR_GLOBAL_FILE))


def stereo_names(i: int, j: int) -> tuple[str, str]:
    """The pair's stereo YAML and map file names."""
    return f"stereo_{i}_{j}.yaml", f"rectify_{i}_{j}.npz"


def write_stereo_pair(folder: str | os.PathLike[str], rig: Rig, i: int, j: int, kind: str | None = None,
                      parametric: Sequence[ParametricCamera] | None = None, maps: bool = True
                      ) -> tuple[StereoRectification, list[Path]]:
    """Rectify cameras ``i`` (first) and ``j`` of ``rig`` (:func:`blurcalib.camera.stereo.stereo_rectify`)
    and write ``stereo_{i}_{j}.yaml`` and ``rectify_{i}_{j}.npz`` (module docstring); with
    ``parametric`` (one camera per rig camera, in its frame: :func:`blurcalib.camera.rig.parametric_frames`)
    also ``camera{i}.yaml`` and ``camera{j}.yaml``; ``maps`` False leaves the maps out. Returns the
    rectification and the paths."""
    out = ensure_writable_dir(folder)
    rect = stereo_rectify(rig.cameras[i], rig.cameras[j], rig.relative(i, j), kind)
    yaml_name, maps_name = stereo_names(i, j)
    entries: dict[str, np.ndarray | int | float | str] = {
        "camera1": i, "camera2": j, "image_width": rect.output.width, "image_height": rect.output.height,
        "rectification_model": rect.output.kind, "R": rect.relative.R, "T": rect.relative.t.reshape(3, 1),
        "E": rect.E, "R1": rect.R1, "R2": rect.R2, "rectified_camera_matrix": rect.K}
    if rect.output.kind == "pinhole":
        entries.update(zip(("P1", "P2", "Q"), rect.projection_matrices(), strict=True))
    write_storage(out / yaml_name, entries)
    paths = [out / yaml_name]
    if maps:
        arrays: dict[str, np.ndarray] = {}
        for which, camera in ((1, rig.cameras[i]), (2, rig.cameras[j])):
            arrays[f"map{which}_x"], arrays[f"map{which}_y"] = rectification_maps(rect, camera, which)
        with atomic_path(out / maps_name) as tmp, open(tmp, "wb") as handle:
            np.savez_compressed(handle, **arrays)  # type: ignore[arg-type]  # numpy stubs: **arrays vs allow_pickle
        paths.append(out / maps_name)
    if parametric is not None:
        for c in (i, j):
            write_opencv_camera(out / f"camera{c}.yaml", parametric[c])
            paths.append(out / f"camera{c}.yaml")
    return rect, paths


def read_stereo_yaml(path: str | os.PathLike[str]) -> StereoRectification:
    """Read a ``stereo_{i}_{j}.yaml`` back.

    Raises:
        CameraFileError: a missing or malformed file (the message names it).
    """
    with StorageReader(path) as file:
        file.require("R", "T", "R1", "R2", "rectified_camera_matrix", "rectification_model",
                     "image_width", "image_height")
        K = file.matrix("rectified_camera_matrix")
        if K.shape != (3, 3):
            raise CameraFileError(f"camera file {file.name!r}: rectified_camera_matrix must be 3x3")
        output = OutputProjection(file.text("rectification_model"), K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                                  int(file.number("image_width")), int(file.number("image_height")))
        relative = Pose(file.matrix("R"), file.matrix("T").reshape(-1))
        R1, R2 = file.matrix("R1"), file.matrix("R2")
    t = R2 @ relative.t
    return StereoRectification(relative, R1, R2, 0 if abs(t[0]) > abs(t[1]) else 1, output)
