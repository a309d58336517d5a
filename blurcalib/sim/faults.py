"""Faults of real captures, rendered into a simulated frame: glare, an occluding finger, a region
out of focus; with the exact set of blocks each one touches.

A fault acts on the frame's irradiance (:meth:`blurcalib.sim.render.Renderer.irradiance`, target
white = 1, ink = 0), before the sensor (:func:`blurcalib.sim.render.sensor_image`): glare is light
added on the target, which the sensor's 8 bits then clip; a finger is an object in front of the
target; a defocus region is a part of the target outside the depth of field. Each fault has a
*footprint*, the pixels whose irradiance it changes by more than :data:`FOOTPRINT_TOLERANCE`
(glare, finger) or that it blurs by a Gaussian of more than :data:`DEFOCUS_TOLERANCE_PX`
(defocus); :func:`touched_blocks` names the pattern's blocks (the star squares) whose image at
``tau = 0``, widened by the frame's blur, meets it. Image points are px, OpenCV convention
(top-left pixel centre at (0, 0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np

from blurcalib.geometry.pose import Pose
from blurcalib.sim.truth import TrueCamera, gauss_ksize
from blurcalib.target.pattern import StarPattern

FOOTPRINT_TOLERANCE = 0.04
"""Irradiance change (of the target's white, 1) from which a pixel is in a glare's or a finger's
footprint: about 7 grey levels at the simulator's white levels, 3 noise sigmas."""
DEFOCUS_TOLERANCE_PX = 0.5
"""Local Gaussian sigma (px) from which a pixel is in a defocus region's footprint."""
DEFOCUS_LEVELS = 6
"""Blurred copies a defocus region blends between (sigma 0 to its largest, evenly spaced)."""


@dataclass(frozen=True)
class Glare:
    """A specular reflection on the target (a lamp's or a window's image on glossy paper): an
    ellipse of added irradiance ``peak`` with an edge ``softness`` px wide.

    Attributes:
        centre: ``(x, y)`` px.
        radius: the ellipse's semi-major axis (px).
        peak: added irradiance inside (1: the target's white; above about 0.25 the sensor clips
            the white there).
        aspect: semi-major over semi-minor axis.
        angle_deg: direction of the major axis (degrees from the image x axis, towards y).
        softness: width of the edge's ramp (px).
    """

    centre: tuple[float, float]
    radius: float
    peak: float
    aspect: float = 1.8
    angle_deg: float = 30.0
    softness: float = 4.0
    kind: str = "glare"

    def strength(self, shape: tuple[int, int]) -> np.ndarray:
        """``(H, W)`` the irradiance added at each pixel."""
        h, w = shape
        ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
        a = math.radians(self.angle_deg)
        dx, dy = xs - self.centre[0], ys - self.centre[1]
        u = dx * math.cos(a) + dy * math.sin(a)
        v = (-dx * math.sin(a) + dy * math.cos(a)) * self.aspect
        d = np.hypot(u, v)
        return cast(np.ndarray,
                    self.peak * np.clip((self.radius - d) / max(self.softness, 1e-6) + 0.5, 0.0, 1.0))

    def apply(self, irradiance: np.ndarray) -> np.ndarray:
        return cast(np.ndarray, irradiance + self.strength(irradiance.shape).astype(irradiance.dtype))

    def footprint(self, shape: tuple[int, int]) -> np.ndarray:
        return self.strength(shape) > FOOTPRINT_TOLERANCE


@dataclass(frozen=True)
class Finger:
    """An opaque finger in front of the target: a capsule (all points within ``radius`` of the
    segment ``start``-``end``) of reflectance ``level``, darker towards its edges (rounded), with
    an edge ``softness`` px wide (it is out of focus and moves with the hand).

    Attributes:
        start, end: ``(x, y)`` px, the segment's ends (the tip is ``end``).
        radius: half its width (px).
        level: irradiance along its middle (skin in the target's light: about 0.6).
        softness: width of the edge's ramp (px).
    """

    start: tuple[float, float]
    end: tuple[float, float]
    radius: float
    level: float = 0.6
    softness: float = 3.0
    kind: str = "finger"

    def distance(self, shape: tuple[int, int]) -> np.ndarray:
        """``(H, W)`` px from each pixel to the segment."""
        h, w = shape
        ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
        a, b = np.asarray(self.start, float), np.asarray(self.end, float)
        ab = b - a
        t = np.clip(((xs - a[0]) * ab[0] + (ys - a[1]) * ab[1]) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        return cast(np.ndarray, np.hypot(xs - (a[0] + t * ab[0]), ys - (a[1] + t * ab[1])))

    def cover(self, shape: tuple[int, int]) -> np.ndarray:
        """``(H, W)`` in [0, 1]: how much of each pixel the finger hides."""
        d = self.distance(shape)
        return np.clip((self.radius + 0.5 * self.softness - d) / max(self.softness, 1e-6), 0.0, 1.0)

    def apply(self, irradiance: np.ndarray) -> np.ndarray:
        d = self.distance(irradiance.shape)
        cover = self.cover(irradiance.shape)
        skin = self.level * (1.0 - 0.35 * np.clip(d / self.radius, 0.0, 1.0) ** 2)
        return cast(np.ndarray, ((1.0 - cover) * irradiance + cover * skin).astype(irradiance.dtype))

    def footprint(self, shape: tuple[int, int]) -> np.ndarray:
        return self.cover(shape) > FOOTPRINT_TOLERANCE


@dataclass(frozen=True)
class Defocus:
    """A region out of focus: a Gaussian blur whose sigma grows from 0 at ``radius`` px from
    ``centre`` to ``sigma`` px at the centre (smoothly, ``sigma (1 - (d / radius)^2)^2``).

    Attributes:
        centre: ``(x, y)`` px.
        radius: px.
        sigma: the largest Gaussian sigma (px).
    """

    centre: tuple[float, float]
    radius: float
    sigma: float
    kind: str = "defocus"

    def local_sigma(self, shape: tuple[int, int]) -> np.ndarray:
        """``(H, W)`` the Gaussian sigma (px) at each pixel."""
        r2 = _distance2(shape, self.centre) / self.radius**2
        return self.sigma * np.clip(1.0 - r2, 0.0, 1.0) ** 2

    def apply(self, irradiance: np.ndarray) -> np.ndarray:
        """Each pixel blends the two of :data:`DEFOCUS_LEVELS` blurred copies whose sigmas
        bracket its own (linear in sigma)."""
        local = self.local_sigma(irradiance.shape)
        levels = np.linspace(0.0, self.sigma, DEFOCUS_LEVELS)
        copies: list[np.ndarray] = [irradiance.astype(np.float64)]
        for s in levels[1:]:
            k = gauss_ksize(float(s))
            copies.append(cv2.GaussianBlur(copies[0], (k, k), float(s), borderType=cv2.BORDER_REFLECT))
        pos = np.clip(local / (levels[1] - levels[0]), 0, DEFOCUS_LEVELS - 1)
        lo = np.minimum(np.floor(pos).astype(int), DEFOCUS_LEVELS - 2)
        frac = pos - lo
        stack = np.stack(copies)
        rows, cols = np.indices(local.shape)
        out = (1.0 - frac) * stack[lo, rows, cols] + frac * stack[lo + 1, rows, cols]
        return cast(np.ndarray, out.astype(irradiance.dtype))

    def footprint(self, shape: tuple[int, int]) -> np.ndarray:
        return self.local_sigma(shape) > DEFOCUS_TOLERANCE_PX


Fault = Glare | Finger | Defocus


def _distance2(shape: tuple[int, int], centre: tuple[float, float]) -> np.ndarray:
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return cast(np.ndarray, (xs - centre[0]) ** 2 + (ys - centre[1]) ** 2)


def apply_faults(irradiance: np.ndarray, faults: tuple[Fault, ...] | list[Fault]) -> np.ndarray:
    """The irradiance ``(H, W)`` with each fault applied in turn (a copy; values may exceed 1
    under glare: the sensor clips)."""
    out = np.asarray(irradiance, dtype=np.float32)
    for fault in faults:
        out = fault.apply(out)
    return out


def block_quads(pattern: StarPattern, camera: TrueCamera, pose: Pose) -> np.ndarray:
    """``(M, 4, 2)`` px: the image of each feature's star square at ``pose`` (``pattern.features``
    order; NaN where a corner is behind the camera or outside the lens's view)."""
    corners = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    pts = (pattern.features[:, None, :] + corners[None]).reshape(-1, 2) * pattern.square_length_m
    cam = pose.transform(np.column_stack([pts, np.zeros(len(pts))]))
    px = camera.project(cam)
    px[~camera.in_view(cam)] = np.nan
    return px.reshape(-1, 4, 2)


def touched_blocks(footprint: np.ndarray, quads: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
    """``(M,)`` bool: the blocks whose square ``quads (M, 4, 2)`` (px), widened by ``margin_px``
    (the frame's blur reaches that far), has a pixel of ``footprint (H, W)``."""
    h, w = footprint.shape
    grown: np.ndarray = footprint.astype(np.uint8)
    if margin_px > 0:
        r = math.ceil(margin_px)
        grown = cv2.dilate(grown, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    out = np.zeros(len(quads), dtype=bool)
    for i, quad in enumerate(quads):
        if not np.all(np.isfinite(quad)):
            continue
        x0, y0 = np.floor(quad.min(axis=0)).astype(int)
        x1, y1 = np.ceil(quad.max(axis=0)).astype(int)
        if x1 < 0 or y1 < 0 or x0 >= w or y0 >= h:
            continue
        cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
        mask = np.zeros((cy1 - cy0 + 1, cx1 - cx0 + 1), np.uint8)
        cv2.fillPoly(mask, [np.round(quad - [cx0, cy0]).astype(np.int32)], 1)
        out[i] = bool((mask & grown[cy0:cy1 + 1, cx0:cx1 + 1]).any())
    return out


def fault_to_dict(fault: Fault) -> dict[str, Any]:
    """A fault as JSON: its kind and parameters."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in fault.__dict__.items()}


def fault_from_dict(data: dict[str, Any]) -> Fault:
    """The inverse of :func:`fault_to_dict`."""
    kinds: dict[str, type[Fault]] = {"glare": Glare, "finger": Finger, "defocus": Defocus}
    args: dict[str, Any] = {k: (tuple(v) if isinstance(v, list) else v)
                            for k, v in data.items() if k != "kind"}
    return kinds[data["kind"]](**args)
