"""Bundle adjustment of a rig's extrinsics: several calibrated cameras, one target pose per image set.

Problem. Camera ``c`` (a calibrated central generic camera, held fixed) sees, in image set ``s``,
target point ``P_i`` (m) at ``p_i`` px (OpenCV convention). With the set's target -> rig pose
``M_s = [R_s | t_s]`` (``rig_tr_global``), the camera's rig -> camera pose ``T_c = [R_c | t_c]``
(``camera_tr_rig``, :mod:`blurcalib.camera.rig`), the camera's projection ``pi_c`` and, for a
blurry frame, its own image shift ``s_cs`` (each camera's frame of a set blurs differently)::

    r_i = p_i - pi_c(R_c (R_s P_i + t_s) + t_c) - s_cs

    min  sum_i w_i rho(|r_i|^2) + sum_{c, s free} |s_cs|^2 / sigma_s^2

with Huber's ``rho`` (``huber_px``) by iteratively reweighted Gauss-Newton, as
:func:`blurcalib.calib.bundle.bundle_adjust`. Gauge: the rig's frame is camera 0's (``T_0`` the
identity, not an unknown); a sharp frame's shift is 0, so a set with one sharp frame is anchored.

Solver: Levenberg-Marquardt (:func:`blurcalib.calib.bundle.adjust_with_outliers`, the outliers
removed once by the same ``Q3 + k (Q3 - Q1)`` rule per camera). The global unknowns are the
extrinsics of cameras ``1 .. C-1`` (rotation increment ``omega`` with ``R_c <- exp(omega) R_c``
and ``t_c <- t_c + dt``: 6 each); the per-set blocks ``(S, 6 + 2 C)`` hold the set's pose
increment (same convention) and the ``C`` shifts, and are eliminated by the Schur complement
(:func:`blurcalib.calib.bundle.schur_step`). A shift that is not free (a sharp frame, or a camera
that does not see the set) is decoupled (identity block, zero gradient).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from blurcalib.calib.bundle import BundleSettings, SchurSystem, adjust_with_outliers, schur_step
from blurcalib.camera.generic import CentralGeneric, GridSpline, param_columns, projection_jacobians
from blurcalib.camera.rig import Rig
from blurcalib.geometry.lie import exp_so3, orthonormal, skew
from blurcalib.geometry.pose import Pose
from blurcalib.optim.lm import SingleProblem

__all__ = ["RigBundleResult", "RigObservations", "camera_sensitivity", "rig_bundle_adjust"]


@dataclass(frozen=True, eq=False)
class RigObservations:
    """One camera's observations in a rig.

    Attributes:
        set_index: ``(N,)`` image set of each observation (``0 .. S-1``).
        points: ``(N, 3)`` target points (m).
        observed: ``(N, 2)`` observed positions (px, OpenCV convention).
        weights: ``(N,)`` observation weights ``>= 0``.
        shift_free: ``(S,)`` bool, the sets whose frame of this camera has a free image shift
            (blurry frames).
    """

    set_index: np.ndarray = field(repr=False)
    points: np.ndarray = field(repr=False)
    observed: np.ndarray = field(repr=False)
    weights: np.ndarray = field(repr=False)
    shift_free: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        n = len(np.asarray(self.set_index).reshape(-1))
        shapes = (np.shape(self.points), np.shape(self.observed), np.shape(self.weights))
        if shapes != ((n, 3), (n, 2), (n,)):
            raise ValueError(f"need set_index (N,), points (N, 3), observed (N, 2), weights (N,); got "
                             f"{n} and {shapes}")


@dataclass(eq=False)
class RigBundleResult:
    """The adjusted rig.

    Attributes:
        rig: the cameras (as given) and their rig -> camera poses, the rig's frame camera 0's.
        rig_tr_global: ``(S,)`` target -> rig pose of each image set.
        shifts: ``(C, S, 2)`` px image shift of each camera's frame of each set (0 where not free).
        residuals: per camera ``(N_c, 2)`` px ``p - pi_c(...) - s``; NaN where the ray left the area.
        inlier: per camera ``(N_c,)`` bool, used in the final fit.
        median_error, rms_error: ``(C,)`` px over each camera's inliers.
        iterations: LM iterations run; cost: final objective (px^2).
        cpu_seconds: process CPU time.
        covariance: ``(6 (C-1), 6 (C-1))`` the covariance of the extrinsics of cameras ``1 .. C-1``
            (per camera the rotation increment ``omega`` (rad, ``R_c <- exp(omega) R_c``) then
            ``dt`` (m)): ``sigma^2 H^-1`` with ``H`` the normal equations' matrix at the solution,
            the sets' blocks eliminated (Schur complement), and ``sigma^2`` the residual variance
            ``sum w |r|^2 / (2 N - unknowns)`` over the inliers; NaN if singular. The cameras are
            held fixed, so their own errors are not in it.
    """

    rig: Rig
    rig_tr_global: list[Pose]
    shifts: np.ndarray
    residuals: list[np.ndarray] = field(repr=False)
    inlier: list[np.ndarray] = field(repr=False)
    median_error: np.ndarray
    rms_error: np.ndarray
    iterations: int
    cost: float
    cpu_seconds: float
    covariance: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 0)))


@dataclass
class _Cam:
    """One camera's fixed data (torch float64)."""

    spline: GridSpline
    sets: torch.Tensor  # (N,)
    points: torch.Tensor  # (N, 3)
    observed: torch.Tensor  # (N, 2)
    weights: torch.Tensor  # (N,) observation weights, 0 for removed outliers
    free: torch.Tensor  # (S,) bool


@dataclass
class _State:
    """An iterate: extrinsics ``Rc (C, 3, 3)``, ``tc (C, 3)``; set poses ``Rs (S, 3, 3)``, ``ts (S, 3)``;
    shifts ``s (C, S, 2)``; per camera projections, inside flags and residuals."""

    Rc: torch.Tensor
    tc: torch.Tensor
    Rs: torch.Tensor
    ts: torch.Tensor
    s: torch.Tensor
    u: list[torch.Tensor]
    inside: list[torch.Tensor]
    r: list[torch.Tensor]


class _RigSteps(SingleProblem[_State, SchurSystem, tuple[torch.Tensor, torch.Tensor]]):
    """The Levenberg-Marquardt steps of :func:`rig_bundle_adjust` (module docstring)."""

    def __init__(self, cams: list[_Cam], settings: BundleSettings) -> None:
        self.cams, self.settings = cams, settings
        self.C = len(cams)
        self.S = len(cams[0].free)
        self.K = 6 + 2 * self.C
        self.shift_w = 1.0 / settings.shift_sigma_px ** 2

    def camera_points(self, st: _State, c: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Camera ``c``'s ``X (N, 3)``, rig points ``Y (N, 3)`` and ``R_s P (N, 3)``."""
        cam = self.cams[c]
        RP = torch.einsum("nij,nj->ni", st.Rs[cam.sets], cam.points)
        Y = RP + st.ts[cam.sets]
        return Y @ st.Rc[c].T + st.tc[c], Y, RP

    def project(self, st: _State) -> _State:
        """``st`` with its projections, inside flags and residuals (warm-started from its ``u``)."""
        us, ins, rs = [], [], []
        for c, cam in enumerate(self.cams):
            X = self.camera_points(st, c)[0]
            u, inside = cam.spline.project(X, st.u[c] if st.u else None)
            us.append(u)
            ins.append(inside & (X[:, 2] > 0))
            rs.append(cam.observed - u - st.s[c, cam.sets])
        return _State(st.Rc, st.tc, st.Rs, st.ts, st.s, us, ins, rs)

    def use(self, st: _State, c: int) -> torch.Tensor:
        return self.cams[c].weights * st.inside[c].to(torch.float64)

    def cost(self, st: _State) -> float:
        d = self.settings.huber_px
        total = torch.zeros((), dtype=torch.float64)
        for c, cam in enumerate(self.cams):
            e = torch.where(st.inside[c], st.r[c].norm(dim=-1), 0.0)
            rho = torch.where(e <= d, e * e, 2 * d * e - d * d)
            free = cam.free.to(torch.float64)[:, None]
            total = total + (self.use(st, c) * rho).sum() + self.shift_w * (free * st.s[c] ** 2).sum()
        return float(total)

    def jacobians(self, x: _State, c: int) -> tuple[torch.Tensor, ...] | None:
        """Camera ``c``'s observations in use at ``x``: their IRLS weights ``w (n,)``, sets ``(n,)``,
        residuals ``(n, 2)``, the prediction's derivatives by the set's block ``J_set (n, 2, K)``
        and by the camera's extrinsics ``J_c (n, 2, 6)`` (``omega``, ``dt``), the projection's by
        the camera's grid ``(n, 2, 32)`` and its parameter columns ``(n, 32)``
        (:func:`blurcalib.camera.generic.projection_jacobians`); None when none is in use."""
        cam = self.cams[c]
        e = x.r[c].norm(dim=-1)
        w = self.use(x, c) * torch.where(e <= self.settings.huber_px, 1.0,
                                         self.settings.huber_px / e.clamp_min(1e-300))
        keep = w > 0
        if not bool(keep.any()):
            return None
        X, _, RP = (v[keep] for v in self.camera_points(x, c))
        J_p, J_grid, nodes = projection_jacobians(cam.spline, x.u[c][keep], X)
        J_pR = J_p @ x.Rc[c]
        J_set = torch.zeros(len(X), 2, self.K, dtype=torch.float64)
        J_set[:, :, 0:3] = -J_pR @ skew(RP)
        J_set[:, :, 3:6] = J_pR
        J_set[:, :, 6 + 2 * c:8 + 2 * c] = torch.eye(2, dtype=torch.float64)
        J_c = torch.cat([-J_p @ skew(X - x.tc[c]), J_p], dim=2)
        return w[keep], cam.sets[keep], x.r[c][keep], J_set, J_c, J_grid, param_columns(nodes)

    def linearise(self, x: _State) -> SchurSystem:
        C, S, K = self.C, self.S, self.K
        G = 6 * (C - 1)
        kw: dict[str, Any] = {"dtype": torch.float64}
        Hgg, bg = torch.zeros(G, G, **kw), torch.zeros(G, **kw)
        Hgp, Hpp, bp = torch.zeros(G, S, K, **kw), torch.zeros(S, K, K, **kw), torch.zeros(S, K, **kw)
        eye2 = torch.eye(2, **kw)
        for c in range(C):
            rows = self.jacobians(x, c)
            if rows is None:
                continue
            w, sets, r, J_set, J_c = rows[:5]
            wJs = w[:, None, None] * J_set
            Hpp.index_add_(0, sets, wJs.transpose(1, 2) @ J_set)
            bp.index_add_(0, sets, (wJs.transpose(1, 2) @ r[:, :, None])[..., 0])
            if c == 0:
                continue
            wJc = w[:, None, None] * J_c
            g = slice(6 * (c - 1), 6 * c)
            Hgg[g, g] += (wJc.transpose(1, 2) @ J_c).sum(0)
            bg[g] += (wJc.transpose(1, 2) @ r[:, :, None])[..., 0].sum(0)
            per_set = torch.zeros(S, 6, K, **kw).index_add_(0, sets, wJc.transpose(1, 2) @ J_set)
            Hgp[g] += per_set.permute(1, 0, 2)
        for c, cam in enumerate(self.cams):
            cols = slice(6 + 2 * c, 8 + 2 * c)
            free, fixed = cam.free, ~cam.free
            Hpp[free, cols, cols] += self.shift_w * eye2
            bp[free, cols] -= self.shift_w * x.s[c, free]
            Hpp[fixed, cols, :] = 0.0
            Hpp[fixed, :, cols] = 0.0
            Hpp[fixed, cols, cols] = eye2
            bp[fixed, cols] = 0.0
            Hgp[:, fixed, cols] = 0.0
        return Hgg, Hgp, Hpp, bg, bp

    def solve(self, system: SchurSystem, lam: float) -> tuple[torch.Tensor, torch.Tensor] | None:
        return schur_step(*system, lam)

    def trial(self, x: _State, step: tuple[torch.Tensor, torch.Tensor]) -> tuple[_State, float]:
        dg, dp = step
        dc = torch.cat([torch.zeros(6, dtype=dg.dtype), dg]).reshape(self.C, 6)
        Rc = exp_so3(dc[:, :3]) @ x.Rc
        tc = x.tc + dc[:, 3:]
        Rs = exp_so3(dp[:, :3]) @ x.Rs
        ts = x.ts + dp[:, 3:6]
        s = x.s + dp[:, 6:].reshape(self.S, self.C, 2).transpose(0, 1)
        moved = self.project(_State(Rc, tc, Rs, ts, s, x.u, x.inside, x.r))
        return moved, self.cost(moved)

    def covariance(self, x: _State) -> np.ndarray:
        """The extrinsics' covariance at ``x`` (:class:`RigBundleResult`)."""
        Hgg, Hgp, Hpp, _, _ = self.linearise(x)
        G = Hgg.shape[0]
        total, count = 0.0, 0
        for c, cam in enumerate(self.cams):
            keep = (cam.weights > 0) & x.inside[c]
            total += float((cam.weights[keep] * (x.r[c][keep] ** 2).sum(-1)).sum())
            count += 2 * int(keep.sum())
        unknowns = G + 6 * self.S + 2 * sum(int(cam.free.sum()) for cam in self.cams)
        try:
            reduced = Hgg - torch.einsum("gfi,fij,hfj->gh", Hgp, torch.linalg.inv(Hpp), Hgp)
            cov = torch.linalg.inv(0.5 * (reduced + reduced.T)) * total / max(count - unknowns, 1)
        except RuntimeError:  # torch.linalg.LinAlgError: a singular reduced system
            return np.full((G, G), math.nan)
        return np.asarray(cov.numpy(), dtype=np.float64)

    def sensitivity(self, x: _State) -> list[torch.Tensor]:
        """``dE/dtheta_c (6 (C-1), G_c)`` per camera at ``x`` (:func:`camera_sensitivity`)."""
        Hgg, Hgp, Hpp, _, _ = self.linearise(x)
        GE = Hgg.shape[0]
        M = torch.einsum("gsk,skl->sgl", Hgp, torch.linalg.inv(Hpp))  # (S, GE, K): H_Es H_ss^-1
        reduced = Hgg - torch.einsum("sgk,hsk->gh", M, Hgp)
        out = []
        for c, cam in enumerate(self.cams):
            coupling = torch.zeros(GE, 2 * cam.spline.grid[..., 0].numel(), dtype=torch.float64)
            rows = self.jacobians(x, c)
            if rows is not None:
                w, sets, _, J_set, J_c, J_grid, cols = rows
                J_E = torch.zeros(len(w), 2, GE, dtype=torch.float64)
                if c > 0:
                    J_E[:, :, 6 * (c - 1):6 * c] = J_c
                J_hat = J_E - J_set @ M[sets].transpose(1, 2)  # (n, 2, GE): the sets eliminated
                blocks = (w[:, None, None] * J_hat).transpose(1, 2) @ J_grid  # (n, GE, 32)
                coupling.index_add_(1, cols.reshape(-1), blocks.permute(1, 0, 2).reshape(GE, -1))
            out.append(-torch.linalg.solve(0.5 * (reduced + reduced.T), coupling))
        return out

    def remove_outliers(self, x: _State) -> tuple[_State, float]:
        """Weight 0 for each camera's observations above ``Q3 + k (Q3 - Q1)`` of its errors in use."""
        for c, cam in enumerate(self.cams):
            e = x.r[c].norm(dim=-1)
            used = e[self.use(x, c) > 0]
            if len(used) < 4:
                continue
            q1, q3 = torch.quantile(used, 0.25), torch.quantile(used, 0.75)
            cam.weights = torch.where(e > q3 + self.settings.outlier_iqr * (q3 - q1), 0.0, cam.weights)
        return x, self.cost(x)


def _checked(models: Sequence[CentralGeneric], observations: Sequence[RigObservations], S: int) -> None:
    if len(models) < 2 or len(models) != len(observations):
        raise ValueError(f"a rig bundle needs two or more cameras and one observation set per camera, got "
                         f"{len(models)} cameras and {len(observations)} observation sets")
    for c, obs in enumerate(observations):
        sets = np.asarray(obs.set_index).reshape(-1)
        if len(sets) and (sets.min() < 0 or sets.max() >= S):
            raise ValueError(f"camera {c}: set indices must lie in [0, {S})")
        if np.shape(obs.shift_free) != (S,):
            raise ValueError(f"camera {c}: shift_free must have shape ({S},)")
        w = np.asarray(obs.weights, dtype=np.float64)
        if np.any(w < 0) or not np.all(np.isfinite(w)):
            raise ValueError(f"camera {c}: weights must be finite and >= 0")


def _cams(models: Sequence[CentralGeneric], observations: Sequence[RigObservations],
          inliers: Sequence[np.ndarray] | None = None) -> list[_Cam]:
    """Each camera's fixed data; ``inliers``: per camera the observations kept (the others weigh 0)."""
    kw: dict[str, Any] = {"dtype": torch.float64}
    keep = [None] * len(models) if inliers is None else inliers
    return [_Cam(m.spline(), torch.as_tensor(np.asarray(o.set_index, dtype=np.int64)),
                 torch.as_tensor(np.asarray(o.points), **kw), torch.as_tensor(np.asarray(o.observed), **kw),
                 torch.as_tensor(np.asarray(o.weights) if k is None else np.asarray(o.weights) * k, **kw),
                 torch.as_tensor(np.asarray(o.shift_free, bool)))
            for m, o, k in zip(models, observations, keep, strict=True)]


def rig_bundle_adjust(models: Sequence[CentralGeneric], camera_tr_rig: Sequence[Pose],
                      rig_tr_global: Sequence[Pose], observations: Sequence[RigObservations],
                      settings: BundleSettings | None = None) -> RigBundleResult:
    """Fit the rig's extrinsics, every image set's target pose and the free shifts (module docstring).

    Args:
        models: ``(C,)`` the calibrated cameras, held fixed.
        camera_tr_rig: ``(C,)`` initial rig -> camera poses in the models' frames (camera 0's is
            taken as the rig's frame: the others are made relative to it).
        rig_tr_global: ``(S,)`` initial target -> rig poses.
        observations: ``(C,)`` each camera's observations.
        settings: the solver's options (Huber threshold, iterations, tolerance, outlier rule,
            shift prior); ``smoothness_px`` is unused (the cameras are fixed).

    Raises:
        ValueError: fewer than two cameras, inconsistent shapes, or an image set no camera sees.
    """
    settings = settings or BundleSettings()
    t_cpu = time.process_time()
    S, C = len(rig_tr_global), len(models)
    _checked(models, observations, S)
    if len(camera_tr_rig) != C:
        raise ValueError(f"need {C} camera poses, got {len(camera_tr_rig)}")
    seen = np.zeros(S, dtype=bool)
    for obs in observations:
        seen[np.asarray(obs.set_index, dtype=np.int64)] = True
    if not seen.all():
        raise ValueError(f"image sets without observations: {np.nonzero(~seen)[0].tolist()[:10]}")
    kw: dict[str, Any] = {"dtype": torch.float64}
    base = camera_tr_rig[0]
    rel = [p.compose(base.inverse()) for p in camera_tr_rig]
    cams = _cams(models, observations)
    steps = _RigSteps(cams, settings)
    poses = [base.compose(p) for p in rig_tr_global]
    def stacked(values: list[np.ndarray]) -> torch.Tensor:
        return torch.as_tensor(np.stack(values), **kw)

    start = steps.project(_State(stacked([p.R for p in rel]), stacked([p.t for p in rel]),
                                 stacked([p.R for p in poses]), stacked([p.t for p in poses]),
                                 torch.zeros(C, S, 2, **kw), [], [], []))
    x, cost, iterations = adjust_with_outliers(steps, start, steps.cost(start), settings,
                                               steps.remove_outliers)
    residuals, inliers, med, rms = [], [], np.full(C, math.nan), np.full(C, math.nan)
    for c, cam in enumerate(cams):
        inlier = (cam.weights > 0) & x.inside[c]
        residuals.append(torch.where(x.inside[c][:, None], x.r[c], torch.nan).numpy())
        inliers.append(inlier.numpy())
        e = x.r[c].norm(dim=-1)[inlier]
        if len(e):
            med[c], rms[c] = float(torch.median(e)), float(torch.sqrt(torch.mean(e * e)))
    Rc, tc, Rs, ts = (v.numpy() for v in (x.Rc, x.tc, x.Rs, x.ts))
    rig = Rig(tuple(models), tuple(Pose(orthonormal(Rc[c]), tc[c]) for c in range(C)))
    covariance = steps.covariance(x)
    return RigBundleResult(rig, [Pose(orthonormal(Rs[k]), ts[k]) for k in range(S)], x.s.numpy(), residuals,
                           inliers, med, rms, iterations, cost, time.process_time() - t_cpu, covariance)


def camera_sensitivity(result: RigBundleResult, observations: Sequence[RigObservations],
                       settings: BundleSettings | None = None) -> list[np.ndarray]:
    """How the adjusted extrinsics move with each camera's own calibration: per camera ``c``
    ``dE/dtheta_c (6 (C-1), G_c)``, ``E`` the extrinsics of cameras ``1 .. C-1`` as in
    :attr:`RigBundleResult.covariance` and ``theta_c`` the ``G_c`` tangent parameters of camera
    ``c``'s grid (:func:`blurcalib.camera.generic.projection_jacobians`' columns).

    At the solution the gradient vanishes; a change ``dtheta`` of a camera moves the prediction
    by ``J_theta dtheta`` and the solution by (implicit-function theorem, Gauss-Newton blocks at
    ``result``'s inliers and Huber weights, the sets' blocks eliminated by the Schur complement)::

        dE/dtheta_c = -H_EE'^-1 H_Etheta_c',   H_EE' = H_EE - H_EP H_PP^-1 H_PE,
        H_Etheta_c' = sum_i (J_E,i - J_P,i H_PP^-1 H_PE)^T w_i J_theta,i

    ``observations``: those ``result`` was adjusted on (:func:`rig_bundle_adjust`'s); ``settings``
    its Huber threshold and shift prior.
    """
    settings = settings or BundleSettings()
    models = result.rig.cameras
    S = len(result.rig_tr_global)
    _checked(models, observations, S)
    steps = _RigSteps(_cams(models, observations, result.inlier), settings)
    kw: dict[str, Any] = {"dtype": torch.float64}
    poses = result.rig.camera_tr_rig
    x = steps.project(_State(torch.as_tensor(np.stack([p.R for p in poses]), **kw),
                             torch.as_tensor(np.stack([p.t for p in poses]), **kw),
                             torch.as_tensor(np.stack([p.R for p in result.rig_tr_global]), **kw),
                             torch.as_tensor(np.stack([p.t for p in result.rig_tr_global]), **kw),
                             torch.as_tensor(result.shifts, **kw), [], [], []))
    return [np.asarray(d.numpy(), dtype=np.float64) for d in steps.sensitivity(x)]
