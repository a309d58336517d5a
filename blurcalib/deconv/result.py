"""The result of the block solver: :class:`BlockFit` (one row per block) and
:class:`BlockModel` (one block's fitted model, for display)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any, NamedTuple, cast

import numpy as np

from blurcalib.deconv.settings import DeconvSettings
from blurcalib.geometry.homography import homography_centre, translation
from blurcalib.io.results import BlockStatus
from blurcalib.psf.kernel import resize_kernels


@dataclass(eq=False)
class BlockFit:
    """Batched result of :func:`fit_blocks` for ``B`` blocks (``K`` the kernel size).

    Blocks that were not fitted (status ``outside_image`` or ``degenerate_homography``) keep
    their initial ``H`` and carry NaN in every other float field. The rows of several fits
    (:meth:`concat`) share the largest of their windows, smaller kernels zero-padded (centred),
    which leaves them unchanged as convolution kernels.

    Attributes:
        H: ``(B, 3, 3)`` float64, block coordinates -> image px, *after* PSF re-centring, so
            ``H(0, 0)`` is the centre of the star's time-averaged (blurred) image;
            ``H[2, 2] = 1``.
        psf: ``(B, K, K)`` float64 re-centred kernels (centroid at the kernel centre), each
            non-negative and summing to 1.
        psf_fit: ``(B, K, K)`` float64 fitted kernels before the sub-pixel re-centring (they go
            with :attr:`H_fit`).
        coeffs: ``(B, 6)`` float64 ``(a1, a2, a3, b1, b2, b3)`` grey levels of the fitted model
            (:attr:`H_fit`, :attr:`psf_fit`).
        uv_centre: ``(B, 2)`` px, ``(x_c, y_c)`` of the normalised coordinates ``u, v``.
        uv_scale: ``(B,)`` px, ``s`` of the normalised coordinates.
        loss: ``(B,)`` mean squared residual over the block's square (grey levels^2).
        residual_rms: ``(B,)`` ``sqrt(loss)`` (grey levels).
        centroid: ``(B, 2)`` px, centroid of :attr:`psf_fit` relative to the kernel centre; the
            re-centring moved ``H`` by it: ``H = T(centroid) H_fit``.
        boundary_energy: ``(B,)`` share of PSF energy in the kernel's outer two-pixel ring.
        sigma_major, sigma_minor: ``(B,)`` px, PSF second-moment ellipse axes.
        eccentricity: ``(B,)``; orientation: ``(B,)`` rad in ``(-pi/2, pi/2]``.
            The moment figures are those of :attr:`psf_fit` (central moments do not depend on
            the re-centring, which would widen the kernel slightly).
        converged: ``(B,)`` bool: fitted, finite, contrast ``a3`` above
            :attr:`DeconvSettings.min_contrast`, and the last LM step moved the star centre by
            less than :attr:`DeconvSettings.converge_tol_px`.
        status: ``B`` :class:`blurcalib.io.results.BlockStatus`: ``accepted``, ``not_converged``,
            ``outside_image`` or ``degenerate_homography``.
        centre_step: ``(B,)`` px, movement of the star centre in the last accepted LM step.
        origin: ``(B, 2)`` int, ``(x0, y0)`` px of the observed window's top-left pixel.
        window_size: ``(B, 2)`` int, ``(width, height)`` px of the observed window.
        num_pixels: ``(B,)`` int, pixels in the loss.
        loss_extent: ``(B,)`` the :attr:`DeconvSettings.loss_extent` each block was fitted with
            (its loss covered ``|q|_inf <= loss_extent``; rows of several fits may differ).
        masks: ``(B,)`` object array of bool ``(height, width)`` arrays over each window: the
            loss's pixels (empty for blocks that were not fitted).
        num_segments: star segments ``N``.
        settings: the solver settings used (of the first fit, for rows of several; they differ
            at most in the loss extent, which :attr:`loss_extent` gives per row).
    """

    H: np.ndarray
    psf: np.ndarray
    psf_fit: np.ndarray
    coeffs: np.ndarray
    uv_centre: np.ndarray
    uv_scale: np.ndarray
    loss: np.ndarray
    residual_rms: np.ndarray
    centroid: np.ndarray
    boundary_energy: np.ndarray
    sigma_major: np.ndarray
    sigma_minor: np.ndarray
    eccentricity: np.ndarray
    orientation: np.ndarray
    converged: np.ndarray
    status: tuple[BlockStatus, ...]
    centre_step: np.ndarray
    origin: np.ndarray
    window_size: np.ndarray
    num_pixels: np.ndarray
    loss_extent: np.ndarray
    masks: np.ndarray
    num_segments: int
    settings: DeconvSettings = field(default_factory=DeconvSettings)

    def __len__(self) -> int:
        return int(self.H.shape[0])

    @property
    def kernel_size(self) -> int:
        """``K``, the side of the PSF window of :attr:`psf` (px)."""
        return int(self.psf.shape[-1])

    def take(self, rows: Sequence[int] | np.ndarray) -> BlockFit:
        """The rows ``rows`` of this fit, in that order."""
        rows = np.asarray(rows, dtype=np.int64)
        values: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "status":
                values[f.name] = tuple(v[i] for i in rows)
            elif isinstance(v, np.ndarray):
                values[f.name] = v[rows]
            else:
                values[f.name] = v
        return BlockFit(**values)

    @staticmethod
    def concat(fits: Sequence[BlockFit]) -> BlockFit:
        """The rows of ``fits`` in order, kernels zero-padded (centred) to the largest window."""
        size = max(f.kernel_size for f in fits)
        values: dict[str, Any] = {}
        for f in fields(fits[0]):
            items = [getattr(fit, f.name) for fit in fits]
            if f.name == "status":
                values[f.name] = tuple(s for fit in fits for s in fit.status)
            elif f.name in ("psf", "psf_fit"):
                values[f.name] = np.concatenate([resize_kernels(k, size) for k in items], axis=0)
            elif isinstance(items[0], np.ndarray):
                values[f.name] = np.concatenate(items, axis=0)
            else:
                values[f.name] = items[0]
        return BlockFit(**values)

    def with_rows(self, rows: np.ndarray, other: BlockFit, other_rows: np.ndarray) -> BlockFit:
        """This fit with its rows ``rows`` replaced by the rows ``other_rows`` of ``other``
        (kernels padded to the larger window)."""
        keep = np.setdiff1d(np.arange(len(self)), rows)
        merged = BlockFit.concat([self.take(keep), other.take(other_rows)])
        return merged.take(np.argsort(np.concatenate([keep, rows]), kind="stable"))

    def converged_within(self, tol_px: float) -> np.ndarray:
        """``(B,)`` bool: the rule of :attr:`converged` with the tolerance ``tol_px`` (px) in place
        of :attr:`DeconvSettings.converge_tol_px`: fitted, finite, with contrast, and the last LM
        step moved the star centre by less than ``tol_px``."""
        fitted = (np.array([st in (BlockStatus.ACCEPTED, BlockStatus.NOT_CONVERGED) for st in self.status],
                           dtype=bool)
                  & np.isfinite(self.loss) & np.all(np.isfinite(self.H), axis=(1, 2))
                  & np.all(np.isfinite(self.psf_fit), axis=(1, 2))
                  & (self.coeffs[:, 2] > self.settings.min_contrast) & (self.num_pixels > 0))
        with np.errstate(invalid="ignore"):
            return cast(np.ndarray, fitted & (self.centre_step < tol_px))

    @property
    def H_fit(self) -> np.ndarray:
        """``(B, 3, 3)``: the fitted homographies before re-centring, ``T(-centroid) H``."""
        return cast(np.ndarray, translation(-self.centroid) @ self.H)

    @property
    def centre(self) -> np.ndarray:
        """``(B, 2)`` px: the star centres ``H(0, 0)`` (time-averaged image positions); NaN for a
        degenerate ``H``."""
        return homography_centre(self.H)


class BlockModel(NamedTuple):
    """One block's fitted model over its observed window, for display (all ``(height, width)``)."""

    model: np.ndarray
    """The model image ``m`` (grey levels)."""
    observed: np.ndarray
    """The observed window ``I`` (grey levels)."""
    residual: np.ndarray
    """``I - m`` (grey levels)."""
    mask: np.ndarray
    """bool, the loss's pixels (the block's square)."""
    origin: np.ndarray
    """``(2,)`` int, ``(x0, y0)`` px of the window's top-left pixel."""
