"""Held-out validation of the calibrated cameras: k-fold over frames (``docs/validation.md``).

Training reprojection errors fall with the number of parameters whatever the truth is; the
error on frames a camera has not seen does not. The frames of the generic fit (sharp and
blurry) are dealt into ``K`` folds; for each fold ``k``:

* the cameras are fitted again without fold ``k``: the parametric camera
  (:func:`blurcalib.calib.sharp.calibrate_sharp` on the other sharp frames, the target points held
  nominal: the points every camera is scored with), the generic camera of
  sharp and blurry frames and, when blurry frames were given, the generic camera of the sharp
  frames alone. A generic camera without fold ``k`` is one damped Gauss-Newton step from the
  full fit: the full fit's reduced camera system minus fold ``k``'s own terms
  (:func:`blurcalib.calib.normal_equations.leave_out_models`: one pass over the observations for all folds,
  then one ``(G, G)`` solve per fold); its smoothness prior keeps the shape of fold ``k``'s
  parametric camera, so no grid cell is held to a shape that fold ``k``'s frames shaped. When
  the other sharp frames are too few for a parametric camera, the fold has no parametric score
  and the generic cameras' prior keeps the full parametric camera's shape;
* every frame of fold ``k`` is scored against those cameras: its pose ``M_f`` (and, for a
  blurry frame, its image shift ``s_f``, the deconvolution's translational ambiguity, with the
  same weak prior as in the bundle adjustment) is fitted alone with the camera held
  (:func:`fit_frames`), and its residuals ``r_i = p_i - pi(M_f P_i) - s_f`` (px) are pooled.

No frame is scored by a camera that saw it. A blurry frame's free shift absorbs a translation of
its features, so its held-out residual measures the camera's shape over the frame, not where
the frame sits; a sharp frame's shift is fixed at 0. Every camera is scored by the same fit
(:func:`fit_frames`) through its own projection (:func:`generic_projector`,
:func:`parametric_projector`).

The cross-validation diff's cameras of two halves of the frames (:func:`half_split`) can come
from the same pass (``kfold_validation(..., halves=True)``).

A score pools the held-out residual norms of all scored frames: the median, and the RMS over
the observations below ``Q3 + 6 (Q3 - Q1)`` (the bundle adjustment's outlier rule).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import cv2
import numpy as np
import torch

from blurcalib.calib.bundle import BundleSettings
from blurcalib.calib.bundle_problem import robust_weights
from blurcalib.calib.frame_block import frame_jacobian
from blurcalib.calib.joint import GenericCalibration
from blurcalib.calib.normal_equations import leave_out_models
from blurcalib.calib.sharp import Calibration, CalibrationError, calibrate_sharp, solve_pose
from blurcalib.camera.generic import CentralGeneric, fit_to_rays, projection_jacobians
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.lie import exp_so3, orthonormal
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureTable
from blurcalib.target.pattern import StarPattern

__all__ = [
    "CameraScore",
    "FrameFit",
    "Validation",
    "ValidationMethod",
    "ValidationSettings",
    "assign_folds",
    "fit_frames",
    "generic_projector",
    "half_split",
    "kfold_validation",
    "leave_out_generic",
    "parametric_prior",
    "parametric_projector",
]

HALF_MIN_SHARP_FRAMES = 5
"""Fewest usable sharp frames of each half of :func:`half_split`: a half's prior is its own
parametric camera (:func:`blurcalib.calib.sharp.calibrate_sharp`)."""
PRIOR_ITERATIONS = 0
"""Gauss-Newton steps of :func:`parametric_prior`'s ray fit after its linear start: a prior's
shape needs none (on the demo the held-out medians agree to 1e-5 px with 4)."""
COST_NOISE = 1e-7
"""Relative rise of a frame's cost that :func:`fit_frames` still accepts: the generic projection
is solved to 1e-8 px, which makes a converged frame's cost that uncertain."""
ValidationMethod = Literal["kfold", "none"]
METHODS: tuple[str, ...] = get_args(ValidationMethod)
Projector = Callable[[torch.Tensor, "torch.Tensor | None"], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
"""A camera's projection for :func:`fit_frames`: camera-frame points ``X (N, 3)`` m and a warm
start ``(N, 2)`` px or None -> pixels ``u (N, 2)`` px (OpenCV), ``du/dX (N, 2, 3)`` px/m and
``inside (N,)`` bool."""


@dataclass(frozen=True)
class ValidationSettings:
    """Options of :func:`kfold_validation`.

    Attributes:
        method: ``"kfold"`` or ``"none"``.
        folds: ``K``, the number of folds.
        min_frames: fewer frames in the generic fit: no validation (too few to hold any out).
    """

    method: ValidationMethod = "kfold"
    folds: int = 5
    min_frames: int = 10

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"validation must be one of {METHODS}, got {self.method!r}")
        if self.folds < 2:
            raise ValueError(f"folds must be at least 2, got {self.folds}")


@dataclass(frozen=True)
class CameraScore:
    """Held-out reprojection errors of one camera (px), pooled over the scored frames.

    Attributes:
        median_px: median residual norm.
        rms_px: RMS residual norm over the non-outliers.
        frames: frames scored; ``observations`` their observations.
        sharp_median_px, blurry_median_px: the median over sharp / blurry frames (NaN without).
    """

    median_px: float
    rms_px: float
    frames: int
    observations: int
    sharp_median_px: float
    blurry_median_px: float

    def to_dict(self) -> dict[str, Any]:
        def value(v: float) -> float | None:
            return round(v, 5) if math.isfinite(v) else None

        return {"median_px": value(self.median_px), "rms_px": value(self.rms_px), "frames": self.frames,
                "observations": self.observations, "sharp_median_px": value(self.sharp_median_px),
                "blurry_median_px": value(self.blurry_median_px)}


@dataclass(eq=False)
class Validation:
    """The k-fold validation of a calibration.

    Attributes:
        method: ``"kfold"``.
        folds: ``K``.
        scores: camera -> its held-out score; keys ``generic`` (sharp + blurry frames),
            ``generic_sharp`` (sharp frames alone; only when blurry frames were given) and
            ``parametric`` (absent when no fold left enough sharp frames for it).
        fold_of: frame -> its fold.
        halves: the generic cameras (sharp + blurry frames) of the two interleaved halves of the
            frames (:func:`half_split`), when asked for and each half has enough sharp frames.
        frame: ``(N,)`` the frame of each observation of the generic fit; errors: camera -> the
            held-out residual norm ``(N,)`` px of each (NaN: not scored).
    """

    method: str
    folds: int
    scores: dict[str, CameraScore]
    fold_of: dict[str, int]
    halves: tuple[CentralGeneric, CentralGeneric] | None = None
    frame: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.str_))
    errors: dict[str, np.ndarray] = field(default_factory=dict)

    def scores_of(self, frames: Sequence[str], blurry_frames: Sequence[str] = ()) -> dict[str, CameraScore]:
        """The held-out scores of the observations of ``frames`` alone (e.g. one pattern's),
        ``blurry_frames`` counted as blurry; a camera without a scored observation there is left out."""
        rows = np.isin(self.frame, np.asarray(frames, dtype=np.str_))
        blurry = np.isin(self.frame[rows], np.asarray(blurry_frames, dtype=np.str_))
        out = {}
        for key, e in self.errors.items():
            ok = np.isfinite(e[rows])
            if ok.any():
                out[key] = _score(e[rows], blurry, len(set(self.frame[rows][ok].tolist())))
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "folds": self.folds,
                **{k: v.to_dict() for k, v in self.scores.items()}}


@dataclass(eq=False)
class FrameFit:
    """Frames fitted alone with the camera held (:func:`fit_frames`).

    Attributes:
        poses: ``(F,)`` poses (target -> camera).
        shifts: ``(F, 2)`` px image shifts (0 where not free).
        residuals: ``(N, 2)`` px ``p_i - pi(M_f P_i) - s_f``; NaN where the ray left the area.
    """

    poses: list[Pose]
    shifts: np.ndarray
    residuals: np.ndarray


def assign_folds(frames: Sequence[str], blurry: Sequence[bool] | np.ndarray, folds: int) -> np.ndarray:
    """Fold ``(F,)`` of every frame: sharp and blurry frames each dealt in turn, in their order
    (neighbouring frames of a sequence land in different folds, every fold gets both kinds)."""
    is_blurry = np.asarray(blurry, dtype=bool)
    out = np.zeros(len(frames), dtype=np.int64)
    out[~is_blurry] = np.arange(int((~is_blurry).sum())) % folds
    out[is_blurry] = (np.arange(int(is_blurry.sum())) + int((~is_blurry).sum())) % folds
    return out


def generic_projector(model: CentralGeneric) -> Projector:
    """The generic camera's projection (:meth:`blurcalib.camera.generic.GridSpline.project`) with its
    implicit derivative (:func:`blurcalib.camera.generic.projection_jacobians`)."""
    spline = model.spline()

    def project(X: torch.Tensor, init: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        u, inside = spline.project(X, init)
        return u, projection_jacobians(spline, u, X)[0], inside & (X[:, 2] > 0)

    return project


def parametric_projector(camera: BrownConrady | ParametricCamera, step_m: float = 1e-6) -> Projector:
    """The Brown-Conrady projection (:meth:`blurcalib.camera.parametric.BrownConrady.project`), its
    derivative by central differences of ``step_m`` m; inside: in front and within the image."""
    size = np.array([camera.width, camera.height], dtype=np.float64)

    def project(X: torch.Tensor, init: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = X.numpy()
        u = camera.project(x)
        J = np.empty((len(x), 2, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = step_m
            J[:, :, k] = (camera.project(x + d) - camera.project(x - d)) / (2 * step_m)
        inside = (x[:, 2] > 0) & np.all((u > -0.5) & (u < size - 0.5), axis=1)
        return torch.as_tensor(u), torch.as_tensor(J), torch.as_tensor(inside)

    return project


def fit_frames(projector: Projector, poses: Sequence[Pose], frame: np.ndarray, points: np.ndarray,
               observed: np.ndarray, shift_free: np.ndarray, *, iterations: int = 10, tol: float = 1e-9,
               huber_px: float = 1.0, shift_sigma_px: float = 20.0) -> FrameFit:
    """Fit every frame's pose (and free shift) alone with the generic camera held.

    The bundle adjustment's objective (:mod:`blurcalib.calib.bundle`) without the grid: per frame
    ``min sum_i rho(|p_i - pi_G(R P_i + t) - s|^2) + |s|^2 / sigma_s^2``, Huber ``rho`` by
    iteratively reweighted Gauss-Newton, all frames batched (``(F, 8, 8)`` normal equations,
    columns ``omega (3), dt (3), s (2)``), with a step halving per frame when the cost rises. A
    frame stops when no component of its step exceeds ``tol`` or when halving finds no lower
    cost; the next iterations project the other frames' observations only.

    Args:
        projector: the camera held (:func:`generic_projector`, :func:`parametric_projector`).
        poses: ``(F,)`` initial poses in the camera's frame.
        frame: ``(N,)`` frame index; points ``(N, 3)`` m; observed ``(N, 2)`` px (OpenCV).
        shift_free: ``(F,)`` bool.
        iterations: Gauss-Newton iterations at most; tol: a frame stops when no component of
            its step (rad, m, px) exceeds it.
        huber_px, shift_sigma_px: as :class:`blurcalib.calib.bundle.BundleSettings`.
    """
    kw: dict[str, Any] = {"dtype": torch.float64}
    F = len(poses)
    fr = torch.as_tensor(np.asarray(frame, dtype=np.int64))
    P = torch.as_tensor(np.asarray(points, dtype=np.float64))
    p = torch.as_tensor(np.asarray(observed, dtype=np.float64))
    free = torch.as_tensor(np.asarray(shift_free, dtype=bool))
    R = torch.as_tensor(np.stack([q.R for q in poses]), **kw)
    t = torch.as_tensor(np.stack([q.t for q in poses]), **kw)
    s = torch.zeros(F, 2, **kw)
    shift_w = 1.0 / shift_sigma_px**2
    eye2 = torch.eye(2, **kw)

    def evaluate(R: torch.Tensor, t: torch.Tensor, s: torch.Tensor, rows: torch.Tensor,
                 init: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
        """Points, projections, their derivatives, inside, residuals of the observations ``rows``
        and the cost ``(F,)`` of their frames (0 for the others)."""
        f = fr[rows]
        X = torch.einsum("nij,nj->ni", R[f], P[rows]) + t[f]
        u, J_p, inside = projector(X, init)
        r = p[rows] - u - s[f]
        e = torch.where(inside, r.norm(dim=-1), 0.0)
        rho = torch.where(e <= huber_px, e * e, 2 * huber_px * e - huber_px**2)
        cost = torch.zeros(F, **kw).index_add_(0, f, rho) + shift_w * (free[:, None] * s * s).sum(-1)
        return X, u, J_p, inside, r, cost

    every = torch.arange(len(fr))
    X, u, J_p, inside, r, cost = evaluate(R, t, s, every, p.clone())  # projections start where observed
    active = torch.ones(F, dtype=torch.bool)
    for _ in range(iterations):
        rows = every[active[fr]]
        sel = rows[inside[rows]]
        f = fr[sel]
        J = frame_jacobian(J_p[sel], X[sel] - t[f])
        w = robust_weights(r[sel], huber_px)[:, None, None]
        H = torch.zeros(F, 8, 8, **kw).index_add_(0, f, J.transpose(1, 2) @ (w * J))
        b = torch.zeros(F, 8, **kw).index_add_(0, f, (J.transpose(1, 2) @ (w * r[sel][:, :, None]))[..., 0])
        H[:, 6, 6] += shift_w
        H[:, 7, 7] += shift_w
        b[:, 6:] -= shift_w * s
        H[~free, 6:, :] = 0.0
        H[~free, :, 6:] = 0.0
        H[~free, 6:, 6:] = eye2
        b[~free, 6:] = 0.0
        H = H + 1e-9 * torch.diag_embed(torch.diagonal(H, dim1=1, dim2=2).clamp_min(1e-12))
        dp = torch.where(active[:, None], torch.linalg.solve(H, b), 0.0)
        step = torch.ones(F, **kw)
        for _half in range(6):
            d = dp * step[:, None]
            R_n = exp_so3(d[:, :3]) @ R
            trial = evaluate(R_n, t + d[:, 3:6], s + d[:, 6:], rows, u[rows])
            worse = active & (trial[-1] > cost * (1 + COST_NOISE))
            if not bool(worse.any()):
                break
            step = torch.where(worse, step * 0.5, step)
        better = active & ~worse
        R = torch.where(better[:, None, None], R_n, R)
        t = torch.where(better[:, None], t + d[:, 3:6], t)
        s = torch.where(better[:, None], s + d[:, 6:], s)
        moved = rows[better[fr[rows]]]
        keep = better[fr[rows]]
        X[moved], u[moved], J_p[moved], inside[moved], r[moved] = (v[keep] for v in trial[:5])
        cost = torch.where(better, trial[-1], cost)
        active &= better & (dp.abs().amax(dim=1) >= tol)
        if not bool(active.any()):
            break
    res = torch.where(inside[:, None], r, torch.nan).numpy()
    Rn, tn = R.numpy(), t.numpy()
    return FrameFit([Pose(orthonormal(Rn[i]), tn[i]) for i in range(F)], s.numpy(), res)


def _score(errors: np.ndarray, blurry: np.ndarray, frames: int) -> CameraScore:
    """Pool held-out residual norms ``(N,)`` (NaN: not projected) into a :class:`CameraScore`."""
    ok = np.isfinite(errors)
    e, b = errors[ok], blurry[ok]
    if not len(e):
        return CameraScore(math.nan, math.nan, frames, 0, math.nan, math.nan)
    q1, q3 = np.quantile(e, [0.25, 0.75])
    inl = e <= q3 + 6.0 * (q3 - q1)

    def median(m: np.ndarray) -> float:
        return float(np.median(e[m])) if m.any() else math.nan

    return CameraScore(median_px=float(np.median(e)), rms_px=float(np.sqrt(np.mean(e[inl] ** 2))),
                       frames=frames, observations=len(e), sharp_median_px=median(~b),
                       blurry_median_px=median(b))


def leave_out_generic(fit: GenericCalibration, left_out: Sequence[np.ndarray],
                      priors: Sequence[CentralGeneric]) -> list[CentralGeneric]:
    """The generic camera of ``fit`` without each set of frames: ``left_out[k] (F,)`` bool over
    ``fit.frames``; camera ``k`` is one step from ``fit`` on the other frames, its smoothness
    prior holding ``priors[k]``'s shape (:func:`blurcalib.calib.normal_equations.leave_out_models`)."""
    return leave_out_models(fit.bundle, left_out, priors)


def half_split(generic: GenericCalibration, sharp_features: FeatureTable, pattern: StarPattern,
               size: tuple[int, int], start: Calibration | None = None
               ) -> tuple[list[np.ndarray], list[CentralGeneric]] | None:
    """The two interleaved halves of ``generic.frames`` (:func:`assign_folds` with 2 folds) as
    frames to leave out, ``[half 0, half 1]`` ``(F,)`` bool, and the priors of the cameras of the
    other half: each the shape of that half's own parametric camera (target points refined, as
    the full calibration's: with half the frames the prior shapes much of the grid, and held
    nominal it moves the halves' diff by half). None when a half has too few sharp frames for it.
    ``start``: the calibration of all sharp frames, which starts the halves' parametric fits."""
    frames = np.array(generic.frames)
    half = assign_folds(frames.tolist(), np.isin(frames, generic.blurry_frames), 2)
    priors = []
    for h in (1, 0):
        train = sharp_features.select(np.isin(sharp_features.frame, frames[half == h]))
        try:
            camera = calibrate_sharp(train, pattern, size, min_frames=HALF_MIN_SHARP_FRAMES,
                                     start=start).camera
        except CalibrationError:
            return None
        priors.append(parametric_prior(camera, generic.model))
    return [half == 0, half == 1], priors


def parametric_prior(camera: BrownConrady | ParametricCamera, model: CentralGeneric) -> CentralGeneric:
    """``camera``'s rays on ``model``'s calibrated area and grid (the cold start's grid)."""
    return fit_to_rays(camera.pixel_to_ray, model.width, model.height,
                       area=(model.min_x, model.min_y, model.max_x, model.max_y),
                       grid_shape=(model.grid_height, model.grid_width), iterations=PRIOR_ITERATIONS)


def _score_frames(projector: Projector, poses: list[Pose], fit: GenericCalibration,
                  scored: np.ndarray, settings: BundleSettings) -> np.ndarray:
    """Residual norms ``(N,)`` of every observation of ``fit`` (NaN outside ``scored`` frames)."""
    names = np.array(fit.frames)[scored]
    index = {f: i for i, f in enumerate(names)}
    rows = np.isin(fit.frame, names)
    frame = np.array([index[f] for f in fit.frame[rows]], dtype=np.int64)
    free = np.array([f in fit.blurry_frames for f in names])
    ff = fit_frames(projector, poses, frame, fit.points[rows], fit.observed[rows], free,
                    huber_px=settings.huber_px, shift_sigma_px=settings.shift_sigma_px)
    out = np.full(len(fit.frame), np.nan)
    out[rows] = np.linalg.norm(ff.residuals, axis=1)
    return out


def kfold_validation(generic: GenericCalibration, generic_sharp: GenericCalibration | None,
                     calibration: Calibration, sharp_features: FeatureTable, pattern: StarPattern,
                     size: tuple[int, int], settings: ValidationSettings | None = None,
                     bundle: BundleSettings | None = None, halves: bool = False) -> Validation | None:
    """Score each camera on frames it has not seen (module docstring); None for ``method="none"``
    or fewer than ``min_frames`` frames.

    Args:
        generic: the generic fit of sharp and blurry frames (or of the sharp frames when no
            blurry frame was given).
        generic_sharp: the generic fit of the sharp frames alone, or None.
        calibration: the parametric (sharp-set) calibration.
        sharp_features: the sharp features it was fitted to (lens-corrected when it was).
        pattern, size: the target and the image size ``(width, height)`` px.
        settings: validation options; bundle: the bundle adjustment's options of the fits.
        halves: also the generic cameras of two halves of the frames (:attr:`Validation.halves`),
            from the same pass over the observations as the folds'.
    """
    settings = settings or ValidationSettings()
    bundle = bundle or BundleSettings()
    frames = generic.frames
    if settings.method == "none" or len(frames) < settings.min_frames:
        return None
    K = min(settings.folds, len(frames))
    blurry = np.array([f in generic.blurry_frames for f in frames])
    fold = assign_folds(frames, blurry, K)
    fold_of = dict(zip(frames, fold.tolist(), strict=True))
    obs_fold = np.array([fold_of[f] for f in generic.frame])
    obs_blurry = np.isin(generic.frame, generic.blurry_frames)
    errors = {k: np.full(len(generic.frame), np.nan) for k in ("generic", "generic_sharp", "parametric")}
    params: list[Calibration | None] = []
    for k in range(K):
        train_sharp = sharp_features.select(~np.isin(sharp_features.frame, np.array(frames)[fold == k]))
        try:
            params.append(calibrate_sharp(train_sharp, pattern, size, refine_points=False,
                                          start=calibration))
        except CalibrationError:  # too few sharp frames left: no parametric score for this fold
            params.append(None)
    shapes = [(param or calibration).camera for param in params]
    masks = [fold == k for k in range(K)]
    priors = [parametric_prior(c, generic.model) for c in shapes]
    split = half_split(generic, sharp_features, pattern, size, calibration) if halves else None
    if split is not None:
        masks += split[0]
        priors += split[1]
    models = {"generic": leave_out_generic(generic, masks, priors)}
    if generic_sharp is not None:
        fold_sharp = np.array([fold_of.get(f, -1) for f in generic_sharp.frames])
        same_grid = _same_grid(generic_sharp.model, generic.model)
        models["generic_sharp"] = leave_out_generic(
            generic_sharp, [fold_sharp == k for k in range(K)],
            priors[:K] if same_grid else [parametric_prior(c, generic_sharp.model) for c in shapes])
    for k in range(K):
        held = fold == k
        held_names = np.array(frames)[held]
        generic_poses = [generic.poses[f] for f in held_names]
        cams: dict[str, tuple[Projector, list[Pose]]] = {
            key: (generic_projector(m[k]), generic_poses) for key, m in models.items()}
        if (param := params[k]) is not None:
            cams["parametric"] = (parametric_projector(param.camera),
                                  [_parametric_pose(param, generic, f) for f in held_names])
        for key, (cam, poses) in cams.items():
            e = _score_frames(cam, poses, generic, held, bundle)
            errors[key][obs_fold == k] = e[obs_fold == k]
    scores = {key: _score(e, obs_blurry, len(set(generic.frame[np.isfinite(e)].tolist())))
              for key, e in errors.items() if np.isfinite(e).any()}
    return Validation("kfold", K, scores, fold_of,
                      None if split is None else (models["generic"][K], models["generic"][K + 1]),
                      frame=np.asarray(generic.frame), errors=errors)


def _same_grid(a: CentralGeneric, b: CentralGeneric) -> bool:
    """Whether two generic cameras share their calibrated area and grid size."""
    return ((a.width, a.height, a.min_x, a.min_y, a.max_x, a.max_y, a.grid.shape)
            == (b.width, b.height, b.min_x, b.min_y, b.max_x, b.max_y, b.grid.shape))


def _parametric_pose(param: Calibration, generic: GenericCalibration, frame: str) -> Pose:
    """A start pose of ``frame`` in the parametric camera's frame: the calibration's own when it
    saw the frame, otherwise a PnP with it (nominal points)."""
    if frame in param.poses:
        return param.poses[frame]
    rows = generic.frame == frame
    try:
        return solve_pose(param.camera, generic.points[rows], generic.observed[rows], ransac_px=20.0)
    except (ValueError, cv2.error):  # no pose, or OpenCV's SQPnP on a degenerate sample
        return generic.poses[frame]
