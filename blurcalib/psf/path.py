"""The frame's PSF field: motion-path PSFs that vary smoothly over the image, fitted with the blocks.

Hand shake moves the camera rigidly during the exposure, so the image of every target point runs
along a short smooth path, and the paths vary smoothly over the frame. Under blur as long as the
star squares, a free (non-parametric) PSF per block trades its shape against the star's position
within the noise: started from the true homography such blocks land 0.3-1.2 px off, the same
blocks fitted with their true PSF 0.04-0.1 px off (``docs/deconvolution.md``). This module gives
the PSF few parameters and shares them over the frame:

* **a path PSF** (``eq:path_psf``)::

      k(d) = 1/T sum_t N(d; p(tau_t), sigma^2 I),    p(tau) = a tau + b (tau^2 - <tau^2>),
      tau_t = (t + 1/2) / T - 1/2,

  the time-averaged image of a point that moves along a quadratic path in equal time steps,
  spread by a Gaussian (defocus, the pixel's area, the latent pattern's soft edge). ``p`` has
  zero time-mean, so the PSF's centroid is 0 and a block's ``H(0, 0)`` is the star's
  time-averaged image position, as after :func:`blurcalib.psf.kernel.recentre`. ``(a, b)`` and
  ``(-a, b)`` give the same kernel (the direction of time is not seen).
* **a field** ``theta(x) = (a(x), b(x), log sigma)``: ``a`` and ``b`` are polynomials of degree
  ``<= 2`` in normalised image coordinates ``u = (x - x_c) / s``, ``v = (y - y_c) / s``
  (``(x_c, y_c)`` the image centre, ``s`` half its longer side; a rigid motion moves the image of
  a plane by a field quadratic in the undistorted image), ``sigma`` is one per frame. On the
  simulated heavy-blur frames a quadratic field holds the true paths to 0.01 px RMS.
The field is fitted with the blocks by :func:`blurcalib.deconv.field.fit_path_field`.

Conventions: OpenCV pixels (top-left pixel centre at ``(0, 0)``); kernels ``K x K`` with
``k[i, j]`` the weight of offset ``(j - c, i - c)`` px (``docs/conventions.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
import torch

from blurcalib.psf.kernel import psf_moments

__all__ = ["NUM_THETA", "PATH_SAMPLES", "TERMS", "PathField", "constant_field", "monomials", "path_kernels"]

PATH_SAMPLES = 48
"""Time samples ``T`` of a path PSF: 0.8 px apart on a 40 px path, below the Gaussian's width."""
NUM_THETA = 5
"""Path parameters per block: ``a_x, a_y, b_x, b_y, log sigma``."""
TERMS = (1, 3, 6)
"""Monomials of a field of degree 0, 1, 2 (:func:`monomials`)."""


def _basis_in_time(T: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(T, 2)``: ``tau_t`` and ``tau_t^2 - <tau^2>`` (zero time-mean columns)."""
    tau = (torch.arange(T, dtype=torch.float64, device=device) + 0.5) / T - 0.5
    return torch.stack([tau, tau * tau - (tau * tau).mean()], dim=1).to(dtype)


def _path_points(theta: np.ndarray) -> np.ndarray:
    """``(B, T, 2)`` px: the path ``p(tau_t)`` of ``eq:path_psf`` at its :data:`PATH_SAMPLES`
    time samples for path parameters ``theta (B, 5)``."""
    basis = _basis_in_time(PATH_SAMPLES, torch.float64, torch.device("cpu")).numpy()
    return cast(np.ndarray,
                np.einsum("tj,bjc->btc", basis, np.asarray(theta, dtype=np.float64)[:, :4].reshape(-1, 2, 2)))


def path_kernels(theta: torch.Tensor, size: int, with_jac: bool = False, samples: int = PATH_SAMPLES
                 ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Path PSFs ``eq:path_psf`` and their derivatives.

    The Gaussian is separable, so each kernel is a ``(K, T) x (T, K)`` product.

    Args:
        theta: ``(B, 5)`` ``(a_x, a_y, b_x, b_y, log sigma)`` (px, px, log px).
        size: ``K`` (odd), the kernel side (px).
        with_jac: also return the derivatives.
        samples: ``T``.
    Returns:
        ``k (B, K, K)`` (sum ~1 while the path and its spread stay inside the window) and, with
        ``with_jac``, ``dk (B, 5, K, K)`` w.r.t. the entries of ``theta``.
    """
    B, dt, dev = theta.shape[0], theta.dtype, theta.device
    basis = _basis_in_time(samples, dt, dev)
    coef = theta[:, :4].reshape(B, 2, 2)  # (B, [a, b], [x, y])
    p = torch.einsum("tj,bjc->btc", basis, coef)  # (B, T, 2)
    sigma = torch.exp(theta[:, 4])[:, None, None]
    d = torch.arange(size, dtype=dt, device=dev) - (size - 1) / 2
    ex = (d[None, None, :] - p[..., 0:1]) / sigma  # (B, T, K)
    ey = (d[None, None, :] - p[..., 1:2]) / sigma
    norm = 1.0 / (math.sqrt(2.0 * math.pi) * sigma)
    gx, gy = torch.exp(-0.5 * ex * ex) * norm, torch.exp(-0.5 * ey * ey) * norm / samples
    k = gy.transpose(1, 2) @ gx  # (B, K, K): row i from y, column j from x
    if not with_jac:
        return k, None
    gx_p, gy_p = gx * ex / sigma, gy * ey / sigma  # d/dp_x of gx, d/dp_y of gy
    gx_s, gy_s = gx * (ex * ex - 1.0), gy * (ey * ey - 1.0)  # d/dlog sigma
    dk = torch.empty((B, NUM_THETA, size, size), dtype=dt, device=dev)
    for j in range(2):  # a, b
        w = basis[None, :, j, None]
        dk[:, 2 * j] = gy.transpose(1, 2) @ (gx_p * w)
        dk[:, 2 * j + 1] = (gy_p * w).transpose(1, 2) @ gx
    dk[:, 4] = gy_s.transpose(1, 2) @ gx + gy.transpose(1, 2) @ gx_s
    return k, dk


@dataclass(frozen=True)
class PathField:
    """A frame's field of path PSFs (``eq:path_psf``).

    Attributes:
        coeffs: ``(P, 4)`` px, the polynomial coefficients of ``(a_x, a_y, b_x, b_y)`` over the
            monomials ``1, u, v, u^2, u v, v^2`` (the first ``P``: 1, 3 or 6 for degree 0, 1, 2).
        log_sigma: log of the Gaussian spread (px).
        image_size: ``(width, height)`` px, which fixes ``u, v``.
    """

    coeffs: np.ndarray
    log_sigma: float
    image_size: tuple[int, int]

    @property
    def degree(self) -> int:
        """Polynomial degree (0, 1 or 2)."""
        return TERMS.index(len(self.coeffs))

    def basis(self, xy: np.ndarray) -> np.ndarray:
        """``(B, P)`` monomials at image points ``xy (B, 2)`` px."""
        return monomials(np.asarray(xy, dtype=np.float64), self.image_size, self.degree)

    def theta(self, xy: np.ndarray) -> np.ndarray:
        """``(B, 5)`` path parameters at image points ``xy (B, 2)`` px."""
        ab = self.basis(xy) @ self.coeffs
        return np.concatenate([ab, np.full((len(ab), 1), self.log_sigma)], axis=1)

    def reach(self, xy: np.ndarray) -> np.ndarray:
        """``(B,)`` px: the largest distance of the path from the star's time-averaged image,
        plus three Gaussian widths (what a window must hold)."""
        return cast(np.ndarray,
                    np.abs(_path_points(self.theta(xy))).max(axis=(1, 2)) + 3.0 * math.exp(self.log_sigma))

    def path_change(self, other: PathField, xy: np.ndarray) -> np.ndarray:
        """``(B,)`` px: how far ``other``'s paths at image points ``xy (B, 2)`` px lie from this
        field's (the largest distance over the time samples, in whichever direction of time
        matches better: ``(a, b)`` and ``(-a, b)`` are the same kernel), plus the change of the
        Gaussian spread."""
        mine, theirs = self.theta(xy), other.theta(xy)
        p, q = _path_points(mine), _path_points(theirs)
        forward = np.linalg.norm(p - q, axis=2).max(axis=1)
        backward = np.linalg.norm(p - q[:, ::-1], axis=2).max(axis=1)  # tau -> -tau: a -> -a
        return cast(np.ndarray,
                    np.minimum(forward, backward) + np.abs(np.exp(mine[:, 4]) - np.exp(theirs[:, 4])))

    def kernel_size(self, xy: np.ndarray, largest: int) -> int:
        """The odd window side (px) that holds the paths at ``xy``, at most ``largest``."""
        k = 2 * math.ceil(float(np.max(self.reach(xy), initial=0.0)) + 1.0) + 1
        return int(min(k, largest - 1 + largest % 2))

    def kernels(self, xy: np.ndarray, size: int) -> np.ndarray:
        """``(B, K, K)`` float64 path PSFs at ``xy (B, 2)`` px, each summing to 1."""
        k, _ = path_kernels(torch.as_tensor(self.theta(xy)), size)
        out = k.numpy()
        return cast(np.ndarray, out / out.sum(axis=(1, 2), keepdims=True))

    def with_degree(self, degree: int) -> PathField:
        """The same field as a polynomial of ``degree`` (higher terms 0; lower ones dropped)."""
        P = TERMS[degree]
        coeffs = np.zeros((P, 4))
        n = min(P, len(self.coeffs))
        coeffs[:n] = self.coeffs[:n]
        return PathField(coeffs, self.log_sigma, self.image_size)

    def footprint(self, xy: np.ndarray, largest: int, margin_px: int = 2) -> np.ndarray:
        """``(F, F)`` uint8: where the PSF at image point ``xy (2,)`` px has weight (above 1 % of
        its peak), dilated by ``margin_px`` px: a pixel sees a tag through the blur only within
        the tag dilated by it (:func:`blurcalib.growth.masks.pixel_mask`)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(1, 2)
        size = self.kernel_size(xy, largest)
        k = self.kernels(xy, size)[0]
        core = (k > 0.01 * k.max()).astype(np.uint8)
        core = np.pad(core, margin_px)
        return cv2.dilate(core, np.ones((2 * margin_px + 1,) * 2, dtype=np.uint8))

    def to_dict(self) -> dict[str, Any]:
        return {"degree": self.degree, "coeffs": np.round(self.coeffs, 6).tolist(),
                "sigma_px": round(math.exp(self.log_sigma), 6), "image_size": list(self.image_size)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PathField:
        coeffs = np.asarray(d["coeffs"], dtype=np.float64).reshape(-1, 4)
        if len(coeffs) not in TERMS or not float(d["sigma_px"]) > 0:
            raise ValueError(f"not a path field: {len(coeffs)} coefficient rows, sigma {d['sigma_px']}")
        return cls(coeffs, math.log(float(d["sigma_px"])), (int(d["image_size"][0]), int(d["image_size"][1])))


def monomials(xy: np.ndarray, image_size: tuple[int, int], degree: int) -> np.ndarray:
    """``(B, P)``: ``1, u, v, u^2, u v, v^2`` (the first ``P`` for ``degree`` 0, 1, 2) at image
    points ``xy (B, 2)`` px, ``u = (x - x_c) / s``, ``v = (y - y_c) / s``."""
    w, h = image_size
    s = max(w, h) / 2.0
    u, v = (xy[:, 0] - (w - 1) / 2.0) / s, (xy[:, 1] - (h - 1) / 2.0) / s
    terms = [np.ones_like(u), u, v, u * u, u * v, v * v]
    return np.stack(terms[:TERMS[degree]], axis=1)


def constant_field(psfs: np.ndarray, image_size: tuple[int, int], degree: int) -> PathField:
    """A field of straight paths, the same everywhere, from fitted (re-centred) PSFs
    ``(B, K, K)``: the median blur extent ``sqrt(12) sigma_major`` along their mean orientation
    (averaged as doubled angles), the median ``sigma_minor`` as the spread, clamped to 0.5-1 px
    (free PSFs under long blur spread into noise, far wider than the optics' spread); the
    higher-degree coefficients 0 (:func:`fit_path_field`'s start)."""
    ok = np.all(np.isfinite(psfs), axis=(1, 2)) & (np.nan_to_num(psfs).sum(axis=(1, 2)) > 0)
    if not ok.any():
        raise ValueError("no finite PSF to start a path field from")
    m = psf_moments(psfs[ok])
    angle = 0.5 * float(np.angle(np.mean(np.exp(2j * np.asarray(m.orientation)))))
    length = math.sqrt(12.0) * float(np.median(m.sigma_major))
    coeffs = np.zeros((TERMS[degree], 4))
    coeffs[0, :2] = length * math.cos(angle), length * math.sin(angle)
    return PathField(coeffs, math.log(min(max(float(np.median(m.sigma_minor)), 0.5), 1.0)), image_size)
