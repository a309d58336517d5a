"""The PSF field of one frame, ``fig:exp_real1`` of :mod:`blurcalib.paper.psf_quality`: the frame
whose true blur varies most over its field, its accepted blocks' PSFs drawn at their places
without and with centroid correction, and a magnified region.

Pixels follow OpenCV's convention: the centre of the top-left pixel is ``(0, 0)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from blurcalib.geometry.homography import apply_homography
from blurcalib.io.atomic import atomic_path
from blurcalib.paper.common import ExtractedFrame
from blurcalib.sim.truth import TrueCamera
from blurcalib.target.pattern import StarPattern

__all__ = ["SQUARE_CORNERS", "FieldChoice", "choose_field_frame", "field_variation", "psf_mosaic",
           "save_fig_exp_real1"]

SQUARE_CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
"""A block's square corners in block coordinates ``q``."""


def field_variation(frame: ExtractedFrame, camera: TrueCamera, pattern: StarPattern) -> float:
    """How much the true blur varies over the accepted blocks of a frame (dimensionless).

    With ``e_k`` the image displacement of feature ``k`` from the first to the last instant of
    the exposure, ``sqrt(mean |e_k - mean e|^2 / mean |e_k|^2)``: near 0 for a pure pan (the
    same blur everywhere), large with roll (blur turning and growing away from the roll centre)
    or zoom.
    """
    growth = frame.growth
    ids = growth.feature_id[growth.accepted]
    poses = frame.truth.motion.poses(frame.truth.pose)
    if len(ids) < 2 or len(poses) < 2:
        return 0.0
    P = pattern.points_3d(ids)
    e = camera.project(poses[-1].transform(P)) - camera.project(poses[0].transform(P))
    spread = np.mean(np.sum((e - e.mean(axis=0)) ** 2, axis=1))
    return float(math.sqrt(spread / max(float(np.mean(np.sum(e**2, axis=1))), 1e-12)))


@dataclass(frozen=True)
class FieldChoice:
    """The frame of ``fig:exp_real1`` and its magnified region.

    Attributes:
        frame: index of the frame in the frame list.
        variation: its :func:`field_variation`.
        region: indices (into the frame's ``growth.fit``) of the magnified blocks.
        box: ``(x0, y0, x1, y1)`` px, the region's bounding box.
    """

    frame: int
    variation: float
    region: np.ndarray
    box: tuple[float, float, float, float]


def choose_field_frame(frames: Sequence[ExtractedFrame], camera: TrueCamera, pattern: StarPattern,
                       tau_be: float, min_blur_px: float, magnified: int) -> FieldChoice | None:
    """The frame with the most varying blur field among those whose PSFs fit the window.

    Eligible: extracted, at least 12 accepted blocks, accepted blocks' median BE at most
    ``tau_be`` and true median blur at least ``min_blur_px`` (px); failing that, the blur
    condition is dropped, then every extracted frame is eligible. The magnified region is the
    accepted block with BE at most ``tau_be`` farthest from the image centre (the paper's
    drifting PSFs sit near the border) and its ``magnified - 1`` nearest accepted neighbours on
    the grid (Manhattan distance, ties broken by the Chebyshev distance).
    """
    ok = [i for i, f in enumerate(frames) if f.ok and f.growth.accepted.sum() >= 2]
    if not ok:
        return None

    def fits(i: int) -> bool:
        g = frames[i].growth
        acc = g.accepted
        return acc.sum() >= 12 and float(np.median(g.fit.boundary_energy[acc])) <= tau_be

    def blurred(i: int) -> bool:
        truth = frames[i].truth
        return float(np.median(truth.blur_length[truth.visible])) >= min_blur_px

    fitting = [i for i in ok if fits(i)]
    eligible = [i for i in fitting if blurred(i)] or fitting or ok
    scores = {i: field_variation(frames[i], camera, pattern) for i in eligible}
    best = max(eligible, key=lambda i: scores[i])
    growth = frames[best].growth
    fit = growth.fit
    acc = np.flatnonzero(growth.accepted)
    good = acc[fit.boundary_energy[acc] <= tau_be]
    pool = good if len(good) else acc
    w, h = frames[best].image_size
    centre = fit.centre
    far = pool[np.argmax(np.hypot(centre[pool, 0] - (w - 1) / 2, centre[pool, 1] - (h - 1) / 2))]
    f = pattern.features[growth.feature_id]
    d = np.abs(f[acc] - f[far])
    region = acc[np.lexsort((d.max(axis=1), d.sum(axis=1)))[:magnified]]
    region = region[np.lexsort((f[region, 0], f[region, 1]))]
    corners = apply_homography(fit.H[region], np.broadcast_to(SQUARE_CORNERS, (len(region), 4, 2)))
    lo, hi = corners.reshape(-1, 2).min(axis=0), corners.reshape(-1, 2).max(axis=0)
    return FieldChoice(best, scores[best], region, (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))


def psf_mosaic(frame: ExtractedFrame, psfs: np.ndarray, zoom: int = 2, fill: float = 0.9) -> np.ndarray:
    """The PSF field of a frame as an image: each accepted block's PSF, normalised to its peak
    and resized (nearest neighbour) to ``fill`` of its square's bounding box, centred on the
    block's star centre. Returns ``(height zoom, width zoom)`` in ``[0, 1]``.

    Args:
        frame: an extracted frame.
        psfs: ``(B, K, K)`` the kernels to draw, aligned with ``growth.fit`` (``psf_fit`` or
            ``psf``).
        zoom: canvas pixels per image pixel.
        fill: tile side over the smaller side of the square's bounding box.
    """
    w, h = frame.image_size
    canvas = np.zeros((h * zoom, w * zoom))
    growth = frame.growth
    fit = growth.fit
    acc = np.flatnonzero(growth.accepted)
    corners = apply_homography(fit.H[acc], np.broadcast_to(SQUARE_CORNERS, (len(acc), 4, 2)))
    for j, k in enumerate(acc):
        psf = np.nan_to_num(psfs[k])
        peak = float(psf.max())
        box = corners[j].max(axis=0) - corners[j].min(axis=0)
        side = int(fill * float(box.min()) * zoom)
        if peak <= 0 or side < 3:
            continue
        tile = cv2.resize(psf / peak, (side, side), interpolation=cv2.INTER_NEAREST)
        cx, cy = (fit.centre[k] + 0.5) * zoom - 0.5
        x0, y0 = round(cx - (side - 1) / 2), round(cy - (side - 1) / 2)
        xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + side, w * zoom), min(y0 + side, h * zoom)
        if xa >= xb or ya >= yb:
            continue
        canvas[ya:yb, xa:xb] = np.maximum(canvas[ya:yb, xa:xb], tile[ya - y0:yb - y0, xa - x0:xb - x0])
    return canvas


def save_fig_exp_real1(frames: Sequence[ExtractedFrame], choice: FieldChoice, path: str | Path,
                       zoom: int = 2) -> Path:
    """``fig:exp_real1``: the PSF field without (left, ``psf_fit``) and with (right, ``psf``)
    centroid correction, and the magnified PSFs of the red-boxed region (bottom row: each
    block's PSF before and after; a cross at the kernel centre, a dot at the centroid)."""
    frame = frames[choice.frame]
    fit = frame.growth.fit
    acc = frame.growth.accepted
    n = len(choice.region)
    fig = Figure(figsize=(12.0, 6.6), dpi=110)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 2 * n, height_ratios=[3.0, 1.2], hspace=0.18, wspace=0.3, left=0.03,
                            right=0.97, bottom=0.03, top=0.9)
    cmag = np.linalg.norm(fit.centroid[acc], axis=1)
    w, h = frame.image_size
    x0, y0, x1, y1 = ((np.array(choice.box) + 0.5) * zoom - 0.5).tolist()
    for col, (name, psfs) in enumerate((("without centroid correction (psf_fit)", fit.psf_fit),
                                        ("with re-centring (psf)", fit.psf))):
        ax = fig.add_subplot(grid[0, col * n:(col + 1) * n])
        ax.imshow(psf_mosaic(frame, psfs, zoom), cmap="magma", vmin=0.0, vmax=1.0,
                  interpolation="nearest", extent=(-0.5, w * zoom - 0.5, h * zoom - 0.5, -0.5))
        centres = (fit.centre[acc] + 0.5) * zoom - 0.5
        ax.scatter(centres[:, 0], centres[:, 1], marker="+", s=5, c="cyan", linewidths=0.4, alpha=0.5)
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="red", linewidth=1.2))
        ax.set_xticks([])
        ax.set_yticks([])
        extra = (f": median |centroid| {np.median(cmag):.2f} px, max {cmag.max():.2f} px" if col == 0
                 else ": centroids at the window centre")
        ax.set_title(name + extra, fontsize=8)
    K = fit.psf.shape[-1]
    c = (K - 1) / 2
    for j, k in enumerate(choice.region):
        for col, (label, psf, centroid) in enumerate((("fit", fit.psf_fit[k], fit.centroid[k]),
                                                      ("re-centred", fit.psf[k], np.zeros(2)))):
            ax = fig.add_subplot(grid[1, col * n + j])
            ax.imshow(np.nan_to_num(psf), cmap="magma", interpolation="nearest")
            ax.axhline(c, color="white", lw=0.4, ls=":")
            ax.axvline(c, color="white", lw=0.4, ls=":")
            ax.plot(c + centroid[0], c + centroid[1], "o", color="cyan", ms=3)
            ax.set_xticks([])
            ax.set_yticks([])
            fx, fy = frame.result.blocks.fx[k], frame.result.blocks.fy[k]
            ax.set_title(f"({fx},{fy}) {label}\nBE {max(fit.boundary_energy[k], 0.0):.2f}, "
                         f"c=({centroid[0]:+.2f},{centroid[1]:+.2f})", fontsize=6)
    truth = frame.truth
    blur = float(np.median(truth.blur_length[truth.visible]))
    fig.suptitle(f"PSF field of {frame.name} ({w}x{h} px, {K}x{K} window, median blur {blur:.1f} px, "
                 f"field variation {choice.variation:.2f}); bottom: the red box magnified "
                 "(paper fig:exp_real1)", fontsize=9)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)
