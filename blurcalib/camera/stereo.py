"""Stereo rectification of two central cameras of a rig, in OpenCV's convention.

Given ``R, T`` with ``X_2 = R X_1 + T`` (camera 2 <- camera 1, :meth:`blurcalib.camera.rig.Rig.relative`),
the rectifying rotations are ``cv2.stereoRectify``'s: each camera turns by half the relative
rotation, ``r = exp(-om / 2)`` with ``om`` the rotation vector of ``R``; then both turn by ``w``,
which takes ``t = r T`` onto the rectified x axis (or y, when ``|t_y| > |t_x|``: one camera above the
other)::

    R1 = w r^T,      R2 = w r,      X_rect_k = R_k X_k

so the baseline ``R2 T`` lies on that axis and every plane through it (an epipolar plane) is one
image row (column) of both rectified images. The rectified images share one output projection
(:class:`blurcalib.camera.remap.OutputProjection`, OpenCV pixels): ``pinhole`` as OpenCV's, with
``P1 = [K | 0]``, ``P2 = [K | K e t']`` (``t'`` the baseline's coordinate ``(R2 T)_axis`` m, ``e``
the axis) and the disparity-to-depth matrix::

        [1  0   0      -cx ]
    Q = [0  1   0      -cy ]          (x, y, d, 1) Q^T ~ (X, Y, Z, 1) in rectified camera 1's frame
        [0  0   0       f  ]
        [0  0  -1/t'    0  ]

with one principal point for both (OpenCV's ``CALIB_ZERO_DISPARITY``); or ``epipolar`` for wide
lenses (rows are the epipolar planes' angles about the baseline, columns angles within them, the
output kind ``epipolar``; ``latlong`` for a vertical pair, whose columns are those planes; a
pinhole image of a 180 degree field is infinite), which has no ``P`` and ``Q``. The maps go from
each camera's own image, through its model (generic or parametric), to the rectified one
(:func:`rectification_maps`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike

from blurcalib.camera.remap import OutputProjection, RayProjector, RotatedCamera, output_for, output_maps
from blurcalib.geometry.pose import Pose

__all__ = ["StereoRectification", "epipolar_errors", "rectification_maps", "rectified_points",
           "rectifying_rotations", "stereo_rectify"]


def rectifying_rotations(relative: Pose) -> tuple[np.ndarray, np.ndarray, int]:
    """``R1, R2 (3, 3)`` and the baseline's axis (0: x, 1: y) of the pair ``relative`` (camera 2 <-
    camera 1), as ``cv2.stereoRectify`` computes them (module docstring)."""
    om, _ = cv2.Rodrigues(np.ascontiguousarray(relative.R))
    r_r, _ = cv2.Rodrigues(-0.5 * om)
    t = r_r @ relative.t
    axis = 0 if abs(t[0]) > abs(t[1]) else 1
    c = float(t[axis])
    if not np.linalg.norm(t) > 0:
        raise ValueError("the two cameras sit at one point: no baseline to rectify along")
    uu = np.zeros(3)
    uu[axis] = 1.0 if c > 0 else -1.0
    ww = np.cross(t, uu)
    nw = float(np.linalg.norm(ww))
    if nw > 0:
        ww *= math.acos(min(1.0, abs(c) / float(np.linalg.norm(t)))) / nw
    wR, _ = cv2.Rodrigues(ww)
    return wR @ r_r.T, wR @ r_r, axis


@dataclass(frozen=True, eq=False)
class StereoRectification:
    """A rectified pair (module docstring).

    Attributes:
        relative: camera 2 <- camera 1 (``R``, ``T`` m).
        R1, R2: ``(3, 3)`` rectifying rotations.
        axis: 0 when the baseline is the rectified x axis (rows are epipolar lines), 1 for y.
        output: the rectified images' projection (both the same).
    """

    relative: Pose
    R1: np.ndarray
    R2: np.ndarray
    axis: int
    output: OutputProjection

    @property
    def baseline_m(self) -> float:
        """``t' = (R2 T)_axis`` (m): camera 2's side of camera 1 along the rectified axis, signed as
        OpenCV's ``P2``."""
        return float((self.R2 @ self.relative.t)[self.axis])

    @property
    def K(self) -> np.ndarray:
        """``(3, 3)`` the rectified images' intrinsics (px, px per rad off a pinhole)."""
        o = self.output
        return np.array([[o.fx, 0.0, o.cx], [0.0, o.fy, o.cy], [0.0, 0.0, 1.0]])

    @property
    def E(self) -> np.ndarray:
        """``(3, 3)`` essential matrix ``[T]_x R`` (OpenCV's ``stereoCalibrate``)."""
        t = self.relative.t
        return cast(np.ndarray, np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
                                @ self.relative.R)

    def projection_matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``P1, P2 (3, 4)`` and ``Q (4, 4)`` of a pinhole rectification (module docstring).

        Raises:
            ValueError: the output is not a pinhole (no such matrices).
        """
        if self.output.kind != "pinhole":
            raise ValueError(f"a {self.output.kind} rectification has no projection matrices")
        P1 = np.hstack([self.K, np.zeros((3, 1))])
        P2 = P1.copy()
        b = self.baseline_m
        f = self.output.fx if self.axis == 0 else self.output.fy
        P2[self.axis, 3] = b * f
        Q = np.zeros((4, 4))
        Q[0, 0] = Q[1, 1] = 1.0
        Q[0, 3], Q[1, 3] = -self.output.cx, -self.output.cy
        Q[2, 3] = f
        Q[3, 2] = -1.0 / b
        return P1, P2, Q

    def rotation(self, which: int) -> np.ndarray:
        """``R1`` (``which = 1``) or ``R2`` (2)."""
        if which not in (1, 2):
            raise ValueError(f"a pair's camera is 1 or 2, got {which}")
        return self.R1 if which == 1 else self.R2


def stereo_rectify(camera1: RayProjector, camera2: RayProjector, relative: Pose, kind: str | None = None,
                   size: tuple[int, int] | None = None, focal_px: float | None = None) -> StereoRectification:
    """The rectification of a pair (module docstring).

    Args:
        camera1, camera2: the cameras (a generic camera, or any :class:`RayProjector`).
        relative: camera 2 <- camera 1.
        kind: ``"pinhole"`` or ``"epipolar"``; None: pinhole unless either camera's field is too
            wide for one (:func:`blurcalib.camera.remap.output_for`).
        size: ``(width, height)`` of the rectified images (default camera 1's).
        focal_px: their focal length, px (per rad at the centre; default the smaller of the two
            cameras' at their image centres, so that neither is magnified).
    """
    R1, R2, axis = rectifying_rotations(relative)
    outputs = [output_for(camera1), output_for(camera2)]
    if kind is None:
        kind = "pinhole" if all(o.kind == "pinhole" for o in outputs) else "epipolar"
    if focal_px is None:
        focal_px = min(min(o.fx, o.fy) for o in outputs)
    if kind not in ("pinhole", "epipolar"):
        raise ValueError(f"rectification kind must be pinhole or epipolar, got {kind!r}")
    if kind == "epipolar" and axis == 1:
        kind = "latlong"  # planes through the y axis are its columns
    width, height = size if size is not None else (camera1.width, camera1.height)
    output = OutputProjection(kind, focal_px, focal_px, (width - 1) / 2.0, (height - 1) / 2.0, width, height)
    return StereoRectification(relative, R1, R2, axis, output)


def rectification_maps(rect: StereoRectification, camera: RayProjector, which: int
                       ) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps ``(H, W)`` float32 from camera ``which``'s (1 or 2) image to its rectified
    image (-1 where the rectified pixel's ray has no pixel of the camera)."""
    return output_maps(RotatedCamera(camera, rect.rotation(which)), rect.output)


def rectified_points(rect: StereoRectification, pixel_to_ray: Callable[[np.ndarray], np.ndarray],
                     which: int, px: ArrayLike) -> np.ndarray:
    """Rectified pixels ``(N, 2)`` of camera ``which``'s pixels ``px (N, 2)``, through its
    ``pixel_to_ray`` (OpenCV pixels; NaN where it has no ray)."""
    rays = pixel_to_ray(np.asarray(px, dtype=np.float64).reshape(-1, 2))
    return rect.output.project(rays @ rect.rotation(which).T)


def epipolar_errors(rect: StereoRectification, rays1: Callable[[np.ndarray], np.ndarray],
                    rays2: Callable[[np.ndarray], np.ndarray], px1: ArrayLike, px2: ArrayLike) -> np.ndarray:
    """``(N,)`` px: how far the rectified images of matched pixels ``px1, px2 (N, 2)`` (the same
    points seen by cameras 1 and 2) lie off one epipolar line: the difference of their rectified
    coordinates across the baseline (rows, or columns for a vertical pair). 0 for a perfect
    calibration; NaN where a camera has no ray."""
    q1 = rectified_points(rect, rays1, 1, px1)
    q2 = rectified_points(rect, rays2, 2, px2)
    across = 1 - rect.axis
    return cast(np.ndarray, np.abs(q1[:, across] - q2[:, across]))
