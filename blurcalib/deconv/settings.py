"""Settings of the block solver (:func:`blurcalib.deconv.blocks.fit_blocks`).

The PSF window is not among them: the caller gives it (:class:`blurcalib.growth.window.WindowPolicy`
chooses it).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class DeconvSettings:
    """Settings of the block solver (docs/deconvolution.md; the evidence for the defaults:
    docs/decisions/).

    Attributes:
        ridge: ``lambda`` of ``eq:deconvolution``, relative to the mean energy of a kernel
            entry's column of the design (dimensionless).
        ridge_border: growth of the ridge towards the kernel's border,
            ``rho(d) = 1 + ridge_border (|d| / c)^ridge_power``: a pedestal in ``k`` is nearly
            indistinguishable from the offset ``B`` and would move the PSF centroid.
        ridge_power: exponent of that growth.
        tau: soft-edge width of the latent pattern (px).
        supersample: latent samples per pixel side (1: pixel centres).
        outer_iterations: stages of (integer re-centring, support, LM steps) after the coarse
            initial kernel.
        gn_steps: Levenberg-Marquardt steps per stage (each re-solves the kernel).
        support_threshold: kernel entries below this share of the previous stage's peak are
            fixed at zero (0: the whole window).
        support_dilation: the support is grown by this many px.
        nonnegative: fix kernel entries that come out negative at zero (active-set passes).
        nonnegative_passes: active-set passes per kernel solve.
        centroid_threshold: kernel values below this share of the peak are ignored by the PSF
            centroid (:func:`blurcalib.psf.kernel.psf_centroid`); 0 keeps all (the kernel is
            non-negative).
        window_margin: px added around the square's bounding box (room for ``H`` to move).
        loss_extent: ``e``, the loss covers ``|q|_inf <= e`` (block units: 1 is the star's own
            square, 1.5 adds a band of half a square of its neighbours' squares, which the
            periodic latent pattern models as well).
        min_square_px: blocks whose square is smaller (sqrt of its area, px) are degenerate.
        min_contrast: a fit whose paper-ink contrast ``a3`` is below this (grey levels) has
            failed (no star in the window) and is ``not_converged``.
        max_window_px: blocks whose window side exceeds this are degenerate.
        batch_size: blocks solved together (grouped by window size).
        stage_batch_size: after the coarse kernel a batch is solved in groups of at most this
            many blocks of similar kernel support, cut where padding costs more than another
            group (the results do not depend on it).
        converge_tol_px: a block has converged when the last accepted LM step moved its star
            centre by less than this (px).
        stop_decrease: a block's LM steps stop once a step's predicted decrease of the objective
            is below this multiple of the block's residual variance (``sse / n``): the step is
            about ``sqrt(stop_decrease)`` of the fit's standard deviation (0: every step is taken).
        stop_rejections: a block's LM steps stop after this many rejected steps in a row (its
            damping has grown 4x each time).
        hinted_stages: stages of blocks given an expected PSF
            (:func:`blurcalib.deconv.blocks.fit_blocks_hinted`), which skip the coarse kernel and
            start from its support.
        fixed_steps: LM steps of blocks given their PSF
            (:func:`blurcalib.deconv.blocks.fit_blocks_fixed`).
        device: torch device of the solve (``"cpu"``, ``"cuda"``, ...).
        dtype: ``"float32"`` or ``"float64"`` for image-sized tensors; the small systems and
            ``H`` are always float64.
    """

    ridge: float = 1e-3
    ridge_border: float = 30.0
    ridge_power: float = 4.0
    tau: float = 0.25
    supersample: int = 1
    outer_iterations: int = 2
    gn_steps: int = 2
    support_threshold: float = 0.15
    support_dilation: int = 1
    nonnegative: bool = True
    nonnegative_passes: int = 3
    centroid_threshold: float = 0.0
    window_margin: int = 2
    loss_extent: float = 1.0
    min_square_px: float = 6.0
    min_contrast: float = 10.0
    max_window_px: int = 256
    batch_size: int = 64
    stage_batch_size: int = 16
    converge_tol_px: float = 0.05
    stop_decrease: float = 0.01
    stop_rejections: int = 2
    hinted_stages: int = 1
    fixed_steps: int = 6
    device: str = "cpu"
    dtype: str = "float32"

    def __post_init__(self) -> None:
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        if self.tau <= 0 or self.ridge < 0 or self.ridge_border < 0:
            raise ValueError("tau must be positive, ridge and ridge_border non-negative")
        if min(self.outer_iterations, self.hinted_stages, self.batch_size, self.stage_batch_size,
               self.supersample, self.fixed_steps) < 1 or self.gn_steps < 0:
            raise ValueError("outer_iterations, hinted_stages, fixed_steps, batch_size, stage_batch_size and "
                             "supersample must be >= 1, gn_steps >= 0")
        if not self.stop_decrease >= 0 or self.stop_rejections < 1:
            raise ValueError("stop_decrease must be >= 0, stop_rejections >= 1")
        if not self.loss_extent > 0:
            raise ValueError(f"loss_extent must be positive, got {self.loss_extent}")
        if not 0.0 <= self.support_threshold < 1.0 or self.support_dilation < 0:
            raise ValueError("support_threshold must be in [0, 1), support_dilation >= 0")

    @property
    def torch_dtype(self) -> torch.dtype:
        """The torch dtype of :attr:`dtype`."""
        return torch.float32 if self.dtype == "float32" else torch.float64


def check_kernel_size(kernel_size: int) -> int:
    """``kernel_size`` (a PSF window side ``K``, px) when it is odd and at least 3; else ValueError."""
    if kernel_size < 3 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be odd and >= 3, got {kernel_size}")
    return int(kernel_size)
