"""Calibration panel: run the parametric and generic calibration of the finished frames, compare
the models, watch the coverage fill in, see which frames were used, export the camera.

The logic is :mod:`state.calibration`; this module draws its figures with cv2 into RGB images.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import viser

from state import AppState, Topic
from state.calibration import AppCalibration, CalibrationRunner, Coverage, input_coverage
from views.common import Coalescer, legend_strip, md, placeholder
from views.errors import draw_cells, draw_quiver
from views.frame_view import DISPLAY_WIDTH

SHARP_COLOUR = (60, 205, 60)
BLURRY_COLOUR = (255, 150, 0)
SCOPES = ("all frames", "current frame")


def draw_coverage(cov: Coverage, width: int = DISPLAY_WIDTH) -> np.ndarray:
    """Observations per cell: the left half of a cell green for sharp observations, the right half
    orange for blurry ones, brighter with more (square root of the count over the largest); a
    legend with the totals below."""
    w, h = cov.image_size
    s = width / w
    canvas = np.full((max(1, round(h * s)), width, 3), 24, np.uint8)
    top = max(int(cov.sharp.max(initial=0)), int(cov.blurry.max(initial=0)), 1)
    c = cov.cell_px * s
    for (i, j), n_sharp in np.ndenumerate(cov.sharp):
        n_blurry = int(cov.blurry[i, j])
        x0, y0 = j * c, i * c
        for k, (n, colour) in enumerate(((int(n_sharp), SHARP_COLOUR), (n_blurry, BLURRY_COLOUR))):
            if n == 0:
                continue
            g = 0.25 + 0.75 * math.sqrt(n / top)
            cv2.rectangle(canvas, (round(x0 + k * c / 2), round(y0)),
                          (round(x0 + (k + 1) * c / 2) - 1, round(y0 + c) - 1),
                          tuple(int(v * g) for v in colour), -1)
        cv2.rectangle(canvas, (round(x0), round(y0)), (round(x0 + c), round(y0 + c)), (70, 70, 70), 1)
    empty = int(((cov.sharp + cov.blurry) == 0).sum())
    legend = legend_strip(width, ((SHARP_COLOUR, f"sharp: {int(cov.sharp.sum())} observations"),
                                  (BLURRY_COLOUR, f"blurry: {int(cov.blurry.sum())} observations"),
                                  ((70, 70, 70), f"{cov.cell_px:g} px cells, {empty} empty")))
    return np.concatenate([canvas, legend])


def residual_image(result: AppCalibration, frame: str | None, image: np.ndarray | None) -> np.ndarray:
    """The generic fit's residuals: over all frames, mean per cell in direction colours; for one
    frame, arrows at its observations over the frame (full length at 2 x the fit's RMS)."""
    g = result.generic
    size = result.inputs.image_size
    full = max(2.0 * g.rms_error, 1e-3)
    if frame is None:
        return draw_cells(size, g.observed, g.residuals, full, max(8, round(size[0] / 64)))
    xy, residuals = result.frame_residuals(frame)
    ok = np.all(np.isfinite(xy), axis=1) & np.all(np.isfinite(residuals), axis=1)
    return draw_quiver(image, size, xy[ok], residuals[ok], full)


def difference_image(result: AppCalibration) -> np.ndarray:
    """Generic minus parametric over the calibrated area, in direction colours (full brightness at
    the largest difference)."""
    xs, ys, diff = result.difference
    xx, yy = np.meshgrid(xs, ys)
    ok = np.all(np.isfinite(diff), axis=2)
    step = int(xs[1] - xs[0]) if len(xs) > 1 else 8
    mag = np.linalg.norm(diff[ok], axis=1)
    full = float(mag.max()) if len(mag) else 1.0
    xy = np.column_stack([xx[ok], yy[ok]])
    return draw_cells(result.inputs.image_size, xy, diff[ok], full, step)


def summary(result: AppCalibration | None, statuses: dict[str, str]) -> str:
    """The markdown summary: errors of both models (and against the truth), frames and why."""
    lines = []
    if result is None:
        lines.append("No calibration yet: extract frames, then press **Run calibration**.")
    else:
        p, g, t = result.parametric, result.generic, result.truth
        blurry = len(g.blurry_frames)
        lines.append(f"**Calibration** of {len(g.poses)} frames ({len(g.poses) - blurry} sharp, {blurry} "
                     f"blurry) in {result.seconds:.1f} s; generic grid {g.model.grid_width} x "
                     f"{g.model.grid_height}.")
        rows = ["| model | median (px) | RMS (px) |" + (" vs truth median | vs truth RMS |" if t else ""),
                "|---|---|---|" + ("---|---|" if t else "")]
        what = "sharp and blurry frames" if result.parametric_with_blurry else "sharp frames"
        rows.append(f"| parametric (Brown-Conrady, {what}) | {p.median_error:.4f} | {p.rms_error:.4f} |"
                    + (f" {t.parametric_median:.4f} | {t.parametric_rms:.4f} |" if t else ""))
        rows.append(f"| generic (all frames) | {g.median_error:.4f} | {g.rms_error:.4f} |"
                    + (f" {t.generic_median:.4f} | {t.generic_rms:.4f} |" if t else ""))
        lines.append("\n".join(rows))
        lines.append(f"generic median error: **{g.median_error:.4f} px** (sharp {g.sharp_median_error:.4f}, "
                     f"blurry {g.blurry_median_error:.4f} px)")
        if t is not None:
            lines.append(f"Against the true camera: over {t.pixels} lattice pixels of the calibrated area, "
                         "after the best-fit rotation.")
        if result.parametric_with_blurry:
            lines.append("Fewer than 5 sharp frames: the parametric stage also used the blurry frames' "
                         "kept blocks (without their shifts).")
    used = sorted(n for n, s in statuses.items() if s == "used")
    other = sorted((n, s) for n, s in statuses.items() if s != "used")
    lines.append(f"At the current thresholds: {len(used)} of {len(statuses)} frames used.")
    if other:
        lines.append("\n".join(f"- {md(n)}: {md(s)}" for n, s in other))
    if any(s.startswith("dropped by the pre-filter") for _, s in other):
        lines.append("Blurry frames below the σ_major pre-filter are left out: lower it in *Quality "
                     "filter* to use them.")
    return "\n\n".join(lines)


class CalibrationPanel:
    """Run and cancel buttons, progress, summary, coverage, residual and difference images, export."""

    def __init__(self, state: AppState, server: viser.ViserServer, runner: CalibrationRunner) -> None:
        self.state = state
        self.server = server
        self.runner = runner
        gui = server.gui
        self.run = gui.add_button("Run calibration", icon=viser.Icon.PLAYER_PLAY,
                                  hint="parametric then generic calibration of the finished frames")
        self.run_all = gui.add_button("Extract all and calibrate", icon=viser.Icon.PLAYER_TRACK_NEXT,
                                      hint="extract the frames not extracted yet, then calibrate")
        self.cancel = gui.add_button("Cancel calibration", icon=viser.Icon.PLAYER_STOP, color="red",
                                     disabled=True)
        self.progress = gui.add_progress_bar(0.0, animated=False)
        self.status = gui.add_markdown("")
        self.summary = gui.add_markdown("")
        self.coverage = gui.add_image(placeholder("no observations yet"), label="Coverage (inputs now)",
                                      format="png")
        self.scope = gui.add_dropdown("Residuals of", options=SCOPES)
        self.residuals = gui.add_image(placeholder("run the calibration"), label="Generic fit residuals",
                                       format="jpeg", jpeg_quality=90)
        self.difference = gui.add_image(placeholder("run the calibration"),
                                        label="Generic minus parametric", format="jpeg", jpeg_quality=90)
        self.difference_text = gui.add_markdown("")
        self.export = gui.add_button("Export camera", icon=viser.Icon.DOWNLOAD, disabled=True,
                                     hint="intrinsics0.yaml, camera.yaml and undistortion_map.npz into "
                                          "<folder>/calibration_app")
        self.export_text = gui.add_markdown("")
        self.run.on_click(lambda _: self.runner.run())
        self.run_all.on_click(lambda _: self.runner.run(extract=True))
        self.cancel.on_click(lambda _: self.runner.cancel())
        self.export.on_click(self._on_export)
        self._redraw = Coalescer(self._draw, 0.2, "calibration")
        self.scope.on_update(self._redraw.request)
        state.subscribe(self._on_change)
        self._redraw.request()

    def close(self) -> None:
        """Stop the redraw thread."""
        self._redraw.close()

    def _on_change(self, topic: Topic) -> None:
        if topic in (Topic.CALIBRATION, Topic.RESULT, Topic.FILTER, Topic.FRAMES, Topic.FOLDER,
                     Topic.CURRENT):
            self._redraw.request()

    def _on_export(self, _: viser.GuiEvent) -> None:
        try:
            paths = self.runner.export()
        except (ValueError, OSError) as exc:
            self.state.notify("error", "Export failed", str(exc))
            return
        self.export_text.content = f"Exported to {md(str(paths[0].parent))}: " + ", ".join(
            md(p.name) for p in paths)

    def _draw(self) -> None:
        progress = self.runner.progress()
        result = self.runner.result
        inputs = self.runner.inputs()
        statuses = self.runner.statuses()
        cov = input_coverage(inputs, self.runner.settings.cell_px) if inputs.image_size[0] else None
        coverage = draw_coverage(cov) if cov is not None and cov.total else placeholder("no observations yet")
        residuals = difference = None
        diff_text = ""
        if result is not None:
            view = self.state.view()
            frame = None
            if self.scope.value == SCOPES[1] and view is not None and view.entry.name in result.generic.poses:
                frame = view.entry.name
            residuals = residual_image(result, frame, view.image if frame is not None else None)
            difference = difference_image(result)
            mag = np.linalg.norm(result.difference[2], axis=2)
            diff_text = (f"generic minus parametric: median {np.nanmedian(mag):.3f} px, max "
                         f"{np.nanmax(mag):.3f} px over the calibrated area")
        busy = progress.running
        with self.server.atomic():
            self.run.disabled = busy
            self.run_all.disabled = busy
            self.cancel.disabled = not busy or progress.cancelling
            self.export.disabled = busy or result is None
            self.progress.value = 100.0 * progress.fraction
            self.progress.animated = busy
            self.status.content = f"**calibrating**: {progress.label}" if busy else ""
            self.summary.content = summary(result, statuses)
            self.coverage.image = coverage
            none = placeholder("run the calibration")
            self.residuals.image = residuals if residuals is not None else none
            self.difference.image = difference if difference is not None else none
            self.difference_text.content = diff_text
