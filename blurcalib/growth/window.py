"""The PSF window: :class:`WindowPolicy` (start, largest and field windows) and its use in a growth.

A front is solved with the window chosen from the previous front's PSFs
(:meth:`WindowPolicy.choose`: about 1.5 x the blur extent ``sqrt(12) sigma_major``, the length of
a straight blur with that second moment; odd, at least :attr:`WindowPolicy.start`, at most
:attr:`WindowPolicy.largest`). A block whose PSF reaches the window's border is re-fitted from the
same prediction with a larger window, up to the cap, rather than dropped (:func:`fit_front`). All
of this only in frames whose tag ring shows more than about 18 px of blur
(:func:`needs_adaptive_window`), or from the first later front whose PSFs reach the window's
border (the blur grows away from the tag); below, the start window is kept (a later front's
extent alone is no signal; docs/decisions/adaptive-window.md). Kernels of one growth are
zero-padded (centred) to its largest window, which leaves them unchanged as convolution kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from blurcalib.deconv.blocks import fit_blocks
from blurcalib.deconv.result import BlockFit
from blurcalib.deconv.settings import DeconvSettings, check_kernel_size
from blurcalib.growth.masks import pixel_mask
from blurcalib.growth.settings import GrowSettings
from blurcalib.io.results import BlockStatus
from blurcalib.psf.kernel import blur_extent, blur_per_square

SHARP_START = 9
"""Start window of sharp frames (px): 1.5 x (:attr:`WindowPolicy.per_extent`) the 5 px blur extent
below which a frame is classified sharp, rounded up to odd, so it holds the PSF of any frame
classified sharp; a smaller window would adapt on sharp frames with a few px of blur
(docs/decisions/sharp-window-9px.md)."""


@dataclass(frozen=True)
class WindowPolicy:
    """The PSF windows of a frame's blocks (px, odd).

    Attributes:
        start: the window of the first front, kept in frames whose blur it holds.
        largest: the largest window of free PSFs; a value not above ``start`` keeps the window
            fixed (and leaves out the path-PSF field).
        field_largest: the largest window of a path-PSF field's kernels
            (:mod:`blurcalib.psf.path`).
        per_extent: window side per px of blur extent (:meth:`choose`).
    """

    start: int = 17
    largest: int = 41
    field_largest: int = 61
    per_extent: float = 1.5

    def __post_init__(self) -> None:
        for name in ("start", "largest", "field_largest"):
            check_kernel_size(getattr(self, name))
        if not self.per_extent > 0:
            raise ValueError(f"per_extent must be positive, got {self.per_extent}")

    @property
    def adapts(self) -> bool:
        """Whether the window may grow beyond :attr:`start`."""
        return self.largest > self.start

    def choose(self, sigma_major: np.ndarray | float, smallest: int | None = None,
               largest: int | None = None) -> int:
        """PSF window side for blurs of second moment ``sigma_major`` (px).

        The blur extent is ``e = sqrt(12) sigma_major`` (:func:`blurcalib.psf.kernel.blur_extent`);
        the window is ``ceil(per_extent e)`` rounded up to odd, within ``[smallest, largest]``
        (default :attr:`start` and :attr:`largest`; a cap below ``smallest`` is no cap).
        ``sigma_major`` may be several values (their 90th percentile is used); none finite gives
        ``smallest``.
        """
        lo = self.start if smallest is None else smallest
        hi = self.largest if largest is None else largest
        s = np.asarray(sigma_major, dtype=np.float64).ravel()
        s = s[np.isfinite(s)]
        if s.size == 0:
            return lo
        k = math.ceil(self.per_extent * blur_extent(float(np.percentile(s, 90))))
        k += 1 - k % 2
        return int(max(min(k, hi), lo))


@dataclass
class FrameWindow:
    """The window of one frame's growth, decided on its first front (or later, when a front's
    PSFs reach the border).

    Attributes:
        size: the window of the next front (px).
        adaptive: whether the window follows the blur (None until decided).
        heavy: the frame is heavily blurred (:attr:`GrowSettings.heavy_above_extent_px`).
        footprint: the blur's footprint (:func:`blurcalib.growth.masks.blur_footprint`) for the
            tag's mask in heavily blurred adaptive frames, or None.
    """

    size: int
    adaptive: bool | None = None
    heavy: bool = False
    footprint: np.ndarray | None = None


def front_blur(fit: BlockFit) -> tuple[float, float]:
    """``(extent px, boundary energy)`` of a front's fitted PSFs: the 90th percentile of
    ``sqrt(12) sigma_major`` and the median boundary energy (NaN when none was fitted)."""
    ok = np.array([st is BlockStatus.ACCEPTED for st in fit.status], dtype=bool)
    ok |= np.isfinite(fit.boundary_energy)
    if not ok.any() or not np.isfinite(fit.sigma_major[ok]).any():
        return float("nan"), float("nan")
    return (blur_extent(float(np.nanpercentile(fit.sigma_major[ok], 90))),
            float(np.nanmedian(fit.boundary_energy[ok])))


def needs_adaptive_window(fit: BlockFit, settings: GrowSettings) -> bool:
    """Whether the first front's fit ``fit`` shows more blur than the start window suits
    (see :attr:`GrowSettings.adapt_above_extent_px`)."""
    extent, be = front_blur(fit)
    return bool(extent > settings.adapt_above_extent_px or be > settings.refit_boundary_energy)


def median_blur_per_square(fit: BlockFit) -> float:
    """Median blur over square side (:func:`blurcalib.psf.kernel.blur_per_square`) of the fitted
    blocks (NaN when none was fitted)."""
    ratio = blur_per_square(fit.sigma_major, fit.H)
    return float(np.median(ratio[np.isfinite(ratio)])) if np.isfinite(ratio).any() else math.nan


def too_small(fit: BlockFit, size: np.ndarray, window: WindowPolicy, settings: GrowSettings) -> np.ndarray:
    """``(B,)`` bool: fitted blocks whose window (``size (B,)`` px) is too small for their PSF:
    it reaches the window's border, or it touches the border (boundary energy above 0.03; the
    solver zeroes kernel entries below 15 % of the peak, so a PSF that fits leaves the ring
    empty) while its extent asks for a larger window (:meth:`WindowPolicy.choose`)."""
    fitted = np.array([st in (BlockStatus.ACCEPTED, BlockStatus.NOT_CONVERGED)
                       for st in fit.status], dtype=bool)
    wanted = np.array([window.choose(s, k) for s, k in zip(fit.sigma_major, size, strict=True)])
    be = np.where(np.isfinite(fit.boundary_energy), fit.boundary_energy, 0.0)
    return fitted & (size < window.largest) & (
        (be > settings.refit_boundary_energy) | ((be > 0.03) & (wanted > size)))


def fit_front(image: np.ndarray, H0: np.ndarray, num_segments: int, first: BlockFit, window: WindowPolicy,
              deconv: DeconvSettings, settings: GrowSettings, tag: np.ndarray | None = None,
              footprint: np.ndarray | None = None) -> BlockFit:
    """Re-fit the blocks of a front's fit ``first`` (from ``H0 (B, 3, 3)``) whose window is too
    small for their PSF (:func:`too_small`) with larger windows (at least 1.4 x larger each time,
    up to :attr:`WindowPolicy.largest`), keeping a re-fit when it is accepted with no more
    boundary energy; a block whose re-fit is not kept is not re-fitted again (its window is not
    what fails it). Kernels come back padded to the largest window used. ``tag``
    (:func:`blurcalib.growth.masks.tag_mask`) keeps pixels near the tags out of the fits (within
    the blur's ``footprint`` when given, :func:`blurcalib.growth.masks.pixel_mask`)."""
    fit = first
    size = first.kernel_size
    block_size = np.full(len(H0), size)
    stuck = np.zeros(len(H0), dtype=bool)
    while size < window.largest:
        redo = np.flatnonzero(too_small(fit, block_size, window, settings) & ~stuck)
        if redo.size == 0:
            break
        grown = math.ceil(1.4 * size)
        size = max(window.choose(fit.sigma_major[redo], size), min(grown + 1 - grown % 2, window.largest))
        refit = fit_blocks(image, H0[redo], num_segments, size, deconv, pixel_mask(tag, size, footprint))
        better = np.array([refit.status[j] is BlockStatus.ACCEPTED
                           and (fit.status[i] is not BlockStatus.ACCEPTED
                                or refit.boundary_energy[j] <= fit.boundary_energy[i])
                           for j, i in enumerate(redo)], dtype=bool)
        stuck[redo[~better]] = True
        if not better.any():
            continue
        fit = fit.with_rows(redo[better], refit, np.flatnonzero(better))
        block_size[redo[better]] = size
    return fit
