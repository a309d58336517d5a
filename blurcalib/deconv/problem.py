"""One batch of blocks set up for the block solver: windows, the linear sub-problem and the model.

:class:`BlockProblem` holds ``b`` blocks padded to a common window: the observed grid ``(h, w)``
and the latent grid ``(h + 2c, w + 2c)`` (``c`` the kernel radius), whose pixel ``(i, j)`` is image
pixel ``origin + (j - c, i - c)``. Homographies are kept in *latent-local* pixels,
``H_loc = T(-(origin - c)) H``, in float64. For given ``(H, alpha)`` the model
``m = A (k * S(H)) + B`` is linear in ``k~ = a3 k`` and in the affine offset ``B``, which
:meth:`BlockProblem.evaluate` solves in closed form (:class:`KernelSolve`), with the reduced
Jacobian of the variable projection.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, fields
from typing import Any, cast

import numpy as np
import torch
import torch.nn.functional as nnf

from blurcalib.deconv.convolution import fft_grid, kernel_spectrum, valid_convolution
from blurcalib.deconv.latent import latent_pattern
from blurcalib.deconv.linear import kernel_support, solve_nonnegative
from blurcalib.deconv.settings import DeconvSettings, check_kernel_size
from blurcalib.geometry.homography import translation
from blurcalib.psf.kernel import psf_centroid

NUM_NL = 10
"""Non-linear parameters: 8 of ``H`` and the 2 of ``alpha``."""


@dataclass
class Design:
    """Index sets of one solver stage (``b`` blocks, ``n`` pixels, ``m`` kernel entries, padded).

    Attributes:
        mask: ``(b, h, w)`` bool, the loss's pixels (inside the square at the stage's start).
        pix: ``(b, n)`` flat indices of those pixels in the observed grid; ``pix_w`` 0/1 weights.
        patch: ``(b, m n)`` flat latent index of kernel entry ``t``'s patch value at pixel ``p``
            (at ``t n + p``): a pixel's patch origin plus the entry's offset. Padded pixels and
            entries point into zeros appended to the latent.
        taps_w: ``(b, m)`` 0/1 weights of the kernel entries; ``kernel_index`` their flat index
            ``i K + j`` in the kernel; ``rho`` their ridge weights.
        coarse: the entries are the 2-px lattice taps of the initial solve (tent-interpolated).
        fixed: ``(b, K, K)`` given kernels, or None. With them the kernel has one unknown, its
            scale ``a3`` (``m = 1``; ``patch``, ``taps_w``, ``kernel_index`` and ``rho`` are
            empty): the design row is the convolution ``k * S`` at the pixels.
        spectrum: the given kernels' transform for :meth:`BlockProblem.conv` (computed once per
            stage), or None (no given kernels, or direct convolution).
        u, v: ``(b, n)`` normalised coordinates at the pixels.
        U: ``(b, 3, n)`` the offset's design rows ``(u, v, 1)`` (0 on padding).
        img: ``(b, n)`` observed grey levels (0 on padding).
    """

    mask: torch.Tensor
    pix: torch.Tensor
    pix_w: torch.Tensor
    patch: torch.Tensor
    taps_w: torch.Tensor
    kernel_index: torch.Tensor
    rho: torch.Tensor
    coarse: bool
    fixed: torch.Tensor | None
    spectrum: torch.Tensor | None
    u: torch.Tensor
    v: torch.Tensor
    U: torch.Tensor
    img: torch.Tensor

    def take(self, rows: torch.Tensor) -> Design:
        """The design of blocks ``rows`` (indices), padded as this one (the pixel and kernel-entry
        lists keep their length, so a block's solve is the same in either)."""
        values: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            values[f.name] = value[rows] if isinstance(value, torch.Tensor) else value
        return Design(**values)


@dataclass
class KernelSolve:
    """The linear sub-problem solved at one ``(H, alpha)`` (:meth:`BlockProblem.evaluate`).

    Attributes:
        x: ``(b, m + 3)`` float64, the kernel entries ``k~ = a3 k`` and the offset's
            coefficients of ``(u, v, 1)``.
        obj: ``(b,)`` the objective ``sum r^2 + x^T Lambda x``.
        sse: ``(b,)`` ``sum r^2`` (grey levels^2).
        lam: ``(b, m + 3)`` the ridge ``Lambda`` (diagonal).
        N: ``(b, 10, 10)`` float64 Gauss-Newton matrix of the reduced problem, or None.
        g: ``(b, 10)`` float64 its gradient, or None.
        J: ``(b, 10, n)`` the Jacobian ``J`` of ``N`` and ``g`` (with given kernels), or None.
        res: ``(b, n)`` the residual ``r = I - m`` on the loss's pixels (with given kernels), or
            None.
    """

    x: torch.Tensor
    obj: torch.Tensor
    sse: torch.Tensor
    lam: torch.Tensor
    N: torch.Tensor | None = None
    g: torch.Tensor | None = None
    J: torch.Tensor | None = None
    res: torch.Tensor | None = None

    def take(self, rows: torch.Tensor) -> KernelSolve:
        """The solves of blocks ``rows`` (indices or a ``(b,)`` bool mask), copied."""
        values: dict[str, Any] = {f.name: None if getattr(self, f.name) is None
                                  else getattr(self, f.name)[rows] for f in fields(self)}
        return KernelSolve(**values)

    def put(self, rows: torch.Tensor, other: KernelSolve) -> None:
        """Replace blocks ``rows`` (indices) by ``other``'s solves (one per row), in place; a field
        that ``other`` lacks stays as it is."""
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if theirs is not None and mine is not None:
                mine[rows] = theirs


class BlockProblem:
    """Tensors of one batch of blocks padded to a common window (``b`` blocks, PSF window ``K``).

    Observed (evaluation) grid ``(h, w)``; latent grid ``(h + 2c, w + 2c)`` whose pixel
    ``(i, j)`` is image pixel ``origin + (j - c, i - c)``. Homographies are kept in *latent-local*
    pixels, ``H_loc = T(-(origin - c)) H``, in float64.
    """

    def __init__(self, image: torch.Tensor, pixel_ok: torch.Tensor | None, origin: np.ndarray,
                 size: np.ndarray, num_segments: int, kernel_size: int, s: DeconvSettings) -> None:
        self.s = s
        self.N = num_segments
        self.K = check_kernel_size(kernel_size)
        dev, dt = image.device, s.torch_dtype
        self.dt = dt
        r = self.r = (self.K - 1) // 2
        b = origin.shape[0]
        h, w = self.h, self.w = int(size[:, 1].max()), int(size[:, 0].max())
        self.Hl, self.Wl = h + 2 * r, w + 2 * r
        self.size = size
        self.lat_origin = origin - r
        rows = torch.as_tensor(origin[:, 1, None] + np.arange(h), device=dev)
        cols = torch.as_tensor(origin[:, 0, None] + np.arange(w), device=dev)
        rows_c = rows.clamp(0, image.shape[0] - 1)[:, :, None]
        cols_c = cols.clamp(0, image.shape[1] - 1)[:, None, :]
        img = image[rows_c, cols_c].to(dt)
        inside = torch.as_tensor((np.arange(h)[None, :, None] < size[:, 1, None, None])
                                 & (np.arange(w)[None, None, :] < size[:, 0, None, None]), device=dev)
        inside &= torch.isfinite(img)
        self.img = torch.where(inside, img, 0.0)
        self.usable = inside if pixel_ok is None else inside & pixel_ok[rows_c, cols_c]
        # normalised coordinates u, v on the latent grid (the observed grid is its interior)
        self.uv_centre = origin + (size - 1) / 2.0
        self.uv_scale = np.maximum(size.max(axis=1), 2) / 2.0
        cen = torch.as_tensor(self.uv_centre - self.lat_origin, device=dev, dtype=dt)
        sc = torch.as_tensor(self.uv_scale, device=dev, dtype=dt)
        jl = torch.arange(self.Wl, device=dev, dtype=dt)
        il = torch.arange(self.Hl, device=dev, dtype=dt)
        shape = (b, self.Hl, self.Wl)
        self.u_l = ((jl[None, None, :] - cen[:, 0, None, None]) / sc[:, None, None]).expand(shape)
        self.v_l = ((il[None, :, None] - cen[:, 1, None, None]) / sc[:, None, None]).expand(shape)
        self.u_e = self.u_l[:, r:r + h, r:r + w]
        self.v_e = self.v_l[:, r:r + h, r:r + w]
        d = torch.arange(self.K, device=dev, dtype=torch.float64) - r
        rad = torch.sqrt(d[None, :] ** 2 + d[:, None] ** 2) / max(r, 1)
        self.rho = (1.0 + s.ridge_border * rad**s.ridge_power).reshape(-1)
        self.offs = d

    def subset(self, idx: np.ndarray) -> BlockProblem:
        """The blocks ``idx`` alone, the padded windows cropped to their largest one (the
        latent-local coordinates of a block do not change)."""
        out = copy.copy(self)
        r = self.r
        size = self.size[idx]
        h, w = out.h, out.w = int(size[:, 1].max()), int(size[:, 0].max())
        Hl, Wl = out.Hl, out.Wl = h + 2 * r, w + 2 * r
        t = torch.as_tensor(idx, device=self.img.device)
        out.size, out.lat_origin = size, self.lat_origin[idx]
        out.uv_centre, out.uv_scale = self.uv_centre[idx], self.uv_scale[idx]
        out.img, out.usable = self.img[t, :h, :w], self.usable[t, :h, :w]
        out.u_l, out.v_l = self.u_l[t, :Hl, :Wl], self.v_l[t, :Hl, :Wl]
        out.u_e, out.v_e = out.u_l[:, r:r + h, r:r + w], out.v_l[:, r:r + h, r:r + w]
        return out

    # ---------------------------------------------------------------- homography conversions
    def to_local(self, H: np.ndarray) -> torch.Tensor:
        """Image-pixel homographies ``(b, 3, 3)`` -> latent-local float64 tensors."""
        return torch.as_tensor(translation(-self.lat_origin.astype(np.float64)) @ H, device=self.img.device)

    def to_image(self, H_loc: torch.Tensor) -> np.ndarray:
        """Latent-local homographies -> image-pixel ``(b, 3, 3)`` float64 arrays."""
        return cast(np.ndarray, translation(self.lat_origin.astype(np.float64)) @ H_loc.cpu().numpy())

    # ------------------------------------------------------------------- pattern and pixels
    def latent(self, H_loc: torch.Tensor, with_jac: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``S(H)`` on the latent grid ``(b, Hl, Wl)`` and, optionally, ``dS / d delta (b, 8, Hl, Wl)``
        (:func:`blurcalib.deconv.latent.latent_pattern`)."""
        return latent_pattern(H_loc, (self.Hl, self.Wl), self.N, self.s.tau, self.s.supersample, self.dt,
                              with_jac)

    def conv(self, L: torch.Tensor, k: torch.Tensor, spectrum: torch.Tensor | None = None,
             latent: torch.Tensor | None = None) -> torch.Tensor:
        """Valid convolution ``(k * L)`` of latent channels ``(b, C, Hl, Wl)`` -> ``(b, C, h, w)``
        (:func:`blurcalib.deconv.convolution.valid_convolution`; ``spectrum`` the kernels' and
        ``latent`` ``L``'s transform when known)."""
        return valid_convolution(L, k, spectrum, latent)

    def square_mask(self, H_loc: torch.Tensor) -> torch.Tensor:
        """Observed pixels of the loss, ``|q|_inf <= e`` (the block's square for ``e = 1``; ``e``
        the loss extent) and usable, ``(b, h, w)``."""
        M = torch.linalg.inv(H_loc)
        dev = M.device
        j = torch.arange(self.w, device=dev, dtype=M.dtype)[None, None, :] + self.r
        i = torch.arange(self.h, device=dev, dtype=M.dtype)[None, :, None] + self.r
        qx, qy, wq = (M[:, k, 0, None, None] * j + M[:, k, 1, None, None] * i + M[:, k, 2, None, None]
                      for k in range(3))
        ew = self.s.loss_extent * wq
        inside = (wq > 0) & (qx.abs() <= ew) & (qy.abs() <= ew)
        return cast(torch.Tensor, inside & self.usable)

    # ------------------------------------------------------------------- the linear sub-problem
    def design(self, H_loc: torch.Tensor, support: torch.Tensor | None,
               fixed: torch.Tensor | None = None) -> Design:
        """Index sets of a stage: the square's pixels at ``H`` and the kernel entries.

        ``support`` ``(b, K, K)`` bool selects the kernel entries; None selects the coarse
        initial kernel (taps on the 2-px lattice, tent-interpolated), or with ``fixed``
        ``(b, K, K)`` given kernels, of which only the scale is unknown.
        """
        b, K, r = H_loc.shape[0], self.K, self.r
        dev = H_loc.device
        mask = self.square_mask(H_loc)
        flat = mask.reshape(b, -1)
        n = max(int(flat.sum(dim=1).max()), 1)
        pix = torch.argsort((~flat).to(torch.int8), dim=1, stable=True)[:, :n]
        pix_w = torch.gather(flat, 1, pix).to(self.dt)
        base = (pix // self.w) * self.Wl + pix % self.w
        u = torch.gather(self.u_e.reshape(b, -1), 1, pix)
        v = torch.gather(self.v_e.reshape(b, -1), 1, pix)
        U = torch.stack([u, v, torch.ones_like(u)], dim=1) * pix_w[:, None, :]
        img = torch.gather(self.img.reshape(b, -1), 1, pix) * pix_w
        if fixed is not None:
            none = torch.zeros((b, 0), dtype=torch.int64, device=dev)
            kernels = fixed.to(self.dt)
            grid = fft_grid((self.Hl, self.Wl), K)
            return Design(mask=mask, pix=pix, pix_w=pix_w, patch=none, taps_w=none.to(self.dt),
                          kernel_index=none, rho=self.rho[none], coarse=False, fixed=kernels,
                          spectrum=None if grid is None else kernel_spectrum(kernels, grid),
                          u=u, v=v, U=U, img=img)
        if support is None:
            rc = (r - 1) // 2  # taps at 2 px spacing whose tents stay inside the window
            c = torch.arange(-rc, rc + 1, device=dev) * 2
            dy, dx = (t.reshape(-1) for t in torch.meshgrid(c, c, indexing="ij"))
            kidx = ((dy + r) * K + dx + r)[None].expand(b, -1)
            taps_w = torch.ones(kidx.shape, dtype=self.dt, device=dev)
        else:
            sup = support.reshape(b, -1)
            m = max(int(sup.sum(dim=1).max()), 1)
            kidx = torch.argsort((~sup).to(torch.int8), dim=1, stable=True)[:, :m]
            taps_w = torch.gather(sup, 1, kidx).to(self.dt)
        # entry (i, j) is the offset d = (j - c, i - c); its patch value at observed pixel x is
        # the latent at x - d, i.e. latent-local (y + 2c - i, x + 2c - j); padded pixels and
        # entries read the zeros appended after the latent (:meth:`evaluate`)
        size = self.Hl * self.Wl
        taps = torch.where(taps_w > 0, (2 * r - kidx // K) * self.Wl + (2 * r - kidx % K), size)
        base = torch.where(pix_w > 0, base, size)
        patch = (base[:, None, :] + taps[:, :, None]).reshape(b, -1)
        return Design(mask=mask, pix=pix, pix_w=pix_w, patch=patch, taps_w=taps_w, kernel_index=kidx,
                      rho=self.rho[kidx], coarse=support is None, fixed=None, spectrum=None, u=u, v=v, U=U,
                      img=img)

    def _patch_source(self, S: torch.Tensor, alpha: torch.Tensor, des: Design
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """The latent image whose patches multiply the kernel entries (tent-filtered for the
        coarse kernel), and the pixel weights ``A / a3`` (0 off the loss's pixels)."""
        src = S
        a_e = 1.0 + alpha[:, 0, None].to(self.dt) * des.u + alpha[:, 1, None].to(self.dt) * des.v
        if des.coarse:
            tent = torch.tensor([0.5, 1.0, 0.5], dtype=self.dt, device=S.device)
            src = nnf.conv2d(src[:, None], (tent[:, None] * tent[None, :])[None, None], padding=1)[:, 0]
        return src, a_e * des.pix_w

    def kernel(self, x: torch.Tensor, des: Design) -> torch.Tensor:
        """The kernel ``k~ (b, K, K)`` of a solution ``x`` (unnormalised, ``a3 k``)."""
        if des.fixed is not None:
            return x[:, :1, None].to(des.fixed.dtype) * des.fixed
        b, K = x.shape[0], self.K
        m = des.kernel_index.shape[1]
        k = torch.zeros((b, K * K), dtype=x.dtype, device=x.device)
        k.scatter_(1, des.kernel_index, x[:, :m] * des.taps_w.to(x.dtype))
        k = k.reshape(b, K, K)
        if des.coarse:
            tent = torch.tensor([0.5, 1.0, 0.5], dtype=x.dtype, device=x.device)
            k = nnf.conv2d(k[:, None], (tent[:, None] * tent[None, :])[None, None], padding=1)[:, 0]
        return k

    def evaluate(self, H_loc: torch.Tensor, alpha: torch.Tensor, des: Design, lam: torch.Tensor | None,
                 with_jac: bool) -> KernelSolve:
        """Solve the kernel sub-problem at ``(H, alpha)`` and, optionally, the reduced Jacobian.

        The model is linear in ``x = (k~, b)``: the stage's kernel entries of ``k~ = a3 k`` and
        the observed-grid affine offset (3 coefficients of ``u, v, 1``), ``m = D^T x`` with ``D``
        the ``(m + 3, n)`` design of latent patches (times ``A / a3``). ``x* = (D D^T +
        Lambda)^{-1} D I`` (the ridge of ``eq:deconvolution``), optionally with kernel entries
        that come out negative fixed at zero (active-set passes). With ``J`` the ``(10, n)``
        derivative of ``m`` w.r.t. the non-linear parameters (8 of ``H``, 2 of ``alpha``) at fixed
        ``x*``, the variable-projection Gauss-Newton system (Kaufman) is
        ``N = J J^T - Y^T G^{-1} Y`` with ``Y = D J^T``, and the gradient ``g = J r``.

        ``Lambda = lambda rho(d)`` times the mean energy of a kernel column (``lam``; None computes
        it here, to be kept fixed through a stage so that objectives compare).

        With given kernels (``des.fixed``) ``D``'s kernel part is the one row ``(k * S) A / a3``
        and ``x = (a3, b)``; the same Jacobian follows from the same convolutions, and the solve
        keeps ``J`` and ``r`` for the chord steps of :func:`blurcalib.deconv.lm.lm_stage`.
        """
        b = H_loc.shape[0]
        S, dS = self.latent(H_loc, with_jac=with_jac)
        src, w = self._patch_source(S, alpha, des)
        fixed = des.fixed is not None
        m, n = (1 if fixed else des.kernel_index.shape[1]), des.pix.shape[1]
        if lam is None:
            scale = ((w * w).sum(dim=1) * (src * src).mean(dim=(1, 2))).double().clamp_min(1e-12)
            tail = torch.full((b, 3), 1e-9, dtype=des.rho.dtype, device=des.rho.device)
            ridge = tail[:, :1] if fixed else self.s.ridge * des.rho
            lam = torch.cat([ridge, tail], dim=1) * scale[:, None]
        # D = [P; U] (b, m + 3, n): the kernel entries' patches, then the offset's rows (u, v, 1)
        D = torch.empty((b, m + 3, n), dtype=self.dt, device=src.device)
        if fixed:
            assert des.fixed is not None
            chans = torch.cat([S[:, None], dS], dim=1) if dS is not None else S[:, None]  # dS iff with_jac
            conv = torch.gather(self.conv(chans, des.fixed, des.spectrum).reshape(b, chans.shape[1], -1), 2,
                                des.pix[:, None, :].expand(-1, chans.shape[1], -1))
            D[:, :1] = conv[:, :1]
        else:
            padded = torch.cat([src.reshape(b, -1), torch.zeros_like(src.reshape(b, -1)),
                                torch.zeros_like(src[:, 0, :1])], dim=1)
            D[:, :m] = torch.gather(padded, 1, des.patch).reshape(b, m, n)
        D[:, :m].mul_(w[:, None, :])
        D[:, m:] = des.U
        G = (D @ D.transpose(1, 2)).double()
        G.diagonal(dim1=1, dim2=2).add_(lam)
        rhs = (des.img[:, None, :] @ D.transpose(1, 2)).double().transpose(1, 2)  # (b, m + 3, 1)
        passes = self.s.nonnegative_passes if self.s.nonnegative and not fixed else 0
        x, factor = solve_nonnegative(G, rhs, m, passes)
        res = des.img - (x.to(self.dt)[:, None, :] @ D)[:, 0]
        sse = (res * res).sum(dim=1).double()
        out = KernelSolve(x=x, obj=sse + (x * x * lam).sum(dim=1), sse=sse, lam=lam,
                          res=res if fixed else None)
        if not with_jac:
            return out
        assert dS is not None
        if fixed:  # the model is a3 (k * S): its convolutions, scaled
            conv = conv * x[:, :1, None].to(self.dt)
        else:
            conv = self.conv(torch.cat([S[:, None], dS], dim=1), self.kernel(x, des).to(self.dt))
            conv = torch.gather(conv.reshape(b, 9, -1), 2, des.pix[:, None, :].expand(-1, 9, -1))
        C = conv[:, 0]
        J = torch.cat([conv[:, 1:] * w[:, None, :], (des.u * C * des.pix_w)[:, None],
                       (des.v * C * des.pix_w)[:, None]], dim=1)
        Y, Z = factor.solve((J @ D.transpose(1, 2)).double().transpose(1, 2))  # (b, F, 10), free rows
        out.N = (J @ J.transpose(1, 2)).double() - Y.transpose(1, 2) @ Z
        out.g = (J @ res[..., None]).double()[..., 0]
        if fixed:
            out.J = J
        return out

    def model(self, H_loc: torch.Tensor, k: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
        """The model image ``m = A (k * S) + B`` ``(b, h, w)`` for ``H``, a kernel ``k (b, K, K)``
        and ``p (b, 6)``."""
        S, _ = self.latent(H_loc, with_jac=False)
        p = coeffs.to(self.dt)
        A = p[:, 0, None, None] * self.u_e + p[:, 1, None, None] * self.v_e + p[:, 2, None, None]
        Bm = p[:, 3, None, None] * self.u_e + p[:, 4, None, None] * self.v_e + p[:, 5, None, None]
        return A * self.conv(S[:, None], k)[:, 0] + Bm

    def centre_estimate(self, H_loc: torch.Tensor, x: torch.Tensor, des: Design) -> torch.Tensor:
        """``H(0, 0) + centroid(k)`` ``(b, 2)`` in latent-local px: the time-averaged star centre."""
        k = self.kernel(x, des).double()
        if self.s.centroid_threshold > 0:
            k = torch.where(k >= self.s.centroid_threshold * k.amax(dim=(1, 2), keepdim=True), k, 0.0)
        tot = k.sum(dim=(1, 2)).clamp_min(1e-300)
        c = torch.stack([k.sum(dim=1) @ self.offs, k.sum(dim=2) @ self.offs], dim=1) / tot[:, None]
        return H_loc[:, :2, 2] / H_loc[:, 2:, 2] + c

    # -------------------------------------------------------------------------- recentring
    def recentre_int(self, H_loc: torch.Tensor, k: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
        """Integer re-centring ``H' = T(n) H``, ``n = round(centroid(k))``; the next solve re-centres k."""
        kn = k.detach().cpu().numpy()
        with np.errstate(invalid="ignore", divide="ignore"):
            c = psf_centroid(kn / kn.sum(axis=(1, 2), keepdims=True), self.s.centroid_threshold)
        n = np.where(np.isfinite(c), np.round(c), 0.0)
        return torch.as_tensor(translation(n), device=H_loc.device) @ H_loc, n

    def support(self, k: torch.Tensor, n: np.ndarray) -> torch.Tensor:
        """Kernel support ``(b, K, K)`` bool of the next stage: ``k`` moved by the integer
        re-centring ``n`` (``k'(d) = k(d + n)``), entries above ``support_threshold`` of the peak,
        dilated by ``support_dilation`` px."""
        K = self.K
        b = k.shape[0]
        dev = k.device
        nt = torch.as_tensor(n.astype(np.int64), device=dev)
        ar = torch.arange(K, device=dev)
        ri = ar[None, :] + nt[:, 1, None]
        cj = ar[None, :] + nt[:, 0, None]
        ok = ((ri >= 0) & (ri < K))[:, :, None] & ((cj >= 0) & (cj < K))[:, None, :]
        k = k[torch.arange(b, device=dev)[:, None, None], ri.clamp(0, K - 1)[:, :, None],
              cj.clamp(0, K - 1)[:, None, :]] * ok
        return kernel_support(k, self.s.support_threshold, self.s.support_dilation)
