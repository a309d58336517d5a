"""The growth's judgement of its blocks: the acceptance rules on a front's fits and, in heavily
blurred frames, the agreement of each block with its neighbours.

Heavily blurred frames (blur extent above
:attr:`blurcalib.growth.settings.GrowSettings.heavy_above_extent_px`, 18 px, in the front that
made the window adapt, read in the adapted window) are checked for blocks that settled px off
at a normal loss (a long PSF shifted in its window), which the loss, boundary energy and jump
limit do not see and whose predictions drag their neighbours along in chains: every front's
blocks must lie within :attr:`~blurcalib.growth.settings.GrowSettings.max_inconsistency_px`
(1 px) of the homography of the 12 blocks accepted before them nearest in the pattern
(:func:`inconsistent`; the ring is judged by the rest of the ring, :func:`off_neighbours`), and
once the growth ends every block is judged again by its neighbours on all sides
(:func:`judge_again`); the blocks this cuts off from the earliest front are marked
disconnected. Sharp frames and frames with little blur are never judged, so their features are
the same as without the check.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

from blurcalib.deconv.result import BlockFit
from blurcalib.geometry.homography import apply_homography, homography_centre, homography_scale
from blurcalib.growth.ledger import Growth, GrowthEvent, GrowthLedger
from blurcalib.growth.quality import connected_blocks
from blurcalib.growth.settings import GrowSettings
from blurcalib.io.results import BlockStatus
from blurcalib.target.pattern import StarPattern


def judge_front(fit: BlockFit, H0: np.ndarray, settings: GrowSettings, off: np.ndarray,
                max_loss: float | None = None) -> list[BlockStatus]:
    """The growth's rules on a front's fits ``fit`` started from ``H0 (B, 3, 3)``: a fitted block
    is rejected for a loss above ``max_loss`` (default :attr:`GrowSettings.max_loss`), boundary
    energy above :attr:`GrowSettings.max_boundary_energy`, a centre more than
    :attr:`GrowSettings.max_jump` squares (the side at the predicted centre,
    :func:`blurcalib.geometry.homography.homography_scale`) from its prediction, or ``off (B,)`` (inconsistent
    with its neighbours)."""
    limit = settings.max_loss if max_loss is None else max_loss
    jump = np.linalg.norm(fit.centre - homography_centre(H0), axis=1) / (2.0 * homography_scale(H0))
    out = []
    for k, status in enumerate(fit.status):
        if status is BlockStatus.ACCEPTED:
            if not np.isfinite(fit.loss[k]) or fit.loss[k] > limit:
                status = BlockStatus.HIGH_LOSS
            elif fit.boundary_energy[k] > settings.max_boundary_energy:
                status = BlockStatus.PSF_TRUNCATED
            elif not np.isfinite(jump[k]) or jump[k] > settings.max_jump or off[k]:
                status = BlockStatus.NOT_CONVERGED
        out.append(status)
    return out


def inconsistent(features: np.ndarray, centres: np.ndarray, ref_features: np.ndarray,
                 ref_centres: np.ndarray, neighbours: int, tol_px: float, min_points: int = 10,
                 min_inliers: int = 6) -> np.ndarray:
    """``(B,)`` bool: blocks whose star centre disagrees with the accepted blocks near them.

    For block ``b`` at integer feature coordinates ``features[b] (2,)`` with star centre
    ``centres[b] (2,)`` px, the ``neighbours`` reference blocks nearest to it in the pattern
    (itself excluded) give a homography feature coordinates -> px (RANSAC, ``tol_px / 2``); the
    block is inconsistent when its centre is more than ``tol_px`` from that homography's
    prediction. Blocks with fewer than ``min_points`` references (a homography extrapolated from
    a thin strip of blocks is no judge; docs/decisions/consistency-check.md), fewer than
    ``min_inliers`` inliers, or references
    (nearly) on a line, are not judged. Over the few squares the neighbours span, lens
    distortion is far below a pixel; a block that settled with its long PSF shifted in the
    window (centre px off at a normal loss) is not.

    Args:
        features: ``(B, 2)`` int feature coordinates of the blocks to judge.
        centres: ``(B, 2)`` px their star centres.
        ref_features: ``(R, 2)`` int feature coordinates of accepted blocks.
        ref_centres: ``(R, 2)`` px their star centres.
        neighbours: reference blocks per judgement.
        tol_px: largest disagreement (px).
        min_points: fewest references for a judgement.
        min_inliers: fewest RANSAC inliers among them.
    """
    finite = np.all(np.isfinite(centres), axis=1)
    bad = np.zeros(len(features), dtype=bool)
    homographies = neighbour_homographies(features[finite], ref_features, ref_centres, neighbours,
                                          cv2.RANSAC, tol_px / 2, min_points, min_inliers)
    for b, H in zip(np.flatnonzero(finite), homographies, strict=True):
        if H is not None:
            p = apply_homography(H, features[b][None].astype(np.float64))[0]
            bad[b] = bool(np.linalg.norm(p - centres[b]) > tol_px)
    return bad


def neighbour_homographies(features: np.ndarray, ref_features: np.ndarray, ref_centres: np.ndarray,
                           neighbours: int, method: int, threshold_px: float, min_points: int = 10,
                           min_inliers: int = 6) -> list[np.ndarray | None]:
    """Per block at integer feature coordinates ``features (B, 2)``: the homography feature
    coordinates -> px (``cv2.findHomography`` with ``method`` and ``threshold_px``) of the
    ``neighbours`` reference blocks nearest it in the pattern (``ref_features (R, 2)`` at star
    centres ``ref_centres (R, 2)`` px; the block itself excluded), or None with fewer than
    ``min_points`` references, references (nearly) on a line, or fewer than ``min_inliers``
    inliers (:func:`inconsistent`'s judges, :func:`blurcalib.growth.field.field_growth`'s predictions)."""
    out: list[np.ndarray | None] = [None] * len(features)
    if len(ref_features) < min_points:
        return out
    ref_f = ref_features.astype(np.float64)
    for b in range(len(features)):
        d = np.linalg.norm(ref_f - features[b], axis=1)
        d[d == 0] = np.inf
        near = np.argsort(d, kind="stable")[:neighbours]
        near = near[np.isfinite(d[near])]
        if len(near) < min_points:
            continue
        src = ref_f[near]
        spread = np.linalg.svd(src - src.mean(axis=0), compute_uv=False)[-1] / math.sqrt(len(src))
        if spread < 0.5:
            continue
        H, inliers = cv2.findHomography(src, ref_centres[near].astype(np.float64), method, threshold_px)
        if H is not None and int(inliers.sum()) >= min_inliers:
            out[b] = H
    return out


def off_neighbours(pattern: StarPattern, front_ids: list[int], fit: BlockFit,
                   accepted_H: dict[int, np.ndarray], settings: GrowSettings) -> np.ndarray:
    """``(B,)`` bool: blocks of a front (feature ids ``front_ids``, fitted as ``fit``) that
    disagree with the blocks accepted before them (``accepted_H``, feature id -> ``(3, 3)``;
    :func:`inconsistent`); with none accepted yet (the ring), with the rest of the front."""
    front_f = pattern.features[np.asarray(front_ids)]
    if accepted_H:
        ref = np.fromiter(accepted_H, dtype=np.int64, count=len(accepted_H))
        ref_f = pattern.features[ref]
        ref_c = homography_centre(np.stack(list(accepted_H.values())))
    else:
        fitted = np.array([st is BlockStatus.ACCEPTED for st in fit.status], dtype=bool)
        ref_f, ref_c = front_f[fitted], fit.centre[fitted]
    return inconsistent(front_f, fit.centre, ref_f, ref_c, settings.consistency_neighbours,
                        settings.max_inconsistency_px)


def judge_again(pattern: StarPattern, growth: Growth, settings: GrowSettings,
                on_event: Callable[[GrowthEvent], None] | None = None) -> Growth:
    """Once grown, judge every accepted block by its neighbours (:func:`inconsistent`) and mark
    the accepted blocks cut off from the earliest front ``disconnected``; an event for every
    change. Returns the growth with the new statuses."""
    ledger = GrowthLedger(pattern, on_event, growth)
    ids, fit = growth.feature_id, growth.fit
    ok = np.flatnonzero(growth.accepted)
    f = pattern.features[ids[ok]]
    off = ok[inconsistent(f, fit.centre[ok], f, fit.centre[ok],
                          settings.consistency_neighbours, settings.max_inconsistency_px)]
    for k in off:
        ledger.status[k] = BlockStatus.NOT_CONVERGED
    cut = cut_off(pattern, ids, growth.front, ledger.status)
    for k in cut:
        ledger.status[k] = BlockStatus.DISCONNECTED
    for k in np.concatenate([off, cut]).astype(np.int64):
        ledger.emit(int(k), fit, int(k))
    return ledger.growth(growth.psf_field)


def cut_off(pattern: StarPattern, ids: np.ndarray, front: np.ndarray,
             status: list[BlockStatus]) -> np.ndarray:
    """Rows of accepted blocks no longer 4-connected to the accepted blocks of the earliest
    front that keeps any (after the final check removed blocks between them; the pipeline's
    block filter keeps one connected component, which could otherwise be a small island)."""
    accepted = np.array([st is BlockStatus.ACCEPTED for st in status], dtype=bool)
    if not accepted.any():
        return np.zeros(0, dtype=np.int64)
    f = pattern.features[ids]
    first = np.flatnonzero(accepted & (front == front[accepted].min()))
    return np.flatnonzero(accepted & ~connected_blocks(f[:, 0], f[:, 1], accepted, first.tolist()))
