"""Realistic optics for the simulator: an asymmetric PSF that varies over the field, the camera's
tone curve, and the pixel grid of a display that shows the target.

All three are off unless :class:`Optics` is given to :class:`blurcalib.sim.synth.Simulator`; with
them off a frame renders bit for bit as without this module.

* :class:`FieldPsf`: the lens's PSF at image point ``x``, a round core plus a comatic lobe along
  the radius from the optical centre, both elongated radially (astigmatism) and growing with the
  field. The frame is ``I = sum_n k_n * (w_n E)``: the PSFs ``k_n`` of a lattice of nodes, each
  spreading the irradiance ``E`` weighted by its bilinear weight ``w_n``, so that a point source
  at ``x`` spreads as ``sum_n w_n(x) k_n``. It is applied to the pixel-integrated irradiance,
  before the defocus.
* :class:`ToneCurve`: the camera's non-linear response (gamma and a contrast S-curve) between
  the linear sensor signal with its noise and the 8-bit quantisation.
* :class:`DisplayGrid`: the page shown on a monitor: rasterised into screen pixels (area-averaged
  or point-sampled), passed through the display's gamma, and emitted by each pixel's three
  sub-pixel stripes (seen by a grey camera with its own weight for each) inside a black matrix.

Ground truth. A feature's position keeps its definition (:class:`blurcalib.sim.truth.FrameTruth`:
the time-averaged projection of the target point, ``mean``). The *centroid* truth adds the
centroid of the optical PSF at that point (:meth:`FieldPsf.centroid_at`): the point whose image
is the PSF's centroid, the position a feature definition that is the same for every pattern
reaches. A display moves the shown pattern on the target plane by the emission centroid of its
pixels (:meth:`DisplayGrid.shift_squares`), which a pose absorbs.

Pixel convention: OpenCV (the centre of the top-left pixel is ``(0, 0)``); PSF ``k[i, j]`` weighs
offset ``(j - c, i - c)`` px (``docs/conventions.md``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import cast

import cv2
import numpy as np
import scipy.sparse as sp

from blurcalib.sim.render import Texture, pattern_texture
from blurcalib.target.pattern import StarPattern

__all__ = ["OPTICS_FILE", "DisplayGrid", "FieldPsf", "Optics", "ToneCurve", "display_texture",
           "display_texture_image"]

OPTICS_FILE = "optics.json"
"""A dataset rendered with optics records their settings here (beside ``ground_truth.json``)."""

_SUB = 8
"""Samples per pixel side when a PSF is integrated over its pixels."""


@dataclass(frozen=True)
class FieldPsf:
    """A lens PSF that is asymmetric and grows with the field, oriented radially.

    With ``h = |x - centre| / r_max`` (``r_max`` the distance from ``centre`` to the farthest
    image corner) and ``e_r`` the outward radial direction, the PSF is

    ``(1 - w) N(0, S_core) + w N(s(h) e_r, S_lobe)``,

    ``s(h) = coma[0] h + coma[1] h^3`` px (negative: the lobe points inwards), core standard
    deviations ``sigma g(h)`` along ``e_r`` times ``1 + astig h^2`` and ``sigma g(h)`` across,
    ``g(h) = 1 + growth h^2``, the lobe's ``lobe_sigma`` times the core's. Each kernel is
    integrated over its ``size x size`` pixels (``_SUB^2`` samples each) and normalised to sum 1.
    Its centroid is ``w s(h) e_r`` (up to the window's truncation; :meth:`centroid_at` gives the
    applied kernels' exact one).

    Attributes:
        sigma: core standard deviation at the centre (px).
        growth: ``g(h)`` coefficient.
        astig: radial elongation coefficient (0: round).
        coma: ``(c1, c3)`` px, the lobe offset's coefficients.
        lobe_weight: ``w`` in [0, 1).
        lobe_sigma: the lobe's standard deviation over the core's.
        centre: ``(x, y)`` px of the optical centre; None: the image centre.
        node_px: spacing of the PSF lattice (px).
        size: kernel side (px, odd).
    """

    sigma: float = 0.8
    growth: float = 0.6
    astig: float = 0.3
    coma: tuple[float, float] = (0.0, 2.0)
    lobe_weight: float = 0.25
    lobe_sigma: float = 1.5
    centre: tuple[float, float] | None = None
    node_px: int = 24
    size: int = 15

    def __post_init__(self) -> None:
        if not self.sigma > 0 or self.size < 3 or self.size % 2 == 0 or self.node_px < 2:
            raise ValueError("sigma must be positive, size odd and >= 3, node_px >= 2")
        if not 0 <= self.lobe_weight < 1 or not self.lobe_sigma > 0 or self.growth < 0 or self.astig < 0:
            raise ValueError("lobe_weight must be in [0, 1), lobe_sigma positive, growth and astig >= 0")

    def _geometry(self, points: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """``h (N,)`` and ``e_r (N, 2)`` of image points ``(N, 2)`` px in an image of ``size``
        ``(width, height)``."""
        w, h = size
        c = np.array(self.centre if self.centre is not None else ((w - 1) / 2, (h - 1) / 2), dtype=np.float64)
        corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=np.float64)
        r_max = float(np.linalg.norm(corners - c, axis=1).max())
        d = np.asarray(points, dtype=np.float64) - c
        r = np.linalg.norm(d, axis=1)
        e = np.where(r[:, None] > 1e-9, d / np.maximum(r, 1e-9)[:, None], np.array([1.0, 0.0]))
        return r / r_max, e

    def kernels(self, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """``(N, K, K)`` PSFs at image points ``(N, 2)`` px of an image of ``size`` ``(w, h)``."""
        h, e = self._geometry(points, size)
        K = self.size
        c = (K - 1) / 2
        o = (np.arange(K * _SUB) + 0.5) / _SUB - 0.5 - c
        X, Y = np.meshgrid(o, o)
        g = 1.0 + self.growth * h**2
        s_r = self.sigma * g * (1.0 + self.astig * h**2)
        s_t = self.sigma * g
        shift = self.coma[0] * h + self.coma[1] * h**3
        dr = X[None] * e[:, 0, None, None] + Y[None] * e[:, 1, None, None]
        dt = -X[None] * e[:, 1, None, None] + Y[None] * e[:, 0, None, None]
        out = np.zeros((len(h), K, K))
        for weight, offset, scale in ((1.0 - self.lobe_weight, 0.0 * shift, 1.0),
                                      (self.lobe_weight, shift, self.lobe_sigma)):
            if weight == 0:
                continue
            sr, st = (s_r * scale)[:, None, None], (s_t * scale)[:, None, None]
            dens = np.exp(-0.5 * (((dr - offset[:, None, None]) / sr) ** 2 + (dt / st) ** 2)) / (sr * st)
            out += weight * dens.reshape(len(h), K, _SUB, K, _SUB).sum(axis=(2, 4))
        return cast(np.ndarray, out / out.sum(axis=(1, 2), keepdims=True))

    def _nodes(self, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Node coordinates along x and y (px): every ``node_px``, from at least a kernel radius
        before the first pixel to at least one past the last."""
        g, r = self.node_px, (self.size - 1) // 2
        first = -g * math.ceil(r / g)
        return tuple(np.arange(first, n - 1 + r + g + 1, g, dtype=np.float64) for n in size)  # type: ignore[return-value]

    def _blend(self, points: np.ndarray, size: tuple[int, int]
               ) -> list[tuple[np.ndarray, np.ndarray]]:
        """The four nodes around each point ``(N, 2)``: ``[(node (N, 2) px, weight (N,))]``."""
        nx, ny = self._nodes(size)
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        fx = np.clip((p[:, 0] - nx[0]) / self.node_px, 0, len(nx) - 1 - 1e-9)
        fy = np.clip((p[:, 1] - ny[0]) / self.node_px, 0, len(ny) - 1 - 1e-9)
        ix, iy = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
        ax, ay = fx - ix, fy - iy
        return [(np.stack([nx[ix + dx], ny[iy + dy]], axis=1), wx * wy)
                for dy, wy in ((0, 1 - ay), (1, ay)) for dx, wx in ((0, 1 - ax), (1, ax))]

    def psf_at(self, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """``(N, K, K)``: the image of a point source at each of ``points`` ``(N, 2)`` px as
        :meth:`apply` renders it (the bilinear blend of the lattice's kernels)."""
        return cast(np.ndarray,
                    sum(w[:, None, None] * self.kernels(node, size) for node, w in self._blend(points, size)))

    def centroid_at(self, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """``(N, 2)`` px: the centroid of :meth:`psf_at` (where the image of a point source at each
        point is centred, relative to the point)."""
        k = self.psf_at(points, size)
        offs = np.arange(self.size) - (self.size - 1) / 2
        return np.stack([k.sum(axis=1) @ offs, k.sum(axis=2) @ offs], axis=1)

    def apply(self, image: np.ndarray) -> np.ndarray:
        """``I = sum_n k_n * (w_n E)`` of an ``(H, W)`` float image ``E`` (module docstring): each
        source point spreads with its own PSF, :meth:`psf_at`, so the image of a point source
        keeps its flux and its centroid is :meth:`centroid_at`. The image is extended by
        reflection beyond its border."""
        H, W = image.shape
        nx, ny = self._nodes((W, H))
        r = (self.size - 1) // 2
        g = self.node_px
        pad = int(-nx[0]) + 2 * (g + r)  # room for the first and the last node's spread
        src = cv2.copyMakeBorder(image.astype(np.float64), pad, pad, pad, pad, cv2.BORDER_REFLECT)
        out = np.zeros_like(src)
        tent = 1.0 - np.abs(np.arange(-g, g + 1, dtype=np.float64)) / g
        weights = tent[:, None] * tent[None, :]
        for y in ny:
            kernels = self.kernels(np.stack([nx, np.full(len(nx), y)], axis=1), (W, H))
            y0 = int(y) + pad - g
            for i, x in enumerate(nx):
                x0 = int(x) + pad - g
                source = np.zeros((2 * g + 1 + 2 * r, 2 * g + 1 + 2 * r))
                source[r:-r, r:-r] = src[y0:y0 + 2 * g + 1, x0:x0 + 2 * g + 1] * weights
                # filter2D correlates: the flipped kernel convolves, k * (w E)
                conv: np.ndarray = cv2.filter2D(source, -1, kernels[i][::-1, ::-1].copy(),
                                               borderType=cv2.BORDER_CONSTANT)
                out[y0 - r:y0 + 2 * g + 1 + r, x0 - r:x0 + 2 * g + 1 + r] += conv
        return out[pad:pad + H, pad:pad + W]


@dataclass(frozen=True)
class ToneCurve:
    """The camera's response from the linear signal to the 8-bit value, on ``[0, 255]``:
    ``y = 255 ((1 - s) t + s (3 t^2 - 2 t^3))`` with ``t = (x / 255)^(1 / gamma)`` (``x`` clipped
    to ``[0, 255]``). Monotonic for ``gamma > 0`` and ``s`` in ``[0, 1]``; the identity for
    ``gamma = 1, s = 0``.

    Attributes:
        gamma: encoding gamma (2.2 brightens the mid-tones as sRGB does).
        s_curve: strength ``s`` of the contrast S-curve.
    """

    gamma: float = 1.0
    s_curve: float = 0.0

    def __post_init__(self) -> None:
        if not self.gamma > 0 or not 0 <= self.s_curve <= 1:
            raise ValueError(f"gamma must be positive and s_curve in [0, 1], got {self.gamma}, "
                             f"{self.s_curve}")

    def __call__(self, grey: np.ndarray) -> np.ndarray:
        t = (np.clip(np.asarray(grey, dtype=np.float64), 0.0, 255.0) / 255.0) ** (1.0 / self.gamma)
        return 255.0 * ((1.0 - self.s_curve) * t + self.s_curve * t * t * (3.0 - 2.0 * t))


@dataclass(frozen=True)
class DisplayGrid:
    """The page shown on a monitor whose pixel rows and columns run along the pattern's axes.

    Screen pixel ``(i, j)`` covers feature coordinates
    ``(origin + (j, i)) / pixels_per_square + ([0, 1] x [0, 1]) / pixels_per_square``. Its drive
    value is the page's reflectance averaged over it (``raster="area"``, as an anti-aliasing
    viewer shows it) or taken at its centre (``"nearest"``), raised to ``display_gamma``
    (luminance). It emits through three vertical stripes (R, G, B, left to right), each a third
    of the pitch minus the black matrix, of weights ``subpixel_weights`` (the grey camera's
    response to each colour), and rows of ``row_fill`` of the pitch; the emission averages to the
    drive value over a pixel.

    Attributes:
        pixels_per_square: screen pixels per star square.
        subpixel_weights: the camera's response to the R, G and B stripes (normalised to sum 1).
        stripe_fill: emitting share of each stripe's third of the pitch (1 - black matrix).
        row_fill: emitting share of the pitch across the rows.
        origin: ``(x, y)`` screen px at feature coordinates ``(0, 0)``... as a sub-pixel phase.
        raster: ``"area"`` or ``"nearest"``.
        display_gamma: the display's response from drive value to luminance.
    """

    pixels_per_square: float = 40.0
    subpixel_weights: tuple[float, float, float] = (0.35, 0.5, 0.15)
    stripe_fill: float = 0.7
    row_fill: float = 0.85
    origin: tuple[float, float] = (0.3, 0.6)
    raster: str = "area"
    display_gamma: float = 1.0
    samples: int = field(default=4, repr=False)

    def __post_init__(self) -> None:
        if self.raster not in ("area", "nearest"):
            raise ValueError(f"raster must be 'area' or 'nearest', got {self.raster!r}")
        if not self.pixels_per_square > 1 or not 0 < self.stripe_fill <= 1 or not 0 < self.row_fill <= 1:
            raise ValueError("pixels_per_square must exceed 1, stripe_fill and row_fill lie in (0, 1]")

    def _weights(self) -> np.ndarray:
        w = np.asarray(self.subpixel_weights, dtype=np.float64)
        return cast(np.ndarray, w / w.sum())

    def shift_squares(self) -> np.ndarray:
        """``(2,)`` squares: how far the emission centroid of a uniformly lit pixel lies from the
        pixel's centre, i.e. how far the shown pattern moves on the target plane."""
        centres = (np.arange(3) + 0.5) / 3.0
        return np.array([float(self._weights() @ centres) - 0.5, 0.0]) / self.pixels_per_square

    def _emission(self, a: np.ndarray, b: np.ndarray, axis: int) -> np.ndarray:
        """``(n,)`` integral over ``[a, b]`` (screen px within one pixel, ``0 <= a <= b <= 1``) of
        the pixel's emission profile along ``axis`` (0: across the stripes, 1: across the rows),
        normalised to integrate to 1 over the pixel."""
        def overlap(lo: float, hi: float) -> np.ndarray:
            return cast(np.ndarray, np.clip(np.minimum(b, hi) - np.maximum(a, lo), 0.0, None))
        if axis == 1:
            m = (1.0 - self.row_fill) / 2
            return overlap(m, 1.0 - m) / self.row_fill
        out = np.zeros_like(a)
        half = self.stripe_fill / 6.0
        for c, wc in enumerate(self._weights()):
            centre = (c + 0.5) / 3.0
            out += wc * overlap(centre - half, centre + half) / (2 * half)
        return out

    def _matrix(self, edges: np.ndarray, first: int, count: int, axis: int) -> sp.csr_matrix:
        """``(T, count)`` sparse: texel ``t`` (screen-px edges ``edges[t], edges[t + 1]``) over
        screen pixels ``first .. first + count - 1``: the emission integral over their overlap
        divided by the texel's width."""
        rows, cols, vals = [], [], []
        width = np.diff(edges)
        for k in range(math.ceil(float(width.max())) + 2):
            pix = np.floor(edges[:-1]).astype(np.int64) + k
            a = np.clip(edges[:-1] - pix, 0.0, 1.0)
            b = np.clip(edges[1:] - pix, 0.0, 1.0)
            v = self._emission(a, b, axis) / width
            ok = (v > 0) & (pix >= first) & (pix < first + count)
            rows.append(np.flatnonzero(ok))
            cols.append(pix[ok] - first)
            vals.append(v[ok])
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(len(edges) - 1, count))

    def drive(self, intensity: Callable[[np.ndarray], np.ndarray], first: tuple[int, int],
              count: tuple[int, int]) -> np.ndarray:
        """``(rows, cols)`` drive luminances of screen pixels ``first + (0 .. count - 1)``
        (``(x, y)``) from ``intensity`` (feature coordinates ``(..., 2)`` -> reflectance)."""
        n = self.samples if self.raster == "area" else 1
        offs = (np.arange(n) + 0.5) / n
        acc = np.zeros((count[1], count[0]))
        jx = np.arange(first[0], first[0] + count[0], dtype=np.float64)
        iy = np.arange(first[1], first[1] + count[1], dtype=np.float64)
        for oy in offs:
            for ox in offs:
                fx = (jx[None, :] + ox - self.origin[0]) / self.pixels_per_square
                fy = (iy[:, None] + oy - self.origin[1]) / self.pixels_per_square
                acc += intensity(np.stack(np.broadcast_arrays(fx, fy), axis=-1))
        return (acc / n**2) ** self.display_gamma


def display_texture_image(display: DisplayGrid, intensity: Callable[[np.ndarray], np.ndarray],
                          texel_x: np.ndarray, texel_y: np.ndarray
                          ) -> np.ndarray:
    """``(len(texel_y) - 1, len(texel_x) - 1)`` float32 texture of the shown page: each texel the
    average emission over its area, its edges at feature coordinates ``texel_x``, ``texel_y``
    (increasing). ``intensity`` maps feature coordinates ``(..., 2)`` to the page's reflectance
    (:meth:`blurcalib.target.pattern.StarPattern.intensity`)."""
    s = display.pixels_per_square
    ex = texel_x * s + display.origin[0]
    ey = texel_y * s + display.origin[1]
    first = (math.floor(ex[0]) - 1, math.floor(ey[0]) - 1)
    count = (math.ceil(ex[-1]) + 2 - first[0], math.ceil(ey[-1]) + 2 - first[1])
    V = display.drive(intensity, first, count)
    Ax = display._matrix(ex, first[0], count[0], 0)
    Ay = display._matrix(ey, first[1], count[1], 1)
    rows = np.asarray(Ay @ V)  # (texel rows, screen columns)
    return np.ascontiguousarray(np.asarray(Ax @ rows.T).T, dtype=np.float32)


def display_texture(pattern: StarPattern, texels_per_square: int, display: DisplayGrid) -> Texture:
    """The page shown on ``display`` as a texture on the grid of
    :func:`blurcalib.sim.render.pattern_texture` at ``texels_per_square`` (same ``to_plane``;
    beyond the page the texture's background)."""
    base = pattern_texture(pattern, texels_per_square)
    r, L = texels_per_square, pattern.square_length_m
    ny, nx = base.image.shape
    tx = base.to_plane[0, 2] / L - 0.5 / r + np.arange(nx + 1) / r
    ty = base.to_plane[1, 2] / L - 0.5 / r + np.arange(ny + 1) / r
    lo = pattern.page_mm_to_feature(np.zeros(2))
    hi = pattern.page_mm_to_feature(np.array([pattern.page.width_mm, pattern.page.height_mm]))

    def page(p: np.ndarray) -> np.ndarray:
        v = pattern.intensity(p)
        off = (p[..., 0] < lo[0]) | (p[..., 0] > hi[0]) | (p[..., 1] < lo[1]) | (p[..., 1] > hi[1])
        v[off] = base.background
        return v

    return Texture(display_texture_image(display, page, tx, ty), base.to_plane, base.background)


@dataclass(frozen=True)
class Optics:
    """The simulator's optional optics; each part is off when None."""

    psf: FieldPsf | None = None
    tone: ToneCurve | None = None
    display: DisplayGrid | None = None
