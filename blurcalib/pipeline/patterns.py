"""One camera from several patterns, and the cross-pattern check (``docs/accuracy.md``).

``blurcalib calibrate --features A --pattern A.yaml --features B --pattern B.yaml`` calibrates one
camera from the frames of every pattern: each file's features become features of the joint target
(:mod:`blurcalib.target.pattern_set`: every frame keeps its own pattern's geometry and its own
pose, frames named ``pattern1/<frame>``, ``pattern2/<frame>``, ...), and the run is the
calibration from features (:func:`blurcalib.pipeline.run.run_from_table`) with its outputs.

Beside it, :func:`pattern_check` calibrates each pattern alone with the same settings and reports
(``report.json``'s ``patterns``):

* ``held_out``: the joint camera's held-out error on each pattern's frames (its k-fold
  validation split by pattern), and each pattern-alone camera's own held-out error when it has
  enough frames for a validation;
* ``cameras``: the first pattern's generic camera against each other pattern's
  (:func:`blurcalib.calib.cross_pattern.compare_cameras`: difference, focal-length scale, and the
  ratio to what their uncertainties predict, with the verdict), and the parametric cameras' focal
  lengths;
* ``features``: when frames are named alike in both files (the same poses), the feature-level
  cross-pattern residual (:func:`blurcalib.calib.cross_pattern.check_patterns`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from blurcalib.calib.cross_pattern import check_patterns, compare_cameras
from blurcalib.calib.sequence import CalibrationRun, calibrate_features
from blurcalib.calib.sharp import CalibrationError, calibrate_sharp
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.io.feature_input import FeatureInputError, read_feature_input
from blurcalib.io.results import FeatureTable
from blurcalib.io.text import count
from blurcalib.pipeline.frames import feature_file_inputs
from blurcalib.pipeline.run import (
    PipelineError,
    PipelineReport,
    PipelineSettings,
    check_feature_route,
    run_from_table,
)
from blurcalib.target.pattern import StarPattern
from blurcalib.target.pattern_set import PatternSet, pattern_set

__all__ = ["pattern_check", "pattern_lines", "run_from_feature_sets"]


def run_from_feature_sets(inputs: Sequence[tuple[str | os.PathLike[str], StarPattern]],
                          out_dir: str | os.PathLike[str], settings: PipelineSettings | None = None,
                          image_size: tuple[int, int] | None = None, overwrite: bool = False,
                          check: bool = True) -> PipelineReport:
    """Calibrate one camera from several feature files, each of its own pattern (module
    docstring); ``check``: also the cross-pattern check (:func:`pattern_check`).

    Raises:
        PipelineError: fewer than two inputs, an unusable file
            (:func:`blurcalib.io.feature_input.read_feature_input`), files of different image
            sizes, patterns of different square lengths, or what
            :func:`blurcalib.pipeline.run.run_from_table` refuses.
        OutputError: as :func:`blurcalib.pipeline.run.run_pipeline`.
    """
    s = settings or PipelineSettings()
    if len(inputs) < 2:
        raise PipelineError(f"a calibration from several patterns needs at least two feature files, got "
                            f"{len(inputs)}")
    check_feature_route(s)
    tables, sizes = [], []
    for path, pattern in inputs:
        try:
            table, size = read_feature_input(path, pattern, image_size)
        except FeatureInputError as exc:
            raise PipelineError(str(exc)) from None
        tables.append(table)
        sizes.append(size)
    paths = [str(path) for path, _ in inputs]
    for path, size in zip(paths[1:], sizes[1:], strict=True):
        if size != sizes[0]:
            raise PipelineError(f"{path}: images of {size[0]}x{size[1]}, {paths[0]}: {sizes[0][0]}x"
                                f"{sizes[0][1]}: the files of one camera have one image size")
    try:
        patterns = pattern_set([pattern for _, pattern in inputs])
    except ValueError as exc:
        raise PipelineError(f"{', '.join(paths)}: {exc}") from None
    joint = FeatureTable.concat([patterns.to_joint(k, t) for k, t in enumerate(tables)])
    source = {"features": [str(Path(p).resolve()) for p in paths]}

    def cross(run: CalibrationRun) -> dict[str, Any]:
        return pattern_check(run, patterns, tables, sizes[0], s, paths)

    return run_from_table(joint, sizes[0], patterns.joint, out_dir, s, overwrite, source,
                          f"{', '.join(paths)}: ", cross if check else None)


def _alone(table: FeatureTable, pattern: StarPattern, size: tuple[int, int], s: PipelineSettings
           ) -> CalibrationRun:
    """One pattern's features calibrated alone, with the run's settings."""
    inputs = feature_file_inputs(table, s.calibration.model != "parametric")
    return calibrate_features(inputs.sharp, None, inputs.frames, pattern, size, s.calibration)


def _brown_conrady(camera: BrownConrady | ParametricCamera) -> BrownConrady:
    """``camera``, which :func:`calibrate_sharp`'s default model makes a Brown-Conrady camera."""
    if not isinstance(camera, BrownConrady):
        raise TypeError(f"expected a Brown-Conrady camera, got {type(camera).__name__}")
    return camera


def _score(score: Any) -> dict[str, Any] | None:
    return None if score is None else score.to_dict()


def pattern_check(run: CalibrationRun, patterns: PatternSet, tables: Sequence[FeatureTable],
                  size: tuple[int, int], s: PipelineSettings, names: Sequence[str]) -> dict[str, Any]:
    """The cross-pattern check of the joint ``run`` (module docstring): ``report.json``'s
    ``patterns``. ``tables``: each pattern's features (its own ids and frame names); ``names``:
    the files they came from. What cannot be measured is said in ``failure``."""
    doc: dict[str, Any] = {"labels": dict(zip(patterns.labels, names, strict=True)), "held_out": {},
                           "alone": {}, "cameras": {}, "features": {}, "failure": ""}
    validation = None if run.trust is None else run.trust.validation
    if validation is not None and run.generic is not None:
        for k, label in enumerate(patterns.labels):
            frames = patterns.frames_of(k, run.generic.frames)
            scores = validation.scores_of(frames, run.generic.blurry_frames)
            doc["held_out"][label] = {"joint": _score(scores.get("generic"))}
    alone: list[CalibrationRun] = []
    for k, label in enumerate(patterns.labels):
        try:
            one = _alone(tables[k], patterns.patterns[k], size, s)
        except (CalibrationError, ValueError) as exc:
            doc["failure"] = f"{label} ({names[k]}) alone: {exc}"
            return doc
        alone.append(one)
        v = None if one.trust is None else one.trust.validation
        doc["held_out"].setdefault(label, {})["alone"] = (
            None if v is None or "generic" not in v.scores else v.scores["generic"].to_dict())
        camera = one.calibration.camera
        doc["alone"][label] = {"fx": round(camera.fx, 4), "fy": round(camera.fy, 4),
                               "generic_failure": one.generic_failure,
                               "uncertainty_median_px": None if one.trust is None
                               else round(one.trust.uncertainty.median(), 5)}
    first = alone[0]
    try:  # Brown-Conrady cameras, as blurcalib compare's: one model for every pattern
        bc = [_brown_conrady(calibrate_sharp(one.sharp, patterns.patterns[k], size).camera)
              for k, one in enumerate(alone)]
    except CalibrationError as exc:
        doc["failure"] = f"Brown-Conrady camera of a pattern alone: {exc}"
        return doc
    for k in range(1, len(alone)):
        label, other = patterns.labels[k], alone[k]
        pair = f"{label} - {patterns.labels[0]}"
        focal = [100.0 * (bc[k].fx / bc[0].fx - 1.0), 100.0 * (bc[k].fy / bc[0].fy - 1.0)]
        entry: dict[str, Any] = {"brown_conrady_focal_pct": [round(v, 4) for v in focal]}
        if first.generic is None or other.generic is None or first.trust is None or other.trust is None:
            entry["failure"] = "no generic camera with an uncertainty for each pattern alone"
        else:
            try:
                cmp = compare_cameras(first.generic.model, first.trust.uncertainty, other.generic.model,
                                      other.trust.uncertainty)
            except ValueError as exc:
                entry["failure"] = str(exc)
            else:
                entry.update(cmp.to_dict(), verdict=cmp.verdict(patterns.labels[0], label))
        doc["cameras"][pair] = entry
        try:
            fc = check_patterns(first.sharp, other.sharp, bc[0], bc[k])
        except ValueError:
            continue  # frames not named alike: no feature-level comparison
        doc["features"][pair] = {"systematic": fc.systematic, "worst_radial_px": round(fc.worst_radial_px, 5),
                                 "median_px": round(fc.median_px, 5), "matches": fc.matches,
                                 "lines": fc.lines()}
    return doc


def pattern_lines(doc: dict[str, Any] | None) -> list[str]:
    """The lines ``calibrate`` prints of ``report.json``'s ``patterns`` (nothing without it)."""
    if not doc:
        return []
    lines = ["patterns: " + ", ".join(f"{label} = {name}" for label, name in doc["labels"].items())]
    for label, held in doc["held_out"].items():
        parts = [f"{what} camera median {_px(score['median_px'])} ({count(score['frames'], 'frame')})"
                 for what, score in (("joint", held.get("joint")), ("own", held.get("alone"))) if score]
        lines.append(f"  held-out error on {label}'s frames: {', '.join(parts) or 'not measured'}")
    if doc["failure"]:
        lines.append(f"  warning: no cross-pattern check: {doc['failure']}")
    for pair, cam in doc["cameras"].items():
        focal = cam["brown_conrady_focal_pct"]
        lines.append(f"  {pair}: Brown-Conrady focal lengths {focal[0]:+.3f} % / {focal[1]:+.3f} %")
        lines.append(f"  {'warning: ' if cam.get('systematic') else ''}"
                     f"{cam.get('verdict') or 'no camera comparison: ' + cam.get('failure', '')}")
    for pair, feat in doc["features"].items():
        lines.append(f"  features {pair}: {feat['lines'][0]}")
    return lines


def _px(v: float | None) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.4f} px"
