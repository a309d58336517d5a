"""Pixels kept out of the blocks' losses: those that see a tag through the blur.

The block model's latent pattern is the periodic star field, so pixels that see a tag through
the blur are left out of every block's loss (:func:`tag_mask`, :func:`pixel_mask`): those nearer
to it than the kernel radius, or in a heavily blurred frame with the adaptive window, those
within the blur's footprint of it (:func:`blur_footprint`, a segment along the blur: a disk of a
35 px window leaves the ring of a 22 px blur on 27 px squares almost no pixels).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from blurcalib.deconv.result import BlockFit
from blurcalib.target.pattern import StarPattern


def tag_mask(pattern: StarPattern, H_feature: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` uint8, 1 on the tags' areas (feature boxes) seen through ``H_feature``."""
    mask = np.zeros(shape, dtype=np.uint8)
    for tag in pattern.apriltags:
        x0, y0, x1, y1 = tag.feature_box
        box = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
        px = cv2.perspectiveTransform(box[None], np.asarray(H_feature, dtype=np.float64))[0]
        if np.all(np.isfinite(px)) and np.abs(px).max() < 1e6:
            cv2.fillConvexPoly(mask, np.round(px).astype(np.int32), 1)
    return mask


def blur_footprint(fit: BlockFit, extent_px: float) -> np.ndarray | None:
    """``(F, F)`` uint8 footprint of the frame's blur, from the ring's fit ``fit``: a segment of
    length ``extent_px`` along the PSFs' major axis (their orientations averaged as doubled
    angles), ``2 + 2 sigma_minor`` px wide on each side (median ``sigma_minor``) plus 2 px of seed
    error at its ends. A pixel sees a tag through the blur only when it lies within the tag
    dilated by this footprint; None when no PSF was fitted."""
    ok = np.isfinite(fit.orientation) & np.isfinite(fit.sigma_minor)
    if not ok.any() or not math.isfinite(extent_px):
        return None
    theta = 0.5 * float(np.angle(np.mean(np.exp(2j * fit.orientation[ok]))))
    half_width = 2 + math.ceil(2.0 * float(np.median(fit.sigma_minor[ok])))
    half_length = math.ceil(extent_px / 2.0) + 2
    r = half_length + half_width
    footprint = np.zeros((2 * r + 1, 2 * r + 1), dtype=np.uint8)
    dx, dy = half_length * math.cos(theta), half_length * math.sin(theta)
    cv2.line(footprint, (round(r - dx), round(r - dy)), (round(r + dx), round(r + dy)), 1,
             thickness=2 * half_width + 1)
    return footprint


def pixel_mask(tag: np.ndarray | None, kernel_size: int, footprint: np.ndarray | None = None
                ) -> np.ndarray | None:
    """Pixels usable by blocks fitted with ``kernel_size``: outside the tags dilated by the
    blur's ``footprint`` (:func:`blur_footprint`), or without one further from a tag than the
    kernel radius plus 2 px (seed error)."""
    if tag is None:
        return None
    x, y, w, h = cv2.boundingRect(tag)
    if w == 0:
        return None
    if footprint is None:
        r = kernel_size // 2 + 2
        footprint = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    # dilate the tag's neighbourhood only, not the whole frame
    ry, rx = footprint.shape[0] // 2, footprint.shape[1] // 2
    y0, y1 = max(y - ry, 0), min(y + h + ry, tag.shape[0])
    x0, x1 = max(x - rx, 0), min(x + w + rx, tag.shape[1])
    ok = np.ones(tag.shape, dtype=bool)
    ok[y0:y1, x0:x1] = cv2.dilate(tag[y0:y1, x0:x1], footprint, borderType=cv2.BORDER_CONSTANT,
                                  borderValue=0) == 0
    return ok


def tag_centre(tag: np.ndarray | None) -> np.ndarray | None:
    """``(2,)`` px, the centroid of a :func:`tag_mask`, or None."""
    if tag is None or not tag.any():
        return None
    m = cv2.moments(tag, binaryImage=True)
    return np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])
