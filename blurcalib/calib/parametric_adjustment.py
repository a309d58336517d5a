"""The least-squares problem of the parametric bundle adjustment of :mod:`blurcalib.calib.sharp`
and its solver, for any model of the parametric family (:mod:`blurcalib.camera.lens`).

:class:`ParametricProblem` holds the index structure: residuals ``pi_d(M_f, P_j) - p_fj`` (px) of
the observations, then (with free points) the points' prior ``(P_j - P_j^0) / sigma_P``, and their
sparse analytic Jacobian over the parameters ``(I intrinsics, 6 F pose parameters, 3 Q points)``
(``I`` the model's parameter count, 9 for Brown-Conrady), through
:func:`blurcalib.camera.lens.project_poses_camera`. :func:`minimise` is Levenberg-Marquardt with
Huber weights whose steps eliminate the poses (:func:`solve_poses_eliminated`); :func:`adjust`
repeats it without the outliers until the inlier set settles (an observation outside the model's
valid field is an outlier), and :func:`gauge_fixed` fixes the gauge of free points.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import scipy.linalg
import scipy.sparse

from blurcalib.camera.lens import ParametricCamera, project_poses_camera
from blurcalib.camera.parametric import rodrigues_jacobian
from blurcalib.optim.lm import Acceptance, Damping, LmRule, SingleProblem, Stopping, run_single

__all__ = ["ADJUSTMENT_DAMPING", "SETTLED_MARGIN", "SETTLED_SHARE", "ParametricProblem", "adjust",
           "gauge_fixed", "minimise", "robust_threshold", "settled", "solve_poses_eliminated", "umeyama"]


@dataclass
class ParametricProblem:
    """Index structure of one bundle adjustment (observations of the calibrated frames).

    ``camera`` is the model (its parameters are the start's; the problem's own live in the
    parameter vector)."""

    camera: ParametricCamera
    frame_idx: np.ndarray  # (N,) frame index
    point_idx: np.ndarray  # (N,) index of each observation's point into ``nominal``
    observed: np.ndarray  # (N, 2) px
    nominal: np.ndarray  # (Q, 3) m, nominal point of each parameter point
    fixed_points: np.ndarray  # (N, 3) m, used when points are not refined
    num_frames: int
    refine_points: bool
    point_sigma: float

    @property
    def num_intrinsics(self) -> int:
        return len(self.camera.params)

    @property
    def num_params(self) -> int:
        return (self.num_intrinsics + 6 * self.num_frames
                + (3 * len(self.nominal) if self.refine_points else 0))

    def unpack(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``params`` -> intrinsics (I,), rvecs (F, 3), tvecs (F, 3), free points (Q, 3)."""
        i = self.num_intrinsics
        poses = params[i:i + 6 * self.num_frames].reshape(-1, 6)
        pts = params[i + 6 * self.num_frames:].reshape(-1, 3) if self.refine_points else self.nominal
        return params[:i], poses[:, :3], poses[:, 3:], pts

    def obs_points(self, pts: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return cast(np.ndarray, pts[self.point_idx[rows]] if self.refine_points else self.fixed_points[rows])

    def predict(self, params: np.ndarray, rows: np.ndarray) -> np.ndarray:
        intr, rvecs, tvecs, pts = self.unpack(params)
        return project_poses_camera(self.camera.with_params(intr), rvecs, tvecs, self.obs_points(pts, rows),
                                    self.frame_idx[rows]).pixels

    def errors(self, params: np.ndarray) -> np.ndarray:
        """``(N,)`` px ``|pi_d(M_f, P_j) - p_fj|`` of every observation; ``inf`` where its point lies
        outside the model's valid field (behind a perspective camera, say)."""
        intr, rvecs, tvecs, pts = self.unpack(params)
        every = np.arange(len(self.observed))
        camera = self.camera.with_params(intr)
        R = rodrigues_jacobian(rvecs)[0][self.frame_idx]
        cam = np.einsum("nab,nb->na", R, self.obs_points(pts, every)) + tvecs[self.frame_idx]
        errors = np.linalg.norm(camera.project(cam) - self.observed, axis=1)
        return np.where(camera.valid_directions(cam), errors, np.inf)

    def residual_fn(self, rows: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        """Residuals ``(2 n + 3 Q,)``: ``pi_d - p`` of the rows (px), then the point prior."""
        def fun(params: np.ndarray) -> np.ndarray:
            res = (self.predict(params, rows) - self.observed[rows]).ravel()
            if not self.refine_points:
                return cast(np.ndarray, res)
            pts = self.unpack(params)[3]
            return np.concatenate([res, ((pts - self.nominal) / self.point_sigma).ravel()])
        return fun

    def jacobian_fn(self, rows: np.ndarray) -> Callable[[np.ndarray], scipy.sparse.csr_matrix]:
        """Sparse Jacobian of :meth:`residual_fn` (CSR): I + 6 (+ 3) non-zeros per data row."""
        n = len(rows)
        i = self.num_intrinsics
        fi = self.frame_idx[rows]
        cols = [np.broadcast_to(np.arange(i), (n, i)),
                i + 6 * fi[:, None] + np.arange(6)]
        if self.refine_points:
            cols.append(i + 6 * self.num_frames + 3 * self.point_idx[rows][:, None] + np.arange(3))
        col = np.concatenate(cols, axis=1)
        data_cols = np.repeat(col[:, None, :], 2, axis=1).ravel()
        width = col.shape[1]
        data_rows = np.repeat(np.arange(2 * n), width)
        num_rows = 2 * n
        if self.refine_points:
            q = len(self.nominal)
            prior_cols = i + 6 * self.num_frames + np.arange(3 * q)
            data_rows = np.concatenate([data_rows, 2 * n + np.arange(3 * q)])
            data_cols = np.concatenate([data_cols, prior_cols])
            num_rows += 3 * q
        shape = (num_rows, self.num_params)

        def jac(params: np.ndarray) -> scipy.sparse.csr_matrix:
            intr, rvecs, tvecs, pts = self.unpack(params)
            camera = self.camera.with_params(intr)
            proj = project_poses_camera(camera, rvecs, tvecs, self.obs_points(pts, rows), fi, jacobian=True)
            assert proj.d_intrinsics is not None and proj.d_pose is not None and proj.d_point is not None
            parts = (proj.d_intrinsics, proj.d_pose, proj.d_point)
            values: np.ndarray = np.concatenate(parts if self.refine_points else parts[:2], axis=2).ravel()
            if self.refine_points:
                values = np.concatenate([values, np.full(3 * len(self.nominal), 1.0 / self.point_sigma)])
            return scipy.sparse.csr_matrix((values, (data_rows, data_cols)), shape=shape)
        return jac


def solve_poses_eliminated(H: scipy.sparse.spmatrix, g: np.ndarray, frames: int, intrinsics: int = 9
                           ) -> np.ndarray:
    """``H^-1 g`` for the adjustment's symmetric positive definite normal matrix ``H (n, n)``
    ordered as :class:`ParametricProblem`'s parameters (``intrinsics`` intrinsics, ``6 F`` pose
    parameters, then ``3 Q`` point coordinates), by the Schur complement on a family of
    independent blocks: the poses' ``6 x 6`` blocks, or, with free points when ``3 Q > 6 F``, the
    points' ``3 x 3`` blocks (a point's residuals and prior involve no other point), so that the
    dense system left is the smaller of ``I + 3 Q`` and ``I + 6 F``. With ``p`` the eliminated
    parameters and ``o`` the others::

        S = H_oo - H_op H_pp^-1 H_po,   S x_o = g_o - H_op H_pp^-1 g_p,   x_p = H_pp^-1 (g_p - H_po x_o)

    Cost: ``O(n_p n_o^2)`` and one dense Cholesky solve of ``S (n_o, n_o)``.
    """
    n = H.shape[0]
    points = (n - intrinsics - 6 * frames) // 3
    if 3 * points > 6 * frames:
        start, size, count = intrinsics + 6 * frames, 3, points
    else:
        start, size, count = intrinsics, 6, frames
    eliminated = np.arange(start, start + size * count)
    other = np.concatenate([np.arange(start), np.arange(start + size * count, n)])
    return _solve_blocks_eliminated(H.tocsr(), g, eliminated.reshape(count, size), other)


def _solve_blocks_eliminated(Hc: scipy.sparse.csr_matrix, g: np.ndarray, blocks: np.ndarray,
                             other: np.ndarray) -> np.ndarray:
    """:func:`solve_poses_eliminated`'s Schur complement with the parameters ``blocks (K, b)``
    eliminated (``H`` block diagonal over them) and ``other (n_o,)`` solved densely."""
    count, size = blocks.shape
    eliminated = blocks.ravel()
    Hpp = np.asarray(Hc[np.repeat(blocks, size, axis=1).ravel(), np.tile(blocks, (1, size)).ravel()]).reshape(
        count, size, size)
    Hpp_inv = np.linalg.inv(Hpp)
    H_op = Hc[other][:, eliminated].toarray()
    Y = np.einsum("okj,kji->oki", H_op.reshape(len(other), count, size), Hpp_inv).reshape(len(other), -1)
    S = Hc[other][:, other].toarray() - Y @ H_op.T
    x = np.empty(Hc.shape[0])
    x[other] = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), g[other] - Y @ g[eliminated])
    x[eliminated] = np.einsum("kij,kj->ki", Hpp_inv,
                              (g[eliminated] - H_op.T @ x[other]).reshape(count, size)).ravel()
    return x


MEDIAN_TO_SIGMA = 1.0 / math.sqrt(2.0 * math.log(2.0))
"""``sigma = median(|e|) / sqrt(2 ln 2)`` for a 2-D isotropic Gaussian error ``e``."""
MIN_OUTLIER_PX = 0.01
"""The outlier threshold never drops below this (px), so noise-free data keeps its points."""
MAX_ROUNDS = 10
"""Outlier rounds at most (each a :func:`minimise` of at most 100 Jacobians)."""
SETTLED_SHARE = 1e-4
"""The outlier rounds also end when at most this share of the observations change side, each
with an error within :data:`SETTLED_MARGIN` of the threshold: flips at the margin, which move
the fit far less than its noise does. Below 10,000 observations the inlier set must be stable."""
SETTLED_MARGIN = 1.5
"""How near the threshold (a factor either way) an observation that changes side must lie for
:data:`SETTLED_SHARE` to end the rounds."""

ADJUSTMENT_DAMPING = Damping(start=1e-6, shrink=10.0, grow=10.0, floor=1e-12, ceiling=1e12)
"""Marquardt's ``lambda`` of :func:`minimise`: 1e-6, /10 (not below 1e-12) after an accepted step,
x10 after a rejected one; no step above 1e12."""


@dataclass
class _Point:
    """An iterate of :func:`minimise`: the parameters ``x (n,)`` and their residuals ``f (m,)``."""

    x: np.ndarray
    f: np.ndarray


class _Robust(SingleProblem[_Point, tuple[Any, ...], np.ndarray]):
    """``sum_i rho(f_i(x))`` with Huber's ``rho`` at ``huber`` (``inf``: squares), its steps solved
    with the poses eliminated (:func:`solve_poses_eliminated`)."""

    def __init__(self, fun: Callable[[np.ndarray], np.ndarray],
                 jac: Callable[[np.ndarray], scipy.sparse.spmatrix], huber: float, frames: int,
                 tol: float, intrinsics: int) -> None:
        self.fun, self.jac, self.huber, self.frames, self.tol = fun, jac, huber, frames, tol
        self.intrinsics = intrinsics

    def cost(self, f: np.ndarray) -> float:
        a = np.abs(f)
        if not math.isfinite(self.huber):
            return float(np.sum(a * a))
        return float(np.sum(np.where(a <= self.huber, a * a, 2.0 * self.huber * a - self.huber * self.huber)))

    def linearise(self, p: _Point) -> tuple[Any, ...]:
        """``(J^T W J, J^T W f, its diagonal)`` with the IRLS weights ``w = min(1, huber / |f|)``."""
        J = self.jac(p.x).tocsr()
        w = np.minimum(1.0, self.huber / np.maximum(np.abs(p.f), 1e-300))
        H = (J.T @ J.multiply(w[:, None])).tocsr()
        g = J.T @ (w * p.f)
        return H, g, scipy.sparse.diags(np.maximum(H.diagonal(), 1e-12))

    def solve(self, system: tuple[Any, ...], lam: float) -> np.ndarray | None:
        """The damped step, or None (a rejected trial) where the system is singular."""
        H, g, diag = system
        try:
            return -solve_poses_eliminated(H + lam * diag, g, self.frames, self.intrinsics)
        except np.linalg.LinAlgError:  # scipy's LinAlgError too
            return None

    def trial(self, p: _Point, step: np.ndarray) -> tuple[_Point, float]:
        x = p.x + step
        f = self.fun(x)
        return _Point(x, f), self.cost(f)

    def accept(self, p: _Point, moved: _Point, step: np.ndarray, cost: float) -> tuple[_Point, float, bool]:
        """Converged when the step is below ``tol (tol + |x|)``."""
        return moved, cost, bool(np.linalg.norm(step) <= self.tol * (self.tol + np.linalg.norm(moved.x)))


def minimise(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], scipy.sparse.spmatrix],
              x: np.ndarray, huber: float, frames: int, max_jacobians: int = 100, tol: float = 1e-10,
              intrinsics: int = 9) -> tuple[np.ndarray, int]:
    """``argmin_x sum_i rho(f_i(x))`` by Levenberg-Marquardt on the sparse normal equations; the
    minimiser and the Jacobians evaluated.

    ``rho`` is Huber's loss at ``huber`` per residual component (``f^2`` inside, ``2 h |f| - h^2``
    beyond; ``huber = inf``: plain squares), by iteratively reweighted Gauss-Newton: weights
    ``w_i = min(1, h / |f_i|)``, the step ``(J^T W J + lambda diag(J^T W J)) dx = -J^T W f``
    (Marquardt's damping, which ``x_scale='jac'`` of ``scipy.optimize.least_squares`` also
    amounts to), solved directly with the ``frames`` poses after the ``intrinsics`` eliminated
    (:func:`solve_poses_eliminated`); the loop is :func:`blurcalib.optim.lm.run_single` with
    :data:`ADJUSTMENT_DAMPING`, a step of equal cost accepted. Stops when an accepted step lowers
    the cost by at most ``tol`` of it or moves ``x`` by at most ``tol (tol + |x|)``, when no damping
    up to the ceiling lowers it, or after ``max_jacobians``.
    """
    problem = _Robust(fun, jac, huber, frames, tol, intrinsics)
    f = fun(x)
    rule = LmRule(ADJUSTMENT_DAMPING, Stopping(max_iterations=max_jacobians, rtol=tol), Acceptance(ties=True))
    run = run_single(problem, _Point(x, f), problem.cost(f), rule)
    return run.x.x, run.iterations


def robust_threshold(errors: np.ndarray, sigmas: float, num_params: int) -> float:
    """Outlier threshold ``max(sigmas * sigma, 0.01 px)`` for inlier error norms ``errors (n,)``.

    ``sigma = median(errors) / sqrt(2 ln 2) * sqrt(2 n / (2 n - p))``: the robust standard
    deviation per axis, corrected for the ``p`` fitted parameters that absorb part of the noise.
    """
    dof = max(2 * errors.size - num_params, 1)
    sigma = float(np.median(errors)) * MEDIAN_TO_SIGMA * math.sqrt(2 * errors.size / dof)
    return max(sigmas * sigma, MIN_OUTLIER_PX)


def settled(changed: np.ndarray, limit: float, count: int) -> bool:
    """Whether the outlier rounds end: the error norms ``changed (k,)`` px of the observations that
    would change side at threshold ``limit`` px are none, or at most :data:`SETTLED_SHARE` of the
    ``count`` observations, each within :data:`SETTLED_MARGIN` of ``limit``."""
    if changed.size == 0:
        return True
    marginal = np.all((changed >= limit / SETTLED_MARGIN) & (changed <= limit * SETTLED_MARGIN))
    return bool(changed.size <= SETTLED_SHARE * count and marginal)


def adjust(problem: ParametricProblem, params: np.ndarray, inlier: np.ndarray, huber: float,
           outlier_sigmas: float) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The robust adjustment of :mod:`blurcalib.calib.sharp`: :func:`minimise` over the inliers
    ``inlier (N,)``, then every observation whose error ``|pi_d(M, P) - p|`` exceeds
    :func:`robust_threshold` of the inliers' errors is an outlier and the rest inliers (rejected
    ones may return), in rounds until the inlier set is :func:`settled` or :data:`MAX_ROUNDS`. An
    observation outside the model's valid field (:meth:`ParametricProblem.errors`) is never an
    inlier.

    Returns:
        The parameters ``(n,)``, the inliers ``(N,)`` they were fitted to, the Jacobians evaluated
        and the rounds.
    """
    iterations = 0
    inlier = inlier & np.isfinite(problem.errors(params))
    for rounds in range(1, MAX_ROUNDS + 1):
        rows = np.flatnonzero(inlier)
        params, njev = minimise(problem.residual_fn(rows), problem.jacobian_fn(rows), params, huber,
                                problem.num_frames, intrinsics=problem.num_intrinsics)
        iterations += njev
        errors = problem.errors(params)
        limit = robust_threshold(errors[inlier], outlier_sigmas, problem.num_params)
        new_inlier = errors <= limit
        if settled(errors[new_inlier != inlier], limit, len(errors)) or rounds == MAX_ROUNDS:
            break
        inlier = new_inlier
    return params, inlier, iterations, rounds


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``(s, Q, b)`` minimising ``sum |s Q source_i + b - target_i|^2`` (Umeyama 1991)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    sc, tc = source - mu_s, target - mu_t
    U, D, Vt = np.linalg.svd(tc.T @ sc / len(source))
    E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    Q = U @ E @ Vt
    s = float(np.trace(np.diag(D) @ E) / np.mean(np.sum(sc**2, axis=1)))
    return s, Q, mu_t - s * Q @ mu_s


def gauge_fixed(problem: ParametricProblem, params: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The intrinsics ``(I,)``, rotations ``(F, 3, 3)``, translations ``(F, 3)`` m and points
    ``(Q, 3)`` m of ``params``, with free points in the gauge of :mod:`blurcalib.calib.sharp`: the
    similarity (:func:`umeyama`) that best maps the points onto the nominal ones applied to points
    and poses (``P -> s Q P + b``, ``R -> R Q^T``, ``t -> s t - R Q^T b``)."""
    intr, rvecs, tvecs, pts = problem.unpack(params)
    rotations = rodrigues_jacobian(rvecs)[0]
    if problem.refine_points:
        s, Q, b = umeyama(pts, problem.nominal)
        pts = s * pts @ Q.T + b
        rotations = rotations @ Q.T
        tvecs = s * tvecs - rotations @ b
    return intr, rotations, tvecs, pts
