"""The acceptance rules of region growing (:class:`GrowSettings`); the PSF window is
:class:`blurcalib.growth.window.WindowPolicy`'s."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

FinalFitFrames = Literal["adaptive", "all", "none"]
"""Which frames get :func:`blurcalib.growth.final.final_fit` (:attr:`GrowSettings.final_fit_frames`)."""


@dataclass(frozen=True)
class GrowSettings:
    """Acceptance rules of region growing (the stricter quality filter comes later).

    Attributes:
        max_loss: reject blocks whose mean squared residual exceeds this (grey levels^2; given
            the frame's noise, :func:`blurcalib.growth.grow.grow` raises it in proportion to the
            noise variance above
            :data:`blurcalib.growth.quality.REFERENCE_NOISE_VAR`,
            :func:`blurcalib.growth.quality.noise_scale`).
        max_boundary_energy: reject blocks whose PSF has more than this share of its energy in
            the outer two-pixel ring of the kernel window (the blur does not fit: truncated).
        max_jump: reject blocks whose star centre moved further than this from its prediction
            (in squares; a block that slid onto a neighbouring star).
        max_blocks: stop after this many attempted blocks (safety net).
        adapt_above_extent_px: the window adapts only in frames whose tag ring shows more blur
            than this (90th percentile of ``sqrt(12) sigma_major``, px) or whose ring PSFs
            reach the border (median boundary energy above ``refit_boundary_energy``); below,
            the start window (:attr:`blurcalib.growth.window.WindowPolicy.start`) is kept
            (docs/decisions/adaptive-window.md).
        refit_boundary_energy: blocks whose PSF has more than this share of its energy in the
            window's outer two-pixel ring are re-fitted with a larger window.
        max_inconsistency_px: in heavily blurred frames only (``heavy_above_extent_px``),
            reject blocks whose star centre is further than this (px) from the homography of
            the previously accepted blocks nearest to it (:func:`blurcalib.growth.judge.inconsistent`).
        consistency_neighbours: that many previously accepted blocks per judgement.
        heavy_above_extent_px: frames whose tag ring shows a blur extent above this (px, 90th
            percentile of ``sqrt(12) sigma_major`` of the ring's fit in the adapted window: a
            truncated PSF reads shorter) are heavily blurred: their blocks are checked against
            their neighbours, and with the adaptive window the tag's mask follows the blur
            (:func:`blurcalib.growth.masks.blur_footprint`).
        psf_hints: blocks after the tag ring start from the mean PSF of the accepted neighbours
            that predicted them (:func:`blurcalib.deconv.blocks.fit_blocks_hinted`: no coarse kernel,
            fewer solver stages).
        retry_below_blur_per_square: a block that its hinted fit leaves not converged, whose hint
            shows a blur per square (:func:`blurcalib.psf.kernel.blur_per_square`) below this, is
            accepted after a last LM step of less than ``hinted_converge_px``, else fitted again
            with the full schedule (:func:`blurcalib.growth.fronts.fit_hinted`); 0: such blocks
            are fitted again only when their front accepts no block.
        hinted_converge_px: the convergence tolerance of those blocks (px; the solver's own is
            :attr:`blurcalib.deconv.settings.DeconvSettings.converge_tol_px`).
        final_extent: loss area of the final fit (:func:`blurcalib.growth.final.final_fit`), the
            square grown about its star centre by this factor
            (:attr:`blurcalib.deconv.settings.DeconvSettings.loss_extent`); 1 skips it.
        final_fit_frames: which frames get the final fit: ``"adaptive"`` (those whose window
            adapted to the blur, the default), ``"all"`` or ``"none"``.
        final_max_shift_px: a final fit whose star centre moved further than this (px) from
            the growth's fit is not kept.
        psf_field: in frames whose window adapted, or whose blur is long for their squares
            (``field_above_blur_per_square``), fit the frame's field of motion-path PSFs and
            fit and grow on with it (:func:`blurcalib.growth.field.field_growth`) instead of the final fit.
        field_above_blur_per_square: frames whose fitted blocks' median blur over square side
            (:func:`blurcalib.psf.kernel.blur_per_square`) reaches this get the field growth even when
            their window did not adapt (small squares, moderate blur).
        field_min_blocks: fewest accepted blocks to fit a field from.
        field_blocks: most blocks in the field's fit (spread over the accepted ones).
        field_loss_factor: a block fitted with the field is rejected when its loss exceeds
            this multiple of the median loss of the accepted blocks' field fits.
        field_refit_px: when the field has been fitted again during the field growth, a block
            accepted with an earlier field is fitted with the last one where the paths moved
            by more than this at the block (px, :meth:`blurcalib.psf.path.PathField.path_change`;
            0 fits every such block again).
        ring_refit_noise: a tag ring's field fit (:func:`blurcalib.growth.field.ring_seed`)
            whose median block loss exceeds this multiple of the frame's noise variance is made
            again from its first field, and the second is kept where its loss is within it (0:
            never).
    """

    max_loss: float = 400.0
    max_boundary_energy: float = 0.3
    max_jump: float = 0.3
    max_blocks: int = 5000
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
    field_refit_px: float = 0.1
    ring_refit_noise: float = 2.0

    def __post_init__(self) -> None:
        if self.final_fit_frames not in get_args(FinalFitFrames):
            raise ValueError(f"final_fit_frames must be one of {get_args(FinalFitFrames)}, got "
                             f"{self.final_fit_frames!r}")
        if not self.final_extent >= 1.0:
            raise ValueError(f"final_extent must be >= 1, got {self.final_extent}")
        if self.field_min_blocks < 1 or self.field_blocks < self.field_min_blocks:
            raise ValueError("need 1 <= field_min_blocks <= field_blocks")
        if not self.field_refit_px >= 0:
            raise ValueError(f"field_refit_px must be >= 0, got {self.field_refit_px}")
        if not self.ring_refit_noise >= 0:
            raise ValueError(f"ring_refit_noise must be >= 0, got {self.ring_refit_noise}")
