"""The calibration's verdict on each input frame: its record (:class:`blurcalib.io.record.FrameRecord`)
with its status decided once from what each stage made of it (``frames.csv`` and
``report.json``'s ``frames``; docs/results-format.md).

A frame is ``used`` when its features enter the final calibration (a sharp frame: the sharp-set
and generic calibrations; a blurry frame: the generic fit, or with ``model="parametric"`` the
global alignment and ``features.bin``). Every other status comes with its reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from blurcalib.calib.joint import GenericCalibration
from blurcalib.calib.sequence import BlurryFrame, BlurryOutcome, SequenceSettings
from blurcalib.calib.sharp import Calibration
from blurcalib.extract.duplicates import mark_duplicates
from blurcalib.io.record import CALIBRATE_COLUMNS, FrameRecord, FrameStatus, Verdict, write_frames_table
from blurcalib.io.results import BLUR_PER_SQUARE_LIMIT, BlockTable, FeatureFlags, FeatureTable
from blurcalib.io.text import count

__all__ = ["FeatureFileInputs", "blurry_row", "feature_file_frames", "feature_file_inputs", "sharp_row",
           "status_counts", "write_frames"]


def _calibrated(extracted: FrameRecord, kind: str, status: FrameStatus, reason: str = "",
                **figures: object) -> FrameRecord:
    """The record of an extracted frame of ``kind`` with the calibration's verdict: its
    ``status``, ``reason`` and ``figures`` (:class:`blurcalib.io.record.Verdict`)."""
    verdict = Verdict(reason=reason, extraction=extracted.status, **figures)  # type: ignore[arg-type]
    return replace(extracted, kind=kind, status=status, verdict=verdict)


def _not_extracted(extracted: FrameRecord, kind: str) -> FrameRecord | None:
    """The record of a frame whose extraction did not end ``ok`` (its status and message), else None."""
    if extracted.status is FrameStatus.OK:
        return None
    reason = extracted.message or f"extraction ended with {extracted.status.value!r}"
    return _calibrated(extracted, kind, extracted.status, reason)


def sharp_row(extracted: FrameRecord, calibration: Calibration,
              generic: GenericCalibration | None) -> FrameRecord:
    """A sharp frame's record with its verdict: ``used`` when it entered the sharp-set calibration
    and, when fitted, the generic one."""
    row = _not_extracted(extracted, "sharp")
    if row is not None:
        return row
    name = extracted.frame
    errors = calibration.frame_errors().get(name)
    if errors is None:
        return _calibrated(extracted, "sharp", FrameStatus.TOO_FEW_FEATURES,
                           f"{count(extracted.features, 'feature')}: too few for the sharp-set calibration "
                           f"(its features are flagged filtered_out)")
    median = round(errors["median_error_px"] or float("nan"), 4)
    if generic is not None and name in generic.skipped_frames:
        return _calibrated(extracted, "sharp", FrameStatus.TOO_FEW_FEATURES,
                           f"{generic.skipped_frames[name]} usable features: too few for the generic fit",
                           calibration_median_error=median)
    return _calibrated(extracted, "sharp", FrameStatus.USED, calibration_median_error=median)


def blurry_row(extracted: FrameRecord, outcome: BlurryOutcome | None, settings: SequenceSettings,
               velocity_px: dict[str, float] | None = None) -> FrameRecord:
    """A blurry frame's record with what the calibration sequence made of it (``outcome`` None: a
    frame of a feature file with the parametric model, which has no blocks to align);
    ``velocity_px``: the rolling-shutter step's median blur velocity of each frame it measured, by
    the frame's name in the calibration (``RollingShutterResult.velocity_px``).

    Its status is the generic fit's where the frame entered it (``used``, or
    ``too_few_features``), else the parametric route's (``used``, ``ill_conditioned``,
    ``alignment_failed``), else why no block is kept (``low_blur``, ``too_few_blocks``)."""
    row = _not_extracted(extracted, "blurry")
    if row is not None:
        return row
    if outcome is None:
        return _calibrated(extracted, "blurry", FrameStatus.NO_BLOCKS,
                           "a feature file holds no blocks to align to the parametric camera (the "
                           "generic model uses it)")
    flt, figures = outcome.filter, dict[str, Any]()
    velocity = (velocity_px or {}).get(outcome.frame.name)
    if velocity is not None and math.isfinite(velocity):
        figures.update(velocity_px=round(float(velocity), 3))
    if flt is not None:
        assert outcome.blocks is not None  # filtered from them
        figures.update(blocks=len(outcome.blocks), kept=int(flt.kept.sum()),
                       centre_sigma_major=round(flt.centre_sigma_major, 3), filter_counts=flt.counts())
        if not flt.frame_ok:
            return _calibrated(extracted, "blurry", FrameStatus.LOW_BLUR,
                               f"centre median sigma_major {flt.centre_sigma_major:.2f} px < "
                               f"{settings.quality.min_sigma_major} px", **figures)
        if outcome.raw is None:
            return _calibrated(extracted, "blurry", FrameStatus.TOO_FEW_BLOCKS,
                               f"{count(int(flt.kept.sum()), 'block')} survive the BE/loss/connectivity "
                               f"filter, {settings.alignment.min_blocks} needed{_blur_note(outcome.blocks)}",
                               **figures)
    status, reason = FrameStatus.USED, ""
    ga = outcome.alignment
    if outcome.alignment_error:
        status, reason = FrameStatus.ALIGNMENT_FAILED, outcome.alignment_error
        figures.update(alignment="failed")
    elif ga is not None:
        angle = math.degrees(ga.angle_to_normal)
        figures.update(alignment="ill_conditioned" if ga.ill_conditioned else "ok",
                       median_error=round(ga.median_error, 4), mean_error=round(ga.mean_error, 4),
                       angle_deg=round(angle, 2), translation=[round(float(v), 4) for v in ga.translation])
        if ga.ill_conditioned:
            status = FrameStatus.ILL_CONDITIONED
            reason = (f"optical axis {angle:.1f} deg from the target normal: translation ill-conditioned, "
                      f"features flagged")
    if outcome.skipped_features is not None:
        return _calibrated(extracted, "blurry", FrameStatus.TOO_FEW_FEATURES,
                           f"{outcome.skipped_features} usable features: too few for the generic fit "
                           f"(or no pose)", **figures)
    if outcome.shift is not None:
        return _calibrated(extracted, "blurry", FrameStatus.USED,
                           shift=[round(float(v), 4) for v in outcome.shift], **figures)
    return _calibrated(extracted, "blurry", status, reason, **figures)


def _blur_note(blocks: BlockTable) -> str:
    """Why a frame keeps few blocks when its blur is as long as its squares: ``""`` or a clause
    with the median :attr:`BlockTable.blur_per_square` of its fitted blocks."""
    ratio = blocks.blur_per_square
    ratio = ratio[np.isfinite(ratio)]
    if not ratio.size or np.median(ratio) < BLUR_PER_SQUARE_LIMIT:
        return ""
    return (f"; its blur is {np.median(ratio):.2f} x the star squares' side (median of its fitted "
            f"blocks), and from {BLUR_PER_SQUARE_LIMIT} few stars can be located: a closer view "
            f"(larger squares) or a shorter exposure helps")


def feature_file_frames(table: FeatureTable) -> tuple[list[FrameRecord], list[FrameRecord]]:
    """The sharp and the blurry frames of a feature file (rows flagged ``BLURRY_FRAME`` are
    blurry), each a record with its feature count, in the file's order; a frame that shows the same
    view as an earlier one (:func:`blurcalib.extract.duplicates.mark_duplicates`, sharp frames
    preferred) has the status ``duplicate`` and names it."""
    blurry = (table.flags & int(FeatureFlags.BLURRY_FRAME)) != 0
    records = []
    for kind, rows in (("sharp", ~blurry), ("blurry", blurry)):
        names, first, counts = np.unique(table.frame[rows], return_index=True, return_counts=True)
        records += [FrameRecord(str(names[i]), FrameStatus.OK, features=int(counts[i]), kind=kind)
                    for i in np.argsort(first, kind="stable")]
    marked = mark_duplicates(records, table)
    return [r for r in marked if r.kind == "sharp"], [r for r in marked if r.kind == "blurry"]


@dataclass(frozen=True)
class FeatureFileInputs:
    """A feature file's frames as the calibration sequence takes them
    (:func:`feature_file_inputs`): the frame records of each kind, the sharp frames' features and
    the blurry frames (each with its features), duplicates left out."""

    sharp_rows: list[FrameRecord]
    blurry_rows: list[FrameRecord]
    sharp: FeatureTable
    blurry: FeatureTable
    frames: list[BlurryFrame]


def feature_file_inputs(table: FeatureTable, with_blurry: bool = True) -> FeatureFileInputs:
    """The frames of a feature file (:func:`feature_file_frames`) and the features the calibration
    sequence calibrates from: the sharp and blurry frames that are not duplicates; ``with_blurry``
    False: no blurry frame to fit (the parametric model)."""
    sharp_rows, blurry_rows = feature_file_frames(table)
    views = {r.frame for r in sharp_rows + blurry_rows if r.status is FrameStatus.OK}
    sharp = table.select(np.isin(table.frame, [r.frame for r in sharp_rows if r.frame in views]))
    blurry = table.select(np.isin(table.frame, [r.frame for r in blurry_rows if r.frame in views]))
    frames = ([BlurryFrame(r.frame, features=table.select(table.frame == r.frame)) for r in blurry_rows
               if r.frame in views] if with_blurry else [])
    return FeatureFileInputs(sharp_rows, blurry_rows, sharp, blurry, frames)


def write_frames(path: Path, rows: list[FrameRecord]) -> Path:
    """``frames.csv``: :data:`blurcalib.io.record.CALIBRATE_COLUMNS` of every calibrated frame's
    row, empty where a row has no value."""
    return write_frames_table(path, rows, CALIBRATE_COLUMNS)


def status_counts(rows: list[FrameRecord]) -> dict[str, dict[str, int]]:
    """Frames per status of each kind: ``{"sharp": {...}, "blurry": {...}}``."""
    counts: dict[str, dict[str, int]] = {"sharp": {}, "blurry": {}}
    for r in rows:
        counts[r.kind][r.status.value] = counts[r.kind].get(r.status.value, 0) + 1
    return counts
