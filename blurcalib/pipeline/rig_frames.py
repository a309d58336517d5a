"""Calibrate a rig of cameras from their frames (``blurcalib calibrate-rig INPUT...``).

Each camera has one input, camera 0 first: a folder of images (or a folder whose sub-folders hold
them, as ``blurcalib synth --rig`` writes ``camN/sharp/`` and ``camN/blurry/``), an image file or a
video (:func:`blurcalib.io.sources.frame_inputs`).

1. Image sets: an image frame belongs to the set of its name (its path relative to the camera's
   input: ``0001.png``, or ``sharp/0001.png`` in a sub-folder), so the cameras' frames of one
   instant share a file name; frame ``i`` of a video belongs to set ``#i`` (six digits), or
   ``#(i - offset)`` with the camera's time offset in frames. A camera that shares no frame name
   with camera 0, directly or through other cameras, is refused before anything is extracted.
2. Each camera runs the one-camera pipeline (:func:`blurcalib.pipeline.run.run_pipeline`, its
   frames classified sharp or blurry by their measured blur) into ``OUT/cameras/camN/``: a
   ``calibrate`` output folder of its own, resumable, with its cameras, features and assessment.
3. Each camera's generic calibration, as its pipeline run computed it (the run's report carries
   it: :attr:`blurcalib.pipeline.run.PipelineReport.camera`, the joint route, a free image shift per
   blurry frame), its frames renamed to their sets, enters the rig's bundle over all cameras
   (:func:`blurcalib.calib.rig_calibration.calibrate_rig`). A camera may miss the target in some
   sets; one that sees it in no set shared with the others is refused, naming its input.
4. Outputs as ``calibrate-rig --features`` writes them (:func:`blurcalib.pipeline.rig.write_rig_outputs`),
   ``report.json`` last.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TypeVar

import numpy as np

from blurcalib.calib.joint import GenericCalibration
from blurcalib.calib.rig_calibration import RigError, calibrate_rig
from blurcalib.io.atomic import claim_output_dir
from blurcalib.io.frames import IMAGE_EXTENSIONS, FrameError
from blurcalib.io.results import FEATURES_FILE
from blurcalib.io.sources import FrameInput, frame_inputs
from blurcalib.pipeline.rig import RigRun, write_rig_outputs
from blurcalib.pipeline.run import MIXED, PipelineError, PipelineReport, PipelineSettings, run_pipeline
from blurcalib.runs.events import RunEvent
from blurcalib.target.pattern import StarPattern

__all__ = ["CAMERAS_DIR", "CameraFrames", "RigFramesRun", "calibrate_rig_frames", "camera_frames",
           "unlinked_camera"]

T = TypeVar("T")

CAMERAS_DIR = "cameras"
"""``OUT/cameras/camN/``: camera ``N``'s own ``calibrate`` output."""


@dataclass(frozen=True)
class CameraFrames:
    """One camera's input: ``source`` as given, its ``frames``, each frame's image set
    (``sets[frame name]``, module docstring) and the video's time ``offset`` in frames."""

    source: str
    frames: list[FrameInput]
    sets: dict[str, str]
    offset: int = 0

    @property
    def output_sets(self) -> dict[str, str]:
        """Each frame's image set by the name the camera's ``calibrate`` output gives the frame
        (``frames/<name>``)."""
        return {f"{MIXED}/{name}": key for name, key in self.sets.items()}


@dataclass(eq=False)
class RigFramesRun:
    """What :func:`calibrate_rig_frames` did: the rig (:class:`blurcalib.pipeline.rig.RigRun`) and
    each camera's own pipeline report."""

    rig: RigRun
    cameras: list[PipelineReport]


def _has_images(folder: Path) -> bool:
    return any(p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".") for p in folder.iterdir())


def camera_frames(source: str | os.PathLike[str], every: int = 1, max_frames: int | None = None,
                  offset: int = 0) -> CameraFrames:
    """The frames of one camera's input and their image sets (module docstring); ``offset``: the
    camera's time offset in frames, for a video (``every`` and ``max_frames`` as
    :func:`blurcalib.io.sources.frame_inputs` takes them).

    Raises:
        PipelineError: an input that holds no frames, or an offset for an input that is no video.
    """
    path = Path(source)
    paths = [path]
    if path.is_dir() and not _has_images(path):
        subs = sorted(p for p in path.iterdir()
                      if p.is_dir() and not p.name.startswith(".") and _has_images(p))
        paths = subs or paths
    try:
        frames = frame_inputs(paths, every=every, max_frames=max_frames)
    except FrameError as exc:
        raise PipelineError(str(exc)) from None
    if offset and any(f.index is None for f in frames):
        raise PipelineError(f"{source}: a time offset applies to a video's frames, and this input is no "
                            "video")
    sets = {f.name: f.name if f.index is None else f"#{f.index - offset:06d}" for f in frames}
    return CameraFrames(str(source), frames, sets, offset)


def unlinked_camera(sets: Sequence[set[str]]) -> int | None:
    """The first camera whose image sets ``sets[c]`` link it to camera 0 through no chain of
    shared sets, or None when every camera is linked."""
    linked, frontier = {0}, [0]
    while frontier:
        a = frontier.pop()
        for b in range(len(sets)):
            if b not in linked and sets[a] & sets[b]:
                linked.add(b)
                frontier.append(b)
    return next((c for c in range(len(sets)) if c not in linked), None)


def _camera(camera: CameraFrames, report: PipelineReport) -> GenericCalibration:
    """The camera's generic calibration from its pipeline run, its frames named by their sets
    (module docstring, step 3).

    Raises:
        PipelineError: the run fitted no generic camera (the message names the input and why).
    """
    cal = report.camera
    if cal is None:
        raise PipelineError(f"{camera.source}: no generic camera for the rig: {report.generic_failure}")
    names = camera.output_sets

    def renamed(values: dict[str, T]) -> dict[str, T]:
        return {names.get(k, k): v for k, v in values.items()}

    return replace(cal, poses=renamed(cal.poses), shifts=renamed(cal.shifts),
                   frames=[names.get(f, f) for f in cal.frames],
                   blurry_frames=[names.get(f, f) for f in cal.blurry_frames],
                   frame=np.array([names.get(f, f) for f in cal.frame.tolist()]),
                   skipped_frames=renamed(cal.skipped_frames), rolling=renamed(cal.rolling))


def calibrate_rig_frames(cameras: Sequence[CameraFrames], pattern: StarPattern,
                         out_dir: str | os.PathLike[str], settings: PipelineSettings | None = None,
                         progress: Callable[[int, str, RunEvent], None] | None = None,
                         maps: bool = True, overwrite: bool = False) -> RigFramesRun:
    """Calibrate the rig whose cameras' frames are ``cameras`` (camera 0 first) into ``out_dir``
    (module docstring); ``progress(camera, stage, event)`` during each camera's extraction.

    Raises:
        PipelineError: fewer than two cameras, settings other than generic cameras on the joint
            route, a camera sharing no image set with the others (the message names its input), a
            camera's pipeline or calibration failing (named likewise).
        OutputError: ``out_dir`` holds something else (unless ``overwrite``) or cannot be written.
    """
    s = settings or PipelineSettings()
    if len(cameras) < 2:
        raise PipelineError(f"a rig needs the frames of two or more cameras, got {len(cameras)}")
    if s.calibration.model != "generic" or s.calibration.generic.route != "joint":
        raise PipelineError("a rig is calibrated with generic cameras on the joint route: leave out --model "
                            "and --route")
    lonely = unlinked_camera([set(c.sets.values()) for c in cameras])
    if lonely is not None:
        raise PipelineError(f"{cameras[lonely].source}: camera {lonely} shares no frame name with camera 0, "
                            "directly or through other cameras (frames of one instant need the same file "
                            "name in every camera's input; a video's frames match by index)")
    t_cpu = time.process_time()
    manifest = {"inputs": [c.source for c in cameras], "settings": asdict(s), "maps": maps}
    out = claim_output_dir(out_dir, "calibrate-rig", manifest, overwrite)
    reports, calibrations, features = [], [], []
    for c, camera in enumerate(cameras):
        folder = out / CAMERAS_DIR / f"cam{c}"
        update = None if progress is None else (lambda stage, event, c=c: progress(c, stage, event))
        try:
            report = run_pipeline([], [], pattern, folder, s, update, mixed=camera.frames)
        except PipelineError as exc:
            raise PipelineError(f"{camera.source}: {exc}") from None
        reports.append(report)
        calibrations.append(_camera(camera, report))
        features.append(folder / FEATURES_FILE)
    lonely = unlinked_camera([set(cal.poses) for cal in calibrations])
    if lonely is not None:
        raise PipelineError(f"{cameras[lonely].source}: camera {lonely} sees the target in no image set "
                            "shared with camera 0, directly or through other cameras: its place in the rig "
                            "is unknown")
    try:
        result = calibrate_rig(calibrations, s.calibration.generic.bundle)
    except RigError as exc:
        raise PipelineError(f"rig: {exc}") from None
    rig = write_rig_outputs(out, result, pattern, features, maps, t_cpu,
                            [(c.source, c.offset) for c in cameras])
    return RigFramesRun(rig, reports)
