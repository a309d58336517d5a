"""Quality filtering of fitted blocks, from their saved figures alone (no fit is recomputed).

The paper's *Real World Evaluation*: a frame is first kept only if it has enough blur for a
reliable PSF (median ``sigma_major`` of the blocks in the centre region at least
``min_sigma_major``; the paper's 3.8 px suits its own camera and rejects everything below about
13 px of blur, while the solver is accurate on little blur too, so this pre-filter is off by
default); then, within a frame,

1. blocks whose boundary energy ``BE > tau_BE`` are removed (their PSF is truncated),
2. blocks whose loss ``> tau_L`` are removed,
3. only the blocks connected (4-neighbours, breadth-first) to a seed are kept: the seed is the
   lowest-loss surviving block among those nearest the frame's centre.

All of it runs on arrays in milliseconds per frame, so a GUI can move the thresholds live.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from blurcalib.results import BlockStatus, BlockTable


@dataclass(frozen=True)
class QualitySettings:
    """Thresholds of the quality filter (the paper's, except the blur pre-filter, off).

    Attributes:
        tau_be: largest boundary energy ratio kept (0.12).
        tau_loss: largest loss kept, grey levels^2 (30).
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


@dataclass(frozen=True)
class FrameFilter:
    """Result of filtering one frame's blocks.

    Attributes:
        status: ``(B,)`` per block: ``accepted``, ``filtered_boundary_energy``, ``filtered_loss``,
            ``disconnected``, or the growth's own rejection.
        kept: ``(B,)`` bool, the blocks that survive.
        seed: index of the BFS seed block (-1 when none survived).
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
    high_loss = grown & ~high_be & ~(loss <= s.tau_loss)
    out[high_loss] = BlockStatus.FILTERED_LOSS.value
    survivors = grown & ~high_be & ~high_loss
    seed = _bfs_seed(centre, loss, survivors, image_size)
    connected = np.zeros(len(blocks), dtype=bool)
    if seed >= 0:
        connected = connected_blocks(blocks.fx, blocks.fy, survivors, [seed])
    out[survivors & ~connected] = BlockStatus.DISCONNECTED.value
    return FrameFilter(out, connected, seed, centre_sigma, bool(frame_ok))


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
