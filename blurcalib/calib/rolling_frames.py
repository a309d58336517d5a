"""Each frame's rolling-shutter geometry fitted with the camera held (``docs/rolling-shutter.md``).

A feature seen in row ``v`` of an ``H``-row sensor, at ``y = (v - (H - 1) / 2) / H`` of the
readout (:func:`row_coordinate`), is seen from the frame's pose moved by the motion over its
row's instant (to second order)::

    p_i = pi(exp([y_i alpha_w + y_i^2 beta_w]_x) (R P_i + t) + y_i alpha_v + y_i^2 beta_v) + s

with the frame's rolling twist ``alpha = (alpha_w rad, alpha_v m)`` per unit of ``y``, its
curvature ``beta`` and ``s`` a blurry frame's free image shift (px). :func:`fit_rolling_frames`
fits ``M_f, s_f, theta_f = (alpha_f, beta_f)`` of every frame at once with the camera held:
per frame ``min sum_i rho(|r_i|^2) + |s|^2 / sigma_s^2 + |theta / sigma_theta|^2``, Huber ``rho``
by iteratively reweighted Levenberg-Marquardt on ``(F, 20, 20)`` normal equations (columns
``omega (3), dt (3), s (2), alpha (6), beta (6)``), a damping per frame
(:func:`blurcalib.optim.lm.run_batch`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import torch

from blurcalib.calib.bundle_problem import robust_weights
from blurcalib.calib.frame_block import rolling_frame_jacobian, rolling_points, rolling_prior_weights
from blurcalib.calib.validation import Projector
from blurcalib.camera.shutter import row_time
from blurcalib.geometry.lie import exp_so3, orthonormal, skew
from blurcalib.geometry.pose import Pose
from blurcalib.optim.lm import Acceptance, Damping, LmRule, Stopping, run_batch

__all__ = ["FRAME_DAMPING", "RollingFit", "fit_rolling_frames", "rolling_displacement", "row_coordinate"]

_PARAMS = 20  # omega (3), dt (3), s (2), alpha (6), beta (6)

FRAME_DAMPING = Damping(start=1e-4, shrink=10.0, grow=10.0, floor=1e-9)
"""Each frame's Marquardt ``lambda`` in :func:`fit_rolling_frames`: 1e-4, /10 (not below 1e-9)
after an accepted step, x10 after a rejected one."""

ROUND_TRIALS = 8
"""Trials at most of a round, in which the frames retry together from their linearisations until
none is rejected; a frame whose last trial of a round is rejected stops."""

STEP_TOL = 1e-10
"""A frame stops once no component of its accepted step (rad, m, px) exceeds this."""


def row_coordinate(v: np.ndarray, height: int) -> np.ndarray:
    """``y(v) = (v - (H - 1) / 2) / H``: the row ``v`` (px) as a share of the readout, ``(N,)``."""
    return row_time(v, height, 1.0)


@dataclass(eq=False)
class RollingFit:
    """Frames fitted with their rolling-shutter geometry, the camera held
    (:func:`fit_rolling_frames`).

    Attributes:
        poses: ``(F,)`` poses at ``y = 0`` (target -> camera).
        shifts: ``(F, 2)`` px.
        theta: ``(F, 12)`` ``alpha (rad, m), beta (rad, m)`` per unit ``y`` and ``y^2``.
        z: ``(F,)`` chi-square statistics of ``theta`` (12 degrees of freedom without a rolling
            shutter); NaN where the frame's rolling parameters are held at 0.
        sigma_px: the residuals' robust scale per coordinate.
        residuals: ``(N, 2)`` px; NaN where the ray left the calibrated area.
        correction: ``(N, 2)`` px, ``pi(rolling pose) - pi(rigid pose)``: what the rolling shutter
            adds to each observation.
        velocity: ``(N, 2)`` px per unit ``y``, ``g_i``.
        velocity_jacobian: ``(N, 2, 12)`` ``d g_i / d theta``.
        theta_cov: ``(F, 12, 12)`` covariance of ``theta`` (``sigma^2 H^-1``; NaN where held).
    """

    poses: list[Pose]
    shifts: np.ndarray
    theta: np.ndarray
    z: np.ndarray
    sigma_px: float
    residuals: np.ndarray
    correction: np.ndarray
    velocity: np.ndarray
    velocity_jacobian: np.ndarray
    theta_cov: np.ndarray




def fit_rolling_frames(projector: Projector, poses: Sequence[Pose], frame: np.ndarray, points: np.ndarray,
                       observed: np.ndarray, shift_free: np.ndarray, rolling: np.ndarray, height: int, *,
                       iterations: int = 30, huber_px: float = 1.0, shift_sigma_px: float = 20.0,
                       twist_sigma: float = 0.3) -> RollingFit:
    """Fit every frame's pose, free shift and (where ``rolling``) rolling twist and curvature
    with the camera held (module docstring): Levenberg-Marquardt with a damping per frame
    (:data:`FRAME_DAMPING`), a trial accepted unless it raises the frame's cost by more than
    1e-12 of it, in lock-step rounds of at most :data:`ROUND_TRIALS` trials (the frames are
    linearised together once per round). A frame stops after ``iterations`` rounds, when its
    accepted step falls below :data:`STEP_TOL`, or when its last trial of a round is rejected (no
    damping lowers its cost); the later trials project the other frames' observations only.

    Args:
        projector: the camera held (:func:`blurcalib.calib.validation.generic_projector`).
        poses: ``(F,)`` initial poses; frame ``(N,)`` index; points ``(N, 3)`` m; observed
            ``(N, 2)`` px (OpenCV).
        shift_free, rolling: ``(F,)`` bool: frames with a free shift, and with rolling parameters.
        height: sensor rows ``H`` (px).
        huber_px, shift_sigma_px: as :class:`blurcalib.calib.bundle.BundleSettings`.
        twist_sigma: a weak prior ``|theta / sigma_theta|^2`` on the rolling parameters,
            ``sigma_theta`` this in rad and this times the frame's distance in m: it holds the
            combinations of pose and rolling geometry that the frame cannot tell apart near 0
            (the covariance and the test use the data alone).
    """
    fit = _RollingFrames(projector, poses, frame, points, observed, shift_free, rolling, height, huber_px,
                         shift_sigma_px, twist_sigma)
    rule = LmRule(FRAME_DAMPING, Stopping(max_iterations=iterations, lockstep=ROUND_TRIALS),
                  Acceptance(ties=True, rtol=1e-12))
    run_batch(fit, rule)
    return _finish(projector, fit)


class _RollingFrames:
    """The frames of :func:`fit_rolling_frames` as a batched least-squares problem
    (:class:`blurcalib.optim.lm.BatchProblem`, one item per frame): the poses ``R (F, 3, 3)``,
    ``t (F, 3)``, shifts ``s (F, 2)``, rolling parameters ``theta (F, 12)``, the observations'
    state (camera points, projections and their derivatives, inside, residuals), each frame's
    cost and normal equations ``H (F, 20, 20)``, ``b (F, 20)`` (linearised again once it moved)."""

    def __init__(self, projector: Projector, poses: Sequence[Pose], frame: np.ndarray, points: np.ndarray,
                 observed: np.ndarray, shift_free: np.ndarray, rolling: np.ndarray, height: int,
                 huber_px: float, shift_sigma_px: float, twist_sigma: float) -> None:
        kw: dict[str, Any] = {"dtype": torch.float64}
        F = len(poses)
        self.projector, self.huber_px = projector, huber_px
        self.fr = torch.as_tensor(np.asarray(frame, dtype=np.int64))
        self.P = torch.as_tensor(np.asarray(points, dtype=np.float64))
        self.p = torch.as_tensor(np.asarray(observed, dtype=np.float64))
        self.y = torch.as_tensor(row_coordinate(np.asarray(observed)[:, 1], height))
        self.free = np.zeros((F, _PARAMS), dtype=bool)
        self.free[:, :6] = True
        self.free[:, 6:8] = np.asarray(shift_free, dtype=bool)[:, None]
        self.free[:, 8:] = np.asarray(rolling, dtype=bool)[:, None]
        self.free_t = torch.as_tensor(self.free)
        self.R = torch.as_tensor(np.stack([q.R for q in poses]), **kw)
        self.t = torch.as_tensor(np.stack([q.t for q in poses]), **kw)
        self.s = torch.zeros(F, 2, **kw)
        self.theta = torch.zeros(F, 12, **kw)
        self.shift_w = 1.0 / shift_sigma_px**2
        self.theta_w = rolling_prior_weights(self.t, twist_sigma)
        self.every = torch.arange(len(self.fr))
        # projections start where observed
        self.state, self.cost = self.evaluate(self.R, self.t, self.s, self.theta, self.every, self.p.clone())
        self.H = torch.zeros(F, _PARAMS, _PARAMS, **kw)
        self.b = torch.zeros(F, _PARAMS, **kw)
        self.H_data = torch.zeros(F, _PARAMS, _PARAMS, **kw)
        self.stale = torch.ones(F, dtype=torch.bool)  # moved since its last linearisation

    def evaluate(self, R: torch.Tensor, t: torch.Tensor, s: torch.Tensor, theta: torch.Tensor,
                 rows: torch.Tensor, init: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        """The state of the observations ``rows`` (``X, Ri, RP, u, J_p, inside, r``) and the cost
        ``(F,)`` of their frames (the others': their priors alone)."""
        f = self.fr[rows]
        X, Ri, RP = rolling_points(R, t, theta, f, self.P[rows], self.y[rows])
        u, J_p, inside = self.projector(X, init)
        r = self.p[rows] - u - s[f]
        e = torch.where(inside, r.norm(dim=-1), 0.0)
        h = self.huber_px
        rho = torch.where(e <= h, e * e, 2 * h * e - h**2)
        cost = torch.zeros(len(R), dtype=torch.float64).index_add_(0, f, rho) \
            + self.shift_w * (s * s).sum(-1) + (self.theta_w * theta * theta).sum(-1)
        return [X, Ri, RP, u, J_p, inside, r], cost

    def linearise(self, frames: torch.Tensor) -> None:
        """The normal equations of the frames ``frames (F,)`` bool (Huber weights; the shift and
        rolling priors; the parameters a frame does not have decoupled)."""
        F = len(frames)
        rows = self.every[frames[self.fr]]
        X, Ri, RP, _, J_p, inside, r = (v[rows] for v in self.state)
        sel = torch.nonzero(inside).squeeze(1)
        J = rolling_frame_jacobian(J_p[sel], Ri[sel], RP[sel], X[sel], self.y[rows][sel])
        w = robust_weights(r[sel], self.huber_px)[:, None, None]
        f = self.fr[rows][sel]
        H = torch.zeros(F, _PARAMS, _PARAMS, dtype=torch.float64).index_add_(0, f,
                                                                              J.transpose(1, 2) @ (w * J))
        b = torch.zeros(F, _PARAMS, dtype=torch.float64).index_add_(
            0, f, (J.transpose(1, 2) @ (w * r[sel][:, :, None]))[..., 0])
        H[:, 6, 6] += self.shift_w
        H[:, 7, 7] += self.shift_w
        b[:, 6:8] -= self.shift_w * self.s
        free = self.free_t
        H = torch.where(free[:, :, None] & free[:, None, :], H, 0.0)
        H = H + torch.diag_embed((~free).to(H.dtype))
        self.H_data = torch.where(frames[:, None, None], H, self.H_data)
        H[:, 8:, 8:] += torch.diag_embed(self.theta_w)
        b[:, 8:] -= self.theta_w * self.theta
        self.H = torch.where(frames[:, None, None], H, self.H)
        self.b = torch.where(frames[:, None], torch.where(free, b, 0.0), self.b)
        self.stale &= ~frames

    def solve(self, lam: torch.Tensor, going: torch.Tensor) -> None:
        if bool((going & self.stale).any()):
            self.linearise(going & self.stale)
        diag = torch.diag_embed(torch.diagonal(self.H, dim1=1, dim2=2).clamp_min(1e-12))
        self.dp = torch.linalg.solve(self.H + lam[:, None, None] * diag, self.b)

    def trial(self, rows: torch.Tensor, index: int, last: bool) -> torch.Tensor:
        dp = self.dp
        tried = torch.zeros(len(self.R), dtype=torch.bool)
        tried[rows] = True
        self.obs = self.every[tried[self.fr]]
        self.moved = (exp_so3(dp[:, :3]) @ self.R, self.t + dp[:, 3:6], self.s + dp[:, 6:8],
                      self.theta + dp[:, 8:])
        self.moved_state, self.moved_cost = self.evaluate(*self.moved, self.obs, self.state[3][self.obs])
        return self.moved_cost[rows]

    def accept(self, rows: torch.Tensor, accepted: torch.Tensor) -> torch.Tensor:
        better = torch.zeros(len(self.R), dtype=torch.bool)
        better[rows[accepted]] = True
        R, t, s, theta = self.moved
        self.R = torch.where(better[:, None, None], R, self.R)
        self.t = torch.where(better[:, None], t, self.t)
        self.s = torch.where(better[:, None], s, self.s)
        self.theta = torch.where(better[:, None], theta, self.theta)
        keep = better[self.fr[self.obs]]
        for k, v in enumerate(self.moved_state):
            self.state[k][self.obs[keep]] = v[keep]
        self.cost = torch.where(better, self.moved_cost, self.cost)
        self.stale |= better
        return cast(torch.Tensor, accepted & (self.dp[rows].abs().amax(dim=1) < STEP_TOL))


def _finish(projector: Projector, fit: _RollingFrames) -> RollingFit:
    """The :class:`RollingFit` of a finished fit: residuals, their robust scale, what the rolling
    geometry adds, the image velocities and the covariance of ``theta`` (``sigma^2 H^-1`` of the
    data's normal equations at the last linearisation)."""
    X, _, RP, u, J_p, inside, r = fit.state
    R, t, s, theta, fr, y, free = fit.R, fit.t, fit.s, fit.theta, fit.fr, fit.y, fit.free
    res = torch.where(inside[:, None], r, torch.nan).numpy()
    ok = np.all(np.isfinite(res), axis=1)
    sigma = float(1.4826 * np.median(np.abs(res[ok]))) if ok.any() else math.nan
    rigid_X = RP + t[fr]
    u_rigid, _, _ = projector(rigid_X, u)
    correction = (u - u_rigid).numpy()
    twist = torch.cat([-J_p @ skew(X), J_p], dim=2)
    th = theta[fr]
    G = torch.cat([twist, 2 * y[:, None, None] * twist], dim=2)
    velocity = (G @ th[:, :, None])[..., 0].numpy()
    z = np.full(len(free), math.nan)
    Hn = fit.H_data.numpy()
    covs = np.full((len(free), 12, 12), math.nan)
    for f in np.flatnonzero(free[:, 8:].all(axis=1)):
        covs[f] = np.linalg.pinv(Hn[f])[8:, 8:] * sigma**2
        th_f = theta[f].numpy()
        z[f] = float(th_f @ np.linalg.pinv(covs[f]) @ th_f)
    Rn, tn = R.numpy(), t.numpy()
    return RollingFit([Pose(orthonormal(Rn[i]), tn[i]) for i in range(len(Rn))], s.numpy(), theta.numpy(),
                      z, sigma, res, np.where(ok[:, None], correction, 0.0),
                      np.where(ok[:, None], velocity, 0.0), np.where(ok[:, None, None], G.numpy(), 0.0),
                      covs)


def rolling_displacement(projector: Projector, poses: Sequence[Pose], theta: np.ndarray, frame: np.ndarray,
                         points: np.ndarray, observed: np.ndarray, height: int) -> np.ndarray:
    """``(N, 2)`` px: ``pi(rolling pose) - pi(rigid pose)`` of each observation under ``projector``
    with the frames' poses ``(F,)`` and rolling parameters ``theta (F, 12)`` (NaN where either
    projection leaves the area)."""
    kw: dict[str, Any] = {"dtype": torch.float64}
    fr = torch.as_tensor(np.asarray(frame, dtype=np.int64))
    P = torch.as_tensor(np.asarray(points, dtype=np.float64))
    y = torch.as_tensor(row_coordinate(np.asarray(observed)[:, 1], height))
    R = torch.as_tensor(np.stack([q.R for q in poses]), **kw)
    t = torch.as_tensor(np.stack([q.t for q in poses]), **kw)
    X, _, RP = rolling_points(R, t, torch.as_tensor(theta, **kw), fr, P, y)
    u, _, inside = projector(X, None)
    u_rigid, _, inside_rigid = projector(RP + t[fr], u)
    ok = (inside & inside_rigid)[:, None]
    return torch.where(ok, u - u_rigid, torch.nan).numpy()


