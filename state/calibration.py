"""The app's calibration: the parametric (Brown-Conrady) and generic cameras of the finished frames.

Inputs (:func:`collect_inputs`), at the current thresholds:

* sharp frames: the star centres of their accepted blocks (``FrameResult.features``), frames with
  at least ``min_sharp_features`` of them;
* blurry frames: the blocks kept by the quality filter (τ_BE, τ_L, connectivity) of frames that
  pass the σ_major pre-filter, with at least ``min_blurry_blocks`` kept, at their star centres
  ``H(0, 0)`` (px, OpenCV convention), weighted ``1 / (1 + loss)``.

The run (:class:`CalibrationRunner`, one worker thread, cancel between stages; the frames not
extracted yet are extracted first, in the state's worker) is the engine's calibration sequence
(:func:`blurcalib.calib.sequence.calibrate_features`), as ``blurcalib calibrate`` runs it, on
these inputs:

1. the parametric camera of the sharp features; with fewer than ``min_sharp_frames`` usable
   sharp frames the blurry frames' kept blocks join this stage (their per-frame shift is not
   modelled there; the generic stage models it); every star centre is corrected for the lens
   bias of its block homography under that camera (:mod:`blurcalib.calib.lens_bias`) and the
   parametric camera fitted again;
2. the generic camera (``route="joint"``: a free image shift per blurry frame), started from
   stage 1;
3. the assessment without ground truth: the generic camera of the sharp frames alone when
   blurry frames entered stage 2, then held-out error, projection uncertainty,
   cross-validation diff and guidance (``docs/validation.md``);
4. figures: observation coverage per grid cell (sharp and blurry apart), the
   generic-minus-parametric difference field (:func:`blurcalib.calib.joint.difference_field`) and, on
   a simulated dataset, both cameras' error against the true camera
   (:func:`blurcalib.paper.generic.projection_errors`: each lattice pixel's true ray, after
   the best-fit rotation, projected by the estimate, minus the pixel).

A cancelled or failed run keeps the previous result. :meth:`CalibrationRunner.export` writes the
reference tool's ``intrinsics0.yaml``, the OpenCV camera file and the undistortion map.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from blurcalib.calib.joint import GenericCalibration, difference_field, save_generic_calibration
from blurcalib.calib.rolling_shutter import RollingShutterResult
from blurcalib.calib.sequence import (
    BLURRY_FLAGS,
    BlurryFrame,
    SequenceCancelledError,
    SequenceSettings,
    Stage,
    calibrate_features,
)
from blurcalib.calib.sharp import Calibration, CalibrationError
from blurcalib.calib.trust import Trust
from blurcalib.camera.parametric import save_camera_yaml
from blurcalib.growth.quality import QualitySettings
from blurcalib.io.atomic import ensure_writable_dir
from blurcalib.io.record import RUN_STATES, FrameStatus
from blurcalib.io.results import BlockTable, FeatureTable
from blurcalib.io.text import count
from blurcalib.sim.evaluate import projection_errors
from blurcalib.sim.truth import TrueCamera
from state.app_state import DONE_STATUSES, AppState
from state.events import Topic
from state.folder import EXPORT_DIR

log = logging.getLogger(__name__)

OPENCV_CAMERA_FILE = "camera.yaml"
"""The parametric camera as an OpenCV FileStorage file
(:func:`blurcalib.camera.parametric.save_camera_yaml`)."""
STAGES = ("extracting frames", "collecting features", *(s.value for s in Stage), "figures")
"""The run's stages; the first only when frames are extracted (or being extracted) first."""
IN_PROGRESS = frozenset({FrameStatus.QUEUED, FrameStatus.RUNNING})
"""Frame statuses of an extraction under way."""
USED = FrameStatus.USED.value


@dataclass(frozen=True)
class CalibrationSettings:
    """Options of the app's calibration.

    Attributes:
        sequence: the calibration sequence's (:class:`blurcalib.calib.sequence.SequenceSettings`):
            the generic grid's cell (the coverage map uses the same cells), the fewest usable
            sharp frames and features of a sharp frame, the fewest kept blocks of a blurry frame
            (``alignment.min_blocks``), the assessment; the blurry frames join the parametric
            stage when the sharp frames are too few.
        lattice_px: step (px) of the lattice of the difference field and the error against truth.
    """

    sequence: SequenceSettings = field(default_factory=lambda: SequenceSettings(blurry_in_parametric=True))
    lattice_px: float = 8.0

    @property
    def cell_px(self) -> float:
        """The generic grid's cell (px)."""
        return self.sequence.generic.cell_px


@dataclass(frozen=True)
class CalibrationInputs:
    """The features a calibration would use now.

    Attributes:
        sharp, blurry: the sharp frames' and blurry frames' observations.
        blocks: the blocks they were made from (for the lens-bias correction,
            :mod:`blurcalib.calib.lens_bias`).
        image_size: ``(width, height)`` px of the frames (the most common size).
        reasons: frame -> why it is not an input (frames absent here are inputs).
        quality: the thresholds the blurry frames were filtered with.
    """

    sharp: FeatureTable
    blurry: FeatureTable
    blocks: BlockTable
    image_size: tuple[int, int]
    reasons: dict[str, str]
    quality: QualitySettings

    @property
    def frames(self) -> list[str]:
        """The input frames, sharp first."""
        return list(dict.fromkeys([*self.sharp.frame.tolist(), *self.blurry.frame.tolist()]))


@dataclass(frozen=True)
class Coverage:
    """Observations per image cell, sharp and blurry apart.

    Attributes:
        sharp, blurry: ``(gh, gw)`` counts; cell ``(i, j)`` covers x in ``[j c - 0.5, (j + 1) c - 0.5)``
            and y in ``[i c - 0.5, (i + 1) c - 0.5)`` px, ``c = cell_px``.
        cell_px: cell side (px).
        image_size: ``(width, height)`` px.
    """

    sharp: np.ndarray
    blurry: np.ndarray
    cell_px: float
    image_size: tuple[int, int]

    @property
    def total(self) -> int:
        """Observations counted."""
        return int(self.sharp.sum() + self.blurry.sum())


def cell_counts(xy: np.ndarray, image_size: tuple[int, int], cell_px: float) -> np.ndarray:
    """``(gh, gw)`` number of points ``xy (N, 2)`` px in each ``cell_px`` cell of the image
    (points outside the image count in the nearest edge cell)."""
    w, h = image_size
    gw, gh = int(np.ceil(w / cell_px)), int(np.ceil(h / cell_px))
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    cx = np.clip(np.floor((xy[:, 0] + 0.5) / cell_px), 0, gw - 1).astype(np.int64)
    cy = np.clip(np.floor((xy[:, 1] + 0.5) / cell_px), 0, gh - 1).astype(np.int64)
    return np.bincount(cy * gw + cx, minlength=gw * gh).reshape(gh, gw)


def coverage(sharp_xy: np.ndarray, blurry_xy: np.ndarray, image_size: tuple[int, int], cell_px: float
             ) -> Coverage:
    """The :class:`Coverage` of sharp and blurry observations ``(N, 2)`` px."""
    return Coverage(cell_counts(sharp_xy, image_size, cell_px), cell_counts(blurry_xy, image_size, cell_px),
                    cell_px, image_size)


def input_coverage(inputs: CalibrationInputs, cell_px: float) -> Coverage:
    """The coverage of a calibration's inputs (every input observation)."""
    return coverage(np.column_stack([inputs.sharp.x, inputs.sharp.y]),
                    np.column_stack([inputs.blurry.x, inputs.blurry.y]), inputs.image_size, cell_px)


def collect_inputs(state: AppState, settings: CalibrationSettings | None = None) -> CalibrationInputs:
    """The sharp and blurry observations of the finished frames at the state's thresholds, and
    why every other frame is not an input (module docstring)."""
    s = settings or CalibrationSettings()
    dataset = state.dataset
    entries = state.entries()
    results = state.results()
    sizes = Counter(size for _, _, size in results.values())
    image_size = sizes.most_common(1)[0][0] if sizes else (0, 0)
    square_m = dataset.pattern.square_length_m if dataset is not None else 0.0
    reasons: dict[str, str] = {}
    sharp, blurry, blocks = [], [], []
    for entry in entries:
        status = entry.record.status
        if status is not FrameStatus.OK or entry.name not in results:
            reasons[entry.name] = "not extracted" if status in RUN_STATES - {FrameStatus.CANCELLED} \
                else f"not extracted ({status.value.replace('_', ' ')})"
            continue
        result, flt, size = results[entry.name]
        if size != image_size:
            reasons[entry.name] = f"another image size ({size[0]} x {size[1]})"
            continue
        if entry.kind == "sharp":
            if len(result.features) < s.sequence.min_sharp_features:
                reasons[entry.name] = (f"too few accepted blocks ({len(result.features)} < "
                                       f"{s.sequence.min_sharp_features})")
                continue
            sharp.append(result.features)
            blocks.append(result.blocks)
            continue
        if flt is None or not flt.frame_ok:
            sigma = flt.centre_sigma_major if flt is not None else float("nan")
            reasons[entry.name] = (f"dropped by the pre-filter (centre σ_major {sigma:.2f} px < "
                                   f"{state.quality.min_sigma_major:g} px)")
            continue
        kept = np.flatnonzero(flt.kept)
        if len(kept) < s.sequence.alignment.min_blocks:
            reasons[entry.name] = f"too few kept blocks ({len(kept)} < {s.sequence.alignment.min_blocks})"
            continue
        blurry.append(result.blocks.select(kept).features(square_m, int(BLURRY_FLAGS)))
        blocks.append(result.blocks.select(kept))
    return CalibrationInputs(FeatureTable.concat(sharp), FeatureTable.concat(blurry),
                             BlockTable.concat(blocks), image_size, reasons, state.quality)


@dataclass(frozen=True)
class TruthErrors:
    """Error (px) of the cameras against the true camera over the generic model's calibrated area
    (lattice pixels, after the best-fit rotation)."""

    generic_median: float
    generic_rms: float
    parametric_median: float
    parametric_rms: float
    pixels: int


def truth_errors(truth: TrueCamera, generic: GenericCalibration, parametric: Calibration,
                 lattice_px: float) -> TruthErrors:
    """Both cameras' :func:`~blurcalib.paper.generic.projection_errors` against ``truth``
    on a ``lattice_px`` lattice of the generic model's calibrated area."""
    x0, y0, x1, y1 = generic.model.area_opencv
    xx, yy = np.meshgrid(np.arange(np.ceil(x0), x1, lattice_px), np.arange(np.ceil(y0), y1, lattice_px))
    px = np.column_stack([xx.ravel(), yy.ravel()])
    eg = projection_errors(truth, generic.model, px)
    ok = np.isfinite(eg)
    ep = projection_errors(truth, parametric.camera, px[ok])
    eg = eg[ok]
    return TruthErrors(float(np.median(eg)), float(np.sqrt(np.mean(eg**2))), float(np.median(ep)),
                       float(np.sqrt(np.mean(ep**2))), int(ok.sum()))


@dataclass(eq=False)
class AppCalibration:
    """A finished calibration of the app's frames.

    Attributes:
        inputs: the features it used.
        parametric: the Brown-Conrady calibration (stage 1).
        parametric_with_blurry: blurry frames entered stage 1 (too few sharp frames).
        generic: the generic calibration (stage 2).
        generic_sharp: the generic calibration of the sharp frames alone, when blurry frames
            entered ``generic`` (stage 3), else None.
        trust: the assessment (stage 3), or None when it failed (``trust_failure`` says why).
        coverage: the generic fit's observations per grid cell.
        difference: ``(xs, ys, diff (H', W', 2))`` px, generic minus parametric.
        truth: errors against the true camera (simulated data), else None.
        status: frame -> ``used`` or why the calibration did not use it.
        seconds: wall time of the run.
        trust_failure: why there is no assessment, or "".
        sharp_failure: why there is no sharp-only generic camera though blurry frames were
            used, or why it was not assessed with the rest (then ``trust`` is the generic
            camera's alone, with the sharp-only uncertainty map added), or "".
        rolling_shutter: the rolling-shutter step (readout ratio, each moving frame's blur
            velocity, the warning), or None.
    """

    inputs: CalibrationInputs
    parametric: Calibration
    parametric_with_blurry: bool
    generic: GenericCalibration
    generic_sharp: GenericCalibration | None
    trust: Trust | None
    coverage: Coverage
    difference: tuple[np.ndarray, np.ndarray, np.ndarray] = field(repr=False)
    truth: TruthErrors | None
    status: dict[str, str]
    seconds: float
    trust_failure: str = ""
    sharp_failure: str = ""
    rolling_shutter: RollingShutterResult | None = None

    def frame_residuals(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """``(N, 2)`` px observations of frame ``name`` and their residuals under the generic model."""
        rows = self.generic.frame == name
        return self.generic.observed[rows], self.generic.residuals[rows]


def fit_status(inputs: CalibrationInputs, generic: GenericCalibration) -> dict[str, str]:
    """Each frame's status after a fit: ``used``, left out by the fit, or its input reason."""
    status = dict(inputs.reasons)
    for name in inputs.frames:
        if name in generic.poses:
            status[name] = USED
        elif name in generic.skipped_frames:
            status[name] = f"left out by the fit ({generic.skipped_frames[name]} usable features)"
        else:
            status[name] = "left out by the fit"
    return status


def _blurry_frames(inputs: CalibrationInputs) -> list[BlurryFrame]:
    """The inputs' blurry frames as the sequence takes them: each with its kept blocks."""
    names = list(dict.fromkeys(inputs.blurry.frame.tolist()))
    return [BlurryFrame(name, blocks=(b := inputs.blocks.select(inputs.blocks.frame == name)),
                        kept=np.ones(len(b), dtype=bool), flags=BLURRY_FLAGS) for name in names]


def fit(inputs: CalibrationInputs, state: AppState, settings: CalibrationSettings,
        stage: Callable[[int], bool]) -> AppCalibration | None:
    """Run the stages on ``inputs`` (module docstring); ``stage(i)`` is called before stage ``i``
    of :data:`STAGES` and returns False to stop (then None is returned).

    Raises:
        CalibrationError: no usable frames.
    """
    t0 = time.perf_counter()
    dataset = state.dataset
    if not inputs.frames:
        raise CalibrationError("no usable frame: none is extracted with enough features and passes the "
                               "filters (see the frames' statuses)")
    try:
        run = calibrate_features(inputs.sharp, inputs.blocks, _blurry_frames(inputs), dataset.pattern,
                                 inputs.image_size, settings.sequence,
                                 on_stage=lambda s: stage(STAGES.index(s.value)))
    except SequenceCancelledError:
        return None
    if run.trust_failure:
        log.warning("assessment failed: %s", run.trust_failure)
    if not stage(5):
        return None
    generic, parametric = run.generic, run.calibration
    blurry_rows = np.isin(generic.frame, generic.blurry_frames)
    cov = coverage(generic.observed[~blurry_rows], generic.observed[blurry_rows], inputs.image_size,
                   settings.cell_px)
    difference = difference_field(generic.model, parametric.camera, settings.lattice_px)
    truth = None
    if dataset.truth is not None:
        truth = truth_errors(dataset.truth.camera, generic, parametric, settings.lattice_px)
    return AppCalibration(inputs, parametric, run.parametric_with_blurry, generic, run.generic_sharp,
                          run.trust, cov, difference, truth, fit_status(inputs, generic),
                          time.perf_counter() - t0, run.trust_failure, run.sharp_failure, run.rolling_shutter)


@dataclass(frozen=True)
class CalibrationProgress:
    """Where the calibration run stands: ``stage`` indexes :data:`STAGES`."""

    running: bool = False
    stage: int = 0
    cancelling: bool = False

    @property
    def fraction(self) -> float:
        """Share of the run done, 0..1."""
        return self.stage / len(STAGES) if self.running else 0.0

    @property
    def label(self) -> str:
        """What the run is doing."""
        if not self.running:
            return ""
        return "cancelling" if self.cancelling else STAGES[self.stage]


class CalibrationRunner:
    """Runs the calibration of an :class:`AppState`'s finished frames in a worker thread, keeps
    the last result and tells the state's subscribers (:attr:`Topic.CALIBRATION`)."""

    def __init__(self, state: AppState, settings: CalibrationSettings | None = None) -> None:
        self.state = state
        self.settings = settings or CalibrationSettings()
        self._lock = threading.Lock()
        self._cancel = threading.Event()
        self._worker: threading.Thread | None = None
        self._progress = CalibrationProgress()
        self._result: AppCalibration | None = None
        state.subscribe(self._on_change)

    def _on_change(self, topic: Topic) -> None:
        if topic is Topic.FOLDER:  # another folder or pattern: the result belongs to the old one
            with self._lock:
                self._result = None
            self.state.events.emit(Topic.CALIBRATION)

    @property
    def result(self) -> AppCalibration | None:
        """The last finished calibration (None before the first)."""
        with self._lock:
            return self._result

    @property
    def is_running(self) -> bool:
        """A calibration is running."""
        with self._lock:
            return self._worker is not None

    def progress(self) -> CalibrationProgress:
        """The run's progress."""
        with self._lock:
            return self._progress

    def inputs(self) -> CalibrationInputs:
        """The inputs a run would use now."""
        return collect_inputs(self.state, self.settings)

    def statuses(self) -> dict[str, str]:
        """Every frame's status now: ``used`` by the last calibration, or why it is not."""
        inputs = self.inputs()
        result = self.result
        status = dict(inputs.reasons)
        for name in inputs.frames:
            if result is None:
                status[name] = "usable: run the calibration"
            elif name not in result.status:
                status[name] = "usable: not in the last calibration, run it again"
            elif result.status[name] == USED or result.status[name].startswith("left out"):
                status[name] = result.status[name]
            else:
                status[name] = "usable: not in the last calibration, run it again"
        return status

    def run(self, extract: bool = True) -> bool:
        """Start a calibration (False when one is running or no folder is open). With ``extract``
        the frames not extracted yet are extracted first, as *Run all* does, and an extraction under
        way is waited for (a cancel stops that extraction too); without it, only the frames
        finished now are used."""
        with self._lock:
            if self._worker is not None or self.state.dataset is None:
                return False
            self._cancel.clear()
            self._progress = CalibrationProgress(running=True)
            self._worker = threading.Thread(target=self._work, args=(extract,), name="blurcalib-calibration",
                                            daemon=True)
            self._worker.start()
        self.state.events.emit(Topic.CALIBRATION)
        return True

    def cancel(self) -> None:
        """Stop the run before its next stage; the previous result is kept."""
        with self._lock:
            if self._worker is None:
                return
            self._cancel.set()
            self._progress = replace(self._progress, cancelling=True)
        self.state.events.emit(Topic.CALIBRATION)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the run to end; returns whether it did within ``timeout`` seconds."""
        with self._lock:
            worker = self._worker
        if worker is None:
            return True
        worker.join(timeout)
        return not worker.is_alive()

    def _stage(self, index: int) -> bool:
        if self._cancel.is_set():
            return False
        with self._lock:
            self._progress = replace(self._progress, stage=index)
        self.state.events.emit(Topic.CALIBRATION)
        return not self._cancel.is_set()

    def _extract(self) -> bool:
        """Extract the frames not extracted yet in the state's worker and wait for it; False when
        cancelled."""
        missing = [e for e in self.state.entries() if e.record.status not in DONE_STATUSES | IN_PROGRESS]
        if not missing and not self.state.is_running:
            return True
        self._stage(0)
        if missing:
            self.state.run_all()
        while not self.state.wait(0.2):
            if self._cancel.is_set():
                self.state.cancel()
        return not self._cancel.is_set()

    def _work(self, extract: bool) -> None:
        dataset = self.state.dataset
        outcome: AppCalibration | None = None
        try:
            if not extract or self._extract():
                self._stage(1)
                outcome = fit(self.inputs(), self.state, self.settings, self._stage)
        except (CalibrationError, ValueError) as exc:
            self.state.notify("error", "Calibration failed", f"{exc}; the previous result is kept")
        except Exception as exc:  # the app must survive any failure of the fit
            log.exception("calibration failed")
            self.state.notify("error", "Calibration failed", f"{type(exc).__name__}: {exc}")
        now = self.state.dataset
        if now is None or (now.folder, now.pattern_path) != (dataset.folder, dataset.pattern_path):
            outcome = None  # another folder or pattern was opened meanwhile
        with self._lock:
            if outcome is not None:
                self._result = outcome
            self._worker = None
            self._progress = CalibrationProgress()
            cancelled = self._cancel.is_set()
        if outcome is not None:
            g = outcome.generic
            self.state.notify("info", "Calibration done",
                              f"generic median {g.median_error:.3f} px, RMS {g.rms_error:.3f} px over "
                              f"{count(len(g.poses), 'frame')} ({outcome.seconds:.1f} s)")
        elif cancelled:
            self.state.notify("info", "Calibration cancelled", "the previous result is kept")
        self.state.events.emit(Topic.CALIBRATION)

    def export(self, folder: str | Path | None = None) -> list[Path]:
        """Write the last calibration into ``folder`` (default ``<dataset>/calibration_app``): the
        generic files of :func:`blurcalib.calib.joint.save_generic_calibration` (``intrinsics0.yaml``,
        poses, ``undistortion_map.npz``, coverage and difference images) and the parametric camera
        as ``camera.yaml``; a notice names the files.

        Raises:
            ValueError: there is no calibration to export.
            OSError: the folder cannot be written.
        """
        result = self.result
        dataset = self.state.dataset
        if result is None or dataset is None:
            raise ValueError("no calibration to export: run the calibration first")
        out = ensure_writable_dir(Path(folder) if folder is not None else dataset.folder / EXPORT_DIR)
        paths = save_generic_calibration(out, result.generic)
        save_camera_yaml(out / OPENCV_CAMERA_FILE, result.parametric.camera)
        paths.append(out / OPENCV_CAMERA_FILE)
        self.state.notify("info", "Calibration exported",
                          f"{out}: " + ", ".join(p.name for p in paths))
        return paths
