"""Calibration panel: extract what is missing and run the parametric and generic calibration,
compare the models, see how far the camera can be trusted without ground truth (held-out error,
projection uncertainty, cross-validation diff, guidance), watch the coverage fill in, see which
frames were used, export the camera.

The logic is :mod:`state.calibration`; this module draws its figures with cv2 (and the
uncertainty maps with matplotlib, as ``blurcalib calibrate`` writes them) into RGB images.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import viser
from matplotlib.figure import Figure

from blurcalib.calib.joint import GenericCalibration
from blurcalib.calib.trust import gain_phrases
from blurcalib.calib.uncertainty import CrossValidationDiff, cross_validation_figure, uncertainty_figure
from blurcalib.calib.validation import HALF_MIN_SHARP_FRAMES
from blurcalib.io.text import count
from state import AppState, Topic
from state.calibration import AppCalibration, CalibrationRunner, Coverage, input_coverage
from views.common import Coalescer, legend_strip, md, placeholder, set_image
from views.errors import draw_cells, draw_quiver
from views.frame_view import DISPLAY_WIDTH

SHARP_COLOUR = (60, 205, 60)
BLURRY_COLOUR = (255, 150, 0)
SCOPES = ("all frames", "current frame", "all frames, rolling shutter off")
GENERIC, GENERIC_BOTH, GENERIC_SHARP = "generic", "generic, sharp + blurry frames", "generic, sharp frames"
"""Names of the generic cameras in the assessment (as ``blurcalib calibrate`` prints them)."""


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


def residual_image(result: AppCalibration, frame: str | None, image: np.ndarray | None,
                   fit: GenericCalibration | None = None) -> np.ndarray:
    """The generic fit's residuals: over all frames, mean per cell in direction colours; for one
    frame, arrows at its observations over the frame (full length at 2 x the fit's RMS).
    ``fit``: another generic fit of the same frames to draw over all frames (the global-shutter
    camera, before the rolling-shutter model), on the result's colour scale."""
    full = max(2.0 * result.generic.rms_error, 1e-3)
    g = fit or result.generic
    size = result.inputs.image_size
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


def uncertainty_image(result: AppCalibration) -> np.ndarray | None:
    """The projection uncertainty maps, sharp-only and sharp + blurry side by side on one
    logarithmic px scale (:func:`blurcalib.calib.uncertainty.save_uncertainty_png`, as
    ``calibration/uncertainty.png``); None without an assessment."""
    trust = result.trust
    if trust is None:
        return None
    maps = [(GENERIC_BOTH if trust.uncertainty_sharp is not None else GENERIC, trust.uncertainty)]
    if trust.uncertainty_sharp is not None:
        maps.insert(0, (GENERIC_SHARP, trust.uncertainty_sharp))
    return _rgb(uncertainty_figure(maps, *result.inputs.image_size))


def _rgb(fig: Figure) -> np.ndarray:
    """A matplotlib figure drawn as an RGB image ``(H, W, 3)`` uint8."""
    fig.canvas.draw()
    return np.ascontiguousarray(np.asarray(fig.canvas.buffer_rgba())[:, :, :3])


def cross_validation_image(diff: CrossValidationDiff, size: tuple[int, int]) -> np.ndarray:
    """The cross-validation diff over the ``(width, height)`` image (px colour scale; grey outside
    the common calibrated area), as an RGB image."""
    return _rgb(cross_validation_figure(diff, *size))


def _px(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.4f}"


def _halves_too_small(generic: GenericCalibration) -> str:
    """Why the cross-validation diff was not measured, with the sharp frames each half has."""
    sharp = len(set(generic.frames) - set(generic.blurry_frames))
    small, large = sharp // 2, sharp - sharp // 2
    if small >= HALF_MIN_SHARP_FRAMES:
        return "a half's own parametric camera could not be fitted"
    return (f"each half's prior is its own parametric camera, from at least {HALF_MIN_SHARP_FRAMES} "
            f"sharp frames; the {count(sharp, 'sharp frame')} used here make halves of {large} and "
            f"{small}: {2 * HALF_MIN_SHARP_FRAMES} or more measure it")


def trust_summary(result: AppCalibration, guidance_px: float) -> str:
    """The markdown of the assessment: held-out error per camera (or why it was not measured),
    projection uncertainty, cross-validation diff, what the blurry frames bought and the guidance.

    Args:
        result: the calibration.
        guidance_px: the guidance's uncertainty threshold (px).
    """
    if result.trust is None:
        return f"**Trust without ground truth**: not assessed ({md(result.trust_failure)})."
    doc = result.trust.to_dict()
    both = result.trust.uncertainty_sharp is not None
    labels = {"generic": GENERIC_BOTH if both else GENERIC, "generic_sharp": GENERIC_SHARP,
              "parametric": "parametric (Brown-Conrady)"}
    parts = ["**Trust without ground truth** (the figures of `blurcalib calibrate`'s report)"]
    v = doc["validation"]
    if v is None:
        parts.append(f"**Held-out reprojection error**: not measured: {doc['validation_skipped']}.")
    else:
        rows = [f"**Held-out reprojection error** ({v['folds']}-fold over frames: each frame scored by "
                "cameras fitted without it, its pose, and a blurry frame's shift, fitted alone)", "",
                "| camera | held-out median (px) | RMS (px) | frames |", "|---|---|---|---|"]
        rows += [f"| {labels[k]} | {_px(v[k]['median_px'])} | {_px(v[k]['rms_px'])} | {v[k]['frames']} |"
                 for k in ("generic", "generic_sharp", "parametric") if v.get(k)]
        parts.append("\n".join(rows))
    if result.sharp_failure and result.generic_sharp is not None:
        parts.append(f"Generic camera of the sharp frames alone: {md(result.sharp_failure)}.")
    unc = doc["uncertainty"]
    rows = [f"**Projection uncertainty** (1 sigma, global rotation removed; noise "
            f"{_px(unc['generic']['noise_px'])} px)", "",
            "| camera | median (px) | border band (px) | max (px) |", "|---|---|---|---|"]
    rows += [f"| {labels[k]} | {_px(unc[k]['median_px'])} | {_px(unc[k]['border_px'])} | "
             f"{_px(unc[k]['max_px'])} |" for k in ("generic_sharp", "generic") if unc.get(k)]
    parts.append("\n".join(rows))
    cv = doc["cross_validation"]
    parts.append("**Cross-validation diff** of the generic cameras of two halves of the frames: "
                 + (f"median {_px(cv['median_px'])} px, 95th percentile {_px(cv['p95_px'])} px; the "
                    "camera is not known better than the halves agree." if cv else
                    f"not measured ({_halves_too_small(result.generic)})."))
    gain = doc.get("blurry_frames_gain")
    if gain:
        parts.append("**What the blurry frames bought** (sharp only → sharp + blurry): "
                     + ", ".join(gain_phrases(gain, "→")) + ".")
    elif result.generic.blurry_frames:
        parts.append("**What the blurry frames bought**: not measured (no generic camera of the sharp "
                     f"frames alone: {md(result.sharp_failure)}).")
    else:
        parts.append("**What the blurry frames bought**: no blurry frame entered the generic fit.")
    if doc["guidance"]:
        parts.append("**Guidance**\n\n" + "\n".join(f"- {md(g)}" for g in doc["guidance"]))
    else:
        parts.append(f"**Guidance**: the uncertainty is below {guidance_px:g} px over every region of the "
                     "image.")
    return "\n\n".join(parts)


def summary(result: AppCalibration | None, statuses: dict[str, str]) -> str:
    """The markdown summary: errors of both models (and against the truth), frames and why."""
    lines = []
    if result is None:
        lines.append("No calibration yet: press **Run calibration** (it extracts the frames not "
                     "extracted yet first).")
    else:
        p, g, t = result.parametric, result.generic, result.truth
        blurry = len(g.blurry_frames)
        lines.append(f"**Calibration** of {count(len(g.poses), 'frame')} ({len(g.poses) - blurry} sharp, "
                     f"{blurry} blurry) in {result.seconds:.1f} s; generic grid {g.model.grid_width} x "
                     f"{g.model.grid_height}.")
        rows = ["| model | median (px) | RMS (px) |"
                + (" vs truth median (px) | vs truth RMS (px) |" if t else ""),
                "|---|---|---|" + ("---|---|" if t else "")]
        what = "sharp and blurry frames" if result.parametric_with_blurry else "sharp frames"
        rows.append(f"| parametric (Brown-Conrady, {what}) | {p.median_error:.4f} | {p.rms_error:.4f} |"
                    + (f" {t.parametric_median:.4f} | {t.parametric_rms:.4f} |" if t else ""))
        rows.append(f"| generic (all frames) | {g.median_error:.4f} | {g.rms_error:.4f} |"
                    + (f" {t.generic_median:.4f} | {t.generic_rms:.4f} |" if t else ""))
        lines.append("\n".join(rows))
        lines.append(f"generic median error: **{g.median_error:.4f} px** (sharp {g.sharp_median_error:.4f}"
                     + (f", blurry {g.blurry_median_error:.4f} px)" if blurry else " px)"))
        if t is not None:
            lines.append(f"Against the true camera: over {t.pixels} lattice pixels of the calibrated area, "
                         "after the best-fit rotation.")
        rs = result.rolling_shutter
        if rs is not None and rs.message:
            velocity = ", ".join(f"{md(n)} {v:.1f}" for n, v in sorted(rs.velocity_px.items()))
            per_frame = f" Blur velocity per moving frame (px per exposure): {velocity}." if velocity else ""
            lines.append(f"**Rolling shutter**: {md(rs.message)}.{per_frame}")
        if result.parametric_with_blurry:
            lines.append("Fewer than 5 sharp frames: the parametric stage also used the blurry frames' "
                         "kept blocks (without their shifts).")
    used = sorted(n for n, s in statuses.items() if s == "used")
    other = sorted((n, s) for n, s in statuses.items() if s != "used")
    lines.append(f"At the current thresholds: {len(used)} of {count(len(statuses), 'frame')} used.")
    if other:
        lines.append("\n".join(f"- {md(n)}: {md(s)}" for n, s in other))
    if any(s.startswith("dropped by the pre-filter") for _, s in other):
        lines.append("Blurry frames below the σ_major pre-filter are left out: lower it in *Quality "
                     "filter* to use them.")
    return "\n\n".join(lines)


class CalibrationPanel:
    """Run and cancel buttons, progress, summary, the assessment (text, uncertainty and
    cross-validation maps), coverage, residual and difference images, export."""

    def __init__(self, state: AppState, server: viser.ViserServer, runner: CalibrationRunner) -> None:
        self.state = state
        self.server = server
        self.runner = runner
        gui = server.gui
        self.run = gui.add_button("Run calibration", icon=viser.Icon.PLAYER_PLAY,
                                  hint="extract the frames not extracted yet, then the parametric and "
                                       "generic calibration and their assessment")
        self.cancel = gui.add_button("Cancel calibration", icon=viser.Icon.PLAYER_STOP, color="red",
                                     disabled=True)
        self.progress = gui.add_progress_bar(0.0, animated=False)
        self.status = gui.add_markdown("")
        self.summary = gui.add_markdown("")
        self.trust = gui.add_markdown("")
        self.uncertainty = gui.add_image(placeholder("run the calibration"),
                                         label="Projection uncertainty (px)", format="png", visible=False)
        self.cross_validation = gui.add_image(placeholder("run the calibration"),
                                              label="Cross-validation diff (px)", format="png", visible=False)
        self.coverage = gui.add_image(placeholder("no observations yet"), label="Coverage (inputs now)",
                                      format="png")
        self.scope = gui.add_dropdown("Residuals of", options=SCOPES,
                                      hint="the last: the global-shutter camera's residuals, before the "
                                           "rolling-shutter model (when it was modelled)")
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
        self.cancel.on_click(lambda _: self.runner.cancel())
        self.export.on_click(self._on_export)
        self._assessed: tuple[AppCalibration | None, str, np.ndarray | None, np.ndarray | None] | None = None
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

    def _assessment(self, result: AppCalibration | None) -> tuple[str, np.ndarray | None, np.ndarray | None]:
        """The assessment's markdown and its two images (None where there is nothing to show),
        drawn once per calibration."""
        if self._assessed is not None and self._assessed[0] is result:
            return self._assessed[1:]
        text, unc, cv = "", None, None
        if result is not None:
            trust = self.runner.settings.sequence.trust
            text = trust_summary(result, trust.guidance_px)
            unc = uncertainty_image(result)
            diff = result.trust.cross_validation if result.trust is not None else None
            if diff is not None:
                cv = cross_validation_image(diff, result.inputs.image_size)
        self._assessed = (result, text, unc, cv)
        return text, unc, cv

    def _draw(self) -> None:
        progress = self.runner.progress()
        result = self.runner.result
        statuses = self.runner.statuses()
        busy = progress.running
        fresh = self._assessed is None or self._assessed[0] is not result
        with self.server.atomic():  # the words first: the figures below take seconds on a busy machine
            self.run.disabled = busy
            self.cancel.disabled = not busy or progress.cancelling
            self.export.disabled = busy or result is None
            self.progress.value = 100.0 * progress.fraction
            self.progress.animated = busy
            self.status.content = (f"**calibrating**: {progress.label}" if busy
                                   else "drawing the figures…" if fresh and result is not None else "")
            self.summary.content = summary(result, statuses)
        inputs = self.runner.inputs()
        cov = input_coverage(inputs, self.runner.settings.cell_px) if inputs.image_size[0] else None
        coverage = draw_coverage(cov) if cov is not None and cov.total else placeholder("no observations yet")
        residuals = difference = None
        diff_text = ""
        if result is not None:
            view = self.state.view()
            frame = None
            if self.scope.value == SCOPES[1] and view is not None and view.entry.name in result.generic.poses:
                frame = view.entry.name
            before = result.rolling_shutter.global_shutter if result.rolling_shutter is not None else None
            if self.scope.value != SCOPES[2]:
                residuals = residual_image(result, frame, view.image if frame is not None else None)
            elif before is not None:
                residuals = residual_image(result, None, None, before)
            else:
                residuals = placeholder("the rolling shutter was not modelled: one field, all frames")
            difference = difference_image(result)
            mag = np.linalg.norm(result.difference[2], axis=2)
            diff_text = (f"generic minus parametric: median {np.nanmedian(mag):.3f} px, max "
                         f"{np.nanmax(mag):.3f} px over the calibrated area")
        trust_text, uncertainty, cross_validation = self._assessment(result)
        none = placeholder("run the calibration")
        with self.server.atomic():
            if not busy:
                self.status.content = ""
            self.trust.content = trust_text
            if fresh:  # the maps change only with the calibration; hidden when not measured
                for handle, image in ((self.uncertainty, uncertainty),
                                      (self.cross_validation, cross_validation)):
                    if image is not None:
                        set_image(handle, image)
                    handle.visible = image is not None
            set_image(self.coverage, coverage)
            set_image(self.residuals, residuals if residuals is not None else none)
            set_image(self.difference, difference if difference is not None else none)
            self.difference_text.content = diff_text
