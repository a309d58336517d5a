"""What the rolling-shutter model does to a simulated run's camera (``blurcalib demo --rolling-shutter R``).

The run's generic camera is fitted with the model (``docs/rolling-shutter.md``);
:func:`camera_without_model` fits the same extraction again with the rolling shutter ``off``
(:func:`blurcalib.calib.sequence.calibrate_features` with the run's other settings, without the
assessment), and :func:`shutter_effect_lines` sets both cameras against the true one
(:func:`blurcalib.sim.evaluate.camera_accuracy`: px over the image, after the best-fit rotation).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from blurcalib.calib.joint import GenericCalibration
from blurcalib.calib.rolling_shutter import RollingShutterSettings
from blurcalib.calib.sequence import BlurryFrame, calibrate_features
from blurcalib.camera.files import read_generic_yaml
from blurcalib.camera.generic import CentralGeneric
from blurcalib.extract.frame import FrameStatus
from blurcalib.io.results import FEATURES_FILE, FeatureFlags, read_block_table, read_feature_table
from blurcalib.pipeline.frames import FrameRow
from blurcalib.pipeline.run import CALIBRATION_DIR, PipelineReport, PipelineSettings
from blurcalib.sim.evaluate import camera_accuracy
from blurcalib.sim.truth import DatasetTruth
from blurcalib.target.pattern import StarPattern

__all__ = ["camera_without_model", "shutter_effect_lines"]


def camera_without_model(folder: Path, rows: Sequence[FrameRow], pattern: StarPattern,
                         size: tuple[int, int], settings: PipelineSettings) -> GenericCalibration:
    """The generic camera of a ``calibrate`` run's extraction (``folder/sharp/``, ``folder/blurry/``;
    the frames whose extraction ``rows`` give as ``ok``, duplicates left out as the run left them)
    calibrated with ``settings`` and the rolling shutter ``off``.

    Raises:
        CalibrationError, ValueError: as :func:`blurcalib.calib.sequence.calibrate_features`.
    """
    ok = sorted(r.frame for r in rows if r.extraction == FrameStatus.OK.value)

    def named(table, kind: str):
        return replace(table, frame=np.char.add(f"{kind}/", table.frame))

    sharp = named(read_feature_table(folder / "sharp" / FEATURES_FILE), "sharp")
    sharp = sharp.select(np.isin(sharp.frame, ok) & ((sharp.flags & int(FeatureFlags.SHARP_FRAME)) != 0))
    blocks = named(read_block_table(folder / "blurry"), "blurry")
    flags = int(FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME)
    if settings.extraction.local_alignment:
        flags |= FeatureFlags.LOCALLY_ALIGNED
    frames = [BlurryFrame(r.frame, blocks=blocks.select(blocks.frame == r.frame), flags=flags)
              for r in rows if r.kind == "blurry" and r.frame in ok]
    off = replace(settings.calibration, rolling_shutter=RollingShutterSettings("off"))
    run = calibrate_features(sharp, named(read_block_table(folder / "sharp"), "sharp"), frames, pattern,
                             size, off, assess=False)
    return run.generic


def shutter_effect_lines(folder: Path, report: PipelineReport, truth: DatasetTruth, pattern: StarPattern,
                         settings: PipelineSettings) -> list[str]:
    """Two lines: the readout ratio simulated and the one estimated, and the run's generic camera
    (fitted with the rolling-shutter model; ``folder`` the run's output folder) and the same
    extraction's camera without the model against the truth (median, p95, max px), with the
    blurry frames each fit used; none when the dataset has no rolling shutter or the run did not
    model it."""
    simulated = max((f.rolling_shutter for f in truth.frames), default=0.0)
    if simulated <= 0 or report.generic is None or not (report.rolling_shutter or {}).get("applied"):
        return []
    model = truth.camera.model
    without = camera_without_model(folder, report.frames, pattern, (model.width, model.height), settings)
    with_model = read_generic_yaml(folder / CALIBRATION_DIR / "intrinsics0.yaml")
    rs = report.rolling_shutter
    estimated = f"{rs['ratio']:.2f} +- {rs['sigma']:.2f}" if rs.get("ratio") is not None else "not"
    blurry = sum(r.kind == "blurry" for r in report.frames)

    def figures(camera: CentralGeneric) -> str:
        a = camera_accuracy(truth.camera, camera)
        return f"median {a.median:.4f}, p95 {a.p95:.4f}, max {a.max:.4f} px"

    return [f"rolling shutter, readout ratio {simulated:g} simulated and {estimated} estimated: the generic "
            f"camera with the model {figures(with_model)} from the true camera "
            f"({report.generic['blurry_frames']} of {blurry} blurry frames);",
            f"  without it (the same features, --rolling-shutter off) {figures(without.model)} "
            f"({len(without.blurry_frames)} of {blurry})"]
