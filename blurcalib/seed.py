"""Seeding: find the target's AprilTag and the homography that starts region growing.

Blur defeats tag detectors, so detection is retried on downscaled copies of the frame (a blur of
``b`` px is ``b s`` px at scale ``s``, while the tag's cells stay several pixels wide). A caller
can instead pass a homography it already has (the previous frame of a sequence, or four corners
clicked in the GUI).

The seed is a homography ``H_f`` from *feature coordinates* (see ``docs/conventions.md``) to
image pixels (OpenCV convention); a block's homography is ``H_f B(fx, fy)`` with
``B = [[1/2, 0, fx], [0, 1/2, fy], [0, 0, 1]]`` mapping block coordinates to feature coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from blurcalib.pattern import StarPattern

DEFAULT_SCALES = (1.0, 0.5, 0.35, 0.25)
"""Image scales tried in turn for tag detection."""

APRILTAG_REFINEMENT_OFFSET_PX = 0.5
"""aruco's CORNER_REFINE_APRILTAG corners sit +0.5 px from the OpenCV pixel-centre convention
(measured on simulated frames against the true corners; also noted for pupil-apriltags)."""


class SeedError(RuntimeError):
    """A frame cannot be seeded: no tag of the pattern found at any scale."""


@dataclass(frozen=True)
class Seed:
    """Where the target is in a frame.

    Attributes:
        H_feature: ``(3, 3)`` homography, feature coordinates -> image px.
        tag_index: tag36h11 id of the tag used (-1 when the caller supplied ``H_feature``).
        corners_px: ``(4, 2)`` tag corners found (aruco order, OpenCV convention), or empty.
        scale: image scale at which the tag was detected (1 for full resolution).
        source: ``"tag"`` or ``"given"``.
    """

    H_feature: np.ndarray
    tag_index: int
    corners_px: np.ndarray
    scale: float
    source: str


def block_homography(H_feature: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """Block homographies ``H_f B(fx, fy)`` of features ``(fx, fy)``: ``(B, 3, 3)``.

    ``B`` maps block coordinates ``q`` (star centre 0, square corners +-1) to feature coordinates
    ``(fx, fy) + q / 2``.
    """
    fx = np.atleast_1d(np.asarray(fx, dtype=np.float64))
    fy = np.atleast_1d(np.asarray(fy, dtype=np.float64))
    B = np.zeros((len(fx), 3, 3))
    B[:, 0, 0] = 0.5
    B[:, 1, 1] = 0.5
    B[:, 0, 2] = fx
    B[:, 1, 2] = fy
    B[:, 2, 2] = 1.0
    return np.asarray(H_feature, dtype=np.float64)[None] @ B


def detect_tags(image: np.ndarray, scales: tuple[float, ...] = DEFAULT_SCALES
                ) -> tuple[dict[int, np.ndarray], float]:
    """Detect tag36h11 markers, trying each scale until one finds any.

    Args:
        image: ``(H, W)`` grey levels (uint8, or float on the 0..255 scale).
        scales: downscale factors to try, in order.
    Returns:
        ``({tag id: (4, 2) corners in full-resolution px, OpenCV convention}, scale)``; empty
        and ``0.0`` when no scale finds a tag.
    """
    grey = np.clip(np.asarray(image), 0, 255).astype(np.uint8)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)
    for s in scales:
        img = grey if s == 1.0 else cv2.resize(grey, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        corners, ids, _ = detector.detectMarkers(img)
        if ids is None or len(ids) == 0:
            continue
        found = {}
        for c, i in zip(corners, ids.ravel(), strict=True):
            pts = c.reshape(4, 2).astype(np.float64) - APRILTAG_REFINEMENT_OFFSET_PX
            found[int(i)] = (pts + 0.5) / s - 0.5
        return found, s
    return {}, 0.0


def seed_frame(image: np.ndarray, pattern: StarPattern, H_feature: np.ndarray | None = None,
               scales: tuple[float, ...] = DEFAULT_SCALES) -> Seed:
    """Find the homography from feature coordinates to the image.

    Args:
        image: ``(H, W)`` grey levels.
        pattern: the target.
        H_feature: a homography the caller already has (used as is).
        scales: detection scales (see :func:`detect_tags`).
    Raises:
        SeedError: no tag of ``pattern`` was found at any scale.
    """
    if H_feature is not None:
        H = np.asarray(H_feature, dtype=np.float64)
        if H.shape != (3, 3) or not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-12:
            raise SeedError("the given homography is not a finite, invertible 3x3 matrix")
        return Seed(H / H[2, 2], -1, np.zeros((0, 2)), 1.0, "given")
    found, scale = detect_tags(image, scales)
    wanted = {t.index: t for t in pattern.apriltags}
    matches = [(i, c) for i, c in found.items() if i in wanted]
    if not matches:
        seen = f" (found tag ids {sorted(found)}, the pattern has {sorted(wanted)})" if found else ""
        raise SeedError(f"no AprilTag of the pattern found at scales {list(scales)}{seen}")
    index, corners = matches[0]
    src = pattern.tag_corners(wanted[index]).astype(np.float32)
    H = cv2.getPerspectiveTransform(src, corners.astype(np.float32)).astype(np.float64)
    return Seed(H / H[2, 2], index, corners, scale, "tag")


def tag_ring_features(pattern: StarPattern) -> np.ndarray:
    """``(M, 2)`` valid features in the ring just outside each tag's blocked box: the first
    blocks to grow from a tag seed."""
    ring = []
    for tag in pattern.apriltags:
        x0, y0, x1, y1 = tag.feature_box
        for fy in range(y0 - 1, y1 + 2):
            for fx in range(x0 - 1, x1 + 2):
                if (fx in (x0 - 1, x1 + 1) or fy in (y0 - 1, y1 + 1)) and \
                        bool(pattern.is_valid_feature(fx, fy)):
                    ring.append((fx, fy))
    return np.array(ring, dtype=np.int64).reshape(-1, 2)
