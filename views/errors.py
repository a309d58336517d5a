"""Reprojection-error fields of the current frame and of all frames passing the pre-filter, and the
frames' poses in 3D.

The error of a block is, by default, its residual after global alignment (``eq:global_align``):
its star centre minus the frame's translation ``x_G`` minus the projection of its target point
with the reference camera at the fitted pose (:mod:`state.alignment`). The *Error source*
dropdown also offers the estimate minus the ground truth's time-averaged position (simulated
data) and the block's local-alignment disagreement with its neighbours; *auto* takes the first
available of global alignment, ground truth and local alignment.

Errors are drawn as the reference tool draws them: each block's square (or, over all frames,
each image cell, averaging the blocks inside it) is filled with a colour whose hue gives the
error's direction ``a = atan2(e_y, e_x)`` (image y down) as ``(127 + 127 sin a, 127 + 127 cos a,
127)`` and whose brightness gives its length (full brightness at a chosen number of pixels); or
as a quiver of arrows, ``ARROW_PX`` display pixels long at that length.

The 3D scene shows the target page in its plane (``Z = 0``, metres, x right and y down the page)
and a camera frustum per frame pose: the ground truth when there is one, else the poses fitted by
global alignment, else poses solved from the finished frames' star centres with an approximate
camera. Clicking a frustum opens its frame.
"""

from __future__ import annotations

from functools import partial

import cv2
import numpy as np
import viser
import viser.transforms as vtf

from blurcalib.calib import report
from blurcalib.geometry.pose import Pose
from blurcalib.io.record import FrameStatus
from blurcalib.io.text import count
from blurcalib.target.pattern import StarPattern
from state import AppState, Topic
from state.alignment import AlignmentCache, AlignmentError, FrameAlignment
from state.calibration import CalibrationRunner
from state.figures import (
    ERROR_SOURCES,
    ErrorField,
    FramePoses,
    alignment_poses,
    cell_means,
    error_field,
    feature_poses,
    generic_poses,
    truth_poses,
    used_frame_fields,
)
from views.common import SHIFT, Coalescer, fit_width, grey_rgb, label, md, placeholder, scaled, to_draw
from views.frame_view import DISPLAY_WIDTH

WHEEL_PX = 90
ARROW_PX = 40
"""Display length (px) of an arrow whose error is the full-brightness length."""
FRUSTUM_COLOURS = {"sharp": (40, 160, 40), "blurry": (60, 90, 220)}
PAGE_DPI = 40.0
SOURCES = ("auto", *ERROR_SOURCES)
SCOPES = ("current frame", "all frames passing the pre-filter")
STYLES = ("direction colours", "quiver")
DESCRIPTIONS = {
    "global alignment": "star centre minus x_G minus the projection of its target point at the fitted pose",
    "ground truth": "estimate minus the ground truth's time-averaged position",
    "local alignment": "the block's disagreement with its neighbours (minus its local-alignment translation)",
}


def direction_colours(error: np.ndarray, full: float) -> np.ndarray:
    """``(N, 3)`` uint8 RGB: hue from the direction of ``error (N, 2)``, brightness from its length
    (full at ``full`` px)."""
    return np.clip(report.direction_colours(error, max(full, 1e-9)), 0, 255).astype(np.uint8)


def colour_wheel(size: int = WHEEL_PX) -> np.ndarray:
    """The legend: direction as hue around the wheel, length as brightness from the centre."""
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size]
    ex, ey = (xx - c) / c, (yy - c) / c
    rgb = direction_colours(np.stack([ex.ravel(), ey.ravel()], axis=1), 1.0).reshape(size, size, 3)
    rgb[np.hypot(ex, ey) > 1.0] = 0
    return rgb


def _wheel_legend(canvas: np.ndarray, full: float) -> None:
    wheel = colour_wheel()
    h, w = canvas.shape[:2]
    y0, x0 = h - WHEEL_PX - 8, w - WHEEL_PX - 8
    region = canvas[y0:y0 + WHEEL_PX, x0:x0 + WHEEL_PX]
    inside = wheel.any(axis=2)
    region[inside] = wheel[inside]
    label(canvas, f"full = {full:.2g} px", (x0 - 20, y0 - 6), 0.45)
    label(canvas, "+x", (x0 + WHEEL_PX - 16, y0 + WHEEL_PX // 2 + 4), 0.4)
    label(canvas, "+y", (x0 + WHEEL_PX // 2 - 8, y0 + WHEEL_PX - 2), 0.4)


def draw_errors(image: np.ndarray, field: ErrorField, full: float, width: int = DISPLAY_WIDTH) -> np.ndarray:
    """The frame (dimmed) with each block's square filled by its error colour, and the legend."""
    canvas, s = fit_width(grey_rgb(image, 0.3), width)
    canvas = np.ascontiguousarray(canvas)
    for quad, colour in zip(to_draw(field.quad, s), direction_colours(field.error, full), strict=True):
        cv2.fillPoly(canvas, [quad], tuple(int(v) for v in colour), cv2.LINE_AA, SHIFT)
    _wheel_legend(canvas, full)
    return canvas


def _background(image: np.ndarray | None, image_size: tuple[int, int], width: int
                ) -> tuple[np.ndarray, float]:
    """The dimmed frame, or black of the frame's size, resized to ``width``."""
    if image is None:
        image = np.zeros((image_size[1], image_size[0]))
    canvas, s = fit_width(grey_rgb(image, 0.3), width)
    return np.ascontiguousarray(canvas), s


def draw_cells(image_size: tuple[int, int], xy: np.ndarray, error: np.ndarray, full: float, cell_px: int,
               width: int = DISPLAY_WIDTH) -> np.ndarray:
    """Errors of many frames: image cells of ``cell_px`` px filled with the colour of their blocks'
    mean error (black where no block falls), and the legend."""
    canvas, s = _background(None, image_size, width)
    corner, mean, _ = cell_means(xy, error, image_size, cell_px)
    for (x, y), colour in zip(corner, direction_colours(mean, full), strict=True):
        quad = np.array([[x, y], [x + cell_px, y], [x + cell_px, y + cell_px], [x, y + cell_px]]) - 0.5
        cv2.fillPoly(canvas, [to_draw(quad, s)], tuple(int(v) for v in colour), cv2.LINE_AA, SHIFT)
    _wheel_legend(canvas, full)
    return canvas


def draw_quiver(image: np.ndarray | None, image_size: tuple[int, int], xy: np.ndarray, error: np.ndarray,
                full: float, width: int = DISPLAY_WIDTH) -> np.ndarray:
    """Arrows from ``xy (N, 2)`` px along ``error (N, 2)`` px, :data:`ARROW_PX` display pixels long
    at ``full`` px and coloured by direction, over the dimmed frame (black without one)."""
    canvas, s = _background(image, image_size, width)
    start = scaled(xy, s)
    end = start + error * (ARROW_PX / max(full, 1e-9))
    colours = direction_colours(error, 1e-9)
    for a, b, colour in zip(start, end, colours, strict=True):
        cv2.arrowedLine(canvas, tuple(int(v) for v in np.round(a * (1 << SHIFT))),
                        tuple(int(v) for v in np.round(b * (1 << SHIFT))), tuple(int(v) for v in colour), 1,
                        cv2.LINE_AA, SHIFT, 0.25)
    h, w = canvas.shape[:2]
    y = h - 14
    cv2.arrowedLine(canvas, (w - ARROW_PX - 12, y), (w - 12, y), (255, 255, 255), 2, cv2.LINE_AA, 0, 0.25)
    label(canvas, f"{full:.2g} px", (w - ARROW_PX - 80, y + 5), 0.45)
    return canvas


def page_placement(pattern: StarPattern) -> tuple[np.ndarray, float, float]:
    """Centre ``(3,)`` m of the page in target coordinates, and its width and height (m)."""
    page = pattern.page
    centre = pattern.page_mm_to_feature(np.array([page.width_mm / 2, page.height_mm / 2]))
    return np.array([*(centre * pattern.square_length_m), 0.0]), page.width_mm / 1000, page.height_mm / 1000


def add_pose_frustum(scene: viser.SceneApi, name: str, pose: Pose, fov: float, aspect: float, scale: float,
                     colour: tuple[int, int, int], thickness: float = 1.5, image: np.ndarray | None = None
                     ) -> viser.CameraFrustumHandle:
    """A camera frustum at ``pose`` (the scene's frame -> camera, ``X_cam = R X + t``): placed at the
    camera's centre, turned by ``R^T`` (``fov`` rad vertical, ``aspect`` width / height, ``scale`` m)."""
    inv = pose.inverse()
    return scene.add_camera_frustum(name, fov=fov, aspect=aspect, scale=scale, color=colour, image=image,
                                    wxyz=vtf.SO3.from_matrix(inv.R).wxyz, position=inv.t, thickness=thickness,
                                    thickness_units="screen")


class ErrorsPanel:
    """The error field image, its source, scope, style and scale, and the 3D scene of the poses."""

    def __init__(self, state: AppState, server: viser.ViserServer, alignments: AlignmentCache,
                 calibration: CalibrationRunner | None = None) -> None:
        self.state = state
        self.server = server
        self.alignments = alignments
        self.calibration = calibration
        gui = server.gui
        self.image = gui.add_image(placeholder("no result"), label="Error field", format="jpeg",
                                   jpeg_quality=90)
        self.source = gui.add_dropdown("Error source", options=SOURCES,
                                       hint="auto: global alignment when there is a reference camera, "
                                            "else ground truth, else local alignment")
        self.scope = gui.add_dropdown("Over", options=SCOPES)
        self.style = gui.add_dropdown("Draw as", options=STYLES)
        self.auto = gui.add_checkbox("Auto scale (2 × RMS)", initial_value=True)
        self.full = gui.add_slider("Full brightness at (px)", min=0.01, max=2.0, step=0.01, initial_value=0.2)
        self.text = gui.add_markdown("")
        self.poses_text = gui.add_markdown("")
        self._frustums: list[viser.CameraFrustumHandle] = []
        self._target: viser.ImageHandle | None = None
        self._target_of: object = None
        server.scene.set_up_direction("-y")
        self._redraw = Coalescer(self._draw, 0.2, "errors")
        self._rescene = Coalescer(self._draw_scene, 0.5, "poses")
        for control in (self.auto, self.source, self.scope, self.style):
            control.on_update(self._redraw.request)
        self.full.on_update(self._on_full)
        state.subscribe(self._on_change)
        self._redraw.request()
        self._rescene.request()

    def close(self) -> None:
        """Stop the redraw threads."""
        self._redraw.close()
        self._rescene.close()

    def _on_full(self, event: viser.GuiEvent) -> None:
        if event.client is not None:
            self.auto.value = False
            self._redraw.request()

    def _on_change(self, topic: Topic) -> None:
        if topic in (Topic.CURRENT, Topic.RESULT, Topic.FILTER, Topic.FOLDER, Topic.FRAMES):
            self._redraw.request()
        if topic in (Topic.FOLDER, Topic.RESULT, Topic.FILTER, Topic.CURRENT, Topic.CALIBRATION):
            self._rescene.request()

    def _scale(self, error: np.ndarray) -> float:
        if self.auto.value and len(error):
            rms = float(np.sqrt(np.mean(np.sum(error**2, axis=1))))
            self.full.value = float(np.clip(round(2.0 * rms, 2), 0.01, 2.0))
        return self.full.value

    def _draw(self) -> None:
        if self.scope.value == SCOPES[0]:
            self._draw_frame()
        else:
            self._draw_all()

    def _draw_frame(self) -> None:
        view = self.state.view()
        if (view is None or view.image is None or view.result is None
                or view.entry.record.status is FrameStatus.RUNNING):
            self.image.image = placeholder("run the frame to see its error field")
            self.text.content = ""
            return
        alignment: FrameAlignment | None = None
        why = ""
        try:
            alignment = self.alignments.frame(view.entry.name)
        except AlignmentError as exc:
            why = str(exc)
        requested = None if self.source.value == "auto" else self.source.value
        field = error_field(view.result, view.filter, view.truth, alignment, requested)
        if field is None:
            self.image.image = placeholder(f"no {requested or 'error'} field for this frame")
            self.text.content = md(why) if requested == "global alignment" else ""
            return
        full = self._scale(field.error)
        if self.style.value == STYLES[0]:
            self.image.image = draw_errors(view.image, field, full)
        else:
            h, w = view.image.shape
            self.image.image = draw_quiver(view.image, (w, h), field.centre, field.error, full)
        length = np.hypot(field.error[:, 0], field.error[:, 1])
        lines = [f"**{field.source}**{self._reference_note(field.source)}: {DESCRIPTIONS[field.source]}. "
                 f"{count(len(length), 'block')}, RMS {field.rms:.3f} px, median {np.median(length):.3f} px, "
                 f"max {length.max():.3f} px."]
        if field.source == "global alignment":
            lines.append(f"x_G = ({alignment.translation[0]:+.3f}, {alignment.translation[1]:+.3f}) px"
                         + ("" if alignment.orientation_ok else
                            "; **ill-conditioned**: the optical axis is near the target normal"))
        elif why and requested is None:
            lines.append(f"(global alignment not shown: {md(why)})")
        self.text.content = "\n\n".join(lines)

    def _reference_note(self, source: str) -> str:
        if source != "global alignment":
            return ""
        reference = self.alignments.reference().reference
        return f" (reference: {md(reference.source)})" if reference is not None else ""

    def _draw_all(self) -> None:
        requested = None if self.source.value == "auto" else self.source.value
        fields = used_frame_fields(self.state, self.alignments, requested)
        if fields is None:
            reason = self.alignments.reference().reason if requested == "global alignment" else ""
            self.image.image = placeholder(f"no {requested} fields")
            self.text.content = md(reason)
            return
        xy, error = fields.stacked()
        note = f" Left out: {md(fields.note)}." if fields.note else ""
        if not fields.fields:
            self.image.image = placeholder("no frame passing the pre-filter has an error field yet")
            self.text.content = f"**{fields.source}**{self._reference_note(fields.source)}: no frame.{note}"
            return
        full = self._scale(error)
        cell = max(8, round(fields.image_size[0] / 64))
        if self.style.value == STYLES[0]:
            self.image.image = draw_cells(fields.image_size, xy, error, full, cell)
        else:
            cell *= 2
            corner, mean, _ = cell_means(xy, error, fields.image_size, cell)
            self.image.image = draw_quiver(None, fields.image_size, corner + cell / 2 - 0.5, mean, full)
        length = np.hypot(error[:, 0], error[:, 1])
        self.text.content = (
            f"**{fields.source}**{self._reference_note(fields.source)} over "
            f"{count(len(fields.fields), 'frame')} passing the pre-filter: {DESCRIPTIONS[fields.source]}. "
            f"{count(len(length), 'block')}, RMS "
            f"{float(np.sqrt(np.mean(length**2))):.3f} px, median {np.median(length):.3f} px, max "
            f"{length.max():.3f} px. Each {cell} px cell shows the mean of its blocks.{note}")

    def _poses(self) -> FramePoses | None:
        dataset = self.state.dataset
        if dataset is None:
            return None
        result = self.calibration.result if self.calibration is not None else None
        if result is not None:
            return generic_poses(result.generic)
        if dataset.truth is not None:
            return truth_poses(dataset.truth)
        reference = self.alignments.reference().reference
        if reference is not None:
            aligned = {}
            for name in self.state.results():
                try:
                    aligned[name] = self.alignments.frame(name)
                except AlignmentError:
                    continue
            poses = alignment_poses(aligned, reference.camera)
            if poses is not None:
                return poses
        return feature_poses(dataset.pattern, self.state.results())

    def _open_frame(self, name: str, _: viser.SceneNodePointerEvent) -> None:
        names = [e.name for e in self.state.entries()]
        if name in names:
            self.state.select_frame(names.index(name))

    def _draw_scene(self) -> None:
        dataset = self.state.dataset
        scene = self.server.scene
        for handle in self._frustums:
            handle.remove()
        self._frustums = []
        if dataset is None:
            return
        if self._target_of is not dataset.pattern:
            if self._target is not None:
                self._target.remove()
            centre, width, height = page_placement(dataset.pattern)
            page = grey_rgb(dataset.pattern.render_page(PAGE_DPI, supersample=2))
            self._target = scene.add_image("/target", page, width, height, position=centre)
            self._target_of = dataset.pattern
            size = max(width, height)
            self.server.initial_camera.look_at = centre
            self.server.initial_camera.position = centre + np.array([0.35, -0.45, -1.3]) * size
        poses = self._poses()
        if poses is None:
            self.poses_text.content = "3D view: no poses yet (finish a frame with enough blocks)"
            return
        view = self.state.view()
        current = view.entry.name if view is not None else None
        entries = {e.name: e for e in self.state.entries()}
        scale = 4.0 * dataset.pattern.square_length_m
        for i, (name, pose) in enumerate(sorted(poses.poses.items())):
            kind = entries[name].kind if name in entries else "blurry"
            colour = (255, 120, 0) if name == current else FRUSTUM_COLOURS.get(kind, (60, 90, 220))
            thumb = None
            if name == current and view is not None and view.image is not None:
                thumb = fit_width(grey_rgb(view.image), 200)[0]
            frustum = add_pose_frustum(scene, f"/cameras/{i}", pose, poses.fov, poses.aspect, scale, colour,
                                       3.0 if name == current else 1.5, thumb)
            frustum.on_click(partial(self._open_frame, name))
            self._frustums.append(frustum)
        self.poses_text.content = (f"3D view: {count(len(poses.poses), 'frame pose')} from the "
                                   f"**{poses.source}** (orange: current frame, green: sharp, blue: blurry), "
                                   "target page in its plane Z = 0. Click a frustum to open its frame.")
