"""Sharp captures of one camera showing several patterns at the same poses, through realistic
optics (:mod:`blurcalib.sim.optics`), with both ground truths of each feature.

As with a target shown on a monitor, the camera stays where it is while the pattern on the
screen changes: :func:`facing_poses` draws poses where the target fills much of the image (as a
monitor close to the camera does), and :func:`render_frame` renders one pattern at one of them.
Each feature has two truths: its projection (:attr:`CaptureTruth.projection`) and the
*centroid truth* (:attr:`CaptureTruth.centroid`), the projection moved by the centroid of the
optical PSF there, i.e. the point whose image is the PSF's centroid.

Pixel convention: OpenCV (the centre of the top-left pixel is ``(0, 0)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from blurcalib.geometry.pose import Pose
from blurcalib.sim.optics import Optics
from blurcalib.sim.render import MIP_TEXELS_PER_SQUARE, mip_levels_for, sensor_image
from blurcalib.sim.synth import Simulator, frame_truth
from blurcalib.sim.truth import Motion, TrueCamera
from blurcalib.target.pattern import StarPattern

__all__ = ["CaptureTruth", "facing_poses", "render_frame"]


@dataclass(frozen=True)
class CaptureTruth:
    """Ground truth of one rendered frame (``M`` pattern features, ``pattern.features`` order).

    Attributes:
        pose: target -> camera.
        projection: ``(M, 2)`` px, each target point's projection (moved by the display's
            emission centroid on the target plane when a display is simulated).
        centroid: ``(M, 2)`` px, ``projection`` plus the optical PSF's centroid there.
        visible: ``(M,)`` bool, the feature's whole square is inside the image.
    """

    pose: Pose
    projection: np.ndarray
    centroid: np.ndarray
    visible: np.ndarray


def facing_poses(camera: TrueCamera, pattern: StarPattern, count: int, rng: np.random.Generator, *,
                 square_px: float = 36.0, tilt_deg: float = 25.0, offset_px: float = 120.0) -> list[Pose]:
    """``count`` poses that show the target's middle near the image centre (within
    ``offset_px``), at a depth where a square is about ``square_px`` px, tilted by up to
    ``tilt_deg`` about a random axis in the target plane and rolled at random."""
    L = pattern.square_length_m
    middle = np.array([(pattern.squares_x - 2) / 2 * L, (pattern.squares_y - 2) / 2 * L, 0.0])
    model = camera.model
    poses = []
    for _ in range(count):
        axis = rng.uniform(0, 2 * np.pi)
        tilt = math.radians(tilt_deg) * math.sqrt(rng.uniform())
        rv = np.array([math.cos(axis), math.sin(axis), 0.0]) * tilt
        R = cv2.Rodrigues(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]))[0] @ cv2.Rodrigues(rv)[0]
        pixel = np.array([model.cx, model.cy]) + rng.uniform(-offset_px, offset_px, 2)
        xn = camera.unproject(pixel[None])[0]
        depth = model.fx * L / square_px
        poses.append(Pose(R, depth * np.array([xn[0], xn[1], 1.0]) - R @ middle))
    return poses


def render_frame(sim: Simulator, pose: Pose, rng: np.random.Generator, optics: Optics | None,
                 defocus_sigma: float = 0.5) -> tuple[np.ndarray, CaptureTruth]:
    """A sharp frame of ``sim``'s pattern at ``pose`` through ``optics`` (``sim``'s own optics
    must be the same or None; its texture holds the display), and its :class:`CaptureTruth`."""
    camera, pattern = sim.camera, sim.pattern
    truth = frame_truth("frame", "sharp", pattern, camera, pose, Motion.still(), defocus_sigma, rng,
                        sim.config.noise_sigma)
    levels = [sim.texture(MIP_TEXELS_PER_SQUARE[k])
              for k in mip_levels_for(camera, pose, pattern, sim.config.supersample)]
    image = sensor_image(sim.renderer.irradiance(levels, pose, Motion.still()), truth, rng, optics)
    size = (camera.model.width, camera.model.height)
    projection = truth.mean
    if optics is not None and optics.display is not None:
        shift = np.append(optics.display.shift_squares() * pattern.square_length_m, 0.0)
        projection = camera.project(pose.transform(pattern.points_3d() + shift))
    centroid = projection.copy()
    if optics is not None and optics.psf is not None:
        centroid = projection + optics.psf.centroid_at(projection, size)
    return image, CaptureTruth(pose, projection, centroid, truth.block_inside)
