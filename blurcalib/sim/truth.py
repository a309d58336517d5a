"""Ground truth of the simulator: the true camera, the motion during an exposure, and what each
simulated frame shows (its poses and every feature's true image positions and blur).

* :class:`TrueCamera`: a lens model (Brown-Conrady, or any model of the parametric family up to a
  200 degree field) plus a smooth non-parametric deviation; :func:`d435i_like_camera` and
  :func:`fisheye_camera` are the presets.
* :class:`Motion`: ``X_cam(tau) = Exp(tau xi + tau^2 xi2) X_cam(0)`` for time ``tau`` in exposure
  times (``tau = 0`` the frame's reference instant).
* :class:`FrameTruth`, :class:`DatasetTruth`: ``ground_truth.json``
  (``docs/synthetic-data.md``). With a rolling shutter (:mod:`blurcalib.camera.shutter`) a feature
  is the time-average of its image over the window of the row where it is seen.

Pixel convention: OpenCV (top-left pixel centre at (0, 0)).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import torch

from blurcalib.camera.family import as_family, camera_from_dict
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.camera.shutter import exposure_grid, row_time, window_weights
from blurcalib.geometry.lie import exp_so3, skew
from blurcalib.geometry.pose import Pose

GROUND_TRUTH_FILE = "ground_truth.json"
GROUND_TRUTH_VERSION = 1


# ------------------------------------------------------------------------------ the true camera
FISHEYE_FIELD_STOP_DEG = 100.0
"""Half angle (deg) of a fisheye preset's image circle: rays further off the axis are dark."""


@dataclass(frozen=True)
class TrueCamera:
    """The simulated lens: a lens model followed by a smooth deviation field.

    ``x = pi(X) + delta(pi(X))`` px, with
    ``delta(p) = sum_m a_m sin(2 pi (k_m . p / (W, H)) + phi_m)`` (``a_m (2,)`` px,
    ``k_m (2,)`` cycles per image). A generic (B-spline) model can represent ``delta``; a
    parametric one cannot, which is what makes the simulated data worth a generic model.

    A :class:`BrownConrady` model is a forward-looking lens (it sees ``Z > 0``; the renderer
    draws it through one perspective canvas); a model of the parametric family
    (:class:`blurcalib.camera.lens.ParametricCamera`) sees every direction of its valid field
    up to ``field_stop_deg`` off the axis (rays beyond are dark), beyond 90 degrees too.

    Attributes:
        model: the lens model.
        waves: ``(M, 5)`` rows ``(a_x, a_y, k_x, k_y, phi)`` of the deviation.
        field_stop_deg: the image circle's half angle (deg) of a family model; None: its whole
            valid field.
    """

    model: BrownConrady | ParametricCamera
    waves: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    field_stop_deg: float | None = None

    @property
    def forward_only(self) -> bool:
        """Whether the lens is the forward-looking Brown-Conrady lens (:class:`BrownConrady`)."""
        return isinstance(self.model, BrownConrady)

    @property
    def width(self) -> int:
        return self.model.width

    @property
    def height(self) -> int:
        return self.model.height

    @property
    def field_stop(self) -> float:
        """The largest angle off the optical axis (rad) the lens sees."""
        if isinstance(self.model, BrownConrady):
            return math.pi / 2
        limit = self.model.max_angle
        return limit if self.field_stop_deg is None else min(limit, math.radians(self.field_stop_deg))

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
        return cast(np.ndarray, p + self.deviation(p))

    def in_view(self, points_cam: np.ndarray) -> np.ndarray:
        """``(N,) bool``: camera-frame points ``(N, 3)`` the lens sees (``Z > 0`` for the
        forward-looking lens; in the valid field and within the field stop otherwise)."""
        pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        if isinstance(self.model, BrownConrady):
            return pts[:, 2] > 0
        cos = pts[:, 2] / np.maximum(np.linalg.norm(pts, axis=1), 1e-300)
        return cast(np.ndarray, self.model.valid_directions(pts) & (cos >= math.cos(self.field_stop)))

    def _undeviate(self, px: np.ndarray) -> np.ndarray:
        """The model's pixel ``y`` with ``y + delta(y) = px``: fixed-point iteration
        ``y <- px - delta(y)`` (a contraction: ``delta`` varies by far less than a pixel per pixel)."""
        px = np.asarray(px, dtype=np.float64)
        y = px.copy()
        for _ in range(8):
            y = px - self.deviation(y)
        return y

    def unproject(self, px: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` px -> undistorted normalised coordinates ``(N, 2)`` (forward rays;
        NaN for a ray with ``Z <= 0``)."""
        y = self._undeviate(px)
        if self.forward_only:
            return self.model.unproject(y)
        rays = self.model.unproject(y)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(rays[..., 2:] > 0, rays[..., :2] / rays[..., 2:], np.nan)

    def pixel_to_ray(self, px: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` px -> unit viewing directions ``(N, 3)`` (NaN where none)."""
        y = self._undeviate(px)
        if not self.forward_only:
            return self.model.unproject(y)
        xn = self.model.unproject(y)
        rays = np.concatenate([xn, np.ones((*xn.shape[:-1], 1))], axis=-1)
        return cast(np.ndarray, rays / np.linalg.norm(rays, axis=-1, keepdims=True))

    def point_jacobian(self, points_cam: np.ndarray) -> np.ndarray:
        """``(N, 2, 3)`` px/m: the lens model's ``d pi / d X`` (the deviation's own slope, below
        1e-2, is left out: this sizes sampling densities)."""
        d_point = as_family(self.model).project_with_jacobian(points_cam).d_point
        assert d_point is not None
        return d_point

    def to_dict(self) -> dict[str, Any]:
        if self.forward_only:
            return {"brown_conrady": self.model.to_dict(), "deviation_waves": self.waves.tolist()}
        return {"lens": self.model.to_dict(), "deviation_waves": self.waves.tolist(),
                "field_stop_deg": self.field_stop_deg}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrueCamera:
        waves = np.asarray(data["deviation_waves"], dtype=np.float64).reshape(-1, 5)
        if "lens" in data:
            stop = data.get("field_stop_deg")
            return cls(camera_from_dict(data["lens"]), waves, None if stop is None else float(stop))
        return cls(BrownConrady.from_dict(data["brown_conrady"]), waves)


def deviation_waves(rng: np.random.Generator, deviation_px: float, count: int = 6) -> np.ndarray:
    """``(count, 5)`` deviation waves of about ``deviation_px`` px peak, 0.5 to 2.5 cycles per image
    in random directions (:class:`TrueCamera`)."""
    directions = rng.uniform(0, 2 * np.pi, count)
    freq = rng.uniform(0.5, 2.5, count)
    amps = rng.normal(size=(count, 2))
    amps *= deviation_px / max(np.abs(amps).sum(axis=0).max(), 1e-9)
    return np.column_stack([amps, freq * np.cos(directions), freq * np.sin(directions),
                            rng.uniform(0, 2 * np.pi, count)])


def d435i_like_camera(seed: int = 0, deviation_px: float = 0.3) -> TrueCamera:
    """A 1280x720 camera like a RealSense D435I's infrared imager, with a lens deviation.

    Brown-Conrady intrinsics near the D435I's (fx = fy ~ 645 px, ~90 degree horizontal field),
    and a deviation of about ``deviation_px`` px peak made of 6 smooth waves of 0.5 to 2.5
    cycles per image.
    """
    rng = np.random.default_rng(seed)
    model = BrownConrady(fx=645.2, fy=644.6, cx=637.8, cy=361.4, k1=0.041, k2=-0.058,
                         p1=0.0007, p2=-0.0004, k3=0.019, width=1280, height=720)
    return TrueCamera(model, deviation_waves(rng, deviation_px))


FISHEYE_COEFFICIENTS = (-0.021, 0.0013, -0.00021, 0.0)
"""``k1..k4`` of the fisheye presets: between the equidistant (``r = f theta``) and the
equisolid-angle (``r = 2 f sin(theta / 2)``) lens, increasing beyond 160 degrees off the axis."""


def fisheye_camera(fov_deg: float = 130.0, seed: int = 0, deviation_px: float = 0.3,
                   width: int = 1280, height: int = 720) -> TrueCamera:
    """A fisheye of ``fov_deg`` horizontal field (up to 200 degrees) on a ``width x height`` sensor.

    Kannala-Brandt with :data:`FISHEYE_COEFFICIENTS`, its focal length such that the image's left
    and right edges are ``fov_deg / 2`` off the axis, the principal point a few pixels off the
    centre, an image circle of :data:`FISHEYE_FIELD_STOP_DEG` (a 190 degree lens's corners are
    dark), and a deviation of about ``deviation_px`` px peak (:func:`deviation_waves`).
    """
    if not 0 < fov_deg <= 2 * FISHEYE_FIELD_STOP_DEG:
        raise ValueError(f"fisheye field of view must be in (0, {2 * FISHEYE_FIELD_STOP_DEG:g}] degrees, "
                         f"got {fov_deg}")
    rng = np.random.default_rng(seed)
    half = math.radians(fov_deg) / 2.0
    k1, k2, k3, k4 = FISHEYE_COEFFICIENTS
    t2 = half * half
    theta_d = half * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    f = width / 2.0 / theta_d
    model = KannalaBrandtCamera.from_values(width, height, fx=f, fy=f * 1.0004, cx=(width - 1) / 2.0 + 2.3,
                                            cy=(height - 1) / 2.0 - 1.6, k1=k1, k2=k2, k3=k3, k4=k4)
    return TrueCamera(model, deviation_waves(rng, deviation_px), FISHEYE_FIELD_STOP_DEG)


# ------------------------------------------------------------------------------------ motion
def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exponential of a twist ``xi = (omega (3,) rad, v (3,) m)``: ``(R (3,3), t (3,) m)``,
    ``R = exp([omega]_x)``, ``t = V v`` with ``V = I + b [omega]_x + c [omega]_x^2``."""
    omega = torch.as_tensor(np.asarray(xi[:3], dtype=np.float64))[None]
    R = exp_so3(omega)[0].numpy()
    W = skew(omega)[0].numpy()
    theta = float(np.linalg.norm(xi[:3]))
    if theta < 1e-9:
        return R, xi[3:] + 0.5 * W @ xi[3:]
    b = (1.0 - math.cos(theta)) / theta**2
    c = (theta - math.sin(theta)) / theta**3
    return R, (np.eye(3) + b * W + c * W @ W) @ xi[3:]


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
        """The camera pose at every time sample of the exposure (:attr:`taus`)."""
        return self.poses_at(mid, self.taus)

    def poses_at(self, mid: Pose, taus: np.ndarray) -> list[Pose]:
        """The camera pose ``Exp(tau xi + tau^2 xi2) o mid`` at times ``taus (K,)``."""
        out = []
        for tau in taus:
            R, t = se3_exp(tau * self.xi + tau * tau * self.xi2)
            out.append(Pose(R, t).compose(mid))
        return out

    def grid_poses(self, mid: Pose, height: int, rolling_shutter: float) -> list[Pose]:
        """The pose at every sample of the frame's exposure grid
        (:func:`blurcalib.camera.shutter.exposure_grid`; the exposure's samples when ``r = 0``)."""
        return self.poses_at(mid, exposure_grid(height, rolling_shutter, self.samples).times)

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
        pose: the pose at ``tau = 0`` (target -> camera): mid-exposure (of the middle row with a
            rolling shutter).
        motion: the camera motion during the exposure (and the readout).
        defocus_sigma: Gaussian defocus (px).
        feature_ids: ``(M,)`` ids of all pattern features (``pattern.features`` order).
        mid: ``(M, 2)`` px image positions at ``tau = 0``.
        mean: ``(M, 2)`` px time-averaged positions (PSF centroids) over the window of the row
            where each is seen (:func:`time_averaged_positions`).
        visible: ``(M,)`` bool, mid position inside the image and in front of the camera.
        block_inside: ``(M,)`` bool, the feature's whole star square is inside the image.
        blur_length: ``(M,)`` px length of the feature's image path during its row's window.
        illumination: ``(3,)`` gradient ``g0 + gx u + gy v`` over ``u, v in [-1, 1]``.
        vignetting: strength ``v`` of ``1 - v r^2`` (``r = 1`` at the image corners).
        levels: ``(black, white)`` grey levels of the ink and the paper.
        noise: ``(gain, read_sigma)`` of the Poisson-Gaussian noise (grey levels).
        rolling_shutter: readout ratio ``r`` (readout time / exposure time; 0: global shutter).
        height: sensor rows ``H`` (px) the row windows are counted over.
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
    rolling_shutter: float = 0.0
    height: int = 0

    def psf_at(self, camera: TrueCamera, point_px: np.ndarray, size: int = 17) -> np.ndarray:
        """The true PSF at an image point: motion path splatted, then defocus.

        The kernel ``k`` is such that the frame near ``point_px`` is ``k * I_mid`` with
        ``I_mid`` the sharp image at ``tau = 0``: ``k[i, j]`` is the weight of offset
        ``(j - c, i - c)`` px, ``c = (size - 1) / 2``. It excludes the pixel's own box
        integration. Its centroid is the time-averaged minus the ``tau = 0`` position. With a
        rolling shutter the path runs over the window of the row where the point is seen.

        Args:
            camera: the frame's true camera.
            point_px: ``(2,)`` image point at ``tau = 0`` (px).
            size: odd kernel side (px).
        Returns:
            ``(size, size)`` float64 kernel summing to 1 (less if the path leaves the window).
        """
        P = _backproject_to_plane(camera, self.pose, np.asarray(point_px, float).reshape(1, 2))
        track, weights = row_window_track(camera, self.pose, self.motion, P, self.height,
                                          self.rolling_shutter)
        kernel = splat(track[:, 0] - np.asarray(point_px, float), size, weights[:, 0])
        if self.defocus_sigma > 0:
            g = cv2.getGaussianKernel(gauss_ksize(self.defocus_sigma), self.defocus_sigma)
            kernel = cv2.filter2D(kernel, -1, g @ g.T, borderType=cv2.BORDER_CONSTANT)
        return kernel

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "kind": self.kind, "pose": self.pose.to_dict(),
            "motion": {"xi": self.motion.xi.tolist(), "xi2": self.motion.xi2.tolist(),
                       "samples": self.motion.samples},
            "defocus_sigma": self.defocus_sigma,
            "illumination": self.illumination.tolist(), "vignetting": self.vignetting,
            "levels": list(self.levels), "noise": list(self.noise),
            "rolling_shutter": self.rolling_shutter, "height": self.height,
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
    def from_dict(cls, d: dict[str, Any]) -> FrameTruth:
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
            vignetting=float(d["vignetting"]), levels=tuple(d["levels"]), noise=tuple(d["noise"]),
            rolling_shutter=float(d.get("rolling_shutter", 0.0)), height=int(d.get("height", 0)))


@dataclass
class DatasetTruth:
    """Ground truth of a simulated dataset (``ground_truth.json``)."""

    camera: TrueCamera
    pattern_file: str
    frames: list[FrameTruth]
    settings: dict[str, Any]

    def frame(self, name: str) -> FrameTruth:
        for f in self.frames:
            if f.name == name:
                return f
        raise KeyError(f"no frame {name!r} in the ground truth")

    def to_dict(self) -> dict[str, Any]:
        return {"format": "blurcalib-synth", "version": GROUND_TRUTH_VERSION,
                "pixel_convention": "opencv (top-left pixel centre at (0, 0))",
                "camera": self.camera.to_dict(), "pattern_file": self.pattern_file,
                "settings": self.settings, "frames": [f.to_dict() for f in self.frames]}


def load_ground_truth(path: str | os.PathLike[str]) -> DatasetTruth:
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
def row_window_track(camera: TrueCamera, pose: Pose, motion: Motion, points: np.ndarray, height: int,
                     rolling_shutter: float, iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Image tracks of target points ``(M, 3)`` m over the exposure grid and each point's weights.

    The weights are those of the window of the row where the point is seen, the row of its
    time-averaged position ``y``: ``c(y)`` (continuous ``y``), found by iterating
    ``y -> c(y) -> weights -> y`` from the ``tau = 0`` position.

    Returns:
        ``(N, M, 2)`` px positions at the grid's ``N`` times and ``(N, M)`` weights (each column
        sums to 1; ``1 / T`` each with a global shutter).
    """
    grid = exposure_grid(height, rolling_shutter, motion.samples)
    tracks = np.stack([camera.project(p.transform(points)) for p in motion.poses_at(pose, grid.times)])
    if rolling_shutter == 0:
        return tracks, np.full(tracks.shape[:2], 1.0 / motion.samples)
    y = camera.project(pose.transform(points))[:, 1]
    for _ in range(iterations):
        weights = window_weights(grid, row_time(y, height, rolling_shutter))
        y = (weights * tracks[..., 1]).sum(axis=0)
    return tracks, window_weights(grid, row_time(y, height, rolling_shutter))


def time_averaged_positions(camera: TrueCamera, pose: Pose, motion: Motion, points: np.ndarray,
                            height: int, rolling_shutter: float) -> tuple[np.ndarray, np.ndarray]:
    """Each target point's ``(M, 3)`` m time-averaged image position ``(M, 2)`` px over its row's
    window (:func:`row_window_track`) and the length ``(M,)`` px of its image path in that window."""
    tracks, weights = row_window_track(camera, pose, motion, points, height, rolling_shutter)
    mean = (weights[..., None] * tracks).sum(axis=0)
    inside = weights > 0
    step = np.linalg.norm(np.diff(tracks, axis=0), axis=2) * (inside[1:] & inside[:-1])
    return mean, step.sum(axis=0)


def _backproject_to_plane(camera: TrueCamera, pose: Pose, px: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 2)`` -> target-plane points ``(N, 3)`` (Z = 0) seen there in ``pose``."""
    rays = camera.pixel_to_ray(px) @ pose.R  # world directions
    origin = pose.camera_center
    s = -origin[2] / rays[:, 2]
    return cast(np.ndarray, origin + s[:, None] * rays)


def splat(offsets: np.ndarray, size: int, weights: np.ndarray | None = None) -> np.ndarray:
    """Bilinearly splat points ``(T, 2)`` px of ``weights (T,)`` (equal, summing to 1, when
    None) into a ``(size, size)`` kernel centred at offset 0 (kernel pixel ``(i, j)`` is offset
    ``(j - c, i - c)``)."""
    c = (size - 1) / 2
    kernel = np.zeros((size, size))
    if weights is None:
        weights = np.full(len(offsets), 1.0 / len(offsets))
    for (dx, dy), w in zip(offsets, weights, strict=True):
        if w == 0:
            continue
        x, y = dx + c, dy + c
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0
        for yy, wy in ((y0, 1 - fy), (y0 + 1, fy)):
            for xx, wx in ((x0, 1 - fx), (x0 + 1, fx)):
                if 0 <= yy < size and 0 <= xx < size:
                    kernel[yy, xx] += w * wx * wy
    return kernel


def gauss_ksize(sigma: float) -> int:
    return 2 * math.ceil(4.0 * sigma) + 1

