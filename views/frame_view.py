"""Frame view: the current frame with its blocks drawn over it.

Each block's square ``H([-1, 1]^2)`` is outlined, coloured by its kept/removed status, its loss or
its boundary energy; star centres ``H(0, 0)`` are dots; the tag found by the seeding is outlined
in cyan and the quality filter's breadth-first seed block in magenta; the selected block is
yellow. While a frame runs the blocks appear as the growth decides them.
"""

from __future__ import annotations

import cv2
import numpy as np
import viser

from blurcalib.geometry.homography import homography_centre
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import BlockStatus
from state import AppState, FrameView, Topic
from state.figures import block_quads
from views.common import (
    SEED_COLOUR,
    SELECTED_COLOUR,
    SHIFT,
    STATUS_COLOURS,
    STATUS_LEGEND,
    TAG_COLOUR,
    Coalescer,
    colour_map,
    colourbar_strip,
    dots,
    fit_width,
    grey_rgb,
    label,
    legend_strip,
    placeholder,
    polylines,
    to_draw,
)

COLOUR_MODES = ("kept / removed", "loss", "boundary energy")
CENTRE_COLOUR = (255, 60, 60)
MARK_LEGEND = ((CENTRE_COLOUR, "star centre"), (TAG_COLOUR, "tag"), (SEED_COLOUR, "BFS seed block"),
               (SELECTED_COLOUR, "selected block"))
DISPLAY_WIDTH = 1100


def draw_frame(view: FrameView, mode: str, centres: bool, seeds: bool, width: int = DISPLAY_WIDTH
               ) -> np.ndarray:
    """The overlay image of a frame snapshot (RGB uint8)."""
    if view.image is None:
        return placeholder(f"{view.entry.name}: unreadable")
    canvas, s = fit_width(grey_rgb(view.image, 0.85), width)
    canvas = np.ascontiguousarray(canvas)
    result, flt, q = view.result, view.filter, view.quality
    live = result is None or view.entry.record.status is FrameStatus.RUNNING
    if live:
        if not view.live:
            return canvas
        H = np.stack([e.H for e in view.live])
        status = np.array([e.status.value for e in view.live])
        loss = np.array([e.loss for e in view.live])
        be = np.full(len(H), np.nan)
    else:
        blocks = result.blocks
        if not len(blocks):
            return canvas
        H, loss, be = blocks.H, blocks.loss, blocks.boundary_energy
        status = flt.status.astype(str) if flt is not None else blocks.status
    fitted = status != BlockStatus.OUTSIDE_IMAGE.value
    if mode == "loss":
        colours = colour_map(loss, 0.0, 2.0 * q.tau_loss)
    elif mode == "boundary energy":
        colours = colour_map(be, 0.0, 2.0 * q.tau_be)
    else:
        colours = np.array([STATUS_COLOURS.get(v, (200, 200, 200)) for v in status], dtype=np.uint8)
    quads = block_quads(H)
    line = max(1, round(s))
    polylines(canvas, quads[fitted], colours[fitted], s, line)
    if centres:
        good = (status == BlockStatus.ACCEPTED.value)
        dots(canvas, homography_centre(H[good]), CENTRE_COLOUR, s, line + 1)
    if seeds and result is not None and result.seed is not None and len(result.seed.corners_px):
        corners = to_draw(result.seed.corners_px, s)
        cv2.polylines(canvas, [corners], True, TAG_COLOUR, 2 * line, cv2.LINE_AA, SHIFT)
        top = result.seed.corners_px.min(axis=0)
        label(canvas, f"tag {result.seed.tag_index}", (int(s * top[0]), max(12, int(s * top[1]) - 6)),
              0.45 * max(1.0, s), TAG_COLOUR)
    if seeds and not live and flt is not None and flt.seed >= 0:
        polylines(canvas, quads[[flt.seed]], [SEED_COLOUR], s, 3 * line)
    if not live and view.selected is not None:
        polylines(canvas, quads[[view.selected]], [SELECTED_COLOUR], s, 3 * line)
        c = result.blocks.centre[view.selected]
        label(canvas, f"#{view.selected}", (int(s * c[0]) + 8, int(s * c[1]) - 8), 0.45 * max(1.0, s),
              SELECTED_COLOUR)
    return canvas


class FrameViewPanel:
    """The frame image with overlays, its colour mode and layer switches."""

    def __init__(self, state: AppState, server: viser.ViserServer) -> None:
        self.state = state
        gui = server.gui
        self.image = gui.add_image(placeholder("no frame open"), label="Frame", format="jpeg",
                                   jpeg_quality=85)
        self.mode = gui.add_dropdown("Colour blocks by", options=COLOUR_MODES)
        self.centres = gui.add_checkbox("Star centres", initial_value=True)
        self.seeds = gui.add_checkbox("Tag and BFS seed", initial_value=True)
        self._redraw = Coalescer(self._draw, 0.1, "frame-view")
        for handle in (self.mode, self.centres, self.seeds):
            handle.on_update(self._redraw.request)
        state.subscribe(self._on_change)
        self._redraw.request()

    def close(self) -> None:
        """Stop the redraw thread."""
        self._redraw.close()

    def _on_change(self, topic: Topic) -> None:
        if topic in (Topic.CURRENT, Topic.LIVE, Topic.RESULT, Topic.FILTER, Topic.SELECTION, Topic.FOLDER):
            self._redraw.request()

    def _draw(self) -> None:
        view = self.state.view()
        if view is None:
            self.image.image = placeholder("no frame open")
            return
        canvas = draw_frame(view, self.mode.value, self.centres.value, self.seeds.value)
        q = view.quality
        if self.mode.value == "loss":
            strip = colourbar_strip(canvas.shape[1], 0.0, 2 * q.tau_loss, "loss (grey levels^2)")
        elif self.mode.value == "boundary energy":
            strip = colourbar_strip(canvas.shape[1], 0.0, 2 * q.tau_be, "boundary energy")
        else:
            strip = legend_strip(canvas.shape[1], STATUS_LEGEND)
        marks = legend_strip(canvas.shape[1], MARK_LEGEND)
        self.image.image = np.concatenate([canvas, strip, marks])
