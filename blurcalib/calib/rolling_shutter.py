"""The rolling shutter in the calibration: each moving frame's row-dependent geometry, the
readout ratio of the camera, and the detector of row-correlated residuals
(``docs/rolling-shutter.md``).

Model. Row ``v`` of an ``H``-row sensor is exposed over the window centred at
``c(v) = r y(v)`` exposure times, ``y(v) = (v - (H - 1) / 2) / H`` in ``[-1/2, 1/2]``
(:func:`blurcalib.camera.shutter.row_time`), ``r = readout / exposure time``. A feature seen in row
``v`` is the time-average of its image over that window, so (to second order in the motion) it
is seen from the frame's pose moved by the motion over ``c(v)``::

    p_i = pi(exp([y_i alpha_w + y_i^2 beta_w]_x) (R P_i + t) + y_i alpha_v + y_i^2 beta_v) + s

with the frame's rolling twist ``alpha = (alpha_w rad, alpha_v m)`` (the camera's velocity times
``r``, per unit of ``y``) and its curvature ``beta`` (``r^2`` times the acceleration), ``s`` the
blurry frame's free image shift. :func:`blurcalib.calib.rolling_frames.fit_rolling_frames` fits
``M_f, s_f, alpha_f, beta_f`` per frame with the camera held.

Readout ratio. A feature's image velocity is ``g_i = dp_i / dy = J_i (alpha + 2 y_i beta)``
(px per unit ``y``), which is ``r`` times its image velocity per exposure time ``u_i``. The blur
measures ``|u_i|``: the PSF of a line blur of length ``L`` has the second moment ``L^2 / 12``
along its axis, so ``L_i = sqrt(12 (sigma_major^2 - sigma_minor^2))`` (the minor axis carries the
optics) along ``d_i`` (``orientation``; its sign is unknown). Per frame
``r_f = sum_i |g_i . d_i| L_i / sum_i L_i^2``; the camera's ``r`` is their mean weighted by
``sum_i L_i^2``, with the standard error of that mean.

Significance. Each moving frame is fitted with and without its rolling parameters (the camera
held). Its ``z_f = (RSS_rigid - RSS_rolling) / s_f^2``, ``s_f^2 = RSS_rolling / (2 n_f - 20)`` its
own residual level, is chi-square with 12 degrees of freedom when the frame has no rolling-shutter
geometry and its errors are noise. Blurry features' errors are larger and correlated (the
deconvolution's), so 12 parameters always explain part of them: the capture has a rolling
shutter when ``sum_f z_f`` exceeds its ``1 - alpha`` quantile *and* the displacement the rolling
parameters explain net of a pose change, ``sqrt(sum_f (RSS_rigid - RSS_rolling) / N)``, exceeds
the residual they leave, ``sqrt(sum_f RSS_rolling / N)`` (:class:`RollingEvidence`), *and*,
where the blur is measured, ``r`` exceeds 3 standard errors (the blur confirms that the
row-dependent geometry follows the motion).

Calibration. When the model applies, the moving frames' rolling parameters are fitted together
with the camera in the bundle adjustment (:class:`blurcalib.calib.frame_block.RollingRows`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.stats import chi2

from blurcalib.calib.joint import GenericCalibration, JointSettings, calibrate_generic
from blurcalib.calib.rolling_frames import RollingFit, fit_rolling_frames, rolling_displacement
from blurcalib.calib.sharp import Calibration
from blurcalib.calib.validation import generic_projector
from blurcalib.io.results import BlockTable, FeatureTable
from blurcalib.target.pattern import StarPattern

__all__ = ["BlurVelocity", "RollingEvidence", "RollingShutterResult", "RollingShutterSettings",
           "blur_velocities", "calibrate_rolling_shutter", "estimate_ratio", "parse_rolling_shutter",
           "rolling_evidence"]


def parse_rolling_shutter(text: str) -> str | float:
    """``off``, ``auto`` or a readout ratio ``R >= 0`` (readout / exposure time).

    Raises:
        ValueError: naming the value, when it is none of these.
    """
    if text in ("off", "auto"):
        return text
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0 <= value <= 10):
        raise ValueError(f"rolling shutter {text!r}: expected off, auto or a readout ratio in [0, 10]")
    return value


@dataclass(frozen=True)
class RollingShutterSettings:
    """How the rolling shutter enters the calibration.

    Attributes:
        mode: ``"off"`` (the global-shutter model; the detector still runs), ``"auto"`` (estimate
            ``r``; correct the frames only when the rolling-shutter geometry is significant) or a
            known readout ratio ``R`` (correct the frames whatever the test says).
        alpha: false-alarm probability of the chi-square test.
        effect: the displacement the rolling geometry explains must exceed this times the
            residual it leaves (:meth:`RollingEvidence.found`).
        correction_twist_sigma: the rolling parameters' prior in the bundle adjustment that fits
            them with the camera (:class:`blurcalib.calib.frame_block.RollingRows`), rad and times the
            frame's distance in m: weaker than that of the frame fits of the test and the ratio
            (0.3, :func:`fit_rolling_frames`), whose estimates it steadies.
    """

    mode: str | float = "off"
    alpha: float = 1e-4
    correction_twist_sigma: float = 3.0
    effect: float = 1.0

    def __post_init__(self) -> None:
        if isinstance(self.mode, str) and self.mode not in ("off", "auto"):
            raise ValueError(f"rolling shutter mode must be off, auto or a ratio, got {self.mode!r}")


@dataclass(frozen=True)
class BlurVelocity:
    """Each block's blur as an image velocity per exposure time, sign unknown (``(B,)`` columns).

    Attributes:
        frame, feature_id: the block.
        length: ``L = sqrt(12 (sigma_major^2 - sigma_minor^2))`` px.
        direction: ``(B, 2)`` unit vector of the PSF's major axis (either sign).
    """

    frame: np.ndarray
    feature_id: np.ndarray
    length: np.ndarray
    direction: np.ndarray


def blur_velocities(tables: Sequence[BlockTable]) -> BlurVelocity:
    """The blocks' blur vectors (module docstring, *Readout ratio*), of every table in order."""
    major = np.concatenate([t.sigma_major for t in tables]) if tables else np.zeros(0)
    minor = np.concatenate([t.sigma_minor for t in tables]) if tables else np.zeros(0)
    theta = np.concatenate([t.orientation for t in tables]) if tables else np.zeros(0)
    return BlurVelocity(np.concatenate([t.frame for t in tables]) if tables else np.zeros(0, str),
                        np.concatenate([t.feature_id for t in tables]) if tables else np.zeros(0, np.int64),
                        np.sqrt(12.0 * np.clip(major**2 - minor**2, 0.0, None)),
                        np.column_stack([np.cos(theta), np.sin(theta)]))


def estimate_ratio(fit: RollingFit, frame: np.ndarray, blur: np.ndarray, direction: np.ndarray
                   ) -> tuple[float, float, np.ndarray]:
    """The readout ratio from the fitted frames and the blur (module docstring).

    Per frame, with ``s_i = sign(g_i . d_i)``, ``r_f = k_f . theta_f`` where
    ``k_f = sum_i s_i L_i d_i^T G_i / sum_i L_i^2`` (``G_i = d g_i / d theta``), of variance
    ``k_f^T Cov(theta_f) k_f``: a frame whose rolling geometry trades off against its pose counts
    little. ``r`` is the inverse-variance mean of the ``r_f``; its standard error the larger of
    the formal one and the frames' weighted scatter over ``sqrt(F)``.

    Args:
        fit: the frames' fit; frame ``(N,)`` int, its observations' frames.
        blur: ``(N,)`` px blur lengths ``L`` (NaN: no PSF); direction ``(N, 2)`` unit axes.
    Returns:
        ``(r, sigma_r, r_f (F,))`` (``r_f`` NaN for frames without blur or rolling parameters).
    """
    F = len(fit.theta)
    r_f = np.full(F, math.nan)
    var = np.full(F, math.nan)
    ok = np.isfinite(blur) & (blur > 0)
    for f in range(F):
        m = ok & (frame == f)
        den = float((blur[m] ** 2).sum())
        if m.sum() < 6 or den <= 0 or not np.all(np.isfinite(fit.theta_cov[f])):
            continue
        sign = np.sign((fit.velocity[m] * direction[m]).sum(axis=1))
        k = np.einsum("n,ni,nij->j", sign * blur[m], direction[m], fit.velocity_jacobian[m]) / den
        r_f[f] = float(k @ fit.theta[f])
        var[f] = float(k @ fit.theta_cov[f] @ k)
    have = np.isfinite(r_f) & (var > 0)
    if not have.any():
        return math.nan, math.nan, r_f
    w = 1.0 / var[have]
    ratio = float((w * r_f[have]).sum() / w.sum())
    n = int(have.sum())
    scatter = float(np.sqrt((w * (r_f[have] - ratio) ** 2).sum() / w.sum() / max(n - 1, 1)))
    return ratio, max(float(np.sqrt(1.0 / w.sum())), scatter if n > 1 else 0.0), r_f


@dataclass(eq=False)
class RollingShutterResult:
    """What the rolling-shutter step found and did.

    Attributes:
        mode: the setting (``off``, ``auto`` or a known ratio).
        ratio, sigma: the estimated readout ratio (readout / exposure time) and its standard
            error; NaN when the blur could not be measured.
        applied: whether the frames were corrected (the returned camera uses the model).
        significant: whether the features fit no rigid pose in the way a rolling shutter
            explains (the test of the module docstring).
        statistic, threshold: ``sum_f z_f`` and its null quantile.
        frames: the moving frames fitted.
        velocity_px: frame -> median blur velocity ``|u|`` (px per exposure time).
        frame_ratio: frame -> ``r_f``.
        rms_correction_px: the RMS displacement the moving frames' rolling parameters explain net
            of a change of pose (:attr:`RollingEvidence.explained_px`, px).
        message: one line for the user ("" with ``off`` when nothing was found).
        corrected: the blurry features the returned camera was fitted to (the raw ones minus
            their frame's rolling displacement), or None when not applied.
        global_shutter: when applied, the camera of the same features without the model (the
            global-shutter fit the step started from); else None.
    """

    mode: str | float
    ratio: float
    sigma: float
    applied: bool
    significant: bool
    statistic: float
    threshold: float
    frames: list[str]
    velocity_px: dict[str, float] = field(default_factory=dict)
    frame_ratio: dict[str, float] = field(default_factory=dict)
    rms_correction_px: float = math.nan
    message: str = ""
    corrected: FeatureTable | None = field(default=None, repr=False)
    global_shutter: GenericCalibration | None = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {"mode": self.mode, "ratio": num(self.ratio), "sigma": num(self.sigma),
                "applied": self.applied, "significant": self.significant,
                "statistic": num(self.statistic), "threshold": num(self.threshold),
                "frames": len(self.frames), "rms_correction_px": num(self.rms_correction_px),
                "velocity_px": {k: num(v) for k, v in self.velocity_px.items()},
                "frame_ratio": {k: num(v) for k, v in self.frame_ratio.items()}, "message": self.message}


def _blur_columns(calib: GenericCalibration, velocities: BlurVelocity | None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(N,)`` blur lengths and ``(N, 2)`` directions of the calibration's observations (NaN where
    no block matches; block frames match by name or by the name after ``blurry/``)."""
    n = len(calib.frame)
    blur = np.full(n, math.nan)
    direction = np.zeros((n, 2))
    if velocities is None:
        return blur, direction
    lookup = {(str(f), int(i)): k for k, (f, i) in enumerate(zip(velocities.frame, velocities.feature_id,
                                                                 strict=True))}
    for row, (f, i) in enumerate(zip(calib.frame, calib.feature_id, strict=True)):
        name = str(f)
        k = lookup.get((name, int(i)), lookup.get((name.split("/", 1)[-1], int(i))))
        if k is not None:
            blur[row] = velocities.length[k]
            direction[row] = velocities.direction[k]
    return blur, direction


def _raw_observed(calib: GenericCalibration, blurry: FeatureTable) -> np.ndarray:
    """``(N, 2)`` px: the calibration's observations, the blurry ones as ``blurry`` gives them (raw)."""
    raw = {(str(f), int(i)): (x, y) for f, i, x, y in zip(blurry.frame, blurry.feature_id, blurry.x, blurry.y,
                                                           strict=True)}
    observed = calib.observed.copy()
    for row, (f, i) in enumerate(zip(calib.frame, calib.feature_id, strict=True)):
        observed[row] = raw.get((str(f), int(i)), observed[row])
    return observed


def _fit(calib: GenericCalibration, blurry: FeatureTable, height: int, rolling: bool = True
         ) -> tuple[RollingFit, np.ndarray, list[str]]:
    """Fit every frame of a generic calibration with its camera held, with rolling parameters for
    its blurry frames (none when not ``rolling``), to the blurry frames' raw observations
    (``blurry``, uncorrected)."""
    names = calib.frames
    index = {f: k for k, f in enumerate(names)}
    frame = np.array([index[f] for f in calib.frame])
    moving = np.array([f in calib.blurry_frames for f in names])
    shifts = np.array([f in calib.shifts for f in names])
    observed = _raw_observed(calib, blurry)
    fit = fit_rolling_frames(generic_projector(calib.model), [calib.poses[f] for f in names], frame,
                             calib.points, observed, shifts, moving & rolling, height)
    return fit, frame, [f for f, m in zip(names, moving, strict=True) if m]


@dataclass(frozen=True)
class RollingEvidence:
    """What the moving frames' rolling parameters explain beyond a rigid pose (module docstring,
    *Significance*).

    Attributes:
        statistic, threshold: ``sum_f z_f`` over the moving frames and its null quantile.
        explained_px: ``sqrt(sum (RSS_rigid - RSS_rolling) / N)``, the RMS displacement the rolling
            geometry explains net of what a change of pose absorbs (px).
        residual_px: ``sqrt(sum RSS_rolling / N)``, the RMS residual left with it (px).
    """

    statistic: float
    threshold: float
    explained_px: float
    residual_px: float

    def found(self, effect: float = 1.0) -> bool:
        """Whether the frames show a rolling shutter: the statistic above its threshold *and* the
        explained displacement above ``effect`` times the residual (errors of the features that
        are not noise, such as a deconvolution's, pass the first test but not the second)."""
        return bool(self.statistic > self.threshold and self.explained_px > effect * self.residual_px)


def rolling_evidence(rolling: RollingFit, rigid: RollingFit, frame: np.ndarray, moving: np.ndarray,
                     alpha: float, outlier_factor: float = 5.0) -> RollingEvidence:
    """The extra-sum-of-squares test of each moving frame's rolling parameters against its own
    residual level.

    Per moving frame ``f`` with ``n_f`` observations inside both fits (those whose rigid residual is
    within ``outlier_factor`` times the frame's median, or 1 px, kept), ``z_f = (RSS_rigid -
    RSS_rolling) / s_f^2`` with ``s_f^2 = RSS_rolling / (2 n_f - 20)``: chi-square with 12 degrees
    of freedom when the frame has no rolling geometry and its residuals are noise of its own level.

    Args:
        rolling, rigid: the frames fitted with and without rolling parameters, the camera held.
        frame: ``(N,)`` the observations' frames; moving ``(F,)`` bool.
        alpha: false-alarm probability of the test.
    """
    stats, gained, left, count = [], 0.0, 0.0, 0
    for f in np.flatnonzero(moving):
        a, b = rolling.residuals[frame == f], rigid.residuals[frame == f]
        ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
        eb = np.linalg.norm(b[ok], axis=1)
        keep = eb < max(outlier_factor * float(np.median(eb)), 1.0) if len(eb) else eb > 0
        n = int(keep.sum())
        if n < 12:
            continue
        rss_a, rss_b = float((a[ok][keep] ** 2).sum()), float((b[ok][keep] ** 2).sum())
        stats.append(max(rss_b - rss_a, 0.0) * (2 * n - 20) / max(rss_a, 1e-300))
        gained += max(rss_b - rss_a, 0.0)
        left += rss_a
        count += n
    if not stats:
        return RollingEvidence(math.nan, math.nan, math.nan, math.nan)
    return RollingEvidence(float(sum(stats)), float(chi2.isf(alpha, 12 * len(stats))),
                           math.sqrt(gained / count), math.sqrt(left / count))


def calibrate_rolling_shutter(sharp: FeatureTable, blurry: FeatureTable, parametric: Calibration,
                              pattern: StarPattern, size: tuple[int, int], settings: RollingShutterSettings,
                              joint: JointSettings | None = None, velocities: BlurVelocity | None = None,
                              first: GenericCalibration | None = None
                              ) -> tuple[GenericCalibration, RollingShutterResult]:
    """The generic calibration with the rolling shutter (module docstring).

    Starts from the global-shutter calibration (``first``, or :func:`calibrate_generic` of the
    features), fits the moving frames' rolling geometry with that camera held, tests it and
    estimates ``r``. When the mode asks for it (``auto`` and significant, or a known ratio), the
    camera is fitted again together with every blurry frame's rolling parameters (the bundle
    adjustment's per-frame blocks grow to pose, shift and ``theta``); the blurry observations are
    corrected by their frame's fitted displacement under that camera, the generic camera of the
    corrected features is the one returned (so that what follows it sees a global-shutter fit),
    and ``r`` is estimated again with it held. With ``off`` or a non-significant ``auto`` the
    returned camera is the global-shutter one, unchanged.
    """
    height = size[1]
    calib = first or calibrate_generic(sharp, blurry, parametric, pattern, size, joint)
    fit, frame, moving = _fit(calib, blurry, height)
    result = _assess(calib, fit, _fit(calib, blurry, height, rolling=False)[0], frame, moving, settings,
                     velocities)
    if not result.applied:
        return calib, result
    rolling = calibrate_generic(sharp, blurry, parametric, pattern, size, joint,
                                rolling_twist_sigma=settings.correction_twist_sigma)
    corrected = _corrected(blurry, rolling, height)
    final = calibrate_generic(sharp, corrected, parametric, pattern, size, joint)
    refit, frame, moving = _fit(final, blurry, height)
    ratio, sigma, r_f = estimate_ratio(refit, frame, _moving_blur(final, frame, moving, velocities),
                                       _blur_columns(final, velocities)[1])
    names = final.frames
    frame_ratio = {names[f]: float(r_f[f]) for f in range(len(r_f)) if np.isfinite(r_f[f])}
    out = replace(result, ratio=ratio, sigma=sigma, frame_ratio=frame_ratio, corrected=corrected,
                  global_shutter=calib)
    return final, replace(out, message=_message(out, True))


def _moving_blur(calib: GenericCalibration, frame: np.ndarray, moving: list[str],
                 velocities: BlurVelocity | None) -> np.ndarray:
    """``(N,)`` blur lengths of the moving frames' observations (NaN elsewhere)."""
    on_moving = np.isin(frame, [calib.frames.index(f) for f in moving])
    blur = _blur_columns(calib, velocities)[0]
    return np.where(on_moving & np.isfinite(blur), blur, math.nan)


def _corrected(blurry: FeatureTable, calib: GenericCalibration, height: int) -> FeatureTable:
    """The raw blurry features minus their frame's rolling displacement ``pi(rolling pose) -
    pi(rigid pose)`` under the camera, poses and rolling parameters fitted together (``calib``,
    a :func:`calibrate_generic` with rolling parameters); 0 where a projection leaves the area."""
    names = calib.frames
    frame = np.array([names.index(f) for f in calib.frame])
    theta = np.stack([calib.rolling.get(f, np.zeros(12)) for f in names])
    poses = [calib.poses[f] for f in names]
    projector = generic_projector(calib.model)
    shift = np.nan_to_num(rolling_displacement(projector, poses, theta, frame, calib.points, calib.observed,
                                               height))
    key = {(str(f), int(i)): k for k, (f, i) in enumerate(zip(calib.frame, calib.feature_id, strict=True))}
    x, y = blurry.x.copy(), blurry.y.copy()
    for row, (f, i) in enumerate(zip(blurry.frame, blurry.feature_id, strict=True)):
        k = key.get((str(f), int(i)))
        if k is not None:
            x[row] -= shift[k, 0]
            y[row] -= shift[k, 1]
    return replace(blurry, x=x, y=y)


def _assess(calib: GenericCalibration, fit: RollingFit, rigid: RollingFit, frame: np.ndarray,
            moving: list[str], settings: RollingShutterSettings, velocities: BlurVelocity | None
            ) -> RollingShutterResult:
    names = calib.frames
    on_moving = np.isin(frame, [names.index(f) for f in moving])
    ev = rolling_evidence(fit, rigid, frame, np.isin(names, moving), settings.alpha)
    blur, direction = _blur_columns(calib, velocities)
    sel = on_moving & np.isfinite(blur)
    ratio, sigma, r_f = estimate_ratio(fit, frame, np.where(sel, blur, math.nan), direction)
    confirmed = not math.isfinite(ratio) or not math.isfinite(sigma) or ratio > 3.0 * sigma
    significant = ev.found(settings.effect) and confirmed
    velocity = {names[f]: float(np.median(blur[frame == f][np.isfinite(blur[frame == f])]))
                for f in np.unique(frame[sel])}
    frame_ratio = {names[f]: float(r_f[f]) for f in range(len(r_f)) if np.isfinite(r_f[f])}
    applied = isinstance(settings.mode, float) or (settings.mode == "auto" and significant)
    out = RollingShutterResult(settings.mode, ratio, sigma, applied, significant, ev.statistic, ev.threshold,
                               moving, velocity, frame_ratio, ev.explained_px)
    return replace(out, message=_message(out, applied))


def _message(res: RollingShutterResult, applied: bool) -> str:
    est = f"readout ratio {res.ratio:.2f} +- {res.sigma:.2f}" if math.isfinite(res.ratio) else \
        "readout ratio not measured (no blur)"
    if res.mode == "off":
        if res.significant:
            return (f"warning: the blurry frames' features fit no rigid pose in the way a rolling shutter "
                    f"explains ({est}, {res.rms_correction_px:.2f} px RMS beyond a pose change); "
                    f"try --rolling-shutter auto")
        return ""
    if applied and not res.significant:
        return (f"warning: rolling shutter modelled as asked (ratio {res.mode:g}), but the blurry frames' "
                f"features show none (test statistic {res.statistic:.0f}, significant above "
                f"{res.threshold:.0f}; {est}): modelling a readout the camera does not have costs accuracy "
                f"and time; --rolling-shutter auto keeps the global-shutter camera")
    if applied:
        return f"rolling shutter: modelled, {est} over {len(res.frames)} moving frames"
    return f"rolling shutter: none found ({est}; not significant): the global-shutter camera is kept"
