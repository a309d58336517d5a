"""The translational ambiguity of deconvolution, as a teaching demo.

A blurred star ``k * L`` is explained equally well by the latent star shifted by ``delta`` and the
kernel shifted by ``-delta`` (:func:`blurcalib.psf.kernel.shift_pair`): ``k' * L' = k * L``. The
image cannot tell where the star "really" is; only a convention can (the PSF's centroid at the
kernel centre) and the target's geometry (neighbouring blocks share corners; one camera model
explains every frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from blurcalib.calib.alignment import align_global
from blurcalib.camera.parametric import BrownConrady
from blurcalib.extract.local_alignment import align_locally, corner_gaps, neighbour_pairs
from blurcalib.geometry.homography import (
    apply_homography,
    homography_centre,
    plane_homography,
    translation,
)
from blurcalib.geometry.pose import Pose
from blurcalib.growth.seed import block_homography
from blurcalib.psf.kernel import shift_pair
from blurcalib.sim.truth import splat
from blurcalib.target.pattern import star_sector_white

TILE_PX = 64
"""Side of the demo's latent tile (px): two squares of 32 px, so the tile is periodic."""
KERNEL_SIZE = 17
MAX_SHIFT = 4
"""Largest ``|delta|`` per axis (px) that keeps the demo kernel inside its window."""


def star_tile(num_segments: int, size: int = TILE_PX, supersample: int = 4) -> np.ndarray:
    """A periodic latent image ``(size, size)`` in 0..1: stars on a grid of ``size / 2`` px
    squares, a star centre at pixel ``(size / 2, size / 2)``."""
    square = size / 2.0
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    j = np.arange(size, dtype=np.float64)
    acc = np.zeros((size, size))
    for oy in offs:
        for ox in offs:
            x = (j[None, :] + ox - size / 2.0) / square
            y = (j[:, None] + oy - size / 2.0) / square
            acc += star_sector_white(x - np.round(x), y - np.round(y), num_segments)
    return acc / supersample**2


def motion_kernel(size: int = KERNEL_SIZE, length: float = 7.0, bend: float = 2.0) -> np.ndarray:
    """A curved motion-blur kernel ``(size, size)`` summing to 1 (a hand-shake arc)."""
    t = np.linspace(-0.5, 0.5, 64)
    offsets = np.column_stack([length * t, bend * (4.0 * t**2 - 1.0 / 3.0)])
    return splat(offsets, size)


def periodic_blur(latent: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``(k * L)(x) = sum_d k(d) L(x - d)`` with ``L`` periodic (via the FFT)."""
    h, w = latent.shape
    c = (kernel.shape[0] - 1) // 2
    wrapped = np.zeros((h, w))
    for i in range(kernel.shape[0]):
        for j in range(kernel.shape[1]):
            wrapped[(i - c) % h, (j - c) % w] += kernel[i, j]
    return np.real(np.fft.ifft2(np.fft.fft2(latent) * np.fft.fft2(wrapped)))


def kernel_centroid(kernel: np.ndarray) -> np.ndarray:
    """``(2,)`` px ``(x, y)``: the kernel's centroid relative to its centre."""
    c = (kernel.shape[0] - 1) / 2.0
    yy, xx = np.mgrid[0:kernel.shape[0], 0:kernel.shape[1]]
    total = kernel.sum()
    return np.array([(kernel * (xx - c)).sum() / total, (kernel * (yy - c)).sum() / total])


@dataclass(frozen=True)
class AmbiguityDemo:
    """One setting of the demo.

    Attributes:
        delta: ``(dx, dy)`` px.
        latent: ``L'``, the latent tile shifted by ``delta``.
        kernel: ``k'``, the kernel shifted by ``-delta``.
        blurred: ``k' * L'``.
        residual: ``k' * L' - k * L`` (zero up to rounding).
        star_centre: ``(2,)`` px, where ``L'`` puts the star centre.
        centroid: ``(2,)`` px, ``k'``'s centroid relative to the kernel centre.
    """

    delta: tuple[int, int]
    latent: np.ndarray
    kernel: np.ndarray
    blurred: np.ndarray
    residual: np.ndarray
    star_centre: np.ndarray
    centroid: np.ndarray


def ambiguity_demo(delta: tuple[int, int], num_segments: int = 16) -> AmbiguityDemo:
    """The latent star shifted by ``delta`` and the kernel by ``-delta``: the same blurred image."""
    latent = star_tile(num_segments)
    kernel = motion_kernel()
    reference = periodic_blur(latent, kernel)
    shifted, k_shifted = shift_pair(latent, kernel, delta)
    blurred = periodic_blur(shifted, k_shifted)
    centre = np.array([TILE_PX / 2.0 + delta[0], TILE_PX / 2.0 + delta[1]])
    return AmbiguityDemo((int(delta[0]), int(delta[1])), shifted, k_shifted, blurred, blurred - reference,
                         centre, kernel_centroid(k_shifted))


DEMO_CAMERA = BrownConrady(fx=500.0, fy=500.0, cx=319.5, cy=239.5, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0,
                           width=640, height=480)
"""The alignment demo's pinhole camera (640 x 480 px)."""
GRID = (12, 8)
"""Star squares of the alignment demo, across and down."""
SQUARE_M = 0.02
"""Square length of the alignment demo's target (m)."""
CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
"""A block's square corners in block coordinates, in drawing order."""


@dataclass(frozen=True)
class AlignmentStep:
    """The blocks after one step of the alignment demo.

    Attributes:
        name: the step (``after deconvolution``, ``after local alignment``,
            ``after global alignment``).
        quads: ``(B, 4, 2)`` px, each block's square ``H([-1, 1]^2)``.
        centres: ``(B, 2)`` px, the star centres ``H(0, 0)``.
        error: ``(B, 2)`` px, ``centres`` minus the true star centres.
        corner_gap_rms: px, RMS distance between the corners that neighbouring blocks share.
    """

    name: str
    quads: np.ndarray
    centres: np.ndarray
    error: np.ndarray
    corner_gap_rms: float

    @property
    def rms(self) -> float:
        """RMS length of the errors (px)."""
        return float(np.sqrt(np.mean(np.sum(self.error**2, axis=1))))


@dataclass(frozen=True)
class AlignmentDemo:
    """How local and global alignment remove the deconvolution's per-block shifts.

    Attributes:
        shift: ``(2,)`` px, the frame's common shift ``delta`` (the star shifted, the PSF not).
        scatter_px: the per-block shifts are uniform in ``[-scatter_px, scatter_px]^2`` on top.
        true_quads: ``(B, 4, 2)`` px, the true squares.
        true_centres: ``(B, 2)`` px, the true star centres.
        steps: after deconvolution, after local alignment, after global alignment.
        x_g: ``(2,)`` px, the global alignment's translation.
        size: ``(width, height)`` px of the demo image.
    """

    shift: np.ndarray
    scatter_px: float
    true_quads: np.ndarray
    true_centres: np.ndarray
    steps: tuple[AlignmentStep, AlignmentStep, AlignmentStep]
    x_g: np.ndarray
    size: tuple[int, int]


def _demo_pose(tilt_deg: float = 40.0, square_px: float = 40.0) -> Pose:
    """The target tilted by ``tilt_deg`` about the image diagonal, centred, squares about ``square_px``."""
    axis = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    R = cv2.Rodrigues(axis * math.radians(tilt_deg))[0]
    centre = np.array([(GRID[0] - 1) / 2.0 * SQUARE_M, (GRID[1] - 1) / 2.0 * SQUARE_M, 0.0])
    depth = DEMO_CAMERA.fx * SQUARE_M / square_px
    return Pose(R, np.array([0.0, 0.0, depth]) - R @ centre)


def _step(name: str, H: np.ndarray, truth: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> AlignmentStep:
    quads = apply_homography(H, np.broadcast_to(CORNERS, (len(H), 4, 2)))
    centres = homography_centre(H)
    gaps = corner_gaps(H, *neighbour_pairs(fx, fy))
    gap_rms = float(np.sqrt(np.mean(np.sum(gaps**2, axis=-1))))
    return AlignmentStep(name, quads, centres, centres - truth, gap_rms)


def alignment_demo(shift: tuple[float, float], scatter_px: float = 1.5, noise_px: float = 0.02,
                   seed: int = 0) -> AlignmentDemo:
    """Blocks of a tilted target whose star centres carry the ambiguity, and the two alignments.

    Each block's homography is the truth moved by ``T(shift + e_i)`` (``e_i`` uniform in
    ``[-scatter_px, scatter_px]^2``: the translation each block's deconvolution is free to
    choose) with its corners perturbed by ``noise_px`` (Gaussian per axis: the fit's own
    error). Local alignment (:func:`blurcalib.extract.local_alignment.align_locally`) then makes the
    shared corners agree, which removes the ``e_i`` up to their mean; global alignment
    (:func:`blurcalib.calib.alignment.align_global`, one translation ``x_G``) removes what is
    left against the (here exact) parametric camera.
    """
    rng = np.random.default_rng(seed)
    fx, fy = (a.ravel() for a in np.meshgrid(np.arange(GRID[0]), np.arange(GRID[1])))
    H_feature = plane_homography(DEMO_CAMERA.K, _demo_pose()) @ np.diag([SQUARE_M, SQUARE_M, 1.0])
    H_true = block_homography(H_feature, fx, fy)
    true_quads = apply_homography(H_true, np.broadcast_to(CORNERS, (len(H_true), 4, 2)))
    truth = homography_centre(H_true)
    offsets = np.asarray(shift, dtype=np.float64) + rng.uniform(-scatter_px, scatter_px, (len(H_true), 2))
    noisy = true_quads + offsets[:, None, :] + rng.normal(scale=noise_px, size=true_quads.shape)
    H_deconv = np.stack([cv2.getPerspectiveTransform(CORNERS.astype(np.float32), q.astype(np.float32))
                         for q in noisy])
    local = align_locally(H_deconv, fx, fy)
    points = np.column_stack([fx * SQUARE_M, fy * SQUARE_M, np.zeros(len(fx))])
    centres = homography_centre(local.H)
    ga = align_global(DEMO_CAMERA, points, centres, bias="translation")
    H_global = translation(-ga.translation) @ local.H
    steps = (_step("after deconvolution", H_deconv, truth, fx, fy),
             _step("after local alignment", local.H, truth, fx, fy),
             _step("after global alignment", H_global, truth, fx, fy))
    return AlignmentDemo(np.asarray(shift, dtype=np.float64), float(scatter_px), true_quads, truth, steps,
                         ga.translation, (DEMO_CAMERA.width, DEMO_CAMERA.height))
