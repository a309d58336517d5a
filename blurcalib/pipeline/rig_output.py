"""Read a ``blurcalib calibrate-rig`` output folder back (``docs/rig.md``): the rig, its image sets,
each camera's features and frames, and each pair's rectification.

The folder ``D`` holds ``report.json`` (written last: a folder without it is no finished rig
output), ``calibration/`` (the reference tool's rig folder:
:func:`blurcalib.camera.rig_files.read_rig_folder`, ``points.yaml``), ``stereo_{i}_{j}.yaml`` with,
unless the run left them out, ``rectify_{i}_{j}.npz`` per pair, and, for a run from frames,
``cameras/camN/`` (camera ``N``'s own ``calibrate`` output, whose ``features.csv`` names a frame
``frames/<its name>``). ``blurcalib demo --rig --out OUT`` writes it into ``OUT/calibration``,
and ``OUT`` is read as that folder. The image sets' names are ``report.json``'s ``set_names``
(one per pose of ``rig_tr_global.yaml``); a report without them gets the sorted frame names of the
cameras' features when there are as many as poses.

A camera's input and features are named in ``report.json`` as the run was given them: a relative
path is looked for from the working folder, then from ``D`` and each folder above it. A camera
whose input is not found has no images (its features are still read).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from blurcalib.camera.rig import Rig
from blurcalib.camera.rig_files import (
    POINTS_FILE,
    RigFileError,
    read_points,
    read_rig_folder,
    read_stereo_yaml,
    stereo_names,
)
from blurcalib.camera.stereo import StereoRectification, rectification_maps, stereo_rectify
from blurcalib.camera.storage import CameraFileError
from blurcalib.geometry.pose import Pose
from blurcalib.io.frames import FrameError
from blurcalib.io.results import FEATURES_FILE, FeatureTable, ResultsFileError, read_feature_table
from blurcalib.io.sources import FrameInput
from blurcalib.pipeline.rig import CALIBRATION_DIR, RIG_REPORT_FILE
from blurcalib.pipeline.rig_frames import CAMERAS_DIR, camera_frames
from blurcalib.pipeline.run import MIXED, PipelineError

__all__ = ["RigCameraOutput", "RigOutput", "RigOutputError", "RigPair", "find_path", "load_set_frame",
           "read_rig_output", "rig_rectification_maps"]


DEMO_RIG_DIR = "calibration"
"""``blurcalib demo --rig --out OUT`` writes its rig output into ``OUT/calibration``."""


class RigOutputError(PipelineError):
    """A folder that is not a readable rig output; the message names it and what is missing."""


@dataclass(frozen=True, eq=False)
class RigCameraOutput:
    """One camera of a rig output.

    Attributes:
        index: the camera's number ``N``.
        features: its observations, each frame named by its image set (empty when none were found).
        frames: image set -> the camera's frame of it (empty when its input is not found).
        source: its input (or its features file) as ``report.json`` names it; "" when unnamed.
        found: that input as found on disk, or None.
        report: its entry in ``report.json`` (frames and errors).
    """

    index: int
    features: FeatureTable = field(repr=False)
    frames: dict[str, FrameInput] = field(repr=False)
    source: str
    found: Path | None
    report: dict[str, Any] = field(repr=False)


@dataclass(frozen=True, eq=False)
class RigPair:
    """A pair of cameras ``i < j``, its rectification and its maps file (None when not written)."""

    i: int
    j: int
    rectification: StereoRectification
    maps_file: Path | None


@dataclass(frozen=True, eq=False)
class RigOutput:
    """A rig output folder's contents (module docstring).

    Attributes:
        folder: the folder.
        rig: the cameras and their rig -> camera poses.
        set_names: ``(S,)`` the image sets' names, or None when the folder does not say them.
        rig_tr_global: ``(S,)`` target -> rig pose of each set (None: not used).
        points: ``(M, 3)`` the target's points (m).
        cameras: ``(C,)`` each camera's features, frames and report.
        pairs: every pair ``i < j`` with a stereo file.
        report: ``report.json``.
    """

    folder: Path
    rig: Rig
    set_names: list[str] | None
    rig_tr_global: list[Pose | None] = field(repr=False)
    points: np.ndarray = field(repr=False)
    cameras: list[RigCameraOutput] = field(repr=False)
    pairs: list[RigPair] = field(repr=False)
    report: dict[str, Any] = field(repr=False)

    def set_label(self, s: int) -> str:
        """Image set ``s``'s name, or ``set s`` when the folder does not say it."""
        return self.set_names[s] if self.set_names is not None else f"set {s}"

    @property
    def set_poses(self) -> dict[str, Pose]:
        """Image set name -> its target -> rig pose, for the named sets with a pose."""
        names = self.set_names or []
        return {n: p for n, p in zip(names, self.rig_tr_global, strict=False) if p is not None}


def find_path(given: str, folder: Path) -> Path | None:
    """``given`` as it exists: absolute, from the working folder, or from ``folder`` or a folder
    above it (module docstring); None when not found."""
    if not given:
        return None
    path = Path(given)
    if path.is_absolute():
        return path if path.exists() else None
    for base in (Path.cwd(), folder, *folder.resolve().parents):
        if (base / path).exists():
            return base / path
    return None


def _report(folder: Path) -> dict[str, Any]:
    path = folder / RIG_REPORT_FILE
    if not folder.is_dir():
        raise RigOutputError(f"{folder}: not a folder")
    if not path.is_file() or not (folder / CALIBRATION_DIR).is_dir():
        missing = RIG_REPORT_FILE if (folder / CALIBRATION_DIR).is_dir() else f"{CALIBRATION_DIR}/"
        raise RigOutputError(f"{folder}: not a calibrate-rig output (no {missing}; calibrate-rig and demo "
                             "--rig write calibration/ and, last, report.json)")
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise RigOutputError(f"{path}: cannot read ({exc})") from None
    if not isinstance(report, dict) or not isinstance(report.get("cameras"), list):
        raise RigOutputError(f"{path}: not a calibrate-rig report (no 'cameras' list)")
    return report


def _camera(folder: Path, c: int, entry: dict[str, Any]) -> RigCameraOutput:
    """Camera ``c``'s features (frames renamed to their sets) and frames (module docstring)."""
    source = str(entry.get("input") or entry.get("features") or "")
    found = find_path(str(entry["input"]), folder) if entry.get("input") else None
    frames: dict[str, FrameInput] = {}
    sets: dict[str, str] = {}
    if found is not None:
        try:
            listed = camera_frames(found, offset=int(entry.get("time_offset") or 0))
        except PipelineError:
            found = None
        else:
            sets = listed.output_sets
            frames = {listed.sets[f.name]: f for f in listed.frames}
    own = folder / CAMERAS_DIR / f"cam{c}" / FEATURES_FILE
    path = own if own.is_file() else find_path(str(entry.get("features") or ""), folder)
    table = FeatureTable.empty()
    if path is not None:
        try:
            table = read_feature_table(path)
        except ResultsFileError as exc:
            raise RigOutputError(str(exc)) from None
        prefix = f"{MIXED}/"
        names = [sets.get(f, f[len(prefix):] if path == own and f.startswith(prefix) else f)
                 for f in table.frame.tolist()]
        table = replace(table, frame=np.array(names, dtype=np.str_))
    return RigCameraOutput(c, table, frames, source, found, entry)


def _set_names(report: dict[str, Any], cameras: Sequence[RigCameraOutput], count: int) -> list[str] | None:
    names = report.get("set_names")
    if isinstance(names, list) and len(names) == count:
        return [str(n) for n in names]
    seen = sorted(set().union(*(set(cam.features.frame.tolist()) for cam in cameras)))
    return seen if len(seen) == count else None


def _pairs(folder: Path, rig: Rig) -> list[RigPair]:
    pairs = []
    for i in range(rig.size):
        for j in range(i + 1, rig.size):
            yaml_name, maps_name = stereo_names(i, j)
            if (folder / yaml_name).is_file():
                try:
                    rect = read_stereo_yaml(folder / yaml_name)
                except CameraFileError as exc:
                    raise RigOutputError(str(exc)) from None
            else:
                rect = stereo_rectify(rig.cameras[i], rig.cameras[j], rig.relative(i, j))
            maps = folder / maps_name
            pairs.append(RigPair(i, j, rect, maps if maps.is_file() else None))
    return pairs


def read_rig_output(folder: str | os.PathLike[str]) -> RigOutput:
    """Read the rig output folder ``folder`` (module docstring), or the one in ``folder/calibration``
    (``blurcalib demo --rig``'s output folder holds it there).

    Raises:
        RigOutputError: not a rig output (no ``report.json`` or ``calibration/``), or a file in it
            missing or malformed; the message names the folder or file and what is wrong.
    """
    base = Path(folder)
    inner = base / DEMO_RIG_DIR
    if not (base / RIG_REPORT_FILE).is_file() and (inner / RIG_REPORT_FILE).is_file():
        base = inner  # demo --rig's output folder: its rig is in calibration/
    report = _report(base)
    try:
        calibration = read_rig_folder(base / CALIBRATION_DIR)
        points_file = base / CALIBRATION_DIR / POINTS_FILE
        points = read_points(points_file)[0] if points_file.is_file() else np.zeros((0, 3))
    except RigFileError as exc:
        raise RigOutputError(str(exc)) from None
    entries = report["cameras"]
    if len(entries) != calibration.rig.size:
        raise RigOutputError(f"{base / RIG_REPORT_FILE}: names {len(entries)} cameras, "
                             f"{base / CALIBRATION_DIR} holds {calibration.rig.size}")
    cameras = [_camera(base, c, entry if isinstance(entry, dict) else {}) for c, entry in enumerate(entries)]
    names = _set_names(report, cameras, len(calibration.rig_tr_global))
    return RigOutput(base, calibration.rig, names, calibration.rig_tr_global, points, cameras,
                     _pairs(base, calibration.rig), report)


def rig_rectification_maps(output: RigOutput, pair: RigPair) -> tuple[np.ndarray, ...]:
    """``map1_x, map1_y, map2_x, map2_y (H, W)`` float32 for ``cv2.remap``: the pair's maps file, or
    computed from the rig's cameras when it was not written
    (:func:`blurcalib.camera.stereo.rectification_maps`).

    Raises:
        RigOutputError: a maps file that cannot be read.
    """
    if pair.maps_file is not None:
        try:
            with np.load(pair.maps_file) as data:
                return tuple(np.asarray(data[k], dtype=np.float32)
                             for k in ("map1_x", "map1_y", "map2_x", "map2_y"))
        except (OSError, KeyError, ValueError) as exc:
            raise RigOutputError(f"{pair.maps_file}: cannot read the rectification maps ({exc})") from None
    rect = pair.rectification
    return (*rectification_maps(rect, output.rig.cameras[pair.i], 1),
            *rectification_maps(rect, output.rig.cameras[pair.j], 2))


def load_set_frame(camera: RigCameraOutput, set_name: str) -> np.ndarray | None:
    """Camera's frame of image set ``set_name``, grey levels ``(H, W)`` float32 0..255; None when
    the camera has no frame of it on disk or it cannot be read."""
    frame = camera.frames.get(set_name)
    if frame is None:
        return None
    try:
        return frame.load()
    except FrameError:
        return None
