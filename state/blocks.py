"""Figures of one frame's blocks in the app: its quality filter and counts, and the blocks
expected in the image while it grows."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from blurcalib.extract.frame import FrameResult
from blurcalib.geometry.homography import homography_centre
from blurcalib.growth.ledger import GrowthEvent
from blurcalib.growth.quality import FrameFilter, QualitySettings, filter_frame
from blurcalib.growth.seed import block_homography
from blurcalib.io.results import BlockStatus
from blurcalib.target.pattern import StarPattern


@dataclass(frozen=True)
class FilterCounts:
    """Blocks of one frame by outcome of the quality filter."""

    kept: int
    removed_be: int
    removed_loss: int
    disconnected: int
    rejected: int

    @property
    def removed(self) -> int:
        """Blocks the growth accepted and the filter removed."""
        return self.removed_be + self.removed_loss + self.disconnected


def filter_counts(flt: FrameFilter) -> FilterCounts:
    """Counts of a frame's filter result."""
    counts = flt.counts()
    removed_be = counts.get(BlockStatus.FILTERED_BOUNDARY_ENERGY.value, 0)
    removed_loss = counts.get(BlockStatus.FILTERED_LOSS.value, 0)
    disconnected = counts.get(BlockStatus.DISCONNECTED.value, 0)
    kept = int(flt.kept.sum())
    rejected = len(flt.status) - kept - removed_be - removed_loss - disconnected
    return FilterCounts(kept, removed_be, removed_loss, disconnected, rejected)


def frame_filter(result: FrameResult, image_size: tuple[int, int], quality: QualitySettings,
                 kind: str = "blurry") -> FrameFilter | None:
    """The quality filter of a result's blocks (None when it has none).

    The σ_major pre-filter applies to blurry frames only: a sharp frame has little blur by design.
    """
    if not len(result.blocks):
        return None
    if kind == "sharp":
        quality = replace(quality, min_sigma_major=0.0)
    return filter_frame(result.blocks, image_size, quality)


def expected_blocks(pattern: StarPattern, event: GrowthEvent, image_size: tuple[int, int]) -> int:
    """Features whose star centre, predicted from one block's homography, lies in the image."""
    B = block_homography(np.eye(3), np.array([event.fx]), np.array([event.fy]))[0]
    H_feature = event.H @ np.linalg.inv(B)
    f = pattern.features
    centres = homography_centre(block_homography(H_feature, f[:, 0], f[:, 1]))
    w, h = image_size
    inside = (centres[:, 0] >= 0) & (centres[:, 0] <= w - 1) & (centres[:, 1] >= 0) \
        & (centres[:, 1] <= h - 1)
    return int(inside.sum())
