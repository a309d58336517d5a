"""``blurcalib demo``'s account of its run: a progress line per stage, then the result in words,
the details after it, and what its terms mean.

Progress goes to the terminal as one line per stage (with the minutes and seconds since the
start); when the output is not a terminal (a pipe, a CI log) the lines also go, with one line per
frame extracted, to ``OUT/demo.log``. The result comes first: what was calibrated, how close it is
to the true camera, and what the blurry frames bought; the coverage warnings are one line (they
are in ``report.json``); the figures of the run and the terms follow.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, TextIO

from blurcalib.io.text import count
from blurcalib.sim.accuracy import GENERIC_BOTH, GENERIC_SHARP, TrueAccuracy

LOG_FILE = "demo.log"
"""The log of the run's progress in the demo's output folder, when the output is not a terminal."""

TERMS = (
    "median / 95% within / worst: the projection error of the camera against the true camera over "
    "the image's pixels (each pixel's true ray projected by the calibrated camera, minus the pixel, "
    "after the one rotation that best aligns the two cameras).",
    "lens shape alone: the same error once the focal lengths and the principal point are also "
    "refitted: what the camera gets wrong about the lens's distortion, as opposed to its scale.",
    "focal length off by: the rest, a scale error, in px at the image corners; it moves between runs "
    "with the frames' poses more than the shape does.",
    "true error N x the predicted uncertainty: the camera's own 1-sigma uncertainty map against its "
    "true error; near 1 the uncertainty can be trusted on real data, where there is no truth.",
    "held-out error: each frame scored by cameras fitted without it (its pose fitted alone); the "
    "estimate of the error on new frames that needs no ground truth.",
    "cross-validation diff: the difference between the generic cameras of two halves of the frames. "
    "Each half has half the observations, so each half's camera errs about 1.4 x as much as the whole "
    "set's, and the diff adds the errors of both: it is an upper bound of the whole camera's error, "
    "often 5 to 10 x the true error, not an estimate of it.",
)
"""What the demo's terms mean, one line each."""


class DemoLog:
    """The demo's progress: :meth:`stage` lines on ``stream`` (and in the log file when ``stream``
    is not a terminal), :meth:`detail` lines in the log file only."""

    def __init__(self, folder: Path, stream: TextIO | None = None) -> None:
        self.stream = stream or sys.stdout
        self.start = time.perf_counter()
        interactive = bool(getattr(self.stream, "isatty", lambda: False)())
        self.path: Path | None = None if interactive else Path(folder) / LOG_FILE
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.path.write_text("", encoding="utf-8")

    def _stamp(self) -> str:
        s = int(time.perf_counter() - self.start)
        return f"[{s // 60:02d}:{s % 60:02d}]"

    def stage(self, text: str) -> None:
        """A stage starts: one line, flushed at once."""
        line = f"{self._stamp()} {text}"
        print(line, file=self.stream, flush=True)
        self._log(line)

    def detail(self, text: str) -> None:
        """A step within a stage (a frame extracted): in the log file only."""
        self._log(f"{self._stamp()}   {text}")

    def _log(self, line: str) -> None:
        if self.path is not None:
            with self.path.open("a", encoding="utf-8") as f:
                f.write(line + "\n")


def _by_label(found: list[TrueAccuracy]) -> dict[str, TrueAccuracy]:
    return {t.label: t for t in found}


def _model_words(model: str) -> str:
    """A parametric model's name (``report.json``'s ``calibration.model``) in words."""
    return {"Brown_Conrady": "Brown-Conrady", "Kannala_Brandt": "Kannala-Brandt (fisheye)",
            "rational": "rational (OpenCV)", "thin_prism_fisheye": "thin-prism fisheye"}.get(model, model)


def result_lines(report: dict[str, Any], found: list[TrueAccuracy], image_size: tuple[int, int]) -> list[str]:
    """The result in words, from ``report.json`` (``report``) and the cameras against the truth
    (:func:`blurcalib.sim.accuracy.true_accuracies`)."""
    g = report.get("generic") or {}
    counts = report.get("counts", {})
    used = sum(1 for f in report.get("frames", []) if f.get("kind") == "blurry" and f.get("status") == "used")
    blurry = sum(counts.get("blurry", {}).values())
    sharp = report.get("calibration", {}).get("num_frames", 0)
    w, h = image_size
    lines = ["Result",
             f"  Calibrated: a simulated {w} x {h} camera, as a generic camera (a grid of "
             f"{g.get('grid_width')} x {g.get('grid_height')} control points of its rays) and as a "
             f"{_model_words(report.get('calibration', {}).get('model', 'Brown_Conrady'))} camera, from "
             f"{count(sharp, 'sharp frame')} and {used} of the {count(blurry, 'blurry frame')}."]
    cams = _by_label(found)
    best = cams.get(GENERIC_BOTH) or cams.get(GENERIC_SHARP)
    if best is not None:
        a = best.accuracy
        lines.append(f"  How good: the generic camera projects within {a.median:.4f} px of the true camera "
                     f"(median over the image; 95% of it within {a.p95:.4f} px).")
    sharp_only, both = cams.get(GENERIC_SHARP), cams.get(GENERIC_BOTH)
    bought = []
    if sharp_only is not None and both is not None:
        bought.append(f"against the truth {sharp_only.accuracy.median:.4f} px from the sharp frames alone, "
                      f"{both.accuracy.median:.4f} px with the blurry frames too")
    gain = report.get("blurry_frames_gain") or {}
    if "held_out_median_px" in gain:
        before, after = gain["held_out_median_px"]
        bought.append(f"held-out error {before:.4f} -> {after:.4f} px")
    if "uncertainty_border_px" in gain:
        before, after = gain["uncertainty_border_px"]
        bought.append(f"uncertainty near the image border {before:.4f} -> {after:.4f} px")
    if bought:
        lines.append("  What the blurry frames bought: " + "; ".join(bought) + ".")
    warnings = len(g.get("warnings", [])) + len((report.get("generic_sharp") or {}).get("warnings", []))
    if warnings:
        lines.append(f"  Coverage: {count(warnings, 'image region')} with grid cells no frame observed, "
                     "where the camera follows its initial model (report.json: generic.warnings).")
    return lines


def figure_lines(outputs: dict[str, str]) -> list[str]:
    """The figures the run wrote (PNG files), one line each."""
    figures = {k: v for k, v in outputs.items() if str(v).endswith(".png")}
    return ["Figures (each with its legend):"] + [f"  {k}: {v}" for k, v in sorted(figures.items())]


def term_lines() -> list[str]:
    """What the terms mean (:data:`TERMS`)."""
    return ["What the terms mean:"] + [f"  - {t}" for t in TERMS]
