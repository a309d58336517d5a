"""Region growing: solve blocks breadth-first from the seed, front by front.

The first front is the ring of features around the tag, predicted from the seed homography.
Every accepted block predicts its 4-neighbours (the pattern is periodic: the neighbour at
``(fx + dx, fy + dy)`` has ``H' = H T_q(2 dx, 2 dy)``, one square being 2 block units), averaged
over all accepted neighbours of a candidate. Each front is solved as one batch
(:func:`blurcalib.deconv.fit_blocks`). A block that fails (window outside the image, degenerate
homography, not converged, loss too high, PSF truncated, or a jump away from its prediction) is
rejected and seeds nothing. Every decision is reported to an optional callback, so a GUI can draw
the growth live.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from blurcalib.camera import apply_homography
from blurcalib.deconv import BlockFit, DeconvSettings, fit_blocks
from blurcalib.pattern import StarPattern
from blurcalib.results import BlockStatus
from blurcalib.seed import Seed, block_homography, tag_ring_features


@dataclass(frozen=True)
class GrowSettings:
    """Acceptance rules of region growing (the stricter quality filter comes later).

    Attributes:
        max_loss: reject blocks whose mean squared residual exceeds this (grey levels^2).
        max_boundary_energy: reject blocks whose PSF has more than this share of its energy in
            the outer two-pixel ring of the kernel window (the blur does not fit: truncated).
        max_jump: reject blocks whose star centre moved further than this from its prediction
            (in squares; a block that slid onto a neighbouring star).
        max_blocks: stop after this many attempted blocks (safety net).
    """

    max_loss: float = 400.0
    max_boundary_energy: float = 0.3
    max_jump: float = 0.3
    max_blocks: int = 5000


@dataclass(frozen=True)
class GrowthEvent:
    """One block's decision, as reported to the callback.

    Attributes:
        feature_id: the block's feature id.
        fx, fy: its feature coordinates.
        status: accepted or the reason for rejection.
        H: ``(3, 3)`` fitted (or, when not fitted, predicted) block homography.
        psf: ``(K, K)`` fitted PSF (NaN when not fitted).
        loss: grey levels^2 (NaN when not fitted).
        front: index of the growth front (0 for the ring around the tag).
    """

    feature_id: int
    fx: int
    fy: int
    status: BlockStatus
    H: np.ndarray
    psf: np.ndarray
    loss: float
    front: int


@dataclass
class Growth:
    """Result of growing one frame.

    Attributes:
        fit: every attempted block's fit, concatenated over the fronts (``len(fit) == B``).
        feature_id: ``(B,)`` feature ids in the order of ``fit``.
        status: ``B`` statuses after the growth rules (``fit.status`` refined).
        front: ``(B,)`` growth front of each block.
        predicted: ``(B, 3, 3)`` the predictions the fits started from.
    """

    fit: BlockFit
    feature_id: np.ndarray
    status: list[BlockStatus]
    front: np.ndarray
    predicted: np.ndarray
    events: list[GrowthEvent] = field(default_factory=list)

    @property
    def accepted(self) -> np.ndarray:
        """``(B,)`` bool, blocks accepted by the growth."""
        return np.array([s is BlockStatus.ACCEPTED for s in self.status], dtype=bool)


def _shift_q(dx: int, dy: int) -> np.ndarray:
    return np.array([[1.0, 0.0, 2.0 * dx], [0.0, 1.0, 2.0 * dy], [0.0, 0.0, 1.0]])


def _normalise(H: np.ndarray) -> np.ndarray:
    return H / H[..., 2:3, 2:3]


def _concat_fits(fits: list[BlockFit]) -> BlockFit:
    first = fits[0]
    values = {}
    for name in first.__dataclass_fields__:
        items = [getattr(f, name) for f in fits]
        if name == "status":
            values[name] = tuple(s for f in fits for s in f.status)
        elif isinstance(items[0], np.ndarray):
            values[name] = np.concatenate(items, axis=0)
        else:
            values[name] = items[0]
    return BlockFit(**values)


def grow(image: np.ndarray, pattern: StarPattern, seed: Seed,
         deconv: DeconvSettings | None = None, settings: GrowSettings | None = None,
         on_event: Callable[[GrowthEvent], None] | None = None,
         should_stop: Callable[[], bool] | None = None) -> Growth | None:
    """Grow from ``seed`` over the frame ``image`` ``(H, W)`` (grey levels).

    Args:
        image: the frame.
        pattern: the target.
        seed: where the target is (:func:`blurcalib.seed.seed_frame`).
        deconv: block solver settings.
        settings: acceptance rules.
        on_event: called once per attempted block, in order, as fronts finish.
        should_stop: polled between fronts; growth ends early when it returns True.
    Returns:
        The growth, or None when not a single block could be attempted.
    """
    deconv = deconv or DeconvSettings()
    settings = settings or GrowSettings()
    h, w = image.shape
    N = pattern.num_star_segments
    attempted: dict[int, int] = {}  # feature id -> row in the concatenated results
    accepted_H: dict[int, np.ndarray] = {}
    fits: list[BlockFit] = []
    ids_all: list[int] = []
    status_all: list[BlockStatus] = []
    front_all: list[int] = []
    predicted_all: list[np.ndarray] = []
    events: list[GrowthEvent] = []

    ring = tag_ring_features(pattern) if seed.source == "tag" else pattern.features
    ring_ids = pattern.feature_ids(ring[:, 0], ring[:, 1])
    H_ring = block_homography(seed.H_feature, ring[:, 0], ring[:, 1])
    if seed.source == "given":
        # Without a tag, start from the block nearest to the image centre that lies inside.
        centres = apply_homography(H_ring, np.zeros((len(ring), 1, 2)))[:, 0]
        inside = (centres[:, 0] > 0) & (centres[:, 0] < w - 1) & (centres[:, 1] > 0) \
            & (centres[:, 1] < h - 1)
        if not inside.any():
            return None
        dist = np.linalg.norm(centres - np.array([w / 2, h / 2]), axis=1)
        dist[~inside] = np.inf
        keep = np.argsort(dist)[:4]
        ring_ids, H_ring = ring_ids[keep], H_ring[keep]
    front_ids = [int(i) for i in ring_ids]
    front_H = [_normalise(Hb) for Hb in H_ring]
    front_index = 0
    while front_ids and len(ids_all) < settings.max_blocks:
        if should_stop is not None and should_stop():
            break
        H0 = np.stack(front_H)
        fit = fit_blocks(image, H0, N, deconv)
        fits.append(fit)
        predicted_centre = apply_homography(H0, np.zeros((len(H0), 1, 2)))[:, 0]
        fitted_centre = fit.centre
        square_px = np.sqrt(np.abs(np.linalg.det(H0[:, :2, :2]))) * 2.0
        newly_accepted = []
        for k, fid in enumerate(front_ids):
            status = fit.status[k]
            if status is BlockStatus.ACCEPTED:
                jump = np.linalg.norm(fitted_centre[k] - predicted_centre[k]) / square_px[k]
                if not np.isfinite(fit.loss[k]) or fit.loss[k] > settings.max_loss:
                    status = BlockStatus.HIGH_LOSS
                elif fit.boundary_energy[k] > settings.max_boundary_energy:
                    status = BlockStatus.PSF_TRUNCATED
                elif not np.isfinite(jump) or jump > settings.max_jump:
                    status = BlockStatus.NOT_CONVERGED
            attempted[fid] = len(ids_all)
            ids_all.append(fid)
            status_all.append(status)
            front_all.append(front_index)
            predicted_all.append(H0[k])
            if status is BlockStatus.ACCEPTED:
                accepted_H[fid] = _normalise(fit.H[k])
                newly_accepted.append(fid)
            fx, fy = (int(v) for v in pattern.features[fid])
            event = GrowthEvent(fid, fx, fy, status,
                                fit.H[k] if status is not BlockStatus.OUTSIDE_IMAGE else H0[k],
                                fit.psf[k], float(fit.loss[k]), front_index)
            events.append(event)
            if on_event is not None:
                on_event(event)
        front_ids, front_H = _next_front(pattern, accepted_H, attempted, newly_accepted)
        front_index += 1
    if not fits:
        return None
    return Growth(_concat_fits(fits), np.array(ids_all, dtype=np.int64), status_all,
                  np.array(front_all, dtype=np.int64), np.stack(predicted_all), events)


def _next_front(pattern: StarPattern, accepted_H: dict[int, np.ndarray],
                attempted: dict[int, int], new_ids: list[int]
                ) -> tuple[list[int], list[np.ndarray]]:
    """Unattempted valid neighbours of the newly accepted blocks, with averaged predictions."""
    candidates: dict[int, list[np.ndarray]] = {}
    for fid in new_ids:
        fx, fy = (int(v) for v in pattern.features[fid])
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nid = int(pattern.feature_ids(fx + dx, fy + dy))
            if nid < 0 or nid in attempted or nid in candidates:
                continue
            preds = []
            for ex, ey in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                src = int(pattern.feature_ids(fx + dx - ex, fy + dy - ey))
                if src in accepted_H:
                    preds.append(_normalise(accepted_H[src] @ _shift_q(ex, ey)))
            candidates[nid] = preds
    ids = sorted(candidates)
    return ids, [np.mean(candidates[i], axis=0) for i in ids]
