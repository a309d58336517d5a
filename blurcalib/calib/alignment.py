"""Global alignment of one frame's features to a calibrated parametric camera (Brown-Conrady, or
any model of the family: :mod:`blurcalib.camera.lens`).

Deconvolution leaves every blurry-frame feature with an unknown translation (paper section
"Global Alignment"). The discrepancy between an observation and its parametric projection is
(``eq:error_decomposition``)::

    p^{ij} - pi_d(M, P^{ij}) = eps_deconv + eps_align + b(r^{ij})

and the frame's translation ``x_G`` is removed jointly with the camera pose ``M`` by the robust
problem (``eq:global_align``)::

    argmin_{x_G, M}  sum_ij  w_ij rho(d[pi_d(M, P^{ij}), p^{ij} - x_G]^2)

This module solves it, and its spatially varying generalisations, for one frame:

* ``bias="translation"``: one translation ``x_G`` (``eq:global_align``);
* ``bias="bilinear"``: the continuous bilinear field (``eq:bilinear_bias``, supplement B)
  ``b(i, j) = a0 + a1 i + a2 j + a3 i j`` per image axis over normalised grid coordinates
  ``(i, j) in [-1, 1]^2``;
* ``bias="quadrants"``: the discrete variant, one translation per quadrant of the grid;
* ``bias="none"``: the pose alone (the frame's own parametric fit, a plain robust PnP).

The models and their grid coordinates are :mod:`blurcalib.calib.bias`'s.

Losses ``rho`` (of the distance ``d`` in px, each point weighted by ``w``):

* ``"mean"``: least squares, ``d^2 / 2`` (for a fixed pose ``x_G`` is the weighted mean of the
  residuals);
* ``"huber"``: ``d^2 / 2`` for ``d <= delta``, ``delta (d - delta / 2)`` beyond
  (``delta = huber_px``);
* ``"median"``: the L1-type loss ``d`` (the sum of distances). For a fixed pose its
  translation is the weighted *spatial (geometric) median* of the residuals, the 2-D median
  that is invariant to rotations of the image; that is what "median" means here.

Solvers (``method``):

* ``"joint"`` (default): Levenberg-Marquardt on the pose and the bias coefficients together,
  with iteratively reweighted least squares (IRLS) for the robust losses. Its normal equations
  contain supplement B's ``4 x 4`` matrices ``M = sum_k w_k phi_k phi_k^T`` as the bias block,
  coupled to the pose block.
* ``"alternating"``: supplement B's scheme literally: (1) the pose by PnP on
  ``p_obs - b`` (a robust Gauss-Newton refinement from the previous pose), (2) the residuals
  ``r = p_obs - proj``, (3) the bias coefficients by weighted least squares from the normal
  equations ``M a = v_x``, ``M c = v_y``. Both solvers have the same fixed points, but the
  alternation is block coordinate descent on a problem whose pose and translation are strongly
  coupled (a translation of the image is almost a change of pose), so it converges very slowly:
  on a 40-degree view of the A4 target, 100 alternations leave about three quarters of a 3.6 px
  shift in the pose. It is kept to reproduce the supplement and to show that.

The translation is genuinely ill-conditioned when the camera looks straight at the target:
the perspective mapping is then nearly affine and a translation of the image is nearly a
change of pose. :func:`orientation_ok` is the paper's orientation filter and
:func:`alignment_covariance` gives the Cramér-Rao covariance that quantifies it.

Pixels follow OpenCV's convention (top-left pixel centre at ``(0, 0)``, x right, y down);
poses map target to camera, ``X_cam = R X + t`` (metres). Weights ``w`` are confidences: pass
``loss_weights(loss)`` = ``1 / (loss + eps)`` to weight features by their per-block
deconvolution loss, as supplement B does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike

from blurcalib.calib.bias import BIASES, bias_basis, coeffs_from_beta, grid_coordinates
from blurcalib.calib.pnp import solve_pose
from blurcalib.camera.lens import ParametricCamera, project_poses_camera
from blurcalib.camera.parametric import BrownConrady, project_poses
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import BlockTable
from blurcalib.optim.lm import Acceptance, Damping, LmRule, SingleProblem, Stopping, run_single
from blurcalib.target.pattern import StarPattern

__all__ = [
    "BIASES",
    "DEFAULT_ANGLE_THRESHOLD",
    "LOSSES",
    "METHODS",
    "MIN_BLOCKS",
    "AlignmentError",
    "AlignmentSettings",
    "GlobalAlignment",
    "align_blocks",
    "align_global",
    "align_kept_blocks",
    "alignment_covariance",
    "loss_weights",
    "orientation_ok",
]

LOSSES: tuple[str, ...] = ("huber", "mean", "median")
"""Robust kernels ``rho`` of ``eq:global_align``."""

METHODS: tuple[str, ...] = ("joint", "alternating")
"""Solvers: joint Levenberg-Marquardt, or supplement B's alternation."""

DEFAULT_ANGLE_THRESHOLD = math.pi / 10
"""The paper's orientation filter: frames whose optical axis is within pi/10 rad (18 degrees)
of the target normal are flagged as ill-conditioned."""

DEFAULT_HUBER_PX = 0.035
"""Default Huber threshold ``delta`` (px): 1.345 times the features' rms noise (about 0.026 px
for star centres, sharp or blurry), the standard 95%-efficiency tuning. A threshold of 0.1 px
touches no simulated residual, which makes "Huber" least squares; ``blurcalib experiment
alignment`` (Table 1, ``docs/experiments.md``) measures the difference."""

MIN_BLOCKS = 12
"""Fewest kept blocks a frame is aligned with by :func:`align_blocks`: the pose (6 DoF) and
``x_G`` (2) need well more than the minimal 4 points to be told apart."""

_L1_FLOOR_PX = 1e-4
"""Smallest distance (px) used in the IRLS weight ``1 / d`` of the L1 ("median") loss."""

ALIGNMENT_DAMPING = Damping(start=1e-6, shrink=10.0, grow=10.0, floor=1e-12, ceiling=1e12)
"""Marquardt's ``lambda`` of the alignment's Levenberg-Marquardt steps: 1e-6, /10 (not below
1e-12) after an accepted step, x10 after a rejected one; no step above 1e12."""

_POSE_STEPS_PER_ALTERNATION = 3


# ---------------------------------------------------------------------------------- weights
def loss_weights(loss: ArrayLike, eps: float = 1e-3) -> np.ndarray:
    """Supplement B's feature weights ``w_k = 1 / (loss_k + eps)`` from per-block losses.

    Args:
        loss: ``(N,)`` per-block deconvolution losses (grey levels squared), ``>= 0``.
        eps: regulariser (same unit as ``loss``), ``> 0``.
    """
    loss = np.asarray(loss, dtype=np.float64)
    if eps <= 0 or np.any(loss < 0) or not np.all(np.isfinite(loss)):
        raise ValueError("losses must be finite and >= 0, and eps > 0")
    return 1.0 / (loss + eps)


# ------------------------------------------------------------------------------ orientation
def orientation_ok(pose: Pose, threshold: float = DEFAULT_ANGLE_THRESHOLD) -> bool:
    """The paper's orientation filter: True when the translation is well conditioned.

    A frame fails (False) when its optical axis is within ``threshold`` rad of the target
    normal: the perspective mapping is then nearly affine, so an image translation is nearly a
    change of pose and ``x_G`` is ill-determined.
    """
    return pose.optical_axis_angle_to_target_normal() >= threshold


# ---------------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class GlobalAlignment:
    """One frame aligned to a parametric camera (``eq:global_align``).

    Attributes:
        pose: the estimated pose ``M`` (target -> camera).
        translation: ``x_G (2,)`` px; for the bilinear and quadrant models the field's mean over
            the features (zero for ``"none"``).
        bias_coeffs: the bias model's coefficients (px): ``(0,)`` for ``"none"``, ``(2,)`` for
            ``"translation"``, ``(2, 4)`` for ``"bilinear"`` (row 0: ``a0..a3`` of ``b_x``, row
            1: ``c0..c3`` of ``b_y``, over ``(1, i, j, ij)``), ``(4, 2)`` for ``"quadrants"``
            (rows top-left, top-right, bottom-left, bottom-right; columns x, y).
        corrected: ``(N, 2)`` px, the aligned features ``p_obs - b``.
        residuals: ``(N, 2)`` px, ``corrected - pi_d(M, P)``.
        robust_weights: ``(N,)`` final IRLS weights of the loss (1 for ``"mean"``), without
            the input ``weights``.
        median_error, mean_error: median / mean of ``|residuals|`` (px).
        angle_to_normal: angle (rad) between the optical axis and the target normal.
        ill_conditioned: ``angle_to_normal < angle_threshold`` (the orientation filter).
        iterations: iterations run.
        converged: whether the solver met its tolerance within ``iterations``.
        loss, bias, method: the options used.
    """

    pose: Pose
    translation: np.ndarray
    bias_coeffs: np.ndarray
    corrected: np.ndarray = field(repr=False)
    residuals: np.ndarray = field(repr=False)
    robust_weights: np.ndarray = field(repr=False)
    median_error: float
    mean_error: float
    angle_to_normal: float
    ill_conditioned: bool
    iterations: int
    converged: bool
    loss: str
    bias: str
    method: str


# ------------------------------------------------------------------------------- the solver
@dataclass(frozen=True)
class _Problem:
    """Fixed data of one alignment: the camera, points, observations, basis and weights."""

    camera: BrownConrady | ParametricCamera
    points: np.ndarray
    observed: np.ndarray
    phi: np.ndarray
    weights: np.ndarray
    loss: str
    huber_px: float

    def project(self, pose6: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """``pi_d`` of the points at pose ``(rvec, tvec)``; with its ``(N, 2, 6)`` Jacobian."""
        if isinstance(self.camera, BrownConrady):
            proj = project_poses(self.camera.params, pose6[:3], pose6[3:], self.points, jacobian=jacobian)
        else:
            proj = project_poses_camera(self.camera, pose6[None, :3], pose6[None, 3:], self.points,
                                        jacobian=jacobian)
        return proj.pixels, proj.d_pose

    def residuals(self, pose6: np.ndarray, beta: np.ndarray) -> np.ndarray:
        """``e = p_obs - b - pi_d(M, P)``, ``(N, 2)`` px."""
        proj, _ = self.project(pose6, jacobian=False)
        return cast(np.ndarray, self.observed - self.phi @ beta.reshape(2, -1).T - proj)

    def robust_weight(self, dist: np.ndarray) -> np.ndarray:
        """IRLS weights ``rho'(d) / d`` of the loss."""
        if self.loss == "mean":
            return np.ones_like(dist)
        if self.loss == "huber":
            return cast(np.ndarray, np.minimum(1.0, self.huber_px / np.maximum(dist, 1e-300)))
        return cast(np.ndarray, 1.0 / np.maximum(dist, _L1_FLOOR_PX))

    def cost(self, e: np.ndarray) -> float:
        """``sum_k w_k rho(d_k)`` with ``rho`` the loss of the distance ``d`` (px)."""
        d = np.hypot(e[:, 0], e[:, 1])
        if self.loss == "mean":
            rho = 0.5 * d * d
        elif self.loss == "huber":
            delta = self.huber_px
            rho = np.where(d <= delta, 0.5 * d * d, delta * (d - 0.5 * delta))
        else:
            rho = d
        return float(np.sum(self.weights * rho))


def _normal_equations(problem: _Problem, pose6: np.ndarray, beta: np.ndarray, with_pose: bool,
                      with_bias: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IRLS normal equations ``A delta = g`` of the selected parameter blocks.

    The model is ``p_obs ~ pi_d(M, P) + phi b``; its Jacobian has the pose columns
    ``d pi_d / d (rvec, tvec)`` and the bias columns ``phi`` per axis, so the bias block of
    ``A`` holds supplement B's matrix ``M = sum_k w_k phi_k phi_k^T`` once per axis.
    Returns ``(A, g, e)`` with ``e`` the current residuals.
    """
    proj, jpose = problem.project(pose6, jacobian=with_pose)
    e = problem.observed - problem.phi @ beta.reshape(2, -1).T - proj
    w = problem.weights * problem.robust_weight(np.hypot(e[:, 0], e[:, 1]))
    blocks: list[np.ndarray] = []
    if with_pose:
        assert jpose is not None  # asked for
        blocks.append(jpose)
    if with_bias:
        nb = problem.phi.shape[1]
        jb = np.zeros((len(e), 2, 2 * nb))
        jb[:, 0, :nb] = problem.phi
        jb[:, 1, nb:] = problem.phi
        blocks.append(jb)
    J = np.concatenate(blocks, axis=2)
    Jw = J * w[:, None, None]
    A = np.einsum("kai,kaj->ij", Jw, J)
    g = np.einsum("kai,ka->i", Jw, e)
    return A, g, e


_Point = tuple[np.ndarray, np.ndarray]
"""An iterate of the alignment: the pose ``(rvec, tvec) (6,)`` and the bias coefficients ``beta``."""


class _Steps(SingleProblem[_Point, tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]):
    """Levenberg-Marquardt steps of the pose and (``with_bias``) the bias coefficients at a point
    ``(pose6, beta)``, from the IRLS normal equations (:func:`_normal_equations`) damped by
    ``lambda diag(A)`` (the diagonal floored at 1e-12 of its largest entry)."""

    def __init__(self, problem: _Problem, with_bias: bool) -> None:
        self.problem, self.with_bias = problem, with_bias

    def linearise(self, x: _Point) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        A, g, _ = _normal_equations(self.problem, *x, True, self.with_bias)
        return A, g, np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))

    def solve(self, system: tuple[np.ndarray, np.ndarray, np.ndarray], lam: float) -> np.ndarray | None:
        A, g, diag = system
        try:
            return np.linalg.solve(A + lam * np.diag(diag), g)
        except np.linalg.LinAlgError:
            return None

    def trial(self, x: _Point, step: np.ndarray) -> tuple[_Point, float]:
        pose6, beta = x
        moved = (pose6 + step[:6], beta + step[6:] if self.with_bias else beta)
        return moved, self.problem.cost(self.problem.residuals(*moved))


def _initial_pose(problem: _Problem) -> np.ndarray:
    """A pose from ``cv2.solvePnP`` (SQPnP, then Levenberg-Marquardt refinement); for a camera of
    the parametric family, :func:`blurcalib.calib.pnp.solve_pose` (in viewing directions)."""
    obj = np.ascontiguousarray(problem.points, dtype=np.float64)
    img = np.ascontiguousarray(problem.observed, dtype=np.float64)
    if not isinstance(problem.camera, BrownConrady):
        try:
            pose = solve_pose(problem.camera, obj, img, ransac_px=20.0)
        except ValueError:
            raise ValueError("no pose found: the observations do not determine a pose") from None
        return np.concatenate([pose.rvec, pose.t])
    ok, rvec, tvec = cv2.solvePnP(obj, img, problem.camera.K, problem.camera.dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise ValueError("solvePnP failed: the observations do not determine a pose")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, problem.camera.K, problem.camera.dist, rvec, tvec)
    return np.concatenate([rvec.reshape(3), tvec.reshape(3)])


def align_global(camera: BrownConrady | ParametricCamera, points_3d: ArrayLike, observed: ArrayLike,
                 weights: ArrayLike | None = None, grid: ArrayLike | None = None, *,
                 loss: str = "huber", huber_px: float = DEFAULT_HUBER_PX, bias: str = "translation",
                 iterations: int = 100, method: str = "joint", initial_pose: Pose | None = None,
                 angle_threshold: float = DEFAULT_ANGLE_THRESHOLD, tol: float = 1e-12) -> GlobalAlignment:
    """Align one frame's features to the parametric camera (``eq:global_align``).

    Minimises ``sum_k w_k rho(|p_k - b(i_k, j_k) - pi_d(M, P_k)|)`` over the pose ``M`` and the
    bias coefficients (``eq:global_align``; ``eq:bilinear_bias`` and supplement B for the
    bilinear field). The pose starts from SQPnP on the raw observations (or ``initial_pose``)
    and the bias from zero.

    Args:
        camera: the calibrated parametric camera ``pi_d`` (from the sharp set).
        points_3d: ``(N, 3)`` target points ``P`` (m) of the observed features.
        observed: ``(N, 2)`` observed feature positions (px, OpenCV convention).
        weights: ``(N,)`` confidences ``w_k >= 0`` (e.g. :func:`loss_weights` of the per-block
            deconvolution losses), or None for equal weights. These are weights, not losses.
        grid: ``(N, 2)`` normalised grid coordinates (:func:`blurcalib.calib.bias.grid_coordinates`);
            required for ``"bilinear"`` and ``"quadrants"``.
        loss: ``"huber"``, ``"mean"`` or ``"median"`` (see the module docstring).
        huber_px: Huber threshold ``delta`` (px).
        bias: ``"none"``, ``"translation"``, ``"bilinear"`` or ``"quadrants"``.
        iterations: maximum solver iterations (LM steps, or alternations).
        method: ``"joint"`` or ``"alternating"`` (see the module docstring).
        initial_pose: starting pose; None runs SQPnP.
        angle_threshold: orientation filter threshold (rad) for ``ill_conditioned``.
        tol: stop when an iteration lowers the cost by less than this fraction.

    Raises:
        ValueError: inconsistent shapes, an unknown option, fewer than 6 weighted points, or a
            failed initial PnP.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if not huber_px > 0:
        raise ValueError(f"huber_px must be positive, got {huber_px}")
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    P = np.asarray(points_3d, dtype=np.float64)
    p = np.asarray(observed, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or p.shape != (len(P), 2):
        raise ValueError(f"need points_3d (N, 3) and observed (N, 2), got {P.shape} and {p.shape}")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(p))):
        raise ValueError("points_3d and observed must be finite")
    w = np.ones(len(P)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(P),) or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError(f"weights must be finite, >= 0 and of shape ({len(P)},)")
    if np.count_nonzero(w) < 6:
        raise ValueError(f"need at least 6 points with positive weight, got {np.count_nonzero(w)}")
    phi = bias_basis(grid, bias, len(P))
    problem = _Problem(camera, P, p, phi, w, loss, float(huber_px))
    pose6 = (_initial_pose(problem) if initial_pose is None
             else np.concatenate([initial_pose.rvec, initial_pose.t]))
    beta = np.zeros(2 * phi.shape[1])
    with_bias = phi.shape[1] > 0
    if method == "joint" or not with_bias:
        pose6, beta, done, converged = _solve_joint(problem, pose6, beta, with_bias, iterations, tol)
    else:
        pose6, beta, done, converged = _solve_alternating(problem, pose6, beta, iterations, tol)
    pose = Pose.from_rvec_tvec(pose6[:3], pose6[3:])
    b = phi @ beta.reshape(2, -1).T
    corrected = p - b
    residuals = problem.residuals(pose6, beta)
    dist = np.hypot(residuals[:, 0], residuals[:, 1])
    angle = pose.optical_axis_angle_to_target_normal()
    return GlobalAlignment(
        pose=pose, translation=b.mean(axis=0) if with_bias else np.zeros(2),
        bias_coeffs=coeffs_from_beta(beta, bias), corrected=corrected, residuals=residuals,
        robust_weights=problem.robust_weight(dist), median_error=float(np.median(dist)),
        mean_error=float(np.mean(dist)), angle_to_normal=angle,
        ill_conditioned=bool(angle < angle_threshold), iterations=done, converged=converged,
        loss=loss, bias=bias, method=method)


def _solve_joint(problem: _Problem, pose6: np.ndarray, beta: np.ndarray, with_bias: bool,
                 iterations: int, tol: float) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Levenberg-Marquardt with IRLS weights over the pose and the bias together
    (:data:`ALIGNMENT_DAMPING`); converged when a step lowers the cost by at most ``tol`` of it or
    no damping lowers it."""
    cost = problem.cost(problem.residuals(pose6, beta))
    rule = LmRule(ALIGNMENT_DAMPING, Stopping(max_iterations=iterations, rtol=tol), Acceptance(ties=True))
    run = run_single(_Steps(problem, with_bias), (pose6, beta), cost, rule)
    return *run.x, run.iterations, run.settled


def _solve_alternating(problem: _Problem, pose6: np.ndarray, beta: np.ndarray, iterations: int,
                       tol: float) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Supplement B: PnP on ``p_obs - b`` (at most :data:`_POSE_STEPS_PER_ALTERNATION`
    Levenberg-Marquardt steps of the pose, the damping carried from one alternation to the next),
    residuals, weighted least squares for the bias."""
    lam = ALIGNMENT_DAMPING.start
    cost = problem.cost(problem.residuals(pose6, beta))
    pose_steps = LmRule(ALIGNMENT_DAMPING, Stopping(max_iterations=_POSE_STEPS_PER_ALTERNATION),
                        Acceptance(ties=True))
    for it in range(1, iterations + 1):
        here = problem.cost(problem.residuals(pose6, beta))
        run = run_single(_Steps(problem, False), (pose6, beta), here, pose_steps, lam)
        (pose6, beta), lam = run.x, run.lam
        proj, _ = problem.project(pose6, jacobian=False)
        r = problem.observed - proj
        e = r - problem.phi @ beta.reshape(2, -1).T
        w = problem.weights * problem.robust_weight(np.hypot(e[:, 0], e[:, 1]))
        M = (problem.phi * w[:, None]).T @ problem.phi
        v = (problem.phi * w[:, None]).T @ r
        candidate = np.linalg.lstsq(M, v, rcond=None)[0].T.reshape(-1)
        new_cost = problem.cost(problem.residuals(pose6, candidate))
        if new_cost <= cost:
            beta = candidate
        decrease = (cost - min(new_cost, cost)) / max(cost, 1e-300)
        cost = min(new_cost, cost)
        if decrease < tol:
            return pose6, beta, it, True
    return pose6, beta, iterations, False


def alignment_covariance(camera: BrownConrady | ParametricCamera, pose: Pose, points_3d: ArrayLike,
                         grid: ArrayLike | None = None, bias: str = "translation",
                         sigma_px: float = 1.0, weights: ArrayLike | None = None) -> np.ndarray:
    """Cramér-Rao covariance (px^2) of the bias coefficients for one frame.

    For isotropic Gaussian feature noise of ``sigma_px`` px per axis (scaled by
    ``1 / sqrt(weights)``), the least-squares estimate of ``(M, b)`` has covariance
    ``sigma^2 (J^T W J)^-1``; this returns its bias block, i.e. how well the frame's geometry
    separates the bias from the pose. It is large for frames facing the target (the
    orientation filter's reason).

    Returns:
        ``(C, C)`` with ``C = bias_coeffs.size``, ordered as ``bias_coeffs.ravel()``.
    """
    P = np.asarray(points_3d, dtype=np.float64)
    n = len(P)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    phi = bias_basis(grid, bias, n)
    if phi.shape[1] == 0:
        return np.zeros((0, 0))
    problem = _Problem(camera, P, np.zeros((n, 2)), phi, w, "mean", 1.0)
    pose6 = np.concatenate([pose.rvec, pose.t])
    A, _, _ = _normal_equations(problem, pose6, np.zeros(2 * phi.shape[1]), True, True)
    cov = sigma_px**2 * np.linalg.pinv(A)[6:, 6:]
    index = coeffs_from_beta(np.arange(cov.shape[0]), bias).ravel()
    return cast(np.ndarray, cov[np.ix_(index, index)])


# ------------------------------------------------------------------ a frame's kept blocks
class AlignmentError(ValueError):
    """A frame's blocks cannot be aligned; the message says why (too few blocks, a failed pose)."""


@dataclass(frozen=True)
class AlignmentSettings:
    """How a frame's kept blocks are aligned (:func:`align_blocks`): the one set of defaults of
    the pipeline, the app and the experiments.

    Attributes:
        loss: ``huber``, ``mean`` or ``median``.
        huber_px: Huber threshold (px), :data:`DEFAULT_HUBER_PX`.
        bias: ``none``, ``translation``, ``bilinear`` or ``quadrants``.
        angle_threshold: orientation filter (rad), :data:`DEFAULT_ANGLE_THRESHOLD`.
        min_blocks: fewest kept blocks aligned, :data:`MIN_BLOCKS`.
    """

    loss: str = "huber"
    huber_px: float = DEFAULT_HUBER_PX
    bias: str = "translation"
    angle_threshold: float = DEFAULT_ANGLE_THRESHOLD
    min_blocks: int = MIN_BLOCKS


def align_blocks(camera: BrownConrady | ParametricCamera, pattern: StarPattern,
                 reference_points: np.ndarray | None,
                 feature_id: ArrayLike, centres: ArrayLike, block_loss: ArrayLike,
                 settings: AlignmentSettings | None = None) -> GlobalAlignment:
    """Align one frame's kept blocks to a calibrated camera (``eq:global_align``).

    Each block's star centre ``H(0, 0)`` is matched to its target point: the reference's refined
    point where it has one, the nominal ``(fx L, fy L, 0)`` otherwise. Blocks are weighted by
    ``1 / (loss + 1e-3)`` of their deconvolution loss (:func:`loss_weights`, supplement B) and
    placed on the normalised grid for the bias models (:func:`blurcalib.calib.bias.grid_coordinates`).

    Args:
        camera: the calibrated parametric camera.
        pattern: the target.
        reference_points: ``(F, 3)`` refined target points (m) per feature id, NaN where
            unknown, or None for the nominal points.
        feature_id: ``(N,)`` feature ids of the kept blocks.
        centres: ``(N, 2)`` their star centres (px, OpenCV convention), finite.
        block_loss: ``(N,)`` their deconvolution losses (grey levels^2).
        settings: loss, bias, orientation filter and the fewest blocks.

    Raises:
        AlignmentError: fewer than ``settings.min_blocks`` blocks, or a failed pose estimate.
    """
    s = settings or AlignmentSettings()
    ids = np.asarray(feature_id, dtype=np.int64).reshape(-1)
    if len(ids) < s.min_blocks:
        raise AlignmentError(f"{len(ids)} blocks kept by the filter, alignment needs {s.min_blocks}")
    nominal = pattern.points_3d(ids)
    points = nominal if reference_points is None else reference_points[ids]
    points = np.where(np.isfinite(points), points, nominal)
    try:
        return align_global(camera, points, centres, loss_weights(block_loss),
                            grid_coordinates(pattern, pattern.features[ids]), loss=s.loss,
                            huber_px=s.huber_px, bias=s.bias, angle_threshold=s.angle_threshold)
    except ValueError as exc:
        raise AlignmentError(f"global alignment failed: {exc}") from None


def align_kept_blocks(camera: BrownConrady | ParametricCamera, pattern: StarPattern,
                      reference_points: np.ndarray | None,
                      blocks: BlockTable, kept: np.ndarray, settings: AlignmentSettings | None = None
                      ) -> tuple[np.ndarray, GlobalAlignment]:
    """:func:`align_blocks` of a frame's blocks kept by the quality filter ``kept (B,)`` with
    finite star centres ``H(0, 0)`` (px, OpenCV convention), each weighted by its deconvolution
    loss: the one alignment of a blurry frame of the pipeline and the app.

    Returns:
        ``(N,)`` the indices of the aligned blocks into ``blocks``, and the alignment.

    Raises:
        AlignmentError: as :func:`align_blocks`.
    """
    centres = blocks.centre
    index = np.flatnonzero(np.asarray(kept, dtype=bool) & np.all(np.isfinite(centres), axis=1))
    return index, align_blocks(camera, pattern, reference_points, blocks.feature_id[index], centres[index],
                               blocks.loss[index], settings)
