"""The frame record: one status enum for every stage, and its rows (the status record, the rows
of ``frames.csv``, ``report.json``'s ``frames``) read back as they were written."""

from __future__ import annotations

import csv
import json
from dataclasses import fields
from pathlib import Path

import pytest

from blurcalib.io.frame_files import read_frame_status, write_frame_results
from blurcalib.io.record import (
    CALIBRATE_COLUMNS,
    EXTRACT_COLUMNS,
    EXTRACTION_OUTCOMES,
    FINAL_STATUSES,
    RUN_STATES,
    VERDICTS,
    FrameRecord,
    FrameStatus,
    Verdict,
    write_frames_table,
)
from blurcalib.io.results import BlockTable, FeatureTable

FIELD = {"degree": 1, "coeffs": [[1.5, -0.25, 0.0, 0.125], [0.5, 0.0, 0.0, 0.0], [0.0, 0.25, 0.0, 0.0]],
         "sigma_px": 0.6, "image_size": [640, 480]}

# A status record as the extraction wrote it before the record existed (a frame seeded from its
# neighbour, fitted with its path-PSF field): resuming reads it back unchanged.
WRITTEN = {"frame": "seq/1.png", "status": "ok", "message": "seeded from neighbour seq/0.png (labelling "
           "verified: residual ratio 0.03 against a square off)", "seeded_by": "neighbour", "psf": "field",
           "psf_field": FIELD, "kind": "blurry", "blur_px": 12.345, "noise_dn": 1.998, "blocks": 412,
           "accepted": 380, "features": 380, "seconds": 31.277, "seconds_neighbour": 30.2,
           "seconds_align": 0.077, "seconds_verify": 1.0, "seconds_fit_free": 20.5, "seconds_fit_field": 6.25,
           "key": "0f" * 32, "source": "/data/seq/1.png", "neighbours_tried": ["seq/0.png", "seq/2.png"]}

# A frame's row of report.json as a calibration wrote it.
REPORTED = {"frame": "blurry/seq/1.png", "kind": "blurry", "status": "ill_conditioned",
            "reason": "optical axis 3.1 deg from the target normal: translation ill-conditioned, features "
                      "flagged", "extraction": "ok", "blur_px": 12.345, "noise_dn": "", "seeded_by": "tag",
            "psf": "free", "features": 380, "blocks": 412, "kept": 301, "centre_sigma_major": 3.912,
            "filter_counts": {"accepted": 301, "high_loss": 79, "outside_image": 32}, "alignment":
            "ill_conditioned", "median_error": 0.0412, "mean_error": 0.0533, "angle_deg": 3.1,
            "translation": [0.1, -0.2, 30.0], "velocity_px": 7.255}


def _extracted(status: FrameStatus) -> FrameRecord:
    """A record at ``status`` with every extraction field set."""
    return FrameRecord("seq/1.png", status, f"why {status.value}", "tag", "field", FIELD, "sharp", 2.5, None,
                       12, 9, 9, 3.25, {"seed": 0.5, "fit": 2.5, "align": 0.25}, {"free": 2.0},
                       "ab" * 32, "/data/seq/1.png", ("seq/0.png",))


def _calibrated(status: FrameStatus) -> FrameRecord:
    """A record with a verdict at ``status``, every verdict field set."""
    verdict = Verdict(f"because {status.value}", FrameStatus.OK, 0.0312, 40, 31, 3.5, {"accepted": 31},
                      "ok", 0.04, 0.05, 12.5, [0.1, 0.2, 30.0], [0.5, -0.25], 7.255)
    return FrameRecord("sharp/1.png", status, "", "tag", "free", None, "sharp", 2.5, 1.25, features=9,
                       verdict=verdict)


def test_one_enum_covers_run_states_extraction_outcomes_and_verdicts() -> None:
    groups = (RUN_STATES, EXTRACTION_OUTCOMES, VERDICTS)
    assert set().union(*groups) == set(FrameStatus) and sum(map(len, groups)) == len(FrameStatus)
    assert FINAL_STATUSES < EXTRACTION_OUTCOMES and FrameStatus.FAILED not in FINAL_STATUSES


@pytest.mark.parametrize("status", list(FrameStatus))
def test_every_status_round_trips_through_json_and_frames_csv(status: FrameStatus, tmp_path: Path) -> None:
    for record, columns in ((_extracted(status), EXTRACT_COLUMNS), (_calibrated(status), CALIBRATE_COLUMNS)):
        row = json.loads(json.dumps(record.to_row()))
        assert FrameRecord.from_row(row) == record
        assert FrameRecord.from_row(row).to_row() == record.to_row()
        path = write_frames_table(tmp_path / "frames.csv", [record], columns)
        with open(path, newline="", encoding="utf-8") as handle:
            (cells,) = list(csv.DictReader(handle))
        assert list(cells) == list(columns)
        again = FrameRecord.from_row(cells)
        assert {c: str(v) for c, v in again.to_row().items() if c in columns} == {
            c: str(v) for c, v in record.to_row().items() if c in columns}


def test_rows_written_before_read_back_unchanged(tmp_path: Path) -> None:
    """A status record and a report.json row of the earlier writers: the same dict, key order
    included, comes back (so folders written before resume, and their reports stay the same)."""
    for row in (WRITTEN, REPORTED):
        back = FrameRecord.from_row(json.loads(json.dumps(row))).to_row()
        assert back == row and list(back) == list(row)
    record = FrameRecord.from_row(WRITTEN)
    assert record.neighbours_tried == ("seq/0.png", "seq/2.png") and record.psf_field == FIELD
    assert record.stage_seconds() == {"neighbour": 30.2, "align": 0.077, "verify": 1.0}
    reported = FrameRecord.from_row(REPORTED)
    assert reported.status is FrameStatus.ILL_CONDITIONED and reported.verdict.extraction is FrameStatus.OK
    assert reported.noise_dn is None and not reported.used


def test_status_file_holds_the_record(tmp_path: Path) -> None:
    record = FrameRecord.from_row(WRITTEN)
    write_frame_results(tmp_path, record.frame, FeatureTable.empty(), BlockTable.empty(), [], record)
    assert read_frame_status(tmp_path, record.frame) == record
    status = next((tmp_path / "frames").glob("*.status.json"))
    assert json.loads(status.read_text()) == WRITTEN
    status.write_text(json.dumps({**WRITTEN, "status": "sideways"}))
    assert read_frame_status(tmp_path, record.frame) is None  # an unknown status: redone


def test_a_record_without_extras_writes_the_plain_row() -> None:
    row = FrameRecord("a.png", FrameStatus.UNREADABLE, "a.png: truncated").to_row()
    assert list(row) == list(EXTRACT_COLUMNS) and row["blur_px"] == row["noise_dn"] == ""
    assert [f.name for f in fields(Verdict)][:2] == ["reason", "extraction"]
