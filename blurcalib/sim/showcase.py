"""The browser app's built-in dataset: a short capture made for the app's three jobs.

Thirteen 640 x 360 frames of the default pattern through a half-size D435I-like camera
(:func:`showcase_camera`), with the faults a user meets and the quality filter exists for, each
named in the frame's file name (:func:`showcase_frames`):

- ``sharp/``: five stills from different poses; one has a region out of focus (``defocus``,
  the boundary energy filter's case) and one sees the target at a grazing angle (``grazing``);
- ``blurry/``: a slow hand-held pass of eight frames (the target moves a few pixels from frame
  to frame, so a frame whose tag is hidden is seeded from its neighbours), with 4 to 8 px of
  blur, one frame with glare over part of the target (``glare``, the loss filter's case), one
  with a finger over a corner (``finger``), one with a thumb over the tag (``tag-hidden``) and one
  with heavy blur (``heavy-blur``, about 20 px).

The faults are rendered by :mod:`blurcalib.sim.faults`; ``faults.json`` records, per frame, a
line saying what it shows and each fault with the pattern features whose blocks it touches
(:func:`load_faults`). The dataset is a deterministic function of :data:`SEED`.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import atomic_path, atomic_write_text, ensure_writable_dir
from blurcalib.runs.runtime import exit_with_parent
from blurcalib.sim.faults import (
    Defocus,
    Fault,
    Finger,
    Glare,
    apply_faults,
    block_quads,
    fault_from_dict,
    fault_to_dict,
    touched_blocks,
)
from blurcalib.sim.render import MIP_TEXELS_PER_SQUARE, mip_levels_for, sensor_image
from blurcalib.sim.synth import SimulatedFrame, Simulator, SynthConfig, frame_truth, sample_motion
from blurcalib.sim.truth import GROUND_TRUTH_FILE, DatasetTruth, Motion, TrueCamera, d435i_like_camera
from blurcalib.target.pattern import StarPattern, layout_pattern

SEED = 0
"""Seed of the dataset's randomness (motions, noise, illumination)."""
FAULTS_FILE = "faults.json"
"""Per frame: what it shows and its faults with the features they touch (:func:`load_faults`)."""
SQUARE_PX = 30.0
"""Star square side near the tag (px)."""
PASS_FRAMES = 8
PASS_STEP_PX = (7.0, 2.5)
"""Image motion of the tag from one frame of the hand-held pass to the next (px)."""
PASS_BLUR_PX = (5.0, 6.0, 7.0, 6.0, 5.0, 8.0, 20.0, 4.0)
"""Median blur length of each frame of the pass (px): frame 6 is the heavy blur."""


@dataclass(frozen=True)
class ShowcaseFrame:
    """One frame of the dataset: its name, kind, what it shows (one line), pose at ``tau = 0``,
    median blur length of its hand shake (px; 0: sharp) and faults (image px at ``tau = 0``)."""

    name: str
    kind: str
    what: str
    pose: Pose
    blur_px: float = 0.0
    faults: tuple[Fault, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class FrameFaults:
    """What ``faults.json`` says of one frame: ``what`` it shows, its ``faults`` and, for each,
    the pattern features whose blocks it touches."""

    what: str
    faults: tuple[Fault, ...]
    features: tuple[np.ndarray, ...]


def showcase_camera() -> TrueCamera:
    """The dataset's camera: the D435I-like camera at half resolution (640 x 360)."""
    full = d435i_like_camera(SEED)
    waves = full.waves.copy()
    waves[:, :2] *= 0.5
    return TrueCamera(full.model.scaled(0.5), waves)


def _rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(axis, float).reshape(3) * math.radians(angle_deg))
    return R


def view_pose(pattern: StarPattern, camera: TrueCamera, anchor: tuple[float, float],
              pixel: tuple[float, float], square_px: float, tilt_deg: float, tilt_dir_deg: float,
              roll_deg: float = 90.0) -> Pose:
    """The pose that puts feature coordinates ``anchor`` at image point ``pixel`` (px), with the
    target turned ``roll_deg`` about the optical axis and tilted ``tilt_deg`` about the in-plane
    axis at ``tilt_dir_deg``, at the distance where a square there is about ``square_px``."""
    L = pattern.square_length_m
    d = math.radians(tilt_dir_deg)
    R = _rotation(np.array([0.0, 0.0, 1.0]), roll_deg) @ _rotation(np.array([math.cos(d), math.sin(d), 0.0]),
                                                                   tilt_deg)
    depth = camera.model.fx * L / square_px
    xn = camera.unproject(np.asarray(pixel, float)[None])[0]
    place = depth * np.array([xn[0], xn[1], 1.0])
    return Pose(R, place - R @ np.array([anchor[0] * L, anchor[1] * L, 0.0]))


def _at(pattern: StarPattern, camera: TrueCamera, pose: Pose, feature: tuple[float, float]
        ) -> tuple[float, float]:
    """Image point (px) of feature coordinates ``feature`` at ``pose``."""
    L = pattern.square_length_m
    p = camera.project(pose.transform(np.array([[feature[0] * L, feature[1] * L, 0.0]])))[0]
    return float(p[0]), float(p[1])


def showcase_frames(pattern: StarPattern, camera: TrueCamera) -> list[ShowcaseFrame]:
    """The dataset's frames in order: the sharp stills, then the hand-held pass."""
    tag = pattern.apriltags[0].feature_box
    centre = ((tag[0] + tag[2]) / 2.0, (tag[1] + tag[3]) / 2.0)
    w, h = camera.model.width, camera.model.height

    def still(name: str, what: str, pixel: tuple[float, float], tilt: float, direction: float,
              roll: float = 90.0, square: float = SQUARE_PX,
              faults: Callable[[Pose], tuple[Fault, ...]] | None = None) -> ShowcaseFrame:
        pose = view_pose(pattern, camera, centre, pixel, square, tilt, direction, roll)
        return ShowcaseFrame(name, "sharp", what, pose, 0.0, faults(pose) if faults else ())

    frames = [
        still("sharp/00-still.png", "a sharp still", (0.45 * w, 0.5 * h), 25.0, 30.0),
        still("sharp/01-still.png", "a sharp still", (0.6 * w, 0.45 * h), 35.0, 150.0, 84.0),
        still("sharp/02-defocus.png", "a sharp still, part of it out of focus", (0.4 * w, 0.55 * h),
              30.0, 250.0, 95.0,
              faults=lambda pose: (Defocus(_at(pattern, camera, pose, (centre[0], centre[1] + 7.5)), 120.0,
                                            4.5),)),
        still("sharp/03-grazing.png", "the target seen at a grazing angle (68 degrees)", (0.5 * w, 0.5 * h),
              68.0, 0.0, 90.0, 36.0),
        still("sharp/04-still.png", "a sharp still", (0.55 * w, 0.55 * h), 20.0, 300.0, 100.0),
    ]
    for i in range(PASS_FRAMES):
        pixel = (0.42 * w + i * PASS_STEP_PX[0], 0.45 * h + i * PASS_STEP_PX[1])
        pose = view_pose(pattern, camera, centre, pixel, SQUARE_PX, 22.0 + 0.8 * i, 60.0 + 2.0 * i,
                         88.0 + 0.5 * i)
        faults: tuple[Fault, ...] = ()
        what, label = "a blurry frame of a slow hand-held pass", "pass"
        if i == 1:
            what, label = "glare: a lamp's highlight on the target beside the tag", "glare"
            faults = (Glare(_at(pattern, camera, pose, (centre[0] - 0.5, centre[1] - 6.5)), 55.0, 0.8),)
        elif i == 3:
            what, label = "a finger over the bottom right corner of the view", "finger"
            faults = (Finger((w + 10.0, 0.55 * h), (0.72 * w, h + 10.0), 16.0),)
        elif i == 4:
            what, label = "a thumb over the tag: the frame is seeded from its neighbours", "tag-hidden"
            tip = _at(pattern, camera, pose, centre)
            faults = (Finger((tip[0] + 40.0, h + 20.0), tip, 0.5 * _tag_half_px(pattern, camera, pose)),)
        elif i == 6:
            what, label = "heavy blur (20 px)", "heavy-blur"
        frames.append(ShowcaseFrame(f"blurry/{i:02d}-{label}.png", "blurry", what, pose, PASS_BLUR_PX[i],
                                    faults))
    return frames


def _tag_half_px(pattern: StarPattern, camera: TrueCamera, pose: Pose) -> float:
    """The radius (px) of the circle around the tag's corners at ``pose``."""
    L = pattern.square_length_m
    corners = pattern.tag_corners(pattern.apriltags[0]) * L
    px = camera.project(pose.transform(np.column_stack([corners, np.zeros(len(corners))])))
    return float(np.linalg.norm(px - px.mean(axis=0), axis=1).max())


class ShowcaseRenderer:
    """Renders the dataset's frames with their ground truth and the features their faults touch."""

    def __init__(self, pattern: StarPattern | None = None, camera: TrueCamera | None = None) -> None:
        self.pattern = pattern or layout_pattern()
        self.camera = camera or showcase_camera()
        self.sim = Simulator(SynthConfig(sharp=0, blurry=0, seed=SEED), self.pattern, self.camera)
        self.frames = showcase_frames(self.pattern, self.camera)

    def render(self, index: int) -> tuple[SimulatedFrame, list[np.ndarray]]:
        """Frame ``index`` and, per fault, the ids of the features whose blocks it touches."""
        spec = self.frames[index]
        cfg = self.sim.config
        rng = np.random.default_rng([SEED, index])
        if spec.blur_px > 0:
            motion = sample_motion(self.sim.renderer, spec.pose, self.pattern, rng, spec.blur_px,
                                   curved=bool(index % 2))
        else:
            motion = Motion.still()
        defocus = float(rng.uniform(*cfg.defocus_px))
        truth = frame_truth(spec.name, spec.kind, self.pattern, self.camera, spec.pose, motion, defocus, rng,
                            cfg.noise_sigma)
        levels = [self.sim.texture(MIP_TEXELS_PER_SQUARE[k])
                  for k in mip_levels_for(self.camera, spec.pose, self.pattern, cfg.supersample)]
        irradiance = apply_faults(self.sim.renderer.irradiance(levels, spec.pose, motion), spec.faults)
        quads = block_quads(self.pattern, self.camera, spec.pose)
        reach = 0.5 * float(np.nanmax(truth.blur_length, initial=0.0)) + 1.0
        touched = [truth.feature_ids[touched_blocks(f.footprint(irradiance.shape), quads, reach)]
                   for f in spec.faults]
        return SimulatedFrame(sensor_image(irradiance, truth, rng), truth), touched


_WORKER: ShowcaseRenderer | None = None
"""The renderer of a worker process of :func:`write_showcase` (never set in the main process)."""


def _init_worker() -> None:
    global _WORKER  # each worker process builds its renderer (lens maps, textures) once
    exit_with_parent()
    cv2.setNumThreads(1)
    _WORKER = ShowcaseRenderer()


def _render_in_worker(index: int) -> tuple[SimulatedFrame, list[np.ndarray]]:
    assert _WORKER is not None
    return _WORKER.render(index)


def write_showcase(out_dir: str | os.PathLike[str], progress: Callable[[int, int, str], None] | None = None,
                   workers: int = 1) -> DatasetTruth:
    """Render the dataset into ``out_dir``: ``pattern.yaml``, ``sharp/*.png``, ``blurry/*.png``,
    :data:`FAULTS_FILE` and ``ground_truth.json``, written last (a folder with it is complete).

    Args:
        out_dir: the folder.
        progress: called after each frame with ``(done, total, name)``.
        workers: render in this many processes (the frames are the same).
    """
    out = ensure_writable_dir(out_dir)
    renderer = ShowcaseRenderer()
    renderer.pattern.save_yaml(out / "pattern.yaml")
    specs = renderer.frames
    truths: list[Any] = [None] * len(specs)
    faults: dict[str, dict[str, Any]] = {}

    def store(index: int, frame: SimulatedFrame, touched: list[np.ndarray]) -> None:
        spec = specs[index]
        ensure_writable_dir((out / spec.name).parent)
        with atomic_path(out / spec.name) as tmp:
            if not cv2.imwrite(str(tmp), frame.image):
                raise OSError(f"{out / spec.name}: cannot write image")
        truths[index] = frame.truth
        faults[spec.name] = {"what": spec.what, "faults": [
            {**fault_to_dict(f), "features": ids.tolist()}
            for f, ids in zip(spec.faults, touched, strict=True)]}
        if progress is not None:
            progress(sum(t is not None for t in truths), len(specs), spec.name)

    if workers > 1:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker) as pool:
            futures = {pool.submit(_render_in_worker, i): i for i in range(len(specs))}
            for future in as_completed(futures):
                store(futures[future], *future.result())
    else:
        for i in range(len(specs)):
            store(i, *renderer.render(i))
    ordered = {s.name: faults[s.name] for s in specs}
    atomic_write_text(out / FAULTS_FILE, json.dumps({"frames": ordered}, indent=1))
    truth = DatasetTruth(renderer.camera, "pattern.yaml", list(truths), {"dataset": "showcase", "seed": SEED})
    atomic_write_text(out / GROUND_TRUTH_FILE, json.dumps(truth.to_dict()))
    return truth


def load_faults(folder: str | os.PathLike[str]) -> dict[str, FrameFaults]:
    """The frames' faults of a dataset folder (empty when it has no :data:`FAULTS_FILE`).

    Raises:
        ValueError: the file cannot be read (the message names it).
    """
    path = Path(folder) / FAULTS_FILE
    if not path.is_file():
        return {}
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        return {name: FrameFaults(entry["what"],
                                  tuple(fault_from_dict({k: v for k, v in f.items() if k != "features"})
                                        for f in entry["faults"]),
                                  tuple(np.asarray(f["features"], dtype=np.int64) for f in entry["faults"]))
                for name, entry in doc["frames"].items()}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: cannot read the frames' faults ({exc})") from None
