"""The rig simulator: synchronised frames of several cameras fixed to each other, with exact truth.

A rig (:class:`TrueRig`) is simulated cameras (:class:`blurcalib.sim.truth.TrueCamera`) and their
rig -> camera poses ``camera_tr_rig`` (:mod:`blurcalib.camera.rig`'s convention; the rig's frame
is camera 0's). Image set ``k`` is meant for a group of cameras: every camera, or, with a
visibility rule ``groups`` (:class:`RigSimulator`), the group ``groups[k % len(groups)]``; the
other cameras' frames are left out of the set. The set has one target -> rig pose
``rig_tr_global`` (mid-exposure): drawn for the group's first camera (its anchor) as the
single-camera simulator draws a frame's pose (:func:`blurcalib.sim.synth.sample_pose`), redrawn
(up to :data:`SET_TRIES` times) until every camera of the group sees 40 features, else kept with
the cameras that do not see it left out. Camera ``c`` sees the target at
``camera_tr_rig[c] o rig_tr_global``.

A blurry set's hand motion is drawn for the anchor camera (:func:`blurcalib.sim.synth.sample_motion`)
and moves the whole rig: camera ``c`` sees the same rigid motion in its own frame, the twist
conjugated by ``T = camera c <- anchor`` (:func:`conjugate_motion`: ``omega' = R omega``,
``v' = R v + t x R omega``), so each camera blurs differently. Frames, feature truth and noise
are the single-camera simulator's (:func:`blurcalib.sim.synth.frame_truth`,
:func:`blurcalib.sim.render.sensor_image`). Pixel convention: OpenCV.

:func:`write_rig_dataset` writes one dataset folder per camera (``cam0/``, ``cam1/``, ...: each
as :func:`blurcalib.sim.synth.write_dataset` writes one camera's, frames of a set named alike
across cameras) and ``rig_truth.json`` (:data:`RIG_TRUTH_FILE`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np

from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import atomic_path, atomic_write_text, ensure_writable_dir
from blurcalib.sim.render import MIP_TEXELS_PER_SQUARE, Renderer, mip_levels_for, sensor_image
from blurcalib.sim.synth import (
    SimulatedFrame,
    Simulator,
    SynthConfig,
    frame_truth,
    sample_motion,
    sample_pose,
)
from blurcalib.sim.truth import (
    GROUND_TRUTH_FILE,
    DatasetTruth,
    FrameTruth,
    Motion,
    TrueCamera,
    d435i_like_camera,
)
from blurcalib.target.pattern import StarPattern, layout_pattern

__all__ = ["RIG_TRUTH_FILE", "SET_TRIES", "RigSet", "RigSimulator", "TrueRig", "chain_rig",
           "conjugate_motion", "d435i_stereo_rig", "load_rig_truth", "write_rig_dataset"]

RIG_TRUTH_FILE = "rig_truth.json"
SET_TRIES = 20
"""Draws of a set's pose before a camera that does not see the target is left out of the set."""

MIN_FEATURES = 40
"""Features a camera must see for its frame to be in a set."""


@dataclass(frozen=True, eq=False)
class TrueRig:
    """Simulated cameras and their rig -> camera poses (module docstring)."""

    cameras: tuple[TrueCamera, ...]
    camera_tr_rig: tuple[Pose, ...]

    def __post_init__(self) -> None:
        if not self.cameras or len(self.cameras) != len(self.camera_tr_rig):
            raise ValueError(f"a rig needs one pose per camera, got {len(self.cameras)} cameras and "
                             f"{len(self.camera_tr_rig)} poses")

    def relative(self, i: int, j: int) -> Pose:
        """``camera j <- camera i``."""
        return self.camera_tr_rig[j].compose(self.camera_tr_rig[i].inverse())

    def to_dict(self) -> dict[str, Any]:
        return {"cameras": [c.to_dict() for c in self.cameras],
                "camera_tr_rig": [p.to_dict() for p in self.camera_tr_rig]}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrueRig:
        return cls(tuple(TrueCamera.from_dict(c) for c in data["cameras"]),
                   tuple(Pose.from_dict(p) for p in data["camera_tr_rig"]))


def d435i_stereo_rig(seed: int = 0, baseline_m: float = 0.05,
                     rotation_deg: Sequence[float] = (0.3, -0.5, 0.2), deviation_px: float = 0.3,
                     scale: float = 1.0) -> TrueRig:
    """A RealSense D435I-like infrared pair: two 1280x720 cameras (:func:`d435i_like_camera`, each
    with its own lens deviation of ``deviation_px`` px peak), camera 1 ``baseline_m`` to the right
    of camera 0 (+x) and turned by the rotation vector ``rotation_deg`` (deg) relative to it;
    ``scale`` resizes both images (:meth:`blurcalib.camera.parametric.BrownConrady.scaled`:
    0.5 gives 640x360 cameras of the same field of view)."""
    R, _ = cv2.Rodrigues(np.radians(np.asarray(rotation_deg, dtype=np.float64)).reshape(3, 1))
    second = Pose(R, -R @ np.array([baseline_m, 0.0, 0.0]))
    cameras = [d435i_like_camera(seed + c, deviation_px) for c in range(2)]
    if scale != 1.0:
        cameras = [TrueCamera(c.model.scaled(scale), c.waves) for c in cameras]
    return TrueRig(tuple(cameras), (Pose.identity(), second))


def chain_rig(cameras: int = 3, seed: int = 0, baseline_m: float = 0.05, yaw_deg: float = 20.0,
              deviation_px: float = 0.3, scale: float = 1.0) -> TrueRig:
    """A row of ``cameras`` D435I-like cameras (:func:`d435i_like_camera`, seeds ``seed + c``):
    camera ``c`` sits ``baseline_m`` to the right (+x) of camera ``c - 1`` and is turned
    ``yaw_deg`` further about its y axis (towards +x), so that the first and the last camera look
    apart; ``scale`` resizes the images as in :func:`d435i_stereo_rig`."""
    poses = []
    for c in range(cameras):
        R, _ = cv2.Rodrigues(np.array([0.0, np.radians(yaw_deg) * c, 0.0]).reshape(3, 1))
        poses.append(Pose(R, -R @ np.array([baseline_m * c, 0.0, 0.0])))
    models = [d435i_like_camera(seed + c, deviation_px) for c in range(cameras)]
    if scale != 1.0:
        models = [TrueCamera(c.model.scaled(scale), c.waves) for c in models]
    return TrueRig(tuple(models), tuple(poses))


def conjugate_motion(motion: Motion, pose: Pose, samples: int | None = None) -> Motion:
    """The motion of one camera (``motion``, in its frame) seen by a camera rigidly fixed to it with
    ``pose`` = that camera <- the first: each twist ``(omega, v)`` becomes ``(R omega, R v + t x R
    omega)`` (the adjoint), so ``Exp(xi') = pose Exp(xi) pose^-1``."""

    def ad(xi: np.ndarray) -> np.ndarray:
        w = pose.R @ xi[:3]
        return np.concatenate([w, pose.R @ xi[3:] + np.cross(pose.t, w)])

    return Motion(ad(motion.xi), ad(motion.xi2), motion.samples if samples is None else samples)


@dataclass(frozen=True, eq=False)
class RigSet:
    """One image set's truth: its target -> rig pose and, per camera, the frame's truth (None where
    the camera does not see the target or is not in the set's group)."""

    name: str
    kind: str
    rig_tr_global: Pose
    frames: tuple[FrameTruth | None, ...]


class RigSimulator:
    """Deterministic generator of a rig dataset: ``SynthConfig`` + pattern + rig -> image sets.

    ``config.sharp`` sharp and ``config.blurry`` blurry sets; each set's randomness depends only
    on the seed and its index. ``groups`` is the visibility rule (module docstring): set ``k`` is
    meant for the cameras ``groups[k % len(groups)]`` (its first camera the anchor); None: every
    camera, camera 0 the anchor."""

    def __init__(self, config: SynthConfig | None = None, rig: TrueRig | None = None,
                 pattern: StarPattern | None = None, groups: Sequence[Sequence[int]] | None = None) -> None:
        self.config = config or SynthConfig()
        self.rig = rig or d435i_stereo_rig(self.config.seed)
        C = len(self.rig.cameras)
        self.groups = [tuple(range(C))] if groups is None else [tuple(g) for g in groups]
        if not self.groups or any(not g or min(g) < 0 or max(g) >= C for g in self.groups):
            raise ValueError(f"each group of the visibility rule needs cameras in [0, {C}), got {groups}")
        self.pattern = pattern or layout_pattern()
        self.sims = [Simulator(self.config, self.pattern, camera) for camera in self.rig.cameras]
        self.renderers: list[Renderer] = [sim.renderer for sim in self.sims]

    def set_names(self) -> list[tuple[str, str]]:
        """``(name, kind)`` of every set (the frames' names in each camera's folder)."""
        return self.sims[0].frame_names()

    def _sees(self, c: int, rig_pose: Pose) -> bool:
        camera = self.rig.cameras[c]
        cam = self.rig.camera_tr_rig[c].compose(rig_pose).transform(self.pattern.points_3d())
        px = camera.project(cam)
        inside = camera.in_view(cam) & np.all((px >= 0) & (px <= [camera.width - 1, camera.height - 1]),
                                              axis=1)
        return int(inside.sum()) >= MIN_FEATURES

    def image_set(self, index: int) -> RigSet:
        """Set ``index``'s poses, motions and per-camera truth, without rendering."""
        name, kind = self.set_names()[index]
        cfg = self.config
        rng = np.random.default_rng([cfg.seed, index])
        group = self.groups[index % len(self.groups)]
        a = group[0]
        first = self.rig.camera_tr_rig[a]
        for _ in range(SET_TRIES):
            pose0 = sample_pose(self.pattern, self.rig.cameras[a], rng, cfg.max_tilt_deg, cfg.square_px)
            rig_pose = first.inverse().compose(pose0)
            if all(self._sees(c, rig_pose) for c in group):
                break
        motion0 = Motion.still()
        if kind == "blurry":
            motion0 = sample_motion(self.renderers[a], pose0, self.pattern, rng,
                                    rng.uniform(cfg.blur_min_px, cfg.blur_max_px),
                                    curved=bool(rng.uniform() < cfg.curved_fraction),
                                    rolling_shutter=cfg.rolling_shutter)
        frames: list[FrameTruth | None] = []
        for c, camera in enumerate(self.rig.cameras):
            if c not in group or not self._sees(c, rig_pose):
                frames.append(None)
                continue
            pose = self.rig.camera_tr_rig[c].compose(rig_pose)
            motion = motion0
            if kind == "blurry" and c != a:
                moved = conjugate_motion(motion0, self.rig.relative(a, c))
                pts = self.pattern.points_3d()
                samples = self.renderers[c].time_samples_for(pose, moved.xi, moved.xi2, pts,
                                                             cfg.rolling_shutter)
                motion = conjugate_motion(motion0, self.rig.relative(a, c), max(samples, motion0.samples))
            cam_rng = np.random.default_rng([cfg.seed, index, c])
            frames.append(frame_truth(name, kind, self.pattern, camera, pose, motion,
                                      float(cam_rng.uniform(*cfg.defocus_px)), cam_rng, cfg.noise_sigma,
                                      cfg.rolling_shutter))
        return RigSet(name, kind, rig_pose, tuple(frames))

    def render(self, image_set: RigSet, c: int) -> SimulatedFrame | None:
        """Camera ``c``'s frame of a set (None where it does not see the target)."""
        truth = image_set.frames[c]
        if truth is None:
            return None
        cfg = self.config
        sim = self.sims[c]
        levels = [sim.texture(MIP_TEXELS_PER_SQUARE[k])
                  for k in mip_levels_for(self.rig.cameras[c], truth.pose, self.pattern, cfg.supersample)]
        irradiance = self.renderers[c].irradiance(levels, truth.pose, truth.motion, cfg.rolling_shutter)
        index = self.set_names().index((image_set.name, image_set.kind))
        rng = np.random.default_rng([cfg.seed, index, c, 1])
        return SimulatedFrame(sensor_image(irradiance, truth, rng), truth)


def write_rig_dataset(out_dir: str | os.PathLike[str], config: SynthConfig | None = None,
                      rig: TrueRig | None = None, pattern: StarPattern | None = None, render: bool = True,
                      progress: Callable[[int, int, str], None] | None = None
                      ) -> tuple[TrueRig, list[RigSet]]:
    """Simulate a rig dataset into ``out_dir`` (module docstring): ``cam{c}/pattern.yaml``,
    ``cam{c}/sharp/*.png``, ``cam{c}/blurry/*.png``, ``cam{c}/ground_truth.json`` and
    ``rig_truth.json`` (written last). ``render=False`` writes the truth only (no images)."""
    out = ensure_writable_dir(out_dir)
    sim = RigSimulator(config, rig, pattern)
    names = sim.set_names()
    sets: list[RigSet] = []
    for k in range(len(names)):
        image_set = sim.image_set(k)
        sets.append(image_set)
        for c in range(len(sim.rig.cameras)):
            frame = sim.render(image_set, c) if render else None
            if frame is None:
                continue
            path = out / f"cam{c}" / image_set.name
            ensure_writable_dir(path.parent)
            with atomic_path(path) as tmp:
                if not cv2.imwrite(str(tmp), frame.image):
                    raise OSError(f"{path}: cannot write image")
        if progress is not None:
            progress(k + 1, len(names), names[k][0])
    for c, camera in enumerate(sim.rig.cameras):
        folder = ensure_writable_dir(out / f"cam{c}")
        sim.pattern.save_yaml(folder / "pattern.yaml")
        frames = [s.frames[c] for s in sets if s.frames[c] is not None]
        truth = DatasetTruth(camera, "pattern.yaml", frames, asdict(sim.config))  # type: ignore[arg-type]
        atomic_write_text(folder / GROUND_TRUTH_FILE, json.dumps(truth.to_dict()))
    doc = {"format": "blurcalib-rig-synth", "rig": sim.rig.to_dict(),
           "sets": [{"name": s.name, "kind": s.kind, "rig_tr_global": s.rig_tr_global.to_dict(),
                     "cameras": [c for c, f in enumerate(s.frames) if f is not None]} for s in sets]}
    atomic_write_text(out / RIG_TRUTH_FILE, json.dumps(doc))
    return sim.rig, sets


def load_rig_truth(path: str | os.PathLike[str]) -> tuple[TrueRig, dict[str, Pose]]:
    """Read ``rig_truth.json`` (the file or its folder): the rig and each set's target -> rig pose.

    Raises:
        ValueError: naming the file, when it is missing or not a rig truth.
    """
    p = os.fspath(path)
    if os.path.isdir(p):
        p = os.path.join(p, RIG_TRUTH_FILE)
    try:
        with open(p, encoding="utf-8") as handle:
            doc = json.load(handle)
        if doc.get("format") != "blurcalib-rig-synth":
            raise ValueError("not a blurcalib rig ground truth")
        poses = {s["name"]: Pose.from_dict(s["rig_tr_global"]) for s in doc["sets"]}
        return TrueRig.from_dict(doc["rig"]), poses
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{p}: cannot read rig ground truth ({exc})") from None
