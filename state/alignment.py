"""Global alignment of the app's frames to a reference parametric camera (paper ``eq:global_align``).

The tuning panel reports the alignment error that the current thresholds give, and the error
views draw its residuals. Both need a reference Brown-Conrady camera ``pi_d`` and target points
``P``. :func:`find_reference` takes the first of:

1. a calibration saved by ``blurcalib calibrate`` (:func:`blurcalib.calib.sharp.save_calibration`)
   beside the frames: ``calibration/`` or ``calibration/calibration/`` (a pipeline's output
   folder named ``calibration``) in the opened folder or in its parent; it also gives the
   refined target points;
2. on a simulated dataset, the Brown-Conrady part of the true camera
   (``DatasetTruth.camera.model``) with the nominal flat target;
3. a calibration (:func:`blurcalib.calib.sharp.calibrate_sharp`) of the app's finished sharp
   frames' star centres, once at least :data:`MIN_SHARP_FRAMES` are finished.

:func:`align_frame` aligns one frame's blocks kept by the quality filter as the pipeline does
(:func:`blurcalib.calib.alignment.align_kept_blocks`: Huber loss, one translation ``x_G``, each
block weighted by ``1 / (loss + eps)``), and
returns the residuals after alignment. :class:`AlignmentCache` keeps the results per frame and
kept-block set, so moving a threshold slider only re-aligns the frames whose kept blocks changed
(a few milliseconds per frame of ~250 blocks).

Pixels follow OpenCV's convention: the top-left pixel's centre is ``(0, 0)``, x right, y down.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from blurcalib.calib.alignment import AlignmentError, AlignmentSettings, align_kept_blocks
from blurcalib.calib.sharp import (
    CALIBRATION_FILE,
    CAMERA_JSON_FILE,
    CalibrationError,
    CalibrationFileError,
    calibrate_sharp,
    load_calibration,
)
from blurcalib.camera.parametric import BrownConrady
from blurcalib.extract.frame import FrameResult
from blurcalib.geometry.pose import Pose
from blurcalib.growth.quality import FrameFilter
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import FeatureTable
from blurcalib.target.pattern import StarPattern
from state.app_state import AppState
from state.folder import Dataset

MIN_SHARP_FRAMES = 5
"""Finished sharp frames needed to calibrate a reference camera in the app (as the pipeline)."""

CALIBRATION_SUBFOLDERS = ("calibration", "calibration/calibration")
"""Where a saved calibration is looked for, in the opened folder and then in its parent."""

NO_REFERENCE = (f"needs ≥{MIN_SHARP_FRAMES} finished sharp frames, a calibration/ folder, "
                "or ground truth")
"""Why there is no reference camera, in short."""


@dataclass(frozen=True, eq=False)
class Reference:
    """The parametric camera and target points that frames are aligned to.

    Attributes:
        camera: the Brown-Conrady camera ``pi_d`` (OpenCV convention, px).
        points: ``(M, 3)`` target points (m) by feature id; NaN rows (features a calibration
            never observed) fall back to the nominal points ``(fx L, fy L, 0)``.
        source: where it comes from, for the user (``calibration folder out/demo/calibration/
            calibration``, ``ground-truth camera``, ``calibration of 5 sharp frames``).
    """

    camera: BrownConrady
    points: np.ndarray = field(repr=False)
    source: str


@dataclass(frozen=True)
class ReferenceChoice:
    """The outcome of :func:`find_reference`.

    Attributes:
        reference: the reference, or None when none is available.
        reason: why there is none (empty when there is one), including candidates that were
            found but could not be used (a malformed calibration folder).
    """

    reference: Reference | None
    reason: str = ""


@dataclass(frozen=True, eq=False)
class FrameAlignment:
    """One frame's kept blocks aligned to the reference (``eq:global_align``).

    Attributes:
        frame: the frame's name.
        index: ``(N,)`` indices of the aligned blocks into ``result.blocks``.
        feature_id: ``(N,)`` their feature ids.
        observed: ``(N, 2)`` px, their star centres ``H(0, 0)``.
        residuals: ``(N, 2)`` px, ``observed - x_G - pi_d(M, P)``: the reprojection error left
            after the pose ``M`` and the translation ``x_G`` are fitted.
        translation: ``(2,)`` px, the frame's translation ``x_G``.
        pose: the fitted pose ``M`` (target -> camera, metres).
        angle_to_normal: rad, between the optical axis and the target normal.
        orientation_ok: the paper's orientation filter: False when the optical axis is within
            pi/10 of the target normal, where ``x_G`` is ill-conditioned.
        converged: the solver met its tolerance.
        reference: the reference it was aligned to.
    """

    frame: str
    index: np.ndarray
    feature_id: np.ndarray
    observed: np.ndarray = field(repr=False)
    residuals: np.ndarray = field(repr=False)
    translation: np.ndarray
    pose: Pose
    angle_to_normal: float
    orientation_ok: bool
    converged: bool
    reference: Reference = field(repr=False)

    @property
    def num_blocks(self) -> int:
        """Number of aligned blocks ``N``."""
        return len(self.index)

    @property
    def errors(self) -> np.ndarray:
        """``(N,)`` px, the residuals' lengths."""
        return np.hypot(self.residuals[:, 0], self.residuals[:, 1])

    @property
    def median_error(self) -> float:
        """Median residual length (px)."""
        return float(np.median(self.errors))

    @property
    def rms_error(self) -> float:
        """RMS residual length (px)."""
        return float(np.sqrt(np.mean(self.errors**2)))


@dataclass(frozen=True)
class AlignmentOverview:
    """The alignment error over every used frame (finished and passing the blur pre-filter).

    Attributes:
        aligned: frame name -> alignment, for used frames that align and pass the orientation
            filter: these make up the figures below.
        ill_conditioned: used frames aligned but failing the orientation filter (left out).
        failed: used frames that could not be aligned -> why (too few kept blocks, ...).
        dropped: finished frames the blur pre-filter drops.
    """

    aligned: dict[str, FrameAlignment]
    ill_conditioned: tuple[str, ...] = ()
    failed: dict[str, str] = field(default_factory=dict)
    dropped: int = 0

    @property
    def num_blocks(self) -> int:
        """Blocks over the aligned frames."""
        return sum(a.num_blocks for a in self.aligned.values())

    def _errors(self) -> np.ndarray:
        return np.concatenate([a.errors for a in self.aligned.values()]) if self.aligned else np.zeros(0)

    @property
    def median_error(self) -> float:
        """Median residual length over all blocks of the aligned frames (px; NaN when none)."""
        e = self._errors()
        return float(np.median(e)) if len(e) else float("nan")

    @property
    def rms_error(self) -> float:
        """RMS residual length over all blocks of the aligned frames (px; NaN when none)."""
        e = self._errors()
        return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


# ------------------------------------------------------------------------------ the reference
def calibration_folders(folder: str | Path) -> list[Path]:
    """Saved calibrations beside a dataset folder, in the order they are tried.

    The candidates are :data:`CALIBRATION_SUBFOLDERS` of ``folder`` and then of its parent;
    a candidate counts when it holds ``camera.json`` and ``calibration.json``.
    """
    root = Path(folder)
    found = []
    for base in (root, root.parent):
        for sub in CALIBRATION_SUBFOLDERS:
            candidate = base / sub
            if (candidate / CAMERA_JSON_FILE).is_file() and (candidate / CALIBRATION_FILE).is_file():
                found.append(candidate)
    return found


def saved_reference(folder: str | Path, pattern: StarPattern) -> ReferenceChoice:
    """The first usable saved calibration beside ``folder`` (:func:`calibration_folders`).

    A candidate that cannot be read, or whose points do not match the pattern, is skipped and
    named in ``reason``.
    """
    problems = []
    for candidate in calibration_folders(folder):
        try:
            calib = load_calibration(candidate)
        except CalibrationFileError as exc:
            problems.append(str(exc))
            continue
        if calib.points.shape != (pattern.num_features, 3):
            problems.append(f"{candidate}: {len(calib.points)} target points, the pattern has "
                            f"{pattern.num_features} features")
            continue
        return ReferenceChoice(Reference(calib.camera, calib.points, f"calibration folder {candidate}"))
    return ReferenceChoice(None, "; ".join(problems))


def truth_reference(dataset: Dataset) -> Reference | None:
    """The Brown-Conrady part of a simulated dataset's true camera, with the nominal target."""
    if dataset.truth is None:
        return None
    return Reference(dataset.truth.camera.model, dataset.pattern.points_3d(), "ground-truth camera")


def sharp_reference(pattern: StarPattern, sharp: Mapping[str, tuple[FrameResult, tuple[int, int]]],
                    min_frames: int = MIN_SHARP_FRAMES) -> ReferenceChoice:
    """Calibrate a reference from finished sharp frames' accepted star centres.

    Args:
        pattern: the target.
        sharp: finished sharp frame name -> its result and image size ``(width, height)`` px.
            Frames of another size than the most common one are left out.
        min_frames: fewest frames to calibrate from.
    """
    sizes = Counter(size for _, size in sharp.values())
    size = sizes.most_common(1)[0][0] if sizes else None
    frames = {name: r for name, (r, s) in sorted(sharp.items()) if s == size and len(r.features)}
    if len(frames) < min_frames:
        return ReferenceChoice(None, f"no reference camera: {NO_REFERENCE} "
                                     f"({len(frames)} sharp frames finished)")
    table = FeatureTable.concat([r.features for r in frames.values()])
    try:
        calib = calibrate_sharp(table, pattern, size, min_frames=min_frames)
    except CalibrationError as exc:
        return ReferenceChoice(None, f"no reference camera: {exc}")
    return ReferenceChoice(Reference(calib.camera, calib.points,
                                     f"calibration of {calib.num_frames} sharp frames "
                                     f"(median {calib.median_error:.3f} px)"))


def find_reference(dataset: Dataset, sharp: Mapping[str, tuple[FrameResult, tuple[int, int]]],
                   min_sharp_frames: int = MIN_SHARP_FRAMES) -> ReferenceChoice:
    """The reference camera: a saved calibration, else the ground truth, else the sharp frames.

    Args:
        dataset: the opened dataset (its folder, pattern and ground truth).
        sharp: finished sharp frames: name -> result and image size ``(width, height)`` px.
        min_sharp_frames: fewest sharp frames to calibrate from.
    """
    saved = saved_reference(dataset.folder, dataset.pattern)
    if saved.reference is not None:
        return saved
    truth = truth_reference(dataset)
    if truth is not None:
        return ReferenceChoice(truth)
    choice = sharp_reference(dataset.pattern, sharp, min_sharp_frames)
    if choice.reference is None and saved.reason:
        return ReferenceChoice(None, f"{choice.reason}; skipped {saved.reason}")
    return choice


# ------------------------------------------------------------------------------- one frame
def align_frame(reference: Reference, pattern: StarPattern, result: FrameResult, flt: FrameFilter | None,
                image_size: tuple[int, int], settings: AlignmentSettings | None = None) -> FrameAlignment:
    """Align a frame's blocks kept by the quality filter to the reference (``eq:global_align``).

    As the pipeline does (:func:`blurcalib.calib.alignment.align_blocks`): the kept blocks'
    finite star centres ``H(0, 0)`` (px) against the reference's points, each weighted by its
    deconvolution loss.

    Args:
        reference: the camera and points.
        pattern: the target.
        result: the frame's extraction result.
        flt: its quality filter (None: no blocks).
        image_size: the frame's ``(width, height)`` px.
        settings: loss, bias and fewest blocks (the engine's defaults).

    Raises:
        AlignmentError: no blocks (a frame not seeded), too few kept blocks, a frame of another
            size than the reference camera's, or a failed pose estimate; the message says which.
    """
    camera = reference.camera
    if not len(result.blocks):
        raise AlignmentError("no blocks: the frame was not seeded" if result.seed is None
                             else "no blocks were grown")
    if tuple(image_size) != (camera.width, camera.height):
        raise AlignmentError(f"the frame is {image_size[0]} x {image_size[1]} px, the reference camera "
                             f"{camera.width} x {camera.height} px")
    kept = np.zeros(len(result.blocks), dtype=bool) if flt is None else flt.kept
    index, ga = align_kept_blocks(camera, pattern, reference.points, result.blocks, kept, settings)
    return FrameAlignment(result.frame, index, result.blocks.feature_id[index], result.blocks.centre[index],
                          ga.residuals, ga.translation, ga.pose, ga.angle_to_normal, not ga.ill_conditioned,
                          ga.converged, reference)


# -------------------------------------------------------------------------------- the cache
class AlignmentCache:
    """Alignments of an :class:`AppState`'s frames, recomputed only when their input changes.

    The reference is found once per opened dataset (the sharp-frame calibration again when the
    set of finished sharp frames changes). A frame's alignment is kept per result and kept-block
    set, so thresholds that keep the same blocks cost nothing and moving back to earlier
    thresholds finds the earlier alignment. Safe to use from several threads. ``settings``: the
    alignment's (loss, bias, orientation filter; the engine's defaults).
    """

    def __init__(self, state: AppState, *, settings: AlignmentSettings | None = None,
                 size: int = 512) -> None:
        self.state = state
        self.settings = settings or AlignmentSettings()
        self._size = size
        self._lock = threading.RLock()
        self._dataset: Dataset | None = None
        self._sharp: dict[str, tuple[FrameResult, tuple[int, int]]] = {}
        self._choice = ReferenceChoice(None, "no dataset open")
        # (frame, packed kept mask) -> the result and reference aligned, and the alignment or why not.
        self._frames: OrderedDict[tuple[str, bytes],
                                  tuple[FrameResult, Reference, FrameAlignment | str]] = OrderedDict()

    def reference(self) -> ReferenceChoice:
        """The current reference (:func:`find_reference`), or why there is none."""
        state = self.state
        with self._lock:
            dataset = state.dataset
            if dataset is None:
                return ReferenceChoice(None, "no dataset open")
            sharp: dict[str, tuple[FrameResult, tuple[int, int]]] = {}
            if dataset.truth is None:
                results = state.results()
                sharp = {e.name: (results[e.name][0], results[e.name][2]) for e in state.entries()
                         if e.kind == "sharp" and e.record.status is FrameStatus.OK and e.name in results}
            same = sharp.keys() == self._sharp.keys() and all(
                sharp[n][0] is self._sharp[n][0] for n in sharp)
            if dataset is not self._dataset or not same:
                if dataset is not self._dataset:
                    self._frames.clear()
                self._dataset, self._sharp = dataset, sharp
                self._choice = find_reference(dataset, sharp)
            return self._choice

    def frame(self, name: str) -> FrameAlignment:
        """The alignment of frame ``name`` at the current thresholds.

        Raises:
            AlignmentError: no reference, no result, or the frame cannot be aligned (why).
        """
        choice = self.reference()
        if choice.reference is None:
            raise AlignmentError(choice.reason)
        finished = self.state.results().get(name)
        if finished is None:
            raise AlignmentError(f"{name} is not extracted yet")
        return self._align(name, choice.reference, *finished)

    def _align(self, name: str, reference: Reference, result: FrameResult, flt: FrameFilter | None,
               size: tuple[int, int]) -> FrameAlignment:
        key = (name, b"" if flt is None else np.packbits(flt.kept).tobytes())
        with self._lock:
            hit = self._frames.get(key)
            if hit is not None and hit[0] is result and hit[1] is reference:
                self._frames.move_to_end(key)
                outcome = hit[2]
            else:
                outcome = None
        if outcome is None:
            try:
                outcome = align_frame(reference, self.state.dataset.pattern, result, flt, size, self.settings)
            except AlignmentError as exc:
                outcome = str(exc)
            with self._lock:
                self._frames[key] = (result, reference, outcome)
                while len(self._frames) > self._size:
                    self._frames.popitem(last=False)
        if isinstance(outcome, str):
            raise AlignmentError(outcome)
        return outcome

    def overview(self) -> AlignmentOverview | None:
        """The alignment of every used frame (None when there is no reference)."""
        choice = self.reference()
        if choice.reference is None:
            return None
        ok = {e.name for e in self.state.entries() if e.record.status is FrameStatus.OK}
        aligned: dict[str, FrameAlignment] = {}
        ill, failed, dropped = [], {}, 0
        for name, (result, flt, size) in sorted(self.state.results().items()):
            if name not in ok or flt is None:
                continue
            if not flt.frame_ok:
                dropped += 1
                continue
            try:
                alignment = self._align(name, choice.reference, result, flt, size)
            except AlignmentError as exc:
                failed[name] = str(exc)
                continue
            if alignment.orientation_ok:
                aligned[name] = alignment
            else:
                ill.append(name)
        return AlignmentOverview(aligned, tuple(ill), failed, dropped)
