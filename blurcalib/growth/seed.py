"""Seeding: find the target's AprilTag and the homography that starts region growing.

Blur defeats tag detectors, so detection is retried on downscaled copies of the frame (a blur of
``b`` px is ``b s`` px at scale ``s``, while the tag's cells stay several pixels wide). From about
15 px of blur that is not enough: the tag's one-cell white ring is blurred into the star field and
no quad is found at any scale. Then the frame is deblurred (:func:`detect_tags_deblurred`): a
straight motion blur ``k(theta, l)`` is assumed, its direction ``theta`` taken from the image's
structure tensor (blur along ``theta`` removes gradient energy along ``theta``; the star field's
gradients are otherwise isotropic), and half-scale Wiener deconvolutions
``F^-1[conj(K) F(I) / (|K|^2 + nsr)]`` for a few lengths ``l`` and directions near ``theta`` are
searched until the detector finds a tag of the pattern (its decoded id is the check; the growth
that follows verifies the homography block by block). A caller can instead pass a homography it
already has (the previous frame of a sequence, or four corners clicked in the GUI).

In a sequence (a video, a folder of numbered frames) a frame whose tag is not found is seeded
from the star centres of its nearest extracted neighbour (:func:`homography_from_features`), and
the labelling its growth ends with is verified against the frame's own pixels
(:func:`check_labelling`): the star field is periodic, so a seed a square off would fit every
block and mislabel every feature; only the tag and the target's border can rule that out.

The seed is a homography ``H_f`` from *feature coordinates* (see ``docs/conventions.md``) to
image pixels (OpenCV convention); a block's homography is ``H_f B(fx, fy)`` with
``B = [[1/2, 0, fx], [0, 1/2, fy], [0, 0, 1]]`` mapping block coordinates to feature coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np

from blurcalib.target.pattern import StarPattern

DEFAULT_SCALES = (1.0, 0.5, 0.35, 0.25)
"""Image scales tried in turn for tag detection."""

DEBLUR_LENGTHS_PX = (12.0, 16.0, 20.0, 24.0, 28.0, 32.0, 8.0)
"""Straight-blur lengths (full-resolution px) tried by :func:`detect_tags_deblurred`, in order."""

DEBLUR_ANGLES_RAD = (0.0, 0.26, -0.26)
"""Offsets from the structure-tensor blur direction tried by :func:`detect_tags_deblurred`."""

APRILTAG_REFINEMENT_OFFSET_PX = 0.5
"""aruco's CORNER_REFINE_APRILTAG corners sit +0.5 px from the OpenCV pixel-centre convention
(against simulated frames' true corners; pupil-apriltags does the same)."""


APRILTAG_QUAD_SIGMA_PX = 0.8
"""Gaussian blur (px) of the AprilTag quad detector's thresholded copy (aruco's
``aprilTagQuadSigma``; 0 in OpenCV). Image noise breaks the tag's edges into many small clusters
whose line fits are most of a detection's time; the blur makes a detection several times faster
and finds as many tags or more. The deblurred search (:func:`detect_tags_deblurred`) keeps the
unblurred detector, whose corners seed heavily blurred frames better
(docs/decisions/tag-detector-quad-sigma.md)."""


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
        method: how the frame was seeded: ``"tag"`` (detected as is), ``"tag_deblurred"``
            (detected after a Wiener deblur, :func:`detect_tags_deblurred`) or ``"given"``.
        blur: ``(length px, direction rad)`` of the straight blur the deblur assumed (NaN when
            none).
    """

    H_feature: np.ndarray
    tag_index: int
    corners_px: np.ndarray
    scale: float
    source: str
    method: str = "tag"
    blur: tuple[float, float] = (float("nan"), float("nan"))


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


def _detector(quad_sigma_px: float = 0.0) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    params.aprilTagQuadSigma = quad_sigma_px
    return cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)


def _detect_once(detector: cv2.aruco.ArucoDetector, grey: np.ndarray, scale: float
                 ) -> dict[int, np.ndarray]:
    """Tags in ``grey`` (uint8, an image at ``scale``), corners in full-resolution px."""
    corners, ids, _ = detector.detectMarkers(grey)
    if ids is None:
        return {}
    return {int(i): (c.reshape(4, 2).astype(np.float64) - APRILTAG_REFINEMENT_OFFSET_PX + 0.5)
            / scale - 0.5 for c, i in zip(corners, ids.ravel(), strict=True)}


def blur_direction(image: np.ndarray) -> float:
    """Direction (rad, x right, y down, in ``[0, pi)``) along which ``image (H, W)`` is most blurred.

    The eigenvector of the smallest eigenvalue of the structure tensor ``sum grad I grad I^T``:
    a motion blur along ``theta`` averages the gradient component along ``theta`` away.
    """
    img = np.asarray(image, dtype=np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1)
    T = np.array([[float(np.mean(gx * gx)), float(np.mean(gx * gy))],
                  [float(np.mean(gx * gy)), float(np.mean(gy * gy))]])
    _, vecs = np.linalg.eigh(T)
    return float(np.arctan2(vecs[1, 0], vecs[0, 0]) % np.pi)


def line_kernel(length: float, angle: float) -> np.ndarray:
    """``(K, K)`` straight motion blur of ``length`` px along ``angle`` (rad), centred, sum 1
    (bilinear splat of the path, ``K`` odd)."""
    size = 2 * int(np.ceil(length / 2)) + 3
    c = size // 2
    t = np.linspace(-length / 2, length / 2, max(8, int(4 * length)))
    x, y = c + t * np.cos(angle), c + t * np.sin(angle)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    k = np.zeros((size, size))
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy),
                      (1, 1, fx * fy)):
        np.add.at(k, (y0 + dy, x0 + dx), w)
    return cast(np.ndarray, k / k.sum())


def wiener_deblur(image: np.ndarray, kernel: np.ndarray, nsr: float = 0.01) -> np.ndarray:
    """Wiener deconvolution ``F^-1[conj(K) F(I) / (|K|^2 + nsr)]`` of ``image (H, W)`` by a
    centred ``kernel (K, K)``; the image is mirror-padded by ``K`` px against wrap-around."""
    img = np.asarray(image, dtype=np.float64)
    ks = kernel.shape[0]
    mean = img.mean()
    padded = cv2.copyMakeBorder(img - mean, ks, ks, ks, ks, cv2.BORDER_REFLECT)
    kpad = np.zeros_like(padded)
    kpad[:ks, :ks] = kernel
    kpad = np.roll(kpad, (-(ks // 2), -(ks // 2)), axis=(0, 1))
    F = np.fft.rfft2(kpad)
    out = np.fft.irfft2(np.fft.rfft2(padded) * np.conj(F) / (np.abs(F) ** 2 + nsr), s=padded.shape)
    return cast(np.ndarray, out[ks:-ks, ks:-ks] + mean)


def detect_tags_deblurred(image: np.ndarray, wanted: set[int], scale: float = 0.5,
                          lengths: tuple[float, ...] = DEBLUR_LENGTHS_PX,
                          angles: tuple[float, ...] = DEBLUR_ANGLES_RAD, nsr: float = 0.01
                          ) -> tuple[dict[int, np.ndarray], tuple[float, float]]:
    """Detect tags on Wiener-deblurred copies of ``image`` (see the module docstring).

    Args:
        image: ``(H, W)`` grey levels.
        wanted: tag ids that end the search.
        scale: image scale of the search.
        lengths: straight-blur lengths tried (full-resolution px), in order.
        angles: offsets (rad) from :func:`blur_direction` tried for each length.
        nsr: Wiener noise-to-signal ratio.
    Returns:
        ``({tag id: (4, 2) corners, full-resolution px}, (length, angle))`` of the first
        deblur that reveals a wanted tag; ``({}, (nan, nan))`` when none does.
    """
    grey = np.clip(np.asarray(image, dtype=np.float64), 0, 255)
    small = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    theta = blur_direction(small)
    detector = _detector()
    for length in lengths:
        for offset in angles:
            k = line_kernel(length * scale, theta + offset)
            sharp = np.clip(wiener_deblur(small, k, nsr), 0, 255).astype(np.uint8)
            found = _detect_once(detector, sharp, scale)
            if wanted & found.keys():
                return found, (float(length), float((theta + offset) % np.pi))
    return {}, (float("nan"), float("nan"))


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
    detector = _detector(APRILTAG_QUAD_SIGMA_PX)
    for s in scales:
        img = grey if s == 1.0 else cv2.resize(grey, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        found = _detect_once(detector, img, s)
        if found:
            return found, s
    return {}, 0.0


@dataclass(frozen=True)
class TagSearch:
    """Where :func:`seed_frame`'s tag detection looked and what it found, to show a user why a
    frame was not seeded.

    Attributes:
        scales: the image scales searched (:data:`DEFAULT_SCALES`).
        found: ``{tag id: (4, 2) corners}`` px of every tag decoded at any scale (the pattern's or
            not).
        rejected: ``(Q, 4, 2)`` px, the candidate quads the detector rejected (its
            ``rejectedImgPoints``: a quad whose cells did not decode) at any scale, full-resolution
            px (OpenCV convention).
    """

    scales: tuple[float, ...]
    found: dict[int, np.ndarray]
    rejected: np.ndarray


def search_tags(image: np.ndarray, scales: tuple[float, ...] = DEFAULT_SCALES) -> TagSearch:
    """Run :func:`detect_tags`'s detector at every scale of ``scales`` on ``image (H, W)`` (grey
    levels) and collect the tags it decodes and the candidate quads it rejects."""
    grey = np.clip(np.asarray(image), 0, 255).astype(np.uint8)
    detector = _detector(APRILTAG_QUAD_SIGMA_PX)
    found: dict[int, np.ndarray] = {}
    rejected: list[np.ndarray] = []
    for s in scales:
        img = grey if s == 1.0 else cv2.resize(grey, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        corners, ids, bad = detector.detectMarkers(img)
        for c, i in zip(corners, ids.ravel() if ids is not None else (), strict=True):
            corner = c.reshape(4, 2).astype(np.float64) - APRILTAG_REFINEMENT_OFFSET_PX + 0.5
            found.setdefault(int(i), corner / s - 0.5)
        rejected.extend((q.reshape(4, 2).astype(np.float64) + 0.5) / s - 0.5 for q in bad)
    quads = np.stack(rejected) if rejected else np.zeros((0, 4, 2))
    return TagSearch(tuple(scales), found, quads)


def seed_frame(image: np.ndarray, pattern: StarPattern, H_feature: np.ndarray | None = None,
               scales: tuple[float, ...] = DEFAULT_SCALES, deblur: bool = True) -> Seed:
    """Find the homography from feature coordinates to the image.

    Args:
        image: ``(H, W)`` grey levels.
        pattern: the target.
        H_feature: a homography the caller already has (used as is).
        scales: detection scales (see :func:`detect_tags`).
        deblur: when no tag of the pattern is found at any scale, search Wiener-deblurred copies
            (:func:`detect_tags_deblurred`).
    Raises:
        SeedError: no tag of ``pattern`` was found at any scale (nor after deblurring).
    """
    if H_feature is not None:
        H = np.asarray(H_feature, dtype=np.float64)
        if H.shape != (3, 3) or not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-12:
            raise SeedError("the given homography is not a finite, invertible 3x3 matrix")
        return Seed(H / H[2, 2], -1, np.zeros((0, 2)), 1.0, "given", "given")
    found, scale = detect_tags(image, scales)
    wanted = {t.index: t for t in pattern.apriltags}
    matches = [(i, c) for i, c in found.items() if i in wanted]
    method, blur = "tag", (float("nan"), float("nan"))
    if not matches and deblur:
        deblurred, blur = detect_tags_deblurred(image, set(wanted))
        matches = [(i, c) for i, c in deblurred.items() if i in wanted]
        method, scale = "tag_deblurred", 0.5
    if not matches:
        seen = f" (found tag ids {sorted(found)}, the pattern has {sorted(wanted)})" if found else ""
        tried = " or after deblurring" if deblur else ""
        raise SeedError(f"no AprilTag of the pattern found at scales {list(scales)}{tried}{seen}")
    index, corners = matches[0]
    src = pattern.tag_corners(wanted[index]).astype(np.float32)
    H = cv2.getPerspectiveTransform(src, corners.astype(np.float32)).astype(np.float64)
    return Seed(H / H[2, 2], index, corners, scale, "tag", method, blur)


def tag_ring_features(pattern: StarPattern) -> np.ndarray:
    """``(M, 2)`` valid features in the ring just outside each tag's blocked box: the first
    blocks to grow from a tag seed."""
    ring = []
    for tag in pattern.apriltags:
        x0, y0, x1, y1 = tag.feature_box
        for fy in range(y0 - 1, y1 + 2):
            for fx in range(x0 - 1, x1 + 2):
                if (fx in (x0 - 1, x1 + 1) or fy in (y0 - 1, y1 + 1)) and \
                        bool(pattern.is_valid_feature(np.asarray(fx), np.asarray(fy))):
                    ring.append((fx, fy))
    return np.array(ring, dtype=np.int64).reshape(-1, 2)


# ------------------------------------------------------------------------ sequence seeding
LABEL_SHIFTS: tuple[tuple[int, int], ...] = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1),
                                             (-1, -1))
"""Whole-square shifts of the labelling that :func:`check_labelling` rules out (feature units)."""

MAX_LABEL_RATIO = 0.5
"""A labelling is accepted when, on the pixels that tell it from every shift in
:data:`LABEL_SHIFTS`, its squared residual is below this share of the shifted one's."""

MIN_TELLING_PIXELS = 100
"""Fewest pixels (at the check's working scale) that must tell a labelling from each shift."""

_CHECK_PIXELS = 120_000
"""The frame is checked at the scale that leaves at most this many pixels."""


@dataclass(frozen=True)
class LabelCheck:
    """Outcome of :func:`check_labelling`.

    Attributes:
        accepted: the labelling is the best of the shifts by the margin :data:`MAX_LABEL_RATIO`.
        ratio: the largest ratio of the labelling's squared residual to a shifted one's, on the
            pixels that tell them apart (NaN when some shift cannot be told apart).
        pixels: fewest telling pixels over the shifts (at the working scale).
        reason: why it was refused (empty when accepted).
    """

    accepted: bool
    ratio: float
    pixels: int
    reason: str


def homography_from_features(fx: np.ndarray, fy: np.ndarray, x: np.ndarray, y: np.ndarray,
                             threshold_px: float = 2.0) -> np.ndarray | None:
    """``(3, 3)`` homography from feature coordinates ``(fx, fy)`` to star centres ``(x, y)`` px
    (RANSAC, ``threshold_px``), normalised to ``H[2, 2] = 1``; None from fewer than 8 points or
    when no homography fits them."""
    src = np.column_stack([fx, fy]).astype(np.float64)
    dst = np.column_stack([x, y]).astype(np.float64)
    ok = np.all(np.isfinite(dst), axis=1)
    if ok.sum() < 8:
        return None
    H, _ = cv2.findHomography(src[ok], dst[ok], cv2.RANSAC, threshold_px)
    if H is None or not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
        return None
    return cast(np.ndarray, H / H[2, 2])


def render_target(pattern: StarPattern, H_feature: np.ndarray, shape: tuple[int, int],
                  scale: float = 1.0, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The target as the frame would show it without blur: ``(image, on_page)``, both ``(h, w)``
    at ``scale`` (``shape`` is the full-resolution ``(H, W)``).

    ``image`` is :meth:`StarPattern.intensity` (1 white, 0 black) averaged over ``supersample^2``
    points per pixel, each full-resolution point ``u`` mapped to feature coordinates by
    ``H_feature^-1 u``; ``on_page`` says which pixels fall on the page (elsewhere the
    background is unknown).
    """
    h, w = (max(1, round(n * scale)) for n in shape)
    Hinv = np.linalg.inv(np.asarray(H_feature, dtype=np.float64))
    x0, y0, x1, y1 = pattern.page_mm_to_feature(np.array([[0.0, 0.0], [pattern.page.width_mm,
                                                                      pattern.page.height_mm]])).ravel()
    image = np.zeros((h, w), dtype=np.float64)
    on_page = np.ones((h, w), dtype=bool)
    offsets = (np.arange(supersample) + 0.5) / supersample
    for oy in offsets:
        for ox in offsets:
            u = (np.arange(w) + ox) / scale - 0.5
            v = (np.arange(h) + oy) / scale - 0.5
            uu, vv = np.meshgrid(u, v)
            q = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ Hinv.T
            with np.errstate(divide="ignore", invalid="ignore"):
                p = q[..., :2] / q[..., 2:3]
            inside = (q[..., 2] > 0) & (p[..., 0] >= x0) & (p[..., 0] <= x1) & (p[..., 1] >= y0) \
                & (p[..., 1] <= y1)
            on_page &= inside
            image += np.where(inside, pattern.intensity(np.where(inside[..., None], p, 0.0)), 1.0)
    return (image / supersample**2).astype(np.float32), on_page


def check_labelling(image: np.ndarray, pattern: StarPattern, H_feature: np.ndarray,
                    psf: np.ndarray | None = None, shifts: tuple[tuple[int, int], ...] = LABEL_SHIFTS,
                    max_ratio: float = MAX_LABEL_RATIO, min_pixels: int = MIN_TELLING_PIXELS
                    ) -> LabelCheck:
    """Whether ``H_feature`` (feature coordinates -> px) labels the frame's stars correctly,
    rather than a whole number of squares off.

    The star field is periodic, so a labelling shifted by a square fits every block as well;
    only the tag and the pattern's border tell them apart. The target is rendered under the
    labelling ``H`` and under each shifted one ``H T(dx, dy)`` (:func:`render_target`), blurred
    by ``psf`` (the frame's PSF, a true convolution), and mapped to grey levels by
    ``a + b r`` fitted to the frame on the page under ``H``. On the pixels where the two renders
    differ by more than a quarter of the white-black contrast, the labelling must leave a
    squared residual below ``max_ratio`` times the shifted one's, for every shift, each told on
    at least ``min_pixels`` pixels.

    Args:
        image: ``(H, W)`` grey levels.
        pattern: the target.
        H_feature: ``(3, 3)`` the labelling to check.
        psf: ``(K, K)`` PSF (full-resolution px, sum 1), or None for no blur.
        shifts: the shifts ruled out (feature units, squares).
        max_ratio, min_pixels: the acceptance margin and the telling pixels required.
    """
    img = np.asarray(image, dtype=np.float32)
    scale = min(1.0, float(np.sqrt(_CHECK_PIXELS / img.size)))
    small = img if scale == 1.0 else cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    kernel = None
    if psf is not None:
        k: np.ndarray = np.clip(np.asarray(psf, dtype=np.float32), 0, None)
        size = max(1, round(k.shape[0] * scale)) | 1
        k = cv2.resize(k, (size, size), interpolation=cv2.INTER_AREA) if size != k.shape[0] else k
        kernel = k[::-1, ::-1] / k.sum() if k.sum() > 0 else None

    def render(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, page = render_target(pattern, H, img.shape, scale)
        if kernel is not None:
            r = cv2.filter2D(r, -1, kernel, borderType=cv2.BORDER_REPLICATE)
        return r, page

    H0 = np.asarray(H_feature, dtype=np.float64)
    r0, page0 = render(H0)
    A = np.column_stack([np.ones(int(page0.sum())), r0[page0]])
    if A.shape[0] < 3 or np.ptp(r0[page0]) == 0:
        return LabelCheck(False, float("nan"), 0, "the target is not in view")
    (a, b), *_ = np.linalg.lstsq(A, small[page0], rcond=None)
    if not b > 0:
        return LabelCheck(False, float("nan"), 0, "the frame does not show the target's contrast")
    worst, fewest = 0.0, None
    for dx, dy in shifts:
        T = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
        rs, pages = render(H0 @ T)
        telling = page0 & pages & (np.abs(rs - r0) > 0.25)
        n = int(telling.sum())
        fewest = n if fewest is None else min(fewest, n)
        if n < min_pixels:
            return LabelCheck(False, float("nan"), n, f"a shift of ({dx}, {dy}) squares cannot be told "
                                                      f"apart ({n} telling pixels): neither the tag nor "
                                                      f"the target's border is in view")
        res0 = float(np.sum((small[telling] - a - b * r0[telling]) ** 2))
        ress = float(np.sum((small[telling] - a - b * rs[telling]) ** 2))
        worst = max(worst, res0 / max(ress, 1e-12))
    if worst >= max_ratio:
        fits = "better than" if worst > 1 else "nearly as well as"
        return LabelCheck(False, worst, int(fewest or 0), f"a labelling a square off fits the frame {fits} "
                                                          f"this one (residual ratio {worst:.2f})")
    return LabelCheck(True, worst, int(fewest or 0), "")
