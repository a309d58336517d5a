"""The whole calibration pipeline: extract, calibrate the sharp set, filter, align, fit the
generic camera to sharp and blurry frames together.

``run_pipeline`` is what ``blurcalib calibrate`` runs:

1. feature extraction of the sharp frames (small PSF window) and the blurry frames (a window
   that fits the blur), resumable, into ``OUT/sharp/`` and ``OUT/blurry/`` (or, for frames
   whose kind each frame's measured blur decides, ``mixed=``, into ``OUT/frames/``)
   (:mod:`blurcalib.extract.frame`), each an ``extract`` output with the frames named as ``blurcalib
   extract`` names them, so that earlier ``extract`` runs into these folders are reused; the
   run's own outputs name the frames ``sharp/<name>`` and ``blurry/<name>``; duplicate views
   are found (:mod:`blurcalib.extract.duplicates`);
2. the calibration sequence (:func:`blurcalib.calib.sequence.calibrate_features`): the
   Brown-Conrady camera of the sharp set, the lens-bias correction of every star centre and
   that camera again (saved in ``OUT/calibration/``); per blurry frame the optional blur
   pre-filter (off by default; the paper's 3.8 px is ``QualitySettings(min_sigma_major=3.8)``),
   the BE / loss / connectivity filter and the global alignment to the parametric camera
   (``eq:global_align``) with the orientation filter; with ``model="generic"`` (the default)
   the central generic camera (:mod:`blurcalib.calib.joint`) of sharp and blurry frames, on the
   joint route (each blurry frame with a free image shift, so frontal frames need no
   orientation filter) or the paper's aligned route, saved as the reference tool's
   ``OUT/calibration/intrinsics0.yaml`` with the poses, report images, and its assessment
   (:mod:`blurcalib.calib.trust`, ``docs/validation.md``); the undistortion map of the generic
   camera, or of the parametric one with ``model="parametric"`` (pinhole, or latitude-longitude
   for a wide field: :func:`blurcalib.calib.undistortion.undistortion_output`);
3. outputs: ``OUT/features.csv`` (sharp features and aligned blurry features, flagged),
   ``OUT/features.bin`` (the reference tool's format, pixel-corner convention),
   ``OUT/frames.csv`` (one row per input frame, :mod:`blurcalib.pipeline.frames`),
   ``OUT/report.json`` and figures (the reprojection-error direction images, per-frame errors).

Frame statuses (:class:`blurcalib.io.record.FrameStatus`): ``used`` marks every frame whose
features enter the final calibration (a sharp frame: the sharp-set and generic calibrations; a
blurry frame: the generic fit, or with ``model="parametric"`` the global alignment and
``features.bin``). Every other status comes with its reason: the extraction's own
(``not_seeded``, ``no_blocks``, ``unreadable``, ``wrong_size``, ``failed``), ``duplicate`` (the same
view as an earlier frame, which is kept; the minimum of usable sharp frames counts distinct
views), ``too_few_features`` (left out of a calibration), ``low_blur`` (the optional
pre-filter), ``too_few_blocks`` (after the block filter), and, where the parametric alignment
decides (``model="parametric"`` or ``route="aligned"``), ``ill_conditioned`` (seen nearly
frontally: its global translation is ill-conditioned, its features are flagged
``filtered_out``) or ``alignment_failed``. The ``alignment`` column keeps the parametric
alignment's verdict on every route.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from blurcalib.calib.capture import CaptureCheck, CaptureSettings, check_capture
from blurcalib.calib.joint import (
    INTRINSICS_FILE,
    GenericCalibration,
    generic_report,
    save_generic_calibration,
)
from blurcalib.calib.sequence import (
    BlurryFrame,
    BlurryOutcome,
    CalibrationRun,
    SequenceSettings,
    calibrate_features,
)
from blurcalib.calib.sharp import CalibrationError, save_calibration
from blurcalib.calib.trust import save_trust
from blurcalib.calib.undistortion import (
    UNDISTORTION_FILE,
    undistortion_output,
    undistortion_report,
    write_undistortion_map,
)
from blurcalib.camera.family import as_family
from blurcalib.camera.files import write_generic_yaml
from blurcalib.extract.duplicates import mark_duplicates
from blurcalib.extract.frame import ExtractSettings
from blurcalib.io.atomic import (
    atomic_write_json,
    claim_output_dir,
    ensure_writable_dir,
    write_run_manifest,
)
from blurcalib.io.feature_input import FeatureInputError, read_feature_input
from blurcalib.io.frames import frame_size, frame_size_problem
from blurcalib.io.record import FrameRecord, FrameStatus
from blurcalib.io.results import (
    FEATURES_FILE,
    BlockTable,
    FeatureFlags,
    FeatureTable,
    read_block_table,
    read_feature_table,
)
from blurcalib.io.sources import FrameInput
from blurcalib.pipeline.frames import (
    blurry_row,
    feature_file_inputs,
    sharp_row,
    status_counts,
)
from blurcalib.pipeline.outputs import write_outputs
from blurcalib.runs.events import RunEvent
from blurcalib.runs.executors import ProcessPool
from blurcalib.runs.folder import extract_to_folder
from blurcalib.runs.runtime import compute_threads
from blurcalib.target.pattern import StarPattern

Table = TypeVar("Table", FeatureTable, BlockTable)
KINDS: tuple[str, ...] = ("sharp", "blurry")
"""The run's extractions, each an ``extract`` output folder ``OUT/<kind>/`` of its own."""
MIXED = "frames"
"""``OUT/frames/``: the extraction of frames whose kind each frame's measured blur decides."""

REPORT_FILE = "report.json"
CALIBRATION_DIR = "calibration"
STAGING_DIR = ".staging"
"""Where the top-level outputs are written before :func:`_publish` moves them into place."""
SHARP_ONLY_DIR = "sharp_only"
"""``OUT/calibration/sharp_only/intrinsics0.yaml``: the generic camera of the sharp frames alone."""
GLOBAL_SHUTTER_DIR = "global_shutter"
"""``OUT/calibration/global_shutter/intrinsics0.yaml``: with the rolling-shutter model applied, the
generic camera of the same features without it."""
PUBLISHED: tuple[str, ...] = ("features.csv", "features.bin", "frames.csv",
                              "error_directions_blurry.png", "error_directions_sharp.png",
                              "error_directions_generic.png", "frame_errors.png", CALIBRATION_DIR,
                              REPORT_FILE)
"""The top-level output set of a run, published together (``report.json`` last)."""


class PipelineError(RuntimeError):
    """Nothing useful can be produced; the message says which frames and which step."""


@dataclass(frozen=True)
class PipelineSettings:
    """Settings of :func:`run_pipeline`.

    Attributes:
        extraction: how blurry frames are extracted (PSF window, the growth's final fit and
            path-PSF field, local alignment), and mixed frames (``run_pipeline(mixed=...)``),
            classified sharp below its ``sharp_below_px``; sharp frames get
            :meth:`blurcalib.extract.frame.ExtractSettings.sharp` with these deconvolution
            settings (the torch device).
        calibration: the calibration sequence: block filter, global alignment, camera model,
            generic fit, lens-bias correction and assessment.
        capture: when a degenerate capture (face-on frames, one orientation, few frames, one
            part of the image) is refused or warned about (:mod:`blurcalib.calib.capture`).
        workers: frames extracted in parallel; the calibration computes with as many threads.
        cluster: a Dask scheduler address; frames are extracted as tasks there (``docs/cluster.md``).
    """

    extraction: ExtractSettings = field(default_factory=ExtractSettings)
    calibration: SequenceSettings = field(default_factory=SequenceSettings)
    capture: CaptureSettings = field(default_factory=CaptureSettings)
    workers: int = 1
    cluster: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The settings that decide the results (``report.json``'s ``settings``): all but
        ``workers`` and ``cluster``."""
        return {k: v for k, v in asdict(self).items() if k not in ("workers", "cluster")}


@dataclass
class PipelineReport:
    """What :func:`run_pipeline` did (also written as ``report.json``): ``calibration`` the
    parametric (sharp-set) camera and its errors, ``frames`` one row per input frame (see the
    module docstring), ``counts`` frames per status of each kind (``{"sharp": {...}, "blurry":
    {...}}``), ``generic`` the generic fit (:func:`blurcalib.calib.joint.generic_report`: grid, median
    and RMS reprojection error in px, frames, coverage warnings; None for ``model="parametric"``),
    ``generic_sharp`` the same for the sharp frames alone, ``undistortion`` the undistortion map's
    projection and parameters (:func:`blurcalib.calib.undistortion.undistortion_report`; the
    parametric camera's without a generic camera), ``trust`` the assessment
    (:meth:`blurcalib.calib.trust.Trust.to_dict`), ``rolling_shutter`` the rolling-shutter step
    (:meth:`blurcalib.calib.rolling_shutter.RollingShutterResult.to_dict`: readout ratio, its
    standard error, each moving frame's blur velocity), ``capture`` the capture check
    (:meth:`blurcalib.calib.capture.CaptureCheck.to_dict`: its figures and warnings),
    ``parametric_choice`` the held-out scores of the parametric models with ``parametric="auto"``
    (:meth:`blurcalib.calib.model_choice.ModelChoice.to_dict`), ``generic_failure`` why the
    generic camera could not be fitted (what the capture lacks; the parametric calibration and
    the features are written all the same), else "", ``assessment_failure`` why the generic
    camera (or the sharp-only one) has no assessment, else "", and ``patterns`` the cross-pattern
    check of a calibration from several patterns (:mod:`blurcalib.pipeline.patterns`), else None.
    ``camera`` is the generic calibration itself (:class:`blurcalib.calib.joint.GenericCalibration`:
    the camera, its frames' poses and observations; None without a generic camera), not written
    to ``report.json``."""

    calibration: dict[str, Any]
    frames: list[FrameRecord]
    outputs: dict[str, str]
    counts: dict[str, dict[str, int]]
    settings: dict[str, Any]
    generic: dict[str, Any] | None = None
    generic_sharp: dict[str, Any] | None = None
    undistortion: dict[str, Any] | None = None
    trust: dict[str, Any] | None = None
    rolling_shutter: dict[str, Any] | None = None
    capture: dict[str, Any] | None = None
    parametric_choice: dict[str, Any] | None = None
    generic_failure: str = ""
    assessment_failure: str = ""
    seconds: dict[str, float] = field(default_factory=dict)
    patterns: dict[str, Any] | None = None
    camera: GenericCalibration | None = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """The ``report.json`` document: the fields, with ``trust``'s sections (``validation``,
        ``uncertainty``, ``cross_validation``, ``guidance``, ``blurry_frames_gain``) at the top."""
        out = {**{k: v for k, v in vars(self).items() if k not in ("frames", "camera")},
               "frames": [r.to_row() for r in self.frames]}
        trust = dict(out.pop("trust") or {})
        out["seconds"] = {**out["seconds"], **trust.pop("seconds", {})}
        out.update(trust)
        return out


@dataclass(frozen=True)
class _Extracted:
    """The extraction stage's outcome: each kind's frame records (names as in the run's
    outputs), the features, and the sharp and blurry frames' blocks."""

    rows: dict[str, list[FrameRecord]]
    features: FeatureTable
    sharp_blocks: BlockTable
    blocks: BlockTable


def _usable_size(frame: Path | FrameInput) -> tuple[int, int] | None:
    """A frame's size, or None when it cannot be processed (extraction records it as
    unreadable)."""
    size = frame.size() if isinstance(frame, FrameInput) else frame_size(frame)
    return None if size is None or frame_size_problem(*size) else size


def _check_sizes(sharp: Sequence[Path | FrameInput], blurry: Sequence[Path | FrameInput],
                 what: str = "sharp frames") -> tuple[int, int]:
    """The run's image size: the most common among ``sharp`` (``what`` names them); frames of
    another size are refused."""
    sizes = [_usable_size(p) for p in sharp]
    known = [s for s in sizes if s is not None]
    if not known:
        raise PipelineError(f"none of the {what} can be read")
    size = max(set(known), key=known.count)
    other = [(p, s) for p, s in zip(list(sharp) + list(blurry),
                                    sizes + [_usable_size(p) for p in blurry], strict=True)
             if s is not None and s != size]
    if other:
        listed = ", ".join(f"{p} ({s[0]}x{s[1]})" for p, s in other[:5])
        more = f" and {len(other) - 5} more" if len(other) > 5 else ""
        raise PipelineError(f"frames of another resolution than the run's {size[0]}x{size[1]}: "
                            f"{listed}{more}")
    return size


def run_pipeline(sharp: Sequence[Path], blurry: Sequence[Path], pattern: StarPattern,
                 out_dir: str | os.PathLike[str], settings: PipelineSettings | None = None,
                 progress: Callable[[str, RunEvent], None] | None = None,
                 overwrite: bool = False, mixed: Sequence[FrameInput] = (),
                 on_stage: Callable[[str], None] | None = None) -> PipelineReport:
    """Run the whole pipeline (see the module docstring); partial results are kept on error.

    The top-level outputs (:data:`PUBLISHED`) are written into a staging folder and moved into
    ``out_dir`` together, ``report.json`` last: a reader that finds ``report.json`` sees the
    whole output set of one run, never a mixture of two.

    Args:
        sharp, blurry: frame files.
        pattern: the target.
        mixed: frames (folders, images, video frames: :func:`blurcalib.io.sources.frame_inputs`)
            each classified sharp or blurry by its own measured blur
            (:attr:`blurcalib.extract.frame.ExtractSettings.sharp_below_px`), extracted into
            ``OUT/frames/``; given instead of ``sharp`` and ``blurry``.
        out_dir: output folder (re-running resumes the extraction).
        settings: pipeline settings.
        progress: ``progress(stage, event)`` during extraction (``sharp``, ``blurry`` or ``frames``
            and a :mod:`blurcalib.runs.events` event).
        overwrite: write into a non-empty folder that is not a ``calibrate`` output
            (:func:`blurcalib.io.atomic.claim_output_dir`).
        on_stage: called with each calibration stage's name as it starts
            (:class:`blurcalib.calib.sequence.Stage`).
    Raises:
        PipelineError: unusable input (no readable sharp frame, mixed resolutions, too few
            usable sharp frames, no tag found in any frame, no blurry frame surviving).
        OutputError: the folder holds something else (without ``overwrite``) or cannot be
            written.
    """
    t_start = time.perf_counter()
    s = settings or PipelineSettings()
    if mixed and (sharp or blurry):
        raise ValueError("give either mixed frames or sharp and blurry frames")
    size = _check_sizes(mixed, [], "frames") if mixed else _check_sizes(sharp, blurry)
    manifest = asdict(s)
    out = claim_output_dir(out_dir, "calibrate", manifest, overwrite, extractions=(*KINDS, MIXED))
    shutil.rmtree(out / STAGING_DIR, ignore_errors=True)  # left by a run killed while writing
    ex = _extract(sharp, blurry, mixed, pattern, out, size, s, progress, overwrite)
    t_extracted = time.perf_counter()
    if not any(r.status is FrameStatus.OK for r in ex.rows["sharp"] + ex.rows["blurry"]):
        raise PipelineError("no AprilTag of the pattern was found in any frame: does the pattern "
                            "YAML match the target in the frames?")
    marked = mark_duplicates(ex.rows["sharp"] + ex.rows["blurry"], ex.features)
    sharp_rows, blurry_rows = marked[:len(ex.rows["sharp"])], marked[len(ex.rows["sharp"]):]
    duplicates = [r.frame for r in marked if r.status is FrameStatus.DUPLICATE]
    sharp_features = ex.features.select(((ex.features.flags & int(FeatureFlags.SHARP_FRAME)) != 0)
                                        & ~np.isin(ex.features.frame, sorted(duplicates)))
    flags = int(FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME)
    if s.extraction.local_alignment:
        flags |= FeatureFlags.LOCALLY_ALIGNED
    frames = [BlurryFrame(r.frame, blocks=ex.blocks.select(ex.blocks.frame == r.frame), flags=flags)
              for r in blurry_rows if r.status is FrameStatus.OK]
    blurry_features = ex.features.select(((ex.features.flags & int(FeatureFlags.BLURRY_FRAME)) != 0)
                                         & ~np.isin(ex.features.frame, sorted(duplicates)))
    capture = _check_capture(sharp_features, blurry_features, size, s, "")
    try:
        with compute_threads(_calibration_threads(s)):
            announce = None if on_stage is None else lambda st: on_stage(st.value) or True
            run = calibrate_features(sharp_features, ex.sharp_blocks, frames, pattern, size, s.calibration,
                                     on_stage=announce)
    except CalibrationError as exc:
        raise PipelineError(f"sharp-set calibration: {exc}{_left_out(sharp_rows)}") from None
    except ValueError as exc:
        raise PipelineError(f"generic calibration: {exc}") from None
    outcomes = {o.frame.name: o for o in run.blurry}
    rows = _rows(sharp_rows, blurry_rows, outcomes, run, s.calibration)
    seconds = {"extraction": t_extracted - t_start, **_calibration_seconds(run)}
    report = _publish_run(out, pattern, size, s, rows, run, seconds, capture, manifest)
    if blurry_rows and not any(r.used for r in rows if r.kind == "blurry"):
        raise PipelineError(f"no blurry frame survived the filters ({report.counts['blurry']}); the "
                            f"sharp-set calibration and all features are kept in {out}")
    return report


def _extract(sharp: Sequence[Path], blurry: Sequence[Path], mixed: Sequence[FrameInput], pattern: StarPattern,
             out: Path, size: tuple[int, int], s: PipelineSettings,
             progress: Callable[[str, RunEvent], None] | None, overwrite: bool) -> _Extracted:
    """Step 1: extract the frames (resumable) into ``OUT/sharp/`` and ``OUT/blurry/``, or the
    mixed frames into ``OUT/frames/``, and read the results back."""
    def stage(name: str) -> Callable[[RunEvent], None] | None:
        if progress is None:
            return None
        return lambda event: progress(name, event)

    pool = ProcessPool(s.workers)  # the sharp and blurry folders share the worker processes

    def extract(frames: Sequence[Any], folder: str, settings: ExtractSettings) -> list[FrameRecord]:
        done = extract_to_folder(frames, pattern, out / folder, settings, workers=s.workers,
                                 progress=stage(folder), expected_size=size, overwrite=overwrite,
                                 cluster=s.cluster, pool=pool)
        return [replace(r, frame=f"{folder}/{r.frame}") for r in done.records]

    with pool:
        if mixed:
            rows = extract(mixed, MIXED, replace(s.extraction, kind="auto"))
        else:
            by_kind = {"sharp": extract(sharp, "sharp", ExtractSettings.sharp(deconv=s.extraction.deconv)),
                       "blurry": extract(blurry, "blurry", s.extraction)}
    if mixed:
        features = _with_kind(read_feature_table(out / MIXED / FEATURES_FILE), MIXED)
        blocks = _with_kind(read_block_table(out / MIXED), MIXED)
        sharp_names = [r.frame for r in rows if r.kind == "sharp"]
        is_sharp = np.isin(blocks.frame, sharp_names)
        return _Extracted({"sharp": [r for r in rows if r.kind == "sharp"],
                           "blurry": [r for r in rows if r.kind != "sharp"]},
                          features, blocks.select(is_sharp), blocks.select(~is_sharp))
    features = FeatureTable.concat([_with_kind(read_feature_table(out / kind / FEATURES_FILE), kind)
                                    for kind in KINDS])
    return _Extracted(by_kind, features, _with_kind(read_block_table(out / "sharp"), "sharp"),
                      _with_kind(read_block_table(out / "blurry"), "blurry"))


def _rows(sharp: list[FrameRecord], blurry: list[FrameRecord], outcomes: Mapping[str, BlurryOutcome | None],
          run: CalibrationRun, s: SequenceSettings) -> list[FrameRecord]:
    """Every frame's row, sharp frames first, each decided once from what the run made of it."""
    velocity = None if run.rolling_shutter is None else run.rolling_shutter.velocity_px
    return ([sharp_row(r, run.calibration, run.generic) for r in sharp]
            + [blurry_row(r, outcomes.get(r.frame), s, velocity) for r in blurry])


def _left_out(sharp: list[FrameRecord]) -> str:
    """The clause of a sharp-set calibration's error naming the sharp frames that did not enter it
    (their status: ``duplicate``, an extraction's), or ``""``."""
    bad = [f"{r.frame} ({r.status.value})" for r in sharp if r.status is not FrameStatus.OK]
    more = f" and {len(bad) - 10} more" if len(bad) > 10 else ""
    return f"; sharp frames left out: {', '.join(bad[:10])}{more}" if bad else ""


def _check_capture(sharp: FeatureTable, blurry: FeatureTable, size: tuple[int, int], s: PipelineSettings,
                   where: str) -> CaptureCheck:
    """The capture check (:func:`blurcalib.calib.capture.check_capture`) of the distinct views the
    parametric camera will be calibrated from: the sharp frames, with the blurry ones where they
    join them (``blurry_in_parametric`` and too few sharp frames), before any calibration; ``where``
    prefixes its refusal (a feature file's ``"PATH: "``).

    Raises:
        PipelineError: a degenerate capture, in one line.
    """
    c = s.calibration
    table, what, least = sharp, "sharp frames", c.min_sharp_features
    if c.blurry_in_parametric and len(blurry) and len(np.unique(sharp.frame)) < c.min_sharp_frames:
        table, what = FeatureTable.concat([sharp, blurry]), "sharp and blurry frames"
        least = c.alignment.min_blocks
    check = check_capture(table, size, what, least, s.capture)
    if check.refusal is not None:
        raise PipelineError(f"{where}{check.refusal}")
    return check


def _calibration_threads(s: PipelineSettings) -> int:
    """Compute threads of the calibration: one per worker (it runs once the workers are done,
    :mod:`blurcalib.runs.runtime`), or this process's own when it has more."""
    import torch

    return max(s.workers, torch.get_num_threads())


def _calibration_seconds(run: CalibrationRun) -> dict[str, float]:
    """The report's ``calibration`` (parametric camera, alignment, generic cameras) and
    ``assessment`` wall times (s)."""
    seconds = {"calibration": run.seconds["parametric"] + run.seconds.get("generic", 0.0)}
    if "assessment" in run.seconds:
        seconds["assessment"] = run.seconds["assessment"]
    return seconds


def run_from_features(path: str | os.PathLike[str], pattern: StarPattern, out_dir: str | os.PathLike[str],
                      settings: PipelineSettings | None = None, image_size: tuple[int, int] | None = None,
                      overwrite: bool = False) -> PipelineReport:
    """Calibrate from an existing feature file instead of images
    (:func:`blurcalib.io.feature_input.read_feature_input`; :func:`run_from_table`).

    Raises:
        PipelineError: unusable input (see :func:`blurcalib.io.feature_input.read_feature_input`
            and :func:`run_from_table`).
        OutputError: as :func:`run_pipeline`.
    """
    s = settings or PipelineSettings()
    check_feature_route(s)
    try:
        table, size = read_feature_input(path, pattern, image_size)
    except FeatureInputError as exc:
        raise PipelineError(str(exc)) from None
    source = {"features": str(Path(path).resolve())}
    return run_from_table(table, size, pattern, out_dir, s, overwrite, source, f"{path}: ")


def check_feature_route(s: PipelineSettings) -> None:
    """Refuse the aligned route for features without blocks."""
    if s.calibration.generic.route != "joint":
        raise PipelineError("calibrating from features needs the joint route (the aligned route aligns "
                            "blocks to the parametric camera): use --route joint")


def run_from_table(table: FeatureTable, size: tuple[int, int], pattern: StarPattern,
                   out_dir: str | os.PathLike[str], s: PipelineSettings, overwrite: bool,
                   source: dict[str, Any], where: str,
                   patterns: Callable[[CalibrationRun], dict[str, Any]] | None = None) -> PipelineReport:
    """Calibrate from features (read and checked): the parametric camera on the sharp frames, then
    the generic cameras, their assessment and the same outputs as :func:`run_pipeline`. Blurry
    frames enter the generic fit on the joint route (a free shift each); without blocks there is
    no lens-bias correction (a blurcalib ``features.csv`` is already corrected) and no parametric
    alignment. ``source``: what the run manifest names as the input; ``where`` prefixes a refusal;
    ``patterns``: the cross-pattern check of the run, kept as ``report.json``'s ``patterns``.

    Raises:
        PipelineError: too few sharp frames, or a generic fit that cannot be made.
        OutputError: as :func:`run_pipeline`.
    """
    inputs = feature_file_inputs(table, s.calibration.model != "parametric")
    capture = _check_capture(inputs.sharp, inputs.blurry, size, s, where)
    manifest = {**asdict(s), **source}
    out = claim_output_dir(out_dir, "calibrate", manifest, overwrite)
    shutil.rmtree(out / STAGING_DIR, ignore_errors=True)
    try:
        with compute_threads(_calibration_threads(s)):
            run = calibrate_features(inputs.sharp, None, inputs.frames, pattern, size, s.calibration)
            checked = None if patterns is None else patterns(run)
    except CalibrationError as exc:
        left = _left_out(inputs.sharp_rows)
        raise PipelineError(f"sharp-set calibration from {where}{exc}{left}") from None
    except ValueError as exc:
        raise PipelineError(f"generic calibration: {exc}") from None
    outcomes: dict[str, BlurryOutcome | None] = {o.frame.name: o for o in run.blurry}
    rows = _rows(inputs.sharp_rows, inputs.blurry_rows, outcomes, run, s.calibration)
    return _publish_run(out, pattern, size, s, rows, run, _calibration_seconds(run), capture, manifest,
                        checked)


def _publish_run(out: Path, pattern: StarPattern, size: tuple[int, int], s: PipelineSettings,
                 rows: list[FrameRecord], run: CalibrationRun, seconds: dict[str, float],
                 capture: CaptureCheck, manifest: dict[str, Any], patterns: dict[str, Any] | None = None
                 ) -> PipelineReport:
    """Write the run's output set into ``OUT/.staging`` and publish it (:func:`_publish`) with the
    run manifest naming ``manifest`` (the run's settings); a failed write (a full disk) removes the
    staging folder and leaves the earlier outputs, and the manifest naming their settings, as they
    were.

    A failed assessment is written as ``report.json``'s ``assessment_failure``.
    """
    staging = out / STAGING_DIR
    try:
        report = _stage_run(out, staging, pattern, size, s, rows, run, seconds, capture, patterns)
    except OSError:  # OutputError too
        shutil.rmtree(staging, ignore_errors=True)
        raise
    _publish(staging, out, manifest)
    return report


def _stage_run(out: Path, staging: Path, pattern: StarPattern, size: tuple[int, int], s: PipelineSettings,
               rows: list[FrameRecord], run: CalibrationRun, seconds: dict[str, float],
               capture: CaptureCheck, patterns: dict[str, Any] | None = None) -> PipelineReport:
    """Write the run's output set into ``staging``; ``report.json`` last."""
    calibration, generic = run.calibration, run.generic
    ensure_writable_dir(staging)
    save_calibration(staging / CALIBRATION_DIR, calibration)
    trust_files: dict[str, Path] = {}
    undistort = s.calibration.generic.undistort
    if generic is not None:
        output = undistortion_output(generic.model, generic.parametric, undistort)
        save_generic_calibration(staging / CALIBRATION_DIR, generic, undistort=output)
        undistortion = undistortion_report(generic.model, output)
    else:
        camera = as_family(calibration.camera)
        output = undistortion_output(camera, calibration.camera, undistort)
        write_undistortion_map(staging / CALIBRATION_DIR / UNDISTORTION_FILE, camera, output)
        undistortion = undistortion_report(camera, output)
    if run.generic_sharp is not None:
        write_generic_yaml(ensure_writable_dir(staging / CALIBRATION_DIR / SHARP_ONLY_DIR) / INTRINSICS_FILE,
                           run.generic_sharp.model)
    if run.rolling_shutter is not None and run.rolling_shutter.global_shutter is not None:
        folder = ensure_writable_dir(staging / CALIBRATION_DIR / GLOBAL_SHUTTER_DIR)
        write_generic_yaml(folder / INTRINSICS_FILE, run.rolling_shutter.global_shutter.model)
    if run.trust is not None:
        trust_files = save_trust(staging / CALIBRATION_DIR, run.trust, size)
    staged = write_outputs(staging, pattern, size, rows, run)
    staged.update(trust_files)
    outputs = {k: out / p.relative_to(staging) for k, p in staged.items()}
    report = PipelineReport(calibration={k: v for k, v in calibration.to_dict().items()
                                         if k in ("model", "camera", "median_error_px", "rms_error_px",
                                                  "num_frames", "num_observations")},
                            frames=rows, outputs={k: str(v) for k, v in outputs.items()},
                            counts=status_counts(rows), settings=s.to_dict(),
                            generic=None if generic is None else generic_report(generic),
                            generic_sharp=None if run.generic_sharp is None
                            else generic_report(run.generic_sharp), undistortion=undistortion,
                            trust=None if run.trust is None else run.trust.to_dict(),
                            rolling_shutter=None if run.rolling_shutter is None
                            else run.rolling_shutter.to_dict(), capture=capture.to_dict(),
                            parametric_choice=None if run.choice is None else run.choice.to_dict(),
                            generic_failure=run.generic_failure,
                            assessment_failure=run.trust_failure or run.sharp_failure, patterns=patterns,
                            seconds={k: round(v, 2) for k, v in seconds.items()}, camera=generic)
    atomic_write_json(staging / REPORT_FILE, report.to_dict(), indent=2, default=str)
    return report


def _with_kind(table: Table, folder: str) -> Table:
    """A table of ``OUT/<folder>/`` with its frames named as in the run's outputs,
    ``<folder>/<frame>``."""
    return replace(table, frame=np.char.add(f"{folder}/", table.frame))


def _publish(staging: Path, out: Path, manifest: dict[str, Any]) -> None:
    """Move the output set staged in ``staging`` into ``out``.

    ``report.json`` (the completion marker) is removed first, the run manifest is then rewritten
    with the run's settings ``manifest``, and ``report.json`` is moved in last; outputs of an
    earlier run that this run does not produce are removed, and the ``calibration`` folder is
    swapped whole. A run killed in between leaves no ``report.json``; the next run removes the
    staging folder and publishes again.
    """
    (out / REPORT_FILE).unlink(missing_ok=True)
    write_run_manifest(out, "calibrate", manifest)
    staged = {p.name: p for p in staging.iterdir()}
    for name in PUBLISHED:
        if name == REPORT_FILE:
            continue
        dest = out / name
        if dest.is_dir():
            os.replace(dest, staging / f".old-{name}")
        elif name not in staged:
            dest.unlink(missing_ok=True)
        if name in staged:
            os.replace(staged[name], dest)
    os.replace(staged[REPORT_FILE], out / REPORT_FILE)
    shutil.rmtree(staging)
