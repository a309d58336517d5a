"""Local deconvolution of star blocks: homography, PSF and brightness per block, batched.

The paper's *Local Deconvolution* (``eq:deconvolution``) with the PSF re-centring of its *Local
Alignment*. For every block (the star square around one feature) we solve::

    argmin_{H, k, p}  sum_{x in square} (I(x) - m(x))^2  +  lambda sum_d rho(d) k(d)^2,   k >= 0

with the model ``m`` in one of two brightness orders (:attr:`DeconvSettings.brightness`)::

    "after_blur" (default):              m = A(p) (k * S(H)) + B(p)
    "before_blur" (the paper's order):   m = k * (S(H) A(p) + B(p))

``A = a1 u + a2 v + a3`` and ``B = b1 u + b2 v + b3`` over normalised pixel coordinates
``u = (x - x_c) / s``, ``v = (y - y_c) / s`` (``(x_c, y_c)`` the window centre, ``s`` half the
window's longer side; both in :class:`BlockFit`), ``p = (a1, a2, a3, b1, b2, b3)`` grey levels.

Conventions (as in ``pattern.py`` and ``results.py``):

* Pixels follow OpenCV: the centre of the top-left pixel is ``(0, 0)``, x right, y down.
* Block coordinates ``q in [-1, 1]^2``: star centre at 0, square corners at ``(+-1, +-1)``,
  feature coordinates ``p = (fx, fy) + q / 2``; a block's ``H`` (3 x 3) maps ``(q_x, q_y, 1)`` to
  homogeneous full-image pixels.
* The PSF ``k`` is ``K x K`` (``K`` odd), ``k[i, j]`` weighs the offset ``d = (j - c, i - c)`` px,
  ``c = (K - 1) / 2``, and ``(k * L)(x) = sum_d k(d) L(x - d)``: a PSF centroid at ``+d`` shows
  the blurred feature displaced by ``+d`` from the latent one.

Latent pattern ``S(H)`` (:attr:`DeconvSettings.pattern`):

* ``"signed_distance"`` (default): ``sigmoid(d_px / tau)``, ``d_px`` the signed distance in
  pixels from the pixel centre to the nearest pattern edge (sector rays *and* square borders,
  :func:`blurcalib.target.pattern.star_signed_distance` divided by its gradient norm through ``H``),
  positive in white: a pixel-consistent soft edge of width ``tau`` px that ``k`` absorbs.
* ``"sigmoid_sin"``: the paper's ``sigmoid(-beta sin(N theta / 2))`` (supplement ``eq:soft``,
  :func:`blurcalib.target.pattern.smooth_star`) sampled at pixel centres (no square borders).

The latent pattern is periodic: beyond the block's square it continues into the neighbouring
stars (which have the opposite colour across the square border), so the loss covers only the
block's own square while the model reaches ``c`` px further out. On the reference target the half
square between a tag-adjacent block and the tag still carries the star of the tag's boundary
feature, so the model stays exact next to the tag while ``c`` is below half a square (px).
Pixels that must not enter the loss (saturation, occluders, a tag nearer than ``c``) are
excluded with ``pixel_mask``.

Solver (variable projection, Golub-Pereyra with Kaufman's Jacobian). Given ``H`` and the relative
gradient ``alpha = (a1, a2) / a3`` of ``A``, the model is linear in ``k~ = a3 k`` and in the
affine offset, which are solved in closed form (ridge least squares, kernel entries that come out
negative fixed at zero); Levenberg-Marquardt then updates the 8 homography parameters and
``alpha`` on the reduced problem, every step re-solving the kernel. Stages:

1. a coarse kernel (taps on a 2-px lattice, tent-interpolated) at ``H0``, the PSF only roughly;
2. ``outer_iterations`` times: integer re-centring of the kernel (``H <- T(n) H``, the
   translational ambiguity ``k' * L' = k * L``), a kernel support (entries above
   ``support_threshold`` of the peak, dilated), the loss's pixels from the current ``H``, and
   ``gn_steps`` LM steps;
3. sub-pixel re-centring ``H <- T(c) H`` with ``c`` the PSF centroid
   (:func:`blurcalib.psf.kernel.recentre`), so that
   ``H(0, 0)`` is the centre of the star's time-averaged image.

A block given an expected PSF (``psf_hint`` of :func:`fit_blocks`: region growing passes the mean
re-centred PSF of the accepted neighbours that predicted it) skips stage 1 and the integer
re-centring: its first support is the hint's, and it runs :attr:`DeconvSettings.hinted_stages`
stages (one by default: half the kernel solves; measured in ``docs/deconvolution.md``).

A block given its PSF (``psf_fixed`` of :func:`fit_blocks`: the frame's motion-path PSF field,
:mod:`blurcalib.psf.field`) keeps it: only ``H``, ``alpha`` and the brightness are fitted, in one
stage of :attr:`DeconvSettings.fixed_steps` LM steps, and the re-centring moves ``H`` by the given
kernel's centroid.

All blocks of a batch are solved together as padded ``(b, ...)`` tensors on
:attr:`DeconvSettings.device` (after the coarse kernel in groups of similar kernel support,
:attr:`DeconvSettings.stage_batch_size`): the solver loops over stages and LM steps, never over
blocks, pixels or kernel entries (one gather builds all patches of a step). Measurements behind
the defaults: ``docs/deconvolution.md`` and ``scripts/bench_deconv.py``.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
import torch
import torch.nn.functional as nnf

from blurcalib.geometry.homography import homography_centre, translation
from blurcalib.io.results import BlockStatus
from blurcalib.psf.kernel import boundary_energy, psf_centroid, psf_moments, recentre
from blurcalib.target.pattern import smooth_star, star_signed_distance_normal

__all__ = [
    "BlockFit",
    "BlockModel",
    "BlockProblem",
    "DeconvSettings",
    "block_windows",
    "fit_blocks",
    "render_model",
    "update_homography",
]

Brightness = Literal["after_blur", "before_blur"]
PatternModel = Literal["signed_distance", "sigmoid_sin"]

_NUM_P = 6
"""Brightness coefficients ``(a1, a2, a3, b1, b2, b3)``."""
_NUM_NL = 10
"""Non-linear parameters: 8 of ``H`` and the 2 of ``alpha``."""


@dataclass(frozen=True)
class DeconvSettings:
    """Settings of :func:`fit_blocks`; the defaults are the measured choice (docs/deconvolution.md).

    Attributes:
        kernel_size: ``K`` (odd), PSF window side in px; about 1.5 x the longest blur is best.
        ridge: ``lambda`` of ``eq:deconvolution``, relative to the mean energy of a kernel
            entry's column of the design (dimensionless).
        ridge_border: growth of the ridge towards the kernel's border,
            ``rho(d) = 1 + ridge_border (|d| / c)^ridge_power``: a pedestal in ``k`` is nearly
            indistinguishable from the offset ``B`` and would move the PSF centroid.
        ridge_power: exponent of that growth.
        tau: soft-edge width of the ``"signed_distance"`` pattern (px).
        supersample: latent samples per pixel side (1: pixel centres).
        beta: edge sharpness of the ``"sigmoid_sin"`` pattern (dimensionless).
        pattern: latent pattern model, ``"signed_distance"`` or ``"sigmoid_sin"``.
        brightness: model order, ``"after_blur"`` ``A (k * S) + B`` or ``"before_blur"``
            ``k * (S A + B)`` (the paper's).
        outer_iterations: stages of (integer re-centring, support, LM steps) after the coarse
            initial kernel.
        gn_steps: Levenberg-Marquardt steps per stage (each re-solves the kernel).
        support_threshold: kernel entries below this share of the previous stage's peak are
            fixed at zero (0: the whole window).
        support_dilation: the support is grown by this many px.
        nonnegative: fix kernel entries that come out negative at zero (active-set passes).
        nonnegative_passes: active-set passes per kernel solve.
        centroid_threshold: kernel values below this share of the peak are ignored by the PSF
            centroid (:func:`psf_centroid`); 0 keeps all (the kernel is non-negative).
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
        hinted_stages: stages of blocks given an expected PSF (:func:`fit_blocks`'s
            ``psf_hint``), which skip the coarse kernel and start from its support.
        fixed_steps: LM steps of blocks given their PSF (:func:`fit_blocks`'s ``psf_fixed``).
        device: torch device of the solve (``"cpu"``, ``"cuda"``, ...).
        dtype: ``"float32"`` or ``"float64"`` for image-sized tensors; the small systems and
            ``H`` are always float64.
    """

    kernel_size: int = 17
    ridge: float = 1e-3
    ridge_border: float = 30.0
    ridge_power: float = 4.0
    tau: float = 0.25
    supersample: int = 1
    beta: float = 5.0
    pattern: PatternModel = "signed_distance"
    brightness: Brightness = "after_blur"
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
    hinted_stages: int = 1
    fixed_steps: int = 6
    device: str = "cpu"
    dtype: str = "float32"

    def __post_init__(self) -> None:
        if self.kernel_size < 3 or self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd and >= 3, got {self.kernel_size}")
        if self.pattern not in ("signed_distance", "sigmoid_sin"):
            raise ValueError(f"pattern must be 'signed_distance' or 'sigmoid_sin', got {self.pattern!r}")
        if self.brightness not in ("after_blur", "before_blur"):
            raise ValueError(f"brightness must be 'after_blur' or 'before_blur', got {self.brightness!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        if self.tau <= 0 or self.beta <= 0 or self.ridge < 0 or self.ridge_border < 0:
            raise ValueError("tau and beta must be positive, ridge and ridge_border non-negative")
        if min(self.outer_iterations, self.hinted_stages, self.batch_size, self.stage_batch_size,
               self.supersample, self.fixed_steps) < 1 or self.gn_steps < 0:
            raise ValueError("outer_iterations, hinted_stages, fixed_steps, batch_size, stage_batch_size and "
                             "supersample must be >= 1, gn_steps >= 0")
        if not self.loss_extent > 0:
            raise ValueError(f"loss_extent must be positive, got {self.loss_extent}")
        if not 0.0 <= self.support_threshold < 1.0 or self.support_dilation < 0:
            raise ValueError("support_threshold must be in [0, 1), support_dilation >= 0")

    @property
    def radius(self) -> int:
        """Kernel radius ``c = (K - 1) / 2`` px."""
        return (self.kernel_size - 1) // 2

    @property
    def torch_dtype(self) -> torch.dtype:
        """The torch dtype of :attr:`dtype`."""
        return torch.float32 if self.dtype == "float32" else torch.float64


@dataclass(eq=False)
class BlockFit:
    """Batched result of :func:`fit_blocks` for ``B`` blocks (``K`` the kernel size).

    Blocks that were not fitted (status ``outside_image`` or ``degenerate_homography``) keep
    their initial ``H`` and carry NaN in every other float field.

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
        settings: the settings used.
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
            return fitted & (self.centre_step < tol_px)

    @property
    def H_fit(self) -> np.ndarray:
        """``(B, 3, 3)``: the fitted homographies before re-centring, ``T(-centroid) H``."""
        return translation(-self.centroid) @ self.H

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


# ----------------------------------------------------------------------------- small helpers
_DIRECT_CONV_MAX_KERNEL = 29
"""Largest kernel side (px) convolved directly rather than by FFT: on one CPU thread the direct
(depthwise) convolution of the 9 Jacobian channels takes 0.28x the FFT's time at 7 px, 0.44x at
19 px and 0.7x at 29 px; at 31 px the FFT is faster (``docs/deconvolution.md``)."""


class _Factor(NamedTuple):
    """The Cholesky factor of a kernel solve's free system, compacted to its free entries.

    ``chol (b, F, F)`` factors ``G`` restricted to ``index (b, F)`` (the free entries first, in
    order, then padding); ``weight (b, F)`` is 1 on free entries and 0 on padding, whose rows
    and columns are the identity.
    """

    chol: torch.Tensor
    index: torch.Tensor
    weight: torch.Tensor

    def solve(self, rhs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``G_FF^{-1} rhs_F`` for ``rhs (b, M, c)``: ``(rhs_F (b, F, c), solution (b, F, c))``."""
        index = self.index[..., None].expand(-1, -1, rhs.shape[2])
        sel = torch.gather(rhs, 1, index) * self.weight[..., None]
        return sel, torch.cholesky_solve(sel, self.chol)


def _solve_nonnegative(G: torch.Tensor, rhs: torch.Tensor, m: int, passes: int
                       ) -> tuple[torch.Tensor, _Factor]:
    """``x = G^{-1} rhs`` with the first ``m`` entries that come out negative fixed at zero.

    Active-set passes: each fixes the entries that are negative in the previous solution (the
    others are free) and re-solves the free block of ``G`` (Cholesky, ``G`` is symmetric positive
    definite through the ridge), gathered into a ``(b, F, F)`` system over the largest free count
    ``F`` (most kernel entries end fixed, so the later passes are cheap); the passes stop early
    once no block's active set changes.

    Args:
        G: ``(b, M, M)`` float64 normal matrices; rhs: ``(b, M, 1)``; m: constrained entries
            (the kernel's); passes: at most this many active-set passes (0: unconstrained).
    Returns:
        ``x (b, M)`` (fixed entries exactly 0) and the :class:`_Factor` of the final free system.
    """
    b, M = rhs.shape[:2]
    dev = G.device
    index = torch.arange(M, device=dev).expand(b, M)
    weight = torch.ones((b, M), dtype=G.dtype, device=dev)
    # cholesky_ex: a bad block must not stop the batch
    factor = _Factor(torch.linalg.cholesky_ex(G)[0], index, weight)
    x = torch.cholesky_solve(rhs, factor.chol)[..., 0]
    free = torch.ones((b, M), dtype=torch.bool, device=dev)
    for _ in range(passes):
        keep = free.clone()
        keep[:, :m] &= x[:, :m] > 0
        if torch.equal(keep, free):
            break
        free = keep
        F = int(free.sum(dim=1).max())
        index = torch.argsort((~free).to(torch.int8), dim=1, stable=True)[:, :F]
        weight = torch.gather(free, 1, index).to(G.dtype)
        flat = (index[:, :, None] * M + index[:, None, :]).reshape(b, F * F)
        Gf = torch.gather(G.reshape(b, M * M), 1, flat).reshape(b, F, F)
        Gf *= weight[:, :, None] * weight[:, None, :]
        Gf.diagonal(dim1=1, dim2=2).add_(1.0 - weight)
        factor = _Factor(torch.linalg.cholesky_ex(Gf)[0], index, weight)
        xf = factor.solve(rhs)[1][..., 0] * weight
        x = torch.zeros_like(x).scatter_(1, index, xf)
    return x, factor


def _support(k: torch.Tensor, threshold: float, dilation: int) -> torch.Tensor:
    """``(b, K, K)`` bool: the entries of kernels ``k (b, K, K)`` at or above ``threshold`` of
    their peak, dilated by ``dilation`` px (a square structuring element)."""
    core = (k >= threshold * k.amax(dim=(1, 2), keepdim=True)).to(torch.float32)
    return nnf.max_pool2d(core[:, None], 2 * dilation + 1, stride=1, padding=dilation)[:, 0] > 0


def _fft_size(n: int) -> int:
    """The smallest ``2^a 3^b 5^c >= n``."""
    best = 1 << max(n - 1, 0).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best


def update_homography(H: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """The block-side update ``H (I + Delta)``, normalised (``H[2, 2] = 1``), for ``H (b, 3, 3)``
    and ``delta (b, 8)``: ``Delta = [[d1, d2, d3], [d4, d5, d6], [d7, d8, 0]]`` (the parameters of
    :meth:`BlockProblem.latent`'s Jacobian)."""
    step = torch.zeros_like(H)
    step[:, 0] = delta[:, 0:3]
    step[:, 1] = delta[:, 3:6]
    step[:, 2, :2] = delta[:, 6:8]
    out = H @ (torch.eye(3, dtype=H.dtype, device=H.device) + step)
    return out / out[:, 2:, 2:]


# ----------------------------------------------------------------------------- block windows
def block_windows(H0: np.ndarray, image_shape: tuple[int, int], s: DeconvSettings
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[BlockStatus]]:
    """Windows of the blocks and which can be fitted (:func:`fit_blocks`'s rules).

    Args:
        H0: ``(B, 3, 3)`` block homographies; image_shape: ``(height, width)``; s: the settings
            (loss extent, window margin, size limits).
    Returns:
        ``origin (B, 2)`` int ``(x0, y0)``, ``size (B, 2)`` int ``(w, h)`` of the observed
        window (bounding box of ``H([-e, e]^2)``, ``e`` the loss extent, plus the margin), the
        normalised ``H (B, 3, 3)`` and a status per block (``accepted`` for those to fit).
    """
    height, width = image_shape
    e = s.loss_extent
    corners = np.array([[-e, -e, 1], [e, -e, 1], [e, e, 1], [-e, e, 1]], dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        finite = np.all(np.isfinite(H0), axis=(1, 2))
        h = np.where(finite[:, None, None], H0, 0.0)
        ok = finite & (np.abs(h[:, 2, 2]) >= 1e-12 * np.maximum(np.abs(h).max(axis=(1, 2)), 1e-300))
        H = np.where(ok[:, None, None], h / np.where(ok, h[:, 2, 2], 1.0)[:, None, None], H0)
        xs = np.einsum("cj,bij->bci", corners, np.where(ok[:, None, None], H, np.eye(3)))  # (B, 4, 3)
        ok &= np.all(xs[..., 2] > 1e-9, axis=1)
        pts = xs[..., :2] / np.where(ok[:, None], xs[..., 2], 1.0)[..., None]
        edges = np.roll(pts, -1, axis=1) - pts
        nxt = np.roll(edges, -1, axis=1)
        cross = edges[..., 0] * nxt[..., 1] - edges[..., 1] * nxt[..., 0]
        area = 0.5 * np.abs(np.sum(pts[..., 0] * np.roll(pts[..., 1], -1, axis=1)
                                   - np.roll(pts[..., 0], -1, axis=1) * pts[..., 1], axis=1))
        ok &= (np.all(cross > 0, axis=1) | np.all(cross < 0, axis=1)) & (np.sqrt(area) / e >= s.min_square_px)
        lo = np.where(ok[:, None], np.floor(pts.min(axis=1)), 0).astype(np.int64) - s.window_margin
        hi = np.where(ok[:, None], np.ceil(pts.max(axis=1)), 0).astype(np.int64) + s.window_margin
    ok &= np.all(hi - lo + 1 <= s.max_window_px, axis=1)
    origin = np.where(ok[:, None], lo, 0)
    size = np.where(ok[:, None], hi - lo + 1, 0)
    outside = (lo[:, 0] < 0) | (lo[:, 1] < 0) | (hi[:, 0] > width - 1) | (hi[:, 1] > height - 1)
    status = [BlockStatus.DEGENERATE_HOMOGRAPHY if not good else
              BlockStatus.OUTSIDE_IMAGE if out else BlockStatus.ACCEPTED
              for good, out in zip(ok.tolist(), outside.tolist(), strict=True)]
    return origin, size, H, status


@dataclass
class _Design:
    """Index sets of one solver stage (``b`` blocks, ``n`` pixels, ``m`` kernel entries, padded).

    Attributes:
        mask: ``(b, h, w)`` bool, the loss's pixels (inside the square at the stage's start).
        pix: ``(b, n)`` flat indices of those pixels in the observed grid; ``pix_w`` 0/1 weights.
        patch: ``(b, m n)`` flat latent index of kernel entry ``t``'s patch value at pixel ``p``
            (at ``t n + p``): a pixel's patch origin plus the entry's offset. Padded pixels and
            entries point into zeros appended to the latent.
        taps_w: ``(b, m)`` 0/1 weights of the kernel entries; ``kernel_index`` their flat index
            ``i K + j`` in the kernel; ``rho`` their ridge weights.
        coarse: the entries are the 2-px lattice taps of the initial solve (tent-interpolated).
        fixed: ``(b, K, K)`` given kernels, or None. With them the kernel has one unknown, its
            scale ``a3`` (``m = 1``; ``patch``, ``taps_w``, ``kernel_index`` and ``rho`` are
            empty): the design row is the convolution ``k * S`` at the pixels.
        u, v: ``(b, n)`` normalised coordinates at the pixels.
        U: ``(b, 3, n)`` the offset's design rows ``(u, v, 1)`` (0 on padding).
        img: ``(b, n)`` observed grey levels (0 on padding).
    """

    mask: torch.Tensor
    pix: torch.Tensor
    pix_w: torch.Tensor
    patch: torch.Tensor
    taps_w: torch.Tensor
    kernel_index: torch.Tensor
    rho: torch.Tensor
    coarse: bool
    fixed: torch.Tensor | None
    u: torch.Tensor
    v: torch.Tensor
    U: torch.Tensor
    img: torch.Tensor


class BlockProblem:
    """Tensors of one batch of blocks padded to a common window (``b`` blocks).

    Observed (evaluation) grid ``(h, w)``; latent grid ``(h + 2c, w + 2c)`` whose pixel
    ``(i, j)`` is image pixel ``origin + (j - c, i - c)``. Homographies are kept in *latent-local*
    pixels, ``H_loc = T(-(origin - c)) H``, in float64.
    """

    def __init__(self, image: torch.Tensor, pixel_ok: torch.Tensor | None, origin: np.ndarray,
                 size: np.ndarray, num_segments: int, s: DeconvSettings) -> None:
        self.s = s
        self.N = num_segments
        dev, dt = image.device, s.torch_dtype
        self.dt = dt
        r = self.r = s.radius
        b = origin.shape[0]
        h, w = self.h, self.w = int(size[:, 1].max()), int(size[:, 0].max())
        self.Hl, self.Wl = h + 2 * r, w + 2 * r
        self.size = size
        self.lat_origin = origin - r
        rows = torch.as_tensor(origin[:, 1, None] + np.arange(h), device=dev)
        cols = torch.as_tensor(origin[:, 0, None] + np.arange(w), device=dev)
        rows_c = rows.clamp(0, image.shape[0] - 1)[:, :, None]
        cols_c = cols.clamp(0, image.shape[1] - 1)[:, None, :]
        img = image[rows_c, cols_c].to(dt)
        inside = torch.as_tensor((np.arange(h)[None, :, None] < size[:, 1, None, None])
                                 & (np.arange(w)[None, None, :] < size[:, 0, None, None]), device=dev)
        inside &= torch.isfinite(img)
        self.img = torch.where(inside, img, 0.0)
        self.usable = inside if pixel_ok is None else inside & pixel_ok[rows_c, cols_c]
        # normalised coordinates u, v on the latent grid (the observed grid is its interior)
        self.uv_centre = origin + (size - 1) / 2.0
        self.uv_scale = np.maximum(size.max(axis=1), 2) / 2.0
        cen = torch.as_tensor(self.uv_centre - self.lat_origin, device=dev, dtype=dt)
        sc = torch.as_tensor(self.uv_scale, device=dev, dtype=dt)
        jl = torch.arange(self.Wl, device=dev, dtype=dt)
        il = torch.arange(self.Hl, device=dev, dtype=dt)
        shape = (b, self.Hl, self.Wl)
        self.u_l = ((jl[None, None, :] - cen[:, 0, None, None]) / sc[:, None, None]).expand(shape)
        self.v_l = ((il[None, :, None] - cen[:, 1, None, None]) / sc[:, None, None]).expand(shape)
        self.u_e = self.u_l[:, r:r + h, r:r + w]
        self.v_e = self.v_l[:, r:r + h, r:r + w]
        d = torch.arange(s.kernel_size, device=dev, dtype=torch.float64) - r
        rad = torch.sqrt(d[None, :] ** 2 + d[:, None] ** 2) / max(r, 1)
        self.rho = (1.0 + s.ridge_border * rad**s.ridge_power).reshape(-1)
        self.offs = d

    def subset(self, idx: np.ndarray) -> BlockProblem:
        """The blocks ``idx`` alone, the padded windows cropped to their largest one (the
        latent-local coordinates of a block do not change)."""
        out = copy.copy(self)
        r = self.r
        size = self.size[idx]
        h, w = out.h, out.w = int(size[:, 1].max()), int(size[:, 0].max())
        Hl, Wl = out.Hl, out.Wl = h + 2 * r, w + 2 * r
        t = torch.as_tensor(idx, device=self.img.device)
        out.size, out.lat_origin = size, self.lat_origin[idx]
        out.uv_centre, out.uv_scale = self.uv_centre[idx], self.uv_scale[idx]
        out.img, out.usable = self.img[t, :h, :w], self.usable[t, :h, :w]
        out.u_l, out.v_l = self.u_l[t, :Hl, :Wl], self.v_l[t, :Hl, :Wl]
        out.u_e, out.v_e = out.u_l[:, r:r + h, r:r + w], out.v_l[:, r:r + h, r:r + w]
        return out

    # ---------------------------------------------------------------- homography conversions
    def to_local(self, H: np.ndarray) -> torch.Tensor:
        """Image-pixel homographies ``(b, 3, 3)`` -> latent-local float64 tensors."""
        return torch.as_tensor(translation(-self.lat_origin.astype(np.float64)) @ H, device=self.img.device)

    def to_image(self, H_loc: torch.Tensor) -> np.ndarray:
        """Latent-local homographies -> image-pixel ``(b, 3, 3)`` float64 arrays."""
        return translation(self.lat_origin.astype(np.float64)) @ H_loc.cpu().numpy()

    # ------------------------------------------------------------------------- latent pattern
    def latent(self, H_loc: torch.Tensor, with_jac: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``S(H)`` on the latent grid ``(b, Hl, Wl)`` and, optionally, ``dS / d delta (b, 8, Hl, Wl)``.

        Averaged over ``supersample^2`` sub-pixel samples. ``delta`` parameterises the block-side
        update ``H <- H (I + Delta)``, ``Delta = [[d1, d2, d3], [d4, d5, d6], [d7, d8, 0]]``.
        """
        ss = self.s.supersample
        offs = [(o + 0.5) / ss - 0.5 for o in range(ss)]
        samples = [self._latent_at(H_loc, with_jac, ox, oy) for oy in offs for ox in offs]
        if ss == 1:
            return samples[0]
        S = torch.stack([smp[0] for smp in samples]).mean(dim=0)
        dS = torch.stack([smp[1] for smp in samples]).mean(dim=0) if with_jac else None
        return S, dS

    def _latent_at(self, H_loc: torch.Tensor, with_jac: bool, ox: float, oy: float
                   ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`latent` sampled at the pixel centres moved by ``(ox, oy)`` px."""
        M = torch.linalg.inv(H_loc).to(self.dt)
        dev = M.device
        j = torch.arange(self.Wl, device=dev, dtype=self.dt)[None, None, :] + ox
        i = torch.arange(self.Hl, device=dev, dtype=self.dt)[None, :, None] + oy

        def row(k: int) -> torch.Tensor:  # one full-grid add: the column and row terms broadcast
            return (M[:, k, 0, None, None] * j + M[:, k, 2, None, None]) + M[:, k, 1, None, None] * i

        inv_w = 1.0 / row(2).clamp_min(1e-6)  # w > 0 in front of the camera (H[2, 2] = 1)
        qx, qy = row(0) * inv_w, row(1) * inv_w
        if self.s.pattern == "signed_distance":
            dist, nx, ny = star_signed_distance_normal(qx, qy, self.N)  # unit normal of the nearest edge
            # |grad_x dist| = |J^T n| with J = dq/dx = (M[:2, :2] - q M[2, :2]) / w
            nq = nx * qx + ny * qy
            jx = nx * M[:, 0, 0, None, None] + ny * M[:, 1, 0, None, None] - nq * M[:, 2, 0, None, None]
            jy = nx * M[:, 0, 1, None, None] + ny * M[:, 1, 1, None, None] - nq * M[:, 2, 1, None, None]
            scale = (torch.sqrt(jx * jx + jy * jy) * inv_w).clamp_min(1e-9) * self.s.tau
            S = torch.sigmoid(dist / scale)
            if not with_jac:
                return S, None
            g = S * (1.0 - S) / scale  # dS/dq = g n, the normaliser held fixed
            gx, gy = g * nx, g * ny
        else:
            with torch.enable_grad():
                q = torch.stack([qx, qy], dim=-1).detach().requires_grad_(True)
                soft = smooth_star(q, self.N, self.s.beta)
                if not with_jac:
                    return soft.detach(), None
                (grad,) = torch.autograd.grad(soft.sum(), q)
                S = soft.detach()
            gx, gy = grad[..., 0].contiguous(), grad[..., 1].contiguous()
        # dq/d delta at delta = 0: -(Delta q~)_xy + q (Delta q~)_w with q~ = (q_x, q_y, 1)
        dS = torch.empty((H_loc.shape[0], 8, *S.shape[1:]), dtype=S.dtype, device=dev)
        torch.neg(gx, out=dS[:, 2])
        torch.neg(gy, out=dS[:, 5])
        torch.mul(dS[:, 2], qx, out=dS[:, 0])
        torch.mul(dS[:, 2], qy, out=dS[:, 1])
        torch.mul(dS[:, 5], qx, out=dS[:, 3])
        torch.mul(dS[:, 5], qy, out=dS[:, 4])
        radial = -(dS[:, 0] + dS[:, 4])
        torch.mul(radial, qx, out=dS[:, 6])
        torch.mul(radial, qy, out=dS[:, 7])
        return S, dS

    def square_mask(self, H_loc: torch.Tensor) -> torch.Tensor:
        """Observed pixels of the loss, ``|q|_inf <= e`` (the block's square for ``e = 1``; ``e``
        the loss extent) and usable, ``(b, h, w)``."""
        M = torch.linalg.inv(H_loc)
        dev = M.device
        j = torch.arange(self.w, device=dev, dtype=M.dtype)[None, None, :] + self.r
        i = torch.arange(self.h, device=dev, dtype=M.dtype)[None, :, None] + self.r
        qx, qy, wq = (M[:, k, 0, None, None] * j + M[:, k, 1, None, None] * i + M[:, k, 2, None, None]
                      for k in range(3))
        ew = self.s.loss_extent * wq
        inside = (wq > 0) & (qx.abs() <= ew) & (qy.abs() <= ew)
        return inside & self.usable

    # ---------------------------------------------------------------------------- convolution
    def conv(self, L: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """Valid convolution ``(k * L)`` of latent channels ``(b, C, Hl, Wl)`` -> ``(b, C, h, w)``.

        ``k`` is ``(b, K, K)`` (one kernel for every channel of a block) or ``(b, C, K, K)`` (one
        per channel; ``L`` may then have one channel, shared). Kernels up to
        :data:`_DIRECT_CONV_MAX_KERNEL` px: direct, as one depthwise ``conv2d`` over the ``b C``
        channels (a correlation, so with the kernel flipped). Larger: circular FFT convolution on
        a grid of at least ``(Hl, Wl)`` (5-smooth sides, the fast FFT sizes): the wrap-around only
        reaches the first ``2c`` rows and columns, outside the output.
        """
        k = k[:, None] if k.ndim == 3 else k
        b, C = L.shape[0], max(L.shape[1], k.shape[1])
        K = k.shape[-1]
        if K <= _DIRECT_CONV_MAX_KERNEL:
            weight = k.flip(-2, -1).expand(b, C, K, K).reshape(b * C, 1, K, K)
            L = L.expand(b, C, self.Hl, self.Wl)
            out = nnf.conv2d(L.reshape(1, b * C, self.Hl, self.Wl), weight, groups=b * C)
            return out.reshape(b, C, self.h, self.w)
        size = (_fft_size(self.Hl), _fft_size(self.Wl))
        kf = torch.fft.rfft2(k, s=size)
        out = torch.fft.irfft2(torch.fft.rfft2(L, s=size) * kf, s=size)
        r2 = 2 * self.r
        return out[..., r2:r2 + self.h, r2:r2 + self.w]

    # ------------------------------------------------------------------- the linear sub-problem
    def design(self, H_loc: torch.Tensor, support: torch.Tensor | None,
               fixed: torch.Tensor | None = None) -> _Design:
        """Index sets of a stage: the square's pixels at ``H`` and the kernel entries.

        ``support`` ``(b, K, K)`` bool selects the kernel entries; None selects the coarse
        initial kernel (taps on the 2-px lattice, tent-interpolated), or with ``fixed``
        ``(b, K, K)`` given kernels, of which only the scale is unknown.
        """
        b, K, r = H_loc.shape[0], self.s.kernel_size, self.r
        dev = H_loc.device
        mask = self.square_mask(H_loc)
        flat = mask.reshape(b, -1)
        n = max(int(flat.sum(dim=1).max()), 1)
        pix = torch.argsort((~flat).to(torch.int8), dim=1, stable=True)[:, :n]
        pix_w = torch.gather(flat, 1, pix).to(self.dt)
        base = (pix // self.w) * self.Wl + pix % self.w
        u = torch.gather(self.u_e.reshape(b, -1), 1, pix)
        v = torch.gather(self.v_e.reshape(b, -1), 1, pix)
        U = torch.stack([u, v, torch.ones_like(u)], dim=1) * pix_w[:, None, :]
        img = torch.gather(self.img.reshape(b, -1), 1, pix) * pix_w
        if fixed is not None:
            none = torch.zeros((b, 0), dtype=torch.int64, device=dev)
            return _Design(mask=mask, pix=pix, pix_w=pix_w, patch=none, taps_w=none.to(self.dt),
                           kernel_index=none, rho=self.rho[none], coarse=False, fixed=fixed.to(self.dt),
                           u=u, v=v, U=U, img=img)
        if support is None:
            rc = (r - 1) // 2  # taps at 2 px spacing whose tents stay inside the window
            c = torch.arange(-rc, rc + 1, device=dev) * 2
            dy, dx = (t.reshape(-1) for t in torch.meshgrid(c, c, indexing="ij"))
            kidx = ((dy + r) * K + dx + r)[None].expand(b, -1)
            taps_w = torch.ones(kidx.shape, dtype=self.dt, device=dev)
        else:
            sup = support.reshape(b, -1)
            m = max(int(sup.sum(dim=1).max()), 1)
            kidx = torch.argsort((~sup).to(torch.int8), dim=1, stable=True)[:, :m]
            taps_w = torch.gather(sup, 1, kidx).to(self.dt)
        # entry (i, j) is the offset d = (j - c, i - c); its patch value at observed pixel x is
        # the latent at x - d, i.e. latent-local (y + 2c - i, x + 2c - j); padded pixels and
        # entries read the zeros appended after the latent (:meth:`evaluate`)
        size = self.Hl * self.Wl
        taps = torch.where(taps_w > 0, (2 * r - kidx // K) * self.Wl + (2 * r - kidx % K), size)
        base = torch.where(pix_w > 0, base, size)
        patch = (base[:, None, :] + taps[:, :, None]).reshape(b, -1)
        return _Design(mask=mask, pix=pix, pix_w=pix_w, patch=patch, taps_w=taps_w, kernel_index=kidx,
                       rho=self.rho[kidx], coarse=support is None, fixed=None, u=u, v=v, U=U, img=img)

    def _patch_source(self, S: torch.Tensor, alpha: torch.Tensor, des: _Design
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """The latent image whose patches multiply the kernel entries, and the pixel weights
        (``A / a3`` after the blur, 1 before; 0 off the loss's pixels)."""
        if self.s.brightness == "after_blur":
            src = S
            a_e = 1.0 + alpha[:, 0, None].to(self.dt) * des.u + alpha[:, 1, None].to(self.dt) * des.v
        else:
            src = (1.0 + alpha[:, 0, None, None].to(self.dt) * self.u_l
                   + alpha[:, 1, None, None].to(self.dt) * self.v_l) * S
            a_e = torch.ones_like(des.u)
        if des.coarse:
            tent = torch.tensor([0.5, 1.0, 0.5], dtype=self.dt, device=S.device)
            src = nnf.conv2d(src[:, None], (tent[:, None] * tent[None, :])[None, None], padding=1)[:, 0]
        return src, a_e * des.pix_w

    def kernel(self, x: torch.Tensor, des: _Design) -> torch.Tensor:
        """The kernel ``k~ (b, K, K)`` of a solution ``x`` (unnormalised, ``a3 k``)."""
        if des.fixed is not None:
            return x[:, :1, None].to(des.fixed.dtype) * des.fixed
        b, K = x.shape[0], self.s.kernel_size
        m = des.kernel_index.shape[1]
        k = torch.zeros((b, K * K), dtype=x.dtype, device=x.device)
        k.scatter_(1, des.kernel_index, x[:, :m] * des.taps_w.to(x.dtype))
        k = k.reshape(b, K, K)
        if des.coarse:
            tent = torch.tensor([0.5, 1.0, 0.5], dtype=x.dtype, device=x.device)
            k = nnf.conv2d(k[:, None], (tent[:, None] * tent[None, :])[None, None], padding=1)[:, 0]
        return k

    def evaluate(self, H_loc: torch.Tensor, alpha: torch.Tensor, des: _Design, lam: torch.Tensor | None,
                 with_jac: bool) -> dict[str, torch.Tensor]:
        """Solve the kernel sub-problem at ``(H, alpha)`` and, optionally, the reduced Jacobian.

        The model is linear in ``x = (k~, b)``: the stage's kernel entries of ``k~ = a3 k`` and
        the observed-grid affine offset (3 coefficients of ``u, v, 1``), ``m = D^T x`` with ``D``
        the ``(m + 3, n)`` design of latent patches (times ``A / a3``). ``x* = (D D^T +
        Lambda)^{-1} D I`` (the ridge of ``eq:deconvolution``), optionally with kernel entries
        that come out negative fixed at zero (active-set passes). With ``J`` the ``(10, n)``
        derivative of ``m`` w.r.t. the non-linear parameters (8 of ``H``, 2 of ``alpha``) at fixed
        ``x*``, the variable-projection Gauss-Newton system (Kaufman) is
        ``N = J J^T - Y^T G^{-1} Y`` with ``Y = D J^T``, and the gradient ``g = J r``.

        ``Lambda = lambda rho(d)`` times the mean energy of a kernel column (``lam``; None computes
        it here, to be kept fixed through a stage so that objectives compare).

        With given kernels (``des.fixed``, brightness after the blur) ``D``'s kernel part is the
        one row ``(k * S) A / a3`` and ``x = (a3, b)``; the same Jacobian follows from the same
        convolutions.

        Returns:
            dict with ``x (b, m + 3)`` float64, ``obj (b,)`` (``sum r^2 + k~^T Lambda k~``),
            ``sse (b,)``, ``lam (b, m + 3)``, and with ``with_jac`` also ``N (b, 10, 10)`` and
            ``g (b, 10)`` float64.
        """
        b = H_loc.shape[0]
        S, dS = self.latent(H_loc, with_jac=with_jac)
        src, w = self._patch_source(S, alpha, des)
        fixed = des.fixed is not None
        m, n = (1 if fixed else des.kernel_index.shape[1]), des.pix.shape[1]
        if lam is None:
            scale = ((w * w).sum(dim=1) * (src * src).mean(dim=(1, 2))).double().clamp_min(1e-12)
            tail = torch.full((b, 3), 1e-9, dtype=des.rho.dtype, device=des.rho.device)
            ridge = tail[:, :1] if fixed else self.s.ridge * des.rho
            lam = torch.cat([ridge, tail], dim=1) * scale[:, None]
        # D = [P; U] (b, m + 3, n): the kernel entries' patches, then the offset's rows (u, v, 1)
        D = torch.empty((b, m + 3, n), dtype=self.dt, device=src.device)
        if fixed:
            chans = torch.cat([S[:, None], dS], dim=1) if with_jac else S[:, None]
            conv = torch.gather(self.conv(chans, des.fixed).reshape(b, chans.shape[1], -1), 2,
                                des.pix[:, None, :].expand(-1, chans.shape[1], -1))
            D[:, :1] = conv[:, :1]
        else:
            padded = torch.cat([src.reshape(b, -1), torch.zeros_like(src.reshape(b, -1)),
                                torch.zeros_like(src[:, 0, :1])], dim=1)
            D[:, :m] = torch.gather(padded, 1, des.patch).reshape(b, m, n)
        P = D[:, :m]
        if self.s.brightness == "after_blur":
            P.mul_(w[:, None, :])
        D[:, m:] = des.U
        G = (D @ D.transpose(1, 2)).double()
        G.diagonal(dim1=1, dim2=2).add_(lam)
        rhs = (des.img[:, None, :] @ D.transpose(1, 2)).double().transpose(1, 2)  # (b, m + 3, 1)
        passes = self.s.nonnegative_passes if self.s.nonnegative and not fixed else 0
        x, factor = _solve_nonnegative(G, rhs, m, passes)
        res = des.img - (x.to(self.dt)[:, None, :] @ D)[:, 0]
        sse = (res * res).sum(dim=1).double()
        out = {"x": x, "obj": sse + (x * x * lam).sum(dim=1), "sse": sse, "lam": lam}
        if not with_jac:
            return out
        if fixed:  # the model is a3 (k * S): its convolutions, scaled
            conv = conv * x[:, :1, None].to(self.dt)
        elif self.s.brightness == "after_blur":
            conv = self.conv(torch.cat([S[:, None], dS], dim=1), self.kernel(x, des).to(self.dt))
            conv = torch.gather(conv.reshape(b, 9, -1), 2, des.pix[:, None, :].expand(-1, 9, -1))
        if self.s.brightness == "after_blur":
            C = conv[:, 0]
            J = torch.cat([conv[:, 1:] * w[:, None, :], (des.u * C * des.pix_w)[:, None],
                           (des.v * C * des.pix_w)[:, None]], dim=1)
        else:
            a_l = (1.0 + alpha[:, 0, None, None].to(self.dt) * self.u_l
                   + alpha[:, 1, None, None].to(self.dt) * self.v_l)
            chans = torch.cat([dS * a_l[:, None], (self.u_l * S)[:, None], (self.v_l * S)[:, None]], dim=1)
            J = torch.gather(self.conv(chans, self.kernel(x, des).to(self.dt)).reshape(b, _NUM_NL, -1), 2,
                             des.pix[:, None, :].expand(-1, _NUM_NL, -1)) * des.pix_w[:, None, :]
        Y, Z = factor.solve((J @ D.transpose(1, 2)).double().transpose(1, 2))  # (b, F, 10), free rows
        out["N"] = (J @ J.transpose(1, 2)).double() - Y.transpose(1, 2) @ Z
        out["g"] = (J @ res[..., None]).double()[..., 0]
        return out

    def model(self, H_loc: torch.Tensor, k: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
        """The model image ``m (b, h, w)`` for ``H``, a kernel ``k (b, K, K)`` and ``p (b, 6)``."""
        S, _ = self.latent(H_loc, with_jac=False)
        p = coeffs.to(self.dt)
        if self.s.brightness == "after_blur":
            A = p[:, 0, None, None] * self.u_e + p[:, 1, None, None] * self.v_e + p[:, 2, None, None]
            Bm = p[:, 3, None, None] * self.u_e + p[:, 4, None, None] * self.v_e + p[:, 5, None, None]
            return A * self.conv(S[:, None], k)[:, 0] + Bm
        A = p[:, 0, None, None] * self.u_l + p[:, 1, None, None] * self.v_l + p[:, 2, None, None]
        Bl = p[:, 3, None, None] * self.u_l + p[:, 4, None, None] * self.v_l + p[:, 5, None, None]
        return self.conv((A * S + Bl)[:, None], k)[:, 0]

    def centre_estimate(self, H_loc: torch.Tensor, x: torch.Tensor, des: _Design) -> torch.Tensor:
        """``H(0, 0) + centroid(k)`` ``(b, 2)`` in latent-local px: the time-averaged star centre."""
        k = self.kernel(x, des).double()
        if self.s.centroid_threshold > 0:
            k = torch.where(k >= self.s.centroid_threshold * k.amax(dim=(1, 2), keepdim=True), k, 0.0)
        tot = k.sum(dim=(1, 2)).clamp_min(1e-300)
        c = torch.stack([k.sum(dim=1) @ self.offs, k.sum(dim=2) @ self.offs], dim=1) / tot[:, None]
        return H_loc[:, :2, 2] / H_loc[:, 2:, 2] + c

    # -------------------------------------------------------------------------- recentring
    def recentre_int(self, H_loc: torch.Tensor, k: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
        """Integer re-centring ``H' = T(n) H``, ``n = round(centroid(k))``; the next solve re-centres k."""
        kn = k.detach().cpu().numpy()
        with np.errstate(invalid="ignore", divide="ignore"):
            c = psf_centroid(kn / kn.sum(axis=(1, 2), keepdims=True), self.s.centroid_threshold)
        n = np.where(np.isfinite(c), np.round(c), 0.0)
        return torch.as_tensor(translation(n), device=H_loc.device) @ H_loc, n

    def support(self, k: torch.Tensor, n: np.ndarray) -> torch.Tensor:
        """Kernel support ``(b, K, K)`` bool of the next stage: ``k`` moved by the integer
        re-centring ``n`` (``k'(d) = k(d + n)``), entries above ``support_threshold`` of the peak,
        dilated by ``support_dilation`` px."""
        K = self.s.kernel_size
        b = k.shape[0]
        dev = k.device
        nt = torch.as_tensor(n.astype(np.int64), device=dev)
        ar = torch.arange(K, device=dev)
        ri = ar[None, :] + nt[:, 1, None]
        cj = ar[None, :] + nt[:, 0, None]
        ok = ((ri >= 0) & (ri < K))[:, :, None] & ((cj >= 0) & (cj < K))[:, None, :]
        k = k[torch.arange(b, device=dev)[:, None, None], ri.clamp(0, K - 1)[:, :, None],
              cj.clamp(0, K - 1)[:, None, :]] * ok
        return _support(k, self.s.support_threshold, self.s.support_dilation)

    # --------------------------------------------------------------------------- the LM loop
    def lm_stage(self, H_loc: torch.Tensor, alpha: torch.Tensor, des: _Design, steps: int
                 ) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Levenberg-Marquardt on ``(H, alpha)`` with ``(k~, b)`` projected out (variable projection).

        Each step costs one kernel solve; a step that does not lower the objective is undone and
        retried from the best point with a larger damping. ``best["move"] (b,)`` is how far the
        last accepted step moved the star-centre estimate (px; 0 if none was accepted).
        """
        b = H_loc.shape[0]
        dev = H_loc.device
        best = self.evaluate(H_loc, alpha, des, None, with_jac=steps > 0)
        lam = best["lam"]
        H_best, a_best = H_loc, alpha
        c_best = self.centre_estimate(H_best, best["x"], des)
        move = torch.zeros(b, dtype=torch.float64, device=dev)
        mu = torch.full((b,), 1e-3, device=dev, dtype=torch.float64)
        for it in range(steps):
            diag = best["N"].diagonal(dim1=1, dim2=2)
            A = best["N"] + torch.diag_embed(mu[:, None] * diag + 1e-12 * diag.mean(1, keepdim=True) + 1e-30)
            delta = torch.nan_to_num(torch.linalg.solve_ex(A, best["g"][..., None])[0][..., 0])
            H_try = update_homography(H_best, delta[:, :8])
            a_try = a_best + delta[:, 8:10]
            cur = self.evaluate(H_try, a_try, des, lam, with_jac=it < steps - 1)
            accept = torch.isfinite(cur["obj"]) & (cur["obj"] < best["obj"])
            H_best = torch.where(accept[:, None, None], H_try, H_best)
            a_best = torch.where(accept[:, None], a_try, a_best)
            c_try = self.centre_estimate(H_try, cur["x"], des)
            move = torch.where(accept, torch.linalg.norm(c_try - c_best, dim=1), move)
            c_best = torch.where(accept[:, None], c_try, c_best)
            for key in cur:
                sel = accept.reshape(-1, *([1] * (best[key].ndim - 1)))
                best[key] = torch.where(sel, cur[key], best[key])
            mu = torch.where(accept, mu / 3.0, mu * 4.0)
        best["move"] = move
        return H_best, a_best, best


# ----------------------------------------------------------------------------------- fitting
_GROUP_COST = 8.6e7
"""Fixed cost of solving one more stage group (its Python-level tensor operations), in units of
the multiply-adds of a normal matrix ``D D^T`` (measured on one CPU thread: ~3 ms per kernel
solve against ~0.035 ns per multiply-add)."""
_LATENT_COST = 4.3e3
"""Cost of one latent-grid pixel of a kernel solve (the pattern, its Jacobian and the
convolutions: ~150 ns, measured with FFT convolutions), in the same units."""


def _stage_groups(support: np.ndarray, pixels: np.ndarray, size: np.ndarray, radius: int, most: int
                  ) -> list[np.ndarray]:
    """Blocks sorted by kernel support, cut into consecutive groups of at most ``most`` blocks.

    A group is padded to its largest support ``m``, loss pixel count ``n`` and window; the cuts
    minimise the modelled cost of its kernel solves, ``sum over groups of (blocks x ((m + 3)^2 n
    + _LATENT_COST x latent pixels) + _GROUP_COST)`` (dynamic programming over the sorted order).

    Args:
        support: ``(b,)`` kernel entries per block; pixels: ``(b,)`` loss pixels per block;
            size: ``(b, 2)`` window ``(w, h)`` px; radius: kernel radius ``c`` px;
            most: the largest group.
    Returns:
        The groups, as arrays of block indices.
    """
    order = np.argsort(support, kind="stable")
    rows = (support[order] + 3).tolist(), pixels[order].tolist(), (size[order] + 2 * radius).tolist()
    b = len(order)
    best = [0.0] + [math.inf] * b
    cut = [0] * (b + 1)
    for end in range(1, b + 1):
        m = n = w = h = 0
        for start in range(end - 1, max(end - most, 0) - 1, -1):
            m, n = max(m, rows[0][start]), max(n, rows[1][start])
            w, h = max(w, rows[2][start][0]), max(h, rows[2][start][1])
            cost = best[start] + (end - start) * (m * m * n + _LATENT_COST * w * h) + _GROUP_COST
            if cost < best[end]:
                best[end], cut[end] = cost, start
    groups = []
    end = b
    while end > 0:
        groups.append(order[cut[end]:end])
        end = cut[end]
    return groups[::-1]


def _fit_chunk(prob: BlockProblem, H: np.ndarray, hint: torch.Tensor | None,
               fixed: torch.Tensor | None = None) -> dict:
    """The solver schedule (module docstring) on one padded batch; per-block numpy results.

    After the coarse kernel the blocks are sorted by the size of their kernel support and solved
    in consecutive groups (:func:`_stage_groups`), each cropped to its own largest window. With
    expected PSFs ``hint (b, K, K)`` the first support is theirs and the coarse kernel is
    skipped (:attr:`DeconvSettings.hinted_stages` stages). With given PSFs ``fixed (b, K, K)``
    one stage of :attr:`DeconvSettings.fixed_steps` LM steps fits ``H`` and the brightness.
    """
    s = prob.s
    b = H.shape[0]
    H_loc = prob.to_local(H)
    if fixed is not None:
        groups = _stage_groups(np.ones(b), prob.square_mask(H_loc).sum(dim=(1, 2)).cpu().numpy(), prob.size,
                               prob.r, s.stage_batch_size)
        parts = [_fit_stages(prob.subset(idx), H_loc[t], None, 1, fixed[t])
                 for idx in groups for t in [torch.as_tensor(idx, device=H_loc.device)]]
        return _merge_groups(parts, groups)
    if hint is None:
        alpha = torch.zeros((b, 2), dtype=torch.float64, device=H_loc.device)
        des = prob.design(H_loc, None)
        k = prob.kernel(prob.evaluate(H_loc, alpha, des, None, with_jac=False)["x"], des)
        H_loc, n = prob.recentre_int(H_loc, k)
        support = prob.support(k, n)
        pixels = des.mask.sum(dim=(1, 2))
    else:
        support = _support(hint, s.support_threshold, s.support_dilation)
        pixels = prob.square_mask(H_loc).sum(dim=(1, 2))
    stages = s.outer_iterations if hint is None else s.hinted_stages
    groups = _stage_groups(support.sum(dim=(1, 2)).cpu().numpy(), pixels.cpu().numpy(), prob.size, prob.r,
                           s.stage_batch_size)
    parts = []
    for idx in groups:
        t = torch.as_tensor(idx, device=H_loc.device)
        parts.append(_fit_stages(prob.subset(idx), H_loc[t], support[t], stages))
    return _merge_groups(parts, groups)


def _merge_groups(parts: list[dict], groups: list[np.ndarray]) -> dict:
    """Per-block results of the stage groups back in the batch's order."""
    inverse = np.argsort(np.concatenate(groups))
    out = {key: np.concatenate([part[key] for part in parts])[inverse] for key in parts[0] if key != "masks"}
    masks = [m for part in parts for m in part["masks"]]
    out["masks"] = [masks[i] for i in inverse]
    return out


def _fit_stages(prob: BlockProblem, H_loc: torch.Tensor, support: torch.Tensor | None, stages: int,
                fixed: torch.Tensor | None = None) -> dict:
    """``stages`` stages from an integer re-centred ``H_loc`` and its first kernel ``support``
    (or with the given kernels ``fixed``), then the sub-pixel re-centring; per-block numpy
    results."""
    s = prob.s
    K = s.kernel_size
    alpha = torch.zeros((H_loc.shape[0], 2), dtype=torch.float64, device=H_loc.device)
    steps = s.gn_steps if fixed is None else s.fixed_steps
    for stage in range(stages):
        des = prob.design(H_loc, support, fixed)
        H_loc, alpha, best = prob.lm_stage(H_loc, alpha, des, steps)
        k = prob.kernel(best["x"], des)
        if stage < stages - 1:
            H_loc, n = prob.recentre_int(H_loc, k)
            support = prob.support(k, n)
    x = best["x"].cpu().numpy()
    H_fit = prob.to_image(H_loc)
    k_t = k.cpu().numpy()
    a3 = k_t.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        k_fit = k_t / a3[:, None, None]
    H_rc, psf, centroid = recentre(H_fit, k_fit, s.centroid_threshold)
    alpha_np = alpha.cpu().numpy()
    coeffs = np.stack([alpha_np[:, 0] * a3, alpha_np[:, 1] * a3, a3, x[:, -3], x[:, -2], x[:, -1]], axis=1)
    if s.brightness == "before_blur":
        # x holds k * B (an affine after the blur); B itself is shifted back by the kernel's mean
        offs = np.arange(K) - prob.r
        mean = np.stack([k_fit.sum(axis=1) @ offs, k_fit.sum(axis=2) @ offs], axis=1) / prob.uv_scale[:, None]
        coeffs[:, 5] += coeffs[:, 3] * mean[:, 0] + coeffs[:, 4] * mean[:, 1]
    npix = des.mask.sum(dim=(1, 2)).cpu().numpy()
    loss = best["sse"].cpu().numpy() / np.maximum(npix, 1)
    masks = des.mask.cpu().numpy()
    return {"H": H_rc / H_rc[:, 2:, 2:], "psf": psf, "psf_fit": k_fit, "coeffs": coeffs, "loss": loss,
            "centroid": centroid, "num_pixels": npix, "centre_step": best["move"].cpu().numpy(),
            "masks": [masks[i, :sz[1], :sz[0]] for i, sz in enumerate(prob.size)]}


def fit_blocks(image: np.ndarray, H0: np.ndarray, num_segments: int,
               settings: DeconvSettings | None = None, pixel_mask: np.ndarray | None = None,
               psf_hint: np.ndarray | None = None, psf_fixed: np.ndarray | None = None) -> BlockFit:
    """Fit ``eq:deconvolution`` to ``B`` star blocks of one grey image, all blocks batched.

    Each block's observed window is the bounding box of its loss area ``H0([-e, e]^2)`` (``e`` =
    :attr:`DeconvSettings.loss_extent`, 1: its square) plus :attr:`DeconvSettings.window_margin`
    px. The loss covers the window's pixels with ``|H^{-1} x|_inf <= e`` (taken at the start of
    every stage), the latent pattern the window grown by the kernel radius (periodic pattern, see
    the module docstring). Blocks are grouped by window size into batches of
    :attr:`DeconvSettings.batch_size`.

    Args:
        image: ``(height, width)`` grey levels (uint8 or float; 0..255 expected).
        H0: ``(B, 3, 3)`` initial homographies, block coordinates -> image px; the solver tolerates
            errors of a few px and a few percent of scale.
        num_segments: star segments ``N``.
        settings: solver settings (default :class:`DeconvSettings`).
        pixel_mask: optional ``(height, width)`` bool, False for pixels that must not enter any
            loss (saturation, occluders, a tag nearer to the square than the kernel radius).
            Non-finite pixels never enter a loss.
        psf_hint: optional ``(B, K, K)`` expected PSFs relative to ``H0`` (``K`` the settings'
            kernel size; e.g. the re-centred PSFs of the neighbouring blocks that predicted
            ``H0``): the first kernel support is taken from them (entries above
            ``support_threshold`` of the peak, dilated by ``support_dilation``, the rule between
            stages) instead of from a coarse kernel, and the blocks are solved in
            :attr:`DeconvSettings.hinted_stages` stages. A block whose hint is not finite or
            all zero gets the whole window as its first support.
        psf_fixed: optional ``(B, K, K)`` known PSFs (non-negative, e.g. the frame's motion-path
            field, :mod:`blurcalib.psf.field`): the kernels are kept, ``H``, the brightness
            gradient and its scale and offset are fitted (:attr:`DeconvSettings.fixed_steps` LM
            steps); the re-centring then moves ``H`` by each kernel's centroid. Brightness after
            the blur only; not with ``psf_hint``.
    Returns:
        :class:`BlockFit`. A block whose window leaves the image is ``outside_image``; one whose
        ``H0`` is non-finite, crosses the horizon, is not convex or is too small or large is
        ``degenerate_homography``. Neither is fitted, neither stops the batch. A fit without
        contrast (no star in the window), with non-finite results or still moving is
        ``not_converged``.
    """
    s = settings or DeconvSettings()
    img_np = np.asarray(image)
    if img_np.ndim != 2:
        raise ValueError(f"image must be (height, width), got shape {img_np.shape}")
    if pixel_mask is not None and np.shape(pixel_mask) != img_np.shape:
        raise ValueError(f"pixel_mask must have the image's shape {img_np.shape}, got {np.shape(pixel_mask)}")
    H0 = np.asarray(H0, dtype=np.float64).reshape(-1, 3, 3)
    B, K = H0.shape[0], s.kernel_size
    if psf_hint is not None:
        psf_hint = np.asarray(psf_hint, dtype=np.float64)
        if psf_hint.shape != (B, K, K):
            raise ValueError(f"psf_hint must be ({B}, {K}, {K}), got {psf_hint.shape}")
        empty = ~np.all(np.isfinite(psf_hint), axis=(1, 2)) | ~(np.nan_to_num(psf_hint).max(axis=(1, 2)) > 0)
        psf_hint = np.where(empty[:, None, None], 1.0, np.nan_to_num(psf_hint))
    if psf_fixed is not None:
        psf_fixed = np.asarray(psf_fixed, dtype=np.float64)
        if psf_fixed.shape != (B, K, K) or psf_hint is not None or s.brightness != "after_blur":
            raise ValueError(f"psf_fixed must be ({B}, {K}, {K}), without psf_hint, with brightness "
                             f"'after_blur'; got {psf_fixed.shape}, brightness {s.brightness!r}")
        if not np.all(np.isfinite(psf_fixed)) or np.any(psf_fixed < 0) \
                or not np.all(psf_fixed.sum(axis=(1, 2)) > 0):
            raise ValueError("psf_fixed must be finite, non-negative and non-zero")
    origin, size, Hn, status = block_windows(H0, img_np.shape, s)
    out = {"H": H0.copy(), "psf": np.full((B, K, K), np.nan), "psf_fit": np.full((B, K, K), np.nan),
           "coeffs": np.full((B, _NUM_P), np.nan), "loss": np.full(B, np.nan),
           "centroid": np.full((B, 2), np.nan), "num_pixels": np.zeros(B, dtype=np.int64),
           "centre_step": np.full(B, np.nan), "uv_centre": np.full((B, 2), np.nan),
           "uv_scale": np.full(B, np.nan)}
    masks = np.empty(B, dtype=object)
    masks[:] = [np.zeros((0, 0), dtype=bool)] * B
    todo = np.array([st == BlockStatus.ACCEPTED for st in status], dtype=bool)
    idx = np.flatnonzero(todo)
    if idx.size:
        dev = torch.device(s.device)
        img_t = torch.as_tensor(img_np.astype(np.float64 if s.dtype == "float64" else np.float32), device=dev)
        ok_t = None if pixel_mask is None else torch.as_tensor(np.asarray(pixel_mask, dtype=bool), device=dev)
        order = idx[np.argsort(size[idx].prod(axis=1), kind="stable")]
        for start in range(0, order.size, s.batch_size):
            sel = order[start:start + s.batch_size]
            prob = BlockProblem(img_t, ok_t, origin[sel], size[sel], num_segments, s)
            hint = None if psf_hint is None else torch.as_tensor(psf_hint[sel], device=dev)
            fixed = None if psf_fixed is None else torch.as_tensor(psf_fixed[sel], device=dev)
            res = _fit_chunk(prob, Hn[sel], hint, fixed)
            for i, m in zip(sel, res.pop("masks"), strict=True):
                masks[i] = m
            for key, val in res.items():
                out[key][sel] = val
            out["uv_centre"][sel] = prob.uv_centre
            out["uv_scale"][sel] = prob.uv_scale
    k_fit = out["psf_fit"]
    fitted = (todo & np.isfinite(out["loss"]) & np.all(np.isfinite(out["H"]), axis=(1, 2))
              & np.all(np.isfinite(k_fit), axis=(1, 2)) & (out["coeffs"][:, 2] > s.min_contrast)
              & (out["num_pixels"] > 0))
    converged = fitted & (out["centre_step"] < s.converge_tol_px)
    status = [BlockStatus.NOT_CONVERGED if todo[b] and not converged[b] else status[b] for b in range(B)]
    figures = {name: np.full(B, np.nan) for name in
               ("boundary_energy", "sigma_major", "sigma_minor", "eccentricity", "orientation")}
    if fitted.any():
        mom = psf_moments(k_fit[fitted])
        for name in ("sigma_major", "sigma_minor", "eccentricity", "orientation"):
            figures[name][fitted] = getattr(mom, name)
        figures["boundary_energy"][fitted] = boundary_energy(k_fit[fitted])
    return BlockFit(
        H=out["H"], psf=out["psf"], psf_fit=k_fit, coeffs=out["coeffs"], uv_centre=out["uv_centre"],
        uv_scale=out["uv_scale"], loss=out["loss"], residual_rms=np.sqrt(out["loss"]),
        centroid=out["centroid"], converged=converged, status=tuple(status),
        centre_step=out["centre_step"], origin=origin, window_size=size, num_pixels=out["num_pixels"],
        loss_extent=np.full(B, s.loss_extent), masks=masks, num_segments=num_segments, settings=s, **figures)


def render_model(fit: BlockFit, image: np.ndarray, index: int) -> BlockModel:
    """The fitted model, the observed window and the residual of block ``index`` (for a GUI).

    The model is evaluated from :attr:`BlockFit.H_fit`, :attr:`BlockFit.psf_fit` and
    :attr:`BlockFit.coeffs` (no re-fit), so ``mean(residual[mask]^2)`` reproduces
    :attr:`BlockFit.loss`.

    Args:
        fit: a result of :func:`fit_blocks`.
        image: the image that was fitted.
        index: the block.
    Raises:
        ValueError: the block was not fitted (status ``outside_image`` or
            ``degenerate_homography``).
    """
    if not np.all(np.isfinite(fit.psf_fit[index])):
        raise ValueError(f"block {index} was not fitted (status {fit.status[index].value})")
    s = fit.settings
    dev = torch.device(s.device)
    img_t = torch.as_tensor(np.asarray(image, dtype=np.float64 if s.dtype == "float64" else np.float32),
                            device=dev)
    sel = slice(index, index + 1)
    prob = BlockProblem(img_t, None, fit.origin[sel], fit.window_size[sel], fit.num_segments, s)
    k = torch.as_tensor(fit.psf_fit[sel], device=dev, dtype=prob.dt)
    p = torch.as_tensor(fit.coeffs[sel], device=dev, dtype=torch.float64)
    model = prob.model(prob.to_local(fit.H_fit[sel]), k, p)[0].double().cpu().numpy()
    obs = prob.img[0].double().cpu().numpy()
    return BlockModel(model, obs, obs - model, fit.masks[index].copy(), fit.origin[index].copy())
