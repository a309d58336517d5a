"""Local deconvolution of star blocks: homography, PSF and brightness per block, batched.

The paper's *Local Deconvolution* (``eq:deconvolution``) with the PSF re-centring of its *Local
Alignment*. For every block (the star square around one feature) we solve::

    argmin_{H, k, p}  sum_{x in square} (I(x) - m(x))^2  +  lambda sum_d rho(d) k(d)^2,   k >= 0,
    m = A(p) (k * S(H)) + B(p)

``A = a1 u + a2 v + a3`` and ``B = b1 u + b2 v + b3`` over normalised pixel coordinates
``u = (x - x_c) / s``, ``v = (y - y_c) / s`` (``(x_c, y_c)`` the window centre, ``s`` half the
window's longer side; both in :class:`blurcalib.deconv.result.BlockFit`), ``p = (a1, a2, a3, b1,
b2, b3)`` grey levels, ``S(H)`` the latent pattern (:mod:`blurcalib.deconv.latent`).

Conventions (as in ``pattern.py`` and ``results.py``):

* Pixels follow OpenCV: the centre of the top-left pixel is ``(0, 0)``, x right, y down.
* Block coordinates ``q in [-1, 1]^2``: star centre at 0, square corners at ``(+-1, +-1)``,
  feature coordinates ``p = (fx, fy) + q / 2``; a block's ``H`` (3 x 3) maps ``(q_x, q_y, 1)`` to
  homogeneous full-image pixels.
* The PSF ``k`` is ``K x K`` (``K`` odd, the PSF window, which the caller gives), ``k[i, j]``
  weighs the offset ``d = (j - c, i - c)`` px, ``c = (K - 1) / 2``, and
  ``(k * L)(x) = sum_d k(d) L(x - d)``: a PSF centroid at ``+d`` shows the blurred feature
  displaced by ``+d`` from the latent one.

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
negative fixed at zero; :mod:`blurcalib.deconv.problem`); Levenberg-Marquardt
(:mod:`blurcalib.deconv.lm`) then updates the 8 homography parameters and ``alpha`` on the reduced
problem, every step re-solving the kernel. Stages (:mod:`blurcalib.deconv.schedule`):

1. a coarse kernel (taps on a 2-px lattice, tent-interpolated) at ``H0``, the PSF only roughly;
2. ``outer_iterations`` times: integer re-centring of the kernel (``H <- T(n) H``, the
   translational ambiguity ``k' * L' = k * L``), a kernel support (entries above
   ``support_threshold`` of the peak, dilated), the loss's pixels from the current ``H``, and
   ``gn_steps`` LM steps;
3. sub-pixel re-centring ``H <- T(c) H`` with ``c`` the PSF centroid
   (:func:`blurcalib.psf.kernel.recentre`), so that
   ``H(0, 0)`` is the centre of the star's time-averaged image.

Three entry points, one per start of the PSF:

* :func:`fit_blocks`: the PSF is unknown (the schedule above) in a window of ``kernel_size`` px;
* :func:`fit_blocks_hinted`: each block has an expected PSF (region growing passes the mean
  re-centred PSF of the accepted neighbours that predicted it); stage 1 and the integer
  re-centring are skipped, the first support is the hint's, and
  :attr:`DeconvSettings.hinted_stages` stages run (one by default: half the kernel solves;
  ``docs/decisions/psf-hints.md``);
* :func:`fit_blocks_fixed`: each block's PSF is given (the frame's motion-path PSF field,
  :mod:`blurcalib.psf.path`) and kept: only ``H``, ``alpha`` and the brightness are fitted, in
  one stage of :attr:`DeconvSettings.fixed_steps` LM steps, and the re-centring moves ``H`` by
  the given kernel's centroid.

All blocks of a batch are solved together as padded ``(b, ...)`` tensors on
:attr:`DeconvSettings.device` (after the coarse kernel in groups of similar kernel support,
:attr:`DeconvSettings.stage_batch_size`): the solver loops over stages and LM steps, never over
blocks, pixels or kernel entries (one gather builds all patches of a step). The evidence for the
defaults: ``docs/decisions/`` and ``scripts/bench_deconv.py``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch

from blurcalib.deconv.convolution import denormals_flushed
from blurcalib.deconv.problem import BlockProblem
from blurcalib.deconv.result import BlockFit, BlockModel
from blurcalib.deconv.schedule import BatchFit, fit_fixed_batch, fit_free_batch, fit_hinted_batch
from blurcalib.deconv.settings import DeconvSettings, check_kernel_size
from blurcalib.deconv.windows import block_windows
from blurcalib.io.results import BlockStatus
from blurcalib.psf.kernel import boundary_energy, psf_moments

__all__ = ["fit_blocks", "fit_blocks_fixed", "fit_blocks_hinted", "render_model"]

PsfStart = Literal["free", "hinted", "fixed"]
"""How a fit starts its PSFs: unknown, from expected kernels or with given kernels held."""

_NUM_P = 6
"""Brightness coefficients ``(a1, a2, a3, b1, b2, b3)``."""


def fit_blocks(image: np.ndarray, H0: np.ndarray, num_segments: int, kernel_size: int,
               settings: DeconvSettings | None = None, pixel_mask: np.ndarray | None = None) -> BlockFit:
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
        kernel_size: ``K``, the PSF window side (px, odd, at least 3); about 1.5 x the longest
            blur is best (:class:`blurcalib.growth.window.WindowPolicy`).
        settings: solver settings (default :class:`DeconvSettings`).
        pixel_mask: optional ``(height, width)`` bool, False for pixels that must not enter any
            loss (saturation, occluders, a tag nearer to the square than the kernel radius).
            Non-finite pixels never enter a loss.
    Returns:
        :class:`BlockFit`. A block whose window leaves the image is ``outside_image``; one whose
        ``H0`` is non-finite, crosses the horizon, is not convex or is too small or large is
        ``degenerate_homography``. Neither is fitted, neither stops the batch. A fit without
        contrast (no star in the window), with non-finite results or still moving is
        ``not_converged``.
    """
    return _fit(image, H0, num_segments, check_kernel_size(kernel_size), settings, pixel_mask, "free", None)


def fit_blocks_hinted(image: np.ndarray, H0: np.ndarray, num_segments: int, hints: np.ndarray,
                      settings: DeconvSettings | None = None, pixel_mask: np.ndarray | None = None
                      ) -> BlockFit:
    """:func:`fit_blocks` from expected PSFs ``hints (B, K, K)`` relative to ``H0`` (the window
    is theirs; e.g. the re-centred PSFs of the neighbouring blocks that predicted ``H0``): the
    first kernel support is taken from them (entries above ``support_threshold`` of the peak,
    dilated by ``support_dilation``, the rule between stages) instead of from a coarse kernel, and
    the blocks are solved in :attr:`DeconvSettings.hinted_stages` stages. A block whose hint is
    not finite or all zero gets the whole window as its first support."""
    hints = np.asarray(hints, dtype=np.float64)
    H0 = np.asarray(H0, dtype=np.float64).reshape(-1, 3, 3)
    B, K = H0.shape[0], hints.shape[-1]
    if hints.shape != (B, K, K):
        raise ValueError(f"hints must be ({B}, K, K), got {hints.shape}")
    empty = ~np.all(np.isfinite(hints), axis=(1, 2)) | ~(np.nan_to_num(hints).max(axis=(1, 2)) > 0)
    hints = np.where(empty[:, None, None], 1.0, np.nan_to_num(hints))
    return _fit(image, H0, num_segments, check_kernel_size(K), settings, pixel_mask, "hinted", hints)


def fit_blocks_fixed(image: np.ndarray, H0: np.ndarray, num_segments: int, psfs: np.ndarray,
                     settings: DeconvSettings | None = None, pixel_mask: np.ndarray | None = None
                     ) -> BlockFit:
    """:func:`fit_blocks` with known PSFs ``psfs (B, K, K)`` (non-negative, e.g. the frame's
    motion-path field, :mod:`blurcalib.psf.path`; the window is theirs): the kernels are kept,
    ``H``, the brightness gradient and its scale and offset are fitted
    (:attr:`DeconvSettings.fixed_steps` LM steps); the re-centring then moves ``H`` by each
    kernel's centroid."""
    psfs = np.asarray(psfs, dtype=np.float64)
    H0 = np.asarray(H0, dtype=np.float64).reshape(-1, 3, 3)
    B, K = H0.shape[0], psfs.shape[-1]
    if psfs.shape != (B, K, K):
        raise ValueError(f"psfs must be ({B}, K, K), got {psfs.shape}")
    if not np.all(np.isfinite(psfs)) or np.any(psfs < 0) or not np.all(psfs.sum(axis=(1, 2)) > 0):
        raise ValueError("psfs must be finite, non-negative and non-zero")
    return _fit(image, H0, num_segments, check_kernel_size(K), settings, pixel_mask, "fixed", psfs)


@denormals_flushed
def _fit(image: np.ndarray, H0: np.ndarray, num_segments: int, K: int, settings: DeconvSettings | None,
         pixel_mask: np.ndarray | None, start: PsfStart, kernels: np.ndarray | None) -> BlockFit:
    """The fit of :func:`fit_blocks` with its PSFs started as ``start`` says (``kernels (B, K, K)``
    the hints or the given PSFs)."""
    s = settings or DeconvSettings()
    img_np = np.asarray(image)
    if img_np.ndim != 2:
        raise ValueError(f"image must be (height, width), got shape {img_np.shape}")
    if pixel_mask is not None and np.shape(pixel_mask) != img_np.shape:
        raise ValueError(f"pixel_mask must have the image's shape {img_np.shape}, got {np.shape(pixel_mask)}")
    H0 = np.asarray(H0, dtype=np.float64).reshape(-1, 3, 3)
    B = H0.shape[0]
    origin, size, Hn, status = block_windows(H0, img_np.shape, s)
    out = BatchFit(H=H0.copy(), psf=np.full((B, K, K), np.nan), psf_fit=np.full((B, K, K), np.nan),
                   coeffs=np.full((B, _NUM_P), np.nan), loss=np.full(B, np.nan),
                   centroid=np.full((B, 2), np.nan), num_pixels=np.zeros(B, dtype=np.int64),
                   centre_step=np.full(B, np.nan),
                   masks=[np.zeros((0, 0), dtype=bool)] * B)
    uv_centre, uv_scale = np.full((B, 2), np.nan), np.full(B, np.nan)
    todo = np.array([st == BlockStatus.ACCEPTED for st in status], dtype=bool)
    idx = np.flatnonzero(todo)
    if idx.size:
        dev = torch.device(s.device)
        img_t = torch.as_tensor(img_np.astype(np.float64 if s.dtype == "float64" else np.float32), device=dev)
        ok_t = None if pixel_mask is None else torch.as_tensor(np.asarray(pixel_mask, dtype=bool), device=dev)
        order = idx[np.argsort(size[idx].prod(axis=1), kind="stable")]
        for first in range(0, order.size, s.batch_size):
            sel = order[first:first + s.batch_size]
            prob = BlockProblem(img_t, ok_t, origin[sel], size[sel], num_segments, K, s)
            if start == "free":
                res = fit_free_batch(prob, Hn[sel])
            elif start == "hinted":
                assert kernels is not None
                res = fit_hinted_batch(prob, Hn[sel], torch.as_tensor(kernels[sel], device=dev))
            else:
                assert kernels is not None
                res = fit_fixed_batch(prob, Hn[sel], torch.as_tensor(kernels[sel], device=dev))
            for i, m in zip(sel, res.masks, strict=True):
                out.masks[i] = m
            for name in ("H", "psf", "psf_fit", "coeffs", "loss", "centroid", "num_pixels", "centre_step"):
                getattr(out, name)[sel] = getattr(res, name)
            uv_centre[sel] = prob.uv_centre
            uv_scale[sel] = prob.uv_scale
    return _block_fit(out, status, todo, origin, size, uv_centre, uv_scale, num_segments, s)


def _block_fit(out: BatchFit, status: list[BlockStatus], todo: np.ndarray, origin: np.ndarray,
               size: np.ndarray, uv_centre: np.ndarray, uv_scale: np.ndarray, num_segments: int,
               s: DeconvSettings) -> BlockFit:
    """The :class:`BlockFit` of the fitted rows ``out``: statuses, convergence and PSF figures."""
    B = len(status)
    k_fit = out.psf_fit
    fitted = (todo & np.isfinite(out.loss) & np.all(np.isfinite(out.H), axis=(1, 2))
              & np.all(np.isfinite(k_fit), axis=(1, 2)) & (out.coeffs[:, 2] > s.min_contrast)
              & (out.num_pixels > 0))
    converged = fitted & (out.centre_step < s.converge_tol_px)
    status = [BlockStatus.NOT_CONVERGED if todo[b] and not converged[b] else status[b] for b in range(B)]
    figures = {name: np.full(B, np.nan) for name in
               ("boundary_energy", "sigma_major", "sigma_minor", "eccentricity", "orientation")}
    if fitted.any():
        mom = psf_moments(k_fit[fitted])
        for name in ("sigma_major", "sigma_minor", "eccentricity", "orientation"):
            figures[name][fitted] = getattr(mom, name)
        figures["boundary_energy"][fitted] = boundary_energy(k_fit[fitted])
    masks = np.empty(B, dtype=object)
    masks[:] = out.masks
    return BlockFit(
        H=out.H, psf=out.psf, psf_fit=k_fit, coeffs=out.coeffs, uv_centre=uv_centre, uv_scale=uv_scale,
        loss=out.loss, residual_rms=np.sqrt(out.loss), centroid=out.centroid, converged=converged,
        status=tuple(status), centre_step=out.centre_step, origin=origin, window_size=size,
        num_pixels=out.num_pixels, loss_extent=np.full(B, s.loss_extent), masks=masks,
        num_segments=num_segments, settings=s, **figures)


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
    prob = BlockProblem(img_t, None, fit.origin[sel], fit.window_size[sel], fit.num_segments,
                        fit.kernel_size, s)
    k = torch.as_tensor(fit.psf_fit[sel], device=dev, dtype=prob.dt)
    p = torch.as_tensor(fit.coeffs[sel], device=dev, dtype=torch.float64)
    model = prob.model(prob.to_local(fit.H_fit[sel]), k, p)[0].double().cpu().numpy()
    obs = prob.img[0].double().cpu().numpy()
    return BlockModel(model, obs, obs - model, fit.masks[index].copy(), fit.origin[index].copy())
