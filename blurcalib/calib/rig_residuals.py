"""A calibrated rig's errors on its own features: each camera's reprojection errors and an image
set's rectified epipolar error.

Reprojection error (:func:`camera_residuals`). Camera ``c`` of the rig sees target point ``P`` of
image set ``s`` at ``pi_c(T_c M_s P)`` (``T_c`` its ``camera_tr_rig``, ``M_s`` the set's
``rig_tr_global``, :mod:`blurcalib.camera.rig`); its residual is ``r = p - pi_c(T_c M_s P)`` px
(OpenCV pixels). A blurry frame has a free image shift in the rig bundle
(:mod:`blurcalib.calib.rig_bundle`), which the files do not hold: its residuals' median is taken
out, as the rig's held-out error does (:mod:`blurcalib.calib.rig_trust`).

Epipolar error (:func:`set_epipolar`). The features of one set that both cameras of a pair see
(matched by feature id) are mapped into the pair's rectified images
(:func:`blurcalib.camera.stereo.rectified_points`); their rectified coordinates across the baseline
differ by the epipolar error (:func:`blurcalib.camera.stereo.epipolar_errors`), 0 px for a perfect
calibration and features. A blurry frame's image shift is in it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from blurcalib.camera.generic import CentralGeneric
from blurcalib.camera.rig import Rig
from blurcalib.camera.stereo import StereoRectification, epipolar_errors, rectified_points
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureFlags, FeatureTable

__all__ = ["CameraResiduals", "SetEpipolar", "camera_residuals", "set_epipolar"]


def _stats(length: np.ndarray) -> tuple[float, float, float]:
    if not len(length):
        return float("nan"), float("nan"), float("nan")
    return (float(np.median(length)), float(np.sqrt(np.mean(length**2))), float(length.max()))


@dataclass(frozen=True, eq=False)
class CameraResiduals:
    """One camera's reprojection errors in the rig (module docstring).

    Attributes:
        set_name: ``(N,)`` the image set of each observation.
        xy: ``(N, 2)`` observed positions (px, OpenCV convention).
        residual: ``(N, 2)`` observed minus projected (px; a blurry frame's median taken out).
        blurry: ``(N,)`` bool, observations of blurry frames.
    """

    set_name: np.ndarray = field(repr=False)
    xy: np.ndarray = field(repr=False)
    residual: np.ndarray = field(repr=False)
    blurry: np.ndarray = field(repr=False)

    def select(self, rows: np.ndarray) -> CameraResiduals:
        """The observations chosen by a boolean mask or index array."""
        return CameraResiduals(self.set_name[rows], self.xy[rows], self.residual[rows], self.blurry[rows])

    @property
    def stats(self) -> tuple[float, float, float]:
        """``(median, RMS, max)`` of the residuals' lengths (px; NaN without observations)."""
        return _stats(np.hypot(self.residual[:, 0], self.residual[:, 1]))


def camera_residuals(rig: Rig, c: int, rig_tr_global: Mapping[str, Pose], features: FeatureTable
                     ) -> CameraResiduals:
    """Camera ``c``'s reprojection errors over its ``features`` (frames named by their image sets;
    rows of sets without a pose in ``rig_tr_global`` are left out, so are points the camera cannot
    project) (module docstring)."""
    keep = np.array([f in rig_tr_global for f in features.frame.tolist()], dtype=bool)
    table = features.select(keep)
    points = np.column_stack([table.X, table.Y, np.zeros(len(table))])
    cam_points = np.zeros_like(points)
    for name in dict.fromkeys(table.frame.tolist()):
        rows = table.frame == name
        cam_points[rows] = rig.camera_tr_rig[c].compose(rig_tr_global[name]).transform(points[rows])
    observed = np.column_stack([table.x, table.y])
    camera: CentralGeneric = rig.cameras[c]
    if len(table):
        projected, ok = camera.project_valid(cam_points)
    else:
        projected, ok = np.zeros((0, 2)), np.zeros(0, dtype=bool)
    residual = observed - projected
    blurry = (table.flags & int(FeatureFlags.BLURRY_FRAME)) != 0
    for name in dict.fromkeys(table.frame[blurry & ok].tolist()):
        rows = (table.frame == name) & ok
        residual[rows] -= np.median(residual[rows], axis=0)
    return CameraResiduals(table.frame[ok], observed[ok], residual[ok], blurry[ok])


@dataclass(frozen=True, eq=False)
class SetEpipolar:
    """An image set's features seen by both cameras of a pair, rectified (module docstring).

    Attributes:
        feature_id: ``(N,)`` the features both cameras see.
        rectified1, rectified2: ``(N, 2)`` their pixels in the rectified images of the pair's
            first and second camera.
        error: ``(N,)`` px, the epipolar error of each (NaN where a camera has no ray).
    """

    feature_id: np.ndarray = field(repr=False)
    rectified1: np.ndarray = field(repr=False)
    rectified2: np.ndarray = field(repr=False)
    error: np.ndarray = field(repr=False)

    @property
    def stats(self) -> tuple[float, float, float]:
        """``(median, RMS, max)`` of the finite errors (px; NaN without any)."""
        return _stats(self.error[np.isfinite(self.error)])


def set_epipolar(rect: StereoRectification, camera1: CentralGeneric, camera2: CentralGeneric,
                 features1: FeatureTable, features2: FeatureTable, set_name: str) -> SetEpipolar:
    """The epipolar error of image set ``set_name`` for the pair ``rect`` of ``camera1`` (first) and
    ``camera2``, from each camera's features (frames named by their image sets; module docstring)."""
    t1 = features1.select(features1.frame == set_name)
    t2 = features2.select(features2.frame == set_name)
    ids, i1, i2 = np.intersect1d(t1.feature_id, t2.feature_id, return_indices=True)
    px1 = np.column_stack([t1.x, t1.y])[i1]
    px2 = np.column_stack([t2.x, t2.y])[i2]
    if not len(ids):
        empty = np.zeros((0, 2))
        return SetEpipolar(ids, empty, empty, np.zeros(0))
    return SetEpipolar(ids, rectified_points(rect, camera1.pixel_to_ray, 1, px1),
                       rectified_points(rect, camera2.pixel_to_ray, 2, px2),
                       epipolar_errors(rect, camera1.pixel_to_ray, camera2.pixel_to_ray, px1, px2))
