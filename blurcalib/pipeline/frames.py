"""The pipeline's frame rows: one per input frame, its status decided once from what each stage
made of it (``frames.csv`` and ``report.json``'s ``frames``; docs/results-format.md).

A frame is ``used`` when its features enter the final calibration (a sharp frame: the sharp-set
and generic calibrations; a blurry frame: the generic fit, or with ``model="parametric"`` the
global alignment and ``features.bin``). Every other status comes with its reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import Enum
from pathlib import Path

import numpy as np

from blurcalib.calib.joint import GenericCalibration
from blurcalib.calib.sequence import BlurryOutcome, SequenceSettings
from blurcalib.calib.sharp import Calibration
from blurcalib.extract.frame import FrameStatus
from blurcalib.io.atomic import atomic_write_csv
from blurcalib.io.results import BLUR_PER_SQUARE_LIMIT, BlockTable
from blurcalib.io.text import count

__all__ = ["FRAMES_COLUMNS", "FrameRow", "RowStatus", "blurry_row", "sharp_row", "status_counts",
           "write_frames"]


class RowStatus(str, Enum):
    """A frame's status in the run: ``used``, the extraction's own outcome, or why the run left
    it out (module docstring of :mod:`blurcalib.pipeline.run`)."""

    USED = "used"
    NOT_SEEDED = FrameStatus.NOT_SEEDED.value
    NO_BLOCKS = FrameStatus.NO_BLOCKS.value
    UNREADABLE = FrameStatus.UNREADABLE.value
    WRONG_SIZE = FrameStatus.WRONG_SIZE.value
    FAILED = FrameStatus.FAILED.value
    DUPLICATE = "duplicate"
    TOO_FEW_FEATURES = "too_few_features"
    LOW_BLUR = "low_blur"
    TOO_FEW_BLOCKS = "too_few_blocks"
    ILL_CONDITIONED = "ill_conditioned"
    ALIGNMENT_FAILED = "alignment_failed"


FRAMES_COLUMNS: tuple[str, ...] = (
    "frame", "kind", "blur_px", "noise_dn", "status", "reason", "extraction", "seeded_by", "psf",
    "features", "blocks", "kept", "centre_sigma_major", "alignment", "median_error", "mean_error",
    "angle_deg", "velocity_px")
"""The columns of ``frames.csv``."""


@dataclass(frozen=True)
class FrameRow:
    """One input frame's row.

    Attributes:
        frame: its name in the run's outputs (``sharp/<name>``, ``blurry/<name>``, ``frames/<name>``).
        kind: ``sharp`` or ``blurry``.
        status: its status, and ``reason`` why when it is not ``used``.
        extraction: the extraction's outcome (``ok``, ``duplicate``, ...), ``seeded_by``, ``psf``
            (``free`` or ``field``), ``blur_px`` (px) and ``noise_dn`` (grey levels; None when
            not measured) and ``features``, as the extraction recorded them.
        calibration_median_error: a used sharp frame's median error in the sharp-set calibration (px).
        blocks, kept, centre_sigma_major, filter_counts: a blurry frame's blocks, blocks kept by
            the filter, centre median sigma_major (px) and blocks per filter status.
        alignment: the parametric alignment's verdict (``ok``, ``ill_conditioned``, ``failed``) with
            ``median_error``, ``mean_error`` (px), ``angle_deg`` (optical axis to target normal) and
            ``translation`` (px).
        shift: the frame's image shift estimated by the generic fit on the joint route (px).
        velocity_px: a blurry frame's median blur velocity ``|u|`` (px per exposure time) where the
            rolling-shutter step measured it (:class:`blurcalib.calib.rolling_shutter.BlurVelocity`).
    """

    frame: str
    kind: str
    status: RowStatus
    reason: str = ""
    extraction: str = FrameStatus.OK.value
    blur_px: float | None = None
    noise_dn: float | None = None
    seeded_by: str = ""
    psf: str = ""
    features: int = 0
    calibration_median_error: float | None = None
    blocks: int | None = None
    kept: int | None = None
    centre_sigma_major: float | None = None
    filter_counts: dict[str, int] | None = None
    alignment: str | None = None
    median_error: float | None = None
    mean_error: float | None = None
    angle_deg: float | None = None
    translation: list[float] | None = None
    shift: list[float] | None = None
    velocity_px: float | None = None

    @property
    def used(self) -> bool:
        """Its features enter the final calibration."""
        return self.status is RowStatus.USED

    def to_dict(self) -> dict:
        """The row of ``report.json``: the extraction's fields always (``""`` where unknown), the
        later stages' where the frame reached them."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in _EXTRACTION_FIELDS:
                out[f.name] = "" if value is None else value
            elif value is not None:
                out[f.name] = value.value if isinstance(value, RowStatus) else value
        return out


_EXTRACTION_FIELDS = frozenset({"frame", "kind", "reason", "extraction", "blur_px", "noise_dn", "seeded_by",
                                "psf", "features"})


def _extraction(extracted: dict, kind: str) -> dict:
    """A row's extraction fields from the extraction's summary of the frame."""
    return dict(frame=extracted["frame"], kind=kind, extraction=extracted.get("status", ""),
                blur_px=extracted.get("blur_px") if extracted.get("blur_px", "") != "" else None,
                noise_dn=extracted.get("noise_dn") if extracted.get("noise_dn", "") != "" else None,
                seeded_by=extracted.get("seeded_by", ""), psf=extracted.get("psf", ""),
                features=extracted.get("features", 0))


def _not_extracted(extracted: dict, kind: str) -> FrameRow | None:
    """The row of a frame whose extraction did not end ``ok`` (its status and message), else None."""
    base = _extraction(extracted, kind)
    if base["extraction"] == FrameStatus.OK.value:
        return None
    status = RowStatus(base["extraction"] or RowStatus.FAILED.value)
    reason = extracted.get("message") or f"extraction ended with {status.value!r}"
    return FrameRow(status=status, reason=reason, **base)


def sharp_row(extracted: dict, calibration: Calibration, generic: GenericCalibration | None) -> FrameRow:
    """A sharp frame's row: ``used`` when it entered the sharp-set calibration and, when fitted,
    the generic one."""
    row = _not_extracted(extracted, "sharp")
    if row is not None:
        return row
    base = _extraction(extracted, "sharp")
    name = base["frame"]
    errors = calibration.frame_errors().get(name)
    if errors is None:
        return FrameRow(status=RowStatus.TOO_FEW_FEATURES, **base,
                        reason=f"{count(base['features'], 'feature')}: too few for the sharp-set calibration "
                               f"(its features are flagged filtered_out)")
    median = round(errors["median_error_px"] or float("nan"), 4)
    if generic is not None and name in generic.skipped_frames:
        return FrameRow(status=RowStatus.TOO_FEW_FEATURES, calibration_median_error=median, **base,
                        reason=f"{generic.skipped_frames[name]} usable features: too few for the generic fit")
    return FrameRow(status=RowStatus.USED, calibration_median_error=median, **base)


def blurry_row(extracted: dict, outcome: BlurryOutcome | None, settings: SequenceSettings,
               velocity_px: dict[str, float] | None = None) -> FrameRow:
    """A blurry frame's row from what the calibration sequence made of it (None: a frame of a
    feature file with the parametric model, which has no blocks to align); ``velocity_px``: the
    rolling-shutter step's median blur velocity of each frame it measured, by the frame's name in
    the calibration (``RollingShutterResult.velocity_px``).

    Its status is the generic fit's where the frame entered it (``used``, or
    ``too_few_features``), else the parametric route's (``used``, ``ill_conditioned``,
    ``alignment_failed``), else why no block is kept (``low_blur``, ``too_few_blocks``)."""
    row = _not_extracted(extracted, "blurry")
    if row is not None:
        return row
    base = _extraction(extracted, "blurry")
    if outcome is None:
        return FrameRow(status=RowStatus.NO_BLOCKS, **base,
                        reason="a feature file holds no blocks to align to the parametric camera (the "
                               "generic model uses it)")
    flt, fields_ = outcome.filter, dict(base)
    velocity = (velocity_px or {}).get(outcome.frame.name)
    if velocity is not None and math.isfinite(velocity):
        fields_.update(velocity_px=round(float(velocity), 3))
    if flt is not None:
        fields_.update(blocks=len(outcome.blocks), kept=int(flt.kept.sum()),
                       centre_sigma_major=round(flt.centre_sigma_major, 3), filter_counts=flt.counts())
        if not flt.frame_ok:
            return FrameRow(status=RowStatus.LOW_BLUR, **fields_,
                            reason=f"centre median sigma_major {flt.centre_sigma_major:.2f} px < "
                                   f"{settings.quality.min_sigma_major} px")
        if outcome.raw is None:
            return FrameRow(status=RowStatus.TOO_FEW_BLOCKS, **fields_,
                            reason=f"{count(int(flt.kept.sum()), 'block')} survive the BE/loss/connectivity "
                                   f"filter, {settings.alignment.min_blocks} needed"
                                   f"{_blur_note(outcome.blocks)}")
    status, reason = RowStatus.USED, ""
    ga = outcome.alignment
    if outcome.alignment_error:
        status, reason = RowStatus.ALIGNMENT_FAILED, outcome.alignment_error
        fields_.update(alignment="failed")
    elif ga is not None:
        angle = math.degrees(ga.angle_to_normal)
        fields_.update(alignment="ill_conditioned" if ga.ill_conditioned else "ok",
                       median_error=round(ga.median_error, 4), mean_error=round(ga.mean_error, 4),
                       angle_deg=round(angle, 2), translation=[round(float(v), 4) for v in ga.translation])
        if ga.ill_conditioned:
            status = RowStatus.ILL_CONDITIONED
            reason = (f"optical axis {angle:.1f} deg from the target normal: translation ill-conditioned, "
                      f"features flagged")
    if outcome.skipped_features is not None:
        return FrameRow(status=RowStatus.TOO_FEW_FEATURES, **fields_,
                        reason=f"{outcome.skipped_features} usable features: too few for the generic fit "
                               f"(or no pose)")
    if outcome.shift is not None:
        return FrameRow(status=RowStatus.USED, shift=[round(float(v), 4) for v in outcome.shift], **fields_)
    return FrameRow(status=status, reason=reason, **fields_)


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


def write_frames(path: Path, rows: list[FrameRow]) -> Path:
    """``frames.csv``: :data:`FRAMES_COLUMNS` of every row, empty where a row has no value."""
    def cell(row: FrameRow, column: str) -> object:
        value = getattr(row, column)
        return "" if value is None else value.value if isinstance(value, RowStatus) else value

    return atomic_write_csv(path, list(FRAMES_COLUMNS), [[cell(r, c) for c in FRAMES_COLUMNS] for r in rows])


def status_counts(rows: list[FrameRow]) -> dict[str, dict[str, int]]:
    """Frames per status of each kind: ``{"sharp": {...}, "blurry": {...}}``."""
    counts: dict[str, dict[str, int]] = {"sharp": {}, "blurry": {}}
    for r in rows:
        counts[r.kind][r.status.value] = counts[r.kind].get(r.status.value, 0) + 1
    return counts

