"""Region growing: solve blocks breadth-first from the seed, front by front.

The first front is the ring of features around the tag, predicted from the seed homography. Under
heavy blur the tag's corners (and so that prediction) are off by several px, and a block fitted
from a poor start can settle with its long PSF partly outside the window, its centre off by a third
of a square at a low loss; so the ring is fitted twice: the seed homography is re-estimated from
the first fit's star centres (RANSAC) and the ring re-fitted from its predictions
(:func:`refine_ring`).
Every accepted block predicts its 4-neighbours (the pattern is periodic: the neighbour at
``(fx + dx, fy + dy)`` has ``H' = H T_q(2 dx, 2 dy)``, one square being 2 block units), averaged
over all accepted neighbours of a candidate. Each front is solved as one batch
(:func:`blurcalib.deconv.blocks.fit_blocks`). A block that fails (window outside the image, degenerate
homography, not converged, loss too high, PSF truncated, or a jump away from its prediction) is
rejected and seeds nothing. Every decision is reported to an optional callback, so a GUI can draw
the growth live.

The PSF window fits the blur. A front is solved with the window chosen from the previous front's
PSFs (:func:`choose_kernel_size`: about 1.5 x the blur extent ``sqrt(12) sigma_major``, the length
of a straight blur with that second moment; odd, at least the configured
:attr:`DeconvSettings.kernel_size`, at most :attr:`GrowSettings.max_kernel_size`). A block whose
PSF reaches the window's border (boundary energy above :attr:`GrowSettings.refit_boundary_energy`)
is re-fitted from the same prediction with a larger window, up to the cap, rather than dropped.
All of this only in frames whose tag ring shows more than about 18 px of blur
(:func:`needs_adaptive_window`), or from the first later front whose PSFs reach the window's
border (median boundary energy above :attr:`GrowSettings.refit_boundary_energy`: the blur grows
away from the tag); below, the configured window is kept, measured best there (a later front's
extent alone is no signal: the 6 frames of 4-15 px blur of ``scripts/bench_yield.py`` read 18.4 px
at most, and one of them lost accuracy with the larger window, 0.029 -> 0.037 px). Kernels of one
growth are zero-padded (centred) to its largest window, which leaves them unchanged as convolution
kernels. The block model's latent pattern is the periodic star field, so pixels that see a tag
through the blur are left out of every block's loss (:func:`tag_mask`, :func:`pixel_mask`): those
nearer to it than the kernel radius, or in a heavily blurred frame with the adaptive window, those
within the blur's footprint of it (:func:`blur_footprint`, a segment along the blur: a disk of a
35 px window leaves the ring of a 22 px blur on 27 px squares almost no pixels).

Heavily blurred frames (blur extent above :attr:`GrowSettings.heavy_above_extent_px`, 18 px, in
the front that made the window adapt, measured in the adapted window) are also checked for blocks
that settled px off at a normal loss (a long PSF shifted in its window), which the loss, boundary
energy and jump limit do not see and whose predictions drag their neighbours along in chains:
every front's blocks must lie within :attr:`GrowSettings.max_inconsistency_px` (1 px) of the
homography of the 12 blocks accepted before them nearest in the pattern (:func:`inconsistent`; the
ring is judged by the rest of the ring), and once the growth ends every block is judged again by
its neighbours on all sides; the blocks this cuts off from the earliest front are marked
disconnected. Sharp frames and frames with little blur are never judged, so their features are the
same as without the check.

Once grown, the accepted blocks of a frame whose window adapted are fitted once more with the loss
over 1.5 x their square (:func:`final_fit`), started from their fit: the centre sees 2.25 x the
pixels (12-25 px of blur: median 0.037 -> 0.030 px). Frames whose window did not adapt skip it by
default (:attr:`GrowSettings.final_fit_frames`): there it costs about 1 s per frame for a smaller
gain.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal, get_args

import cv2
import numpy as np

from blurcalib.deconv.blocks import BlockFit, DeconvSettings, fit_blocks
from blurcalib.extract.noise import NoiseModel
from blurcalib.extract.quality import connected_blocks, noise_scale
from blurcalib.geometry.homography import apply_homography, homography_centre, homography_scale
from blurcalib.growth.seed import Seed, block_homography, tag_ring_features
from blurcalib.io.results import BlockStatus
from blurcalib.psf.field import FieldSettings, PathField, constant_field, fit_path_field
from blurcalib.psf.kernel import blur_extent, blur_per_square, psf_moments
from blurcalib.target.pattern import StarPattern

FinalFitFrames = Literal["adaptive", "all", "none"]
"""Which frames get :func:`final_fit` (:attr:`GrowSettings.final_fit_frames`)."""


@dataclass(frozen=True)
class GrowSettings:
    """Acceptance rules of region growing (the stricter quality filter comes later).

    Attributes:
        max_loss: reject blocks whose mean squared residual exceeds this (grey levels^2; given
            the frame's noise, :func:`grow` raises it in proportion to the noise variance above
            :data:`blurcalib.extract.quality.REFERENCE_NOISE_VAR`,
            :func:`blurcalib.extract.quality.noise_scale`).
        max_boundary_energy: reject blocks whose PSF has more than this share of its energy in
            the outer two-pixel ring of the kernel window (the blur does not fit: truncated).
        max_jump: reject blocks whose star centre moved further than this from its prediction
            (in squares; a block that slid onto a neighbouring star).
        max_blocks: stop after this many attempted blocks (safety net).
        max_kernel_size: largest PSF window (px, odd); a value not above the deconvolution's
            ``kernel_size`` keeps that window fixed.
        kernel_per_extent: window side per px of blur extent.
        adapt_above_extent_px: the window adapts only in frames whose tag ring shows more blur
            than this (90th percentile of ``sqrt(12) sigma_major``, px) or whose ring PSFs
            reach the border (median boundary energy above ``refit_boundary_energy``); below,
            the configured window is kept (the measured best for up to 15 px of blur).
        refit_boundary_energy: blocks whose PSF has more than this share of its energy in the
            window's outer two-pixel ring are re-fitted with a larger window.
        max_inconsistency_px: in heavily blurred frames only (``heavy_above_extent_px``),
            reject blocks whose star centre is further than this (px) from the homography of
            the previously accepted blocks nearest to it (:func:`inconsistent`).
        consistency_neighbours: that many previously accepted blocks per judgement.
        heavy_above_extent_px: frames whose tag ring shows a blur extent above this (px, 90th
            percentile of ``sqrt(12) sigma_major`` of the ring's fit in the adapted window: a
            truncated PSF reads shorter) are heavily blurred: their blocks are checked against
            their neighbours, and with the adaptive window the tag's mask follows the blur
            (:func:`blur_footprint`).
        psf_hints: blocks after the tag ring start from the mean PSF of the accepted neighbours
            that predicted them (:func:`blurcalib.deconv.blocks.fit_blocks`'s ``psf_hint``: no coarse
            kernel, fewer solver stages).
        retry_below_blur_per_square: a block that its hinted fit leaves not converged, whose hint
            shows a blur per square (:func:`blurcalib.psf.kernel.blur_per_square`) below this, is
            accepted after a last LM step of less than ``hinted_converge_px``, else fitted again
            with the full schedule (:func:`fit_hinted`); 0: such blocks are fitted again only
            when their front accepts no block.
        hinted_converge_px: the convergence tolerance of those blocks (px; the solver's own is
            :attr:`blurcalib.deconv.blocks.DeconvSettings.converge_tol_px`).
        final_extent: loss area of the final fit (:func:`final_fit`), the square grown about
            its star centre by this factor (:attr:`DeconvSettings.loss_extent`); 1 skips it.
        final_fit_frames: which frames get the final fit: ``"adaptive"`` (those whose window
            adapted to the blur, the default), ``"all"`` or ``"none"``.
        final_max_shift_px: a final fit whose star centre moved further than this (px) from
            the growth's fit is not kept.
        psf_field: in frames whose window adapted, or whose blur is long for their squares
            (``field_above_blur_per_square``), fit the frame's field of motion-path PSFs and
            fit and grow on with it (:func:`field_growth`) instead of the final fit.
        field_above_blur_per_square: frames whose fitted blocks' median blur over square side
            (:func:`blurcalib.psf.kernel.blur_per_square`) reaches this get the field growth even when
            their window did not adapt (small squares, moderate blur).
        field_min_blocks: fewest accepted blocks to fit a field from.
        field_blocks: most blocks in the field's fit (spread over the accepted ones).
        field_loss_factor: a block fitted with the field is rejected when its loss exceeds
            this multiple of the median loss of the accepted blocks' field fits.
        field_max_kernel: largest window of a field PSF (px, odd).
    """

    max_loss: float = 400.0
    max_boundary_energy: float = 0.3
    max_jump: float = 0.3
    max_blocks: int = 5000
    max_kernel_size: int = 41
    kernel_per_extent: float = 1.5
    refit_boundary_energy: float = 0.1
    adapt_above_extent_px: float = 18.0
    max_inconsistency_px: float = 1.0
    consistency_neighbours: int = 12
    heavy_above_extent_px: float = 18.0
    psf_hints: bool = True
    retry_below_blur_per_square: float = 0.5
    hinted_converge_px: float = 0.15
    final_extent: float = 1.5
    final_fit_frames: FinalFitFrames = "adaptive"
    final_max_shift_px: float = 0.5
    psf_field: bool = True
    field_above_blur_per_square: float = 0.6
    field_min_blocks: int = 8
    field_blocks: int = 24
    field_loss_factor: float = 3.0
    field_max_kernel: int = 61

    def __post_init__(self) -> None:
        if self.final_fit_frames not in get_args(FinalFitFrames):
            raise ValueError(f"final_fit_frames must be one of {get_args(FinalFitFrames)}, got "
                             f"{self.final_fit_frames!r}")
        if not self.final_extent >= 1.0:
            raise ValueError(f"final_extent must be >= 1, got {self.final_extent}")
        for name in ("max_kernel_size", "field_max_kernel"):
            if getattr(self, name) < 3 or getattr(self, name) % 2 == 0:
                raise ValueError(f"{name} must be odd and >= 3, got {getattr(self, name)}")
        if self.field_min_blocks < 1 or self.field_blocks < self.field_min_blocks:
            raise ValueError("need 1 <= field_min_blocks <= field_blocks")
        if self.kernel_per_extent <= 0:
            raise ValueError(f"kernel_per_extent must be positive, got {self.kernel_per_extent}")


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
        events: every decision, in order (as reported to the callback).
        psf_field: the frame's path-PSF field when the growth used one (:func:`field_growth`).
    """

    fit: BlockFit
    feature_id: np.ndarray
    status: list[BlockStatus]
    front: np.ndarray
    predicted: np.ndarray
    events: list[GrowthEvent] = field(default_factory=list)
    psf_field: PathField | None = None

    @property
    def accepted(self) -> np.ndarray:
        """``(B,)`` bool, blocks accepted by the growth."""
        return np.array([s is BlockStatus.ACCEPTED for s in self.status], dtype=bool)


def _shift_q(dx: int, dy: int) -> np.ndarray:
    return np.array([[1.0, 0.0, 2.0 * dx], [0.0, 1.0, 2.0 * dy], [0.0, 0.0, 1.0]])


def _normalise(H: np.ndarray) -> np.ndarray:
    return H / H[..., 2:3, 2:3]


def choose_kernel_size(sigma_major: np.ndarray | float, smallest: int, largest: int,
                       per_extent: float = 1.5) -> int:
    """PSF window side for blurs of second moment ``sigma_major`` (px).

    The blur extent is ``e = sqrt(12) sigma_major`` (:func:`blurcalib.psf.kernel.blur_extent`); the
    window is ``ceil(per_extent e)`` rounded up to odd, within ``[smallest, largest]``.
    ``sigma_major`` may be several values (their 90th percentile is used); none finite gives
    ``smallest``.
    """
    s = np.asarray(sigma_major, dtype=np.float64).ravel()
    s = s[np.isfinite(s)]
    if s.size == 0:
        return smallest
    k = math.ceil(per_extent * blur_extent(float(np.percentile(s, 90))))
    k += 1 - k % 2
    return int(max(min(k, largest), smallest))


def _resize_kernels(k: np.ndarray, size: int) -> np.ndarray:
    """``(..., K, K)`` kernels zero-padded or cropped (centred) to ``(..., size, size)``."""
    p = (size - k.shape[-1]) // 2
    if p >= 0:
        return np.pad(k, [(0, 0)] * (k.ndim - 2) + [(p, p), (p, p)]) if p else k
    return k[..., -p:k.shape[-1] + p, -p:k.shape[-1] + p]


def _concat_fits(fits: list[BlockFit]) -> BlockFit:
    """Rows of several fits in order; kernels padded to the largest window."""
    size = max(f.settings.kernel_size for f in fits)
    first = max(fits, key=lambda f: f.settings.kernel_size)
    values = {}
    for name in first.__dataclass_fields__:
        items = [getattr(f, name) for f in fits]
        if name == "status":
            values[name] = tuple(s for f in fits for s in f.status)
        elif name in ("psf", "psf_fit"):
            values[name] = np.concatenate([_resize_kernels(k, size) for k in items], axis=0)
        elif isinstance(items[0], np.ndarray):
            values[name] = np.concatenate(items, axis=0)
        else:
            values[name] = getattr(first, name)
    return BlockFit(**values)


def _take(fit: BlockFit, rows: np.ndarray) -> BlockFit:
    """The rows ``rows`` of a fit."""
    values = {}
    for name in fit.__dataclass_fields__:
        v = getattr(fit, name)
        if name == "status":
            values[name] = tuple(v[i] for i in rows)
        elif isinstance(v, np.ndarray):
            values[name] = v[rows]
        else:
            values[name] = v
    return BlockFit(**values)


def _too_small(fit: BlockFit, size: np.ndarray, settings: GrowSettings) -> np.ndarray:
    """``(B,)`` bool: fitted blocks whose window (``size (B,)`` px) is too small for their PSF:
    it reaches the window's border, or it touches the border (boundary energy above 0.03; the
    solver zeroes kernel entries below 15 % of the peak, so a PSF that fits leaves the ring
    empty) while its extent asks for a larger window (:func:`choose_kernel_size`)."""
    fitted = np.array([st in (BlockStatus.ACCEPTED, BlockStatus.NOT_CONVERGED)
                       for st in fit.status], dtype=bool)
    wanted = np.array([choose_kernel_size(s, k, settings.max_kernel_size,
                                          settings.kernel_per_extent)
                       for s, k in zip(fit.sigma_major, size, strict=True)])
    be = np.where(np.isfinite(fit.boundary_energy), fit.boundary_energy, 0.0)
    return fitted & (size < settings.max_kernel_size) & (
        (be > settings.refit_boundary_energy) | ((be > 0.03) & (wanted > size)))


def _front_blur(fit: BlockFit) -> tuple[float, float]:
    """``(extent px, boundary energy)`` of a front's fitted PSFs: the 90th percentile of
    ``sqrt(12) sigma_major`` and the median boundary energy (NaN when none was fitted)."""
    ok = np.array([st is BlockStatus.ACCEPTED for st in fit.status], dtype=bool)
    ok |= np.isfinite(fit.boundary_energy)
    if not ok.any() or not np.isfinite(fit.sigma_major[ok]).any():
        return float("nan"), float("nan")
    return (blur_extent(float(np.nanpercentile(fit.sigma_major[ok], 90))),
            float(np.nanmedian(fit.boundary_energy[ok])))


def needs_adaptive_window(fit: BlockFit, settings: GrowSettings) -> bool:
    """Whether the first front's fit ``fit`` shows more blur than the configured window suits
    (see :attr:`GrowSettings.adapt_above_extent_px`)."""
    extent, be = _front_blur(fit)
    return bool(extent > settings.adapt_above_extent_px or be > settings.refit_boundary_energy)


def inconsistent(features: np.ndarray, centres: np.ndarray, ref_features: np.ndarray,
                 ref_centres: np.ndarray, neighbours: int, tol_px: float, min_points: int = 10,
                 min_inliers: int = 6) -> np.ndarray:
    """``(B,)`` bool: blocks whose star centre disagrees with the accepted blocks near them.

    For block ``b`` at integer feature coordinates ``features[b] (2,)`` with star centre
    ``centres[b] (2,)`` px, the ``neighbours`` reference blocks nearest to it in the pattern
    (itself excluded) give a homography feature coordinates -> px (RANSAC, ``tol_px / 2``); the
    block is inconsistent when its centre is more than ``tol_px`` from that homography's
    prediction. Blocks with fewer than ``min_points`` references (a homography extrapolated from
    a thin strip of blocks is no judge: measured, a frame whose growth crept out of a ring of 4
    blocks lost 96 of its 102 blocks with 6), fewer than ``min_inliers`` inliers, or references
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
    inliers (:func:`inconsistent`'s judges, :func:`field_growth`'s predictions)."""
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


def tag_mask(pattern: StarPattern, H_feature: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` uint8, 1 on the tags' areas (feature boxes) seen through ``H_feature``."""
    mask = np.zeros(shape, dtype=np.uint8)
    for tag in pattern.apriltags:
        x0, y0, x1, y1 = tag.feature_box
        box = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
        px = cv2.perspectiveTransform(box[None], np.asarray(H_feature, dtype=np.float64))[0]
        if np.all(np.isfinite(px)) and np.abs(px).max() < 1e6:
            cv2.fillConvexPoly(mask, np.round(px).astype(np.int32), 1)
    return mask


def blur_footprint(fit: BlockFit, extent_px: float) -> np.ndarray | None:
    """``(F, F)`` uint8 footprint of the frame's blur, from the ring's fit ``fit``: a segment of
    length ``extent_px`` along the PSFs' major axis (their orientations averaged as doubled
    angles), ``2 + 2 sigma_minor`` px wide on each side (median ``sigma_minor``) plus 2 px of seed
    error at its ends. A pixel sees a tag through the blur only when it lies within the tag
    dilated by this footprint; None when no PSF was fitted."""
    ok = np.isfinite(fit.orientation) & np.isfinite(fit.sigma_minor)
    if not ok.any() or not math.isfinite(extent_px):
        return None
    theta = 0.5 * float(np.angle(np.mean(np.exp(2j * fit.orientation[ok]))))
    half_width = 2 + math.ceil(2.0 * float(np.median(fit.sigma_minor[ok])))
    half_length = math.ceil(extent_px / 2.0) + 2
    r = half_length + half_width
    footprint = np.zeros((2 * r + 1, 2 * r + 1), dtype=np.uint8)
    dx, dy = half_length * math.cos(theta), half_length * math.sin(theta)
    cv2.line(footprint, (round(r - dx), round(r - dy)), (round(r + dx), round(r + dy)), 1,
             thickness=2 * half_width + 1)
    return footprint


def pixel_mask(tag: np.ndarray | None, kernel_size: int, footprint: np.ndarray | None = None
                ) -> np.ndarray | None:
    """Pixels usable by blocks fitted with ``kernel_size``: outside the tags dilated by the
    blur's ``footprint`` (:func:`blur_footprint`), or without one further from a tag than the
    kernel radius plus 2 px (seed error)."""
    if tag is None:
        return None
    x, y, w, h = cv2.boundingRect(tag)
    if w == 0:
        return None
    if footprint is None:
        r = kernel_size // 2 + 2
        footprint = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    # dilate the tag's neighbourhood only (the whole frame took ~3 ms per front)
    ry, rx = footprint.shape[0] // 2, footprint.shape[1] // 2
    y0, y1 = max(y - ry, 0), min(y + h + ry, tag.shape[0])
    x0, x1 = max(x - rx, 0), min(x + w + rx, tag.shape[1])
    ok = np.ones(tag.shape, dtype=bool)
    ok[y0:y1, x0:x1] = cv2.dilate(tag[y0:y1, x0:x1], footprint, borderType=cv2.BORDER_CONSTANT,
                                  borderValue=0) == 0
    return ok


def fit_front(image: np.ndarray, H0: np.ndarray, num_segments: int, deconv: DeconvSettings,
              settings: GrowSettings, kernel_size: int, tag: np.ndarray | None = None,
              first: BlockFit | None = None, footprint: np.ndarray | None = None,
              psf_hint: np.ndarray | None = None) -> BlockFit:
    """Fit one front's blocks ``H0 (B, 3, 3)`` with a window of ``kernel_size`` px; re-fit those
    whose window is too small for their PSF with larger windows (at least 1.4 x larger each
    time, up to :attr:`GrowSettings.max_kernel_size`), keeping a re-fit when it is accepted with
    no more boundary energy; a block whose re-fit is not kept is not re-fitted again (its
    window is not what fails it). Kernels come back padded to the largest window used. ``tag``
    (:func:`tag_mask`) keeps pixels near the tags out of the fits (within the blur's
    ``footprint`` when given, :func:`pixel_mask`); ``first`` is the fit with ``kernel_size``
    when already done, else it is fitted with ``psf_hint`` (:func:`fit_hinted`; the re-fits in
    larger windows are not hinted)."""
    fit = first if first is not None else fit_hinted(
        image, H0, num_segments, replace(deconv, kernel_size=kernel_size),
        pixel_mask(tag, kernel_size, footprint), psf_hint, settings)
    block_size = np.full(len(H0), kernel_size)
    stuck = np.zeros(len(H0), dtype=bool)
    size = kernel_size
    while size < settings.max_kernel_size:
        redo = np.flatnonzero(_too_small(fit, block_size, settings) & ~stuck)
        if redo.size == 0:
            break
        grown = math.ceil(1.4 * size)
        size = max(choose_kernel_size(fit.sigma_major[redo], size, settings.max_kernel_size,
                                      settings.kernel_per_extent),
                   min(grown + 1 - grown % 2, settings.max_kernel_size))
        refit = fit_blocks(image, H0[redo], num_segments, replace(deconv, kernel_size=size),
                           pixel_mask(tag, size, footprint))
        better = np.array([refit.status[j] is BlockStatus.ACCEPTED
                           and (fit.status[i] is not BlockStatus.ACCEPTED
                                or refit.boundary_energy[j] <= fit.boundary_energy[i])
                           for j, i in enumerate(redo)], dtype=bool)
        stuck[redo[~better]] = True
        if not better.any():
            continue
        fit = _replace_rows(fit, redo[better], refit, np.flatnonzero(better))
        block_size[redo[better]] = size
    return fit


def _replace_rows(fit: BlockFit, rows: np.ndarray, other: BlockFit, other_rows: np.ndarray) -> BlockFit:
    """``fit`` with its rows ``rows`` replaced by the rows ``other_rows`` of ``other`` (kernels
    padded to the larger window)."""
    keep = np.setdiff1d(np.arange(len(fit)), rows)
    merged = _concat_fits([_take(fit, keep), _take(other, other_rows)])
    return _take(merged, np.argsort(np.concatenate([keep, rows]), kind="stable"))


def fit_hinted(image: np.ndarray, H0: np.ndarray, num_segments: int, deconv: DeconvSettings,
               mask: np.ndarray | None, psf_hint: np.ndarray | None,
               settings: GrowSettings | None = None) -> BlockFit:
    """:func:`blurcalib.deconv.blocks.fit_blocks` with ``psf_hint``, then a second look at the blocks it
    leaves not converged:

    * when the front accepts none, all of them are fitted again with the full schedule (no hint)
      and a re-fit is kept where it is accepted: hints from poor neighbours must not end a growth
      that creeps through single blocks;
    * otherwise those whose hint shows a blur short for their square
      (:func:`blurcalib.psf.kernel.blur_per_square` of the hint at ``H0`` below
      :attr:`GrowSettings.retry_below_blur_per_square`) are accepted when their last LM step moved
      the star centre less than :attr:`GrowSettings.hinted_converge_px`, and fitted again with
      the full schedule when it moved more. There the one hinted stage is slow, not wrong: on real
      frames under 5-12 px of blur (``scripts/bench_real_texture.py``, blur per square 0.14-0.40)
      it still moves 0.05-0.15 px at its last step, within 0.15 px of the full schedule's fit.
      Where the blur reaches half the square a block still moving is often px off, and the full
      schedule settles px off too (``scripts/bench_speed.py``: 21 of 47 blocks > 0.5 px off at
      0.56-0.99): those stay not converged.
    """
    s = settings or GrowSettings()
    fit = fit_blocks(image, H0, num_segments, deconv, mask, psf_hint)
    failed = np.array([st is BlockStatus.NOT_CONVERGED for st in fit.status], dtype=bool)
    if psf_hint is None or not failed.any():
        return fit
    if BlockStatus.ACCEPTED in fit.status:
        with np.errstate(invalid="ignore", divide="ignore"):
            failed &= blur_per_square(psf_moments(psf_hint).sigma_major, H0) < s.retry_below_blur_per_square
        settled = failed & fit.converged_within(s.hinted_converge_px)
        if settled.any():
            fit = replace(fit, converged=fit.converged | settled,
                          status=tuple(BlockStatus.ACCEPTED if ok else st
                                       for ok, st in zip(settled, fit.status, strict=True)))
        failed &= ~settled
    redo = np.flatnonzero(failed)
    if redo.size == 0:
        return fit
    refit = fit_blocks(image, H0[redo], num_segments, deconv, mask)
    better = np.flatnonzero([st is BlockStatus.ACCEPTED for st in refit.status])
    return _replace_rows(fit, redo[better], refit, better) if better.size else fit


def final_fit(image: np.ndarray, pattern: StarPattern, ids: np.ndarray, fit: BlockFit,
              accepted: np.ndarray, deconv: DeconvSettings, settings: GrowSettings,
              tag: np.ndarray | None, footprint: np.ndarray | None = None) -> BlockFit:
    """Fit the accepted blocks once more over a larger area, from their growth fit.

    ``eq:deconvolution`` with the loss over ``|q|_inf <= e`` (``e`` =
    :attr:`GrowSettings.final_extent`: the star's square and a band of its neighbours' squares)
    instead of the square alone: the periodic latent pattern and a PSF that varies slowly over
    the image hold there too, and the centre's noise falls with the pixels it sees (measured in
    docs/deconvolution.md). Each block starts from its fitted ``H`` and re-centred PSF (the PSF
    as ``psf_hint``: :attr:`DeconvSettings.hinted_stages` stages) in the window its PSF asks for
    (:func:`choose_kernel_size`, at most the growth's largest). Blocks on the pattern's outer
    rim are left as they are (the grown area would reach the paper beyond the printed stars,
    which the periodic model does not know), as are blocks whose final fit is not accepted by
    the growth's rules or whose centre moved further than :attr:`GrowSettings.final_max_shift_px`.

    Args:
        image: the frame.
        pattern: the target.
        ids: ``(B,)`` feature ids of ``fit``'s rows.
        fit: the growth's fits (kernels padded to its largest window).
        accepted: ``(B,)`` bool, the rows the growth accepted.
        deconv: block solver settings.
        settings: growth rules.
        tag, footprint: as for :func:`pixel_mask`.
    Returns:
        ``fit`` with the kept final fits in place of their rows.
    """
    rows = np.flatnonzero(accepted & _inner(pattern, ids))
    if rows.size == 0 or settings.final_extent <= 1.0:
        return fit
    largest = fit.settings.kernel_size
    sizes = np.array([choose_kernel_size(sm, deconv.kernel_size, largest, settings.kernel_per_extent)
                      for sm in fit.sigma_major[rows]])
    for size in np.unique(sizes):
        sel = rows[sizes == size]
        final = fit_blocks(image, fit.H[sel], pattern.num_star_segments,
                           replace(deconv, kernel_size=int(size), loss_extent=settings.final_extent),
                           pixel_mask(tag, int(size), footprint), _resize_kernels(fit.psf[sel], int(size)))
        shift = np.linalg.norm(final.centre - fit.centre[sel], axis=1)
        keep = np.array([st is BlockStatus.ACCEPTED for st in final.status], dtype=bool)
        keep &= (final.loss <= settings.max_loss) & (final.boundary_energy <= settings.max_boundary_energy)
        keep &= shift < settings.final_max_shift_px
        if keep.any():
            fit = _replace_rows(fit, sel[keep], final, np.flatnonzero(keep))
    return fit


def _inner(pattern: StarPattern, ids: np.ndarray) -> np.ndarray:
    """``(B,)`` bool: features ``ids`` off the pattern's outer rim, whose squares grown by half a
    square (a loss over 1.5 x the square) still show printed stars only."""
    f = pattern.features[ids]
    return (f[:, 0] > 0) & (f[:, 1] > 0) & (f[:, 0] < pattern.squares_x - 2) \
        & (f[:, 1] < pattern.squares_y - 2)


def refine_ring(image: np.ndarray, pattern: StarPattern, ids: list[int], fit: BlockFit,
                deconv: DeconvSettings, settings: GrowSettings, tag: np.ndarray | None,
                adaptive: bool = True, footprint: np.ndarray | None = None
                ) -> tuple[np.ndarray, BlockFit] | None:
    """Re-fit the ring around the tag from the homography of its first fit's star centres.

    Args:
        image: the frame.
        pattern: the target.
        ids: the ring's feature ids (rows of ``fit``).
        fit: the first fit of the ring.
        deconv, settings: as for :func:`fit_front`.
        tag: :func:`tag_mask`.
        adaptive: choose the window from the first fit's PSFs (else the configured one).
        footprint: :func:`blur_footprint` (adaptive only), for :func:`pixel_mask`.
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
    H0 = _normalise(block_homography(H, f[:, 0], f[:, 1]))
    if not adaptive:
        return H0, fit_blocks(image, H0, pattern.num_star_segments, deconv,
                              pixel_mask(tag, deconv.kernel_size))
    size = choose_kernel_size(fit.sigma_major[ok], deconv.kernel_size, settings.max_kernel_size,
                              settings.kernel_per_extent)
    return H0, fit_front(image, H0, pattern.num_star_segments, deconv, settings, size, tag,
                         footprint=footprint)


def grow(image: np.ndarray, pattern: StarPattern, seed: Seed,
         deconv: DeconvSettings | None = None, settings: GrowSettings | None = None,
         on_event: Callable[[GrowthEvent], None] | None = None,
         should_stop: Callable[[], bool] | None = None, noise: NoiseModel | None = None) -> Growth | None:
    """Grow from ``seed`` over the frame ``image`` ``(H, W)`` (grey levels).

    Args:
        image: the frame.
        pattern: the target.
        seed: where the target is (:func:`blurcalib.growth.seed.seed_frame`).
        deconv: block solver settings.
        settings: acceptance rules.
        on_event: called once per attempted block, in order, as fronts finish, and once more
            for a block that the final consistency check of an adaptive frame rejects.
        should_stop: polled between fronts; growth ends early when it returns True.
        noise: the frame's noise (:func:`blurcalib.extract.noise.estimate_noise`): the loss limit
            :attr:`GrowSettings.max_loss` grows with its variance at the frame's level above the
            reference (:func:`blurcalib.extract.quality.noise_scale`); None keeps it as given.
    Returns:
        The growth, or None when not a single block could be attempted.
    """
    deconv = deconv or DeconvSettings()
    settings = settings or GrowSettings()
    if noise is not None:
        scale = float(noise_scale(noise.variance(noise.level)))
        settings = replace(settings, max_loss=settings.max_loss * scale)
    h, w = image.shape
    N = pattern.num_star_segments
    attempted: dict[int, int] = {}  # feature id -> row in the concatenated results
    accepted_H: dict[int, np.ndarray] = {}
    accepted_psf: dict[int, np.ndarray] = {}  # their re-centred PSFs
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
        centres = homography_centre(H_ring)
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
    front_src: list[list[int]] = []  # the accepted blocks that predicted each (none for the ring)
    front_index = 0
    kernel_size = deconv.kernel_size
    tag = tag_mask(pattern, seed.H_feature, (h, w))
    adaptive: bool | None = None  # decided on the first front, or later when a front shows the blur
    heavy = False  # decided with adaptive (heavy_above_extent_px)
    footprint = None  # of the blur, for the tag's mask in adaptive frames
    while front_ids and len(ids_all) < settings.max_blocks:
        if should_stop is not None and should_stop():
            break
        H0 = np.stack(front_H)
        if adaptive is None:
            fit = fit_blocks(image, H0, N, deconv, pixel_mask(tag, deconv.kernel_size))
            adaptive = needs_adaptive_window(fit, settings)
            if adaptive:
                fit = fit_front(image, H0, N, deconv, settings, kernel_size, tag, first=fit)
            # judged with the window that holds the blur: a truncated PSF reads shorter
            heavy = bool(_front_blur(fit)[0] > settings.heavy_above_extent_px)
            if adaptive and heavy:
                extent = max(fit.settings.kernel_size / settings.kernel_per_extent,
                             seed.blur[0] if math.isfinite(seed.blur[0]) else 0.0)
                footprint = blur_footprint(fit, extent)
            if seed.source == "tag":
                refined = refine_ring(image, pattern, front_ids, fit, deconv, settings, tag,
                                      adaptive, footprint)
                if refined is not None:
                    H0, fit = refined
        elif adaptive:
            fit = fit_front(image, H0, N, deconv, settings, kernel_size, tag, footprint=footprint,
                            psf_hint=_psf_hint(accepted_psf, front_src, kernel_size, settings))
        else:
            fit = fit_hinted(image, H0, N, deconv, pixel_mask(tag, deconv.kernel_size),
                             _psf_hint(accepted_psf, front_src, deconv.kernel_size, settings), settings)
            if _front_blur(fit)[1] > settings.refit_boundary_energy:  # the blur outgrew the window
                adaptive = True
                fit = fit_front(image, H0, N, deconv, settings, kernel_size, tag, first=fit)
                heavy = bool(_front_blur(fit)[0] > settings.heavy_above_extent_px)
        fits.append(fit)
        fitted_centre = fit.centre
        newly_accepted, accepted_rows = [], []
        off = np.zeros(len(front_ids), dtype=bool)
        if heavy:
            front_f = pattern.features[np.asarray(front_ids)]
            if accepted_H:
                ref = np.fromiter(accepted_H, dtype=np.int64, count=len(accepted_H))
                ref_f = pattern.features[ref]
                ref_c = homography_centre(np.stack(list(accepted_H.values())))
            else:  # the ring: judged by the rest of the ring
                fitted = np.array([st is BlockStatus.ACCEPTED for st in fit.status], dtype=bool)
                ref_f, ref_c = front_f[fitted], fitted_centre[fitted]
            off = inconsistent(front_f, fitted_centre, ref_f, ref_c,
                               settings.consistency_neighbours, settings.max_inconsistency_px)
        for k, (fid, status) in enumerate(zip(front_ids, judge_front(fit, H0, settings, off), strict=True)):
            attempted[fid] = len(ids_all)
            ids_all.append(fid)
            status_all.append(status)
            front_all.append(front_index)
            predicted_all.append(H0[k])
            if status is BlockStatus.ACCEPTED:
                accepted_H[fid] = _normalise(fit.H[k])
                accepted_psf[fid] = fit.psf[k]
                newly_accepted.append(fid)
                accepted_rows.append(k)
            _emit(events, on_event, pattern, fid, status, fit, k, front_index)
        front_ids, front_H, front_src = _next_front(pattern, accepted_H, attempted, newly_accepted)
        front_index += 1
        if adaptive:
            kernel_size = choose_kernel_size(fit.sigma_major[accepted_rows], deconv.kernel_size,
                                             settings.max_kernel_size, settings.kernel_per_extent)
    if not fits:
        return None
    growth = Growth(_concat_fits(fits), np.array(ids_all, dtype=np.int64), status_all,
                    np.array(front_all, dtype=np.int64), np.stack(predicted_all), events)
    stopped = should_stop is not None and should_stop()
    if not stopped and settings.psf_field and settings.max_kernel_size > deconv.kernel_size and (
            adaptive or _median_blur_per_square(growth.fit) >= settings.field_above_blur_per_square):
        growth = field_growth(image, pattern, growth, deconv, settings, tag, on_event, should_stop)
    if growth.psf_field is None and (settings.final_fit_frames == "all"
                                     or (adaptive and settings.final_fit_frames == "adaptive")):
        growth.fit = final_fit(image, pattern, growth.feature_id, growth.fit, growth.accepted, deconv,
                               settings, tag, footprint)
    if heavy or growth.psf_field is not None:  # every block now has neighbours on all sides: judge again
        _judge_again(pattern, growth, settings, on_event)
    return growth


def _emit(events: list[GrowthEvent], on_event: Callable[[GrowthEvent], None] | None, pattern: StarPattern,
          feature_id: int, status: BlockStatus, fit: BlockFit, k: int, front: int) -> None:
    """Record, and report to ``on_event``, the decision ``status`` on block ``feature_id`` fitted
    as row ``k`` of ``fit`` (a block not fitted keeps its prediction as ``H``) in ``front``."""
    fx, fy = (int(v) for v in pattern.features[feature_id])
    event = GrowthEvent(int(feature_id), fx, fy, status, fit.H[k], fit.psf[k], float(fit.loss[k]), int(front))
    events.append(event)
    if on_event is not None:
        on_event(event)


def _median_blur_per_square(fit: BlockFit) -> float:
    """Median blur over square side (:func:`blurcalib.psf.kernel.blur_per_square`) of the fitted blocks
    (NaN when none was fitted)."""
    ratio = blur_per_square(fit.sigma_major, fit.H)
    return float(np.median(ratio[np.isfinite(ratio)])) if np.isfinite(ratio).any() else math.nan


def _judge_again(pattern: StarPattern, growth: Growth, settings: GrowSettings,
                 on_event: Callable[[GrowthEvent], None] | None) -> None:
    """Once grown, judge every accepted block by its neighbours (:func:`inconsistent`) and mark
    the accepted blocks cut off from the earliest front ``disconnected``; in place, with an event
    for every change."""
    ids, fit, status = growth.feature_id, growth.fit, growth.status
    ok = np.flatnonzero(growth.accepted)
    f = pattern.features[ids[ok]]
    off = ok[inconsistent(f, fit.centre[ok], f, fit.centre[ok],
                          settings.consistency_neighbours, settings.max_inconsistency_px)]
    for k in off:
        status[k] = BlockStatus.NOT_CONVERGED
    cut = _cut_off(pattern, ids, growth.front, status)
    for k in cut:
        status[k] = BlockStatus.DISCONNECTED
    for k in np.concatenate([off, cut]).astype(np.int64):
        _emit(growth.events, on_event, pattern, ids[k], status[k], fit, k, growth.front[k])


def field_degree(xy: np.ndarray, image_size: tuple[int, int], count: int | None = None) -> int:
    """Polynomial degree of a path field fitted from blocks at ``xy (B, 2)`` px (``count`` of
    them, default ``B``): 2 from 30 blocks spanning 0.3 of the image's longer side, 1 from 10
    spanning 0.1, else 0 (a field of higher degree than its blocks span would be extrapolated).
    Measured on a 22 px blur: the tag ring (24 blocks over 0.14 of the image) fitted with
    degree 0 lands 0.28 px off the truth at a loss of twice the noise's variance, with degree 1
    0.09 px off at the noise's."""
    ok = np.all(np.isfinite(xy), axis=1)
    if not ok.any():
        return 0
    n = int(ok.sum()) if count is None else count
    span = float((xy[ok].max(axis=0) - xy[ok].min(axis=0)).max()) / max(image_size)
    if n >= 30 and span >= 0.3:
        return 2
    return 1 if n >= 10 and span >= 0.1 else 0


def _spread(xy: np.ndarray, most: int) -> np.ndarray:
    """Sorted indices of at most ``most`` of the points ``xy (B, 2)``, spread over them
    (farthest-point sampling from the point nearest their mean)."""
    if len(xy) <= most:
        return np.arange(len(xy))
    chosen = [int(np.argmin(np.linalg.norm(xy - xy.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(xy - xy[chosen[0]], axis=1)
    for _ in range(most - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(xy - xy[chosen[-1]], axis=1))
    return np.sort(np.array(chosen))


def _tag_centre(tag: np.ndarray | None) -> np.ndarray | None:
    """``(2,)`` px, the centroid of a :func:`tag_mask`, or None."""
    if tag is None or not tag.any():
        return None
    m = cv2.moments(tag, binaryImage=True)
    return np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])


def fit_with_field(image: np.ndarray, pattern: StarPattern, ids: np.ndarray, H0: np.ndarray,
                   psf_field: PathField, deconv: DeconvSettings, settings: GrowSettings,
                   tag: np.ndarray | None) -> BlockFit:
    """Fit blocks ``ids (B,)`` from ``H0 (B, 3, 3)`` with their PSFs held at the field's
    (:func:`blurcalib.deconv.blocks.fit_blocks` with ``psf_fixed``), over ``|q|_inf <=``
    :attr:`GrowSettings.final_extent` (blocks on the pattern's rim over their square,
    :func:`_inner`), in one window that holds every block's path; pixels that see the tag
    through the field's blur at the tag are left out (:func:`pixel_mask`)."""
    xy = homography_centre(H0)
    xy = np.where(np.isfinite(xy), xy, 0.0)  # degenerate blocks are not fitted
    size = psf_field.kernel_size(xy, settings.field_max_kernel)
    centre = _tag_centre(tag)
    footprint = None if centre is None else psf_field.footprint(centre, settings.field_max_kernel)
    mask = pixel_mask(tag, size, footprint)
    inner = _inner(pattern, ids)
    fits, rows = [], []
    for sel, extent in ((np.flatnonzero(inner), settings.final_extent), (np.flatnonzero(~inner), 1.0)):
        if sel.size:
            fits.append(fit_blocks(image, H0[sel], pattern.num_star_segments,
                                   replace(deconv, kernel_size=size, loss_extent=extent), mask,
                                   psf_fixed=psf_field.kernels(xy[sel], size)))
            rows.append(sel)
    return _take(_concat_fits(fits), np.argsort(np.concatenate(rows), kind="stable"))


def _fit_field(image: np.ndarray, pattern: StarPattern, ids: np.ndarray, H: np.ndarray, start: PathField,
               deconv: DeconvSettings, settings: GrowSettings, tag: np.ndarray | None,
               tied: bool = False) -> tuple[PathField, np.ndarray]:
    """:func:`blurcalib.psf.field.fit_path_field` on blocks ``ids (B,)`` from ``H (B, 3, 3)``,
    at most :attr:`GrowSettings.field_blocks` of them spread over the frame (all when ``tied``),
    none on the pattern's rim (:func:`_inner`: their loss area would reach the paper beyond the
    stars; farthest-point sampling picked them first, and 7 of 40 blocks fitted at 50 x the
    noise's variance); pixels seeing the tag through ``start``'s blur are left out. Returns the
    field and the fitted blocks' homographies ``(B, 3, 3)`` (rows not in the fit keep ``H``)."""
    largest = settings.field_max_kernel
    inner = np.flatnonzero(_inner(pattern, ids))
    rows = inner if tied else inner[_spread(homography_centre(H[inner]), settings.field_blocks)]
    centre = _tag_centre(tag)
    size = start.kernel_size(homography_centre(H[rows]), largest)
    mask = pixel_mask(tag, size, None if centre is None else start.footprint(centre, largest))
    fit = fit_path_field(image, H[rows], pattern.num_star_segments, start, deconv,
                         FieldSettings(loss_extent=settings.final_extent, largest_kernel=largest), mask,
                         pattern.features[ids[rows]] if tied else None)
    out = H.copy()
    out[rows] = fit.H
    return fit.field, out


def _ring_seed(image: np.ndarray, pattern: StarPattern, growth: Growth, deconv: DeconvSettings,
               settings: GrowSettings, tag: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, PathField]:
    """The tag ring's blocks fitted tied to one feature homography with a path field
    (:func:`blurcalib.psf.field.fit_path_field` with ``features``), from their predictions:
    a field of degree 0, then of degree 1 when the ring spans enough of the image
    (:func:`field_degree`). Returns the ring's rows, their homographies and the field."""
    h, w = image.shape
    ring = np.flatnonzero(growth.front == 0)
    start = constant_field(growth.fit.psf[ring], (w, h), 0)
    ids = growth.feature_id[ring]
    psf_field, H = _fit_field(image, pattern, ids, growth.predicted[ring], start, deconv, settings, tag,
                              tied=True)
    if field_degree(homography_centre(H), (w, h), len(ring)) >= 1:
        psf_field, H = _fit_field(image, pattern, ids, H, psf_field.with_degree(1), deconv, settings, tag,
                                  tied=True)
    return ring, H, psf_field


def _local_predictions(pattern: StarPattern, ids: np.ndarray, accepted_H: dict[int, np.ndarray],
                       fallback: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """``(B, 3, 3)`` predictions of blocks ``ids`` from the homography of the ``neighbours``
    accepted blocks nearest each in the pattern (:func:`neighbour_homographies`, least median of
    squares), where one exists, else ``fallback (B, 3, 3)`` (the mean of the adjacent blocks'
    predictions); and ``(B,)`` bool, where it exists. Under blur as long as the squares a
    block's fit stays where it starts along the blur, so a prediction from one or two neighbours
    passes their errors on in chains (measured: 10 blocks 0.5-1 px off in a row); many
    neighbours, most with shorter blur, hold it."""
    ref = np.fromiter(accepted_H, dtype=np.int64, count=len(accepted_H))
    f = pattern.features[ids]
    homographies = neighbour_homographies(f, pattern.features[ref],
                                          homography_centre(np.stack([accepted_H[i] for i in ref])),
                                          neighbours, cv2.LMEDS, 0.0)
    out = fallback.copy()
    local = np.array([H is not None for H in homographies], dtype=bool)
    for b in np.flatnonzero(local):
        out[b] = _normalise(block_homography(homographies[b], f[b, 0:1], f[b, 1:2])[0])
    return out, local


def field_growth(image: np.ndarray, pattern: StarPattern, growth: Growth, deconv: DeconvSettings,
                 settings: GrowSettings, tag: np.ndarray | None,
                 on_event: Callable[[GrowthEvent], None] | None = None,
                 should_stop: Callable[[], bool] | None = None) -> Growth:
    """Fit the frame's path-PSF field from a growth and grow on with it.

    Under blur as long as the star squares a block's free PSF trades its shape against the
    star's position; the frame's motion-path field (:mod:`blurcalib.psf.field`) does not. So:

    1. **Seeds.** The field is fitted (:func:`blurcalib.psf.field.fit_path_field`) with at most
       :attr:`GrowSettings.field_blocks` of the growth's accepted blocks spread over the frame,
       from a straight path along their PSFs (:func:`blurcalib.psf.field.constant_field`), its
       degree by their spread (:func:`field_degree`). When the growth failed (it accepted fewer
       than half of the blocks it fitted, or fewer than :attr:`GrowSettings.field_min_blocks`:
       blur as long as the squares, whose free fits settle px off) the seeds are the tag ring
       instead, fitted tied to one feature homography (:func:`_ring_seed`), and the growth's
       other accepted blocks are tried again.
    2. The seeds are fitted again with the field's PSF over :attr:`GrowSettings.final_extent`
       x their square (:func:`fit_with_field`), kept where accepted and moved less than
       :attr:`GrowSettings.final_max_shift_px`.
    3. The growth goes on, front by front, from the accepted blocks into every block not
       accepted yet, each fitted with the field's PSF and judged by the growth's rules
       (:func:`judge_front`, the loss limited to :attr:`GrowSettings.field_loss_factor` x the
       median of step 2's) and by its neighbours (:func:`inconsistent`). Whenever the accepted
       blocks have doubled since the field was fitted, it is fitted again from them (warm
       start); at the end the blocks fitted with an earlier field are fitted with the last.

    ``on_event`` and ``should_stop`` are :func:`grow`'s (polled between fronts). Returns the
    growth unchanged when no field could be fitted; else a new growth (rows of
    blocks accepted now replace their earlier ones, new blocks are appended) with
    :attr:`Growth.psf_field` set.
    """
    h, w = image.shape
    growth_ids = [int(v) for v in growth.feature_id]
    status = list(growth.status)
    acc = np.flatnonzero(growth.accepted)
    ring = np.flatnonzero(growth.front == 0)
    fitted = int(np.isfinite(growth.fit.loss).sum())
    from_ring = ring.size >= 6 and (acc.size < settings.field_min_blocks or 2 * acc.size < fitted)
    events = list(growth.events)
    front = growth.front.tolist()
    predicted = list(growth.predicted)

    def report(k: int, fit: BlockFit, row: int) -> None:
        """The event of row ``row``'s decision, fitted as row ``k`` of ``fit``."""
        _emit(events, on_event, pattern, growth_ids[row], status[row], fit, k, front[row])

    try:
        if from_ring:
            seeds, H_seed, psf_field = _ring_seed(image, pattern, growth, deconv, settings, tag)
        elif acc.size >= settings.field_min_blocks:
            seeds, H_seed = acc, growth.fit.H[acc]
            start = constant_field(growth.fit.psf[acc], (w, h), field_degree(growth.fit.centre[acc], (w, h)))
            psf_field, _ = _fit_field(image, pattern, growth.feature_id[acc], H_seed, start, deconv, settings,
                                      tag)
        else:
            return growth
    except ValueError:  # no usable PSF or block to fit a field from
        return growth
    refit = fit_with_field(image, pattern, growth.feature_id[seeds], H_seed, psf_field, deconv, settings, tag)
    ok = np.array([st is BlockStatus.ACCEPTED for st in refit.status], dtype=bool) & np.isfinite(refit.loss)
    ok &= np.linalg.norm(refit.centre - homography_centre(H_seed), axis=1) < settings.final_max_shift_px
    if not ok.any():
        return growth
    max_loss = min(settings.max_loss, settings.field_loss_factor * float(np.median(refit.loss[ok])))
    ok &= (refit.loss <= max_loss) & (refit.boundary_energy <= settings.max_boundary_energy)
    fit = _replace_rows(growth.fit, seeds[ok], refit, np.flatnonzero(ok))
    for k in np.flatnonzero(ok):
        status[seeds[k]] = BlockStatus.ACCEPTED
        report(k, refit, int(seeds[k]))
    # tried again below: blocks whose two fits disagree (measured: free fits next to the tag
    # 0.6-1 px off), and with seeds from the ring the other blocks the growth accepted
    demoted = np.union1d(seeds[~ok], np.setdiff1d(acc, seeds) if from_ring else [])
    for k in demoted.astype(np.int64):
        if status[k] is BlockStatus.ACCEPTED:
            status[k] = BlockStatus.NOT_CONVERGED
            report(int(k), growth.fit, int(k))
    row = {fid: k for k, fid in enumerate(growth_ids)}
    accepted_H = {growth_ids[k]: _normalise(fit.H[k])
                  for k, st in enumerate(status) if st is BlockStatus.ACCEPTED}
    tried = dict.fromkeys(accepted_H, 0)
    new_ids = list(accepted_H)
    generation = 0  # fits of the field so far, after the first
    fitted_in = dict.fromkeys(accepted_H, generation)  # the field each accepted block was fitted with
    fitted_with = len(accepted_H)  # accepted blocks when the field was last fitted
    appended: list[BlockFit] = []
    front_index = max(front) + 1
    while new_ids and len(growth_ids) < settings.max_blocks:
        if should_stop is not None and should_stop():
            break
        if len(accepted_H) >= 2 * fitted_with:
            ids = np.fromiter(accepted_H, dtype=np.int64, count=len(accepted_H))
            H_acc = np.stack(list(accepted_H.values()))
            degree = max(psf_field.degree, field_degree(homography_centre(H_acc), (w, h)))
            try:
                psf_field, _ = _fit_field(image, pattern, ids, H_acc, psf_field.with_degree(degree), deconv,
                                          settings, tag)
                generation += 1
            except ValueError:
                pass
            fitted_with = len(accepted_H)
        fids, preds, _ = _next_front(pattern, accepted_H, tried, new_ids)
        if not fids:
            break
        H0, local = _local_predictions(pattern, np.asarray(fids), accepted_H, np.stack(preds),
                                       settings.consistency_neighbours)
        ffit = fit_with_field(image, pattern, np.asarray(fids), H0, psf_field, deconv, settings, tag)
        # judged by the neighbours that predicted it (inconsistent's rule, one fit per block)
        off = local & (np.linalg.norm(ffit.centre - homography_centre(H0), axis=1)
                       > settings.max_inconsistency_px)
        new_ids, again, fresh = [], [], []
        for k, (fid, st) in enumerate(zip(fids, judge_front(ffit, H0, settings, off, max_loss), strict=True)):
            tried[fid] = 0
            if fid in row and st is not BlockStatus.ACCEPTED:
                continue  # tried before and failed again: its first record stands
            if fid in row:
                again.append(k)
                status[row[fid]], front[row[fid]], predicted[row[fid]] = st, front_index, H0[k]
            else:
                fresh.append(k)
                row[fid] = len(growth_ids)
                growth_ids.append(fid)
                status.append(st)
                front.append(front_index)
                predicted.append(H0[k])
            if st is BlockStatus.ACCEPTED:
                accepted_H[fid] = _normalise(ffit.H[k])
                fitted_in[fid] = generation
                new_ids.append(fid)
        if again:
            fit = _replace_rows(fit, np.array([row[fids[k]] for k in again]), ffit, np.array(again))
        if fresh:
            appended.append(_take(ffit, np.array(fresh)))
        for k in again + fresh:
            report(k, ffit, row[fids[k]])
        front_index += 1
    fit = _concat_fits([fit, *appended])
    # the blocks fitted with an earlier field, with the last one
    rows = np.array([k for k, (fid, st) in enumerate(zip(growth_ids, status, strict=True))
                     if st is BlockStatus.ACCEPTED and fitted_in[fid] < generation], dtype=np.int64)
    if rows.size:
        last = fit_with_field(image, pattern, np.array(growth_ids)[rows], fit.H[rows], psf_field, deconv,
                              settings, tag)
        keep = np.array([st is BlockStatus.ACCEPTED for st in last.status], dtype=bool)
        keep &= (last.loss <= max_loss) & (np.linalg.norm(last.centre - fit.centre[rows], axis=1)
                                           < settings.final_max_shift_px)
        fit = _replace_rows(fit, rows[keep], last, np.flatnonzero(keep))
        for k in np.flatnonzero(keep):
            report(k, last, int(rows[k]))
    return Growth(fit, np.array(growth_ids, dtype=np.int64), status, np.array(front, dtype=np.int64),
                  np.stack(predicted), events, psf_field)


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


def _cut_off(pattern: StarPattern, ids: np.ndarray, front: np.ndarray,
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


def _next_front(pattern: StarPattern, accepted_H: dict[int, np.ndarray],
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
                    preds.append(_normalise(accepted_H[src] @ _shift_q(ex, ey)))
                    srcs.append(src)
            candidates[nid], sources[nid] = preds, srcs
    ids = sorted(candidates)
    return ids, [np.mean(candidates[i], axis=0) for i in ids], [sources[i] for i in ids]


def _psf_hint(accepted_psf: dict[int, np.ndarray], sources: list[list[int]], size: int,
              settings: GrowSettings) -> np.ndarray | None:
    """``(B, size, size)`` mean re-centred PSF of the accepted blocks that predicted each block
    of a front (padded or cropped, centred, to ``size``), or None when hints are off
    (:attr:`GrowSettings.psf_hints`) or some block has no source (the ring)."""
    if not settings.psf_hints or not sources or not all(sources):
        return None
    return np.stack([np.mean([_resize_kernels(accepted_psf[fid], size) for fid in srcs], axis=0)
                     for srcs in sources])
