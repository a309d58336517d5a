"""Physically based simulator of sharp and motion-blurred frames of the star target.

A frame is rendered as a real camera records it:

1. the target's reflectance ``S`` (exact, anti-aliased texture of the page, ``pattern.py``);
2. camera motion during the exposure: ``X_cam(tau) = Exp(tau xi + tau^2 xi2) X_cam(0)`` for
   normalised time ``tau in [-1/2, 1/2]`` (``xi = (omega, v)`` a twist in the camera frame,
   ``xi2`` its curvature), integrated by ``T`` time samples ``tau_i = (i + 1/2) / T - 1/2``;
3. the true lens (:class:`TrueCamera`: Brown-Conrady plus a smooth non-parametric deviation),
   applied once to the time integral, which is exact because the lens maps every time sample
   through the same coordinate change;
4. the pixel's area: everything above is rendered ``supersample`` times finer and box-averaged;
5. defocus (a Gaussian of ``defocus_sigma`` px), illumination (a linear gradient) and
   vignetting, both applied to the blurred irradiance;
6. Poisson-Gaussian noise and 8-bit quantisation.

Ground truth per frame: the mid-exposure pose (``tau = 0``), each feature's mid-exposure image
position and its time-averaged position (the mean of the ``T`` sampled positions, which is the
centroid of the feature's motion PSF; the symmetric defocus does not move it), visibility, the
local blur length (the length of the sampled image path), and the true PSF at any image point
(:meth:`FrameTruth.psf_at`). Pixel convention: OpenCV (top-left pixel centre at (0, 0)).
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.interpolate import RectBivariateSpline

from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.homography import homography_centre, translation
from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import atomic_path, atomic_write_text, ensure_writable_dir
from blurcalib.pipeline.runtime import exit_with_parent
from blurcalib.psf.kernel import psf_centroid
from blurcalib.target.pattern import StarPattern, layout_pattern, star_sector_white

GROUND_TRUTH_FILE = "ground_truth.json"
GROUND_TRUTH_VERSION = 1


# ------------------------------------------------------------------------------ the true camera
@dataclass(frozen=True)
class TrueCamera:
    """The simulated lens: Brown-Conrady followed by a smooth deviation field.

    ``x = pi_BC(X) + delta(pi_BC(X))`` px, with
    ``delta(p) = sum_m a_m sin(2 pi (k_m . p / (W, H)) + phi_m)`` (``a_m (2,)`` px,
    ``k_m (2,)`` cycles per image). A generic (B-spline) model can represent ``delta``; a
    parametric one cannot, which is what makes the simulated data worth a generic model.

    Attributes:
        model: the Brown-Conrady part.
        waves: ``(M, 5)`` rows ``(a_x, a_y, k_x, k_y, phi)`` of the deviation.
    """

    model: BrownConrady
    waves: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))

    def deviation(self, px: np.ndarray) -> np.ndarray:
        """``delta(px)``: ``(N, 2)`` px -> ``(N, 2)`` px."""
        px = np.asarray(px, dtype=np.float64)
        out = np.zeros_like(px)
        size = np.array([self.model.width, self.model.height], dtype=np.float64)
        for ax, ay, kx, ky, phi in self.waves:
            s = np.sin(2.0 * np.pi * (px[..., 0] * kx / size[0] + px[..., 1] * ky / size[1]) + phi)
            out[..., 0] += ax * s
            out[..., 1] += ay * s
        return out

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points ``(N, 3)`` m -> pixels ``(N, 2)`` px."""
        p = self.model.project(points_cam)
        return p + self.deviation(p)

    def unproject(self, px: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` px -> undistorted normalised coordinates ``(N, 2)``.

        Inverts the deviation by fixed-point iteration ``y <- px - delta(y)`` (a contraction:
        ``delta`` varies by far less than a pixel per pixel), then the Brown-Conrady part.
        """
        px = np.asarray(px, dtype=np.float64)
        y = px.copy()
        for _ in range(8):
            y = px - self.deviation(y)
        return self.model.unproject(y)

    def to_dict(self) -> dict:
        return {"brown_conrady": self.model.to_dict(), "deviation_waves": self.waves.tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> TrueCamera:
        return cls(BrownConrady.from_dict(data["brown_conrady"]),
                   np.asarray(data["deviation_waves"], dtype=np.float64).reshape(-1, 5))


def d435i_like_camera(seed: int = 0, deviation_px: float = 0.3) -> TrueCamera:
    """A 1280x720 camera like a RealSense D435I's infrared imager, with a lens deviation.

    Brown-Conrady intrinsics near the D435I's (fx = fy ~ 645 px, ~90 degree horizontal field),
    and a deviation of about ``deviation_px`` px peak made of 6 smooth waves of 0.5 to 2.5
    cycles per image.
    """
    rng = np.random.default_rng(seed)
    model = BrownConrady(fx=645.2, fy=644.6, cx=637.8, cy=361.4, k1=0.041, k2=-0.058,
                         p1=0.0007, p2=-0.0004, k3=0.019, width=1280, height=720)
    m = 6
    directions = rng.uniform(0, 2 * np.pi, m)
    freq = rng.uniform(0.5, 2.5, m)
    amps = rng.normal(size=(m, 2))
    amps *= deviation_px / max(np.abs(amps).sum(axis=0).max(), 1e-9)
    waves = np.column_stack([amps, freq * np.cos(directions), freq * np.sin(directions),
                             rng.uniform(0, 2 * np.pi, m)])
    return TrueCamera(model, waves)


# ------------------------------------------------------------------------------------ motion
def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exponential of a twist ``xi = (omega (3,) rad, v (3,) m)``: ``(R (3,3), t (3,))``."""
    omega, v = xi[:3], xi[3:]
    theta = float(np.linalg.norm(omega))
    W = _skew(omega)
    if theta < 1e-9:
        return np.eye(3) + W, v + 0.5 * W @ v
    a = math.sin(theta) / theta
    b = (1.0 - math.cos(theta)) / theta**2
    c = (theta - math.sin(theta)) / theta**3
    R = np.eye(3) + a * W + b * W @ W
    V = np.eye(3) + b * W + c * W @ W
    return R, V @ v


@dataclass(frozen=True)
class Motion:
    """Camera motion during one exposure, in the mid-exposure camera frame.

    Attributes:
        xi: ``(6,)`` twist ``(omega rad, v m)`` over the whole exposure.
        xi2: ``(6,)`` curvature term (hand-shake paths that bend and change speed).
        samples: number of time samples T.
    """

    xi: np.ndarray
    xi2: np.ndarray
    samples: int

    @property
    def taus(self) -> np.ndarray:
        """``(T,)`` normalised sample times in ``(-1/2, 1/2)``."""
        return (np.arange(self.samples) + 0.5) / self.samples - 0.5

    def poses(self, mid: Pose) -> list[Pose]:
        """The camera pose at every time sample: ``Exp(tau xi + tau^2 xi2) o mid``."""
        out = []
        for tau in self.taus:
            R, t = se3_exp(tau * self.xi + tau * tau * self.xi2)
            out.append(Pose(R, t).compose(mid))
        return out

    @staticmethod
    def still() -> Motion:
        return Motion(np.zeros(6), np.zeros(6), 1)


# ----------------------------------------------------------------------------- ground truth
@dataclass
class FrameTruth:
    """Ground truth of one simulated frame (pixels in the OpenCV convention).

    Attributes:
        name: file name of the frame (``sharp/0003.png``).
        kind: ``"sharp"`` or ``"blurry"``.
        pose: mid-exposure pose (target -> camera).
        motion: the camera motion during the exposure.
        defocus_sigma: Gaussian defocus (px).
        feature_ids: ``(M,)`` ids of all pattern features (``pattern.features`` order).
        mid: ``(M, 2)`` px mid-exposure image positions.
        mean: ``(M, 2)`` px time-averaged positions (PSF centroids).
        visible: ``(M,)`` bool, mid position inside the image and in front of the camera.
        block_inside: ``(M,)`` bool, the feature's whole star square is inside the image.
        blur_length: ``(M,)`` px length of the feature's image path during the exposure.
        illumination: ``(3,)`` gradient ``g0 + gx u + gy v`` over ``u, v in [-1, 1]``.
        vignetting: strength ``v`` of ``1 - v r^2`` (``r = 1`` at the image corners).
        levels: ``(black, white)`` grey levels of the ink and the paper.
        noise: ``(gain, read_sigma)`` of the Poisson-Gaussian noise (grey levels).
    """

    name: str
    kind: str
    pose: Pose
    motion: Motion
    defocus_sigma: float
    feature_ids: np.ndarray
    mid: np.ndarray
    mean: np.ndarray
    visible: np.ndarray
    block_inside: np.ndarray
    blur_length: np.ndarray
    illumination: np.ndarray
    vignetting: float
    levels: tuple[float, float]
    noise: tuple[float, float]

    def psf_at(self, camera: TrueCamera, point_px: np.ndarray, size: int = 17) -> np.ndarray:
        """The true PSF at an image point: motion path splatted, then defocus.

        The kernel ``k`` is such that the frame near ``point_px`` is ``k * I_mid`` with
        ``I_mid`` the sharp mid-exposure image: ``k[i, j]`` is the weight of offset
        ``(j - c, i - c)`` px, ``c = (size - 1) / 2``. It excludes the pixel's own box
        integration. Its centroid is the time-averaged minus the mid-exposure position.

        Args:
            camera: the frame's true camera.
            point_px: ``(2,)`` mid-exposure image point (px).
            size: odd kernel side (px).
        Returns:
            ``(size, size)`` float64 kernel summing to 1 (less if the path leaves the window).
        """
        offsets = image_path(camera, self.pose, self.motion, point_px) - np.asarray(point_px)
        kernel = splat(offsets, size)
        if self.defocus_sigma > 0:
            g = cv2.getGaussianKernel(_gauss_ksize(self.defocus_sigma), self.defocus_sigma)
            kernel = cv2.filter2D(kernel, -1, g @ g.T, borderType=cv2.BORDER_CONSTANT)
        return kernel

    def to_dict(self) -> dict:
        return {
            "name": self.name, "kind": self.kind, "pose": self.pose.to_dict(),
            "motion": {"xi": self.motion.xi.tolist(), "xi2": self.motion.xi2.tolist(),
                       "samples": self.motion.samples},
            "defocus_sigma": self.defocus_sigma,
            "illumination": self.illumination.tolist(), "vignetting": self.vignetting,
            "levels": list(self.levels), "noise": list(self.noise),
            "features": {
                "feature_id": self.feature_ids.tolist(),
                "mid": np.round(self.mid, 9).tolist(),
                "mean": np.round(self.mean, 9).tolist(),
                "visible": self.visible.astype(int).tolist(),
                "block_inside": self.block_inside.astype(int).tolist(),
                "blur_length": np.round(self.blur_length, 6).tolist(),
            },
        }

    @classmethod
    def from_dict(cls, d: dict) -> FrameTruth:
        f = d["features"]
        m = d["motion"]
        return cls(
            name=d["name"], kind=d["kind"], pose=Pose.from_dict(d["pose"]),
            motion=Motion(np.asarray(m["xi"], float), np.asarray(m["xi2"], float), int(m["samples"])),
            defocus_sigma=float(d["defocus_sigma"]),
            feature_ids=np.asarray(f["feature_id"], dtype=np.int64),
            mid=np.asarray(f["mid"], dtype=np.float64).reshape(-1, 2),
            mean=np.asarray(f["mean"], dtype=np.float64).reshape(-1, 2),
            visible=np.asarray(f["visible"], dtype=bool),
            block_inside=np.asarray(f["block_inside"], dtype=bool),
            blur_length=np.asarray(f["blur_length"], dtype=np.float64),
            illumination=np.asarray(d["illumination"], dtype=np.float64),
            vignetting=float(d["vignetting"]), levels=tuple(d["levels"]), noise=tuple(d["noise"]))


@dataclass
class DatasetTruth:
    """Ground truth of a simulated dataset (``ground_truth.json``)."""

    camera: TrueCamera
    pattern_file: str
    frames: list[FrameTruth]
    settings: dict

    def frame(self, name: str) -> FrameTruth:
        for f in self.frames:
            if f.name == name:
                return f
        raise KeyError(f"no frame {name!r} in the ground truth")

    def to_dict(self) -> dict:
        return {"format": "blurcalib-synth", "version": GROUND_TRUTH_VERSION,
                "pixel_convention": "opencv (top-left pixel centre at (0, 0))",
                "camera": self.camera.to_dict(), "pattern_file": self.pattern_file,
                "settings": self.settings, "frames": [f.to_dict() for f in self.frames]}


def load_ground_truth(path: str | os.PathLike) -> DatasetTruth:
    """Read ``ground_truth.json`` (a file, or the dataset folder containing it).

    Raises:
        ValueError: naming the file, when it is missing or not a blurcalib ground truth.
    """
    path = Path(path)
    if path.is_dir():
        path = path / GROUND_TRUTH_FILE
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if doc.get("format") != "blurcalib-synth":
            raise ValueError("not a blurcalib synthetic ground truth")
        return DatasetTruth(TrueCamera.from_dict(doc["camera"]), doc["pattern_file"],
                            [FrameTruth.from_dict(f) for f in doc["frames"]], doc["settings"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: cannot read ground truth ({exc})") from None


# ------------------------------------------------------------------------------- geometry
def image_path(camera: TrueCamera, pose: Pose, motion: Motion, point_px: np.ndarray) -> np.ndarray:
    """``(T, 2)`` px: where the target point seen at ``point_px`` at mid-exposure is imaged
    at each time sample."""
    P = _backproject_to_plane(camera, pose, np.asarray(point_px, float).reshape(1, 2))
    return np.stack([camera.project(p.transform(P))[0] for p in motion.poses(pose)])


def _backproject_to_plane(camera: TrueCamera, pose: Pose, px: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 2)`` -> target-plane points ``(N, 3)`` (Z = 0) seen there in ``pose``."""
    xn = camera.unproject(px)
    rays = np.concatenate([xn, np.ones((len(xn), 1))], axis=1) @ pose.R  # world directions
    origin = pose.camera_center
    s = -origin[2] / rays[:, 2]
    return origin + s[:, None] * rays


def splat(offsets: np.ndarray, size: int) -> np.ndarray:
    """Bilinearly splat equal-weight points ``(T, 2)`` px into a ``(size, size)`` kernel
    centred at offset 0 (kernel pixel ``(i, j)`` is offset ``(j - c, i - c)``)."""
    c = (size - 1) / 2
    kernel = np.zeros((size, size))
    w = 1.0 / len(offsets)
    for dx, dy in offsets:
        x, y = dx + c, dy + c
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0
        for yy, wy in ((y0, 1 - fy), (y0 + 1, fy)):
            for xx, wx in ((x0, 1 - fx), (x0 + 1, fx)):
                if 0 <= yy < size and 0 <= xx < size:
                    kernel[yy, xx] += w * wx * wy
    return kernel


def _gauss_ksize(sigma: float) -> int:
    return 2 * math.ceil(4.0 * sigma) + 1


# ------------------------------------------------------------------------------- texture
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


# ------------------------------------------------------------------------------- renderer
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
    """Renders frames of one :class:`TrueCamera`; caches the lens remap tables."""

    def __init__(self, camera: TrueCamera, settings: RenderSettings | None = None) -> None:
        self.camera = camera
        self.settings = settings or RenderSettings()
        ss = self.settings.supersample
        w, h = camera.model.width, camera.model.height
        # The lens map is smooth: solve it exactly on a coarse lattice of sensor sub-samples
        # and interpolate with bicubic splines (error far below 1e-3 px).
        step = 4
        fine_x = np.arange(w * ss)
        fine_y = np.arange(h * ss)
        coarse_x = np.append(fine_x[::step], fine_x[-1])
        coarse_y = np.append(fine_y[::step], fine_y[-1])
        gx, gy = np.meshgrid((coarse_x + 0.5) / ss - 0.5, (coarse_y + 0.5) / ss - 0.5)
        xn = camera.unproject(np.stack([gx.ravel(), gy.ravel()], axis=1))
        lo = xn.min(axis=0)
        hi = xn.max(axis=0)
        f = np.array([camera.model.fx, camera.model.fy]) * ss
        margin = 4.0
        self.canvas_K = np.array([[f[0], 0.0, -lo[0] * f[0] + margin],
                                  [0.0, f[1], -lo[1] * f[1] + margin],
                                  [0.0, 0.0, 1.0]])
        self.canvas_size = (math.ceil((hi[0] - lo[0]) * f[0] + 2 * margin),
                            math.ceil((hi[1] - lo[1]) * f[1] + 2 * margin))
        maps = []
        for axis in range(2):
            coarse = (xn[:, axis] * f[axis] + self.canvas_K[axis, 2]).reshape(len(coarse_y), -1)
            spline = RectBivariateSpline(coarse_y, coarse_x, coarse, kx=3, ky=3)
            maps.append(spline(fine_y, fine_x).astype(np.float32))
        self._map_x, self._map_y = maps

    def irradiance(self, levels: Sequence[Texture], pose: Pose, motion: Motion) -> np.ndarray:
        """Time-integrated, lens-mapped, pixel-integrated target image: ``(H, W)`` in [0, 1].

        Each time sample warps the texture onto an undistorted, supersampled canvas with the
        homography ``K_canvas [r1 r2 t](tau) to_plane`` (``eq:T``); the mean over samples is
        then mapped through the true lens and box-averaged over each pixel.

        ``levels`` is a mip pyramid of the same target (finest first, each level half the
        resolution of the previous). Every canvas sample blends the two levels whose texel
        size is closest to its own footprint (trilinear mip-mapping, weights from the
        mid-exposure pose), so the texture is neither aliased where the target is far nor
        blurred where it is near.
        """
        weights = self._level_weights(levels, pose)
        acc = np.zeros(self.canvas_size[::-1], dtype=np.float32)
        for level, (weight, box) in zip(levels, weights, strict=True):
            if weight is None:
                continue
            x0, y0, x1, y1 = box
            shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
            level_acc = np.zeros((y1 - y0, x1 - x0), dtype=np.float32)
            for p in motion.poses(pose):
                H = shift @ self.canvas_K @ np.column_stack([p.R[:, 0], p.R[:, 1], p.t]) \
                    @ level.to_plane
                warped = cv2.warpPerspective(level.image, H, (x1 - x0, y1 - y0),
                                             flags=cv2.INTER_LINEAR,
                                             borderMode=cv2.BORDER_CONSTANT,
                                             borderValue=float(level.background))
                cv2.accumulate(warped, level_acc)
            cv2.accumulateProduct(level_acc, weight, acc[y0:y1, x0:x1])
        acc /= motion.samples
        background = float(levels[0].background)
        sensor = cv2.remap(acc, self._map_x, self._map_y, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=background)
        w, h = self.camera.model.width, self.camera.model.height
        return cv2.resize(sensor, (w, h), interpolation=cv2.INTER_AREA)

    def _level_weights(self, levels: Sequence[Texture], pose: Pose
                       ) -> list[tuple[np.ndarray | None, tuple[int, int, int, int]]]:
        """Per-level blend weights over the canvas and their bounding boxes.

        The finest level's texels per canvas sample at canvas point ``x`` is
        ``rho(x) = sqrt(|det G| / |w(x)|^3)`` for the canvas-to-texture homography ``G`` with
        ``w(x) = G[2] . (x, y, 1)``; level ``lambda = log2 rho`` (clipped to the pyramid) is
        blended linearly between its two neighbouring integer levels.
        """
        cw, ch = self.canvas_size
        H = self.canvas_K @ np.column_stack([pose.R[:, 0], pose.R[:, 1], pose.t]) \
            @ levels[0].to_plane
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
                         probe_points: np.ndarray) -> int:
        """T such that no probe point moves more than ``max_step_px`` between samples."""
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


def sensor_image(irradiance: np.ndarray, truth: FrameTruth, rng: np.random.Generator) -> np.ndarray:
    """Defocus, illumination, vignetting, Poisson-Gaussian noise, 8-bit quantisation.

    ``grey = (black + (white - black) (g_d * E)) G(u, v) V(r)``, then
    ``noisy = gain Poisson(grey / gain) + N(0, read_sigma^2)``, rounded and clipped to
    ``[0, 255]``.
    """
    img = irradiance.astype(np.float64)
    if truth.defocus_sigma > 0:
        k = _gauss_ksize(truth.defocus_sigma)
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
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------ scenarios
@dataclass(frozen=True)
class SynthConfig:
    """What to simulate. Defaults: the README's demo dataset.

    Attributes:
        sharp, blurry: number of frames of each set.
        blur_min_px, blur_max_px: range of the median feature blur length of blurry frames.
        curved_fraction: share of blurry frames with curved hand-shake paths.
        max_tilt_deg: largest angle between optical axis and target normal.
        square_px: range of the star square's size in the image (px).
        defocus_px: range of the Gaussian defocus sigma (px).
        noise_sigma: approximate noise standard deviation at mid grey (grey levels).
        seed: random seed; the dataset is a deterministic function of the config.
    """

    sharp: int = 20
    blurry: int = 60
    blur_min_px: float = 2.0
    blur_max_px: float = 20.0
    curved_fraction: float = 0.5
    max_tilt_deg: float = 60.0
    square_px: tuple[float, float] = (24.0, 42.0)
    defocus_px: tuple[float, float] = (0.4, 0.9)
    noise_sigma: float = 2.0
    seed: int = 0
    supersample: int = 3

    def __post_init__(self) -> None:
        if self.sharp < 0 or self.blurry < 0:
            raise ValueError(f"frame counts must be >= 0, got {self.sharp} sharp, {self.blurry} blurry")
        if not (math.isfinite(self.noise_sigma) and self.noise_sigma >= 0):
            raise ValueError(f"noise (noise_sigma) must be a finite number >= 0 grey levels, got "
                             f"{self.noise_sigma}")
        if not 0 <= self.blur_min_px <= self.blur_max_px < math.inf:
            raise ValueError(f"need 0 <= blur_min_px <= blur_max_px, got {self.blur_min_px}, "
                             f"{self.blur_max_px}")
        if not 0 <= self.max_tilt_deg < 85:
            raise ValueError(f"max_tilt_deg must be in [0, 85), got {self.max_tilt_deg}")
        if not 0 < self.square_px[0] <= self.square_px[1]:
            raise ValueError(f"square_px must be an increasing positive range, got {self.square_px}")
        if self.supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(axis, float).reshape(3) * angle)
    return R


def sample_pose(pattern: StarPattern, camera: TrueCamera, rng: np.random.Generator,
                max_tilt_deg: float, square_px: tuple[float, float],
                tries: int = 200) -> Pose:
    """A pose with the tag fully in view, tilt up to ``max_tilt_deg``, anywhere in the image.

    A random target point is placed at a random image point (so that over many frames every
    image region, corners included, is covered) at the depth giving a random square size.
    """
    model = camera.model
    L = pattern.square_length_m
    tag_pts = np.concatenate([
        np.column_stack([pattern.tag_corners(t) * L, np.zeros(4)]) for t in pattern.apriltags])
    lo = np.array([-1.0, -1.0]) * L
    hi = np.array([pattern.squares_x - 1, pattern.squares_y - 1]) * L
    all_pts = pattern.points_3d()
    for _ in range(tries):
        tilt = math.radians(max_tilt_deg) * rng.uniform(0.0, 1.0)
        tilt_axis_angle = rng.uniform(0, 2 * np.pi)
        tilt_axis = np.array([math.cos(tilt_axis_angle), math.sin(tilt_axis_angle), 0.0])
        roll = rng.uniform(-0.5, 0.5)
        R = _rotation(np.array([0.0, 0.0, 1.0]), roll) @ _rotation(tilt_axis, tilt)
        anchor = np.append(rng.uniform(lo, hi), 0.0)
        pixel = rng.uniform([0, 0], [model.width - 1, model.height - 1])
        depth = model.fx * L / rng.uniform(*square_px)
        xn = camera.unproject(pixel[None])[0]
        t = depth * np.array([xn[0], xn[1], 1.0]) - R @ anchor
        pose = Pose(R, t)
        cam_pts = pose.transform(tag_pts)
        if np.any(cam_pts[:, 2] <= 0.05):
            continue
        tag_px = camera.project(cam_pts)
        margin = 30.0
        if not (np.all(tag_px >= margin) and np.all(tag_px[:, 0] <= model.width - 1 - margin)
                and np.all(tag_px[:, 1] <= model.height - 1 - margin)):
            continue
        feat_px = camera.project(pose.transform(all_pts))
        inside = ((feat_px[:, 0] >= 0) & (feat_px[:, 0] <= model.width - 1)
                  & (feat_px[:, 1] >= 0) & (feat_px[:, 1] <= model.height - 1))
        if inside.sum() >= 40:
            return pose
    raise RuntimeError("could not sample a pose with the tag in view; check the camera/pattern")


def sample_motion(renderer: Renderer, pose: Pose, pattern: StarPattern, rng: np.random.Generator,
                  blur_px: float, curved: bool) -> Motion:
    """A hand-shake motion whose median feature blur length over the visible part is ``blur_px``.

    Mostly rotation (as hand shake is), with some roll about the optical axis (blur that grows
    towards the image border) and some translation (including along the axis: zoom blur).
    """
    omega = rng.normal(size=3) * np.array([1.0, 1.0, 0.45])
    depth = float(pose.t[2])
    v = rng.normal(size=3) * np.array([0.25, 0.25, 0.35]) * depth
    xi = np.concatenate([omega, v])
    xi2 = np.concatenate([rng.normal(size=3), rng.normal(size=3) * 0.3 * depth]) if curved \
        else np.zeros(6)
    if curved:
        xi2 *= rng.uniform(0.4, 1.0) * np.linalg.norm(xi) / max(np.linalg.norm(xi2), 1e-12)
    pts = _visible_points(renderer.camera, pose, pattern)
    base = _path_lengths(renderer.camera, pose, Motion(xi, xi2, 33), pts)
    scale = blur_px / max(float(np.median(base)), 1e-9)
    # Path length is close to linear in the scale for small motions; refine once.
    base = _path_lengths(renderer.camera, pose, Motion(xi * scale, xi2 * scale, 33), pts)
    scale *= blur_px / max(float(np.median(base)), 1e-9)
    xi, xi2 = xi * scale, xi2 * scale
    samples = renderer.time_samples_for(pose, xi, xi2, pts)
    return Motion(xi, xi2, samples)


def _visible_points(camera: TrueCamera, pose: Pose, pattern: StarPattern) -> np.ndarray:
    pts = pattern.points_3d()
    px = camera.project(pose.transform(pts))
    m = camera.model
    inside = (px[:, 0] >= 0) & (px[:, 0] <= m.width - 1) & (px[:, 1] >= 0) & (px[:, 1] <= m.height - 1)
    return pts[inside]


def _path_lengths(camera: TrueCamera, pose: Pose, motion: Motion, pts: np.ndarray) -> np.ndarray:
    tracks = np.stack([camera.project(p.transform(pts)) for p in motion.poses(pose)])
    return np.linalg.norm(np.diff(tracks, axis=0), axis=2).sum(axis=0)


def frame_truth(name: str, kind: str, pattern: StarPattern, camera: TrueCamera, pose: Pose,
                motion: Motion, defocus_sigma: float, rng: np.random.Generator,
                noise_sigma: float) -> FrameTruth:
    """Ground truth of a frame (feature positions from the exact geometry)."""
    pts = pattern.points_3d()
    tracks = np.stack([camera.project(p.transform(pts)) for p in motion.poses(pose)])
    cam = pose.transform(pts)
    mid = camera.project(cam)
    m = camera.model
    visible = ((cam[:, 2] > 0) & (mid[:, 0] >= 0) & (mid[:, 0] <= m.width - 1)
               & (mid[:, 1] >= 0) & (mid[:, 1] <= m.height - 1))
    corners = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    fpts = pattern.features[:, None, :] + corners[None]
    corner_px = camera.project(pose.transform(np.concatenate(
        [fpts.reshape(-1, 2) * pattern.square_length_m, np.zeros((fpts.size // 2, 1))], axis=1)))
    corner_px = corner_px.reshape(-1, 4, 2)
    block_inside = visible & np.all((corner_px[..., 0] >= 0) & (corner_px[..., 0] <= m.width - 1)
                                    & (corner_px[..., 1] >= 0) & (corner_px[..., 1] <= m.height - 1),
                                    axis=1)
    blur = np.linalg.norm(np.diff(tracks, axis=0), axis=2).sum(axis=0) if len(tracks) > 1 \
        else np.zeros(len(pts))
    white = rng.uniform(170, 225)
    black = rng.uniform(15, 40)
    gain = noise_sigma**2 / ((white + black) / 2)
    return FrameTruth(
        name=name, kind=kind, pose=pose, motion=motion, defocus_sigma=defocus_sigma,
        feature_ids=np.arange(pattern.num_features), mid=mid, mean=tracks.mean(axis=0),
        visible=visible, block_inside=block_inside, blur_length=blur,
        illumination=np.array([1.0, rng.uniform(-0.12, 0.12), rng.uniform(-0.12, 0.12)]),
        vignetting=float(rng.uniform(0.1, 0.3)), levels=(black, white),
        noise=(gain, 0.5 * noise_sigma / 2.0))


MIP_TEXELS_PER_SQUARE = (320, 160, 80, 40, 20, 10)
"""Texture resolutions of the mip pyramid, finest first (multiples of 10, halving)."""


def mip_levels_for(camera: TrueCamera, pose: Pose, pattern: StarPattern, supersample: int) -> range:
    """Which pyramid levels a frame needs: from the one whose texels are no larger than a
    canvas sample at the nearest feature, down to the coarsest."""
    cam = pattern.points_3d()
    z = pose.transform(cam)[:, 2]
    z = z[z > 0]
    px_per_square = camera.model.fx * pattern.square_length_m / float(z.min()) if len(z) else 40.0
    need = px_per_square * supersample
    finest = 0
    while finest + 1 < len(MIP_TEXELS_PER_SQUARE) and MIP_TEXELS_PER_SQUARE[finest + 1] >= need:
        finest += 1
    return range(finest, len(MIP_TEXELS_PER_SQUARE))


@dataclass
class SimulatedFrame:
    """A rendered frame and its ground truth."""

    image: np.ndarray
    truth: FrameTruth


class Simulator:
    """Deterministic generator of a dataset: ``SynthConfig`` + pattern + camera -> frames."""

    def __init__(self, config: SynthConfig | None = None, pattern: StarPattern | None = None,
                 camera: TrueCamera | None = None) -> None:
        self.config = config or SynthConfig()
        self.pattern = pattern or layout_pattern()
        self.camera = camera or d435i_like_camera(self.config.seed)
        self.renderer = Renderer(self.camera, RenderSettings(supersample=self.config.supersample))
        self._textures: dict[int, Texture] = {}

    def texture(self, texels_per_square: int) -> Texture:
        """The page texture at a resolution (built once, then cached)."""
        if texels_per_square not in self._textures:
            self._textures[texels_per_square] = pattern_texture(self.pattern, texels_per_square)
        return self._textures[texels_per_square]

    def frame_names(self) -> list[tuple[str, str]]:
        """``(name, kind)`` of every frame, sharp ones first."""
        return ([(f"sharp/{i:04d}.png", "sharp") for i in range(self.config.sharp)]
                + [(f"blurry/{i:04d}.png", "blurry") for i in range(self.config.blurry)])

    def frame(self, index: int) -> SimulatedFrame:
        """Render frame ``index`` (its randomness depends only on the seed and the index)."""
        name, kind = self.frame_names()[index]
        cfg = self.config
        rng = np.random.default_rng([cfg.seed, index])
        pose = sample_pose(self.pattern, self.camera, rng, cfg.max_tilt_deg, cfg.square_px)
        if kind == "blurry":
            blur = rng.uniform(cfg.blur_min_px, cfg.blur_max_px)
            motion = sample_motion(self.renderer, pose, self.pattern, rng, blur,
                                   curved=bool(rng.uniform() < cfg.curved_fraction))
        else:
            motion = Motion.still()
        defocus = float(rng.uniform(*cfg.defocus_px))
        truth = frame_truth(name, kind, self.pattern, self.camera, pose, motion, defocus, rng,
                            cfg.noise_sigma)
        levels = [self.texture(MIP_TEXELS_PER_SQUARE[k])
                  for k in mip_levels_for(self.camera, pose, self.pattern, cfg.supersample)]
        irradiance = self.renderer.irradiance(levels, pose, motion)
        return SimulatedFrame(sensor_image(irradiance, truth, rng), truth)


_WORKER_SIM: Simulator | None = None
"""The simulator of a worker process of :func:`write_dataset` (never set in the main process)."""


def _init_worker(config: SynthConfig, pattern: StarPattern, camera: TrueCamera) -> None:
    global _WORKER_SIM  # each worker process builds its simulator (lens maps, textures) once
    exit_with_parent()
    cv2.setNumThreads(1)
    _WORKER_SIM = Simulator(config, pattern, camera)


def _render_in_worker(index: int) -> SimulatedFrame:
    assert _WORKER_SIM is not None
    return _WORKER_SIM.frame(index)


def write_dataset(out_dir: str | os.PathLike, config: SynthConfig | None = None,
                  pattern: StarPattern | None = None, camera: TrueCamera | None = None,
                  progress: Callable[[int, int, str], None] | None = None,
                  workers: int = 1) -> DatasetTruth:
    """Simulate a dataset into ``out_dir``: ``pattern.yaml``, ``sharp/*.png``,
    ``blurry/*.png`` and ``ground_truth.json`` (see ``docs/synthetic-data.md``).

    Every file is written atomically; the ground truth is written last, so a folder with a
    ``ground_truth.json`` is complete. ``workers > 1`` renders frames in that many processes
    (the result is identical: each frame's randomness depends only on the seed and its index).
    """
    out = ensure_writable_dir(out_dir)
    sim = Simulator(config, pattern, camera)
    sim.pattern.save_yaml(out / "pattern.yaml")
    names = sim.frame_names()
    truths: list[FrameTruth | None] = [None] * len(names)

    def store(index: int, frame: SimulatedFrame) -> None:
        name = names[index][0]
        ensure_writable_dir((out / name).parent)
        with atomic_path(out / name) as tmp:
            if not cv2.imwrite(str(tmp), frame.image):
                raise OSError(f"{out / name}: cannot write image")
        truths[index] = frame.truth
        if progress is not None:
            progress(sum(t is not None for t in truths), len(names), name)

    if workers > 1 and len(names) > 1:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                 initargs=(sim.config, sim.pattern, sim.camera)) as pool:
            futures = {pool.submit(_render_in_worker, i): i for i in range(len(names))}
            for future in as_completed(futures):
                store(futures[future], future.result())
    else:
        for i in range(len(names)):
            store(i, sim.frame(i))
    frames = [t for t in truths if t is not None]
    truth = DatasetTruth(sim.camera, "pattern.yaml", frames, asdict(sim.config))
    atomic_write_text(out / GROUND_TRUTH_FILE, json.dumps(truth.to_dict()))
    return truth


# --------------------------------------------------------------------------- simulated blocks
# Single blocks with exact ground truth, for the block solver's tests and benchmarks.
@dataclass(eq=False)
class SimulatedBlocks:
    """Synthetic blocks with ground truth (for tests and ``scripts/bench_deconv.py``).

    Attributes:
        image: ``(height, width)`` uint8, the blocks' tiles side by side.
        H_true: ``(B, 3, 3)`` true block homographies (block coords -> image px).
        H0: ``(B, 3, 3)`` perturbed initial homographies.
        psf_true: ``(B, Kt, Kt)`` true kernels (sum 1).
        centre_true: ``(B, 2)`` px, ``H_true(0, 0)`` plus the true kernel's centroid: the star
            centre's time-averaged position.
        features: ``(B, 2)`` int feature coordinates of the blocks.
    """

    image: np.ndarray
    H_true: np.ndarray
    H0: np.ndarray
    psf_true: np.ndarray
    centre_true: np.ndarray
    features: np.ndarray


def _motion_kernel(rng: np.random.Generator, length: float, size: int, gauss_sigma: float) -> np.ndarray:
    """A curved, unevenly travelled motion path of ``length`` px splatted into ``size x size``."""
    theta = rng.uniform(0, 2 * np.pi)
    d = np.array([math.cos(theta), math.sin(theta)])
    nrm = np.array([-d[1], d[0]])
    bend = rng.uniform(-0.25, 0.25) * length
    t = np.linspace(0.0, 1.0, 400) ** rng.uniform(0.7, 1.4)  # uneven speed
    pts = ((t - 0.5)[:, None] * length * d[None] + (4 * t * (1 - t))[:, None] * bend * nrm[None])
    pts = pts - pts.mean(axis=0) + rng.uniform(-1.0, 1.0, 2)
    k = splat(pts, size)
    if gauss_sigma > 0:
        k = cv2.GaussianBlur(k, (0, 0), gauss_sigma, borderType=cv2.BORDER_CONSTANT)
    return k / k.sum()


def simulate_blocks(pattern: StarPattern, num_blocks: int, rng: np.random.Generator, *,
                    square_px: tuple[float, float] = (26.0, 34.0), blur_px: tuple[float, float] = (4.0, 15.0),
                    gauss_sigma: tuple[float, float] = (0.0, 0.6), noise_sigma: float = 2.0,
                    init_shift_px: float = 1.5, init_scale: float = 0.03, supersample: int = 8,
                    tile_px: int = 96, ink: float = 30.0, paper: float = 200.0,
                    truth_kernel_size: int = 31, psf: np.ndarray | None = None) -> SimulatedBlocks:
    """Render ``num_blocks`` blurred star blocks with known ``H`` and PSF, one per tile.

    Each tile shows the exact pattern (:meth:`StarPattern.intensity`, box-filtered over
    ``supersample^2`` samples per pixel) around a random valid feature through a random
    perspective homography (square side in ``square_px``), blurred by a random curved motion
    path of ``blur_px`` length (:func:`blurcalib.sim.synth.splat`) and a Gaussian, scaled to
    ``ink..paper`` with gain and offset gradients applied after the blur (as ``synth.py`` does),
    with Gaussian noise of ``noise_sigma`` grey levels, quantised to 8 bits. ``H0`` is ``H_true``
    moved by up to ``init_shift_px`` px and scaled by up to ``init_scale`` about the centre.
    ``psf`` (``(Kt, Kt)`` or ``(B, Kt, Kt)``, odd ``Kt``) replaces the random motion kernels.
    """
    from scipy.signal import fftconvolve  # here: importing scipy.signal takes seconds

    if psf is not None:
        given = np.broadcast_to(np.asarray(psf, dtype=np.float64), (num_blocks, *np.shape(psf)[-2:]))
        truth_kernel_size = given.shape[-1]
    cols = math.ceil(math.sqrt(num_blocks))
    rows = math.ceil(num_blocks / cols)
    image = np.zeros((rows * tile_px, cols * tile_px))
    feats = pattern.features[rng.choice(pattern.num_features, num_blocks, replace=False)]
    H_true = np.zeros((num_blocks, 3, 3))
    H0 = np.zeros_like(H_true)
    kernels = np.zeros((num_blocks, truth_kernel_size, truth_kernel_size))
    centre = np.zeros((num_blocks, 2))
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    yy, xx = np.mgrid[0:tile_px, 0:tile_px].astype(np.float64)
    for b in range(num_blocks):
        ty, tx = divmod(b, cols)
        half = 0.5 * rng.uniform(*square_px)
        ang = rng.uniform(0, 2 * np.pi)
        R = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
        Aff = half * R @ np.array([[1.0 + rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)], [0.0, 1.0]])
        Hb = np.eye(3)
        Hb[:2, :2] = Aff
        Hb[:2, 2] = tile_px / 2 - 0.5 + rng.uniform(-0.5, 0.5, 2)
        Hb = Hb @ np.array([[1, 0, 0], [0, 1, 0], [*rng.uniform(-0.08, 0.08, 2), 1.0]])
        Hb /= Hb[2, 2]
        fx, fy = feats[b]
        to_feature = np.array([[0.5, 0, fx], [0, 0.5, fy], [0, 0, 1.0]]) @ np.linalg.inv(Hb)
        acc = np.zeros((tile_px, tile_px))
        for oy in offs:
            for ox in offs:
                X = np.stack([xx + ox, yy + oy, np.ones_like(xx)], axis=-1) @ to_feature.T
                acc += pattern.intensity(X[..., :2] / X[..., 2:])
        latent = acc / supersample**2
        if psf is None:
            k = _motion_kernel(rng, rng.uniform(*blur_px), truth_kernel_size, rng.uniform(*gauss_sigma))
        else:
            k = given[b] / given[b].sum()
        blurred = fftconvolve(latent, k, mode="same")
        u = (xx - tile_px / 2) / (tile_px / 2)
        v = (yy - tile_px / 2) / (tile_px / 2)
        gain = (paper - ink) * (1.0 + rng.uniform(-0.08, 0.08) * u + rng.uniform(-0.08, 0.08) * v)
        offset = ink * (1.0 + rng.uniform(-0.2, 0.2) * u + rng.uniform(-0.2, 0.2) * v)
        tile = offset + gain * blurred + rng.normal(0.0, noise_sigma, blurred.shape)
        image[ty * tile_px:(ty + 1) * tile_px, tx * tile_px:(tx + 1) * tile_px] = tile
        Hi = translation(np.array([tx * tile_px, ty * tile_px], dtype=np.float64)) @ Hb
        H_true[b] = Hi
        kernels[b] = k
        c0 = homography_centre(Hi)
        centre[b] = c0 + psf_centroid(k, 0.0)
        shift = rng.normal(size=2)
        shift *= rng.uniform(0, init_shift_px) / np.linalg.norm(shift)
        sc = 1.0 + rng.uniform(-init_scale, init_scale)
        H0[b] = translation(c0 + shift) @ np.diag([sc, sc, 1.0]) @ translation(-c0) @ Hi
    img8 = np.clip(np.round(image), 0, 255).astype(np.uint8)
    return SimulatedBlocks(img8, H_true, H0, kernels, centre, feats)
