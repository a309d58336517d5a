"""One frame's record at every stage, and the one status of a frame.

A :class:`FrameRecord` is what is known about one frame: queued or running in a run, what its
extraction made of it (seeding, PSFs, blur, noise, block and feature counts, time per stage, the
resume key) and, in a calibration, what the calibration made of it (:class:`Verdict`). Its
:attr:`FrameRecord.status` is one :class:`FrameStatus` through all of these stages.

:meth:`FrameRecord.to_row` and :meth:`FrameRecord.from_row` are the one boundary to dicts: an
extracted frame's row is its per-frame status record (``frames/<stem>.status.json``) and its row
of an ``extract`` folder's ``frames.csv`` (:data:`EXTRACT_COLUMNS`); a calibrated frame's row is
its entry of ``report.json``'s ``frames`` and its row of a ``calibrate`` folder's ``frames.csv``
(:data:`CALIBRATE_COLUMNS`). ``docs/results-format.md`` documents both.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from enum import Enum
from pathlib import Path
from typing import Any

from blurcalib.io.atomic import atomic_write_csv

__all__ = ["CALIBRATE_COLUMNS", "EXTRACTION_OUTCOMES", "EXTRACT_COLUMNS", "FINAL_STATUSES", "FRAMES_TABLE",
           "RUN_STATES", "VERDICTS", "FrameRecord", "FrameStatus", "Verdict", "split_fit_seconds",
           "write_frames_table"]

FRAMES_TABLE = "frames.csv"
"""The per-frame table of an output folder."""


class FrameStatus(str, Enum):
    """A frame's status: where a run stands with it, the outcome of its extraction, or what the
    calibration made of it (docs/results-format.md, "Frame status")."""

    PENDING = "pending"
    QUEUED = "queued"
    RUNNING = "running"
    CANCELLED = "cancelled"
    OK = "ok"
    NOT_SEEDED = "not_seeded"
    NO_BLOCKS = "no_blocks"
    UNREADABLE = "unreadable"
    WRONG_SIZE = "wrong_size"
    FAILED = "failed"
    USED = "used"
    DUPLICATE = "duplicate"
    TOO_FEW_FEATURES = "too_few_features"
    LOW_BLUR = "low_blur"
    TOO_FEW_BLOCKS = "too_few_blocks"
    ILL_CONDITIONED = "ill_conditioned"
    ALIGNMENT_FAILED = "alignment_failed"


RUN_STATES = frozenset({FrameStatus.PENDING, FrameStatus.QUEUED, FrameStatus.RUNNING, FrameStatus.CANCELLED})
"""A frame not extracted (yet): waiting, in progress, or stopped by a cancel (never on disk)."""

EXTRACTION_OUTCOMES = frozenset({FrameStatus.OK, FrameStatus.NOT_SEEDED, FrameStatus.NO_BLOCKS,
                                 FrameStatus.UNREADABLE, FrameStatus.WRONG_SIZE, FrameStatus.FAILED})
"""How a frame's extraction ended."""

FINAL_STATUSES = frozenset({FrameStatus.OK, FrameStatus.NOT_SEEDED, FrameStatus.NO_BLOCKS})
"""Extraction outcomes a resumed run keeps; unreadable, wrong-size and failed frames are retried."""

VERDICTS = frozenset({FrameStatus.USED, FrameStatus.DUPLICATE, FrameStatus.TOO_FEW_FEATURES,
                      FrameStatus.LOW_BLUR, FrameStatus.TOO_FEW_BLOCKS, FrameStatus.ILL_CONDITIONED,
                      FrameStatus.ALIGNMENT_FAILED})
"""What a calibration decided about an extracted frame (besides keeping its extraction's outcome)."""

EXTRACT_COLUMNS: tuple[str, ...] = ("frame", "status", "message", "seeded_by", "psf", "kind", "blur_px",
                                    "noise_dn", "blocks", "accepted", "features", "seconds")
"""The columns of an ``extract`` folder's ``frames.csv``."""

CALIBRATE_COLUMNS: tuple[str, ...] = (
    "frame", "kind", "blur_px", "noise_dn", "status", "reason", "extraction", "seeded_by", "psf",
    "features", "blocks", "kept", "centre_sigma_major", "alignment", "median_error", "mean_error",
    "angle_deg", "velocity_px")
"""The columns of a ``calibrate`` folder's ``frames.csv``."""


def split_fit_seconds(seconds: Mapping[str, float], fit: Mapping[str, float]) -> dict[str, float]:
    """Wall time (s) by stage with the growth's split out: the stages of ``seconds`` in order,
    ``fit`` replaced by the growth's stages ``fit`` (``free``, ``field``, ``final``, ``judge``)
    and ``fit_other``, the rest of it."""
    out: dict[str, float] = {}
    for k, v in seconds.items():
        if k == "fit":
            out.update(fit)
            out["fit_other"] = v - sum(fit.values())
        else:
            out[k] = v
    return out


@dataclass(frozen=True)
class Verdict:
    """What a calibration made of an extracted frame (its row of ``report.json``'s ``frames``).

    Attributes:
        reason: why the frame's status is not ``used`` (empty when it is).
        extraction: the extraction's outcome (``duplicate`` for a frame left out as the same view
            as an earlier one).
        calibration_median_error: a used sharp frame's median error in the sharp-set calibration (px).
        blocks, kept, centre_sigma_major, filter_counts: a blurry frame's blocks, blocks kept by
            the filter, centre median sigma_major (px) and blocks per filter status.
        alignment: the parametric alignment's verdict (``ok``, ``ill_conditioned``, ``failed``) with
            ``median_error``, ``mean_error`` (px), ``angle_deg`` (optical axis to target normal) and
            ``translation`` (px).
        shift: the frame's image shift estimated by the generic fit on the joint route (px).
        velocity_px: a blurry frame's median blur velocity ``|u|`` (px per exposure time) where the
            rolling-shutter step measured it.
    """

    reason: str = ""
    extraction: FrameStatus = FrameStatus.OK
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


@dataclass(frozen=True)
class FrameRecord:
    """What is known about one frame.

    Attributes:
        frame: the frame's name in the tables (``sharp/<name>`` in a calibration's own files).
        status: its status now: a run state, its extraction's outcome or the calibration's verdict.
        message: why, when the extraction did not end ``ok`` (or how it was seeded from a neighbour).
        seeded_by: how its blocks were seeded (``tag``, ``tag_deblurred``, ``neighbour``, ``given``;
            empty when not seeded).
        psf: ``field`` (its blocks were fitted with its path-PSF field), ``free`` or empty (not grown);
            ``psf_field`` the field (:meth:`blurcalib.psf.path.PathField.to_dict`), None without one.
        kind: ``sharp`` or ``blurry`` as extracted (empty when not known).
        blur_px: its measured blur (px, 3 decimals; None when not measured).
        noise_dn: its noise at its typical level (grey levels, 3 decimals; None when not estimated).
        blocks, accepted, features: attempted blocks, accepted blocks and feature observations.
        seconds: wall time (s, 3 decimals) of the whole frame; ``stages`` of each stage (``seed``,
            ``neighbour``, ``verify``, ``fit``, ``align``, ``load``, ``failed``) and ``fit_stages``
            of the growth's stages within ``fit`` (``free``, ``field``, ``final``, ``judge``).
        key: the resume key of what produced the result (pattern, settings, input file).
        source: the file it was extracted from (``walk.mp4#12`` for a video's frame).
        neighbours_tried: the neighbours whose seeds were tried (None: none was).
        verdict: what the calibration made of it (None outside a calibration).
    """

    frame: str
    status: FrameStatus = FrameStatus.PENDING
    message: str = ""
    seeded_by: str = ""
    psf: str = ""
    psf_field: dict[str, Any] | None = None
    kind: str = ""
    blur_px: float | None = None
    noise_dn: float | None = None
    blocks: int = 0
    accepted: int = 0
    features: int = 0
    seconds: float = 0.0
    stages: dict[str, float] = field(default_factory=dict)
    fit_stages: dict[str, float] = field(default_factory=dict)
    key: str = ""
    source: str = ""
    neighbours_tried: tuple[str, ...] | None = None
    verdict: Verdict | None = None

    @property
    def used(self) -> bool:
        """Its features enter the final calibration."""
        return self.status is FrameStatus.USED

    def stage_seconds(self) -> dict[str, float]:
        """Wall time (s) by stage, the growth's split out (:func:`split_fit_seconds`)."""
        return split_fit_seconds(self.stages, self.fit_stages)

    def to_row(self) -> dict[str, Any]:
        """The record as a JSON-serialisable dict: an extracted frame's status record (the columns
        of :data:`EXTRACT_COLUMNS`, ``psf_field`` after ``psf`` where there is one, ``seconds_<stage>``
        and ``seconds_fit_<stage>``, then ``key``, ``source`` and ``neighbours_tried`` where known;
        ``""`` for an unknown blur or noise), or, with a :attr:`verdict`, its row of ``report.json``
        (the extraction's fields always, ``""`` where unknown, the verdict's where known)."""
        if self.verdict is not None:
            return self._verdict_row(self.verdict)
        psf: dict[str, Any] = {"psf": self.psf}
        if self.psf_field is not None:
            psf["psf_field"] = self.psf_field
        row = {"frame": self.frame, "status": self.status.value, "message": self.message,
               "seeded_by": self.seeded_by, **psf, "kind": self.kind, "blur_px": _cell(self.blur_px),
               "noise_dn": _cell(self.noise_dn), "blocks": self.blocks, "accepted": self.accepted,
               "features": self.features, "seconds": self.seconds,
               **{f"seconds_{k}": v for k, v in self.stages.items()},
               **{f"seconds_fit_{k}": v for k, v in self.fit_stages.items()}}
        row.update({k: v for k, v in (("key", self.key), ("source", self.source)) if v})
        if self.neighbours_tried is not None:
            row["neighbours_tried"] = list(self.neighbours_tried)
        return row

    def _verdict_row(self, v: Verdict) -> dict[str, Any]:
        row = {"frame": self.frame, "kind": self.kind, "status": self.status.value, "reason": v.reason,
               "extraction": v.extraction.value, "blur_px": _cell(self.blur_px),
               "noise_dn": _cell(self.noise_dn), "seeded_by": self.seeded_by, "psf": self.psf,
               "features": self.features}
        for f in fields(Verdict)[2:]:
            value = getattr(v, f.name)
            if value is not None:
                row[f.name] = value
        return row

    @classmethod
    def from_row(cls, row: Mapping[str, object]) -> FrameRecord:
        """The record of a row written by :meth:`to_row` (as JSON, or as the strings of a
        ``frames.csv`` row): a row with an ``extraction`` is a calibrated frame's.

        Raises:
            ValueError: an unknown status, or a count or figure that is not a number.
            KeyError: no ``frame``.
        """
        frame = str(row["frame"])
        status = FrameStatus(str(row.get("status") or FrameStatus.PENDING.value))
        seeded_by, psf, kind = (str(row.get(k, "")) for k in ("seeded_by", "psf", "kind"))
        blur_px, noise_dn = _float(row.get("blur_px")), _float(row.get("noise_dn"))
        features = _int(row.get("features")) or 0
        if "extraction" in row:
            return cls(frame, status, seeded_by=seeded_by, psf=psf, kind=kind, blur_px=blur_px,
                       noise_dn=noise_dn, features=features, verdict=_verdict(row))
        seconds = {k: v for k, value in row.items()
                   if k.startswith("seconds_") and (v := _float(value)) is not None}
        tried, field_doc = row.get("neighbours_tried"), row.get("psf_field")
        return cls(frame, status, str(row.get("message", "")), seeded_by, psf,
                   dict(field_doc) if isinstance(field_doc, Mapping) else None, kind, blur_px, noise_dn,
                   _int(row.get("blocks")) or 0, _int(row.get("accepted")) or 0, features,
                   _float(row.get("seconds")) or 0.0,
                   {k[len("seconds_"):]: v for k, v in seconds.items() if not k.startswith("seconds_fit_")},
                   {k[len("seconds_fit_"):]: v for k, v in seconds.items() if k.startswith("seconds_fit_")},
                   str(row.get("key", "")), str(row.get("source", "")),
                   None if not isinstance(tried, Sequence) else tuple(str(n) for n in tried))


def _verdict(row: Mapping[str, object]) -> Verdict:
    """The verdict of a calibrated frame's row."""
    def listed(name: str) -> list[float] | None:
        value = row.get(name)
        listed = isinstance(value, Sequence) and not isinstance(value, str)
        return [float(x) for x in value] if listed else None  # type: ignore[attr-defined]

    counts, alignment = row.get("filter_counts"), row.get("alignment")
    return Verdict(str(row.get("reason", "")), FrameStatus(str(row["extraction"])),
                   _float(row.get("calibration_median_error")), _int(row.get("blocks")),
                   _int(row.get("kept")), _float(row.get("centre_sigma_major")),
                   None if not isinstance(counts, Mapping) else {str(k): int(n) for k, n in counts.items()},
                   None if alignment in (None, "") else str(alignment), _float(row.get("median_error")),
                   _float(row.get("mean_error")), _float(row.get("angle_deg")), listed("translation"),
                   listed("shift"), _float(row.get("velocity_px")))


def _cell(value: float | None) -> float | str:
    """A figure as written: ``""`` when unknown."""
    return "" if value is None else value


def _float(value: object) -> float | None:
    """A figure of a row (a JSON number or a CSV string); None for a missing or empty one."""
    return None if value is None or value == "" else float(value)  # type: ignore[arg-type]


def _int(value: object) -> int | None:
    """A count of a row (a JSON number or a CSV string); None for a missing or empty one."""
    return None if value is None or value == "" else int(value)  # type: ignore[call-overload]


def write_frames_table(path: str | os.PathLike[str], records: Sequence[FrameRecord],
                       columns: Sequence[str] = EXTRACT_COLUMNS) -> Path:
    """``frames.csv``: the ``columns`` of every record's row (:meth:`FrameRecord.to_row`), in the
    given order, empty where a row has no value."""
    rows = [r.to_row() for r in records]
    return atomic_write_csv(path, list(columns), [[row.get(c, "") for c in columns] for row in rows])
