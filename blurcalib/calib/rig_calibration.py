"""Calibration of a rig: each camera calibrated alone, then its extrinsics by a joint bundle.

Each camera's generic calibration (:func:`blurcalib.calib.joint.calibrate_generic`, its sharp and
blurry frames) gives its camera and a target pose per frame, in its own frame. Frames of different
cameras with the same name form one image set (the target seen at one instant). The initial
extrinsics chain the cameras from camera 0 through the sets they share (:func:`initial_rig`: for
two cameras ``a, b`` seeing a set, ``camera b <- camera a = M_b M_a^-1``, averaged over their
shared sets: the chordal mean of the rotations, the mean of the translations), so a camera
linked to camera 0 only through another is handled; a camera that shares no set with the others
(directly or through others) is an error. Then :func:`blurcalib.calib.rig_bundle.rig_bundle_adjust`
refines the extrinsics with one target pose per set over every camera's observations, each
blurry frame keeping its own image shift.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np

from blurcalib.calib.bundle import BundleSettings
from blurcalib.calib.joint import GenericCalibration
from blurcalib.calib.rig_bundle import RigBundleResult, RigObservations, rig_bundle_adjust
from blurcalib.geometry.pose import Pose

__all__ = ["RigCalibration", "RigError", "calibrate_rig", "initial_rig", "mean_pose", "rig_problem"]


class RigError(ValueError):
    """The cameras cannot be calibrated as one rig (the message says which camera and why)."""


def mean_pose(poses: Sequence[Pose]) -> Pose:
    """The chordal mean of the rotations (the nearest rotation to their sum) and the mean translation."""
    U, _, Vt = np.linalg.svd(np.sum([p.R for p in poses], axis=0))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return Pose(R, np.mean([p.t for p in poses], axis=0))


def initial_rig(camera_poses: Sequence[Sequence[Pose | None]]) -> tuple[list[Pose], list[Pose | None]]:
    """Initial ``camera_tr_rig (C,)`` (camera 0's the identity) and ``rig_tr_global (S,)`` from each
    camera's own target poses ``camera_poses[c][s]`` (None where camera ``c`` has no frame of set
    ``s``) (module docstring). A set no camera sees gets None.

    Raises:
        RigError: a camera linked to camera 0 by no chain of shared sets.
    """
    C = len(camera_poses)
    S = len(camera_poses[0]) if C else 0
    rig: list[Pose | None] = [Pose.identity()] + [None] * (C - 1)
    frontier = [0]
    while frontier:
        a = frontier.pop(0)
        for b in range(C):
            if rig[b] is not None:
                continue
            shared = [s for s in range(S)
                      if camera_poses[a][s] is not None and camera_poses[b][s] is not None]
            if not shared:
                continue
            between = mean_pose([camera_poses[b][s].compose(camera_poses[a][s].inverse())  # type: ignore[union-attr]
                                 for s in shared])
            rig[b] = between.compose(rig[a])  # type: ignore[arg-type]
            frontier.append(b)
    lonely = [c for c in range(C) if rig[c] is None]
    if lonely:
        raise RigError(f"camera {lonely[0]} shares no image set with camera 0, directly or through other "
                       f"cameras: its pose in the rig is unknown")
    camera_tr_rig = [p for p in rig if p is not None]
    sets: list[Pose | None] = []
    for s in range(S):
        seen = [c for c in range(C) if camera_poses[c][s] is not None]
        sets.append(camera_tr_rig[seen[0]].inverse().compose(camera_poses[seen[0]][s])  # type: ignore[arg-type]
                    if seen else None)
    return camera_tr_rig, sets


@dataclass(eq=False)
class RigCalibration:
    """A calibrated rig.

    Attributes:
        cameras: ``(C,)`` each camera's own calibration.
        sets: ``(S,)`` the image sets' names (frame names), in the bundle's order.
        bundle: the joint bundle's result (the rig, the sets' target poses, residuals).
    """

    cameras: list[GenericCalibration]
    sets: list[str]
    bundle: RigBundleResult


def rig_problem(cameras: Sequence[GenericCalibration], leave_out: Collection[str] = ()
                ) -> tuple[list[str], list[Pose], list[Pose], list[RigObservations]]:
    """The joint bundle's inputs from the cameras' own calibrations, the sets named in
    ``leave_out`` left out: the sets' names, the initial ``camera_tr_rig (C,)`` and
    ``rig_tr_global (S,)`` (:func:`initial_rig`) and each camera's observations.

    Raises:
        RigError: a camera that shares no image set with the others.
    """
    names = sorted(set().union(*(cal.frames for cal in cameras)) - set(leave_out))
    index = {name: k for k, name in enumerate(names)}
    camera_poses = [[cal.poses.get(name) for name in names] for cal in cameras]
    camera_tr_rig, rig_tr_global = initial_rig(camera_poses)
    used = [k for k, p in enumerate(rig_tr_global) if p is not None]
    renumber = np.full(len(names), -1)
    renumber[used] = np.arange(len(used))
    observations = []
    for cal in cameras:
        keep = np.array([f in index for f in cal.frame.tolist()], dtype=bool)
        sets = renumber[np.array([index[f] for f in cal.frame[keep].tolist()], dtype=np.int64)]
        blurry = set(cal.blurry_frames) & set(cal.shifts)
        free = np.array([names[k] in blurry for k in used], dtype=bool)
        observations.append(RigObservations(sets, cal.points[keep], cal.observed[keep],
                                            (cal.weight * cal.inlier)[keep], free))
    return [names[k] for k in used], camera_tr_rig, [rig_tr_global[k] for k in used], observations  # type: ignore[misc]


def calibrate_rig(cameras: Sequence[GenericCalibration], settings: BundleSettings | None = None
                  ) -> RigCalibration:
    """The rig of calibrated cameras (module docstring); frames match by name across cameras.

    Raises:
        RigError: fewer than two cameras, or a camera that shares no image set with the others.
    """
    if len(cameras) < 2:
        raise RigError(f"a rig needs two or more cameras, got {len(cameras)}")
    names, camera_tr_rig, rig_tr_global, observations = rig_problem(cameras)
    bundle = rig_bundle_adjust([cal.model for cal in cameras], camera_tr_rig, rig_tr_global, observations,
                               settings)
    return RigCalibration(list(cameras), names, bundle)
