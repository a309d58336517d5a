"""The final fit: the accepted blocks of a frame fitted once more over a larger area.

Once grown, the accepted blocks of a frame whose window adapted are fitted once more with the loss
over 1.5 x their square (:func:`final_fit`), started from their fit: the centre sees 2.25 x the
pixels. Frames whose window did not adapt skip it by default
(:attr:`blurcalib.growth.settings.GrowSettings.final_fit_frames`): there it costs more for a
smaller gain (docs/decisions/final-fit-extent.md).
"""

from __future__ import annotations

from dataclasses import replace
from typing import cast

import numpy as np

from blurcalib.deconv.blocks import fit_blocks_hinted
from blurcalib.deconv.result import BlockFit
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.growth.masks import pixel_mask
from blurcalib.growth.settings import GrowSettings
from blurcalib.growth.window import WindowPolicy
from blurcalib.io.results import BlockStatus
from blurcalib.psf.kernel import resize_kernels
from blurcalib.target.pattern import StarPattern


def final_fit(image: np.ndarray, pattern: StarPattern, ids: np.ndarray, fit: BlockFit,
              accepted: np.ndarray, window: WindowPolicy, deconv: DeconvSettings, settings: GrowSettings,
              tag: np.ndarray | None, footprint: np.ndarray | None = None) -> BlockFit:
    """Fit the accepted blocks once more over a larger area, from their growth fit.

    ``eq:deconvolution`` with the loss over ``|q|_inf <= e`` (``e`` =
    :attr:`GrowSettings.final_extent`: the star's square and a band of its neighbours' squares)
    instead of the square alone: the periodic latent pattern and a PSF that varies slowly over
    the image hold there too, and the centre's noise falls with the pixels it sees
    (docs/decisions/final-fit-extent.md). Each block starts from its fitted ``H`` and re-centred PSF (the PSF
    as its hint: :attr:`DeconvSettings.hinted_stages` stages) in the window its PSF asks for
    (:meth:`WindowPolicy.choose`, at most the growth's largest). Blocks on the pattern's outer
    rim are left as they are (the grown area would reach the paper beyond the printed stars,
    which the periodic model does not know), as are blocks whose final fit is not accepted by
    the growth's rules or whose centre moved further than :attr:`GrowSettings.final_max_shift_px`.

    Args:
        image: the frame.
        pattern: the target.
        ids: ``(B,)`` feature ids of ``fit``'s rows.
        fit: the growth's fits (kernels padded to its largest window).
        accepted: ``(B,)`` bool, the rows the growth accepted.
        window: the PSF windows.
        deconv: block solver settings.
        settings: growth rules.
        tag, footprint: as for :func:`blurcalib.growth.masks.pixel_mask`.
    Returns:
        ``fit`` with the kept final fits in place of their rows.
    """
    rows = np.flatnonzero(accepted & inner(pattern, ids))
    if rows.size == 0 or settings.final_extent <= 1.0:
        return fit
    sizes = np.array([window.choose(sm, largest=fit.kernel_size) for sm in fit.sigma_major[rows]])
    for size in np.unique(sizes):
        sel = rows[sizes == size]
        final = fit_blocks_hinted(image, fit.H[sel], pattern.num_star_segments,
                                  resize_kernels(fit.psf[sel], int(size)),
                                  replace(deconv, loss_extent=settings.final_extent),
                                  pixel_mask(tag, int(size), footprint))
        shift = np.linalg.norm(final.centre - fit.centre[sel], axis=1)
        keep = np.array([st is BlockStatus.ACCEPTED for st in final.status], dtype=bool)
        keep &= (final.loss <= settings.max_loss) & (final.boundary_energy <= settings.max_boundary_energy)
        keep &= shift < settings.final_max_shift_px
        if keep.any():
            fit = fit.with_rows(sel[keep], final, np.flatnonzero(keep))
    return fit


def inner(pattern: StarPattern, ids: np.ndarray) -> np.ndarray:
    """``(B,)`` bool: features ``ids`` off the pattern's outer rim, whose squares grown by half a
    square (a loss over 1.5 x the square) still show printed stars only."""
    f = pattern.features[ids]
    return cast(np.ndarray, (f[:, 0] > 0) & (f[:, 1] > 0) & (f[:, 0] < pattern.squares_x - 2)
                & (f[:, 1] < pattern.squares_y - 2))
