"""Quality filtering of fitted blocks, from their saved figures alone (no fit is recomputed).

The paper's *Real World Evaluation*: a frame is first kept only if it has enough blur for a
reliable PSF (median ``sigma_major`` of the blocks in the centre region at least
``min_sigma_major``; the paper's 3.8 px suits its own camera and rejects everything below about
13 px of blur, while the solver is accurate on little blur too, so this pre-filter is off by
default); then, within a frame,

1. blocks whose boundary energy ``BE > tau_BE`` are removed (their PSF is truncated),
2. blocks whose loss is above the loss threshold are removed (:meth:`QualitySettings.loss_limit`),
3. only the largest group of the survivors connected through 4-neighbours is kept (the paper
   grows it breadth-first from a seed near the frame's centre, which can sit on an island);
   its seed is its lowest-loss block among those nearest the frame's centre.

The loss threshold follows the frame's own noise by default (``loss_mode = "relative"``). A
block's loss, its mean squared residual, is the mean noise variance over its pixels, ``a + b mu``
at its mean level ``mu`` (:mod:`blurcalib.growth.noise`), plus what the model does not explain (the
print, a display's pixel grid, the blur model): shot noise makes the first grow with the
brightness, so one threshold in grey levels^2 drops the well-fitted blocks of bright, noisy
frames. The block is kept when::

    loss <= tau_L * max(noise_var, REFERENCE_NOISE_VAR) / REFERENCE_NOISE_VAR

``noise_var`` the frame's noise variance at the block's level (:attr:`BlockTable.noise_var`),
``REFERENCE_NOISE_VAR`` = 4 grey levels^2 (noise of 2 grey levels): the paper's ``tau_L = 30``
grey levels^2 on frames with up to 2 grey levels of noise (30 is then at least 7.5 noise
variances), 7.5 noise variances on noisier ones. The threshold does not fall below ``tau_L`` on
quieter frames: the model's own errors do not shrink with the noise (real frames of a display
recorded through video compression read about 0 grey levels of noise at a median loss of 6).
With ``loss_mode = "absolute"`` the paper's rule ``loss <= tau_L`` (grey levels^2) applies; it
also applies to blocks whose noise is not known (NaN ``noise_var``, results written without it).

All of it runs on arrays in milliseconds per frame, so a GUI can move the thresholds live.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from blurcalib.io.results import BlockStatus, BlockTable

LossMode = Literal["relative", "absolute"]
"""How :attr:`QualitySettings.tau_loss` is read: in the frame's noise units or in grey levels^2."""

REFERENCE_NOISE_VAR = 4.0
"""Noise variance (grey levels^2) up to which a relative ``tau_L`` equals the absolute one: noise
of 2 grey levels, that of the simulated demo frames."""


def noise_scale(noise_var: np.ndarray | float) -> np.ndarray:
    """``max(noise_var, REFERENCE_NOISE_VAR) / REFERENCE_NOISE_VAR`` (1 where ``noise_var`` is
    NaN): the factor by which the noise-relative loss limits exceed their absolute values."""
    v = np.asarray(noise_var, dtype=np.float64)
    return np.where(np.isfinite(v), np.maximum(v / REFERENCE_NOISE_VAR, 1.0), 1.0)


@dataclass(frozen=True)
class QualitySettings:
    """Thresholds of the quality filter (the paper's, except the blur pre-filter, off).

    Attributes:
        tau_be: largest boundary energy ratio kept (0.12).
        tau_loss: ``tau_L``, largest loss kept (30 grey levels^2), in ``"relative"`` mode for
            blocks with at most the reference noise (:data:`REFERENCE_NOISE_VAR`).
        loss_mode: ``"relative"`` (the default: the threshold grows with each block's noise
            variance above the reference) or ``"absolute"`` (the paper's rule).
        min_sigma_major: frames whose centre-region median sigma_major is below this (px) are
            dropped: too little blur for a reliable PSF. 0 (the default) keeps every frame; the
            paper uses 3.8.
        centre_fraction: the centre region is the middle ``centre_fraction`` of the image in
            each direction (for the frame pre-filter and the BFS seed).
    """

    tau_be: float = 0.12
    tau_loss: float = 30.0
    min_sigma_major: float = 0.0
    centre_fraction: float = 0.5
    loss_mode: LossMode = "relative"

    def __post_init__(self) -> None:
        if self.loss_mode not in get_args(LossMode):
            raise ValueError(f"loss_mode must be one of {get_args(LossMode)}, got {self.loss_mode!r}")

    def loss_limit(self, noise_var: np.ndarray) -> np.ndarray:
        """``(B,)`` the largest loss kept per block (grey levels^2), from the blocks' noise
        variances ``noise_var (B,)`` (grey levels^2; NaN: unknown, judged by ``tau_loss`` as is)."""
        noise_var = np.asarray(noise_var, dtype=np.float64)
        if self.loss_mode == "absolute":
            return np.full(noise_var.shape, self.tau_loss)
        return self.tau_loss * noise_scale(noise_var)


@dataclass(frozen=True)
class FrameFilter:
    """Result of filtering one frame's blocks.

    Attributes:
        status: ``(B,)`` per block: ``accepted``, ``filtered_boundary_energy``, ``filtered_loss``,
            ``disconnected``, or the growth's own rejection.
        kept: ``(B,)`` bool, the blocks that survive.
        seed: index of the kept group's seed block, its lowest-loss block among the quarter
            nearest the image centre (-1 when none survived).
        centre_sigma_major: median sigma_major of the accepted blocks in the centre region (px;
            of all accepted blocks when none lies in the centre region).
        frame_ok: the frame passes the blur pre-filter.
    """

    status: np.ndarray
    kept: np.ndarray
    seed: int
    centre_sigma_major: float
    frame_ok: bool

    def counts(self) -> dict[str, int]:
        """Number of blocks per status."""
        values, counts = np.unique(self.status, return_counts=True)
        return {str(v): int(c) for v, c in zip(values, counts, strict=True)}


def _in_centre(xy: np.ndarray, image_size: tuple[int, int], fraction: float) -> np.ndarray:
    w, h = image_size
    half = fraction / 2.0
    return ((np.abs(xy[:, 0] - (w - 1) / 2) <= half * w)
            & (np.abs(xy[:, 1] - (h - 1) / 2) <= half * h))


def filter_frame(blocks: BlockTable, image_size: tuple[int, int], settings: QualitySettings | None = None
                 ) -> FrameFilter:
    """Filter one frame's blocks, from their figures and star centres (:attr:`BlockTable.centre`).

    Args:
        blocks: the frame's ``B`` blocks (statuses as the growth left them).
        image_size: ``(width, height)`` px.
        settings: thresholds.
    """
    s = settings or QualitySettings()
    grown, centre, loss, sigma_major = blocks.accepted, blocks.centre, blocks.loss, blocks.sigma_major
    in_centre = _in_centre(centre, image_size, s.centre_fraction)
    central = grown & in_centre & np.isfinite(sigma_major)
    if not central.any():  # the target does not reach the centre region: use every block
        central = grown & np.isfinite(sigma_major)
    centre_sigma = float(np.median(sigma_major[central])) if central.any() else float("nan")
    frame_ok = s.min_sigma_major <= 0 or (np.isfinite(centre_sigma)
                                          and centre_sigma >= s.min_sigma_major)
    out = blocks.status.astype(object)
    high_be = grown & ~(blocks.boundary_energy <= s.tau_be)
    out[high_be] = BlockStatus.FILTERED_BOUNDARY_ENERGY.value
    assert blocks.noise_var is not None  # filled in by BlockTable
    high_loss = grown & ~high_be & ~(loss <= s.loss_limit(blocks.noise_var))
    out[high_loss] = BlockStatus.FILTERED_LOSS.value
    survivors = grown & ~high_be & ~high_loss
    connected = _largest_group(blocks.fx, blocks.fy, survivors)
    seed = _bfs_seed(centre, loss, connected, image_size)
    out[survivors & ~connected] = BlockStatus.DISCONNECTED.value
    return FrameFilter(out, connected, seed, centre_sigma, bool(frame_ok))


def _largest_group(fx: np.ndarray, fy: np.ndarray, survivors: np.ndarray) -> np.ndarray:
    """``(B,)`` bool: the largest group of ``survivors`` 4-connected in the pattern (the first
    found of equal ones). A seed chosen near the image centre alone can sit on an island: a demo
    frame (blurry/0019, 10-12 px of blur) kept 2 of its 205 accepted blocks that way, an island
    of 2 beside a group of 201."""
    best = np.zeros(len(fx), dtype=bool)
    left = survivors.copy()
    while left.sum() > best.sum():
        group = connected_blocks(fx, fy, survivors, [int(np.flatnonzero(left)[0])])
        if group.sum() > best.sum():
            best = group
        left &= ~group
    return best


def _bfs_seed(centre: np.ndarray, loss: np.ndarray, survivors: np.ndarray,
              image_size: tuple[int, int]) -> int:
    """The lowest-loss survivor among the quarter of survivors nearest the image centre."""
    idx = np.flatnonzero(survivors)
    if len(idx) == 0:
        return -1
    w, h = image_size
    dist = np.hypot(centre[idx, 0] - (w - 1) / 2, centre[idx, 1] - (h - 1) / 2)
    near = idx[np.argsort(dist)[:max(1, len(idx) // 4)]]
    return int(near[np.argmin(loss[near])])


def connected_blocks(fx: np.ndarray, fy: np.ndarray, allowed: np.ndarray, seeds: Sequence[int]
                     ) -> np.ndarray:
    """``(B,)`` bool: the blocks reached from ``seeds`` through 4-neighbours in the pattern
    (feature coordinates ``fx, fy (B,)``) that are ``allowed (B,)`` (breadth-first)."""
    index = {(int(x), int(y)): i for i, (x, y) in enumerate(zip(fx, fy, strict=True)) if allowed[i]}
    seen = np.zeros(len(fx), dtype=bool)
    seen[list(seeds)] = True
    queue = deque(seeds)
    while queue:
        i = queue.popleft()
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            j = index.get((int(fx[i]) + dx, int(fy[i]) + dy))
            if j is not None and not seen[j]:
                seen[j] = True
                queue.append(j)
    return seen
