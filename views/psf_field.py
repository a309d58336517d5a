"""PSF field: every block's PSF drawn at its place in the image, over the dimmed frame.

Each kernel is scaled to its own peak, coloured (inferno) and resized to a tile of a chosen
share of the block's square side, centred on the block's star centre. The mosaic shows how the
blur changes across the frame (rotation, roll and zoom blur make it vary).
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
from views.common import Coalescer, fit_width, grey_rgb, heat, placeholder, scaled
from views.frame_view import DISPLAY_WIDTH

SHOW = ("kept blocks", "all fitted blocks")


def psf_mosaic(view: FrameView, tile: float, show: str, width: int = DISPLAY_WIDTH) -> np.ndarray:
    """The PSF-field image of a frame snapshot (RGB uint8)."""
    if view.image is None:
        return placeholder(f"{view.entry.name}: unreadable")
    canvas, s = fit_width(grey_rgb(view.image, 0.3), width)
    canvas = np.ascontiguousarray(canvas)
    result = view.result
    if result is None or view.entry.record.status is FrameStatus.RUNNING:
        items = [(e.H, e.psf) for e in view.live if e.status is BlockStatus.ACCEPTED]
    else:
        blocks = result.blocks
        use = view.filter.kept if show == SHOW[0] and view.filter is not None else np.isfinite(blocks.loss)
        items = list(zip(blocks.H[use], blocks.psf[use], strict=True))
    if not items:
        return canvas
    H = np.stack([h for h, _ in items])
    quads = block_quads(H)
    d1, d2 = quads[:, 2] - quads[:, 0], quads[:, 3] - quads[:, 1]
    side = np.sqrt(0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])) * s
    centres = scaled(homography_centre(H), s)
    h, w = canvas.shape[:2]
    for (_, psf), c, a in zip(items, centres, side, strict=True):
        n = max(3, round(tile * a))
        if not np.all(np.isfinite(psf)) or not np.isfinite(c).all():
            continue
        patch = cv2.resize(heat(psf), (n, n), interpolation=cv2.INTER_LINEAR)
        x0, y0 = round(c[0] - n / 2), round(c[1] - n / 2)
        xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + n, w), min(y0 + n, h)
        if xa >= xb or ya >= yb:
            continue
        region = canvas[ya:yb, xa:xb]
        np.maximum(region, patch[ya - y0:yb - y0, xa - x0:xb - x0], out=region)
    return canvas


class PsfFieldPanel:
    """The PSF mosaic of the current frame."""

    def __init__(self, state: AppState, server: viser.ViserServer) -> None:
        self.state = state
        gui = server.gui
        self.image = gui.add_image(placeholder("no frame open"), label="PSF field", format="jpeg",
                                   jpeg_quality=90)
        self.show = gui.add_dropdown("Show", options=SHOW)
        self.tile = gui.add_slider("Tile size (squares)", min=0.4, max=2.0, step=0.05, initial_value=0.9)
        gui.add_markdown("Each block's PSF, scaled to its own peak (inferno), drawn at the block's star "
                         "centre; the tile is a share of the block's square side.")
        self._redraw = Coalescer(self._draw, 0.1, "psf-field")
        self.show.on_update(self._redraw.request)
        self.tile.on_update(self._redraw.request)
        state.subscribe(self._on_change)
        self._redraw.request()

    def close(self) -> None:
        """Stop the redraw thread."""
        self._redraw.close()

    def _on_change(self, topic: Topic) -> None:
        if topic in (Topic.CURRENT, Topic.LIVE, Topic.RESULT, Topic.FILTER, Topic.FOLDER):
            self._redraw.request()

    def _draw(self) -> None:
        view = self.state.view()
        self.image.image = (placeholder("no frame open") if view is None
                            else psf_mosaic(view, self.tile.value, self.show.value))
