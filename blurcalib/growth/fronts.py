"""Growth fronts: the ring around the tag, the next front from the accepted blocks, their
predictions and PSF hints, and a front's fit from its hints.

Every accepted block predicts its 4-neighbours (the pattern is periodic: the neighbour at
``(fx + dx, fy + dy)`` has ``H' = H T_q(2 dx, 2 dy)``, one square being 2 block units), averaged
over all accepted neighbours of a candidate. Under heavy blur the tag's corners (and so the
ring's prediction) are off by several px, and a block fitted from a poor start can settle with
its long PSF partly outside the window, its centre off by a third of a square at a low loss; so
the ring is fitted twice: the seed homography is re-estimated from the first fit's star centres
(RANSAC) and the ring re-fitted from its predictions (:func:`refine_ring`).
"""

from __future__ import annotations

from dataclasses import replace
from typing import cast

import cv2
import numpy as np

from blurcalib.deconv.blocks import fit_blocks, fit_blocks_hinted
from blurcalib.deconv.result import BlockFit
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.geometry.homography import homography_centre
from blurcalib.growth.masks import pixel_mask
from blurcalib.growth.seed import Seed, block_homography, tag_ring_features
from blurcalib.growth.settings import GrowSettings
from blurcalib.growth.window import WindowPolicy, fit_front
from blurcalib.io.results import BlockStatus
from blurcalib.psf.kernel import blur_per_square, psf_moments, resize_kernels
from blurcalib.target.pattern import StarPattern


def shift_q(dx: int, dy: int) -> np.ndarray:
    """``T_q(2 dx, 2 dy)`` ``(3, 3)``: block coordinates of the neighbour ``(dx, dy)`` squares away."""
    return np.array([[1.0, 0.0, 2.0 * dx], [0.0, 1.0, 2.0 * dy], [0.0, 0.0, 1.0]])


def normalise(H: np.ndarray) -> np.ndarray:
    """Homographies ``(..., 3, 3)`` scaled to ``H[2, 2] = 1``."""
    return cast(np.ndarray, H / H[..., 2:3, 2:3])


def first_front(pattern: StarPattern, seed: Seed, image_shape: tuple[int, int]
                ) -> tuple[list[int], list[np.ndarray]] | None:
    """The first front's feature ids and predictions ``(3, 3)`` from ``seed``: the ring around
    the tag, or without a tag the 4 blocks nearest the image centre that lie inside it (None
    when none does)."""
    h, w = image_shape
    ring = tag_ring_features(pattern) if seed.source == "tag" else pattern.features
    ring_ids = pattern.feature_ids(ring[:, 0], ring[:, 1])
    H_ring = block_homography(seed.H_feature, ring[:, 0], ring[:, 1])
    if seed.source == "given":
        centres = homography_centre(H_ring)
        inside = (centres[:, 0] > 0) & (centres[:, 0] < w - 1) & (centres[:, 1] > 0) \
            & (centres[:, 1] < h - 1)
        if not inside.any():
            return None
        dist = np.linalg.norm(centres - np.array([w / 2, h / 2]), axis=1)
        dist[~inside] = np.inf
        keep = np.argsort(dist)[:4]
        ring_ids, H_ring = ring_ids[keep], H_ring[keep]
    return [int(i) for i in ring_ids], [normalise(Hb) for Hb in H_ring]


def fit_hinted(image: np.ndarray, H0: np.ndarray, num_segments: int, kernel_size: int,
               deconv: DeconvSettings, mask: np.ndarray | None, psf_hint: np.ndarray | None,
               settings: GrowSettings | None = None) -> BlockFit:
    """:func:`blurcalib.deconv.blocks.fit_blocks_hinted` with ``psf_hint (B, K, K)``
    (``K = kernel_size``; None: :func:`blurcalib.deconv.blocks.fit_blocks`), then a second look at
    the blocks it leaves not converged:

    * when the front accepts none, all of them are fitted again with the full schedule (no hint)
      and a re-fit is kept where it is accepted: hints from poor neighbours must not end a growth
      that creeps through single blocks;
    * otherwise those whose hint shows a blur short for their square
      (:func:`blurcalib.psf.kernel.blur_per_square` of the hint at ``H0`` below
      :attr:`GrowSettings.retry_below_blur_per_square`) are accepted when their last LM step moved
      the star centre less than :attr:`GrowSettings.hinted_converge_px`, and fitted again with
      the full schedule when it moved more. There the one hinted stage is slow, not wrong: on
      low-contrast real frames it still moves by up to 0.15 px at its last step, within 0.15 px
      of the full schedule's fit. Where the blur reaches half the square a block still moving is
      often px off, and the full schedule settles px off too: those stay not converged
      (docs/decisions/hinted-second-look.md).
    """
    s = settings or GrowSettings()
    if psf_hint is None:
        return fit_blocks(image, H0, num_segments, kernel_size, deconv, mask)
    fit = fit_blocks_hinted(image, H0, num_segments, psf_hint, deconv, mask)
    failed = np.array([st is BlockStatus.NOT_CONVERGED for st in fit.status], dtype=bool)
    if not failed.any():
        return fit
    if BlockStatus.ACCEPTED in fit.status:
        with np.errstate(invalid="ignore", divide="ignore"):
            failed &= (blur_per_square(np.asarray(psf_moments(psf_hint).sigma_major), H0)
                       < s.retry_below_blur_per_square)
        settled = failed & fit.converged_within(s.hinted_converge_px)
        if settled.any():
            fit = replace(fit, converged=fit.converged | settled,
                          status=tuple(BlockStatus.ACCEPTED if ok else st
                                       for ok, st in zip(settled, fit.status, strict=True)))
        failed &= ~settled
    redo = np.flatnonzero(failed)
    if redo.size == 0:
        return fit
    refit = fit_blocks(image, H0[redo], num_segments, kernel_size, deconv, mask)
    better = np.flatnonzero([st is BlockStatus.ACCEPTED for st in refit.status])
    return fit.with_rows(redo[better], refit, better) if better.size else fit


def refine_ring(image: np.ndarray, pattern: StarPattern, ids: list[int], fit: BlockFit,
                window: WindowPolicy, deconv: DeconvSettings, settings: GrowSettings,
                tag: np.ndarray | None, adaptive: bool = True, footprint: np.ndarray | None = None
                ) -> tuple[np.ndarray, BlockFit] | None:
    """Re-fit the ring around the tag from the homography of its first fit's star centres.

    Args:
        image: the frame.
        pattern: the target.
        ids: the ring's feature ids (rows of ``fit``).
        fit: the first fit of the ring.
        window, deconv, settings: as for :func:`blurcalib.growth.window.fit_front`.
        tag: :func:`blurcalib.growth.masks.tag_mask`.
        adaptive: choose the window from the first fit's PSFs (else the start window).
        footprint: :func:`blurcalib.growth.masks.blur_footprint` (adaptive only), for
            :func:`blurcalib.growth.masks.pixel_mask`.
    Returns:
        ``(H0 (B, 3, 3), fit)``: the new predictions and their fit; None when fewer than 6
        blocks were accepted or no homography fits them (RANSAC, 1.5 px).
    """
    ok = np.array([st is BlockStatus.ACCEPTED for st in fit.status], dtype=bool)
    ok &= np.all(np.isfinite(fit.centre), axis=1)
    if ok.sum() < 6:
        return None
    f = pattern.features[np.asarray(ids)]
    H, inliers = cv2.findHomography(f[ok].astype(np.float64), fit.centre[ok], cv2.RANSAC, 1.5)
    if H is None or inliers.sum() < 6:
        return None
    H0 = normalise(block_homography(H, f[:, 0], f[:, 1]))
    N = pattern.num_star_segments
    if not adaptive:
        return H0, fit_blocks(image, H0, N, window.start, deconv, pixel_mask(tag, window.start))
    size = window.choose(fit.sigma_major[ok])
    first = fit_blocks(image, H0, N, size, deconv, pixel_mask(tag, size, footprint))
    return H0, fit_front(image, H0, N, first, window, deconv, settings, tag, footprint)


def next_front(pattern: StarPattern, accepted_H: dict[int, np.ndarray],
                attempted: dict[int, int], new_ids: list[int]
                ) -> tuple[list[int], list[np.ndarray], list[list[int]]]:
    """Unattempted valid neighbours of the newly accepted blocks, with averaged predictions and
    the accepted blocks that predicted each."""
    candidates: dict[int, list[np.ndarray]] = {}
    sources: dict[int, list[int]] = {}
    grid = pattern.id_grid.tolist()  # scalar look-ups: pattern.feature_ids costs ~75 us per call

    def feature_id(x: int, y: int) -> int:
        return grid[y][x] if 0 <= y < len(grid) and 0 <= x < len(grid[0]) else -1

    for fid in new_ids:
        fx, fy = (int(v) for v in pattern.features[fid])
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nid = feature_id(fx + dx, fy + dy)
            if nid < 0 or nid in attempted or nid in candidates:
                continue
            preds, srcs = [], []
            for ex, ey in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                src = feature_id(fx + dx - ex, fy + dy - ey)
                if src in accepted_H:
                    preds.append(normalise(accepted_H[src] @ shift_q(ex, ey)))
                    srcs.append(src)
            candidates[nid], sources[nid] = preds, srcs
    ids = sorted(candidates)
    return ids, [np.mean(candidates[i], axis=0) for i in ids], [sources[i] for i in ids]


def psf_hint(accepted_psf: dict[int, np.ndarray], sources: list[list[int]], size: int,
              settings: GrowSettings) -> np.ndarray | None:
    """``(B, size, size)`` mean re-centred PSF of the accepted blocks that predicted each block
    of a front (padded or cropped, centred, to ``size``), or None when hints are off
    (:attr:`GrowSettings.psf_hints`) or some block has no source (the ring)."""
    if not settings.psf_hints or not sources or not all(sources):
        return None
    return np.stack([np.mean([resize_kernels(accepted_psf[fid], size) for fid in srcs], axis=0)
                     for srcs in sources])
