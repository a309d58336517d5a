"""What a rendered dot should show: its intensity centroid and the image area it covers."""

from __future__ import annotations

import numpy as np

from blurcalib.geometry.pose import Pose
from blurcalib.sim.render import Renderer, Texture
from blurcalib.sim.truth import Motion, TrueCamera


def centroid(img: np.ndarray) -> np.ndarray:
    """Intensity centroid ``(2,)`` px of an image (OpenCV convention)."""
    ys, xs = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    return np.array([(img * xs).sum(), (img * ys).sum()]) / img.sum()


def area_scale(camera: TrueCamera, pose: Pose, P: np.ndarray) -> float:
    """Image area (px^2) per target-plane area (m^2) at target point ``P (3,)`` seen at ``pose``."""
    eps = 1e-5
    a = camera.project(pose.transform(P[None]))[0]
    bx = camera.project(pose.transform((P + np.array([eps, 0.0, 0.0]))[None]))[0]
    by = camera.project(pose.transform((P + np.array([0.0, eps, 0.0]))[None]))[0]
    return abs(np.linalg.det(np.column_stack([bx - a, by - a])))


def blurred_dot_error(renderer: Renderer, texture: Texture, pose: Pose, xi: np.ndarray, xi2: np.ndarray,
                      P: np.ndarray) -> tuple[float, np.ndarray]:
    """Render the dot ``texture`` centred at target point ``P (3,)`` blurred by the motion
    ``(xi, xi2)``; the distance (px) of its intensity centroid from the time average of its image
    positions weighted by the image area the dot covers at each, and that track ``(T, 2)`` px."""
    motion = Motion(xi, xi2, renderer.time_samples_for(pose, xi, xi2, P[None]))
    img = renderer.irradiance([texture], pose, motion).astype(np.float64)
    poses = motion.poses(pose)
    track = np.stack([renderer.camera.project(p.transform(P[None]))[0] for p in poses])
    weight = np.array([area_scale(renderer.camera, p, P) for p in poses])
    expected = (track * weight[:, None]).sum(axis=0) / weight.sum()
    return float(np.linalg.norm(centroid(img) - expected)), track
