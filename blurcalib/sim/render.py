"""The simulator's renderer: the target's texture, its image through the moving true camera
during the exposure, and the sensor.

A frame is rendered as a real camera records it (``docs/synthetic-data.md``):

1. the target's reflectance ``S`` (exact, anti-aliased texture of the page, mip-mapped);
2. camera motion during the exposure (:class:`blurcalib.sim.truth.Motion`), integrated by time
   samples: each warps the texture onto a pinhole canvas finer than the sensor
   (:mod:`blurcalib.sim.canvas`: the undistorted image of a forward-looking lens, or, for any
   field of view up to 200 degrees, a canvas rotated to face the target);
3. the true lens, applied to the time integral (exact: the lens maps every time sample through
   the same coordinate change); with a rolling shutter (:mod:`blurcalib.camera.shutter`) each
   sample is lens-mapped onto the band of sensor rows whose windows contain it and weighted per
   row, so each row integrates its own window;
4. the pixel's area: everything above is rendered ``supersample`` times finer and box-averaged;
5. defocus, illumination, vignetting, Poisson-Gaussian noise and 8-bit quantisation
   (:func:`sensor_image`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import cv2
import numpy as np

from blurcalib.camera.shutter import exposure_grid, row_time, window_weights
from blurcalib.geometry.pose import Pose
from blurcalib.sim.canvas import LensMap, WideLens, perspective_lens_map
from blurcalib.sim.truth import FrameTruth, Motion, TrueCamera, gauss_ksize
from blurcalib.target.pattern import StarPattern
from blurcalib.target.star import star_sector_white

if TYPE_CHECKING:
    from blurcalib.sim.optics import Optics

MIP_TEXELS_PER_SQUARE = (320, 160, 80, 40, 20, 10)
"""Texture resolutions of the mip pyramid, finest first (multiples of 10, halving)."""

_Box = tuple[int, int, int, int]


@dataclass(frozen=True)
class Texture:
    """A planar target's reflectance as an image on the target plane.

    ``texel (j, i)`` (column, row) centre sits at target-plane point
    ``to_plane @ (j, i, 1)`` (metres, homogeneous); values in [0, 1].
    """

    image: np.ndarray
    to_plane: np.ndarray
    background: float = 0.35


def pattern_texture(pattern: StarPattern, texels_per_square: int) -> Texture:
    """The printed page as an exactly anti-aliased texture.

    The star area is periodic, so one anti-aliased star cell (``texels_per_square`` squared,
    4 x 4 to 16 x 16 samples per texel) is tiled; the pattern border and the tag's cells fall on texel
    boundaries (``texels_per_square`` a multiple of 10), so they are exact too. The page
    outside the patterned area is white; beyond the page is ``background``.
    """
    r = int(texels_per_square)
    if r % 10:
        raise ValueError(f"texels_per_square must be a multiple of 10, got {r}")
    ss = max(4, min(16, 1280 // r))  # samples per texel side
    o = (np.arange(r * ss) + 0.5) / (r * ss) - 0.5  # cell-local offsets in squares
    u, v = np.meshgrid(o, o)
    cell = star_sector_white(u, v, pattern.num_star_segments).astype(np.float32)
    cell = cell.reshape(r, ss, r, ss).mean(axis=(1, 3))
    # Page extent in feature coordinates, rounded outwards to whole half squares.
    x_min = math.floor(float(pattern.page_mm_to_feature(np.zeros(2))[0]) * 2) / 2
    y_min = math.floor(float(pattern.page_mm_to_feature(np.zeros(2))[1]) * 2) / 2
    far = pattern.page_mm_to_feature(np.array([pattern.page.width_mm, pattern.page.height_mm]))
    x_max = math.ceil(float(far[0]) * 2) / 2
    y_max = math.ceil(float(far[1]) * 2) / 2
    # The tile starts at a cell boundary (half-integer feature coordinate).
    nx = round((x_max - x_min) * r)
    ny = round((y_max - y_min) * r)
    shift_x = round((x_min + 0.5) % 1.0 * r)
    shift_y = round((y_min + 0.5) % 1.0 * r)
    reps = (ny // r + 3, nx // r + 3)
    image = np.tile(cell, reps)[shift_y:shift_y + ny, shift_x:shift_x + nx].copy()
    cols = x_min + (np.arange(nx) + 0.5) / r
    rows = y_min + (np.arange(ny) + 0.5) / r
    outside = ((cols[None, :] < -1) | (cols[None, :] > pattern.squares_x - 1)
               | (rows[:, None] < -1) | (rows[:, None] > pattern.squares_y - 1))
    image[outside] = 1.0
    for tag in pattern.apriltags:
        x0, y0, x1, y1 = tag.feature_box
        c0, r0 = round((x0 - x_min) * r), round((y0 - y_min) * r)
        c1, r1 = round((x1 - x_min) * r), round((y1 - y_min) * r)
        cells = pattern.tag_cells(tag).astype(np.float32)
        image[r0:r1, c0:c1] = cv2.resize(cells, (c1 - c0, r1 - r0), interpolation=cv2.INTER_NEAREST)
    page_lo = pattern.page_mm_to_feature(np.zeros(2))
    page_hi = far
    off_page = ((cols[None, :] < page_lo[0]) | (cols[None, :] > page_hi[0])
                | (rows[:, None] < page_lo[1]) | (rows[:, None] > page_hi[1]))
    background = 0.35
    image[off_page] = background
    L = pattern.square_length_m
    to_plane = np.array([[L / r, 0.0, L * (x_min + 0.5 / r)],
                         [0.0, L / r, L * (y_min + 0.5 / r)],
                         [0.0, 0.0, 1.0]])
    return Texture(image, to_plane, background)


def dot_texture(center_m: tuple[float, float], radius_m: float, texel_m: float,
                extent_m: float) -> Texture:
    """A single bright disc (value 1) of ``radius_m`` on black, centred at ``center_m``.

    Used to check the renderer: the intensity centroid of a small dot's image is the
    time-averaged projection of its centre.
    """
    n = round(2 * extent_m / texel_m) | 1
    ss = 8
    o = ((np.arange(n * ss) + 0.5) / ss - n / 2) * texel_m
    u, v = np.meshgrid(o, o)
    disc = ((u * u + v * v) <= radius_m**2).astype(np.float32)
    image = disc.reshape(n, ss, n, ss).mean(axis=(1, 3))
    half = (n - 1) / 2
    to_plane = np.array([[texel_m, 0.0, center_m[0] - half * texel_m],
                         [0.0, texel_m, center_m[1] - half * texel_m],
                         [0.0, 0.0, 1.0]])
    return Texture(image, to_plane, 0.0)


@dataclass(frozen=True)
class RenderSettings:
    """Renderer accuracy settings.

    Attributes:
        supersample: samples per pixel side (box filter of the pixel area).
        max_step_px: largest image displacement between consecutive time samples (px).
        max_time_samples: cap on T.
    """

    supersample: int = 3
    max_step_px: float = 0.35
    max_time_samples: int = 160


class Renderer:
    """Renders frames of one :class:`TrueCamera`; caches the lens's remap tables (a forward-looking
    lens's one canvas) or its viewing directions (a wide lens's per-frame canvases)."""

    def __init__(self, camera: TrueCamera, settings: RenderSettings | None = None) -> None:
        self.camera = camera
        self.settings = settings or RenderSettings()
        ss = self.settings.supersample
        self._fixed = perspective_lens_map(camera, ss) if camera.forward_only else None
        self._wide = None if camera.forward_only else WideLens(camera, ss)

    def lens_map(self, texture: Texture, pose: Pose, poses: Sequence[Pose]) -> LensMap:
        """The canvas of a frame at ``pose`` whose time samples are ``poses`` (the target's
        ``texture`` extent sizes a wide lens's canvas)."""
        if self._wide is None:
            assert self._fixed is not None
            return self._fixed
        h, w = texture.image.shape
        corners = np.array([[-0.5, -0.5, 1.0], [w - 0.5, -0.5, 1.0], [w - 0.5, h - 0.5, 1.0],
                            [-0.5, h - 0.5, 1.0]])
        plane = corners @ texture.to_plane.T
        return self._wide.frame_map(pose, list(poses), plane[:, :2] / plane[:, 2:])

    def irradiance(self, levels: Sequence[Texture], pose: Pose, motion: Motion,
                   rolling_shutter: float = 0.0) -> np.ndarray:
        """Time-integrated, lens-mapped, pixel-integrated target image: ``(H, W)`` in [0, 1].

        Each time sample warps the texture onto the frame's canvas (:meth:`lens_map`) with the
        homography ``K_canvas (R_canvas) [r1 r2 t](tau) to_plane`` (``eq:T``). Global shutter
        (``rolling_shutter = 0``, or no motion): the mean over the samples is mapped through the
        true lens and box-averaged over each pixel. Rolling shutter (readout ratio ``r``): the
        samples of the frame's exposure grid (:func:`blurcalib.camera.shutter.exposure_grid`) are
        each lens-mapped onto the rows whose windows contain them, weighted by
        :func:`blurcalib.camera.shutter.window_weights` per sensor row (every sub-sample row of a
        pixel row shares its window), and summed. Sub-samples beyond a wide lens's field stop are
        dark (0).

        ``levels`` is a mip pyramid of the same target (finest first, each level half the
        resolution of the previous). Every canvas sample blends the two levels whose texel
        size is closest to its footprint (trilinear mip-mapping, weights from the ``tau = 0``
        pose): a canvas sample's own on a forward-looking lens's canvas, the sensor
        sub-sample's on the target through a wide lens. So the texture is neither aliased where
        the target is far nor blurred where it is near.
        """
        rolling = not (rolling_shutter == 0 or motion.samples == 1)
        height = self.camera.model.height
        poses = motion.grid_poses(pose, height, rolling_shutter) if rolling else motion.poses(pose)
        lens = self.lens_map(levels[0], pose, poses)
        weights = self._level_weights(levels, pose, lens)
        background = float(levels[0].background)
        w, h = self.camera.model.width, height
        if not rolling:
            cw, ch = lens.size
            acc = self._canvas(levels, weights, lens, poses, (0, 0, cw, ch))
            acc /= motion.samples
            sensor = cv2.remap(acc, lens.map_x, lens.map_y, cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=background)
        else:
            sensor = self._rolling_sensor(levels, weights, lens, poses, motion, rolling_shutter)
        if lens.dark is not None:
            sensor[lens.dark] = 0.0
        return cv2.resize(sensor, (w, h), interpolation=cv2.INTER_AREA)

    def _rolling_sensor(self, levels: Sequence[Texture], weights: list[tuple[np.ndarray | None, _Box]],
                        lens: LensMap, poses: Sequence[Pose], motion: Motion, ratio: float) -> np.ndarray:
        """The supersampled sensor image ``(H ss, W ss)`` of a rolling shutter of readout ratio
        ``ratio``, the samples of the motion's exposure grid at ``poses``: per grid sample, the
        canvas over the bounding box of its rows' lens map."""
        ss = self.settings.supersample
        height = self.camera.model.height
        grid = exposure_grid(height, ratio, motion.samples)
        row_w = window_weights(grid, row_time(np.arange(height), height, ratio)).astype(np.float32)
        sensor = np.zeros(lens.map_x.shape, dtype=np.float32)
        background = float(levels[0].background)
        for j, p in enumerate(poses):
            rows = np.flatnonzero(row_w[j] > 0)
            if not len(rows):
                continue
            s0, s1 = int(rows[0]) * ss, (int(rows[-1]) + 1) * ss
            box = lens.box(s0, s1)
            band: np.ndarray
            if box is None:
                band = np.full_like(lens.map_x[s0:s1], background)
            else:
                x0, y0 = box[0], box[1]
                canvas = self._canvas(levels, weights, lens, [p], box)
                band = cv2.remap(canvas, lens.map_x[s0:s1] - np.float32(x0),
                                 lens.map_y[s0:s1] - np.float32(y0), cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=background)
            sensor[s0:s1] += band * np.repeat(row_w[j, rows[0]:rows[-1] + 1], ss)[:, None]
        return sensor

    def _canvas(self, levels: Sequence[Texture], weights: list[tuple[np.ndarray | None, _Box]],
                lens: LensMap, poses: Sequence[Pose], box: _Box) -> np.ndarray:
        """The sum over ``poses`` of the mip-blended texture warped onto the canvas box
        ``(x0, y0, x1, y1)`` (canvas px)."""
        bx0, by0, bx1, by1 = box
        acc = np.zeros((by1 - by0, bx1 - bx0), dtype=np.float32)
        for level, (weight, (lx0, ly0, lx1, ly1)) in zip(levels, weights, strict=True):
            x0, y0, x1, y1 = max(bx0, lx0), max(by0, ly0), min(bx1, lx1), min(by1, ly1)
            if weight is None or x1 <= x0 or y1 <= y0:
                continue
            shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
            level_acc = np.zeros((y1 - y0, x1 - x0), dtype=np.float32)
            for p in poses:
                H = lens.homography(p, shift) @ level.to_plane
                warped = cv2.warpPerspective(level.image, H, (x1 - x0, y1 - y0),
                                             flags=cv2.INTER_LINEAR,
                                             borderMode=cv2.BORDER_CONSTANT,
                                             borderValue=float(level.background))
                cv2.accumulate(warped, level_acc)
            cv2.accumulateProduct(level_acc, weight[y0 - ly0:y1 - ly0, x0 - lx0:x1 - lx0],
                                  acc[y0 - by0:y1 - by0, x0 - bx0:x1 - bx0])
        return acc

    def _level_weights(self, levels: Sequence[Texture], pose: Pose, lens: LensMap
                       ) -> list[tuple[np.ndarray | None, tuple[int, int, int, int]]]:
        """Per-level blend weights over the canvas and their bounding boxes.

        Forward-looking lens: the finest level's texels per canvas sample at canvas point ``x``
        is ``rho(x) = sqrt(|det G| / |w(x)|^3)`` for the canvas-to-texture homography ``G`` with
        ``w(x) = G[2] . (x, y, 1)``. Wide lens: texels per sensor sub-sample
        (:meth:`blurcalib.sim.canvas.WideLens.level_lambda`). Level ``lambda = log2 rho``
        (clipped to the pyramid) is blended linearly between its two neighbouring integer levels.
        """
        cw, ch = lens.size
        if self._wide is not None:
            texel_m = float(levels[0].to_plane[0, 0])
            lam = self._wide.level_lambda(lens, pose, texel_m, len(levels))
        else:
            H = lens.homography(pose) @ levels[0].to_plane
            G = np.linalg.inv(H)
            step = 16
            ys, xs = np.mgrid[0:ch + step:step, 0:cw + step:step].astype(np.float64)
            w = G[2, 0] * xs + G[2, 1] * ys + G[2, 2]
            rho = np.sqrt(abs(np.linalg.det(G)) / np.maximum(np.abs(w), 1e-12) ** 3)
            lam = np.clip(np.log2(np.maximum(rho, 1e-12)), 0, len(levels) - 1)
            lam = cv2.resize(lam.astype(np.float32), (xs.shape[1] * step, xs.shape[0] * step),
                             interpolation=cv2.INTER_LINEAR)[:ch, :cw]
        out: list[tuple[np.ndarray | None, tuple[int, int, int, int]]] = []
        for k in range(len(levels)):
            weight = np.maximum(0.0, 1.0 - np.abs(lam - k)).astype(np.float32)
            rows = np.flatnonzero(weight.max(axis=1) > 0)
            cols = np.flatnonzero(weight.max(axis=0) > 0)
            if len(rows) == 0:
                out.append((None, (0, 0, 0, 0)))
                continue
            box = (int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1)
            out.append((np.ascontiguousarray(weight[box[1]:box[3], box[0]:box[2]]), box))
        return out

    def time_samples_for(self, pose: Pose, xi: np.ndarray, xi2: np.ndarray,
                         probe_points: np.ndarray, rolling_shutter: float = 0.0) -> int:
        """T (samples per exposure time) such that no probe point moves more than
        ``max_step_px`` between samples: over the exposure, or with a rolling shutter of
        readout ratio ``r`` anywhere in the readout (where the motion's speed may be higher)."""
        if rolling_shutter > 0:
            height = self.camera.model.height
            half = 0.5 + float(row_time(height - 1.0, height, rolling_shutter))
            count = 64 * math.ceil(2 * half) + 1
            times = np.linspace(-half, half, count)
            tracks = np.stack([self.camera.project(p.transform(probe_points))
                               for p in Motion(xi, xi2, 1).poses_at(pose, times)])
            speed = np.linalg.norm(np.diff(tracks, axis=0), axis=2) / (times[1] - times[0])
            fastest = float(speed.max()) if speed.size else 0.0
            t = math.ceil(fastest / self.settings.max_step_px) + 1
            return int(np.clip(t, 1, self.settings.max_time_samples))
        dense = Motion(xi, xi2, 64)
        length = np.zeros(len(probe_points))
        prev = None
        for p in dense.poses(pose):
            cur = self.camera.project(p.transform(probe_points))
            if prev is not None:
                length += np.linalg.norm(cur - prev, axis=1)
            prev = cur
        longest = float(length.max()) if len(length) else 0.0
        t = math.ceil(longest / self.settings.max_step_px) + 1
        return int(np.clip(t, 1, self.settings.max_time_samples))


def sensor_image(irradiance: np.ndarray, truth: FrameTruth, rng: np.random.Generator,
                 optics: Optics | None = None) -> np.ndarray:
    """Defocus, illumination, vignetting, Poisson-Gaussian noise, 8-bit quantisation.

    ``grey = (black + (white - black) (g_d * E)) G(u, v) V(r)``, then
    ``noisy = gain Poisson(grey / gain) + N(0, read_sigma^2)``, rounded and clipped to
    ``[0, 255]``. ``optics`` (:mod:`blurcalib.sim.optics`) may add the lens's field-varying PSF
    (convolved before the defocus) and a tone curve (after the noise, before the rounding).
    """
    img: np.ndarray = irradiance.astype(np.float64)
    if optics is not None and optics.psf is not None:
        img = optics.psf.apply(img)
    if truth.defocus_sigma > 0:
        k = gauss_ksize(truth.defocus_sigma)
        img = cv2.GaussianBlur(img, (k, k), truth.defocus_sigma, borderType=cv2.BORDER_REFLECT)
    h, w = img.shape
    u = (np.arange(w) - (w - 1) / 2) / ((w - 1) / 2)
    v = (np.arange(h) - (h - 1) / 2) / ((h - 1) / 2)
    U, V = np.meshgrid(u, v)
    g0, gx, gy = truth.illumination
    gain_field = (g0 + gx * U + gy * V) * (1.0 - truth.vignetting * (U**2 + V**2) / 2.0)
    black, white = truth.levels
    grey = (black + (white - black) * img) * gain_field
    gain, read_sigma = truth.noise
    noisy = gain * rng.poisson(np.maximum(grey, 0) / gain) + rng.normal(0, read_sigma, grey.shape)
    if optics is not None and optics.tone is not None:
        noisy = optics.tone(noisy)
    return cast(np.ndarray, np.clip(np.round(noisy), 0, 255).astype(np.uint8))


def mip_levels_for(camera: TrueCamera, pose: Pose, pattern: StarPattern, supersample: int) -> range:
    """Which pyramid levels a frame needs: from the one whose texels are no larger than a
    canvas sample (a sensor sub-sample, through a wide lens) at the nearest feature, down to
    the coarsest."""
    cam = pattern.points_3d()
    if camera.forward_only:
        z = pose.transform(cam)[:, 2]
        z = z[z > 0]
        px_per_square = camera.model.fx * pattern.square_length_m / float(z.min()) if len(z) else 40.0
    else:
        pts = pose.transform(cam)
        J = camera.point_jacobian(pts[camera.in_view(pts)]) @ pose.R[:, :2]
        px_per_metre = np.linalg.svd(J, compute_uv=False)[:, 0].max(initial=0.0)
        px_per_square = float(px_per_metre) * pattern.square_length_m if len(J) else 40.0
    need = px_per_square * supersample
    finest = 0
    while finest + 1 < len(MIP_TEXELS_PER_SQUARE) and MIP_TEXELS_PER_SQUARE[finest + 1] >= need:
        finest += 1
    return range(finest, len(MIP_TEXELS_PER_SQUARE))
