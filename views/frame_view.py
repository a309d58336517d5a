"""Frame view: the current frame with its blocks drawn over it.

Each block's square ``H([-1, 1]^2)`` is outlined, coloured by its kept/removed status, its loss or
its boundary energy (blocks never fitted, their square leaving the image, in grey where in view);
star centres ``H(0, 0)`` are dots; the tag found by the seeding is outlined in cyan and the
quality filter's breadth-first seed block in magenta; the selected block is yellow. While a frame
runs the blocks appear as the growth decides them. A frame that was not seeded shows where the
tag search looked instead (:mod:`state.seeding`): the tags it decoded (not the pattern's) and
the candidate quads the detector rejected.

A click on a block in the image selects it for the block inspector (the page relays the click,
:mod:`views.browser`); a pixel typed into *Block at (px)* does the same.
"""

from __future__ import annotations

import cv2
import numpy as np
import viser

from blurcalib.geometry.homography import homography_centre
from blurcalib.growth.seed import TagSearch
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import BlockStatus
from state import AppState, FrameView, Topic
from state.blocks import block_at, block_quads
from state.seeding import TagSearchCache
from views.browser import CLICK_FIELD, CLICK_MARK, parse_click
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
    md,
    placeholder,
    polylines,
    to_draw,
)

COLOUR_MODES = ("kept / removed", "loss", "boundary energy")
CENTRE_COLOUR = (255, 60, 60)
MARK_LEGEND = ((CENTRE_COLOUR, "star centre"), (TAG_COLOUR, "tag"), (SEED_COLOUR, "BFS seed block"),
               (SELECTED_COLOUR, "selected block"))
CANDIDATE_COLOUR = (255, 150, 0)
OTHER_TAG_COLOUR = (230, 40, 40)
SEARCH_LEGEND = ((CANDIDATE_COLOUR, "quad the tag detector rejected"),
                 (OTHER_TAG_COLOUR, "a tag not of the pattern"))
DISPLAY_WIDTH = 1100
FRAME_LABEL = f"Frame · {CLICK_MARK}"


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
    outside = ~fitted & np.all(np.isfinite(quads), axis=(1, 2))
    polylines(canvas, quads[outside], np.full((int(outside.sum()), 3), 120, np.uint8), s, 1)
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


def draw_search(image: np.ndarray, search: TagSearch, width: int = DISPLAY_WIDTH) -> np.ndarray:
    """A frame that was not seeded, with the tag search's findings over it: the quads the
    detector rejected (orange) and the tags it decoded that are not the pattern's (red, with
    their id)."""
    canvas, s = fit_width(grey_rgb(image, 0.85), width)
    canvas = np.ascontiguousarray(canvas)
    if len(search.rejected):
        polylines(canvas, search.rejected, [CANDIDATE_COLOUR] * len(search.rejected), s, max(1, round(s)))
    for tag, corners in search.found.items():
        polylines(canvas, corners[None], [OTHER_TAG_COLOUR], s, 2 * max(1, round(s)))
        top = corners.min(axis=0)
        label(canvas, f"tag {tag}", (int(s * top[0]), max(12, int(s * top[1]) - 6)), 0.5, OTHER_TAG_COLOUR)
    return canvas


def search_caption(search: TagSearch, pattern_tags: list[int], message: str) -> str:
    """Markdown: where the tag search looked and what it found, and the seeding's own message."""
    scales = ", ".join(f"{v:g}" for v in search.scales)
    found = (f"it decoded tag {', '.join(str(t) for t in sorted(search.found))}, not the pattern's "
             if search.found else "it decoded no tag; ")
    return (f"**Not seeded.** The tag search looked over the whole frame at scales {scales} (and in "
            f"deblurred copies) for tag {', '.join(str(t) for t in pattern_tags)}: {found}"
            f"the detector rejected {len(search.rejected)} candidate quads (orange: a quad whose cells "
            f"did not decode, such as a tag partly hidden). {md(message)}")


class FrameViewPanel:
    """The frame image with overlays, its colour mode and layer switches, and the block picker."""

    def __init__(self, state: AppState, server: viser.ViserServer, searches: TagSearchCache | None = None
                 ) -> None:
        self.state = state
        self.searches = searches or TagSearchCache(state)
        gui = server.gui
        self.image = gui.add_image(placeholder("no frame open"), label=FRAME_LABEL, format="jpeg",
                                   jpeg_quality=85)
        self.caption = gui.add_markdown("")
        self.pick = gui.add_text(CLICK_FIELD, initial_value="",
                                 hint="click a block in the frame, or type a pixel x, y: the block there "
                                      "opens in the Block tab")
        self.picked = gui.add_markdown("")
        self.mode = gui.add_dropdown("Colour blocks by", options=COLOUR_MODES)
        self.centres = gui.add_checkbox("Star centres", initial_value=True)
        self.seeds = gui.add_checkbox("Tag and BFS seed", initial_value=True)
        self._layout: tuple[int, int, int, float] | None = None  # drawn (height, width), frame rows, scale
        self._redraw = Coalescer(self._draw, 0.1, "frame-view")
        for handle in (self.mode, self.centres, self.seeds):
            handle.on_update(self._redraw.request)
        self.pick.on_update(self._on_pick)
        state.subscribe(self._on_change)
        self._redraw.request()

    def _on_pick(self, event: viser.GuiEvent) -> None:
        if event.client is None:
            return
        text = self.pick.value.strip()
        point = self.image_point(text)
        if point is None:
            if text:
                self.picked.content = f"*{md(text)}*: not a pixel (type x, y) or a click on the frame"
            return
        view = self.state.view()
        if view is None or view.result is None or not len(view.result.blocks):
            self.picked.content = "no blocks in this frame yet: run it first"
            return
        index = block_at(view.result.blocks, point)
        x, y = point
        self.pick.value = f"{x:.0f}, {y:.0f}"
        if index is None:
            self.picked.content = f"no block at ({x:.0f}, {y:.0f}) px"
            return
        self.state.select_block(index)
        self.picked.content = (f"block **#{index}** at ({x:.0f}, {y:.0f}) px: open the **Block** tab to "
                               "inspect it")

    def image_point(self, text: str) -> tuple[float, float] | None:
        """The frame pixel of a relayed click (fractions of the drawn image) or of a typed
        ``x, y``; None for anything else (or a click on the legends)."""
        click = parse_click(text)
        if click is not None:
            if self._layout is None:
                return None
            height, width, rows, s = self._layout
            px, py = click[0] * width, click[1] * height
            if py >= rows:
                return None
            return (px + 0.5) / s - 0.5, (py + 0.5) / s - 0.5
        try:
            x, y = (float(v) for v in text.replace(";", ",").split(","))
        except ValueError:
            return None
        return (x, y) if np.isfinite(x) and np.isfinite(y) else None

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
            self._layout = None
            return
        search = self.searches.search(view.entry.name) if view.image is not None else None
        if search is not None:
            canvas = draw_search(view.image, search)
            strip = legend_strip(canvas.shape[1], SEARCH_LEGEND)
            self.caption.content = search_caption(search, [t.index for t in view.pattern.apriltags],
                                                  view.entry.record.message)
            self._layout = None
            self.image.image = np.concatenate([canvas, strip])
            return
        self.caption.content = ""
        canvas = draw_frame(view, self.mode.value, self.centres.value, self.seeds.value)
        s = canvas.shape[1] / view.image.shape[1] if view.image is not None else 1.0
        q = view.quality
        if self.mode.value == "loss":
            strip = colourbar_strip(canvas.shape[1], 0.0, 2 * q.tau_loss, "loss (grey levels^2)")
        elif self.mode.value == "boundary energy":
            strip = colourbar_strip(canvas.shape[1], 0.0, 2 * q.tau_be, "boundary energy")
        else:
            strip = legend_strip(canvas.shape[1], STATUS_LEGEND)
        marks = legend_strip(canvas.shape[1], MARK_LEGEND)
        drawn = np.concatenate([canvas, strip, marks])
        self._layout = (drawn.shape[0], drawn.shape[1], canvas.shape[0], s)
        self.image.image = drawn
