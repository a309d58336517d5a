"""The scene of the generic bundle adjustment's tests: a 320 x 240 camera with a non-parametric
deviation, a 12 x 9 planar target (2 cm) and random poses from which it is seen."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from blurcalib.camera.generic import CentralGeneric, fit_to_rays
from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.pose import Pose

TRUE_CAM = BrownConrady(fx=300.0, fy=298.0, cx=160.4, cy=119.7, k1=-0.12, k2=0.03, p1=0.0005,
                        p2=-0.0003, k3=0.0, width=320, height=240)

_gx, _gy = np.meshgrid(np.arange(12) * 0.02, np.arange(9) * 0.02)
TARGET = np.column_stack([_gx.ravel() - 0.11, _gy.ravel() - 0.08, np.zeros(_gx.size)])
"""``(108, 3)`` m: the target's points, centred near its middle."""


def random_pose(rng: np.random.Generator, low_px: tuple[float, float], high_px: tuple[float, float]) -> Pose:
    """A pose (target -> camera) tilted at random, 0.35-0.5 m away, with the target's origin seen
    at a pixel drawn uniformly in ``[low_px, high_px]`` (OpenCV convention)."""
    rvec = rng.normal(size=3) * [0.35, 0.35, 0.2]
    centre_px = rng.uniform(low_px, high_px)
    ray = TRUE_CAM.pixel_to_ray(centre_px[None])[0]
    return Pose.from_rvec_tvec(rvec, ray / ray[2] * rng.uniform(0.35, 0.5))


def bumped_truth() -> CentralGeneric:
    """The true generic camera: :data:`TRUE_CAM`'s rays on a 40 px grid, each node moved at random
    (4e-4 in direction, a deviation no Brown-Conrady camera has)."""
    base = fit_to_rays(TRUE_CAM.pixel_to_ray, 320, 240, cell_px=40.0)
    rng = np.random.default_rng(7)
    return base.with_grid(base.grid + 4e-4 * rng.normal(size=base.grid.shape))


def observed_scene(rng: np.random.Generator, frames: int, low_px: tuple[float, float],
                   high_px: tuple[float, float],
                   view: Callable[[Pose, int], tuple[np.ndarray, np.ndarray, Any]]
                   ) -> tuple[list[Pose], list[Any], np.ndarray, np.ndarray, np.ndarray]:
    """``frames`` random poses (:func:`random_pose`) that see at least 40 of the target's points:
    ``view(pose, k)`` gives frame ``k``'s projections of :data:`TARGET` ``(108, 2)`` px, which are
    inside and anything else to keep per frame. Returns the poses, those extras and the
    observations' frame index ``(N,)``, target points ``(N, 3)`` m and pixels ``(N, 2)``."""
    poses, extras, index, points, observed = [], [], [], [], []
    while len(poses) < frames:
        pose = random_pose(rng, low_px, high_px)
        px, inside, extra = view(pose, len(poses))
        if inside.sum() < 40:
            continue
        index.append(np.full(int(inside.sum()), len(poses)))
        points.append(TARGET[inside])
        observed.append(px[inside])
        poses.append(pose)
        extras.append(extra)
    return poses, extras, np.concatenate(index), np.concatenate(points), np.concatenate(observed)
