"""What a calibration can be trusted for without ground truth (``docs/validation.md``).

:func:`assess_calibration` gathers, for the generic camera of sharp and blurry frames and the
generic camera of the sharp frames alone:

* the held-out reprojection error (:func:`blurcalib.calib.validation.kfold_validation`), with the
  parametric camera's beside it;
* the projection uncertainty (:func:`blurcalib.calib.uncertainty.projection_uncertainty`: the bundle
  adjustment's covariance propagated to pixels, global rotation removed);
* the cross-validation diff of the generic cameras of two halves of the frames
  (:func:`blurcalib.calib.uncertainty.cross_validation_diff`), which bounds what the data can tell;
* plain-words guidance naming the image regions whose uncertainty exceeds a threshold;
* what the blurry frames bought: the held-out error and the uncertainty, sharp-only against
  sharp + blurry;
* the model-error check (:mod:`blurcalib.calib.model_error`): whether random noise explains the
  generic camera's residuals over the image and the halves' diff.

:func:`save_trust` writes ``uncertainty.npz``, ``uncertainty.png`` and
``cross_validation.png`` (``docs/results-format.md``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from blurcalib.calib.bundle import BundleSettings
from blurcalib.calib.joint import GenericCalibration
from blurcalib.calib.model_error import ModelError, model_error
from blurcalib.calib.sharp import Calibration
from blurcalib.calib.uncertainty import (
    CrossValidationDiff,
    ProjectionUncertainty,
    cross_validation_diff,
    cross_validation_figure,
    guidance,
    projection_uncertainty,
    save_figure_png,
    save_uncertainty_npz,
    save_uncertainty_png,
)
from blurcalib.calib.validation import (
    Validation,
    ValidationSettings,
    half_split,
    kfold_validation,
    leave_out_generic,
)
from blurcalib.io.results import FeatureTable
from blurcalib.io.text import count
from blurcalib.target.pattern import StarPattern

__all__ = ["Trust", "TrustSettings", "assess_calibration", "gain_phrases", "save_trust", "summary_lines"]

UNCERTAINTY_NPZ = "uncertainty.npz"
UNCERTAINTY_PNG = "uncertainty.png"
CROSS_VALIDATION_PNG = "cross_validation.png"


@dataclass(frozen=True)
class TrustSettings:
    """Options of :func:`assess_calibration`.

    Attributes:
        validation: the k-fold validation's options.
        step_px: lattice step of the uncertainty and cross-validation maps (px, <= 16).
        guidance_px: uncertainty above which a region is named in the guidance (px).
        cross_validation: fit the two halves of the frames and compare them.
        prior_scale: the spread, in units of the bundle adjustment's ``smoothness_px``, that the
            uncertainty gives the initial (parametric) camera's shape where the data do not
            determine the grid (:func:`blurcalib.calib.uncertainty.projection_uncertainty`). Chosen by
            measurement against the truth on simulated data (``scripts/bench_uncertainty.py``,
            the demo): at 1 the predicted uncertainty is 2-20 x the true error where the frames
            are thin, because a lens deviates from its Brown-Conrady fit far less than 1 px in
            second differences; 0.1 gives a true-over-predicted RMS ratio of 0.50-1.50 on four
            simulated seeds and the demo (docs/uncertainty.md).
    """

    validation: ValidationSettings = field(default_factory=ValidationSettings)
    step_px: float = 16.0
    guidance_px: float = 0.05
    cross_validation: bool = True
    prior_scale: float = 0.1

    def __post_init__(self) -> None:
        if not 0 < self.step_px <= 16:
            raise ValueError(f"step_px must lie in (0, 16], got {self.step_px}")
        if not self.guidance_px > 0:
            raise ValueError(f"guidance_px must be positive, got {self.guidance_px}")


@dataclass(eq=False)
class Trust:
    """The figures of :func:`assess_calibration` (module docstring).

    Attributes:
        validation: held-out scores, or None (too few frames, or turned off).
        uncertainty: the generic camera's projection uncertainty.
        uncertainty_sharp: the sharp-only generic camera's, when blurry frames were used.
        cross_validation: the two halves' generic cameras compared, or None.
        guidance: plain-words advice on where more frames are needed.
        seconds: wall time (s) of each part: ``validation``, ``uncertainty``,
            ``cross_validation`` (the comparison alone when the validation ran: the halves'
            cameras come from its pass), ``model_error``.
        validation_skipped: why the validation did not run (too few frames, or turned off);
            None when it ran.
        model_error: whether random noise explains the data (:mod:`blurcalib.calib.model_error`).
    """

    validation: Validation | None
    uncertainty: ProjectionUncertainty
    uncertainty_sharp: ProjectionUncertainty | None
    cross_validation: CrossValidationDiff | None
    guidance: list[str]
    seconds: dict[str, float]
    validation_skipped: str | None = None
    model_error: ModelError | None = None

    def to_dict(self) -> dict[str, Any]:
        """The ``report.json`` sections ``validation`` (and ``validation_skipped``),
        ``uncertainty``, ``cross_validation``, ``model_error``, ``guidance`` and
        ``blurry_frames_gain``."""
        def unc(u: ProjectionUncertainty | None) -> dict[str, Any] | None:
            if u is None:
                return None
            return {"median_px": _round(u.median()), "border_px": _round(u.border_band()),
                    "max_px": _round(float(np.max(u.sigma_px))), "noise_px": _round(u.noise_px)}

        out: dict[str, Any] = {
            "validation": None if self.validation is None else self.validation.to_dict(),
            "validation_skipped": self.validation_skipped,
            "uncertainty": {"generic": unc(self.uncertainty), "generic_sharp": unc(self.uncertainty_sharp),
                            "step_px": float(self.uncertainty.x[1] - self.uncertainty.x[0])
                            if len(self.uncertainty.x) > 1 else None},
            "cross_validation": None if self.cross_validation is None else
            {"median_px": _round(self.cross_validation.median_px),
             "p95_px": _round(float(np.nanpercentile(self.cross_validation.diff_px, 95)))},
            "model_error": None if self.model_error is None else self.model_error.to_dict(),
            "guidance": self.guidance,
            "seconds": {k: round(v, 2) for k, v in self.seconds.items()},
        }
        gain = self.gain()
        if gain:
            out["blurry_frames_gain"] = gain
        return out

    def gain(self) -> dict[str, Any]:
        """What the blurry frames bought: sharp-only -> sharp + blurry figures (empty without a
        sharp-only camera)."""
        if self.uncertainty_sharp is None:
            return {}
        out = {"uncertainty_median_px": [_round(self.uncertainty_sharp.median()),
                                         _round(self.uncertainty.median())],
               "uncertainty_border_px": [_round(self.uncertainty_sharp.border_band()),
                                         _round(self.uncertainty.border_band())]}
        v = self.validation
        if v is not None and "generic_sharp" in v.scores:
            out["held_out_median_px"] = [_round(v.scores["generic_sharp"].median_px),
                                         _round(v.scores["generic"].median_px)]
        return out


def _round(v: float) -> float | None:
    return round(float(v), 5) if math.isfinite(v) else None


def assess_calibration(generic: GenericCalibration, generic_sharp: GenericCalibration | None,
                       calibration: Calibration, sharp_features: FeatureTable, pattern: StarPattern,
                       size: tuple[int, int], settings: TrustSettings | None = None,
                       bundle: BundleSettings | None = None) -> Trust:
    """Held-out error, projection uncertainty, cross-validation diff and guidance (module
    docstring) of a calibration.

    Args:
        generic: the generic fit of the sharp and blurry frames (or the sharp frames alone).
        generic_sharp: the generic fit of the sharp frames alone when ``generic`` used blurry
            frames, else None.
        calibration: the parametric (sharp-set) calibration; sharp_features: its features.
        pattern, size: the target and the image size ``(width, height)`` px.
        settings: options; bundle: the bundle adjustment's options of the fits.
    """
    settings = settings or TrustSettings()
    bundle = bundle or BundleSettings()
    t0 = time.perf_counter()
    validation = kfold_validation(generic, generic_sharp, calibration, sharp_features, pattern, size,
                                  settings.validation, bundle, halves=settings.cross_validation)
    t1 = time.perf_counter()
    unc = projection_uncertainty(generic.bundle, step_px=settings.step_px, prior_scale=settings.prior_scale)
    unc_sharp = None if generic_sharp is None else projection_uncertainty(
        generic_sharp.bundle, step_px=settings.step_px, prior_scale=settings.prior_scale)
    t2 = time.perf_counter()
    cv = None
    if validation is not None and validation.halves is not None:
        cv = cross_validation_diff(*validation.halves)
    elif settings.cross_validation and validation is None:
        split = half_split(generic, sharp_features, pattern, size, calibration)
        if split is not None:
            a, b = leave_out_generic(generic, *split)
            cv = cross_validation_diff(a, b)
    advice = guidance(unc, size[0], size[1], threshold_px=settings.guidance_px)
    seconds = {"validation": t1 - t0, "uncertainty": t2 - t1, "cross_validation": time.perf_counter() - t2}
    skipped = None
    if validation is None:
        vs = settings.validation
        skipped = ("turned off (--validation none)" if vs.method == "none" else
                   f"{count(len(generic.frames), 'frame')} in the generic fit, the k-fold validation "
                   f"needs at least {vs.min_frames}")
    t3 = time.perf_counter()
    inl = np.asarray(generic.inlier, dtype=bool)
    halves_unc = None if cv is None else projection_uncertainty(generic.bundle, step_px=settings.step_px)
    check = model_error(np.asarray(generic.observed)[inl], np.asarray(generic.residuals)[inl], size, cv,
                        halves_unc)
    seconds["model_error"] = time.perf_counter() - t3
    return Trust(validation, unc, unc_sharp, cv, advice, seconds, skipped, check)


def save_trust(folder: Path, trust: Trust, size: tuple[int, int]) -> dict[str, Path]:
    """Write ``uncertainty.npz``, ``uncertainty.png`` and (when measured) ``cross_validation.png``
    into ``folder``."""
    width, height = size
    out = {"uncertainty": save_uncertainty_npz(folder / UNCERTAINTY_NPZ, trust.uncertainty,
                                               trust.uncertainty_sharp)}
    maps = [("generic, sharp + blurry frames" if trust.uncertainty_sharp is not None else "generic",
             trust.uncertainty)]
    if trust.uncertainty_sharp is not None:
        maps.insert(0, ("generic, sharp frames", trust.uncertainty_sharp))
    out["uncertainty_map"] = save_uncertainty_png(folder / UNCERTAINTY_PNG, maps, width, height)
    if trust.cross_validation is not None:
        out["cross_validation"] = save_figure_png(folder / CROSS_VALIDATION_PNG, cross_validation_figure(
            trust.cross_validation, width, height))
    return out


def summary_lines(doc: dict[str, Any]) -> list[str]:
    """The lines ``calibrate`` and ``demo`` print, from :meth:`Trust.to_dict`'s sections (as
    ``report.json`` holds them)."""
    both = (doc.get("uncertainty") or {}).get("generic_sharp") is not None
    labels = {"generic": "generic, sharp + blurry frames" if both else "generic",
              "generic_sharp": "generic, sharp frames", "parametric": "parametric (Brown-Conrady)"}
    lines = []
    v = doc.get("validation")
    if v is None:
        lines.append(f"held-out error: not measured ({doc.get('validation_skipped') or 'no validation'})")
    else:
        lines.append(f"held-out reprojection error ({v['folds']}-fold over frames; each held-out frame's "
                     "pose, and a blurry frame's shift, fitted alone with the camera held):")
        for key in ("generic", "generic_sharp", "parametric"):
            if v.get(key):
                sc = v[key]
                lines.append(f"  {labels[key]:<32} median {_px(sc['median_px'])}, RMS {_px(sc['rms_px'])} "
                             f"({count(sc['frames'], 'frame')})")
    unc = doc.get("uncertainty") or {}
    if unc.get("generic"):
        lines.append(f"projection uncertainty (1 sigma, global rotation removed; noise "
                     f"{_px(unc['generic']['noise_px'])}):")
        for key in ("generic", "generic_sharp"):
            if unc.get(key):
                u = unc[key]
                lines.append(f"  {labels[key]:<32} median {_px(u['median_px'])}, border band "
                             f"{_px(u['border_px'])}, max {_px(u['max_px'])}")
    cv = doc.get("cross_validation")
    if cv:
        lines.append(f"cross-validation diff of the generic cameras of two halves of the frames: median "
                     f"{_px(cv['median_px'])}, p95 {_px(cv['p95_px'])}")
    me = doc.get("model_error")
    if me:
        lines.append(f"model error: {me['verdict']}")
    gain = doc.get("blurry_frames_gain")
    if gain:
        lines.append("what the blurry frames bought (sharp only -> sharp + blurry): "
                     + ", ".join(gain_phrases(gain)))
    lines += [f"guidance: {g}" for g in doc.get("guidance") or []]
    return lines


def gain_phrases(gain: dict[str, Any], arrow: str = "->") -> list[str]:
    """What the blurry frames bought (``report.json``'s ``blurry_frames_gain``), one phrase per
    figure: ``"held-out median 0.0181 px -> 0.0147 px"``."""
    names = (("held_out_median_px", "held-out median"), ("uncertainty_median_px", "median uncertainty"),
             ("uncertainty_border_px", "border-band uncertainty"))
    return [f"{what} {_px(gain[key][0])} {arrow} {_px(gain[key][1])}" for key, what in names if key in gain]


def _px(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.4f} px"
