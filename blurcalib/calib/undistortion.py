"""The undistortion map of a calibrated camera, generic or parametric: an image in a projection
the camera's field calls for, and the ``cv2.remap`` maps from the camera's image to it.

:func:`undistortion_output` picks the output image (``pinhole`` up to
:data:`blurcalib.camera.remap.PINHOLE_FIELD_DEG` of field, ``latlong`` beyond, or the projection
asked for), :func:`write_undistortion_map` writes ``undistortion_map.npz`` and
:func:`undistortion_report` is its section of ``report.json``. Pixels follow OpenCV (top-left
pixel centre at ``(0, 0)``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.camera.remap import (
    OutputProjection,
    RayProjector,
    auto_output_kind,
    field_of_view_deg,
    output_for,
    output_maps,
)
from blurcalib.io.atomic import atomic_path

__all__ = ["UNDISTORT", "UNDISTORTION_FILE", "undistortion_output", "undistortion_report",
           "write_undistortion_map"]

UNDISTORT = ("auto", "pinhole", "latlong", "stereographic")
"""Projections of the undistortion map (:func:`undistortion_output`)."""
UNDISTORTION_FILE = "undistortion_map.npz"


def undistortion_output(camera: RayProjector, pinhole: BrownConrady | ParametricCamera,
                        undistort: str = "auto") -> OutputProjection:
    """The output image of ``camera``'s undistortion map (:mod:`blurcalib.camera.remap`).

    ``undistort`` ``"auto"``: ``pinhole`` for a camera whose field is at most
    :data:`blurcalib.camera.remap.PINHOLE_FIELD_DEG` (:func:`blurcalib.camera.remap.auto_output_kind`),
    ``latlong`` beyond. A pinhole output is the camera ``pinhole``'s ``K`` and size (its distortion
    ignored; the parametric camera of a calibration); a ``latlong`` or ``stereographic`` output has
    ``camera``'s size, its principal point at the image centre and the px per radian of the image
    centre, lowered so that the middle row and column fit (:func:`blurcalib.camera.remap.output_for`).
    """
    if undistort not in UNDISTORT:
        raise ValueError(f"undistort must be one of {UNDISTORT}, got {undistort!r}")
    kind = auto_output_kind(camera) if undistort == "auto" else undistort
    if kind == "pinhole":
        return OutputProjection("pinhole", pinhole.fx, pinhole.fy, pinhole.cx, pinhole.cy, pinhole.width,
                                pinhole.height)
    return output_for(camera, kind)


def undistortion_report(camera: RayProjector, output: OutputProjection) -> dict[str, Any]:
    """The ``undistortion`` section of ``report.json``: the map's ``file`` (in ``calibration/``),
    its output projection (:meth:`blurcalib.camera.remap.OutputProjection.to_dict`) and the
    camera's field ``field_deg`` (:func:`blurcalib.camera.remap.field_of_view_deg`)."""
    return {"file": UNDISTORTION_FILE, **output.to_dict(), "field_deg": field_of_view_deg(camera)}


def write_undistortion_map(path: str | os.PathLike[str], camera: RayProjector, output: OutputProjection
                           ) -> Path:
    """Write ``undistortion_map.npz`` (atomically): ``map_x, map_y (H, W)`` float32 for
    ``cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR)`` from ``camera``'s image to ``output``'s
    (:func:`blurcalib.camera.remap.output_maps`: -1 where an output pixel's ray has no pixel of the
    camera), ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (px; px per rad for ``latlong`` and
    ``stereographic``), ``width``, ``height``, ``projection`` (the output's kind) and ``field_deg``
    (:func:`blurcalib.camera.remap.field_of_view_deg` of ``camera``). Returns the path."""
    map_x, map_y = output_maps(camera, output)
    K = np.array([[output.fx, 0, output.cx], [0, output.fy, output.cy], [0, 0, 1.0]])
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        np.savez_compressed(handle, map_x=map_x, map_y=map_y, K=K, width=output.width, height=output.height,
                            projection=np.array(output.kind), field_deg=field_of_view_deg(camera))
    return Path(path)
