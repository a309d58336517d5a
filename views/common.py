"""Helpers shared by the panels: a coalescing redraw thread and small drawing utilities.

Drawing happens with cv2 (or matplotlib Agg) into RGB ``uint8`` arrays, which the panels push to
viser image handles; viser encodes them in the calling thread and sends only the latest image.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np
import viser
from matplotlib import colormaps

from blurcalib.io.results import BlockStatus

log = logging.getLogger(__name__)

STATUS_COLOURS: dict[str, tuple[int, int, int]] = {
    BlockStatus.ACCEPTED.value: (60, 205, 60),
    BlockStatus.FILTERED_LOSS.value: (255, 150, 0),
    BlockStatus.FILTERED_BOUNDARY_ENERGY.value: (190, 70, 255),
    BlockStatus.DISCONNECTED.value: (70, 170, 255),
    BlockStatus.HIGH_LOSS.value: (230, 40, 40),
    BlockStatus.PSF_TRUNCATED.value: (230, 40, 40),
    BlockStatus.NOT_CONVERGED.value: (230, 40, 40),
    BlockStatus.OUTSIDE_IMAGE.value: (120, 120, 120),
    BlockStatus.DEGENERATE_HOMOGRAPHY.value: (120, 120, 120),
}
"""RGB outline colour of a block by its (filtered) status: green kept, orange removed by loss,
purple removed by boundary energy, blue disconnected, red rejected by growth, grey not fitted."""

STATUS_LEGEND: tuple[tuple[tuple[int, int, int], str], ...] = (
    (STATUS_COLOURS[BlockStatus.ACCEPTED.value], "kept"),
    (STATUS_COLOURS[BlockStatus.FILTERED_LOSS.value], "loss > tau_L"),
    (STATUS_COLOURS[BlockStatus.FILTERED_BOUNDARY_ENERGY.value], "BE > tau_BE"),
    (STATUS_COLOURS[BlockStatus.DISCONNECTED.value], "not connected"),
    (STATUS_COLOURS[BlockStatus.HIGH_LOSS.value], "rejected by growth"),
    (STATUS_COLOURS[BlockStatus.OUTSIDE_IMAGE.value], "not fitted"),
)
SELECTED_COLOUR = (255, 230, 0)
SEED_COLOUR = (255, 0, 220)
TAG_COLOUR = (0, 230, 230)


class Coalescer:
    """Runs ``fn`` in its own thread after requests, at most once per ``min_interval`` seconds.

    Requests that arrive while ``fn`` runs or waits collapse into one more call, so a burst of
    changes (growth events, slider drags) costs one redraw with the latest state.
    """

    def __init__(self, fn: Callable[[], None], min_interval: float = 0.1, name: str = "redraw") -> None:
        self._fn = fn
        self._interval = min_interval
        self._wake = threading.Event()
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def request(self, *_: object) -> None:
        """Ask for a call (cheap; safe from any thread)."""
        self._wake.set()

    def close(self) -> None:
        """Stop the thread (a call in progress finishes first)."""
        self._stopped.set()
        self._wake.set()
        self._thread.join(timeout=5.0)

    def _loop(self) -> None:
        while True:
            self._wake.wait()
            if self._stopped.is_set():
                return
            self._wake.clear()
            t0 = time.monotonic()
            try:
                self._fn()
            except Exception:
                log.exception("redraw failed")
            if self._stopped.wait(max(0.0, self._interval - (time.monotonic() - t0))):
                return


def set_image(handle: viser.GuiImageHandle, image: np.ndarray) -> bool:
    """Show ``image`` in ``handle`` unless it shows that image already; True when sent.

    Every assignment sends the image again and the browser swaps the image's blob URL; an image
    sent again unchanged on each redraw (a coverage map redrawn with every progress step) made the
    browser revoke a blob it was still loading on a busy machine (``ERR_FILE_NOT_FOUND`` in its
    console)."""
    shown = handle.image
    if shown is not None and shown.shape == image.shape and np.array_equal(shown, image):
        return False
    handle.image = image
    return True


def md(text: str) -> str:
    """Text safe inside markdown (paths contain underscores and stars)."""
    return text.replace("\\", "\\\\").replace("_", "\\_").replace("*", "\\*").replace("|", "\\|")


def grey_rgb(image: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """``(H, W)`` grey levels 0..255 -> ``(H, W, 3)`` uint8 RGB, multiplied by ``gain``."""
    grey = np.clip(np.asarray(image, dtype=np.float32) * gain, 0, 255).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def fit_width(image: np.ndarray, width: int) -> tuple[np.ndarray, float]:
    """Resize to ``width`` px wide; returns the image and the scale ``s`` (pixel ``x`` maps to
    ``s (x + 0.5) - 0.5``)."""
    s = width / image.shape[1]
    if s == 1.0:
        return image, 1.0
    size = (width, round(image.shape[0] * s))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR), s


SHIFT = 4
"""Fractional bits of cv2 drawing coordinates."""


def scaled(points: np.ndarray, s: float) -> np.ndarray:
    """Image px ``(..., 2)`` -> px of the image resized by ``s``."""
    return s * (np.asarray(points, dtype=np.float64) + 0.5) - 0.5


def to_draw(points: np.ndarray, s: float) -> np.ndarray:
    """Image px ``(..., 2)`` -> int32 cv2 drawing coordinates in an image resized by ``s``."""
    p = scaled(points, s)
    return np.round(np.nan_to_num(p, nan=-1e4, posinf=1e4, neginf=-1e4) * (1 << SHIFT)).astype(np.int32)


def polylines(canvas: np.ndarray, quads: np.ndarray, colours: np.ndarray | list, s: float,
              thickness: int = 1) -> None:
    """Draw closed polygons ``quads (N, 4, 2)`` (image px) with one RGB colour each."""
    pts = to_draw(quads, s)
    for quad, colour in zip(pts, colours, strict=True):
        cv2.polylines(canvas, [quad], True, tuple(int(c) for c in colour), thickness, cv2.LINE_AA, SHIFT)


def dots(canvas: np.ndarray, points: np.ndarray, colour: tuple[int, int, int], s: float,
         radius: int = 2) -> None:
    """Filled dots at image px ``points (N, 2)``."""
    for p in to_draw(points, s):
        cv2.circle(canvas, (int(p[0]), int(p[1])), radius << SHIFT, colour, -1, cv2.LINE_AA, SHIFT)


def colour_map(values: np.ndarray, lo: float, hi: float, name: str = "viridis") -> np.ndarray:
    """``(N, 3)`` uint8 RGB of ``values`` mapped linearly from ``[lo, hi]`` (clipped); NaN grey."""
    v = np.asarray(values, dtype=np.float64)
    t = np.clip((v - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    rgb = (colormaps[name](np.nan_to_num(t))[:, :3] * 255).astype(np.uint8)
    rgb[~np.isfinite(v)] = 120
    return rgb


def heat(image: np.ndarray, name: str = "inferno") -> np.ndarray:
    """``(H, W)`` values -> ``(H, W, 3)`` uint8 RGB, scaled to the image's own maximum."""
    v = np.nan_to_num(np.asarray(image, dtype=np.float64))
    top = v.max()
    t = v / top if top > 0 else v
    return (colormaps[name](np.clip(t, 0, 1))[..., :3] * 255).astype(np.uint8)


def placeholder(text: str, size: tuple[int, int] = (640, 360)) -> np.ndarray:
    """A dark grey image ``(width, height)`` with a centred line of text."""
    w, h = size
    canvas = np.full((h, w, 3), 48, np.uint8)
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.7, 1)
    cv2.putText(canvas, text, ((w - tw) // 2, (h + th) // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.7,
                (220, 220, 220), 1, cv2.LINE_AA)
    return canvas


def label(canvas: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.5,
          colour: tuple[int, int, int] = (255, 255, 255)) -> None:
    """Text with a dark outline, readable on any background."""
    cv2.putText(canvas, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(canvas, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def upscale(image: np.ndarray, height: int) -> np.ndarray:
    """Nearest-neighbour resize to ``height`` px (pixels stay visible as squares)."""
    s = height / image.shape[0]
    return cv2.resize(image, (max(1, round(image.shape[1] * s)), height), interpolation=cv2.INTER_NEAREST)


def legend_strip(width: int, items: tuple[tuple[tuple[int, int, int], str], ...] | list,
                 height: int = 30) -> np.ndarray:
    """A white strip with a coloured swatch and a text per item, wrapped onto more rows if needed."""
    rows: list[list[tuple[tuple[int, int, int], str, int]]] = [[]]
    x = 8
    for colour, text in items:
        (tw, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        if x + 22 + tw > width and rows[-1]:
            rows.append([])
            x = 8
        rows[-1].append((colour, text, x))
        x += 22 + tw + 18
    strip = np.full((height * len(rows), width, 3), 255, np.uint8)
    for r, row in enumerate(rows):
        y = r * height + height // 2
        for colour, text, x0 in row:
            cv2.rectangle(strip, (x0, y - 7), (x0 + 14, y + 7), tuple(int(c) for c in colour), -1)
            cv2.putText(strip, text, (x0 + 20, y + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (30, 30, 30), 1,
                        cv2.LINE_AA)
    return strip


def colourbar_strip(width: int, lo: float, hi: float, title: str, name: str = "viridis",
                    height: int = 30) -> np.ndarray:
    """A white strip with a horizontal colour bar from ``lo`` to ``hi`` and a title."""
    strip = np.full((height, width, 3), 255, np.uint8)
    (tw, _), _ = cv2.getTextSize(title, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    cv2.putText(strip, title, (8, height // 2 + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (30, 30, 30), 1,
                cv2.LINE_AA)
    x0, x1 = tw + 60, width - 70
    bar = colour_map(np.linspace(lo, hi, max(x1 - x0, 2)), lo, hi, name)
    strip[height // 2 - 7:height // 2 + 7, x0:x0 + len(bar)] = bar[None]
    for value, x in ((lo, x0 - 8), (hi, x1 + 6)):
        text = f"{value:g}"
        (vw, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        cv2.putText(strip, text, (x - vw if x < x0 else x, height // 2 + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (30, 30, 30), 1, cv2.LINE_AA)
    return strip


def titled(panel: np.ndarray, title: str, note: str = "", scale: float = 0.5) -> np.ndarray:
    """``panel`` with ``title`` in a white strip above it and ``note`` (if any) in one below, dark
    text on white (readable whatever the panel shows)."""
    width = panel.shape[1]

    def strip(text: str) -> np.ndarray:
        out = np.full((24, width, 3), 255, np.uint8)
        (tw, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        cv2.putText(out, text, (max(2, (width - tw) // 2), 17), cv2.FONT_HERSHEY_SIMPLEX, scale,
                    (30, 30, 30), 1, cv2.LINE_AA)
        return out

    parts = [strip(title), panel] + ([strip(note)] if note else [])
    return np.concatenate(parts)


def hstack(panels: list[np.ndarray], gap: int = 6, background: int = 255) -> np.ndarray:
    """Panels of equal height side by side with a gap."""
    h = max(p.shape[0] for p in panels)
    parts = []
    for i, p in enumerate(panels):
        if p.shape[0] < h:
            p = np.concatenate([p, np.full((h - p.shape[0], p.shape[1], 3), background, np.uint8)])
        parts.append(p)
        if i < len(panels) - 1:
            parts.append(np.full((h, gap, 3), background, np.uint8))
    return np.concatenate(parts, axis=1)
