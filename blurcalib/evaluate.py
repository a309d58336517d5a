"""Accuracy of extracted or aligned features against a simulated dataset's ground truth.

The figure of merit for aligned blurry-frame features is the reprojection error against the
*true* camera (Brown-Conrady plus its non-parametric deviation) with each frame's pose refitted
to the features: it measures the features' error, not the pose's or the parametric model's.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from blurcalib.camera import Pose
from blurcalib.pattern import StarPattern
from blurcalib.results import FeatureFlags, FeatureTable
from blurcalib.synth import DatasetTruth, TrueCamera


@dataclass(frozen=True)
class FrameAccuracy:
    """Per-frame accuracy (px).

    Attributes:
        frame: frame name.
        count: features evaluated.
        median, p90, max: of the reprojection error with the pose refitted under the true camera.
        median_vs_mean: median distance to the ground-truth time-averaged positions after
            removing the frame's mean offset.
    """

    frame: str
    count: int
    median: float
    p90: float
    max: float
    median_vs_mean: float


def refit_pose(camera: TrueCamera, points: np.ndarray, xy: np.ndarray, start: Pose) -> Pose:
    """Least-squares pose under the true camera: ``argmin_M sum |pi(M P) - x|^2``."""
    def residual(v: np.ndarray) -> np.ndarray:
        R, _ = cv2.Rodrigues(v[:3])
        return (camera.project(points @ R.T + v[3:]) - xy).ravel()

    sol = least_squares(residual, np.concatenate([start.rvec, start.t]), method="lm")
    return Pose.from_rvec_tvec(sol.x[:3], sol.x[3:])


def evaluate_features(features: FeatureTable, truth: DatasetTruth, pattern: StarPattern,
                      required_flags: int = int(FeatureFlags.GLOBALLY_ALIGNED),
                      skip_flags: int = int(FeatureFlags.FILTERED_OUT)) -> list[FrameAccuracy]:
    """Evaluate every frame's features that carry ``required_flags`` and none of ``skip_flags``."""
    keep = ((features.flags & required_flags) == required_flags) & ((features.flags & skip_flags) == 0)
    out = []
    for name in sorted(set(features.frame[keep].tolist())):
        rows = np.flatnonzero(keep & (features.frame == name))
        if len(rows) < 6:
            continue
        frame = truth.frame(name)
        ids = features.feature_id[rows]
        xy = np.stack([features.x[rows], features.y[rows]], axis=1)
        pose = refit_pose(truth.camera, pattern.points_3d(ids), xy, frame.pose)
        err = np.linalg.norm(truth.camera.project(pose.transform(pattern.points_3d(ids))) - xy, axis=1)
        d = xy - frame.mean[ids]
        d -= d.mean(axis=0)
        out.append(FrameAccuracy(name, len(rows), float(np.median(err)),
                                 float(np.percentile(err, 90)), float(err.max()),
                                 float(np.median(np.linalg.norm(d, axis=1)))))
    return out
