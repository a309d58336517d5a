"""Bundle adjustment of the central generic camera (:mod:`blurcalib.camera.generic`) over many frames.

Problem. Observation ``i`` of frame ``f`` sees target point ``P_i`` (m, fixed: the parametric
calibration's refined points) at ``p_i`` px (OpenCV convention). With the pose
``M_f = [R_f | t_f]``, the generic projection ``pi_G`` and, for blurry frames, a per-frame image
translation ``s_f`` (the deconvolution's translational ambiguity, paper ``eq:global_align``)::

    r_i = p_i - pi_G(R_f P_i + t_f) - s_f

    min  sum_i w_i rho(|r_i|^2) + |s_f|^2 / sigma_s^2 + sum |D2 v - D2 v0|^2 / sigma_D^2

* ``rho``: Huber on the 2-D residual norm at ``huber_px`` (1 px, as the reference tool), solved
  by iteratively reweighted Gauss-Newton; ``w_i`` per-observation weights.
* ``sigma_s`` (``shift_sigma_px``): the shift's weak prior (frames whose shift is free only).
* ``D2``: second differences of the node directions along grid rows and columns; ``v0`` the
  initial grid. A weak smoothness prior (``smoothness_px``, converted to radians by the grid's
  angular pitch) that only matters where no observation pins a node: there the grid follows the
  initial (parametric) camera's shape instead of drifting. Cells without observations are
  reported in :attr:`BundleResult.warnings` by image region.

Solver: Levenberg-Marquardt (:func:`blurcalib.optim.lm.run_single`; Marquardt's ``lambda diag(H)``
damping, :data:`BUNDLE_DAMPING`; a step that raises the cost by less than ``tol`` of it ends the
iterations as converged: the projections are solved to 1e-8 px, which makes a converged cost
that uncertain). The normal equations are :mod:`blurcalib.calib.bundle_problem`'s. The per-frame
blocks (pose: rotation increment ``omega`` with ``R <- exp(omega) R`` and ``t <- t + dt``; plus
``s_f``) are eliminated by the Schur complement;
the reduced system on the ``2 GW GH`` grid parameters is dense (formed frame chunk by frame
chunk, :func:`reduce_frames`) and solved to float64 accuracy (on a CPU by a float32 Cholesky
factor refined in float64: :func:`blurcalib.calib.spd_solve.solve_lower`). Projections are
warm-started from the previous iteration's pixels; an observation whose ray leaves the
calibrated area gets weight 0 (a clamped projection carries no gradient).

Gauge. A central model's orientation is free (rotating every direction and every pose together
changes nothing). As the reference tool does, after every accepted step the grid is re-rotated
so that the image centre looks along +z and the centre of the right edge lies in the x-z plane
(x > 0), and the poses are rotated with it.

Rolling shutter (optional, :class:`RollingRows`). A moving frame read row by row is seen from
its pose moved by the motion over its row's instant (``docs/rolling-shutter.md``); with
``y_i`` the observation's row as a share of the readout, its camera point becomes::

    X_i = exp([y_i a_w + y_i^2 b_w]_x) (R_f P_i + t_f) + y_i a_v + y_i^2 b_v

with the frame's rolling parameters ``theta_f = (a_w rad, a_v m, b_w rad, b_v m)`` (12 values,
zero-mean Gaussian prior of ``twist_sigma`` rad and ``twist_sigma`` times the frame's distance
m). The per-frame blocks then hold ``omega, dt, s, theta`` (20 columns) and are eliminated by
the same Schur complement; without rolling rows they hold 8 columns and nothing changes.

Outliers: once, after ``outlier_iteration`` iterations (or at convergence if that comes first),
observations with an error above ``Q3 + 6 (Q3 - Q1)`` (quartiles of the error norms) are removed,
as the reference tool does.

The result keeps its observations (:class:`BundleData`), from which
:mod:`blurcalib.calib.normal_equations` rebuilds the Gauss-Newton blocks at the solution (the
projection uncertainty's information, the held-out validation's leave-out cameras).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, TypeVar

import numpy as np
import torch
from numpy.typing import ArrayLike

from blurcalib.calib.bundle_problem import BundleProblem, BundleState, normal_equations, robust_weights
from blurcalib.calib.coverage import cell_coverage, coverage_warnings
from blurcalib.calib.frame_block import RollingRows, checked_rolling_rows
from blurcalib.calib.spd_solve import solve_lower
from blurcalib.camera.generic import CentralGeneric, GridSpline, apply_update
from blurcalib.geometry.lie import exp_so3, orthonormal
from blurcalib.geometry.pose import Pose
from blurcalib.optim.lm import Damping, LmRule, SingleProblem, Stopping, run_single

__all__ = ["BUNDLE_DAMPING", "BundleData", "BundleResult", "BundleSettings", "adjust_with_outliers",
           "bundle_adjust", "gauge_rotation", "reduce_frames", "remove_outliers", "schur_step"]

log = logging.getLogger(__name__)

FRAME_CHUNK = 64
"""Frames whose Schur complement terms are formed by one matrix product (:func:`reduce_frames`)."""

ROW_BLOCK = 512
"""Rows of the reduced system per product when :func:`reduce_frames` forms its lower triangle
alone, block row by block row."""


@dataclass(frozen=True)
class BundleSettings:
    """Options of :func:`bundle_adjust`.

    Attributes:
        huber_px: Huber threshold on the residual norm (px).
        max_iterations: LM iterations at most.
        tol: stop when an accepted step lowers the cost by less than this fraction.
        outlier_iteration: iteration after which outliers are removed once (0: never).
        outlier_iqr: the rule's factor ``k`` in ``Q3 + k (Q3 - Q1)``.
        shift_sigma_px: prior standard deviation of a free per-frame shift (px).
        smoothness_px: prior standard deviation of the grid's second differences from the
            initial grid's, in px (via the grid's angular pitch).
        device: torch device.
    """

    huber_px: float = 1.0
    max_iterations: int = 40
    tol: float = 1e-7
    outlier_iteration: int = 3
    outlier_iqr: float = 6.0
    shift_sigma_px: float = 20.0
    smoothness_px: float = 1.0
    device: str = "cpu"


@dataclass(eq=False)
class BundleData:
    """The observations of a bundle adjustment, as its final iteration used them.

    Attributes:
        frame: ``(N,)`` frame index of each observation.
        points: ``(N, 3)`` target points (m).
        observed: ``(N, 2)`` observed positions (px, OpenCV convention).
        weights: ``(N,)`` observation weights, 0 for the removed outliers.
        shift_free: ``(F,)`` bool, frames with a free image shift.
        settings: the solver options (priors, Huber threshold, device).
        angular_pitch: radians per pixel of the grid, as the smoothness prior converted
            ``smoothness_px`` with it.
    """

    frame: np.ndarray = field(repr=False)
    points: np.ndarray = field(repr=False)
    observed: np.ndarray = field(repr=False)
    weights: np.ndarray = field(repr=False)
    shift_free: np.ndarray
    settings: BundleSettings
    angular_pitch: float


@dataclass(eq=False)
class BundleResult:
    """The adjusted generic camera, poses and per-frame shifts.

    Attributes:
        model: the generic camera (gauge: image centre along +z, right edge in the x-z plane).
        poses: ``(F,)`` poses (target -> camera) in the model's frame.
        shifts: ``(F, 2)`` px per-frame image shifts ``s_f`` (0 where not free).
        residuals: ``(N, 2)`` px ``p_i - pi_G(M_f P_i) - s_f``; NaN where the ray left the area.
        inlier: ``(N,)`` bool, used in the final fit (not an outlier, inside the area, w > 0).
        median_error, rms_error: over inliers (px).
        iterations: LM iterations run; cost: final objective.
        seconds, cpu_seconds: wall-clock and process CPU time.
        warnings: one line per image region with unobserved grid cells.
        coverage: ``(GH - 3, GW - 3)`` observation count per grid cell of the calibrated area.
        data: the observations and options (what
            :func:`blurcalib.calib.normal_equations.normal_equations` needs).
        theta: ``(F, 12)`` rolling parameters (0 for frames without), or None without rolling rows.
    """

    model: CentralGeneric
    poses: list[Pose]
    shifts: np.ndarray
    residuals: np.ndarray = field(repr=False)
    inlier: np.ndarray = field(repr=False)
    median_error: float
    rms_error: float
    iterations: int
    cost: float
    seconds: float
    cpu_seconds: float
    warnings: list[str]
    coverage: np.ndarray = field(repr=False)
    data: BundleData = field(repr=False)
    theta: np.ndarray | None = field(default=None, repr=False)


def reduce_frames(Hgg: torch.Tensor, Hgp: torch.Tensor, Hpp_inv: torch.Tensor, bg: torch.Tensor | None = None,
                  bp: torch.Tensor | None = None, lower: bool = False, overwrite: bool = False
                  ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The reduced camera system: the per-frame blocks eliminated by the Schur complement::

        S = Hgg - sum_f Hgp_f Hpp_f^-1 Hgp_f^T        (G, G)
        c = bg  - sum_f Hgp_f Hpp_f^-1 bp_f            (G,)

    from ``Hgg (G, G)``, ``Hgp (G, F, 8)``, ``Hpp_inv (F, 8, 8)`` and, optionally, ``bg (G,)``,
    ``bp (F, 8)`` (``c`` is None without them). With ``lower``, only the lower triangle of ``S``
    is formed (its upper triangle keeps ``Hgg``'s): all a Cholesky factorisation reads, at about
    half the products. A frame's rows of ``Hgp`` are zero outside the grid parameters its
    observations touch, which lie within one span of rows (the target's footprint); frames are
    sorted by that span and taken :data:`FRAME_CHUNK` at a time, each chunk's product restricted
    to the union of its spans. Memory: ``S`` and one chunk; with ``overwrite``, ``S`` is formed in
    ``Hgg``'s storage (``Hgg`` is lost).
    """
    G = Hgp.shape[0]
    S = Hgg if overwrite else Hgg.clone()
    c = None if bg is None else bg.clone()
    touched = (Hgp != 0).any(2)
    rows = torch.arange(G, device=Hgp.device)[:, None]
    first = torch.where(touched, rows, G).amin(0)
    last = torch.where(touched, rows, -1).amax(0)
    order = torch.argsort(first)
    order = order[first[order] < G]
    for chunk in order.split(FRAME_CHUNK):  # type: ignore[no-untyped-call]  # torch stubs: Tensor.split
        a, b = int(first[chunk].min()), int(last[chunk].max()) + 1
        H = Hgp[a:b, chunk]
        Y = torch.einsum("gfi,fij->gfj", H, Hpp_inv[chunk]).reshape(b - a, -1)
        H = H.reshape(b - a, -1)
        if lower:
            for i in range(a, b, ROW_BLOCK):
                j = min(i + ROW_BLOCK, b)
                S[i:j, a:j].addmm_(Y[i - a:j - a], H[:j - a].T, alpha=-1.0)
        else:
            S[a:b, a:b].addmm_(Y, H.T, alpha=-1.0)
        if c is not None and bp is not None:
            c[a:b].sub_(Y @ bp[chunk].reshape(-1))
    return S, c


SchurSystem = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]
"""The normal equations ``(Hgg, Hgp, Hpp, bg, bp)`` that :func:`schur_step` solves."""


def schur_step(Hgg: torch.Tensor, Hgp: torch.Tensor, Hpp: torch.Tensor, bg: torch.Tensor,
               bp: torch.Tensor, lam: float) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The damped step ``(dg (G,), dp (F, K))`` of the normal equations with global unknowns
    ``Hgg (G, G)``, per-item blocks ``Hpp (F, K, K)`` and their coupling ``Hgp (G, F, K)``
    (right-hand sides ``bg (G,)``, ``bp (F, K)``): Marquardt's ``lambda diag`` added, the items
    eliminated (:func:`reduce_frames`) and the reduced system solved
    (:func:`blurcalib.calib.spd_solve.solve_lower`). None if not positive definite."""
    eye = torch.eye(Hpp.shape[1], dtype=Hpp.dtype, device=Hpp.device)
    Hpp_d = Hpp + lam * torch.diag_embed(torch.diagonal(Hpp, dim1=1, dim2=2)) + 1e-12 * eye
    try:
        Lp = torch.linalg.cholesky(Hpp_d)
    except torch.linalg.LinAlgError:  # type: ignore[attr-defined]  # torch stubs: not re-exported
        return None
    Hpp_inv = torch.cholesky_inverse(Lp)
    S, rhs = reduce_frames(Hgg, Hgp, Hpp_inv, bg, bp, lower=True)
    diag = torch.diagonal(Hgg)
    S.diagonal().add_(lam * diag + 1e-12 * float(diag.mean()))
    assert rhs is not None  # bg given
    try:
        dg = solve_lower(S, rhs)
    except torch.linalg.LinAlgError:  # type: ignore[attr-defined]  # torch stubs: not re-exported
        return None
    dp = torch.einsum("fij,fj->fi", Hpp_inv, bp - torch.einsum("gfi,g->fi", Hgp, dg))
    return dg, dp


def gauge_rotation(spline: GridSpline, grid: torch.Tensor) -> torch.Tensor:
    """``Q (3, 3)``: maps the image centre's direction to +z and the right edge's into x-z (x > 0)."""
    lo, hi = spline.lo, spline.hi
    mid = 0.5 * (lo + hi)
    px = torch.stack([mid, torch.stack([hi[0], mid[1]])])
    d = spline.with_grid(grid).evaluate(px).d
    z = d[0]
    x = d[1] - (d[1] @ z) * z
    x = x / x.norm()
    y = torch.linalg.cross(z, x, dim=0)
    return torch.stack([x, y, z])


def _checked_inputs(F: int, frame: ArrayLike, points: ArrayLike, observed: ArrayLike,
                    weights: ArrayLike | None, shift_free: ArrayLike | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`bundle_adjust`'s observations as arrays ``frame (N,)``, ``points (N, 3)``,
    ``observed (N, 2)``, ``weights (N,)`` and ``shift_free (F,)``; ValueError names what is wrong."""
    fr_np = np.asarray(frame, dtype=np.int64).reshape(-1)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(observed, dtype=np.float64).reshape(-1, 2)
    n = len(fr_np)
    if P.shape[0] != n or p.shape[0] != n:
        raise ValueError(f"need frame (N,), points (N, 3), observed (N, 2); got {n}, {P.shape}, {p.shape}")
    if n == 0 or fr_np.min() < 0 or fr_np.max() >= F:
        raise ValueError(f"frame indices must lie in [0, {F})")
    counts = np.bincount(fr_np, minlength=F)
    if np.any(counts == 0):
        raise ValueError(f"frames without observations: {np.nonzero(counts == 0)[0].tolist()[:10]}")
    w_np = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w_np.shape != (n,) or np.any(w_np < 0) or not np.all(np.isfinite(w_np)):
        raise ValueError(f"weights must be finite, >= 0 and of shape ({n},)")
    free_np = np.zeros(F, bool) if shift_free is None else np.asarray(shift_free, bool).reshape(-1)
    if free_np.shape != (F,):
        raise ValueError(f"shift_free must have shape ({F},)")
    return fr_np, P, p, w_np, free_np


def remove_outliers(pb: BundleProblem, st: BundleState, r: torch.Tensor, use: torch.Tensor
                    ) -> tuple[torch.Tensor, float]:
    """Give the observations with an error above ``Q3 + k (Q3 - Q1)`` (over those in use) weight 0
    in ``pb``; the new use weights ``(N,)`` and cost."""
    e = r.norm(dim=-1)[use > 0]
    q1, q3 = torch.quantile(e, 0.25), torch.quantile(e, 0.75)
    thresh = float(q3 + pb.settings.outlier_iqr * (q3 - q1))
    outlier = r.norm(dim=-1) > thresh
    pb.weights = torch.where(outlier, 0.0, pb.weights)
    use = pb.weights * st.inside.to(torch.float64)
    log.info("outlier removal: %d observations above %.3f px", int(outlier.sum()), thresh)
    return use, pb.cost(st, torch.where(st.inside[:, None], r, 0.0), use)


def _regauged(spline: GridSpline, st: BundleState) -> BundleState:
    """``st`` rotated into the gauge (module docstring): grid, initial grid, poses and rolling
    parameters by the rotation :func:`gauge_rotation` gives for its grid."""
    Q = gauge_rotation(spline, st.grid)
    theta = None if st.theta is None else (st.theta.reshape(-1, 4, 3) @ Q.T).reshape(-1, 12)
    return BundleState(st.grid @ Q.T, st.grid0 @ Q.T, Q @ st.R, st.t @ Q.T, st.s, st.u, st.inside, theta)


BUNDLE_DAMPING = Damping(start=1e-6, shrink=5.0, grow=4.0, floor=1e-12, ceiling=1e8)
"""Marquardt's ``lambda`` of :func:`bundle_adjust`: 1e-6, /5 (not below 1e-12) after an accepted
step, x4 after a rejected one; no step above 1e8."""


@dataclass
class _Iterate:
    """An iterate of :func:`bundle_adjust`: the unknowns, the residuals ``r (N, 2)`` px and the use
    weights ``(N,)`` (the observations' weights, 0 outside the calibrated area)."""

    st: BundleState
    r: torch.Tensor
    use: torch.Tensor


class _Steps(SingleProblem[_Iterate, SchurSystem, tuple[torch.Tensor, torch.Tensor]]):
    """The Levenberg-Marquardt steps of :func:`bundle_adjust`: Huber-weighted normal equations,
    the per-frame blocks eliminated (:func:`schur_step`), the grid re-gauged after each accepted step."""

    def __init__(self, pb: BundleProblem, spline: GridSpline) -> None:
        self.pb, self.spline = pb, spline

    def linearise(self, x: _Iterate) -> SchurSystem:
        w = x.use * robust_weights(x.r, self.pb.settings.huber_px)
        return normal_equations(self.pb, x.st, w, x.r)[:5]

    def solve(self, system: SchurSystem, lam: float) -> tuple[torch.Tensor, torch.Tensor] | None:
        return schur_step(*system, lam)

    def trial(self, x: _Iterate, step: tuple[torch.Tensor, torch.Tensor]) -> tuple[_Iterate, float]:
        pb, st = self.pb, x.st
        dg, dp = step
        grid_n = apply_update(st.grid, dg.reshape(pb.gh, pb.gw, 2))
        R_n = exp_so3(dp[:, :3]) @ st.R
        t_n = st.t + dp[:, 3:6]
        s_n = st.s + dp[:, 6:8]
        theta_n = None if st.theta is None else st.theta + dp[:, 8:]
        u_n, in_n, r_n = pb.project(grid_n, R_n, t_n, s_n, st.u, theta_n)
        use_n = pb.weights * in_n.to(torch.float64)
        trial = BundleState(grid_n, st.grid0, R_n, t_n, s_n, u_n, in_n, theta_n)
        return _Iterate(trial, r_n, use_n), pb.cost(trial, torch.where(in_n[:, None], r_n, 0.0), use_n)

    def accept(self, x: _Iterate, moved: _Iterate, step: tuple[torch.Tensor, torch.Tensor], cost: float
               ) -> tuple[_Iterate, float, bool]:
        return _Iterate(_regauged(self.spline, moved.st), moved.r, moved.use), cost, False


X = TypeVar("X")


def adjust_with_outliers(steps: SingleProblem[X, Any, Any], x: X, cost: float, settings: BundleSettings,
                         remove: Callable[[X], tuple[X, float]]) -> tuple[X, float, int]:
    """Levenberg-Marquardt from ``x`` of cost ``cost`` (:data:`BUNDLE_DAMPING`), the outliers
    removed once (``remove``: the iterate with them weighted 0 and its cost) after
    :attr:`BundleSettings.outlier_iteration` iterations or at convergence if that comes first, and
    the fit continued (the damping carried on). Converged when a step changes the cost by at most
    ``tol`` of it, up or down, or no damping up to the ceiling lowers it. Returns the iterate, its
    cost and the iterations (linearisations)."""
    s = settings

    def rule(iterations: int) -> LmRule:
        return LmRule(BUNDLE_DAMPING, Stopping(max_iterations=iterations, rtol=s.tol, rtol_rejected=True))

    first = run_single(steps, x, cost, rule(min(s.outlier_iteration, s.max_iterations) if s.outlier_iteration
                                            else s.max_iterations))
    x, cost, iterations = first.x, first.cost, first.iterations
    if s.outlier_iteration and iterations < s.max_iterations:
        x, cost = remove(x)
        second = run_single(steps, x, cost, rule(s.max_iterations - iterations), first.lam)
        x, cost = second.x, second.cost
        iterations += max(second.iterations, 1)  # the iteration that removed them counts
    return x, cost, iterations


def _adjust(pb: BundleProblem, spline: GridSpline, x: _Iterate, cost: float) -> tuple[_Iterate, float, int]:
    """:func:`adjust_with_outliers` of :func:`bundle_adjust`'s steps (:class:`_Steps`)."""

    def remove(it: _Iterate) -> tuple[_Iterate, float]:
        use, removed_cost = remove_outliers(pb, it.st, it.r, it.use)
        return replace(it, use=use), removed_cost

    return adjust_with_outliers(_Steps(pb, spline), x, cost, pb.settings, remove)


def bundle_adjust(model: CentralGeneric, poses: Sequence[Pose], frame: ArrayLike, points: ArrayLike,
                  observed: ArrayLike, weights: ArrayLike | None = None,
                  shift_free: ArrayLike | None = None, settings: BundleSettings | None = None,
                  prior: CentralGeneric | None = None,
                  rolling: RollingRows | None = None) -> BundleResult:
    """Fit the generic camera's grid, every frame's pose and the free per-frame shifts.

    Args:
        model: initial generic camera (e.g. :func:`blurcalib.camera.generic.fit_to_rays` of the
            parametric calibration); its calibrated area and grid size are kept.
        poses: ``(F,)`` initial poses (target -> camera) in ``model``'s camera frame.
        frame: ``(N,)`` frame index of each observation.
        points: ``(N, 3)`` target points (m).
        observed: ``(N, 2)`` observed positions (px, OpenCV convention).
        weights: ``(N,)`` observation weights ``>= 0`` (default 1).
        shift_free: ``(F,)`` bool, frames with a free image shift ``s_f`` (blurry frames).
        settings: solver options.
        prior: the camera whose shape the smoothness prior keeps (its grid's second
            differences; same grid as ``model``, each in its own gauge). Default ``model``: a
            warm start from another fit's camera passes the initial camera of a cold start here,
            so that cells without observations follow it and not the warm start.
        rolling: the rows and the moving frames of the rolling-shutter geometry (module
            docstring); None: the global shutter.

    Raises:
        ValueError: inconsistent shapes or a frame without observations.
    """
    settings = settings or BundleSettings()
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    dev = torch.device(settings.device)
    kw: dict[str, Any] = {"dtype": torch.float64, "device": dev}
    fr_np, P, p, w_np, free_np = _checked_inputs(len(poses), frame, points, observed, weights, shift_free)
    spline = model.spline(dev)
    pb = BundleProblem(spline, torch.as_tensor(fr_np, device=dev), torch.as_tensor(P, **kw),
                       torch.as_tensor(p, **kw), torch.as_tensor(w_np, **kw),
                       torch.as_tensor(free_np, device=dev), settings,
                       checked_rolling_rows(rolling, len(P), len(poses)))
    x, cost, iterations = _adjust(pb, spline, *_start(pb, spline, poses, prior, rolling is not None))
    st = x.st
    inlier = (pb.weights > 0) & st.inside
    e = x.r.norm(dim=-1)[inlier]
    out_model = model.with_grid(st.grid.cpu().numpy())
    coverage = cell_coverage(out_model, st.u[inlier].cpu().numpy())
    warnings = coverage_warnings(out_model, coverage)
    for line in warnings:
        log.info(line)
    Rn, tn = st.R.cpu().numpy(), st.t.cpu().numpy()
    return BundleResult(
        model=out_model,
        poses=[Pose(orthonormal(Rn[f]), tn[f]) for f in range(len(poses))],
        shifts=st.s.cpu().numpy(), residuals=torch.where(st.inside[:, None], x.r, torch.nan).cpu().numpy(),
        inlier=inlier.cpu().numpy(),
        median_error=float(torch.median(e)) if len(e) else math.nan,
        rms_error=float(torch.sqrt(torch.mean(e * e))) if len(e) else math.nan,
        iterations=iterations, cost=cost, seconds=time.perf_counter() - t_wall,
        cpu_seconds=time.process_time() - t_cpu, warnings=warnings, coverage=coverage,
        data=BundleData(fr_np, P, p, pb.weights.cpu().numpy(), free_np, settings, pb.pitch),
        theta=None if st.theta is None else st.theta.cpu().numpy())


def _start(pb: BundleProblem, spline: GridSpline, poses: Sequence[Pose], prior: CentralGeneric | None,
           rolling: bool) -> tuple[_Iterate, float]:
    """The first iterate of :func:`bundle_adjust` in the gauge (module docstring): the model's grid,
    the initial grid the smoothness prior keeps (``prior``'s, else the model's), the poses, zero
    shifts and (``rolling``) zero rolling parameters; and its cost."""
    kw: dict[str, Any] = {"dtype": torch.float64, "device": spline.grid.device}
    Q = gauge_rotation(spline, spline.grid)
    grid = spline.grid @ Q.T
    grid0 = grid.clone()
    if prior is not None:
        if (prior.grid_height, prior.grid_width) != spline.shape:
            raise ValueError(f"prior grid {prior.grid_height}x{prior.grid_width} differs from the model's "
                             f"{spline.shape[0]}x{spline.shape[1]}")
        prior_grid = prior.spline(spline.grid.device).grid
        grid0 = prior_grid @ gauge_rotation(spline, prior_grid).T
    R = Q @ torch.as_tensor(np.stack([q.R for q in poses]), **kw)
    t = torch.as_tensor(np.stack([q.t for q in poses]), **kw) @ Q.T
    s = torch.zeros(len(poses), 2, **kw)
    theta = None
    if rolling:
        theta = torch.zeros(len(poses), 12, **kw)
        pb.set_distance(t)
    u, inside, r = pb.project(grid, R, t, s, None, theta)
    st = BundleState(grid, grid0, R, t, s, u, inside, theta)
    use = pb.weights * inside.to(torch.float64)
    return _Iterate(st, r, use), pb.cost(st, torch.where(inside[:, None], r, 0.0), use)
