"""Reprojection-error direction field of the current frame, and the frames' poses in 3D.

Each used block's square is filled with a colour whose hue gives the error's direction ``a``
(``atan2(e_y, e_x)`` in the image, y down) as ``(127 + 127 sin a, 127 + 127 cos a, 127)`` and whose
brightness gives its length (full brightness at a chosen number of pixels). The error is the
estimate minus the ground truth's time-averaged position on a simulated dataset, else the
block's local-alignment disagreement with its neighbours (the global-alignment error comes
later).

The 3D scene shows the target page in its plane (``Z = 0``, metres, x right and y down the page)
and a camera frustum per frame pose: the ground truth when there is one, else poses solved
from the finished frames' star centres with an approximate camera.
"""

from __future__ import annotations

import cv2
import numpy as np
import viser
import viser.transforms as vtf

from blurcalib.pattern import StarPattern
from state import AppState, Topic
from state.figures import ErrorField, FramePoses, error_field, feature_poses, truth_poses
from views.common import Coalescer, fit_width, grey_rgb, label, placeholder, to_draw
from views.frame_view import DISPLAY_WIDTH

WHEEL_PX = 90
FRUSTUM_COLOURS = {"sharp": (40, 160, 40), "blurry": (60, 90, 220)}
PAGE_DPI = 40.0


def direction_colours(error: np.ndarray, full: float) -> np.ndarray:
    """``(N, 3)`` uint8 RGB: hue from the direction of ``error (N, 2)``, brightness from its length
    (full at ``full`` px)."""
    a = np.arctan2(error[:, 1], error[:, 0])
    base = np.stack([127 + 127 * np.sin(a), 127 + 127 * np.cos(a), np.full_like(a, 127.0)], axis=1)
    m = np.clip(np.hypot(error[:, 0], error[:, 1]) / max(full, 1e-9), 0.0, 1.0)
    return np.clip(base * m[:, None], 0, 255).astype(np.uint8)


def colour_wheel(size: int = WHEEL_PX) -> np.ndarray:
    """The legend: direction as hue around the wheel, length as brightness from the centre."""
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size]
    ex, ey = (xx - c) / c, (yy - c) / c
    rgb = direction_colours(np.stack([ex.ravel(), ey.ravel()], axis=1), 1.0).reshape(size, size, 3)
    rgb[np.hypot(ex, ey) > 1.0] = 0
    return rgb


def draw_errors(image: np.ndarray, field: ErrorField, full: float, width: int = DISPLAY_WIDTH) -> np.ndarray:
    """The frame (dimmed) with each block's square filled by its error colour, and the legend."""
    canvas, s = fit_width(grey_rgb(image, 0.3), width)
    canvas = np.ascontiguousarray(canvas)
    for quad, colour in zip(to_draw(field.quad, s), direction_colours(field.error, full), strict=True):
        cv2.fillPoly(canvas, [quad], tuple(int(v) for v in colour), cv2.LINE_AA, 4)
    wheel = colour_wheel()
    h, w = canvas.shape[:2]
    y0, x0 = h - WHEEL_PX - 8, w - WHEEL_PX - 8
    region = canvas[y0:y0 + WHEEL_PX, x0:x0 + WHEEL_PX]
    inside = wheel.any(axis=2)
    region[inside] = wheel[inside]
    label(canvas, f"full = {full:.2g} px", (x0 - 20, y0 - 6), 0.45)
    label(canvas, "+x", (x0 + WHEEL_PX - 16, y0 + WHEEL_PX // 2 + 4), 0.4)
    label(canvas, "+y", (x0 + WHEEL_PX // 2 - 8, y0 + WHEEL_PX - 2), 0.4)
    return canvas


def page_placement(pattern: StarPattern) -> tuple[np.ndarray, float, float]:
    """Centre ``(3,)`` m of the page in target coordinates, and its width and height (m)."""
    page = pattern.page
    centre = pattern.page_mm_to_feature(np.array([page.width_mm / 2, page.height_mm / 2]))
    return np.array([*(centre * pattern.square_length_m), 0.0]), page.width_mm / 1000, page.height_mm / 1000


class ErrorsPanel:
    """The error field image, its scale, and the 3D scene of the frames' poses."""

    def __init__(self, state: AppState, server: viser.ViserServer) -> None:
        self.state = state
        self.server = server
        gui = server.gui
        self.image = gui.add_image(placeholder("no result"), label="Error direction field", format="jpeg",
                                   jpeg_quality=90)
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
        self.auto.on_update(self._redraw.request)
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
        if topic in (Topic.CURRENT, Topic.RESULT, Topic.FILTER, Topic.FOLDER):
            self._redraw.request()
        if topic in (Topic.FOLDER, Topic.RESULT, Topic.FILTER, Topic.CURRENT):
            self._rescene.request()

    def _draw(self) -> None:
        view = self.state.view()
        field = None
        if view is not None and view.result is not None and view.entry.status != "running":
            field = error_field(view.result, view.filter, view.truth)
        if view is None or view.image is None or field is None:
            self.image.image = placeholder("run the frame to see its error field")
            self.text.content = ""
            return
        if self.auto.value:
            self.full.value = float(np.clip(round(2.0 * field.rms, 2), 0.01, 2.0))
        self.image.image = draw_errors(view.image, field, self.full.value)
        length = np.hypot(field.error[:, 0], field.error[:, 1])
        what = ("estimate minus the ground truth's time-averaged position" if field.source == "ground truth"
                else "the block's disagreement with its neighbours (minus its local-alignment translation)")
        self.text.content = (f"**{field.source}**: {what}. {len(length)} blocks, RMS {field.rms:.3f} px, "
                             f"median {np.median(length):.3f} px, max {length.max():.3f} px. Hue: direction, "
                             "brightness: length.")

    def _poses(self) -> FramePoses | None:
        dataset = self.state.dataset
        if dataset is None:
            return None
        if dataset.truth is not None:
            return truth_poses(dataset.truth)
        return feature_poses(dataset.pattern, self.state.results())

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
            inv = pose.inverse()
            kind = entries[name].kind if name in entries else "blurry"
            colour = (255, 120, 0) if name == current else FRUSTUM_COLOURS.get(kind, (60, 90, 220))
            thumb = None
            if name == current and view is not None and view.image is not None:
                thumb = fit_width(grey_rgb(view.image), 200)[0]
            self._frustums.append(scene.add_camera_frustum(
                f"/cameras/{i}", fov=poses.fov, aspect=poses.aspect, scale=scale, color=colour,
                image=thumb, wxyz=vtf.SO3.from_matrix(inv.R).wxyz, position=inv.t,
                thickness=3.0 if name == current else 1.5, thickness_units="screen"))
        self.poses_text.content = (f"3D view: {len(poses.poses)} frame poses from the **{poses.source}** "
                                   "(orange: current frame, green: sharp, blue: blurry), target page in its "
                                   "plane Z = 0")
