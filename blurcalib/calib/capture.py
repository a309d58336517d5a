"""Degenerate captures: frames whose poses cannot determine a camera, found before it is calibrated.

A planar target determines a camera's focal length and principal point only through the
perspective of frames that see it tilted, at several orientations (Zhang's method: each frame's
target-plane homography ``H = K [r1 r2 t]``, ``eq:T``, constrains ``K`` through its plane's
orientation alone; frames of parallel target planes, face-on ones included, repeat one
constraint). A capture of face-on frames, or of frames at nearly one orientation, still gives a
calibration with a small reprojection and held-out error, and a camera hundreds of pixels from
the truth. :func:`check_capture` measures, from the features of the frames of the parametric
stage alone (no camera needed):

* each frame's target-plane homography (least squares over its star centres, image centred) and
  from all of them a rough focal length: Zhang's two constraints per frame,
  ``h1^T W h2 = 0`` and ``h1^T W h1 = h2^T W h2`` with ``W = diag(1, 1, f^2)`` (square pixels,
  principal point at the image centre), solved for ``f^2`` in least squares, with its relative
  standard error from the constraints' residuals; ``f^2 <= 0`` or an error above
  :data:`MAX_FOCAL_ERROR` means the frames' perspective gives no focal length;
* each frame's tilt (the angle between the optical axis and the target's normal,
  ``n = K^-1 h1 x K^-1 h2`` at that focal length) and the spread of the normals (the largest angle
  between two frames' normals);
* the share of the image that holds features (cells of an 8 x 8 grid) and the frame count.

The check was measured on simulated features (a 1280 x 720 lens of fx 645 px, 20 frames, 0.03 px
noise, :func:`blurcalib.sim.synth.sample_pose`): frames tilted up to 50 degrees give the rough
focal length within 1 % (relative error 0.004); up to 10 degrees within 10 % (0.08-0.09; the 3rd
most tilted frame at 6-8 degrees: warned); up to 2 degrees none (refused). Lenses of 100 to 190
degrees, whose distortion no homography follows, give relative errors of 0.05-0.14 and pass; 27
real frames of a 1280 x 720 camera (the reference detector's features) give 884 px, 0.005, tilts up
to 32 degrees, and pass. A face-on capture calibrates to a camera hundreds of pixels from the truth
with held-out errors of hundredths of a pixel, which is why it is refused before any calibration.
The warning thresholds (:class:`CaptureSettings`) are deliberately wider than the refusals.

Pixels follow OpenCV's convention (the top-left pixel's centre at ``(0, 0)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, cast

import cv2
import numpy as np

from blurcalib.io.results import FeatureTable

__all__ = [
    "CaptureCheck",
    "CaptureSettings",
    "check_capture",
    "frame_homographies",
    "plane_normals",
    "rough_focal",
]

MAX_FOCAL_ERROR = 0.5
"""Largest relative standard error of the rough focal length with which the frames' perspective
counts as giving one (20 simulated frames of a 100-190 degree lens, whose distortion no homography
follows, give 0.05-0.14; frames within 2 degrees of face-on give no positive ``f^2``)."""

COVERAGE_CELLS = 8
"""The image is split into this many cells along each side for the coverage figure."""

_REGIONS = (("top", "middle", "bottom"), ("left", "centre", "right"))


@dataclass(frozen=True)
class CaptureSettings:
    """When a capture is refused (:attr:`CaptureCheck.refusal`) and when it is calibrated with a
    warning (:attr:`CaptureCheck.warnings`); measured thresholds in the module docstring.

    Attributes:
        refuse: refuse a degenerate capture (False: every refusal becomes a warning).
        tilted_frames: how many frames must be tilted (the ``tilted_frames``-th largest tilt is
            compared with the thresholds).
        refuse_tilt_deg, warn_tilt_deg: that tilt (deg from face-on) below which the capture is
            refused, and warned about.
        refuse_spread_deg, warn_spread_deg: the largest angle between two frames' target normals
            (deg) below which the capture is refused, and warned about.
        warn_coverage: share of the image's cells holding features below which it warns.
        warn_frames: frames below which it warns that the uncertainty is not to be trusted.
    """

    refuse: bool = True
    tilted_frames: int = 3
    refuse_tilt_deg: float = 5.0
    warn_tilt_deg: float = 15.0
    refuse_spread_deg: float = 1.5
    warn_spread_deg: float = 10.0
    warn_coverage: float = 0.5
    warn_frames: int = 10


@dataclass
class CaptureCheck:
    """What :func:`check_capture` measured and decided.

    Attributes:
        frames: frames measured (those with enough features).
        focal_px: the rough focal length (px) from the frames' perspective, None when they give
            none.
        focal_error: its relative standard error (inf when there is no focal length).
        tilt_deg: each measured frame's tilt (deg), largest first (empty without a focal length).
        spread_deg: the largest angle between two frames' target normals (deg; 0 without a focal
            length).
        coverage: share of the image's :data:`COVERAGE_CELLS` x :data:`COVERAGE_CELLS` cells
            holding features.
        refusal: why the capture cannot give a camera (one line), or None.
        warnings: what makes the camera weaker than its figures say, one line each.
    """

    frames: int
    focal_px: float | None
    focal_error: float
    tilt_deg: list[float]
    spread_deg: float
    coverage: float
    refusal: str | None = None
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """``report.json``'s ``capture`` section (docs/results-format.md)."""
        def r(v: float | None, digits: int = 2) -> float | None:
            return None if v is None or not math.isfinite(v) else round(float(v), digits)

        return {"frames": self.frames, "focal_px": r(self.focal_px, 1),
                "focal_error": r(self.focal_error, 4),
                "tilt_median_deg": r(float(np.median(self.tilt_deg))) if self.tilt_deg else None,
                "tilt_max_deg": r(self.tilt_deg[0]) if self.tilt_deg else None,
                "spread_deg": r(self.spread_deg), "coverage": r(self.coverage, 3),
                "warnings": list(self.warnings)}


def frame_homographies(table: FeatureTable, min_features: int) -> dict[str, np.ndarray]:
    """Each frame's target-plane homography ``(3, 3)``, metric target ``(X, Y, 1)`` to pixels, least
    squares over its star centres; frames with fewer than ``min_features`` (at least 4) features, or
    whose points give none, are left out."""
    order = np.argsort(table.frame, kind="stable")
    names, starts = np.unique(table.frame[order], return_index=True)
    out: dict[str, np.ndarray] = {}
    for name, rows in zip(names.tolist(), np.split(order, starts[1:]), strict=True):
        if len(rows) < max(min_features, 4):
            continue
        src = np.column_stack([table.X[rows], table.Y[rows]])
        dst = np.column_stack([table.x[rows], table.y[rows]])
        H, _ = cv2.findHomography(src, dst, 0)
        if H is not None and np.all(np.isfinite(H)):
            out[str(name)] = H
    return out


def _centred(homographies: list[np.ndarray], size: tuple[int, int]) -> np.ndarray:
    """``(F, 3, 3)``: the homographies to pixels relative to the image centre, each scaled to a
    unit upper-left ``2 x 2`` block (Frobenius)."""
    w, h = size
    T = np.array([[1.0, 0.0, -(w - 1) / 2], [0.0, 1.0, -(h - 1) / 2], [0.0, 0.0, 1.0]])
    Hc = T @ np.stack(homographies)
    return cast(np.ndarray, Hc / np.linalg.norm(Hc[:, :2, :2], axis=(1, 2))[:, None, None])


def rough_focal(homographies: list[np.ndarray], size: tuple[int, int]) -> tuple[float | None, float]:
    """The focal length (px) the homographies' perspective gives, and its relative standard error
    (module docstring): ``(None, inf)`` when there is none (``f^2 <= 0``) or fewer than one
    homography."""
    if not homographies:
        return None, math.inf
    Hc = _centred(homographies, size)
    h1, h2 = Hc[:, :, 0], Hc[:, :, 1]
    a = np.concatenate([h1[:, 0] * h2[:, 0] + h1[:, 1] * h2[:, 1],
                        h1[:, 0] ** 2 + h1[:, 1] ** 2 - h2[:, 0] ** 2 - h2[:, 1] ** 2])
    b = np.concatenate([h1[:, 2] * h2[:, 2], h1[:, 2] ** 2 - h2[:, 2] ** 2])
    bb = float(b @ b)
    if not bb > 0:
        return None, math.inf
    u = -float(a @ b) / bb
    if not u > 0:
        return None, math.inf
    residual = a + u * b
    sigma_u = math.sqrt(float(residual @ residual) / max(len(a) - 1, 1) / bb)
    return math.sqrt(u), sigma_u / (2.0 * u)


def plane_normals(homographies: list[np.ndarray], size: tuple[int, int], focal_px: float) -> np.ndarray:
    """``(F, 3)`` unit normals of the frames' target planes in the camera frame (towards the
    camera's side, ``n_z >= 0``), for a pinhole of ``focal_px`` centred on the image."""
    Hc = _centred(homographies, size)
    M = np.diag([1.0 / focal_px, 1.0 / focal_px, 1.0]) @ Hc
    r1 = M[:, :, 0] / np.linalg.norm(M[:, :, 0], axis=1, keepdims=True)
    r2 = M[:, :, 1] / np.linalg.norm(M[:, :, 1], axis=1, keepdims=True)
    n = np.cross(r1, r2)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n * np.where(n[:, 2:] < 0, -1.0, 1.0)


def _spread_deg(normals: np.ndarray) -> float:
    """The largest angle (deg) between two normals: among the vertices of the convex hull of
    their gnomonic projections ``(n_x, n_y) / n_z`` (great circles map to lines, so the farthest
    pair is among them)."""
    if len(normals) < 2:
        return 0.0
    t = normals[:, :2] / np.maximum(normals[:, 2:], 1e-9)
    hull = cv2.convexHull(t.astype(np.float32), returnPoints=False).reshape(-1)
    n = normals[np.unique(hull)]
    return float(np.degrees(np.arccos(np.clip((n @ n.T).min(), -1.0, 1.0))))


def _coverage(table: FeatureTable, size: tuple[int, int]) -> tuple[float, list[str]]:
    """Share of the image's cells holding features, and the names of the image's ninths holding
    any (``top-left``, ..., ``centre``)."""
    w, h = size
    c = COVERAGE_CELLS
    cx = np.clip(np.floor((table.x + 0.5) / w * c).astype(np.int64), 0, c - 1)
    cy = np.clip(np.floor((table.y + 0.5) / h * c).astype(np.int64), 0, c - 1)
    cells = np.zeros((c, c), dtype=bool)
    cells[cy, cx] = True
    ninths = {(int(y) * 3 // c, int(x) * 3 // c) for y, x in zip(*np.nonzero(cells), strict=True)}
    names = ["centre" if (y, x) == (1, 1) else f"{_REGIONS[0][y]}-{_REGIONS[1][x]}"
             for y, x in sorted(ninths)]
    return float(cells.mean()), names


def check_capture(table: FeatureTable, size: tuple[int, int], what: str = "sharp frames",
                  min_features: int = 20, settings: CaptureSettings | None = None) -> CaptureCheck:
    """Measure a capture's pose diversity and coverage and decide whether it can give a camera
    (module docstring).

    Args:
        table: the features of the frames the parametric camera is calibrated from (distinct
            views; px, OpenCV convention; metric target points ``X``, ``Y``).
        size: ``(width, height)`` px.
        what: the frames as the messages name them.
        min_features: frames with fewer features are not measured (the parametric stage does not
            use them either).
        settings: the thresholds.
    Returns:
        The figures, a refusal (one line) or None, and the warnings. Fewer than two measured
        frames are left to the calibration's own frame count.
    """
    s = settings or CaptureSettings()
    homographies = list(frame_homographies(table, min_features).values())
    coverage, regions = _coverage(table, size) if len(table) else (0.0, [])
    focal, error = rough_focal(homographies, size)
    if focal is not None and error > MAX_FOCAL_ERROR:
        focal = None
    tilts: list[float] = []
    spread = 0.0
    if focal is not None:
        normals = plane_normals(homographies, size, focal)
        tilts = sorted(np.degrees(np.arccos(np.clip(normals[:, 2], -1.0, 1.0))).tolist(), reverse=True)
        spread = _spread_deg(normals)
    check = CaptureCheck(len(homographies), focal, error, tilts, spread, coverage)
    if len(homographies) < 2:
        return check
    problems = _problems(check, what, s)
    refusals = [text for refuse, text in problems if refuse]
    if refusals and s.refuse:
        check.refusal = f"degenerate capture: {refusals[0]}"
    check.warnings = [text for refuse, text in problems if not refuse or not s.refuse]
    if coverage < s.warn_coverage:
        check.warnings.append(f"the features of the {what} cover {coverage:.0%} of the image "
                              f"({', '.join(regions)} of its ninths): the camera elsewhere is extrapolated; "
                              f"move the target into every part of the image, corners included")
    if len(homographies) < s.warn_frames:
        check.warnings.append(f"{len(homographies)} {what}: below {s.warn_frames} the projection "
                              f"uncertainty can understate the camera's error several-fold; add frames")
    return check


_ADVICE = "tilt the target 20 to 45 degrees from face-on, about different axes, in at least 3 frames"


def _problems(c: CaptureCheck, what: str, s: CaptureSettings) -> list[tuple[bool, str]]:
    """``(refuse, line)`` for each pose problem of a capture of at least two measured frames."""
    n = f"{c.frames} {what}"
    if c.focal_px is None:
        return [(True, f"the {n} all see the target nearly face-on: their perspective gives no "
                       f"focal length, and a calibration from them can be hundreds of pixels off; {_ADVICE}")]
    k = min(s.tilted_frames, c.frames)
    tilt = c.tilt_deg[k - 1]
    which = "the most tilted" if k == 1 else f"the {_ordinal(k)} most tilted"
    out = []
    apart = c.spread_deg < s.refuse_spread_deg
    if tilt < s.warn_tilt_deg:
        out.append((tilt < s.refuse_tilt_deg,
                    f"the {n} see the target nearly face-on ({which} {tilt:.1f} deg from it, "
                    f"focal length about {c.focal_px:.0f} px): the focal length is "
                    f"{'not measurable' if tilt < s.refuse_tilt_deg else 'weakly determined'}; {_ADVICE}"))
    if c.spread_deg < s.warn_spread_deg:
        out.append((apart,
                    f"the {n} see the target at nearly one orientation (its normals within "
                    f"{c.spread_deg:.1f} deg of each other): the focal length and the principal point "
                    f"{'cannot be told apart' if apart else 'are weakly determined'}"
                    f"; vary the target's tilt between frames, about different axes"))
    return out


def _ordinal(k: int) -> str:
    return {2: "2nd", 3: "3rd"}.get(k, f"{k}th")
