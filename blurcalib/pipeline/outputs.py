"""The files of a calibration run beside its cameras: the features (``features.csv``, the reference
tool's ``features.bin``), ``frames.csv`` and the figures (``docs/results-format.md``)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from blurcalib.calib.report import error_direction_image, save_frame_error_plot
from blurcalib.calib.sequence import CalibrationRun
from blurcalib.io.atomic import atomic_path
from blurcalib.io.record import FrameRecord
from blurcalib.io.refformat import to_ref_dataset, write_ref_dataset
from blurcalib.io.results import FeatureFlags, FeatureTable, write_features
from blurcalib.pipeline.frames import write_frames
from blurcalib.target.pattern import StarPattern

__all__ = ["write_outputs"]


def write_outputs(out: Path, pattern: StarPattern, size: tuple[int, int], rows: list[FrameRecord],
                  run: CalibrationRun) -> dict[str, Path]:
    """The features (``features.csv``, ``features.bin``), ``frames.csv`` and the figures."""
    calibration, generic = run.calibration, run.generic
    features = FeatureTable.concat([run.sharp, *(o.aligned for o in run.blurry if o.aligned is not None)])
    outputs = {"features": write_features(out / "features.csv", features)}
    names = sorted(set(features.frame.tolist()))
    index = {f: i for i, f in enumerate(names)}
    usable = (features.flags & int(FeatureFlags.FILTERED_OUT)) == 0
    ref = to_ref_dataset(size, names, np.array([index[f] for f in features.frame[usable]]),
                         features.feature_id[usable], features.x[usable], features.y[usable],
                         pattern)
    outputs["reference_features"] = write_ref_dataset(out / "features.bin", ref)
    outputs["frames"] = write_frames(out / "frames.csv", rows)

    def direction_image(key: str, xy: np.ndarray, residuals: np.ndarray, title: str) -> None:
        path = out / f"{key}.png"
        with atomic_path(path) as tmp:
            cv2.imwrite(str(tmp), error_direction_image(xy, residuals, size, title=title))
        outputs[key] = path

    # Reprojection-error directions: the parametric alignment of the blurry frames, the sharp-set
    # calibration and, when fitted, the generic camera (its inliers).
    aligned = [(o.raw, o.alignment) for o in run.blurry if o.alignment is not None and o.raw is not None]
    if aligned:
        direction_image("error_directions_blurry",
                        np.concatenate([np.stack([raw.x, raw.y], axis=1) for raw, _ in aligned]),
                        np.concatenate([ga.residuals for _, ga in aligned]),
                        "blurry frames after alignment to the parametric camera")
    direction_image("error_directions_sharp", calibration.observed, calibration.residuals,
                    "sharp frames under the parametric camera")
    if generic is not None:
        direction_image("error_directions_generic", generic.observed[generic.inlier],
                        generic.residuals[generic.inlier], "all frames under the generic camera")
    outputs["frame_errors"] = save_frame_error_plot(out / "frame_errors.png",
                                                    [r.to_row() for r in rows if r.kind == "blurry"],
                                                    calibration.frame_errors())
    return outputs
