"""A frame's own noise: the signal-dependent (Poisson-Gaussian) variance, estimated from the image.

A camera's raw grey level ``I`` at a true level ``mu`` has the variance::

    var(I | mu) = a + b mu        (grey levels^2)

``b`` the grey levels per photo-electron (shot noise, ``1 / b`` electrons per grey level) and ``a``
the signal-independent part (read noise, quantisation, the dark offset's shot noise). The loss of a
block (its mean squared residual) is, for a model that fits, the mean of this variance over the
block's pixels, so the loss threshold is expressed in it (:mod:`blurcalib.growth.quality`).

The estimate (:func:`estimate_noise`) uses the image alone, so that it exists before any block is
fitted and does not absorb the model errors the loss threshold is there to catch:

1. the high-pass residual ``r = (I * N) / 6`` with Immerkær's mask
   ``N = [1, -2, 1]^T [1, -2, 1]`` (J. Immerkær, *Fast noise variance estimation*, CVIU 1996):
   it cancels every bilinear function of ``(x, y)``, so flat areas and straight blurred ramps leave
   only noise, and white noise of variance ``s^2`` gives ``var(r) = s^2``;
2. the level ``mu`` of each pixel: the 3 x 3 mean of ``I``; pixels whose 3 x 3 neighbourhood
   touches the clipping levels are left out, and of the others every other row and column is
   used;
3. pixels sorted into levels (equal-count bins); in each bin only the third with the smallest
   gradient of the smoothed image (Gaussian, sigma 2 px) is kept, which drops the edges and
   corners whose curvature the mask does not cancel, and the bin's variance is
   ``(1.4826 median |r|)^2`` (robust to the edges that remain);
4. ``a, b`` by least squares on the bins' variances, weighted by their precision, ``a, b >= 0``.

A bin's variance is at least that of rounding to whole grey levels of the 8-bit scale,
:data:`QUANTISATION_VAR`: where a camera's noise is well below a grey level, flat areas round to
one level (or, in a colour frame or a video, to one colour), the residual's median is 0 and such a
bin would read no noise at all, at a precision that outweighed every other bin
(docs/decisions/noise-quantisation-floor.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

_MAD_TO_SIGMA = 1.4826
"""Standard deviation per median absolute deviation of a Gaussian."""

QUANTISATION_VAR = 1.0 / 12.0
"""Variance (grey levels^2) of rounding to whole grey levels of the 8-bit scale: the least a level
bin reads (:func:`estimate_noise`). Frames come as 8-bit grey levels, or as colour or 16-bit
ones rounded at least as finely; the loss limits do not fall below their values at 2 grey levels
(:func:`blurcalib.growth.quality.noise_scale`), so the floor changes none of them."""


@dataclass(frozen=True)
class NoiseModel:
    """A frame's noise ``var(I | mu) = a + b mu`` (grey levels^2, ``mu`` in grey levels).

    Attributes:
        a: signal-independent variance (grey levels^2).
        b: variance per grey level of signal (grey levels; ``1 / b`` electrons per grey level).
        level: a representative level of the frame (grey levels): the midpoint of the 5th and 95th
            percentiles of its unclipped pixels' levels, at which :attr:`sigma` is quoted.
    """

    a: float
    b: float
    level: float

    def variance(self, mu: np.ndarray | float) -> np.ndarray:
        """``a + b mu`` (grey levels^2) at levels ``mu`` (grey levels; any shape)."""
        return self.a + self.b * np.maximum(np.asarray(mu, dtype=np.float64), 0.0)

    def block_variance(self, coeffs: np.ndarray) -> np.ndarray:
        """``(B,)`` the variance at the mean level of blocks with the brightness coefficients
        ``coeffs (B, 6)`` ``(a1, a2, a3, b1, b2, b3)`` of :class:`blurcalib.deconv.result.BlockFit`
        (grey levels^2; NaN where not fitted). The star is half paper, half ink and the gradients
        vanish at the window's centre, so the mean level is ``b3 + a3 / 2``."""
        coeffs = np.asarray(coeffs, dtype=np.float64).reshape(-1, 6)
        return self.variance(coeffs[:, 5] + coeffs[:, 2] / 2.0)

    @property
    def sigma(self) -> float:
        """Noise standard deviation at :attr:`level` (grey levels): the frame's ``noise_dn``."""
        return float(np.sqrt(self.variance(self.level)))


def highpass_residual(image: np.ndarray) -> np.ndarray:
    """``(H, W)``: Immerkær's residual ``(I * N) / 6``, unit gain on white noise (border pixels
    computed with reflection; callers leave them out)."""
    d2 = np.array([1.0, -2.0, 1.0])
    return cv2.sepFilter2D(np.asarray(image, dtype=np.float64), cv2.CV_64F, d2, d2 / 6.0,
                           borderType=cv2.BORDER_REFLECT)


def estimate_noise(image: np.ndarray, bins: int = 12, clip: tuple[float, float] = (0.0, 255.0),
                   min_pixels: int = 200) -> NoiseModel:
    """The noise model of one frame ``image (H, W)`` (grey levels), from its pixels alone.

    Args:
        image: the frame.
        bins: level bins (equal pixel counts) of the fit.
        clip: the frame's clipping levels (grey levels); pixels within 0.5 of them, and their
            neighbours, are left out.
        min_pixels: fewest kept pixels per bin.
    Raises:
        ValueError: the image is not 2-D or has too few unclipped pixels (fewer than
            ``bins * min_pixels`` after the edge selection).
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be (height, width), got shape {img.shape}")
    r = highpass_residual(img)
    mu = cv2.blur(img, (3, 3), borderType=cv2.BORDER_REFLECT)
    lo = cv2.erode(img, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REFLECT)
    hi = cv2.dilate(img, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REFLECT)
    smooth = cv2.GaussianBlur(img, (0, 0), 2.0, borderType=cv2.BORDER_REFLECT)
    grad = np.hypot(cv2.Sobel(smooth, cv2.CV_64F, 1, 0), cv2.Sobel(smooth, cv2.CV_64F, 0, 1))
    ok = (lo > clip[0] + 0.5) & (hi < clip[1] - 0.5) & np.isfinite(r)
    ok[:2, :] = ok[-2:, :] = False
    ok[:, :2] = ok[:, -2:] = False
    ok[1::2, :] = False  # every other row and column: plenty of pixels, a quarter of the sorting
    ok[:, 1::2] = False
    mu, r, grad = mu[ok], r[ok], grad[ok]
    if mu.size < 3 * bins * min_pixels:
        raise ValueError(f"too few unclipped pixels for a noise estimate: {mu.size}")
    order = np.argsort(mu, kind="stable")
    levels, variances, weights = [], [], []
    for part in np.array_split(order, bins):
        flat = part[grad[part] <= np.quantile(grad[part], 1.0 / 3.0)]
        if flat.size < min_pixels:
            continue
        var = max((_MAD_TO_SIGMA * float(np.median(np.abs(r[flat])))) ** 2, QUANTISATION_VAR)
        levels.append(float(np.mean(mu[flat])))
        variances.append(var)
        weights.append(flat.size / var**2)  # precision of a variance ~ n / var^2
    a, b = _fit_affine(np.array(levels), np.array(variances), np.array(weights))
    lo_level, hi_level = np.percentile(mu, [5.0, 95.0])
    return NoiseModel(a, b, float((lo_level + hi_level) / 2))


def _fit_affine(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """``(a, b) >= 0`` minimising ``sum w (a + b x - y)^2`` (the constrained optimum lies on an
    edge when the free one is outside the quadrant)."""
    sw = np.sqrt(w)
    A = np.stack([np.ones_like(x), x], axis=1) * sw[:, None]
    t = y * sw
    (a, b), *_ = np.linalg.lstsq(A, t, rcond=None)
    if a >= 0 and b >= 0:
        return float(a), float(b)
    only_a = float(max(np.sum(w * y) / np.sum(w), 0.0))
    only_b = float(max(np.sum(w * x * y) / max(np.sum(w * x * x), 1e-12), 0.0))
    cost_a = np.sum(w * (only_a - y) ** 2)
    cost_b = np.sum(w * (only_b * x - y) ** 2)
    return (only_a, 0.0) if cost_a <= cost_b else (0.0, only_b)


def frame_noise(image: np.ndarray) -> NoiseModel | None:
    """:func:`estimate_noise` of a frame, None when it has too few unclipped pixels."""
    try:
        return estimate_noise(image)
    except ValueError:
        return None
