"""The same target points seen through two patterns: the feature-level cross-pattern residual.

Two feature sets of one camera at the same poses (e.g. the 16-segment star and the four-segment
checkerboard shown in turn on a monitor, the target maybe moved a little on the screen between
them) should place each target point consistently. :func:`cross_residuals` matches the two sets
on ``(frame, feature_id)``, takes both into undistorted pixels with a camera (so that a plane's
two images differ by a homography exactly), fits one homography per frame from set ``a`` to set
``b`` (which absorbs the target's move on the screen and any focal-length-like scale), and returns
``b``'s residual against ``a`` mapped through it, in distorted pixels::

    r = x_b - pi(H_f u_a),   u = pi^-1(x) (undistorted px),   H_f = argmin sum |u_b - H_f u_a|^2

split into its radial and tangential components about the principal point.
:func:`radial_profile` bins them by radius with a z-score (the bin's mean over its standard
error). A feature definition that depends on the pattern shows here as a radial profile that
differs from zero where random error cannot explain it; :func:`check_patterns` names it so
(systematic error: a bin whose radial mean is both beyond ``z_limit`` standard errors and larger
than ``limit_px``), with the two patterns' Brown-Conrady focal lengths beside it.

The cameras too: :func:`compare_cameras` takes the generic cameras calibrated from each pattern
alone and compares them over the image (each pixel's ray in ``a``, after the best-fit rotation of
``a``'s rays onto ``b``'s, projected by ``b``: ``d(u) = pi_b(Q ray_a(u)) - u``) against what
their projection uncertainties predict for two independent estimates of one camera,
``sqrt(sigma_a(u)^2 + sigma_b(u)^2)``; the RMS ratio of the two is about 1 when random error
explains the difference, and beyond ``ratio_limit`` it is named systematic. The focal-length
scale of ``b`` against ``a`` is the best-fit ``s`` of ``d(u) ~ t + s (u - c)`` (``c`` the image
centre).

Pixel convention: OpenCV (the centre of the top-left pixel is ``(0, 0)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np

from blurcalib.calib.uncertainty import ProjectionUncertainty
from blurcalib.camera.generic import CentralGeneric, best_fit_rotation
from blurcalib.camera.parametric import BrownConrady
from blurcalib.io.results import FeatureTable

__all__ = ["CameraComparison", "CrossResiduals", "PatternCheck", "RadialProfile", "check_patterns",
           "compare_cameras", "cross_residuals", "radial_profile"]

RATIO_LIMIT = 2.0
"""The cameras' RMS difference over what their uncertainties predict beyond which
:func:`compare_cameras` names it systematic: random error gives about 1 (halves of one capture
0.4-0.8 on the real fixtures' camera)."""


@dataclass(frozen=True)
class CrossResiduals:
    """Set ``b``'s features against set ``a``'s through one homography per frame (``N`` matches).

    Attributes:
        frame: ``(N,)`` str; feature_id: ``(N,)`` int64.
        xy: ``(N, 2)`` px, set ``a``'s positions.
        residual: ``(N, 2)`` px, ``x_b - pi(H_f u_a)`` (module docstring).
        radius: ``(N,)`` px, distance of ``xy`` from ``centre``.
        radial, tangential: ``(N,)`` px, the residual along the outward radius and along the
            radius turned by +90 degrees (x towards y).
        inlier: ``(N,)`` bool, used in the homography fit (residual within the outlier limit).
        centre: ``(2,)`` px, the principal point of the camera used.
    """

    frame: np.ndarray
    feature_id: np.ndarray
    xy: np.ndarray
    residual: np.ndarray
    radius: np.ndarray
    radial: np.ndarray
    tangential: np.ndarray
    inlier: np.ndarray
    centre: np.ndarray

    @property
    def median_px(self) -> float:
        """Median residual length over inliers (px)."""
        return float(np.median(np.linalg.norm(self.residual[self.inlier], axis=1)))


@dataclass(frozen=True)
class RadialProfile:
    """Cross-pattern residual components binned by radius (``M`` bins).

    Attributes:
        edges: ``(M + 1,)`` px bin edges of the radius.
        count: ``(M,)`` inliers per bin.
        radial, tangential: ``(M,)`` px, mean components per bin (NaN for an empty bin).
        radial_sem: ``(M,)`` px, standard error of the radial mean.
        z: ``(M,)`` the radial mean over its standard error.
    """

    edges: np.ndarray
    count: np.ndarray
    radial: np.ndarray
    tangential: np.ndarray
    radial_sem: np.ndarray
    z: np.ndarray

    def rows(self) -> list[str]:
        """One printable line per bin."""
        return [f"{self.edges[i]:5.0f}-{self.edges[i + 1]:4.0f} px: n {self.count[i]:4d}, radial "
                f"{self.radial[i]:+.4f} +- {self.radial_sem[i]:.4f} px (z {self.z[i]:+5.1f}), tangential "
                f"{self.tangential[i]:+.4f} px" for i in range(len(self.count))]


def _undistorted_px(camera: BrownConrady, xy: np.ndarray) -> np.ndarray:
    """``(N, 2)`` distorted px -> undistorted px ``K pi^-1(x)``."""
    xn = camera.unproject(xy)
    return np.stack([camera.fx * xn[:, 0] + camera.cx, camera.fy * xn[:, 1] + camera.cy], axis=1)


def _distorted_px(camera: BrownConrady, u: np.ndarray) -> np.ndarray:
    """``(N, 2)`` undistorted px -> distorted px."""
    xn = np.stack([(u[:, 0] - camera.cx) / camera.fx, (u[:, 1] - camera.cy) / camera.fy], axis=1)
    d = camera.distort(xn)
    return np.stack([camera.fx * d[:, 0] + camera.cx, camera.fy * d[:, 1] + camera.cy], axis=1)


def _apply(H: np.ndarray, p: np.ndarray) -> np.ndarray:
    q = p @ H[:, :2].T + H[:, 2]
    return cast(np.ndarray, q[:, :2] / q[:, 2:])


def _fit_homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares homography ``dst ~ H src`` (normalised DLT, then Gauss-Newton on the
    geometric error in ``dst``)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    ss = np.sqrt(2.0) / max(np.sqrt(((src - ms) ** 2).sum(axis=1)).mean(), 1e-12)
    sd = np.sqrt(2.0) / max(np.sqrt(((dst - md) ** 2).sum(axis=1)).mean(), 1e-12)
    Ts = np.array([[ss, 0, -ss * ms[0]], [0, ss, -ss * ms[1]], [0, 0, 1.0]])
    Td = np.array([[sd, 0, -sd * md[0]], [0, sd, -sd * md[1]], [0, 0, 1.0]])
    a, b = _apply(Ts, src), _apply(Td, dst)
    n = len(a)
    A = np.zeros((2 * n, 9))
    A[:n, 0:2], A[:n, 2] = a, 1.0
    A[:n, 6:8], A[:n, 8] = -b[:, :1] * a, -b[:, 0]
    A[n:, 3:5], A[n:, 5] = a, 1.0
    A[n:, 6:8], A[n:, 8] = -b[:, 1:] * a, -b[:, 1]
    h = np.linalg.svd(A)[2][-1]
    G = h.reshape(3, 3) / h[8]
    for _ in range(5):  # Gauss-Newton on the 8 entries (h33 = 1), normalised coordinates
        q = a @ G[:, :2].T + G[:, 2]
        w = q[:, 2:]
        p = q[:, :2] / w
        J: np.ndarray = np.zeros((n, 2, 8))
        J[:, 0, 0:2], J[:, 0, 2] = a / w, 1.0 / w[:, 0]
        J[:, 1, 3:5], J[:, 1, 5] = a / w, 1.0 / w[:, 0]
        J[:, :, 6] = -p * a[:, :1] / w
        J[:, :, 7] = -p * a[:, 1:] / w
        J = J.reshape(2 * n, 8)
        r = (b - p).reshape(-1)
        step = np.linalg.lstsq(J, r, rcond=None)[0]
        G = G + np.append(step, 0.0).reshape(3, 3)
    return cast(np.ndarray, np.linalg.inv(Td) @ G @ Ts)


def cross_residuals(a: FeatureTable, b: FeatureTable, camera: BrownConrady, *, outlier_px: float = 0.3,
                    min_matches: int = 12) -> CrossResiduals:
    """``b``'s features against ``a``'s of the same ``(frame, feature_id)`` through one homography
    per frame in undistorted pixels of ``camera`` (module docstring).

    Each frame's homography is fitted twice: the second time without matches whose residual
    exceeds ``outlier_px`` or 5 robust sigmas of the first fit, whichever is larger (a feature
    that one set got wrong). Frames with fewer than ``min_matches`` matches are left out.

    Args:
        a, b: feature tables (px, OpenCV convention) of the two patterns.
        camera: the camera whose distortion is removed (e.g. calibrated from ``a``).
    Returns:
        :class:`CrossResiduals` of every match of the frames kept.
    """
    key_a = {(f, int(i)): k for k, (f, i) in enumerate(zip(a.frame, a.feature_id, strict=True))}
    rows_a, rows_b = [], []
    for k, (f, i) in enumerate(zip(b.frame, b.feature_id, strict=True)):
        j = key_a.get((f, int(i)))
        if j is not None and np.isfinite(a.x[j] + a.y[j] + b.x[k] + b.y[k]):
            rows_a.append(j)
            rows_b.append(k)
    ia, ib = np.asarray(rows_a, dtype=np.int64), np.asarray(rows_b, dtype=np.int64)
    xa = np.stack([a.x[ia], a.y[ia]], axis=1)
    xb = np.stack([b.x[ib], b.y[ib]], axis=1)
    frames = a.frame[ia]
    residual = np.full_like(xa, np.nan)
    inlier = np.zeros(len(ia), dtype=bool)
    for name in np.unique(frames):
        sel = np.flatnonzero(frames == name)
        if len(sel) < min_matches:
            continue
        ua, ub = _undistorted_px(camera, xa[sel]), _undistorted_px(camera, xb[sel])
        use = np.ones(len(sel), dtype=bool)
        for _ in range(2):
            H = _fit_homography(ua[use], ub[use])
            r = xb[sel] - _distorted_px(camera, _apply(H, ua))
            e = np.linalg.norm(r, axis=1)
            mad = 1.4826 * np.median(np.abs(e[use] - np.median(e[use])))
            use = e <= max(outlier_px, np.median(e[use]) + 5.0 * mad)
        residual[sel] = r
        inlier[sel] = use
    keep = np.all(np.isfinite(residual), axis=1)
    centre = np.array([camera.cx, camera.cy])
    d = xa[keep] - centre
    radius = np.linalg.norm(d, axis=1)
    unit = d / np.maximum(radius, 1e-9)[:, None]
    res = residual[keep]
    return CrossResiduals(frame=frames[keep], feature_id=a.feature_id[ia][keep], xy=xa[keep], residual=res,
                          radius=radius, radial=np.sum(res * unit, axis=1),
                          tangential=res[:, 1] * unit[:, 0] - res[:, 0] * unit[:, 1], inlier=inlier[keep],
                          centre=centre)


def radial_profile(res: CrossResiduals, edges: np.ndarray | None = None) -> RadialProfile:
    """The inliers' radial and tangential components binned by radius (default bins of 100 px
    up to the farthest feature)."""
    if edges is None:
        edges = np.arange(0.0, float(res.radius.max()) + 100.0, 100.0)
    edges = np.asarray(edges, dtype=np.float64)
    m = len(edges) - 1
    count = np.zeros(m, dtype=np.int64)
    rad, tan, sem = np.full(m, np.nan), np.full(m, np.nan), np.full(m, np.nan)
    for i in range(m):
        sel = res.inlier & (res.radius >= edges[i]) & (res.radius < edges[i + 1])
        count[i] = int(sel.sum())
        if count[i]:
            rad[i] = float(res.radial[sel].mean())
            tan[i] = float(res.tangential[sel].mean())
            sem[i] = float(res.radial[sel].std(ddof=1) / np.sqrt(count[i])) if count[i] > 1 else np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        z = rad / sem
    return RadialProfile(edges=edges, count=count, radial=rad, tangential=tan, radial_sem=sem, z=z)


@dataclass(frozen=True)
class PatternCheck:
    """Two patterns' features of one camera compared (:func:`check_patterns`).

    Attributes:
        profile: the feature-level residual's :class:`RadialProfile` (``b`` against ``a``).
        matches: inliers of the residual; frames: frames with a homography.
        median_px: median residual length (px).
        focal_pct: ``(2,)`` percent, ``b``'s camera's ``(fx, fy)`` over ``a``'s, minus one.
        worst_radial_px: the largest ``|radial mean|`` of a bin beyond ``z_limit`` (0 if none), px.
        systematic: a bin's radial mean exceeds ``z_limit`` standard errors and ``limit_px``.
        z_limit, limit_px: the thresholds used.
    """

    profile: RadialProfile
    matches: int
    frames: int
    median_px: float
    focal_pct: np.ndarray
    worst_radial_px: float
    systematic: bool
    z_limit: float
    limit_px: float

    def lines(self) -> list[str]:
        """The printable check: the verdict, the cameras' focal lengths, the profile by radius."""
        verdict = (f"systematic error: the two patterns place the same target points up to "
                   f"{self.worst_radial_px:.4f} px apart radially, beyond noise (|z| >= {self.z_limit:g})"
                   if self.systematic else
                   f"no systematic error found: every radius bin within {self.limit_px:g} px or "
                   f"{self.z_limit:g} standard errors")
        return [verdict,
                f"{self.matches} matches in {self.frames} frames, median {self.median_px:.4f} px; second "
                f"camera's focal lengths {self.focal_pct[0]:+.3f} % / {self.focal_pct[1]:+.3f} %",
                *self.profile.rows()]


def check_patterns(a: FeatureTable, b: FeatureTable, camera_a: BrownConrady, camera_b: BrownConrady, *,
                   edges: np.ndarray | None = None, z_limit: float = 5.0, limit_px: float = 0.01
                   ) -> PatternCheck:
    """Compare two patterns' features of one camera at the same poses: :func:`cross_residuals` of
    ``b`` against ``a`` in ``camera_a``'s undistorted pixels, binned by :func:`radial_profile`, and
    the verdict (module docstring).

    Args:
        a, b: feature tables (px, OpenCV convention) of the two patterns, frames named alike.
        camera_a, camera_b: the Brown-Conrady cameras calibrated from ``a`` and from ``b``.
        z_limit: a bin's radial mean over its standard error beyond which noise does not explain it.
        limit_px: radial means up to this are not reported as systematic (px).
    Raises:
        ValueError: no frame has enough matches.
    """
    res = cross_residuals(a, b, camera_a)
    if not res.inlier.any():
        raise ValueError("the two feature sets share no frame with enough matching features")
    profile = radial_profile(res, edges)
    beyond = np.abs(np.nan_to_num(profile.z)) >= z_limit
    worst = float(np.max(np.abs(profile.radial[beyond]))) if beyond.any() else 0.0
    focal = 100.0 * np.array([camera_b.fx / camera_a.fx - 1.0, camera_b.fy / camera_a.fy - 1.0])
    return PatternCheck(profile=profile, matches=int(res.inlier.sum()), frames=len(set(res.frame.tolist())),
                        median_px=res.median_px, focal_pct=focal, worst_radial_px=worst,
                        systematic=worst > limit_px, z_limit=z_limit, limit_px=limit_px)


@dataclass(frozen=True)
class CameraComparison:
    """Two generic cameras of one physical camera compared against their uncertainty
    (:func:`compare_cameras`; module docstring).

    Attributes:
        median_px, p90_px, rms_px: the difference ``|d(u)|`` over the lattice pixels both cameras
            cover (px).
        predicted_rms_px: RMS of ``sqrt(sigma_a^2 + sigma_b^2)`` there (px).
        ratio: ``rms_px / predicted_rms_px``.
        scale_pct: ``b``'s focal-length scale against ``a`` (percent).
        shape_median_px: median ``|d(u)|`` after the best-fit shift and scale (px).
        pixels: lattice pixels compared.
        systematic: ``ratio > ratio_limit``; ratio_limit: the threshold used.
    """

    median_px: float
    p90_px: float
    rms_px: float
    predicted_rms_px: float
    ratio: float
    scale_pct: float
    shape_median_px: float
    pixels: int
    systematic: bool
    ratio_limit: float

    def verdict(self, a: str = "the first pattern", b: str = "the second") -> str:
        """The plain-words verdict."""
        scale = (f"; focal-length scale {self.scale_pct:+.3f} %, the rest {self.shape_median_px:.4f} px "
                 f"median")
        if self.systematic:
            return (f"systematic difference between patterns: the cameras of {a} and {b} differ by "
                    f"{self.rms_px:.4f} px RMS ({self.median_px:.4f} px median), {self.ratio:.1f} x what "
                    f"their uncertainties predict ({self.predicted_rms_px:.4f} px): random error does not "
                    f"explain it{scale}")
        return (f"the cameras of {a} and {b} agree within their uncertainty: {self.rms_px:.4f} px RMS "
                f"({self.median_px:.4f} px median), {self.ratio:.1f} x the {self.predicted_rms_px:.4f} px "
                f"predicted{scale}")

    def to_dict(self) -> dict[str, float | int | bool]:
        return {k: (round(v, 5) if isinstance(v, float) else v) for k, v in vars(self).items()}


def compare_cameras(a: CentralGeneric, unc_a: ProjectionUncertainty, b: CentralGeneric,
                    unc_b: ProjectionUncertainty, ratio_limit: float = RATIO_LIMIT) -> CameraComparison:
    """Compare the generic cameras ``a`` and ``b`` (e.g. of two patterns alone) on ``unc_a``'s
    lattice against their projection uncertainties (module docstring).

    Raises:
        ValueError: different image sizes, or no lattice pixel that both cameras cover.
    """
    if (a.width, a.height) != (b.width, b.height):
        raise ValueError(f"image sizes differ: {a.width} x {a.height} and {b.width} x {b.height}")
    px = np.column_stack([unc_a.x, unc_a.y])
    ray_a, ray_b = a.pixel_to_ray(px), b.pixel_to_ray(px)
    ok = np.all(np.isfinite(ray_a), axis=1) & np.all(np.isfinite(ray_b), axis=1)
    if ok.sum() < 3:
        raise ValueError("the two cameras' calibrated areas do not overlap")
    Q = best_fit_rotation(ray_a[ok], ray_b[ok])
    u, inside = b.project(np.where(ok[:, None], ray_a, [0.0, 0.0, 1.0]) @ Q.T, init=px)
    predicted = np.hypot(unc_a.sigma_px, unc_b.at(px))
    ok &= inside & np.isfinite(predicted)
    if ok.sum() < 3:
        raise ValueError("the two cameras' calibrated areas do not overlap")
    d, px, predicted = (u - px)[ok], px[ok], predicted[ok]
    norm = np.linalg.norm(d, axis=1)
    centre = np.array([(a.width - 1) / 2.0, (a.height - 1) / 2.0])
    rel = px - centre
    design = np.zeros((2 * len(d), 3))
    design[0::2, 0], design[1::2, 1] = 1.0, 1.0
    design[:, 2] = rel.reshape(-1)
    coef = np.linalg.lstsq(design, d.reshape(-1), rcond=None)[0]
    shape = np.linalg.norm((d.reshape(-1) - design @ coef).reshape(-1, 2), axis=1)
    rms, pred = float(np.sqrt(np.mean(norm ** 2))), float(np.sqrt(np.mean(predicted ** 2)))
    ratio = rms / pred if pred > 0 else float("inf")
    return CameraComparison(median_px=float(np.median(norm)), p90_px=float(np.percentile(norm, 90)),
                            rms_px=rms, predicted_rms_px=pred, ratio=ratio, scale_pct=100.0 * float(coef[2]),
                            shape_median_px=float(np.median(shape)), pixels=int(ok.sum()),
                            systematic=bool(ratio > ratio_limit), ratio_limit=ratio_limit)
