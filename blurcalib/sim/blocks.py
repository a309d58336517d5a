"""Single simulated star blocks with exact ground truth (homography, PSF, centre), for the block
solver's tests and benchmarks (``scripts/bench_deconv.py``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np

from blurcalib.geometry.homography import homography_centre, translation
from blurcalib.psf.kernel import psf_centroid
from blurcalib.sim.truth import splat
from blurcalib.target.pattern import StarPattern


@dataclass(eq=False)
class SimulatedBlocks:
    """Synthetic blocks with ground truth (for tests and ``scripts/bench_deconv.py``).

    Attributes:
        image: ``(height, width)`` uint8, the blocks' tiles side by side.
        H_true: ``(B, 3, 3)`` true block homographies (block coords -> image px).
        H0: ``(B, 3, 3)`` perturbed initial homographies.
        psf_true: ``(B, Kt, Kt)`` true kernels (sum 1).
        centre_true: ``(B, 2)`` px, ``H_true(0, 0)`` plus the true kernel's centroid: the star
            centre's time-averaged position.
        features: ``(B, 2)`` int feature coordinates of the blocks.
    """

    image: np.ndarray
    H_true: np.ndarray
    H0: np.ndarray
    psf_true: np.ndarray
    centre_true: np.ndarray
    features: np.ndarray


def _motion_kernel(rng: np.random.Generator, length: float, size: int, gauss_sigma: float) -> np.ndarray:
    """A curved, unevenly travelled motion path of ``length`` px splatted into ``size x size``."""
    theta = rng.uniform(0, 2 * np.pi)
    d = np.array([math.cos(theta), math.sin(theta)])
    nrm = np.array([-d[1], d[0]])
    bend = rng.uniform(-0.25, 0.25) * length
    t = np.linspace(0.0, 1.0, 400) ** rng.uniform(0.7, 1.4)  # uneven speed
    pts = ((t - 0.5)[:, None] * length * d[None] + (4 * t * (1 - t))[:, None] * bend * nrm[None])
    pts = pts - pts.mean(axis=0) + rng.uniform(-1.0, 1.0, 2)
    k = splat(pts, size)
    if gauss_sigma > 0:
        k = cv2.GaussianBlur(k, (0, 0), gauss_sigma, borderType=cv2.BORDER_CONSTANT)
    return cast(np.ndarray, k / k.sum())


def simulate_blocks(pattern: StarPattern, num_blocks: int, rng: np.random.Generator, *,
                    square_px: tuple[float, float] = (26.0, 34.0), blur_px: tuple[float, float] = (4.0, 15.0),
                    gauss_sigma: tuple[float, float] = (0.0, 0.6), noise_sigma: float = 2.0,
                    init_shift_px: float = 1.5, init_scale: float = 0.03, supersample: int = 8,
                    tile_px: int = 96, ink: float = 30.0, paper: float = 200.0,
                    truth_kernel_size: int = 31, psf: np.ndarray | None = None) -> SimulatedBlocks:
    """Render ``num_blocks`` blurred star blocks with known ``H`` and PSF, one per tile.

    Each tile shows the exact pattern (:meth:`StarPattern.intensity`, box-filtered over
    ``supersample^2`` samples per pixel) around a random valid feature through a random
    perspective homography (square side in ``square_px``), blurred by a random curved motion
    path of ``blur_px`` length (:func:`blurcalib.sim.truth.splat`) and a Gaussian, scaled to
    ``ink..paper`` with gain and offset gradients applied after the blur (as
    :func:`blurcalib.sim.render.sensor_image` does), with Gaussian noise of ``noise_sigma`` grey
    levels, quantised to 8 bits. ``H0`` is ``H_true`` moved by up to ``init_shift_px`` px and
    scaled by up to ``init_scale`` about the centre. ``psf`` (``(Kt, Kt)`` or ``(B, Kt, Kt)``,
    odd ``Kt``) replaces the random motion kernels.
    """
    from scipy.signal import fftconvolve  # here: importing scipy.signal takes seconds

    if psf is not None:
        given = np.broadcast_to(np.asarray(psf, dtype=np.float64), (num_blocks, *np.shape(psf)[-2:]))
        truth_kernel_size = given.shape[-1]
    cols = math.ceil(math.sqrt(num_blocks))
    rows = math.ceil(num_blocks / cols)
    image = np.zeros((rows * tile_px, cols * tile_px))
    feats = pattern.features[rng.choice(pattern.num_features, num_blocks, replace=False)]
    H_true = np.zeros((num_blocks, 3, 3))
    H0 = np.zeros_like(H_true)
    kernels = np.zeros((num_blocks, truth_kernel_size, truth_kernel_size))
    centre = np.zeros((num_blocks, 2))
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    yy, xx = np.mgrid[0:tile_px, 0:tile_px].astype(np.float64)
    for b in range(num_blocks):
        ty, tx = divmod(b, cols)
        half = 0.5 * rng.uniform(*square_px)
        ang = rng.uniform(0, 2 * np.pi)
        R = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
        Aff = half * R @ np.array([[1.0 + rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)], [0.0, 1.0]])
        Hb = np.eye(3)
        Hb[:2, :2] = Aff
        Hb[:2, 2] = tile_px / 2 - 0.5 + rng.uniform(-0.5, 0.5, 2)
        Hb = Hb @ np.array([[1, 0, 0], [0, 1, 0], [*rng.uniform(-0.08, 0.08, 2), 1.0]])
        Hb /= Hb[2, 2]
        fx, fy = feats[b]
        to_feature = np.array([[0.5, 0, fx], [0, 0.5, fy], [0, 0, 1.0]]) @ np.linalg.inv(Hb)
        acc = np.zeros((tile_px, tile_px))
        for oy in offs:
            for ox in offs:
                X = np.stack([xx + ox, yy + oy, np.ones_like(xx)], axis=-1) @ to_feature.T
                acc += pattern.intensity(X[..., :2] / X[..., 2:])
        latent = acc / supersample**2
        if psf is None:
            k = _motion_kernel(rng, rng.uniform(*blur_px), truth_kernel_size, rng.uniform(*gauss_sigma))
        else:
            k = given[b] / given[b].sum()
        blurred = fftconvolve(latent, k, mode="same")
        u = (xx - tile_px / 2) / (tile_px / 2)
        v = (yy - tile_px / 2) / (tile_px / 2)
        gain = (paper - ink) * (1.0 + rng.uniform(-0.08, 0.08) * u + rng.uniform(-0.08, 0.08) * v)
        offset = ink * (1.0 + rng.uniform(-0.2, 0.2) * u + rng.uniform(-0.2, 0.2) * v)
        tile = offset + gain * blurred + rng.normal(0.0, noise_sigma, blurred.shape)
        image[ty * tile_px:(ty + 1) * tile_px, tx * tile_px:(tx + 1) * tile_px] = tile
        Hi = translation(np.array([tx * tile_px, ty * tile_px], dtype=np.float64)) @ Hb
        H_true[b] = Hi
        kernels[b] = k
        c0 = homography_centre(Hi)
        centre[b] = c0 + psf_centroid(k, 0.0)
        shift = rng.normal(size=2)
        shift *= rng.uniform(0, init_shift_px) / np.linalg.norm(shift)
        sc = 1.0 + rng.uniform(-init_scale, init_scale)
        H0[b] = translation(c0 + shift) @ np.diag([sc, sc, 1.0]) @ translation(-c0) @ Hi
    img8 = np.clip(np.round(image), 0, 255).astype(np.uint8)
    return SimulatedBlocks(img8, H_true, H0, kernels, centre, feats)
