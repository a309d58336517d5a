"""Which model of the parametric family describes the lens, chosen by held-out error
(``--parametric auto``).

The sharp frames split into two folds (alternate frames in name order). Each candidate model
(:data:`CANDIDATES`) is calibrated on each fold (:func:`blurcalib.calib.sharp.calibrate_sharp`)
and scored on the other, the target points nominal (the choice needs the lens, not the points'
last micrometres, and a fit without free points costs a fraction): each held-out frame's pose is
solved with that camera (:func:`blurcalib.calib.pnp.solve_pose`, in viewing directions for the family's
models, so a point beyond 90 degrees off the axis counts as any other), and its errors
``|p - pi(M, P)|`` (px) are those of the observations within :data:`HELD_OUT_INLIER_PX` of it.
A model's score is the median over every held-out observation of both folds; an observation
the camera cannot project, or a frame whose pose cannot be solved, counts as an error of
``inf``, so a model that explains only part of the image scores badly.

The chosen model is the first of :data:`CANDIDATES` (Brown-Conrady, the paper's model, first;
then the fisheye, then the models with more parameters) whose score is within
:data:`CHOICE_MARGIN` of the best score: a model with more parameters must beat a simpler one
clearly. The Kannala-Brandt fold fits start the other models' (their camera converted:
:func:`blurcalib.calib.parametric_start.converted_start`), except Brown-Conrady's, which start
as its calibration does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from blurcalib.calib.calibration import Calibration
from blurcalib.calib.pnp import solve_pose
from blurcalib.calib.sharp import CalibrationError, calibrate_sharp
from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.family import as_family
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.rational import RationalCamera
from blurcalib.camera.thin_prism import ThinPrismFisheyeCamera
from blurcalib.io.results import FeatureTable
from blurcalib.target.pattern import StarPattern

__all__ = ["AUTO", "CANDIDATES", "CHOICE_MARGIN", "ModelChoice", "choose_model"]

AUTO = "auto"
"""The model setting that chooses by held-out error."""
CANDIDATES: tuple[str, ...] = (BrownConradyCamera.MODEL, KannalaBrandtCamera.MODEL, RationalCamera.MODEL,
                               ThinPrismFisheyeCamera.MODEL)
"""The models :func:`choose_model` compares, in order of preference."""
CHOICE_MARGIN = 0.10
"""A later candidate is chosen only if it beats every earlier one by more than this share of its
score."""
HELD_OUT_INLIER_PX = 20.0
"""A held-out observation further than this (px) from its frame's solved pose is an outlier of
the pose (scored, not used for the pose)."""


@dataclass
class ModelChoice:
    """The models' held-out scores and the choice.

    Attributes:
        model: the chosen model's name.
        scores: model -> median held-out error (px; ``inf`` when it failed).
        failures: model -> why a fold's calibration failed (only the models that failed).
        folds: the frames of each fold.
    """

    model: str
    scores: dict[str, float]
    failures: dict[str, str] = field(default_factory=dict)
    folds: list[list[str]] = field(default_factory=list)

    def ranked(self) -> list[str]:
        """The chosen model, then the others that did not fail by increasing score."""
        rest = sorted((m for m, s in self.scores.items() if m != self.model and math.isfinite(s)),
                      key=self.scores.__getitem__)
        return [self.model, *rest]

    def to_dict(self) -> dict[str, Any]:
        """``report.json``'s ``parametric_choice``: the model, each model's score (px; None for
        ``inf``) and failures."""
        return {"model": self.model,
                "held_out_median_px": {m: (s if math.isfinite(s) else None) for m, s in self.scores.items()},
                "failures": dict(self.failures), "summary": self.summary()}

    def summary(self) -> str:
        """One line: the chosen model and every model's held-out median ("" without scores)."""
        if not self.scores:
            return ""
        parts = [f"{m} {s:.3f} px" if math.isfinite(s) else f"{m} failed" for m, s in self.scores.items()]
        return f"parametric model {self.model} (held-out median: {', '.join(parts)})"


def _held_out_errors(calibration: Calibration, table: FeatureTable, pattern: StarPattern) -> np.ndarray:
    """``(N,)`` px: the errors of ``table``'s observations with each frame's pose solved by
    ``calibration``'s camera (module docstring); ``inf`` where none."""
    camera = as_family(calibration.camera)
    points = np.where(np.isfinite(calibration.points), calibration.points, pattern.points_3d())
    out = np.full(len(table), np.inf)
    for name in np.unique(table.frame):
        rows = np.flatnonzero(table.frame == name)
        obj, obs = points[table.feature_id[rows]], np.column_stack([table.x[rows], table.y[rows]])
        try:
            pose = solve_pose(camera, obj, obs, ransac_px=HELD_OUT_INLIER_PX)
        except (ValueError, np.linalg.LinAlgError):
            continue
        cam = pose.transform(obj)
        err = np.linalg.norm(camera.project(cam) - obs, axis=1)
        out[rows] = np.where(camera.valid_directions(cam) & np.isfinite(err), err, np.inf)
    return out


def choose_model(table: FeatureTable, pattern: StarPattern, image_size: tuple[int, int],
                 **calibrate: Any) -> ModelChoice:
    """The model of :data:`CANDIDATES` with the lowest held-out error (module docstring).

    Args:
        table: the sharp features (as :func:`calibrate_sharp` takes them).
        pattern, image_size: the target and ``(width, height)`` px.
        calibrate: :func:`calibrate_sharp`'s keyword options but ``refine_points`` (``min_frames``
            applies to the whole set; each fold needs 2 frames).

    With fewer than 4 usable frames (two folds of two) nothing can be held out: the choice is
    the first candidate, without scores.
    """
    min_frames = int(calibrate.pop("min_frames", 5))
    min_features = int(calibrate.get("min_features", 20))
    names, counts = np.unique(table.frame[np.isfinite(table.x)], return_counts=True)
    usable = [str(n) for n, c in zip(names, counts, strict=True) if c >= min_features]
    if len(usable) < max(4, min_frames):
        return ModelChoice(CANDIDATES[0], {})
    folds = [usable[0::2], usable[1::2]]
    errors: dict[str, list[np.ndarray]] = {m: [] for m in CANDIDATES}
    failures: dict[str, str] = {}
    for k, train in enumerate(folds):
        train_table = table.select(np.isin(table.frame, train))
        test_table = table.select(np.isin(table.frame, folds[1 - k]))
        fisheye: Calibration | None = None
        for model in CANDIDATES:
            start = fisheye if model not in (BrownConradyCamera.MODEL, KannalaBrandtCamera.MODEL) else None
            try:
                fitted = calibrate_sharp(train_table, pattern, image_size, False, min_frames=2, model=model,
                                         start=start, **calibrate)
            except (CalibrationError, ValueError, np.linalg.LinAlgError) as exc:
                failures.setdefault(model, str(exc))
                errors[model].append(np.full(len(test_table), np.inf))
                continue
            if model == KannalaBrandtCamera.MODEL:
                fisheye = fitted
            errors[model].append(_held_out_errors(fitted, test_table, pattern))
    scores = {m: float(np.median(np.concatenate(e))) for m, e in errors.items()}
    best = min(scores.values())
    chosen = next((m for m in CANDIDATES if scores[m] <= best * (1.0 + CHOICE_MARGIN)), CANDIDATES[0])
    return ModelChoice(chosen, scores, failures, folds)
