"""The fit of a frame's path-PSF field (:class:`blurcalib.psf.path.PathField`) with its blocks.

:func:`fit_path_field` fits the field and every block's homography and brightness in one
Gauss-Newton problem (``eq:field_fit``), the blocks' parameters eliminated by the Schur
complement. The blocks' fit with the field's kernels held is
:func:`blurcalib.deconv.blocks.fit_blocks_fixed`.

Conventions: OpenCV pixels (top-left pixel centre at ``(0, 0)``); kernels ``K x K`` with
``k[i, j]`` the weight of offset ``(j - c, i - c)`` px (``docs/conventions.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
import torch

from blurcalib.deconv.convolution import denormals_flushed, latent_spectrum
from blurcalib.deconv.latent import update_homography
from blurcalib.deconv.problem import BlockProblem
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.deconv.windows import block_windows
from blurcalib.io.results import BlockStatus
from blurcalib.optim.lm import Damping, LmRule, SingleProblem, Stopping, run_single
from blurcalib.psf.path import NUM_THETA, PathField, path_kernels

__all__ = ["FieldFit", "FieldSettings", "fit_path_field"]


@dataclass(frozen=True)
class FieldSettings:
    """Settings of :func:`fit_path_field`.

    Attributes:
        iterations: largest number of Levenberg-Marquardt steps.
        loss_extent: the blocks' loss covers ``|q|_inf <= loss_extent`` (block units).
        largest_kernel: largest PSF window (px, odd).
        outlier_loss: blocks whose mean squared residual exceeds this multiple of the median
            block's are down-weighted (weight ``outlier_loss median / loss``; a block that
            settled off must not bend the field).
        tolerance: stop when a step lowers the objective by less than this share.
        min_sigma_px: the Gaussian spread is kept above this (px).
        hold_steps: at most this many first steps hold the blocks' homographies at their
            starts (only the field and the brightness move; not when tied): a block fitted
            with a poor early field runs away (measured on a 24 px curved blur: 10 of 40 blocks
            that started 0.05-0.27 px off ended 5-27 px off).
    """

    iterations: int = 25
    loss_extent: float = 1.5
    largest_kernel: int = 81
    outlier_loss: float = 2.0
    tolerance: float = 1e-4
    min_sigma_px: float = 0.35
    hold_steps: int = 10


@dataclass
class FieldFit:
    """Result of :func:`fit_path_field` for ``B`` blocks.

    Attributes:
        field: the fitted :class:`PathField`.
        H: ``(B, 3, 3)`` the blocks' homographies (``H(0, 0)`` the time-averaged star centre);
            the start for blocks that could not be fitted.
        loss: ``(B,)`` mean squared residual over each block's loss area (grey levels^2; NaN
            where not fitted).
        weight: ``(B,)`` the final block weights (0 where not fitted).
        kernel_size: the window used (px).
        iterations: LM steps taken.
        objective: ``(iterations + 1,)`` the weighted objective before each step and at the end.
    """

    field: PathField
    H: np.ndarray
    loss: np.ndarray
    weight: np.ndarray
    kernel_size: int
    iterations: int
    objective: np.ndarray


class _FieldProblem:
    """The blocks of :func:`fit_path_field`: their windows, pixels and the field's basis."""

    def __init__(self, image: np.ndarray, H0: np.ndarray, num_segments: int, kernel_size: int,
                 s: DeconvSettings, pixel_mask: np.ndarray | None, basis: np.ndarray) -> None:
        origin, size, Hn, status = block_windows(H0, image.shape, s)
        self.rows = np.flatnonzero([st is BlockStatus.ACCEPTED for st in status])
        dev = torch.device(s.device)
        img = torch.as_tensor(np.asarray(image, dtype=np.float32 if s.dtype == "float32" else np.float64),
                              device=dev)
        ok = None if pixel_mask is None else torch.as_tensor(np.asarray(pixel_mask, dtype=bool), device=dev)
        r = self.rows
        self.prob = BlockProblem(img, ok, origin[r], size[r], num_segments, kernel_size, s)
        self.H_loc = self.prob.to_local(Hn[r])
        self.mask = self.prob.square_mask(self.H_loc).to(self.prob.dt)  # held through the fit
        self.basis = torch.as_tensor(basis[r], dtype=self.prob.dt, device=dev)
        self.one = torch.ones_like(self.prob.u_e)
        self._latent: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None] | None = None

    def latent(self, H_loc: torch.Tensor, with_jac: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The latent channels ``(b, C, Hl, Wl)`` at ``H_loc``: ``S``, then with ``with_jac`` its 8
        derivatives; and their transform (:func:`blurcalib.deconv.convolution.latent_spectrum`;
        None where the convolutions are direct). The last channels computed are kept for the same
        ``H_loc`` tensor: while the blocks' homographies are held
        (:attr:`FieldSettings.hold_steps`) every evaluation reuses them."""
        held = self._latent
        if held is None or held[0] is not H_loc or (with_jac and held[1].shape[1] == 1):
            S, dS = self.prob.latent(H_loc, with_jac=with_jac)
            chans = S[:, None] if dS is None else torch.cat([S[:, None], dS], dim=1)
            held = self._latent = (H_loc, chans, latent_spectrum(chans, self.prob.K))
        chans, spec = held[1], held[2]
        if with_jac:
            return chans, spec
        return chans[:, :1], None if spec is None else spec[:, :1]

    def evaluate(self, H_loc: torch.Tensor, bright: torch.Tensor | None, coeffs: torch.Tensor,
                 log_sigma: torch.Tensor, with_jac: bool, with_h: bool = True) -> dict[str, torch.Tensor]:
        """Residuals ``(b, n)`` and, optionally, the Jacobians of the blocks' own parameters
        ``Jl (b, 14, n)`` (8 of ``H``, 6 of the brightness; the 6 alone without ``with_h``, while
        the homographies are held) and of the shared ones ``Js (b, 4 P + 1, n)``; ``bright`` None
        solves the brightness in closed form first."""
        pb, b = self.prob, H_loc.shape[0]
        dt = pb.dt
        theta = torch.cat([self.basis @ coeffs.to(dt), log_sigma.to(dt).expand(b, 1)], dim=1)
        k, dk = path_kernels(theta, pb.K, with_jac)
        chans, spec = self.latent(H_loc, with_jac=with_jac and with_h)
        conv = pb.conv(chans, k, latent=spec)
        C, u, v = conv[:, 0], pb.u_e, pb.v_e
        lin = torch.stack([u * C, v * C, C, u, v, self.one], dim=1) * self.mask[:, None]  # (b, 6, h, w)
        if bright is None:
            L = lin.reshape(b, 6, -1)
            G = (L @ L.transpose(1, 2)).double()
            diag = G.diagonal(dim1=1, dim2=2)
            diag.add_(1e-9 * diag.mean(dim=1, keepdim=True) + 1e-12)
            rhs = (L @ (pb.img * self.mask).reshape(b, -1, 1)).double()
            bright = torch.linalg.solve_ex(G, rhs)[0][..., 0]
        p = bright.to(dt)
        r = (pb.img * self.mask - (lin * p[:, :, None, None]).sum(dim=1)).reshape(b, -1)
        out = {"r": r, "bright": bright}
        if with_jac:
            assert dk is not None
            A = (p[:, 0, None, None] * u + p[:, 1, None, None] * v + p[:, 2, None, None]) * self.mask
            # (b, 5, h, w): d model / d theta
            dC = pb.conv(chans[:, :1], dk, latent=None if spec is None else spec[:, :1]) * A[:, None]
            out["Jl"] = torch.cat([conv[:, 1:] * A[:, None], lin], dim=1).flatten(2)
            Jt = dC.reshape(b, NUM_THETA, -1)
            shared = (Jt[:, None, :4] * self.basis[:, :, None, None]).reshape(b, -1, Jt.shape[-1])
            out["Js"] = torch.cat([shared, Jt[:, 4:]], dim=1)
        return out


_UPDATE_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2), (2, 0), (2, 1))
"""Entries of the 8-parameter update ``Delta`` of a homography
(:func:`blurcalib.deconv.latent.update_homography`)."""


def _tied_map(A: np.ndarray) -> np.ndarray:
    """``(b, 8, 8)``: the block-side updates ``Delta_b`` (rows, :data:`_UPDATE_ENTRIES`) that a
    feature-side update ``H_F (I + Delta_F)`` makes of the blocks ``H_b = H_F A_b`` (columns):
    ``Delta_b = A_b^-1 Delta_F A_b``, its ``[2, 2]`` entry moved into the others (to first order
    ``I + Delta`` and ``(I + Delta) / (1 + Delta_22)`` are the same homography)."""
    A_inv = np.linalg.inv(A)
    out = np.zeros((len(A), 8, 8))
    for j, (r, c) in enumerate(_UPDATE_ENTRIES):
        E = np.zeros((3, 3))
        E[r, c] = 1.0
        D = A_inv @ E @ A
        D -= D[:, 2:, 2:] * np.eye(3)
        out[:, :, j] = np.stack([D[:, rr, cc] for rr, cc in _UPDATE_ENTRIES], axis=1)
    return out


def _feature_blocks(features: np.ndarray) -> np.ndarray:
    """``(B, 3, 3)``: block coordinates -> feature coordinates ``(fx, fy) + q / 2``."""
    A = np.zeros((len(features), 3, 3))
    A[:, 0, 0] = A[:, 1, 1] = 0.5
    A[:, :2, 2] = features
    A[:, 2, 2] = 1.0
    return A


def _normal_equations(Jl: torch.Tensor, Js: torch.Tensor, r: torch.Tensor, w: torch.Tensor
                      ) -> tuple[torch.Tensor, int]:
    """The weighted normal equations of :func:`fit_path_field` at one point: the blocks' own
    parameters ``Jl (b, L, n)``, the shared ones ``Js (b, S, n)``, residuals ``r (b, n)`` and
    block weights ``w (b,)``. One product ``w_b [Jl; Js; r] [Jl; Js; r]^T`` per block: returns
    it, ``(b, L + S + 1, L + S + 1)`` float64, and ``L``."""
    J = torch.cat([Jl, Js, r[:, None]], dim=1)
    return (J @ J.transpose(1, 2)).double() * w.double()[:, None, None], Jl.shape[1]


def _schur_step(normal: torch.Tensor, L: int, mu: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One Levenberg-Marquardt step of :func:`fit_path_field` from its normal equations
    (:func:`_normal_equations`, ``L`` the blocks' own parameters), damped by ``mu``; the blocks'
    parameters are eliminated (Schur complement, ``(b, L, L)`` batched solves). Returns
    ``(ds (S,), dl (b, L))``."""
    Nll = normal[:, :L, :L].clone()
    Nls = normal[:, :L, L:-1]
    Nss = normal[:, L:-1, L:-1].sum(dim=0)
    gl = normal[:, :L, -1:]
    gs = normal[:, L:-1, -1:].sum(dim=0)
    Nll.diagonal(dim1=1, dim2=2).mul_(1.0 + mu).add_(1e-12)
    Nss.diagonal().mul_(1.0 + mu).add_(1e-12)
    X = torch.linalg.solve_ex(Nll, torch.cat([Nls, gl], dim=2))[0]
    reduced = Nss - (Nls.transpose(1, 2) @ X[..., :-1]).sum(dim=0)
    ds = torch.linalg.solve_ex(reduced, gs - (Nls.transpose(1, 2) @ X[..., -1:]).sum(dim=0))[0][:, 0]
    dl = torch.linalg.solve_ex(Nll, gl - Nls @ ds[:, None])[0][..., 0]
    return ds, dl


def _tied_start(H0: np.ndarray, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The blocks ``H0 (B, 3, 3)`` at feature coordinates ``features (B, 2)`` as blocks of one
    feature homography ``H_F`` (least squares on their star centres): ``(H_F B(f) (B, 3, 3),
    H_F (3, 3))``."""
    centres = H0[:, :2, 2] / H0[:, 2:, 2]
    ok = np.all(np.isfinite(centres), axis=1)
    if ok.sum() < 4:
        raise ValueError("a tied path field needs at least 4 blocks")
    H_F, _ = cv2.findHomography(features[ok], centres[ok], 0)
    if H_F is None:
        raise ValueError("no homography fits the tied blocks' centres")
    H = H_F[None] @ _feature_blocks(features)
    return H / H[:, 2:, 2:], H_F


def _field_fit(fp: _FieldProblem, H0: np.ndarray, H_loc: torch.Tensor, loss: torch.Tensor,
               weight: torch.Tensor, field: PathField, K: int, steps: int, history: list[float]) -> FieldFit:
    """The :class:`FieldFit` of the fitted rows ``fp.rows``: ``H_loc``, their ``loss`` and
    ``weight`` (tensors); the other rows keep ``H0`` with NaN loss and weight 0."""
    B = len(H0)
    H = H0.copy()
    H[fp.rows] = fp.prob.to_image(H_loc)
    loss_np = np.full(B, np.nan)
    loss_np[fp.rows] = loss.cpu().numpy()
    weight_np = np.zeros(B)
    weight_np[fp.rows] = weight.cpu().numpy()
    return FieldFit(field, H / H[:, 2:, 2:], loss_np, weight_np, K, steps, np.asarray(history))


def _fit_window(start: PathField, centres: np.ndarray, largest: int) -> int:
    """The PSF window (odd, px) of the field's fit: the start's paths with room to grow by a
    quarter during the fit, at most ``largest``."""
    K = start.kernel_size(centres, largest)
    K = max(K, 2 * math.ceil(1.25 * (K // 2)) + 1)
    return min(K, largest - 1 + largest % 2)


FIELD_DAMPING = Damping(start=1e-3, shrink=3.0, grow=4.0, ceiling=4e5)
"""The damping ``mu`` of :func:`fit_path_field` (``N + mu diag(N)``): 1e-3 at the start of each
phase, /3 after an accepted step, x4 after a rejected one; a step rejected at ``mu > 1e5`` ends the
phase (no trial is made above ``4e5``)."""


@dataclass
class _FieldPoint:
    """A point of :func:`fit_path_field`: the blocks' ``H_loc (b, 3, 3)``, the field's ``coeffs
    (P, 4)`` and ``log_sigma (1,)``, tied, ``H_F (3, 3)`` (else None), the evaluation ``cur``
    (:meth:`_FieldProblem.evaluate`) and the block weights ``w (b,)`` of the objective."""

    H_loc: torch.Tensor
    coeffs: torch.Tensor
    log_sigma: torch.Tensor
    H_F: torch.Tensor | None
    cur: dict[str, torch.Tensor]
    w: torch.Tensor


class _FieldLm(SingleProblem[_FieldPoint, tuple[torch.Tensor, int], tuple[torch.Tensor, torch.Tensor]]):
    """The least-squares problem of :func:`fit_path_field` (:class:`blurcalib.optim.lm.SingleProblem`):
    the weighted objective ``sum_i w_i sum_x r_i(x)^2``; steps from the Schur complement on the
    blocks' own parameters (:func:`_schur_step`). While :attr:`held`, the blocks' homographies
    stay at their starts."""

    def __init__(self, fp: _FieldProblem, fs: FieldSettings, P: int, tie: tuple[torch.Tensor, ...] | None,
                 held: bool) -> None:
        self.fp, self.fs, self.P, self.held = fp, fs, P, held
        self.tie = tie  # (to_local (b, 3, 3), A (b, 3, 3), the map (b, 8, 8)) of a tied fit
        self.nh = 8 if tie is not None else 0  # shared homography parameters
        self.npix = fp.mask.reshape(len(fp.rows), -1).sum(dim=1).double().clamp_min(1)

    def block_loss(self, r: torch.Tensor) -> torch.Tensor:
        """``(b,)`` mean squared residual of each block (grey levels^2)."""
        return (r.double() ** 2).sum(dim=1) / self.npix

    def weighted(self, H_loc: torch.Tensor, coeffs: torch.Tensor, log_sigma: torch.Tensor,
                 H_F: torch.Tensor | None, cur: dict[str, torch.Tensor]) -> tuple[_FieldPoint, float]:
        """The point of evaluation ``cur``, re-weighted (:attr:`FieldSettings.outlier_loss`), and its
        objective."""
        loss = self.block_loss(cur["r"])
        limit = self.fs.outlier_loss * loss.median()
        w = torch.where(loss > limit, limit / loss, torch.ones_like(loss))
        obj = float((w * self.block_loss(cur["r"]) * self.npix).sum())
        return _FieldPoint(H_loc, coeffs, log_sigma, H_F, cur, w), obj

    def jacobians(self, cur: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """``(Jl (b, 14 or 6, n), Js (b, nh + 4 P + 1, n))``: the blocks' own and the shared
        ones (each block's ``H`` is its own unless tied or held: while held, ``cur`` has no
        Jacobian of ``H``)."""
        if self.tie is not None:
            J_F = torch.einsum("bin,bij->bjn", cur["Jl"][:, :8], self.tie[2].to(cur["Jl"].dtype))
            return cur["Jl"][:, 8:], torch.cat([J_F, cur["Js"]], dim=1)
        return cur["Jl"], cur["Js"]

    def released(self, x: _FieldPoint) -> _FieldPoint:
        """``x`` with the Jacobians of the blocks' homographies, once they are no longer held."""
        self.held = False
        cur = self.fp.evaluate(x.H_loc, x.cur["bright"], x.coeffs, x.log_sigma, with_jac=True)
        return replace(x, cur=cur)

    def linearise(self, x: _FieldPoint) -> tuple[torch.Tensor, int]:
        return _normal_equations(*self.jacobians(x.cur), x.cur["r"], x.w)

    def solve(self, system: tuple[torch.Tensor, int], lam: float) -> tuple[torch.Tensor, torch.Tensor]:
        return _schur_step(*system, lam)

    def trial(self, x: _FieldPoint, step: tuple[torch.Tensor, torch.Tensor]) -> tuple[_FieldPoint, float]:
        ds, dl = step
        nh, P = self.nh, self.P
        H_F_try = None
        if self.tie is not None and x.H_F is not None:
            to_local, A, _ = self.tie
            H_F_try = update_homography(x.H_F[None], ds[None, :8])[0]
            H_try = to_local @ H_F_try[None] @ A
            H_try = H_try / H_try[:, 2:, 2:]
        else:
            H_try = x.H_loc if self.held else update_homography(x.H_loc, dl[:, :8])
        coeffs_try = x.coeffs + ds[nh:nh + 4 * P].reshape(P, 4)
        sigma_try = (x.log_sigma + ds[nh + 4 * P:]).clamp_min(math.log(self.fs.min_sigma_px))
        bright_try = x.cur["bright"] + dl[:, -6:]
        trial = self.fp.evaluate(H_try, bright_try, coeffs_try, sigma_try, with_jac=False)
        obj_try = float((x.w * self.block_loss(trial["r"]) * self.npix).sum())
        return _FieldPoint(H_try, coeffs_try, sigma_try, H_F_try, trial, x.w), obj_try

    def accept(self, x: _FieldPoint, moved: _FieldPoint, step: tuple[torch.Tensor, torch.Tensor], cost: float
               ) -> tuple[_FieldPoint, float, bool]:
        """The Jacobians only where a step is taken; then re-weighted (IRLS; the objective follows)."""
        cur = self.fp.evaluate(moved.H_loc, moved.cur["bright"], moved.coeffs, moved.log_sigma, with_jac=True,
                               with_h=not self.held)
        point, obj = self.weighted(moved.H_loc, moved.coeffs, moved.log_sigma, moved.H_F, cur)
        return point, obj, False


def _field_phase(lm: _FieldLm, x: _FieldPoint, obj: float, trials: int, history: list[float]
                 ) -> tuple[_FieldPoint, float, int]:
    """One phase of :func:`fit_path_field`: at most ``trials`` steps from ``x`` of objective ``obj``
    with a fresh damping; appends the objective after each accepted step to ``history``. Returns
    the point, its objective and the steps taken."""
    run = run_single(lm, x, obj, LmRule(FIELD_DAMPING, Stopping(max_trials=trials, rtol=lm.fs.tolerance)))
    history += [float(step.cost[0]) for step in run.log if step.moved[0]]
    return run.x, run.cost, run.trials


def _tied(fp: _FieldProblem, H0: np.ndarray, features: np.ndarray, H_F: np.ndarray
          ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
    """A tied fit's ``H_F (3, 3)`` and the map of its updates to the blocks' (:class:`_FieldLm`'s
    ``tie``): the blocks in latent-local px are ``T(-origin) H_F A_b``."""
    dev = fp.H_loc.device
    H_F_t = torch.as_tensor(H_F / H_F[2, 2], dtype=torch.float64, device=dev)
    A = torch.as_tensor(_feature_blocks(features[fp.rows]), dtype=torch.float64, device=dev)
    to_local = fp.H_loc @ torch.linalg.inv(torch.as_tensor(H0[fp.rows], dtype=torch.float64, device=dev))
    return H_F_t, (to_local, A, torch.as_tensor(_tied_map(_feature_blocks(features[fp.rows])), device=dev))


@denormals_flushed
def fit_path_field(image: np.ndarray, H0: np.ndarray, num_segments: int, start: PathField,
                   deconv: DeconvSettings | None = None, settings: FieldSettings | None = None,
                   pixel_mask: np.ndarray | None = None, features: np.ndarray | None = None) -> FieldFit:
    """Fit a frame's path field and its blocks together (``eq:field_fit``)::

        argmin_{field, H_i, p_i}  sum_i w_i sum_{x in block i} (I(x) - m_i(x))^2,
        m_i = A_i (k(theta(x_i)) * S(H_i)) + B_i

    with ``k`` the path PSF ``eq:path_psf`` at the block's star centre ``x_i`` (from the start),
    ``A_i, B_i`` affine brightness and ``w_i`` block weights (:attr:`FieldSettings.outlier_loss`).
    Levenberg-Marquardt on all parameters (:func:`blurcalib.optim.lm.run_single`,
    :data:`FIELD_DAMPING`); each step solves the shared ``4 P + 1`` after eliminating every
    block's 14 (Schur complement, ``(b, 14, 14)`` batched solves); a trial point's residuals come
    first, its Jacobians only once it is accepted (a rejected step re-solves the normal equations
    it had, more damped). The first phase (at most :attr:`FieldSettings.hold_steps` steps, not
    when tied) holds the blocks' homographies; the second, with a fresh damping, frees them. A
    phase ends when a step lowers the objective by less than :attr:`FieldSettings.tolerance` of it
    or no damping up to the ceiling lowers it.

    *Tied* (``features`` given): the blocks are those of one feature homography, ``H_i = H_F
    B(f_i)`` (:func:`blurcalib.growth.seed.block_homography`), and ``H_F``'s 8 parameters are shared
    instead of each block's: the blocks around a tag, whose starts are px off under long blur,
    move together (a plane over a few squares; the lens bends it by far less than that).

    Args:
        image: ``(height, width)`` grey levels.
        H0: ``(B, 3, 3)`` block homographies to start from (the blocks' fits; a few tenths of a
            px off is fine, or, tied, a few px).
        num_segments: star segments ``N``.
        start: the field to start from, e.g. :func:`constant_field` (its degree is the fit's).
        deconv: settings of the blocks' windows and latent pattern (the loss extent is set
            here; the PSF window follows the start's paths).
        settings: :class:`FieldSettings`.
        pixel_mask: as for :func:`blurcalib.deconv.blocks.fit_blocks`.
        features: ``(B, 2)`` feature coordinates of the blocks to tie them (``H_F`` starts from
            the least-squares homography of ``H0``'s star centres), or None.
    Returns:
        :class:`FieldFit`.
    Raises:
        ValueError: no block can be fitted (all windows outside the image or degenerate), or,
            tied, fewer than 4 blocks.
    """
    fs = settings or FieldSettings()
    H0 = np.asarray(H0, dtype=np.float64).reshape(-1, 3, 3)
    if features is not None:
        features = np.asarray(features, dtype=np.float64).reshape(-1, 2)
        H0, H_F = _tied_start(H0, features)
    centres = H0[:, :2, 2] / H0[:, 2:, 2]
    K = _fit_window(start, centres, fs.largest_kernel)
    s = replace(deconv or DeconvSettings(), loss_extent=fs.loss_extent)
    fp = _FieldProblem(image, H0, num_segments, K, s, pixel_mask, start.basis(centres))
    if len(fp.rows) == 0 or (features is not None and len(fp.rows) < 4):
        raise ValueError("too few blocks of the path field's fit lie inside the image")
    dev = fp.H_loc.device
    coeffs = torch.as_tensor(start.coeffs, dtype=torch.float64, device=dev)
    log_sigma = torch.tensor([start.log_sigma], dtype=torch.float64, device=dev)
    H_F_t, tie = _tied(fp, H0, features, H_F) if features is not None else (None, None)
    hold = 0 if features is not None else fs.hold_steps  # steps with the blocks' H held
    lm = _FieldLm(fp, fs, len(start.coeffs), tie, held=hold > 0)
    cur = fp.evaluate(fp.H_loc, None, coeffs, log_sigma, with_jac=True, with_h=not hold)
    x, obj = lm.weighted(fp.H_loc, coeffs, log_sigma, H_F_t, cur)
    history, steps = [obj], 0
    if hold:
        x, obj, steps = _field_phase(lm, x, obj, min(hold, fs.iterations), history)
        if steps < fs.iterations:
            x = lm.released(x)
    if steps < fs.iterations:
        x, obj, more = _field_phase(lm, x, obj, fs.iterations - steps, history)
        steps += more
    field = PathField(x.coeffs.cpu().numpy(), float(x.log_sigma), start.image_size)
    return _field_fit(fp, H0, x.H_loc, lm.block_loss(x.cur["r"]), x.w, field, K, steps, history)
