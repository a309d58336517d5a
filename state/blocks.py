"""Figures of one frame's blocks in the app: its quality filter and counts by reason, the block
at an image point, the blocks expected in the image while it grows, and the range of each
threshold over the finished frames."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from blurcalib.extract.frame import FrameResult
from blurcalib.geometry.homography import apply_homography, homography_centre
from blurcalib.growth.ledger import GrowthEvent
from blurcalib.growth.quality import FrameFilter, QualitySettings, filter_frame, noise_scale
from blurcalib.growth.seed import block_homography
from blurcalib.growth.settings import GrowSettings
from blurcalib.io.results import BlockStatus, BlockTable
from blurcalib.target.pattern import StarPattern

NOT_FITTED = (BlockStatus.OUTSIDE_IMAGE.value, BlockStatus.DEGENERATE_HOMOGRAPHY.value)
"""Growth statuses of blocks that were never fitted: their square leaves the image (or maps to
no square)."""
FILTER_REASONS = {BlockStatus.FILTERED_BOUNDARY_ENERGY.value: "boundary energy above τ_BE",
                  BlockStatus.FILTERED_LOSS.value: "loss above τ_L",
                  BlockStatus.DISCONNECTED.value: "cut off from the largest connected group"}
"""Why the quality filter removed a block the growth accepted, in words."""
GROWTH_REASONS = {BlockStatus.HIGH_LOSS.value: "loss above the growth's limit",
                  BlockStatus.PSF_TRUNCATED.value: "PSF cut by its window",
                  BlockStatus.NOT_CONVERGED.value: "star centre off its prediction",
                  BlockStatus.DISCONNECTED.value: "cut off by the growth's neighbour check"}
"""Why the growth rejected a fitted block, in words."""

SQUARE_CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
"""A block's square corners in block coordinates, in drawing order."""


def block_quads(H: np.ndarray) -> np.ndarray:
    """``(B, 4, 2)`` px: the squares ``H([-1, 1]^2)`` of block homographies ``(B, 3, 3)``."""
    return apply_homography(H, np.broadcast_to(SQUARE_CORNERS, (len(H), 4, 2)))


@dataclass(frozen=True)
class FilterCounts:
    """Blocks of one frame by outcome: kept, removed by the quality filter (by reason), rejected
    by the growth (by its status) and never fitted.

    Attributes:
        kept: blocks the filter keeps.
        removed_be, removed_loss, disconnected: blocks the growth accepted and the filter
            removed, by reason.
        rejected: ``{growth status: count}`` of the fitted blocks the growth rejected.
        not_fitted: blocks whose square leaves the image (:data:`NOT_FITTED`).
    """

    kept: int
    removed_be: int
    removed_loss: int
    disconnected: int
    rejected: dict[str, int]
    not_fitted: int

    @property
    def removed(self) -> int:
        """Blocks the growth accepted and the filter removed."""
        return self.removed_be + self.removed_loss + self.disconnected


def filter_counts(flt: FrameFilter, growth: np.ndarray | None = None) -> FilterCounts:
    """Counts of a frame's filter result ``flt``; ``growth (B,)`` the growth's statuses of the
    blocks (default: the filter's statuses of the blocks it did not judge)."""
    status = flt.status.astype(str)
    if growth is None:  # the filter's own statuses stand for the blocks it judged
        grown = status
        judged = (status == BlockStatus.ACCEPTED.value) | np.isin(status, list(FILTER_REASONS))
    else:
        grown = np.asarray(growth).astype(str)
        judged = grown == BlockStatus.ACCEPTED.value
    removed = {k: int(np.sum(judged & (status == k))) for k in FILTER_REASONS}
    outside = np.isin(grown, NOT_FITTED)
    values, counts = np.unique(grown[~judged & ~outside], return_counts=True)
    rejected = {str(v): int(c) for v, c in zip(values, counts, strict=True)}
    return FilterCounts(int(flt.kept.sum()), removed[BlockStatus.FILTERED_BOUNDARY_ENERGY.value],
                        removed[BlockStatus.FILTERED_LOSS.value], removed[BlockStatus.DISCONNECTED.value],
                        rejected, int(outside.sum()))


def lower_loss_removed(blocks: BlockTable, flt: FrameFilter) -> dict[str, int]:
    """Why the blocks that were not kept although their loss is below the largest kept loss
    were dropped: ``{reason in words: count}`` (:data:`FILTER_REASONS`, :data:`GROWTH_REASONS`);
    empty when none was. Loss is only one of the rules: such a block was removed by another."""
    fitted = np.isfinite(blocks.loss)
    if not flt.kept.any():
        return {}
    top = float(np.max(blocks.loss[flt.kept]))
    low = fitted & ~flt.kept & (blocks.loss < top)
    out: dict[str, int] = {}
    status, grown = flt.status.astype(str), blocks.status.astype(str)
    for i in np.flatnonzero(low):
        if grown[i] == BlockStatus.ACCEPTED.value:
            reason = FILTER_REASONS.get(status[i], status[i])
        else:
            reason = f"rejected by the growth: {GROWTH_REASONS.get(grown[i], grown[i])}"
        out[reason] = out.get(reason, 0) + 1
    return out


def block_at(blocks: BlockTable, point: tuple[float, float]) -> int | None:
    """The block whose square ``H([-1, 1]^2)`` contains the image point ``point`` (px), else
    the fitted block whose star centre is nearest within a square's side; None when none is."""
    if not len(blocks):
        return None
    quads = block_quads(blocks.H)
    x, y = float(point[0]), float(point[1])
    for i, quad in enumerate(quads):
        if np.all(np.isfinite(quad)) and cv2.pointPolygonTest(quad.astype(np.float32), (x, y), False) >= 0:
            return i
    centres = homography_centre(blocks.H)
    d = np.hypot(centres[:, 0] - x, centres[:, 1] - y)
    d[~np.isfinite(d)] = np.inf
    i = int(np.argmin(d))
    side = float(np.nanmedian(np.linalg.norm(quads[:, 1] - quads[:, 0], axis=1)))
    return i if d[i] <= side else None


@dataclass(frozen=True)
class Range:
    """A threshold's slider range ``[lo, hi]`` and whether it is logarithmic (then the slider
    moves ``log10`` of the threshold)."""

    lo: float
    hi: float
    log: bool = False


@dataclass(frozen=True)
class FilterRanges:
    """The slider ranges of the three thresholds over the finished frames' figures."""

    tau_be: Range
    tau_loss: Range
    sigma: Range


def effective_loss(blocks: BlockTable, quality: QualitySettings) -> np.ndarray:
    """``(B,)`` each block's loss as τ_L judges it: divided by its noise factor in the relative
    mode (:func:`blurcalib.growth.quality.noise_scale`), as is in the absolute one."""
    if quality.loss_mode == "absolute":
        return np.asarray(blocks.loss, dtype=np.float64)
    return np.asarray(blocks.loss, dtype=np.float64) / noise_scale(blocks.noise_var)


def filter_ranges(frames: Iterable[tuple[BlockTable, FrameFilter | None]], quality: QualitySettings,
                  grow: GrowSettings | None = None) -> FilterRanges:
    """Slider ranges from the frames' own figures: τ_L (logarithmic) from 0.8 x the lowest to
    1.25 x the highest loss of the blocks the growth accepted (within the growth's own limit,
    above which nothing is left to remove), τ_BE from 0 to 1.2 x their highest boundary energy
    (within the growth's limit), the σ_major pre-filter from 0 to 1.15 x the largest frame
    median; each range also holds the defaults and the current values."""
    g = grow or GrowSettings()
    d = QualitySettings()
    loss, be, sigma = [], [], []
    for blocks, flt in frames:
        ok = blocks.accepted & np.isfinite(blocks.loss) & (blocks.loss > 0)
        loss.append(effective_loss(blocks, quality)[ok])
        be.append(np.asarray(blocks.boundary_energy)[ok])
        if flt is not None and math.isfinite(flt.centre_sigma_major):
            sigma.append(flt.centre_sigma_major)
    losses = np.concatenate(loss) if loss else np.zeros(0)
    energies = np.concatenate(be) if be else np.zeros(0)
    lo_l, hi_l = (0.8 * float(losses.min()), 1.25 * float(losses.max())) if losses.size else (1.0, g.max_loss)
    lo_l = min(lo_l, d.tau_loss, quality.tau_loss)
    hi_l = max(min(hi_l, g.max_loss), d.tau_loss, quality.tau_loss)
    top_be = 1.2 * float(energies.max()) if energies.size else g.max_boundary_energy
    hi_be = min(top_be, g.max_boundary_energy)
    hi_be = max(hi_be, d.tau_be, quality.tau_be)
    hi_s = max(1.15 * max(sigma, default=0.0), 1.0, quality.min_sigma_major)
    return FilterRanges(Range(0.0, hi_be), Range(max(lo_l, 0.1), hi_l, log=True), Range(0.0, hi_s))


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
