"""The least-squares problem of the parametric (Brown-Conrady) bundle adjustment of
:mod:`blurcalib.calib.sharp` and its solver.

:class:`ParametricProblem` holds the index structure: residuals ``pi_d(M_f, P_j) - p_fj`` (px) of
the observations, then (with free points) the points' prior ``(P_j - P_j^0) / sigma_P``, and their
sparse analytic Jacobian over the parameters ``(9 intrinsics, 6 F pose parameters, 3 Q points)``.
:func:`minimise` is Levenberg-Marquardt with Huber weights whose steps eliminate the poses
(:func:`solve_poses_eliminated`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse

from blurcalib.camera.parametric import project_poses

__all__ = ["ParametricProblem", "minimise", "solve_poses_eliminated"]


@dataclass
class ParametricProblem:
    """Index structure of one bundle adjustment (observations of the calibrated frames)."""

    frame_idx: np.ndarray  # (N,) frame index
    point_idx: np.ndarray  # (N,) index of each observation's point into ``nominal``
    observed: np.ndarray  # (N, 2) px
    nominal: np.ndarray  # (Q, 3) m, nominal point of each parameter point
    fixed_points: np.ndarray  # (N, 3) m, used when points are not refined
    num_frames: int
    refine_points: bool
    point_sigma: float

    @property
    def num_params(self) -> int:
        return 9 + 6 * self.num_frames + (3 * len(self.nominal) if self.refine_points else 0)

    def unpack(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``params`` -> intrinsics (9,), rvecs (F, 3), tvecs (F, 3), free points (Q, 3)."""
        poses = params[9:9 + 6 * self.num_frames].reshape(-1, 6)
        pts = params[9 + 6 * self.num_frames:].reshape(-1, 3) if self.refine_points else self.nominal
        return params[:9], poses[:, :3], poses[:, 3:], pts

    def obs_points(self, pts: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return pts[self.point_idx[rows]] if self.refine_points else self.fixed_points[rows]

    def predict(self, params: np.ndarray, rows: np.ndarray) -> np.ndarray:
        intr, rvecs, tvecs, pts = self.unpack(params)
        return project_poses(intr, rvecs, tvecs, self.obs_points(pts, rows), self.frame_idx[rows]).pixels

    def residual_fn(self, rows: np.ndarray):
        """Residuals ``(2 n + 3 Q,)``: ``pi_d - p`` of the rows (px), then the point prior."""
        def fun(params: np.ndarray) -> np.ndarray:
            res = (self.predict(params, rows) - self.observed[rows]).ravel()
            if not self.refine_points:
                return res
            pts = self.unpack(params)[3]
            return np.concatenate([res, ((pts - self.nominal) / self.point_sigma).ravel()])
        return fun

    def jacobian_fn(self, rows: np.ndarray):
        """Sparse Jacobian of :meth:`residual_fn` (CSR): 9 + 6 (+ 3) non-zeros per data row."""
        n = len(rows)
        fi = self.frame_idx[rows]
        cols = [np.broadcast_to(np.arange(9), (n, 9)),
                9 + 6 * fi[:, None] + np.arange(6)]
        if self.refine_points:
            cols.append(9 + 6 * self.num_frames + 3 * self.point_idx[rows][:, None] + np.arange(3))
        col = np.concatenate(cols, axis=1)
        data_cols = np.repeat(col[:, None, :], 2, axis=1).ravel()
        width = col.shape[1]
        data_rows = np.repeat(np.arange(2 * n), width)
        num_rows = 2 * n
        if self.refine_points:
            q = len(self.nominal)
            prior_cols = 9 + 6 * self.num_frames + np.arange(3 * q)
            data_rows = np.concatenate([data_rows, 2 * n + np.arange(3 * q)])
            data_cols = np.concatenate([data_cols, prior_cols])
            num_rows += 3 * q
        shape = (num_rows, self.num_params)

        def jac(params: np.ndarray) -> scipy.sparse.csr_matrix:
            intr, rvecs, tvecs, pts = self.unpack(params)
            proj = project_poses(intr, rvecs, tvecs, self.obs_points(pts, rows), fi, jacobian=True)
            parts = (proj.d_intrinsics, proj.d_pose, proj.d_point)
            values = np.concatenate(parts if self.refine_points else parts[:2], axis=2).ravel()
            if self.refine_points:
                values = np.concatenate([values, np.full(3 * len(self.nominal), 1.0 / self.point_sigma)])
            return scipy.sparse.csr_matrix((values, (data_rows, data_cols)), shape=shape)
        return jac


def solve_poses_eliminated(H: scipy.sparse.spmatrix, g: np.ndarray, frames: int) -> np.ndarray:
    """``H^-1 g`` for the adjustment's symmetric positive definite normal matrix ``H (n, n)``
    ordered as :class:`ParametricProblem`'s parameters (9 intrinsics, ``6 F`` pose parameters, then the
    points), by the Schur complement on the poses: their ``6 x 6`` blocks are independent, so::

        S = H_oo - H_op H_pp^-1 H_po,   S x_o = g_o - H_op H_pp^-1 g_p,   x_p = H_pp^-1 (g_p - H_po x_o)

    with ``o`` the intrinsics and points (``9 + 3 Q``, dense) and ``p`` the poses. Cost:
    ``O(F (9 + 3 Q)^2)`` and one dense Cholesky solve of ``S``.
    """
    Hc = H.tocsr()
    n = Hc.shape[0]
    pose = np.arange(9, 9 + 6 * frames)
    other = np.concatenate([np.arange(9), np.arange(9 + 6 * frames, n)])
    blocks = pose.reshape(frames, 6)
    Hpp = np.asarray(Hc[np.repeat(blocks, 6, axis=1).ravel(), np.tile(blocks, (1, 6)).ravel()]).reshape(
        frames, 6, 6)
    Hpp_inv = np.linalg.inv(Hpp)
    H_op = Hc[other][:, pose].toarray()
    Y = np.einsum("ofj,fji->ofi", H_op.reshape(len(other), frames, 6), Hpp_inv).reshape(len(other), -1)
    S = Hc[other][:, other].toarray() - Y @ H_op.T
    x = np.empty(n)
    x[other] = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), g[other] - Y @ g[pose])
    x[pose] = np.einsum("fij,fj->fi", Hpp_inv, (g[pose] - H_op.T @ x[other]).reshape(frames, 6)).ravel()
    return x


def minimise(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], scipy.sparse.spmatrix],
              x: np.ndarray, huber: float, frames: int, max_jacobians: int = 100, tol: float = 1e-10
              ) -> tuple[np.ndarray, int]:
    """``argmin_x sum_i rho(f_i(x))`` by Levenberg-Marquardt on the sparse normal equations; the
    minimiser and the Jacobians evaluated.

    ``rho`` is Huber's loss at ``huber`` per residual component (``f^2`` inside, ``2 h |f| - h^2``
    beyond; ``huber = inf``: plain squares), by iteratively reweighted Gauss-Newton: weights
    ``w_i = min(1, h / |f_i|)``, the step ``(J^T W J + lambda diag(J^T W J)) dx = -J^T W f``
    (Marquardt's damping, which ``x_scale='jac'`` of ``scipy.optimize.least_squares`` also
    amounts to), solved directly with the ``frames`` poses eliminated
    (:func:`solve_poses_eliminated`). ``lambda`` starts at 1e-6, /10 after
    an accepted step, x10 after a rejected one. Stops when an accepted step lowers the cost by
    less than ``tol`` of it or moves ``x`` by less than ``tol (tol + |x|)``, or after
    ``max_jacobians``.
    """
    def cost(f: np.ndarray) -> float:
        a = np.abs(f)
        if not math.isfinite(huber):
            return float(np.sum(a * a))
        return float(np.sum(np.where(a <= huber, a * a, 2.0 * huber * a - huber * huber)))

    f = fun(x)
    c = cost(f)
    lam = 1e-6
    for njev in range(1, max_jacobians + 1):
        J = jac(x).tocsr()
        w = np.minimum(1.0, huber / np.maximum(np.abs(f), 1e-300))
        H = (J.T @ J.multiply(w[:, None])).tocsr()
        g = J.T @ (w * f)
        diag = scipy.sparse.diags(np.maximum(H.diagonal(), 1e-12))
        while True:
            dx = -solve_poses_eliminated(H + lam * diag, g, frames)
            f_new = fun(x + dx)
            c_new = cost(f_new)
            if np.isfinite(c_new) and c_new <= c:
                break
            lam *= 10.0
            if lam > 1e12:
                return x, njev
        x, f, c_old, c = x + dx, f_new, c, c_new
        lam = max(lam / 10.0, 1e-12)
        if c_old - c <= tol * c_old or np.linalg.norm(dx) <= tol * (tol + np.linalg.norm(x)):
            return x, njev
    return x, max_jacobians
