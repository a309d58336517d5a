"""Pattern comparison (paper section "Patterns Comparison", figure ``fig:exp2_test``).

A 15 x 15 glyph kernel is the sole unknown of the paper's local deconvolution
(``eq:deconvolution``): the geometry ``H`` and the brightness ``A = 1, B = 0`` are fixed to the
truth, so the problem is the ridge least squares

    ``k* = argmin_k  mean_x (I(x) - (k * L)(x))^2 + lam ||k||^2``

over the ``K^2`` kernel values, solved in closed form from the ``K^2 x K^2`` normal equations.
It is run on the 16-segment star pattern and on a checkerboard with the same square size, over
80 x 80 and 160 x 160 px crops, with and without 5% Gaussian noise, and the recovered kernels are
scored against the truth with SSIM and PSNR.

Units: latent images are intensities in ``[0, 1]`` (0 black ink, 1 white paper); noise levels are
fractions of that range; kernels follow ``docs/conventions.md`` (``k[i, j]`` weights the offset
``(j - c, i - c)`` px, ``I(x) = sum_d k(d) L(x - d)``) and sum to 1.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.font_manager import FontProperties
from matplotlib.path import Path as MplPath
from matplotlib.textpath import TextPath
from scipy.ndimage import gaussian_filter
from scipy.signal import convolve2d, correlate2d

from blurcalib.io.atomic import atomic_path, atomic_write_text, ensure_writable_dir
from blurcalib.paper.common import Option, experiment_parser, run_experiment_cli, settings_from
from blurcalib.target.star import star_sector_white

PATTERNS: tuple[str, ...] = ("star", "checkerboard")
"""The calibration patterns compared: the 16-segment star and a checkerboard."""

GLYPHS: tuple[str, ...] = ("a", "g", "R", "&")
"""The four glyphs used as blur kernels (the paper's figure also shows four)."""

GLYPH_FONT = Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSerif-Italic.ttf"
"""The glyph font: DejaVu Serif Italic, shipped with matplotlib (the paper's Lucida Handwriting
is not freely available)."""

PAPER_NOISY: dict[str, tuple[float, float]] = {"star": (0.96, 22.0), "checkerboard": (0.58, 13.0)}
"""The paper's scores with 5% noise, ``(SSIM, PSNR dB)``: "SSIM of approximately 0.96 and PSNR
above 22 dB" for the star, "approximately 0.58 and 13 dB" for the checkerboard. Without noise
the paper reports both patterns as comparable, without numbers."""


@dataclass(frozen=True)
class PatternSettings:
    """Fixed choices of the experiment.

    Attributes:
        kernel_size: K, the kernel side (px, odd).
        glyph_sigma: sigma of the Gaussian that smooths the resized glyph (px).
        glyph_margin_px: empty border around the glyph's bounding box in the K x K raster (px).
        square_px: side of one pattern square (star cell or checkerboard square) in pixels.
        rotation: angle of the pattern axes against the pixel grid (radians), the known geometry.
        num_segments: N, the star's segment count.
        supersample: samples per pixel side when rendering the latent images (box filter).
        lam: ridge weight ``lam`` of ``eq:deconvolution``, against the *mean* squared residual
            (so it does not depend on the crop size), intensities in [0, 1].
        nonneg: clip negative kernel values to 0 after the solve.
        unit_sum: rescale the solved kernel to sum 1 (a PSF's sum; done after clipping).
    """

    kernel_size: int = 15
    glyph_sigma: float = 0.8
    glyph_margin_px: float = 1.0
    square_px: float = 32.0
    rotation: float = 0.0
    num_segments: int = 16
    supersample: int = 8
    lam: float = 1e-3
    nonneg: bool = True
    unit_sum: bool = True

    def __post_init__(self) -> None:
        if self.kernel_size < 3 or self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd and >= 3, got {self.kernel_size}")
        if not self.square_px > 0:
            raise ValueError(f"square_px must be positive, got {self.square_px}")
        if not self.lam >= 0:
            raise ValueError(f"lam must be >= 0, got {self.lam}")
        if self.supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")


@dataclass(frozen=True)
class PatternResult:
    """One configuration of the comparison and its scores.

    Attributes:
        pattern: ``"star"`` or ``"checkerboard"``.
        glyph: the character whose glyph is the true kernel.
        crop: side of the observed image (px).
        noise: Gaussian noise sigma as a fraction of the intensity range (0.05 is the paper's 5%).
        ssim: SSIM between recovered and true kernel, both scaled by the true kernel's max.
        psnr: PSNR (dB) of the recovered kernel, peak = the true kernel's max.
        kernel: ``(K, K)`` the recovered kernel.
    """

    pattern: str
    glyph: str
    crop: int
    noise: float
    ssim: float
    psnr: float
    kernel: np.ndarray = field(repr=False, compare=False)


# ----------------------------------------------------------------------------------- kernels
def glyph_kernel(char: str, size: int = 15, sigma: float = 0.8, margin_px: float = 1.0,
                 supersample: int = 16) -> np.ndarray:
    """A glyph of :data:`GLYPH_FONT` as a blur kernel, as in the paper's pattern comparison.

    The glyph outline is rasterised on a ``size * supersample`` square grid (even-odd rule, so
    counters stay empty); its bounding box, aspect kept, fills the raster less ``margin_px`` on
    each side. The raster is ink coverage (the colour-inverted glyph: strokes bright), area-
    resized to ``size x size``, smoothed by a Gaussian of ``sigma`` px and normalised to sum 1.

    Args:
        char: one character.
        size: K, the kernel side (px).
        sigma: Gaussian smoothing (px); the paper's 0.8.
        margin_px: empty border (px) before smoothing.
        supersample: raster samples per kernel pixel side.
    Returns:
        ``(size, size)`` float64, non-negative, sum 1.
    Raises:
        ValueError: not one character, a character with no outline (e.g. a space), or a margin
            leaving no room.
    """
    if len(char) != 1:
        raise ValueError(f"a glyph is one character, got {char!r}")
    if char.isspace():
        raise ValueError(f"glyph {char!r} has no outline")
    inner = size - 2.0 * margin_px
    if inner <= 0:
        raise ValueError(f"margin {margin_px} px leaves no room in a {size} px kernel")
    text = TextPath((0.0, 0.0), char, size=1.0, prop=FontProperties(fname=GLYPH_FONT))
    if len(text.vertices) == 0:
        raise ValueError(f"glyph {char!r} has no outline")
    polygons = text.to_polygons(closed_only=True)
    ext = text.get_extents()
    scale = inner / max(ext.width, ext.height)
    n = size * supersample
    centres = (np.arange(n) + 0.5) / supersample
    x, y = np.meshgrid(centres, centres)
    points = np.stack([((x - size / 2.0) / scale + 0.5 * (ext.x0 + ext.x1)).ravel(),
                       (-(y - size / 2.0) / scale + 0.5 * (ext.y0 + ext.y1)).ravel()], axis=1)
    ink = np.zeros(len(points), dtype=bool)
    for poly in polygons:
        ink ^= MplPath(poly).contains_points(points)
    coverage = ink.reshape(size, supersample, size, supersample).mean(axis=(1, 3))
    kernel = gaussian_filter(coverage, sigma, mode="constant")
    return cast(np.ndarray, kernel / kernel.sum())


# ------------------------------------------------------------------------------ latent images
def centred_homography(size: int, square_px: float, rotation: float = 0.0) -> np.ndarray:
    """``(3, 3)`` homography from pattern coordinates (squares) to the pixels of a latent image.

    Pattern point ``(0, 0)`` (a star centre, a checkerboard corner) lands on the centre of the
    ``size x size`` image, ``square_px`` px per square, the pattern axes turned by ``rotation``
    (radians, from +x towards +y) from the pixel grid.
    """
    c = (size - 1) / 2.0
    cos, sin = square_px * math.cos(rotation), square_px * math.sin(rotation)
    return np.array([[cos, -sin, c], [sin, cos, c], [0.0, 0.0, 1.0]])


def pattern_intensity(pattern: str, p: np.ndarray, num_segments: int = 16) -> np.ndarray:
    """Exact intensity (1 white, 0 black) of ``pattern`` at pattern coordinates ``p (..., 2)``.

    The star pattern has a star of ``num_segments`` segments centred on every integer point
    (``star_sector_white``, the target's convention); the checkerboard has its corners on the
    integer points and square ``(i, j)`` white when ``i + j`` is odd.
    """
    px, py = p[..., 0], p[..., 1]
    if pattern == "star":
        return star_sector_white(px - np.round(px), py - np.round(py), num_segments).astype(float)
    if pattern == "checkerboard":
        return cast(np.ndarray, np.mod(np.floor(px) + np.floor(py), 2.0))
    raise ValueError(f"unknown pattern {pattern!r}; expected one of {', '.join(PATTERNS)}")


def latent_image(pattern: str, size: int, square_px: float = 32.0, num_segments: int = 16,
                 homography: np.ndarray | None = None, supersample: int = 8) -> np.ndarray:
    """Anti-aliased latent image ``L`` of a pattern seen through a known homography.

    Args:
        pattern: ``"star"`` or ``"checkerboard"``.
        size: image side (px).
        square_px: pixels per square when ``homography`` is None (:func:`centred_homography`).
        num_segments: N of the star.
        homography: ``(3, 3)`` pattern coordinates to pixels (OpenCV pixel centres).
        supersample: samples per pixel side; pixel ``(i, j)`` averages its area
            ``[j - 0.5, j + 0.5] x [i - 0.5, i + 0.5]``.
    Returns:
        ``(size, size)`` float64 intensities in [0, 1].
    """
    h = centred_homography(size, square_px) if homography is None else np.asarray(homography, float)
    sub = (np.arange(size * supersample) + 0.5) / supersample - 0.5
    x, y = np.meshgrid(sub, sub)
    pix = np.stack([x, y, np.ones_like(x)], axis=-1) @ np.linalg.inv(h).T
    p = pix[..., :2] / pix[..., 2:]
    value = pattern_intensity(pattern, p, num_segments)
    return cast(np.ndarray, value.reshape(size, supersample, size, supersample).mean(axis=(1, 3)))


def window_gram(latent: np.ndarray, kernel_size: int) -> np.ndarray:
    """``W = V^T V`` for the matrix ``V`` of all ``K x K`` windows of ``latent`` (valid positions).

    ``W[a, b] = sum_{y, x} L[y + a1, x + a2] L[y + b1, x + b2]`` over the ``(H - K + 1) x
    (W - K + 1)`` window positions, with ``a = a1 K + a2`` and ``b`` the flattened in-window
    offsets. Each lag ``b - a`` is one product image summed over ``K x K`` boxes by an integral
    image, which avoids a large multi-threaded matrix product (slow on busy machines).

    Args:
        latent: ``(H, W)``.
        kernel_size: K.
    Returns:
        ``(K^2, K^2)`` symmetric positive semi-definite.
    """
    k = kernel_size
    h, w = latent.shape
    nh, nw = h - k + 1, w - k + 1
    pad = k - 1
    padded = np.zeros((h + 2 * pad, w + 2 * pad))
    padded[pad:pad + h, pad:pad + w] = latent
    a1, a2 = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    gram = np.empty((k * k, k * k))
    integral = np.zeros((h + 1, w + 1))
    for d1 in range(0, k):
        for d2 in range(-k + 1, k):
            if d1 == 0 and d2 < 0:
                continue
            product = latent * padded[pad + d1:pad + d1 + h, pad + d2:pad + d2 + w]
            np.cumsum(np.cumsum(product, axis=0), axis=1, out=integral[1:, 1:])
            box = (integral[nh:nh + k, nw:nw + k] - integral[:k, nw:nw + k]
                   - integral[nh:nh + k, :k] + integral[:k, :k])
            ok = (a1 + d1 < k) & (a2 + d2 >= 0) & (a2 + d2 < k)
            ia = (a1 * k + a2)[ok]
            ib = ((a1 + d1) * k + a2 + d2)[ok]
            gram[ia, ib] = box[ok]
            gram[ib, ia] = box[ok]
    return gram


def blur_valid(latent: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """The observed image ``I = k * L`` on the valid region.

    Args:
        latent: ``(S, S)``.
        kernel: ``(K, K)``, convention of ``docs/conventions.md``.
    Returns:
        ``(S - K + 1, S - K + 1)``; pixel ``(y, x)`` sees latent pixel ``(y + c, x + c)``.
    """
    return cast(np.ndarray, convolve2d(latent, kernel, mode="valid"))


# ----------------------------------------------------------------------------------- solver
class KernelSolver:
    """Closed-form ridge solve of ``eq:deconvolution`` for the kernel alone, for one latent.

    The design matrix ``D`` (``N x K^2``, N observed pixels) holds, for each observed pixel, the
    latent window that the kernel weights, so ``D vec(k) = vec(k * L)``. The normal matrix
    ``G = D^T D / N`` (:func:`window_gram`, without forming ``D``) is eigendecomposed once; each
    solve then costs one ``K x K`` valid correlation of ``L`` with ``I``.
    """

    def __init__(self, latent: np.ndarray, kernel_size: int, lam: float) -> None:
        """Args: latent ``(S, S)``; kernel_size K (odd); lam the ridge weight (>= 0)."""
        if lam < 0:
            raise ValueError(f"lam must be >= 0, got {lam}")
        self.latent = np.asarray(latent, dtype=np.float64)
        self.kernel_size = kernel_size
        self.lam = lam
        self.num_pixels = (self.latent.shape[0] - kernel_size + 1) * (self.latent.shape[1] - kernel_size + 1)
        gram = window_gram(self.latent, kernel_size)[::-1, ::-1] / self.num_pixels
        self.eigenvalues, self.eigenvectors = np.linalg.eigh(gram)

    @property
    def noise_gain(self) -> float:
        """RMS error per kernel value of the unregularised solve, per unit of noise sigma.

        ``sqrt(trace((D^T D)^-1) / K^2)``: the noise amplification of the pattern (lower is
        better; it is infinite when the kernel is not identifiable from the pattern).
        """
        if self.eigenvalues[0] <= 0:
            return math.inf
        return float(np.sqrt(np.sum(1.0 / self.eigenvalues) / self.num_pixels / self.eigenvalues.size))

    def solve(self, observed: np.ndarray, nonneg: bool = True, unit_sum: bool = True) -> np.ndarray:
        """The kernel minimising ``mean (I - k * L)^2 + lam ||k||^2``.

        Args:
            observed: ``(S - K + 1, S - K + 1)`` image ``I``.
            nonneg: clip negative values to 0 afterwards.
            unit_sum: rescale to sum 1 afterwards (unless the sum is not positive).
        Returns:
            ``(K, K)`` kernel.
        """
        rhs = correlate2d(self.latent, np.asarray(observed, dtype=np.float64), mode="valid")
        rhs = rhs[::-1, ::-1].ravel() / self.num_pixels
        denom = self.eigenvalues + self.lam
        tiny = denom <= 1e-12 * max(float(denom[-1]), 1e-300)
        coef = (self.eigenvectors.T @ rhs) / np.where(tiny, 1.0, denom)
        coef[tiny] = 0.0
        kernel = (self.eigenvectors @ coef).reshape(self.kernel_size, self.kernel_size)
        if nonneg:
            kernel = np.clip(kernel, 0.0, None)
        total = kernel.sum()
        if unit_sum and total > 0:
            kernel = kernel / total
        return cast(np.ndarray, kernel)


# ---------------------------------------------------------------------------------- metrics
def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0, sigma: float = 1.5,
         radius: int = 5) -> float:
    """Mean SSIM (Wang et al. 2004) with a Gaussian window, over the window's valid positions.

    As the authors' reference code: an 11 x 11 Gaussian window of sigma 1.5, ``C1 = (0.01 R)^2``,
    ``C2 = (0.03 R)^2`` with ``R = data_range``, local (population) statistics, the SSIM map over
    the positions where the window lies inside the image, averaged.

    Args:
        a, b: ``(H, W)`` images, ``H, W >= 2 radius + 1``.
        data_range: R, the dynamic range of the values.
        sigma: window sigma (px).
        radius: window half-size (px).
    Returns:
        SSIM in [-1, 1]; exactly 1 for identical images.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or min(a.shape) < 2 * radius + 1:
        raise ValueError(f"need equal shapes of at least {2 * radius + 1} px, got {a.shape}, {b.shape}")
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    inner = (slice(radius, a.shape[0] - radius), slice(radius, a.shape[1] - radius))

    def local_mean(z: np.ndarray) -> np.ndarray:
        return cast(np.ndarray, gaussian_filter(z, sigma, mode="constant", truncate=radius / sigma)[inner])

    mu_a, mu_b = local_mean(a), local_mean(b)
    var_a = local_mean(a * a) - mu_a**2
    var_b = local_mean(b * b) - mu_b**2
    cov = local_mean(a * b) - mu_a * mu_b
    ssim_map = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)
                / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)))
    return float(ssim_map.mean())


def psnr(estimate: np.ndarray, truth: np.ndarray, peak: float | None = None) -> float:
    """PSNR in dB, ``10 log10(peak^2 / MSE)``; ``peak`` defaults to ``truth.max()``.

    Returns ``inf`` for identical arrays.
    """
    peak = float(np.max(truth)) if peak is None else peak
    mse = float(np.mean((np.asarray(estimate, float) - np.asarray(truth, float)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(peak**2 / mse)


def kernel_scores(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """``(SSIM, PSNR dB)`` of a recovered kernel, both kernels scaled by the true kernel's max."""
    peak = float(np.max(truth))
    return ssim(estimate / peak, truth / peak, data_range=1.0), psnr(estimate / peak, truth / peak, 1.0)


# ------------------------------------------------------------------------------- experiment
def experiment_latent(pattern: str, crop: int, settings: PatternSettings) -> np.ndarray:
    """The ``(crop + K - 1)`` px square latent whose valid blur is the ``crop x crop`` observation,
    with the pattern's point ``(0, 0)`` at its centre (:func:`centred_homography`)."""
    size = crop + settings.kernel_size - 1
    return latent_image(pattern, size, num_segments=settings.num_segments,
                        homography=centred_homography(size, settings.square_px, settings.rotation),
                        supersample=settings.supersample)


def pattern_solvers(crops: Sequence[int] = (80, 160),
                    settings: PatternSettings | None = None) -> dict[tuple[str, int], KernelSolver]:
    """One :class:`KernelSolver` per ``(pattern, crop)`` on its :func:`experiment_latent`."""
    settings = PatternSettings() if settings is None else settings
    return {(pattern, int(crop)): KernelSolver(experiment_latent(pattern, crop, settings),
                                               settings.kernel_size, settings.lam)
            for pattern in PATTERNS for crop in crops}


def run_pattern_experiment(seed: int = 0, crops: Sequence[int] = (80, 160),
                           noise_levels: Sequence[float] = (0.0, 0.05),
                           glyphs: Sequence[str] = GLYPHS,
                           settings: PatternSettings | None = None,
                           solvers: dict[tuple[str, int], KernelSolver] | None = None,
                           ) -> list[PatternResult]:
    """Recover every glyph kernel from both patterns, each crop and noise level (``fig:exp2_test``).

    For each pattern and crop ``C`` the latent is ``(C + K - 1)`` px square, so the observed
    image (valid convolution) is ``C x C`` px; Gaussian noise of ``noise`` times the latent's
    intensity range is added, drawn from ``default_rng([seed, pattern, glyph, crop, noise])``
    (the pattern's index in :data:`PATTERNS`, the glyph's code point, the crop in px, the noise
    in millionths), so a configuration's noise does not depend on the other configurations run.

    Args:
        seed: noise seed (>= 0).
        crops: observed image sides (px).
        noise_levels: noise sigmas as fractions of the intensity range.
        glyphs: characters of the true kernels (:func:`glyph_kernel`).
        settings: the fixed choices (default :class:`PatternSettings`).
        solvers: :func:`pattern_solvers` of the same crops and settings, to reuse them.
    Returns:
        One row per (pattern, glyph, crop, noise), in that nesting order.
    """
    settings = PatternSettings() if settings is None else settings
    solvers = pattern_solvers(crops, settings) if solvers is None else solvers
    k = settings.kernel_size
    truths = {g: glyph_kernel(g, k, settings.glyph_sigma, settings.glyph_margin_px) for g in glyphs}
    results = []
    for pi, pattern in enumerate(PATTERNS):
        for crop in crops:
            solver = solvers[pattern, int(crop)]
            sigma_scale = float(solver.latent.max() - solver.latent.min())
            for g in glyphs:
                clean = blur_valid(solver.latent, truths[g])
                for noise in noise_levels:
                    rng = np.random.default_rng([seed, pi, ord(g), int(crop), round(noise * 1e6)])
                    observed = clean + noise * sigma_scale * rng.standard_normal(clean.shape)
                    estimate = solver.solve(observed, settings.nonneg, settings.unit_sum)
                    s, p = kernel_scores(estimate, truths[g])
                    results.append(PatternResult(pattern, g, int(crop), float(noise), s, p, estimate))
    results.sort(key=lambda r: (PATTERNS.index(r.pattern), glyphs.index(r.glyph), r.crop, r.noise))
    return results


def noise_gains(solvers: dict[tuple[str, int], KernelSolver]) -> dict[tuple[str, int], float]:
    """:attr:`KernelSolver.noise_gain` of each ``(pattern, crop)`` of :func:`pattern_solvers`: how
    much each pattern amplifies noise into the unregularised kernel (the paper's argument, made
    quantitative; independent of ``lam``)."""
    return {key: solver.noise_gain for key, solver in solvers.items()}


def mean_scores(results: Sequence[PatternResult]) -> dict[tuple[str, float], tuple[float, float]]:
    """Mean ``(SSIM, PSNR dB)`` over glyphs and crops for each ``(pattern, noise)``."""
    groups: dict[tuple[str, float], list[PatternResult]] = {}
    for r in results:
        groups.setdefault((r.pattern, r.noise), []).append(r)
    return {key: (float(np.mean([r.ssim for r in rows])), float(np.mean([r.psnr for r in rows])))
            for key, rows in groups.items()}


def _paper_cell(pattern: str, noise: float) -> str:
    if noise == 0.0:
        return "comparable"
    if math.isclose(noise, 0.05) and pattern in PAPER_NOISY:
        s, p = PAPER_NOISY[pattern]
        return f"~{s:.2f}  {'>' if pattern == 'star' else '~'}{p:.0f}"
    return "-"


def format_table(results: Sequence[PatternResult]) -> str:
    """Every configuration's SSIM/PSNR, then the means per (pattern, noise) beside the paper's."""
    lines = ["Pattern comparison (paper fig:exp2_test): recovered glyph kernels",
             f"{'pattern':<13} {'glyph':>5} {'crop':>5} {'noise':>6} {'SSIM':>7} {'PSNR dB':>8}"]
    for r in results:
        lines.append(f"{r.pattern:<13} {r.glyph:>5} {r.crop:>5} {r.noise:>6.0%} {r.ssim:>7.3f} "
                     f"{r.psnr:>8.1f}")
    lines += ["", "Means over glyphs and crops        measured          paper",
              f"{'pattern':<13} {'noise':>6} {'SSIM':>9} {'PSNR dB':>8}    {'SSIM  PSNR dB':>15}"]
    for (pattern, noise), (s, p) in mean_scores(results).items():
        lines.append(f"{pattern:<13} {noise:>6.0%} {s:>9.3f} {p:>8.1f}    "
                     f"{_paper_cell(pattern, noise):>15}")
    return "\n".join(lines)


def results_json(results: Sequence[PatternResult], settings: PatternSettings, seed: int,
                 gains: dict[tuple[str, int], float]) -> dict[str, Any]:
    """The experiment as a JSON-able dict (PSNR ``inf`` is written as ``null``)."""
    def finite(v: float) -> float | None:
        return v if math.isfinite(v) else None

    return {
        "experiment": "patterns",
        "paper": "fig:exp2_test",
        "seed": seed,
        "settings": asdict(settings),
        "glyph_font": GLYPH_FONT.name,
        "rows": [{"pattern": r.pattern, "glyph": r.glyph, "crop": r.crop, "noise": r.noise,
                  "ssim": r.ssim, "psnr": finite(r.psnr)} for r in results],
        "means": [{"pattern": pattern, "noise": noise, "ssim": s, "psnr": finite(p)}
                  for (pattern, noise), (s, p) in mean_scores(results).items()],
        "noise_gain": [{"pattern": pattern, "crop": crop, "gain": finite(g)}
                       for (pattern, crop), g in gains.items()],
        "paper_noisy": {pattern: {"ssim": s, "psnr": p} for pattern, (s, p) in PAPER_NOISY.items()},
    }


def save_figure(results: Sequence[PatternResult], kernels: dict[str, np.ndarray],
                path: str | Path) -> Path:
    """Write a PNG grid like ``fig:exp2_test``, atomically.

    Rows are glyphs; the first column is the true kernel, then one column per (noise, pattern,
    crop) with the recovered kernel and its SSIM / PSNR. Every panel of a row shares the grey
    scale ``[0, max of the true kernel]``.

    Args:
        results: rows of :func:`run_pattern_experiment`.
        kernels: the true kernel of each glyph, ``{glyph: (K, K)}``.
        path: destination PNG.
    """
    glyphs = [g for g in kernels if any(r.glyph == g for r in results)]
    columns = sorted({(r.noise, PATTERNS.index(r.pattern), r.crop) for r in results})
    by_key = {(r.glyph, r.noise, r.pattern, r.crop): r for r in results}
    fig = Figure(figsize=(1.25 * (len(columns) + 1), 1.45 * len(glyphs) + 0.4), dpi=120)
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(glyphs), len(columns) + 1, squeeze=False)
    for row, g in enumerate(glyphs):
        truth = kernels[g]
        panels = [("true kernel", truth, "")]
        for noise, pi, crop in columns:
            r = by_key.get((g, noise, PATTERNS[pi], crop))
            if r is not None:
                panels.append((f"{PATTERNS[pi]}\n{crop} px, {noise:.0%} noise", r.kernel,
                               f"{r.ssim:.2f} / {r.psnr:.1f} dB"))
        for col, ax in enumerate(axes[row]):
            ax.set_xticks([])
            ax.set_yticks([])
            if col >= len(panels):
                ax.set_axis_off()
                continue
            title, image, score = panels[col]
            ax.imshow(image, cmap="gray", vmin=0.0, vmax=float(truth.max()), interpolation="nearest")
            ax.set_xlabel(score, fontsize=7)
            if row == 0:
                ax.set_title(title, fontsize=7)
            if col == 0:
                ax.set_ylabel(repr(g), fontsize=9)
    fig.suptitle("Recovered 15x15 glyph kernels: SSIM / PSNR (paper fig:exp2_test)", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


# --------------------------------------------------------------------------------- command
OPTIONS: tuple[Option, ...] = (
    Option("--lam", "lam", "ridge weight on ||k||^2 against the mean squared residual"),
    Option("--square-px", "square_px", "pattern square side in pixels"))
"""The options of ``blurcalib experiment patterns``."""


def build_parser() -> argparse.ArgumentParser:
    """Options of ``blurcalib experiment patterns``."""
    return experiment_parser(
        "patterns", "Reproduce the paper's pattern comparison (fig:exp2_test): recover 15x15 "
                    "glyph kernels from star and checkerboard images with the geometry fixed.",
        "patterns.png and patterns.json", PatternSettings, OPTIONS)


def _run(args: argparse.Namespace) -> list[Path]:
    settings = settings_from(PatternSettings, OPTIONS, args)
    out = ensure_writable_dir(args.out)
    solvers = pattern_solvers(settings=settings)
    results = run_pattern_experiment(seed=args.seed, settings=settings, solvers=solvers)
    gains = noise_gains(solvers)
    kernels = {g: glyph_kernel(g, settings.kernel_size, settings.glyph_sigma,
                               settings.glyph_margin_px) for g in GLYPHS}
    print(format_table(results))
    print("\nNoise gain of the unregularised solve (RMS kernel error per unit noise sigma):")
    for (pattern, crop), gain in gains.items():
        print(f"  {pattern:<13} {crop:>4} px: {gain:.3g}")
    payload = results_json(results, settings, args.seed, gains)
    json_path = atomic_write_text(out / "patterns.json", json.dumps(payload, indent=2) + "\n")
    return [save_figure(results, kernels, out / "patterns.png"), json_path]


def main(argv: Sequence[str] | None = None) -> int:
    """``blurcalib experiment patterns [--out DIR] [--seed N] [--lam L] [--square-px S]``.

    Prints the table and writes ``DIR/patterns.png`` and ``DIR/patterns.json`` atomically.
    Returns 0, or 2 (with ``blurcalib: error: ...`` on stderr) for bad options or an
    unwritable output folder.
    """
    return run_experiment_cli(build_parser(), argv, _run)
