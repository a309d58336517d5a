"""The simulator: what to simulate (:class:`SynthConfig`), random poses and hand-shake motions,
and :class:`Simulator`, which renders frames (:mod:`blurcalib.sim.render`) with their exact
ground truth (:mod:`blurcalib.sim.truth`) into a dataset folder (:func:`write_dataset`).

Ground truth per frame: the pose at ``tau = 0`` (mid-exposure; of the middle row with a rolling
shutter), each feature's image position at ``tau = 0`` and its time-averaged position over the
window of the row where it is seen (the centroid of the feature's motion PSF; the symmetric
defocus does not move it), visibility, the local blur length, and the true PSF at any image
point (:meth:`blurcalib.sim.truth.FrameTruth.psf_at`). Pixel convention: OpenCV (top-left pixel
centre at (0, 0)).
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from typing import cast

import cv2
import numpy as np

from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import atomic_path, atomic_write_text, ensure_writable_dir
from blurcalib.runs.runtime import exit_with_parent
from blurcalib.sim.optics import OPTICS_FILE, Optics, display_texture
from blurcalib.sim.render import (
    MIP_TEXELS_PER_SQUARE,
    Renderer,
    RenderSettings,
    Texture,
    mip_levels_for,
    pattern_texture,
    sensor_image,
)
from blurcalib.sim.truth import (
    GROUND_TRUTH_FILE,
    DatasetTruth,
    FrameTruth,
    Motion,
    TrueCamera,
    d435i_like_camera,
    time_averaged_positions,
)
from blurcalib.target.pattern import StarPattern, layout_pattern


@dataclass(frozen=True)
class SynthConfig:
    """What to simulate. Defaults: the README's demo dataset.

    Attributes:
        sharp, blurry: number of frames of each set.
        blur_min_px, blur_max_px: range of the median feature blur length of blurry frames.
        curved_fraction: share of blurry frames with curved hand-shake paths.
        max_tilt_deg: largest angle between optical axis and target normal (through a lens of
            the parametric family, between the ray the target is seen along and its normal:
            :func:`sample_wide_pose`).
        square_px: range of the star square's size in the image (px).
        defocus_px: range of the Gaussian defocus sigma (px).
        noise_sigma: approximate noise standard deviation at mid grey (grey levels).
        seed: random seed; the dataset is a deterministic function of the config.
        supersample: canvas samples per pixel side.
        rolling_shutter: readout ratio ``r = readout time / exposure time`` of a rolling shutter
            (:mod:`blurcalib.camera.shutter`); 0 is a global shutter.
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
    rolling_shutter: float = 0.0

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
        if not (math.isfinite(self.rolling_shutter) and 0 <= self.rolling_shutter <= 10):
            raise ValueError(f"rolling shutter (rolling_shutter, readout / exposure time) must be in "
                             f"[0, 10], got {self.rolling_shutter}")
        if self.supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(axis, float).reshape(3) * angle)
    return R


def _anchored_pose(pattern: StarPattern, camera: TrueCamera, R: np.ndarray, anchor: np.ndarray,
                   place: np.ndarray, margin: float = 30.0) -> Pose | None:
    """The pose putting target point ``anchor`` at camera point ``place`` with rotation ``R``, if
    the tag is in view at least ``margin`` px inside the image and 40 features are in view."""
    L = pattern.square_length_m
    tag_pts = np.concatenate([
        np.column_stack([pattern.tag_corners(t) * L, np.zeros(4)]) for t in pattern.apriltags])
    pose = Pose(R, place - R @ anchor)
    cam_pts = pose.transform(tag_pts)
    if np.any(cam_pts[:, 2] <= 0.05) if camera.forward_only else not np.all(camera.in_view(cam_pts)):
        return None
    tag_px = camera.project(cam_pts)
    if not (np.all(tag_px >= margin) and np.all(tag_px[:, 0] <= camera.width - 1 - margin)
            and np.all(tag_px[:, 1] <= camera.height - 1 - margin)):
        return None
    cam = pose.transform(pattern.points_3d())
    feat_px = camera.project(cam)
    inside = ((feat_px[:, 0] >= 0) & (feat_px[:, 0] <= camera.width - 1)
              & (feat_px[:, 1] >= 0) & (feat_px[:, 1] <= camera.height - 1))
    if not camera.forward_only:
        inside &= camera.in_view(cam)
    return pose if inside.sum() >= 40 else None


def sample_pose(pattern: StarPattern, camera: TrueCamera, rng: np.random.Generator,
                max_tilt_deg: float, square_px: tuple[float, float],
                tries: int = 200) -> Pose:
    """A pose with the tag fully in view, tilt up to ``max_tilt_deg``, anywhere in the image.

    A random target point is placed at a random image point (so that over many frames every
    image region, corners included, is covered) at the depth giving a random square size. A lens
    that sees beyond the front half-space gets :func:`sample_wide_pose`.
    """
    if not camera.forward_only:
        return sample_wide_pose(pattern, camera, rng, max_tilt_deg, square_px, 2 * tries)
    model = camera.model
    L = pattern.square_length_m
    lo = np.array([-1.0, -1.0]) * L
    hi = np.array([pattern.squares_x - 1, pattern.squares_y - 1]) * L
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
        pose = _anchored_pose(pattern, camera, R, anchor, depth * np.array([xn[0], xn[1], 1.0]))
        if pose is not None:
            return pose
    raise RuntimeError("could not sample a pose with the tag in view; check the camera/pattern")


def _tag_square_px(pattern: StarPattern, camera: TrueCamera, pose: Pose) -> float:
    """The smallest short side (px) of a square at the tags' corners seen at ``pose``."""
    L = pattern.square_length_m
    corners = np.concatenate([pattern.tag_corners(t) for t in pattern.apriltags]) * L
    cam = pose.transform(np.column_stack([corners, np.zeros(len(corners))]))
    J = camera.point_jacobian(cam) @ pose.R[:, :2]
    return float(np.linalg.svd(J, compute_uv=False)[:, 1].min()) * L


def sample_wide_pose(pattern: StarPattern, camera: TrueCamera, rng: np.random.Generator,
                     max_tilt_deg: float, square_px: tuple[float, float], tries: int = 400) -> Pose:
    """A pose for a lens of any field of view: a random target point at a random pixel of the
    lens's image circle (its corners and rays far off the axis as often as the centre), the
    target facing that pixel's ray up to ``max_tilt_deg`` off it, at the distance where a square
    is a random size of ``square_px`` (the lens's px per radian there, geometric mean of the two
    directions). The tag is fully in view, its squares at least half the smallest ``square_px`` on
    their short side (a close target spans tens of degrees, and its far part is seen obliquely),
    and 40 features are seen."""
    L = pattern.square_length_m
    lo = np.array([-1.0, -1.0]) * L
    hi = np.array([pattern.squares_x - 1, pattern.squares_y - 1]) * L
    cos_stop = math.cos(camera.field_stop)
    for _ in range(tries):
        tilt = math.radians(max_tilt_deg) * rng.uniform(0.0, 1.0)
        tilt_axis_angle = rng.uniform(0, 2 * np.pi)
        tilt_axis = np.array([math.cos(tilt_axis_angle), math.sin(tilt_axis_angle), 0.0])
        roll = rng.uniform(-np.pi, np.pi)
        anchor = np.append(rng.uniform(lo, hi), 0.0)
        pixel = rng.uniform([0, 0], [camera.width - 1, camera.height - 1])
        ray = camera.pixel_to_ray(pixel[None])[0]
        if not (np.all(np.isfinite(ray)) and ray[2] >= cos_stop):
            continue
        to_ray = np.cross([0.0, 0.0, 1.0], ray)
        angle = math.atan2(float(np.linalg.norm(to_ray)), float(ray[2]))
        axis = to_ray / max(float(np.linalg.norm(to_ray)), 1e-300)
        R = _rotation(axis, angle) @ _rotation(np.array([0.0, 0.0, 1.0]), roll) @ _rotation(tilt_axis, tilt)
        sv = np.linalg.svd(camera.point_jacobian(ray[None])[0], compute_uv=False)
        distance = math.sqrt(float(sv[0] * sv[1])) * L / rng.uniform(*square_px)
        pose = _anchored_pose(pattern, camera, R, anchor, distance * ray)
        if pose is not None and _tag_square_px(pattern, camera, pose) >= 0.5 * square_px[0]:
            return pose
    raise RuntimeError("could not sample a pose with the tag in view; check the camera/pattern")


def sample_motion(renderer: Renderer, pose: Pose, pattern: StarPattern, rng: np.random.Generator,
                  blur_px: float, curved: bool, rolling_shutter: float = 0.0) -> Motion:
    """A hand-shake motion whose median feature blur length over the visible part is ``blur_px``.

    Mostly rotation (as hand shake is), with some roll about the optical axis (blur that grows
    towards the image border) and some translation (including along the axis: zoom blur). The
    blur length is measured over the exposure at ``tau = 0``; ``rolling_shutter`` sets how many
    time samples the readout needs.
    """
    omega = rng.normal(size=3) * np.array([1.0, 1.0, 0.45])
    depth = float(pose.t[2]) if renderer.camera.forward_only else float(np.linalg.norm(pose.t))
    v = rng.normal(size=3) * np.array([0.25, 0.25, 0.35]) * depth
    xi = np.concatenate([omega, v])
    xi2 = np.concatenate([rng.normal(size=3), rng.normal(size=3) * 0.3 * depth]) if curved \
        else np.zeros(6)
    if curved:
        xi2 *= rng.uniform(0.4, 1.0) * np.linalg.norm(xi) / max(float(np.linalg.norm(xi2)), 1e-12)
    pts = _visible_points(renderer.camera, pose, pattern)
    base = _path_lengths(renderer.camera, pose, Motion(xi, xi2, 33), pts)
    scale = blur_px / max(float(np.median(base)), 1e-9)
    # Path length is close to linear in the scale for small motions; refine once.
    base = _path_lengths(renderer.camera, pose, Motion(xi * scale, xi2 * scale, 33), pts)
    scale *= blur_px / max(float(np.median(base)), 1e-9)
    xi, xi2 = xi * scale, xi2 * scale
    samples = renderer.time_samples_for(pose, xi, xi2, pts, rolling_shutter)
    return Motion(xi, xi2, samples)


def _visible_points(camera: TrueCamera, pose: Pose, pattern: StarPattern) -> np.ndarray:
    pts = pattern.points_3d()
    cam = pose.transform(pts)
    px = camera.project(cam)
    m = camera.model
    inside = (px[:, 0] >= 0) & (px[:, 0] <= m.width - 1) & (px[:, 1] >= 0) & (px[:, 1] <= m.height - 1)
    if not camera.forward_only:
        inside &= camera.in_view(cam)
    return pts[inside]


def _path_lengths(camera: TrueCamera, pose: Pose, motion: Motion, pts: np.ndarray) -> np.ndarray:
    tracks = np.stack([camera.project(p.transform(pts)) for p in motion.poses(pose)])
    return cast(np.ndarray, np.linalg.norm(np.diff(tracks, axis=0), axis=2).sum(axis=0))


def frame_truth(name: str, kind: str, pattern: StarPattern, camera: TrueCamera, pose: Pose,
                motion: Motion, defocus_sigma: float, rng: np.random.Generator,
                noise_sigma: float, rolling_shutter: float = 0.0) -> FrameTruth:
    """Ground truth of a frame (feature positions from the exact geometry; with a rolling shutter
    of readout ratio ``rolling_shutter``, time averages over each feature's row window)."""
    pts = pattern.points_3d()
    height = camera.model.height
    mean, blur = time_averaged_positions(camera, pose, motion, pts, height, rolling_shutter)
    cam = pose.transform(pts)
    mid = camera.project(cam)
    m = camera.model
    visible = (camera.in_view(cam) & (mid[:, 0] >= 0) & (mid[:, 0] <= m.width - 1)
               & (mid[:, 1] >= 0) & (mid[:, 1] <= m.height - 1))
    corners = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    fpts = pattern.features[:, None, :] + corners[None]
    corner_cam = pose.transform(np.concatenate(
        [fpts.reshape(-1, 2) * pattern.square_length_m, np.zeros((fpts.size // 2, 1))], axis=1))
    corner_px = camera.project(corner_cam).reshape(-1, 4, 2)
    corner_in = (camera.in_view(corner_cam).reshape(-1, 4) & (corner_px[..., 0] >= 0)
                 & (corner_px[..., 0] <= m.width - 1) & (corner_px[..., 1] >= 0)
                 & (corner_px[..., 1] <= m.height - 1))
    block_inside = visible & np.all(corner_in, axis=1)
    white = rng.uniform(170, 225)
    black = rng.uniform(15, 40)
    gain = noise_sigma**2 / ((white + black) / 2)
    return FrameTruth(
        name=name, kind=kind, pose=pose, motion=motion, defocus_sigma=defocus_sigma,
        feature_ids=np.arange(pattern.num_features), mid=mid, mean=mean,
        visible=visible, block_inside=block_inside, blur_length=blur,
        illumination=np.array([1.0, rng.uniform(-0.12, 0.12), rng.uniform(-0.12, 0.12)]),
        vignetting=float(rng.uniform(0.1, 0.3)), levels=(black, white),
        noise=(gain, 0.5 * noise_sigma / 2.0), rolling_shutter=rolling_shutter, height=height)


@dataclass
class SimulatedFrame:
    """A rendered frame and its ground truth."""

    image: np.ndarray
    truth: FrameTruth


class Simulator:
    """Deterministic generator of a dataset: ``SynthConfig`` + pattern + camera -> frames."""

    def __init__(self, config: SynthConfig | None = None, pattern: StarPattern | None = None,
                 camera: TrueCamera | None = None, optics: Optics | None = None) -> None:
        self.config = config or SynthConfig()
        self.optics = optics
        self.pattern = pattern or layout_pattern()
        self.camera = camera or d435i_like_camera(self.config.seed)
        self.renderer = Renderer(self.camera, RenderSettings(supersample=self.config.supersample))
        self._textures: dict[int, Texture] = {}

    def texture(self, texels_per_square: int) -> Texture:
        """The page texture at a resolution (built once, then cached)."""
        if texels_per_square not in self._textures:
            display = self.optics.display if self.optics is not None else None
            self._textures[texels_per_square] = (
                pattern_texture(self.pattern, texels_per_square) if display is None
                else display_texture(self.pattern, texels_per_square, display))
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
                                   curved=bool(rng.uniform() < cfg.curved_fraction),
                                   rolling_shutter=cfg.rolling_shutter)
        else:
            motion = Motion.still()
        defocus = float(rng.uniform(*cfg.defocus_px))
        truth = frame_truth(name, kind, self.pattern, self.camera, pose, motion, defocus, rng,
                            cfg.noise_sigma, cfg.rolling_shutter)
        levels = [self.texture(MIP_TEXELS_PER_SQUARE[k])
                  for k in mip_levels_for(self.camera, pose, self.pattern, cfg.supersample)]
        irradiance = self.renderer.irradiance(levels, pose, motion, cfg.rolling_shutter)
        return SimulatedFrame(sensor_image(irradiance, truth, rng, self.optics), truth)


_WORKER_SIM: Simulator | None = None
"""The simulator of a worker process of :func:`write_dataset` (never set in the main process)."""


def _init_worker(config: SynthConfig, pattern: StarPattern, camera: TrueCamera,
                 optics: Optics | None) -> None:
    global _WORKER_SIM  # each worker process builds its simulator (lens maps, textures) once
    exit_with_parent()
    cv2.setNumThreads(1)
    _WORKER_SIM = Simulator(config, pattern, camera, optics)


def _render_in_worker(index: int) -> SimulatedFrame:
    assert _WORKER_SIM is not None
    return _WORKER_SIM.frame(index)


def write_dataset(out_dir: str | os.PathLike[str], config: SynthConfig | None = None,
                  pattern: StarPattern | None = None, camera: TrueCamera | None = None,
                  progress: Callable[[int, int, str], None] | None = None,
                  workers: int = 1, optics: Optics | None = None) -> DatasetTruth:
    """Simulate a dataset into ``out_dir``: ``pattern.yaml``, ``sharp/*.png``,
    ``blurry/*.png`` and ``ground_truth.json`` (see ``docs/synthetic-data.md``).

    Every file is written atomically; the ground truth is written last, so a folder with a
    ``ground_truth.json`` is complete. ``workers > 1`` renders frames in that many processes
    (the result is identical: each frame's randomness depends only on the seed and its index).
    ``optics`` (:mod:`blurcalib.sim.optics`) renders through a realistic lens, tone curve or
    display; its settings are written to ``optics.json``.
    """
    out = ensure_writable_dir(out_dir)
    sim = Simulator(config, pattern, camera, optics)
    sim.pattern.save_yaml(out / "pattern.yaml")
    if optics is not None:
        atomic_write_text(out / OPTICS_FILE, json.dumps(asdict(optics)))
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
                                 initargs=(sim.config, sim.pattern, sim.camera, sim.optics)) as pool:
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
