"""The rig view: a calibrated rig's cameras and image sets in 3D, each camera's reprojection errors,
and a pair's rectified image set with its epipolar lines and error.

The logic is :mod:`state.rig`; this module draws with cv2 into RGB images, the error fields with
the Errors tab's helpers (:func:`views.errors.draw_cells`, :func:`views.errors.draw_quiver`:
direction colours, full brightness at twice the camera's RMS) and the frustums with
:func:`views.errors.add_pose_frustum`. The 3D scene is in the rig's frame (camera 0's, metres, y
down): one frustum per camera at its ``camera_tr_rig``, labelled ``cam0``, ``cam1``, ..., and the
target's points of each image set at its ``rig_tr_global`` (the chosen set in orange).
"""

from __future__ import annotations

import threading

import cv2
import numpy as np
import viser

from blurcalib.io.text import count
from state.figures import vertical_fov
from state.rig import RectifiedSet, RigOutputError, RigState
from views.common import Coalescer, fit_width, grey_rgb, hstack, md, placeholder, set_image, titled
from views.errors import add_pose_frustum, draw_cells, draw_quiver
from views.frame_view import DISPLAY_WIDTH

SCOPES = ("all image sets", "chosen image set")
CAMERA_COLOURS = ((220, 40, 40), (40, 120, 220), (40, 170, 60), (200, 120, 0))
SET_COLOUR, CHOSEN_COLOUR = (120, 120, 160), (255, 120, 0)
LINE_COLOUR, FEATURE_COLOUR = (0, 200, 220), (255, 230, 0)
EPIPOLAR_LINES = 16
"""Epipolar lines drawn across each rectified image."""


def summary(rig: RigState) -> str:
    """The rig in words: folder, cameras (frames and errors from ``report.json``), pairs, sets."""
    out = rig.output
    lines = [f"**Rig** {md(str(out.folder))}: {count(out.rig.size, 'camera')}, "
             f"{count(sum(p is not None for p in out.rig_tr_global), 'image set')}."]
    for cam in out.cameras:
        r = cam.report
        figures = (f"{r['frames']} frames ({r.get('blurry_frames', 0)} blurry), rig bundle median "
                   f"{r['rig_median_px']:.4f} px" if "rig_median_px" in r and "frames" in r else "")
        lines.append(f"- cam{cam.index}: {md(cam.source) or 'input not named'}"
                     + (f"; {figures}" if figures else ""))
    for pair in out.report.get("pairs", []):
        i, j = pair["cameras"]
        held = pair.get("holdout_error_px")
        lines.append(f"- cam{j} <- cam{i}: baseline {pair['baseline_mm']:.3f} mm"
                     + (f", held-out error {held:.4f} px" if held is not None else ""))
    if out.set_names is None:
        lines.append("The folder does not name its image sets: they are numbered, without features or "
                     "frames.")
    return "\n".join(lines)


def camera_errors_image(rig: RigState, c: int, set_name: str | None) -> tuple[np.ndarray, str]:
    """Camera ``c``'s reprojection errors in the rig, over all its image sets (mean per cell) or
    over ``set_name``'s frame (arrows at its features), and the text under it."""
    res = rig.residuals(c)
    cam = rig.output.rig.cameras[c]
    size = (cam.width, cam.height)
    if not len(res.xy):
        return placeholder(f"cam{c}: no features in the rig's image sets"), ""
    full = max(2.0 * res.stats[1], 1e-3)
    if set_name is None:
        image = draw_cells(size, res.xy, res.residual, full, max(8, round(size[0] / 64)))
        chosen, where = res, f"over {count(len(set(res.set_name.tolist())), 'image set')}"
    else:
        chosen = res.select(res.set_name == set_name)
        if not len(chosen.xy):
            return placeholder(f"cam{c} has no features of {set_name}"), ""
        image = draw_quiver(rig.frame(c, set_name), size, chosen.xy, chosen.residual, full)
        where = f"in {md(set_name)}"
    median, rms, worst = chosen.stats
    blurry = " (blurry frames: their median taken out, as the rig bundle's free image shift)" \
        if chosen.blurry.any() else ""
    text = (f"**cam{c}** reprojection error in the rig {where}: {count(len(chosen.xy), 'feature')}, median "
            f"{median:.4f} px, RMS {rms:.4f} px, max {worst:.4f} px{blurry}.")
    return image, text


def camera_sets_table(rig: RigState, c: int) -> str:
    """Camera ``c``'s image sets: features and median reprojection error (px) of each."""
    res = rig.residuals(c)
    rows = ["| image set | features | median (px) |", "|---|---|---|"]
    for name in rig.set_labels:
        rows_of = res.set_name == name
        n = int(rows_of.sum())
        median = res.select(rows_of).stats[0] if n else float("nan")
        rows.append(f"| {md(name)} | {n} | {'-' if not n else f'{median:.4f}'} |")
    return "\n".join(rows)


def _rectified_side(image: np.ndarray | None, points: np.ndarray, size: tuple[int, int], axis: int,
                    note: str) -> np.ndarray:
    """One rectified image (dimmed; dark grey with ``note`` when missing) with its epipolar lines
    and the set's features."""
    w, h = size
    canvas = grey_rgb(image, 0.8) if image is not None else placeholder(note, (w, h))
    canvas = np.ascontiguousarray(canvas)
    across = h if axis == 0 else w
    for k in range(1, EPIPOLAR_LINES):
        v = round(k * across / EPIPOLAR_LINES)
        ends = ((0, v), (w - 1, v)) if axis == 0 else ((v, 0), (v, h - 1))
        cv2.line(canvas, ends[0], ends[1], LINE_COLOUR, 1, cv2.LINE_AA)
    for x, y in points[np.all(np.isfinite(points), axis=1)]:
        cv2.circle(canvas, (round(x), round(y)), 2, FEATURE_COLOUR, -1, cv2.LINE_AA)
    return canvas


def draw_rectified(view: RectifiedSet, width: int = DISPLAY_WIDTH) -> np.ndarray:
    """Both cameras' frames of the set in the pair's rectified images, side by side, with epipolar
    lines (rows, or columns for a vertical pair) and the features both cameras see."""
    rect = view.pair.rectification
    size = (rect.output.width, rect.output.height)
    sides = []
    for k, (c, points) in enumerate(((view.pair.i, view.epipolar.rectified1),
                                     (view.pair.j, view.epipolar.rectified2))):
        side = _rectified_side(view.images[k], points, size, rect.axis, f"cam{c}: frame not available")
        sides.append(titled(side, f"cam{c}, rectified"))
    both = hstack(sides)
    return fit_width(both, width)[0] if both.shape[1] > width else both


def epipolar_text(view: RectifiedSet) -> str:
    """The set's epipolar error in words, and why frames are missing."""
    median, rms, worst = view.epipolar.stats
    n = int(np.isfinite(view.epipolar.error).sum())
    direction = "rows" if view.pair.rectification.axis == 0 else "columns"
    lines = [f"**Epipolar error of {md(view.set_name)}** (cam{view.pair.i} - cam{view.pair.j}): "
             + (f"{count(n, 'feature')} both cameras see, median {median:.4f} px, RMS {rms:.4f} px, max "
                f"{worst:.4f} px: how far apart their rectified {direction} are." if n else
                "no feature that both cameras see in this set.")]
    if view.blurry and n:
        lines.append("A frame of this set is blurry: its image shift, free in the rig bundle, is in this "
                     "error.")
    if view.missing:
        lines.append(f"Frames not shown: {md(view.missing)}.")
    return "\n\n".join(lines)


class RigPanel:
    """The rig's summary, camera, image set and pair choices, its 3D scene and, in ``views``' tabs,
    the camera's errors and the pair's rectified set."""

    def __init__(self, rig: RigState, server: viser.ViserServer, views: viser.GuiTabGroupHandle) -> None:
        self.rig = rig
        self.server = server
        gui = server.gui
        self.summary = gui.add_markdown(summary(rig))
        self.camera = gui.add_dropdown("Camera", options=rig.camera_labels)
        self.image_set = gui.add_dropdown("Image set", options=rig.set_labels or ["none"])
        self.pair = gui.add_dropdown("Pair", options=rig.pair_labels or ["none"])
        self.scope = gui.add_dropdown("Errors over", options=SCOPES)
        self.scene_text = gui.add_markdown("")
        with views.add_tab("Camera errors", viser.Icon.ARROWS_MOVE):
            self.errors_image = gui.add_image(placeholder("loading"), label="Reprojection error",
                                              format="jpeg", jpeg_quality=90)
            self.errors_text = gui.add_markdown("")
            self.sets_table = gui.add_markdown("")
        with views.add_tab("Rectified pair", viser.Icon.CAMERA):
            self.pair_image = gui.add_image(placeholder("loading"), label="Rectified image set",
                                            format="jpeg", jpeg_quality=90)
            self.pair_text = gui.add_markdown("")
        self._scene_handles: list[object] = []
        self._lock = threading.Lock()  # one drawing at a time: the redraw threads and direct calls
        server.scene.set_up_direction("-y")
        self._redraw_errors = Coalescer(self.draw_errors, 0.2, "rig errors")
        self._redraw_pair = Coalescer(self.draw_pair, 0.2, "rig pair")
        self._redraw_scene = Coalescer(self.draw_scene, 0.3, "rig scene")
        self.camera.on_update(self._redraw_errors.request)
        self.scope.on_update(self._redraw_errors.request)
        self.pair.on_update(self._redraw_pair.request)
        for redraw in (self._redraw_errors, self._redraw_pair, self._redraw_scene):
            self.image_set.on_update(redraw.request)
            redraw.request()

    def close(self) -> None:
        """Stop the redraw threads."""
        for redraw in (self._redraw_errors, self._redraw_pair, self._redraw_scene):
            redraw.close()

    def _set_name(self) -> str | None:
        return self.image_set.value if self.image_set.value in self.rig.set_labels else None

    def draw_errors(self) -> None:
        """The chosen camera's error field and its image sets."""
        with self._lock:
            self._draw_errors()

    def draw_pair(self) -> None:
        """The chosen pair's rectified image set, or why it cannot be shown."""
        with self._lock:
            self._draw_pair()

    def draw_scene(self) -> None:
        """The cameras' frustums and labels and each image set's target points, in the rig's frame."""
        with self._lock:
            self._draw_scene()

    def _draw_errors(self) -> None:
        c = self.rig.camera_labels.index(self.camera.value)
        chosen = self._set_name() if self.scope.value == SCOPES[1] else None
        image, text = camera_errors_image(self.rig, c, chosen)
        set_image(self.errors_image, image)
        self.errors_text.content = text
        self.sets_table.content = camera_sets_table(self.rig, c)

    def _draw_pair(self) -> None:
        name = self._set_name()
        if self.pair.value not in self.rig.pair_labels or name is None:
            set_image(self.pair_image, placeholder("no pair of cameras" if name else "no image set"))
            self.pair_text.content = ""
            return
        try:
            view = self.rig.rectified(self.rig.pair_labels.index(self.pair.value), name)
        except RigOutputError as exc:
            set_image(self.pair_image, placeholder("rectification maps unreadable"))
            self.pair_text.content = md(str(exc))
            return
        set_image(self.pair_image, draw_rectified(view))
        self.pair_text.content = epipolar_text(view)

    def _draw_scene(self) -> None:
        scene, out = self.server.scene, self.rig.output
        for handle in self._scene_handles:
            handle.remove()  # type: ignore[attr-defined]
        self._scene_handles = []
        clouds = [(s, self.rig.set_points(s)) for s in range(len(out.rig_tr_global))]
        placed = [(s, p) for s, p in clouds if p is not None and len(p)]
        baseline = max((float(np.linalg.norm(p.t)) for p in out.rig.camera_tr_rig), default=0.0)
        extent = max((float(np.ptp(p, axis=0).max()) for _, p in placed), default=0.1)
        scale = max(0.4 * baseline, 0.1 * extent, 0.01)
        for c, pose in enumerate(out.rig.camera_tr_rig):
            camera = out.rig.cameras[c]
            fov, aspect = vertical_fov(camera), camera.width / camera.height
            colour = CAMERA_COLOURS[c % len(CAMERA_COLOURS)]
            self._scene_handles.append(add_pose_frustum(scene, f"/rig/cam{c}", pose, fov, aspect, scale,
                                                        colour, 2.5))
            self._scene_handles.append(scene.add_label(f"/rig/cam{c}_label", f"cam{c}",
                                                       position=pose.inverse().t, anchor="bottom-center"))
        chosen = self.image_set.value
        spacing = extent / max(np.sqrt(len(out.points)), 1.0)
        for s, points in placed:
            colour = CHOSEN_COLOUR if self.rig.set_labels[s] == chosen else SET_COLOUR
            size = spacing * (0.25 if colour == CHOSEN_COLOUR else 0.12)
            self._scene_handles.append(scene.add_point_cloud(f"/sets/{s}", points, colour, point_size=size,
                                                             point_shape="circle"))
        if placed:
            centre = np.mean([p.mean(axis=0) for _, p in placed], axis=0)
            reach = max(float(np.linalg.norm(centre)), extent)
            self.server.initial_camera.look_at = centre
            self.server.initial_camera.position = centre + np.array([0.6, -0.8, -1.8]) * reach
        self.scene_text.content = (f"3D view, the rig's frame (cam0's, metres): "
                                   f"{count(out.rig.size, 'camera')} at their camera_tr_rig poses and the "
                                   f"target's points of "
                                   f"{count(len(placed), 'image set')} (orange: the chosen set).")

