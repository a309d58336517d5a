"""What ``blurcalib calibrate`` prints of a run (:class:`blurcalib.pipeline.run.PipelineReport`):
both cameras' errors, the assessment, the frames per status and the files, with the generic fit's
coverage warnings grouped into one line (each is in ``report.json``'s ``generic.warnings``)."""

from __future__ import annotations

import re

from blurcalib.calib.trust import summary_lines
from blurcalib.io.text import count
from blurcalib.pipeline.patterns import pattern_lines
from blurcalib.pipeline.run import REPORT_FILE, PipelineReport

_REGION = re.compile(r"^(\d+) grid cells? without observations in the (.+?) of the image")


def warning_line(fit: str, warnings: list[str], section: str) -> str | None:
    """One line for the generic fit ``fit``'s coverage ``warnings`` (None without any): how many
    grid cells have no observation and in which image regions; the lines themselves are in
    ``report.json``'s ``section``."""
    if not warnings:
        return None
    cells, regions = 0, []
    for w in warnings:
        m = _REGION.match(w)
        if m is None:
            return (f"warning: {fit}: {count(len(warnings), 'warning')} (the first: {warnings[0]}); all in "
                    f"{REPORT_FILE}, {section}")
        cells += int(m[1])
        regions.append(m[2])
    return (f"warning: {fit}: {count(cells, 'grid cell')} without observations in {', '.join(regions)} of "
            f"the image, where the camera follows its initial model; take frames that cover them "
            f"({REPORT_FILE}, {section})")


def report_lines(report: PipelineReport) -> list[str]:
    """The lines ``calibrate`` prints after a run."""
    cal = report.calibration
    lines = [f"warning: capture: {warning}" for warning in (report.capture or {}).get("warnings", [])]
    lines += [f"sharp-set calibration ({cal['model']}): {count(cal['num_frames'], 'frame')}, "
              f"median {cal['median_error_px']:.4f} px, RMS {cal['rms_error_px']:.4f} px"]
    if report.parametric_choice is not None and report.parametric_choice["summary"]:
        lines.append(report.parametric_choice["summary"])
    if report.generic_failure:
        lines.append(f"warning: {report.generic_failure}")
    if report.assessment_failure:
        lines.append(f"warning: no assessment: {report.assessment_failure}")
    if report.generic is not None:
        g = report.generic
        lines.append(f"generic calibration ({g['route']} route): {g['grid_width']}x{g['grid_height']} grid, "
                     f"{count(g['frames'], 'frame')} ({g['blurry_frames']} blurry), "
                     f"median {g['median_error_px']:.4f} px, RMS {g['rms_error_px']:.4f} px")
        fit = "generic, sharp + blurry frames" if g["blurry_frames"] else "generic, sharp frames"
        lines.append(warning_line(fit, g["warnings"], "generic.warnings") or "")
    if report.undistortion is not None:
        u = report.undistortion
        unit = "px" if u["projection"] == "pinhole" else "px per rad"
        lines.append(f"undistortion map ({u['file']}): {u['projection']} image of {u['width']}x{u['height']} "
                     f"px, fx {u['fx']:.1f} {unit} (generic camera's field {u['field_deg']:.0f} degrees)")
    if report.generic_sharp is not None:
        lines.append(warning_line("generic, sharp frames", report.generic_sharp["warnings"],
                                  "generic_sharp.warnings") or "")
    if report.rolling_shutter is not None and report.rolling_shutter["message"]:
        lines.append(report.rolling_shutter["message"])
    lines += summary_lines(report.to_dict())
    lines += pattern_lines(report.patterns)
    for kind in ("sharp", "blurry"):
        statuses = ", ".join(f"{v} {k}" for k, v in sorted(report.counts[kind].items()))
        lines.append(f"{kind} frames: {statuses or 'none'}")
    lines += [f"  {kind}: {path}" for kind, path in report.outputs.items()]
    return [line for line in lines if line]
