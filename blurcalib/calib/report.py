"""Report figures: the reprojection-error direction image and per-frame error plots.

The direction image follows the reference calibration tool's drawing: the error direction ``a``
(angle of the residual vector, image x right and y down) is the colour
``(R, G, B) = (127 + 127 sin a, 127 + 127 cos a, 127)``; here that colour is scaled by the error
magnitude (brightness), saturating at ``saturate_px`` (by default the 95th percentile of the
cells' mean errors, so that the image is not black where the errors are hundredths of a pixel).
A systematic (directional) bias shows as large areas of one hue; unbiased noise as a random
speckle of hues. A strip below the image is its legend: the colour wheel of the directions, the
brightness scale in px and what the image shows.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from blurcalib.io.atomic import atomic_path


def direction_colours(error: np.ndarray, full_px: float | None = None) -> np.ndarray:
    """RGB (0..255, float) of error vectors ``error (..., 2)`` (px, x right, y down), the
    reference tool's ``(127 + 127 sin a, 127 + 127 cos a, 127)`` for ``a = atan2(e_y, e_x)``.

    With ``full_px`` the colour is scaled by the error's length, full brightness at ``full_px``
    px and black at zero; without it every colour has full brightness.
    """
    e = np.asarray(error, dtype=np.float64)
    a = np.arctan2(e[..., 1], e[..., 0])
    rgb = np.stack([127 + 127 * np.sin(a), 127 + 127 * np.cos(a), np.full_like(a, 127.0)], axis=-1)
    if full_px is None:
        return rgb
    bright = np.clip(np.hypot(e[..., 0], e[..., 1]) / max(full_px, 1e-12), 0.0, 1.0)
    return rgb * bright[..., None]


LEGEND_PX = 96
"""Height of the legend strip below a direction image (px)."""


def error_direction_image(xy: np.ndarray, residuals: np.ndarray, image_size: tuple[int, int],
                          cell_px: int = 8, saturate_px: float | None = None, title: str = "") -> np.ndarray:
    """Render residual directions and magnitudes as a BGR ``uint8`` image of ``image_size``, with
    a legend strip :data:`LEGEND_PX` px high below it (:func:`direction_legend`).

    Args:
        xy: ``(N, 2)`` feature positions (px, OpenCV convention).
        residuals: ``(N, 2)`` residual vectors (px), observed minus model.
        image_size: ``(width, height)`` px.
        cell_px: residuals are averaged over square cells of this side (px).
        saturate_px: magnitude shown at full brightness (px); None: the 95th percentile of the
            cells' mean magnitudes.
        title: what the residuals are, written in the legend.
    Returns:
        ``(height + LEGEND_PX, width, 3)`` BGR image; cells without features are black.
    """
    w, h = image_size
    gw, gh = -(-w // cell_px), -(-h // cell_px)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    res = np.asarray(residuals, dtype=np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(xy), axis=1) & np.all(np.isfinite(res), axis=1)
    cx = np.clip((xy[ok, 0] + 0.5) // cell_px, 0, gw - 1).astype(np.int64)
    cy = np.clip((xy[ok, 1] + 0.5) // cell_px, 0, gh - 1).astype(np.int64)
    sums = np.zeros((gh, gw, 2))
    count = np.zeros((gh, gw))
    np.add.at(sums, (cy, cx), res[ok])
    np.add.at(count, (cy, cx), 1.0)
    mean = sums / np.maximum(count, 1)[..., None]
    if saturate_px is None:
        mags = np.hypot(mean[..., 0], mean[..., 1])[count > 0]
        saturate_px = float(np.percentile(mags, 95)) if mags.size and np.percentile(mags, 95) > 0 else 1.0
    rgb = direction_colours(mean, saturate_px) * (count > 0)[..., None]
    cells = np.round(rgb[..., ::-1]).astype(np.uint8)
    image = np.repeat(np.repeat(cells, cell_px, axis=0), cell_px, axis=1)[:h, :w]
    legend = direction_legend(w, saturate_px, title or f"mean residual per {cell_px} px cell",
                              int(ok.sum()))
    return np.concatenate([image, legend])


def direction_legend(width: int, full_px: float, title: str, observations: int) -> np.ndarray:
    """A white BGR strip ``(LEGEND_PX, width, 3)``: the colour wheel (direction as hue, length as
    brightness), the brightness scale from 0 to ``full_px`` px, and ``title``; drawn at least as wide
    as the wheel and a short scale, and cut to ``width`` for a narrower image."""
    size = LEGEND_PX - 16
    strip = np.full((LEGEND_PX, max(width, 2 * size + 70), 3), 255, np.uint8)
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size]
    e = np.stack([(xx - c) / c, (yy - c) / c], axis=-1)
    wheel = direction_colours(e, 1.0)[..., ::-1]
    inside = np.hypot(e[..., 0], e[..., 1]) <= 1.0
    region = strip[8:8 + size, 8:8 + size]
    region[inside] = np.round(wheel[inside]).astype(np.uint8)
    font, ink = cv2.FONT_HERSHEY_SIMPLEX, (40, 40, 40)
    cv2.putText(strip, "+x", (8 + size + 2, 8 + size // 2 + 4), font, 0.4, ink, 1, cv2.LINE_AA)
    cv2.putText(strip, "+y", (8 + size // 2 - 8, LEGEND_PX - 1), font, 0.35, ink, 1, cv2.LINE_AA)
    x0 = 8 + size + 30
    bar_w = max(min(strip.shape[1] - x0 - 16, 240), 20)
    ramp = direction_colours(np.stack([np.linspace(0, full_px, bar_w), np.zeros(bar_w)], axis=-1), full_px)
    strip[50:64, x0:x0 + bar_w] = np.round(ramp[None, :, ::-1]).astype(np.uint8)
    cv2.putText(strip, "0", (x0, 80), font, 0.42, ink, 1, cv2.LINE_AA)
    cv2.putText(strip, f"{full_px:.3g} px and more", (x0 + bar_w - 100, 80), font, 0.42, ink, 1, cv2.LINE_AA)
    cv2.putText(strip, f"{title} ({observations} observations)", (x0, 18), font, 0.42, ink, 1, cv2.LINE_AA)
    cv2.putText(strip, "hue: direction (observed minus model); brightness: length", (x0, 38), font, 0.42, ink,
                1, cv2.LINE_AA)
    return strip[:, :width]


def save_frame_error_plot(path: str | os.PathLike[str], rows: list[dict[str, Any]],
                          sharp_errors: dict[str, dict[str, Any]]) -> Path:
    """Bar plot of the median alignment error per blurry frame (coloured by status) beside the
    sharp frames' median calibration errors (px)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4), gridspec_kw={"width_ratios": [3, 1]})
    blurry = [r for r in rows if "median_error" in r]
    axes[0].bar(range(len(blurry)), [r["median_error"] for r in blurry],
                color=["black" if r.get("alignment") == "ill_conditioned" else
                       "tab:blue" if r["status"] == "used" else "tab:red" for r in blurry])
    axes[0].set_xlabel("blurry frame (black: flagged by the orientation filter)")
    axes[0].set_ylabel("median error after global alignment (px)")
    axes[0].set_title(f"{len(blurry)} aligned blurry frames of {len(rows)}")
    sharp = [v["median_error_px"] for v in sharp_errors.values() if v["median_error_px"] is not None]
    axes[1].bar(range(len(sharp)), sharp, color="tab:green")
    axes[1].set_xlabel("sharp frame")
    axes[1].set_title("sharp-set calibration")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)
    return Path(path)
