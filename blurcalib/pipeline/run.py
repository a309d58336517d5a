"""The whole calibration pipeline: extract, calibrate the sharp set, filter, align, fit the
generic camera to sharp and blurry frames together.

``run_pipeline`` is what ``blurcalib calibrate`` runs:

1. feature extraction of the sharp frames (small PSF window) and the blurry frames (a window
   that fits the blur), resumable, into ``OUT/sharp/`` and ``OUT/blurry/`` (or, for frames
   whose kind each frame's measured blur decides, ``mixed=``, into ``OUT/frames/``)
   (:mod:`blurcalib.extract.frame`), each an ``extract`` output with the frames named as ``blurcalib
   extract`` names them, so that earlier ``extract`` runs into these folders are reused; the
   run's own outputs name the frames ``sharp/<name>`` and ``blurry/<name>``;
2. Brown-Conrady calibration of the sharp set together with the target points
   (:mod:`blurcalib.calib.sharp`); every star centre, sharp and blurry, is then moved by minus the
   bias of its block homography under that camera's distortion (:mod:`blurcalib.calib.lens_bias`) and
   the sharp set calibrated again from the corrected features; saved in ``OUT/calibration/``;
3. per blurry frame, the optional blur pre-filter (off by default; the paper's 3.8 px is
   ``QualitySettings(min_sigma_major=3.8)``) and the BE / loss / connectivity filter on the saved
   block figures (:mod:`blurcalib.extract.quality`);
4. per blurry frame, global alignment of the kept blocks to the parametric camera
   (``eq:global_align``, :func:`blurcalib.calib.alignment.align_blocks`), with the orientation
   filter flagging frames seen nearly frontally;
5. with ``model="generic"`` (the default), the central generic camera (:mod:`blurcalib.calib.joint`)
   fitted by bundle adjustment to the sharp features and the blurry frames' star centres, each
   blurry frame with its own free image shift (the deconvolution's translational ambiguity), so
   frontal frames need no orientation filter (``route="joint"``); or, on the paper's route, to
   the globally aligned features held fixed (``route="aligned"``). Saved as the reference tool's
   ``OUT/calibration/intrinsics0.yaml`` with the poses, an undistortion map and report images;
6. with the generic model, the assessment (:mod:`blurcalib.calib.trust`): the generic camera of the
   sharp frames alone when blurry frames entered, the k-fold held-out error of every camera,
   the projection uncertainty, the cross-validation diff of two halves, and guidance
   (``docs/validation.md``);
7. outputs: ``OUT/features.csv`` (sharp features and aligned blurry features, flagged),
   ``OUT/features.bin`` (the reference tool's format, pixel-corner convention),
   ``OUT/frames.csv`` (per-frame status), ``OUT/report.json`` and figures (the
   reprojection-error direction images, per-frame errors).

Frame statuses (``frames.csv``, one row per input frame, sharp and blurry): ``used`` marks every
frame whose features enter the final calibration (a sharp frame: the sharp-set and generic
calibrations; a blurry frame: the generic fit, or with ``model="parametric"`` the global
alignment and ``features.bin``). Every other status comes with its reason: the extraction's own
(``not_seeded``, ``no_blocks``, ``unreadable``, ``wrong_size``, ``failed``), ``duplicate`` (the same
view as an earlier frame, which is kept: :mod:`blurcalib.extract.duplicates`; the minimum of usable sharp
frames counts distinct views), ``too_few_features`` (left out of a calibration), ``low_blur``
(the optional pre-filter), ``too_few_blocks`` (after the block filter), and, where the
parametric alignment decides (``model="parametric"`` or ``route="aligned"``), ``ill_conditioned``
(seen nearly frontally: its global translation is ill-conditioned, its features are flagged
``filtered_out``) or ``alignment_failed``. The ``alignment`` column keeps the parametric
alignment's verdict on every route.
"""

from __future__ import annotations

import math
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from blurcalib.calib.alignment import MIN_BLOCKS, AlignmentError, AlignmentSettings, align_blocks
from blurcalib.calib.joint import (
    INTRINSICS_FILE,
    GenericCalibration,
    JointSettings,
    calibrate_generic,
    generic_report,
    save_generic_calibration,
)
from blurcalib.calib.lens_bias import correct_blocks, correct_features
from blurcalib.calib.report import error_direction_image, save_frame_error_plot
from blurcalib.calib.sharp import Calibration, calibrate_sharp, save_calibration
from blurcalib.calib.trust import Trust, TrustSettings, assess_calibration, save_trust
from blurcalib.camera.files import write_generic_yaml
from blurcalib.camera.generic import DEFAULT_CELL_PX
from blurcalib.extract.duplicates import mark_duplicates
from blurcalib.extract.frame import SHARP_BELOW_PX, ExtractSettings, extract_to_folder
from blurcalib.extract.quality import QualitySettings, filter_frame
from blurcalib.growth.grow import FinalFitFrames, GrowSettings
from blurcalib.io.atomic import (
    atomic_path,
    atomic_write_csv,
    atomic_write_json,
    claim_output_dir,
    ensure_writable_dir,
)
from blurcalib.io.frames import frame_size, frame_size_problem
from blurcalib.io.refformat import to_ref_dataset, write_ref_dataset
from blurcalib.io.results import (
    BLUR_PER_SQUARE_LIMIT,
    FEATURES_FILE,
    BlockTable,
    FeatureFlags,
    FeatureTable,
    read_block_table,
    read_feature_table,
    write_features,
)
from blurcalib.io.sources import FrameInput
from blurcalib.io.text import count
from blurcalib.target.pattern import StarPattern

Table = TypeVar("Table", FeatureTable, BlockTable)
KINDS: tuple[str, ...] = ("sharp", "blurry")
"""The run's extractions, each an ``extract`` output folder ``OUT/<kind>/`` of its own."""
MIXED = "frames"
"""``OUT/frames/``: the extraction of frames whose kind each frame's measured blur decides."""
MODELS: tuple[str, ...] = ("generic", "parametric")
"""Camera models :func:`run_pipeline` delivers."""

REPORT_FILE = "report.json"
CALIBRATION_DIR = "calibration"
STAGING_DIR = ".staging"
SHARP_ONLY_DIR = "sharp_only"
"""``OUT/calibration/sharp_only/intrinsics0.yaml``: the generic camera of the sharp frames alone."""
"""Where the top-level outputs are written before :func:`_publish` moves them into place."""
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
        quality: the block filter and the blur pre-filter.
        loss: robust loss of the global alignment (``huber``, ``mean``, ``median``).
        bias: bias model of the global alignment (``translation``, ``bilinear``, ``quadrants``).
            ``translation`` by default: the features are PSF-centroid positions without the
            drift the paper's bilinear field compensates, and on simulated data the bilinear
            field also absorbs part of the true lens's non-parametric deviation (aligned
            blurry features 0.037 px against the true camera with ``translation``, 0.068 px
            with ``bilinear``; docs/pipeline.md).
        angle_threshold: frames whose optical axis is within this angle (rad) of the target
            normal are flagged (translation ill-conditioned).
        blurry_kernel: PSF window of blurry frames (px, odd).
        final_fit: which blurry frames get the growth's final fit over 1.5 x each block's square
            (:attr:`blurcalib.growth.grow.GrowSettings.final_fit_frames`): ``adaptive`` (default: those
            whose PSF window grew), ``all`` (more accurate features, about 1 s more per frame
            with little blur) or ``none``. Sharp frames never get it.
        psf_field: fit blurry frames whose blur is long with their field of motion-path PSFs
            (:attr:`blurcalib.growth.grow.GrowSettings.psf_field`; default on).
        local_alignment: use the local-alignment translations for blurry frames.
        workers: frames extracted in parallel.
        model: ``generic`` (default: the central generic camera fitted to sharp and blurry
            frames together, :mod:`blurcalib.calib.joint`) or ``parametric`` (Brown-Conrady only).
        route: how blurry frames enter the generic fit: ``joint`` (default: raw star centres,
            each frame's translational ambiguity a free shift in the bundle adjustment, no
            orientation filter) or ``aligned`` (the paper's route: globally aligned to the
            parametric camera, then held fixed; ill-conditioned frames left out). Measured on
            simulated data (``blurcalib experiment generic``, docs/generic.md): 0.005 px median
            error against the true camera for ``joint``, 0.14 px for ``aligned``.
        cell_px: the generic grid's cell length (px).
        lens_correction: move every star centre by minus the bias of its block homography
            under the sharp-set parametric camera's distortion (:mod:`blurcalib.calib.lens_bias`),
            then calibrate the parametric camera again from the corrected sharp features.
        cluster: a Dask scheduler address; frames are extracted as tasks there (``docs/cluster.md``).
        sharp_below_px: mixed frames (``run_pipeline(mixed=...)``) whose measured blur is below
            this are sharp (:attr:`blurcalib.extract.frame.ExtractSettings.sharp_below_px`).
        trust: the held-out validation, uncertainty and guidance of the generic camera
            (:mod:`blurcalib.calib.trust`).
    """

    quality: QualitySettings = field(default_factory=QualitySettings)
    loss: str = "huber"
    bias: str = "translation"
    angle_threshold: float = math.pi / 10
    blurry_kernel: int = 17
    final_fit: FinalFitFrames = "adaptive"
    psf_field: bool = True
    local_alignment: bool = False
    workers: int = 1
    model: str = "generic"
    route: str = "joint"
    cell_px: float = DEFAULT_CELL_PX
    lens_correction: bool = True
    cluster: str | None = None
    sharp_below_px: float = SHARP_BELOW_PX
    trust: TrustSettings = field(default_factory=TrustSettings)

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        JointSettings(cell_px=self.cell_px, route=self.route)  # validates both
        GrowSettings(final_fit_frames=self.final_fit)  # validates it


@dataclass
class PipelineReport:
    """What :func:`run_pipeline` did (also written as ``report.json``): ``calibration`` the
    parametric (sharp-set) camera and its errors, ``frames`` one row per input frame (see the
    module docstring), ``counts`` frames per status of each kind (``{"sharp": {...}, "blurry":
    {...}}``), ``generic`` the generic fit (:func:`blurcalib.calib.joint.generic_report`: grid, median
    and RMS reprojection error in px, frames, coverage warnings; None for ``model="parametric"``),
    ``generic_sharp`` the same for the sharp frames alone, ``trust`` the assessment
    (:meth:`blurcalib.calib.trust.Trust.to_dict`)."""

    calibration: dict
    frames: list[dict]
    outputs: dict[str, str]
    counts: dict[str, dict[str, int]]
    settings: dict
    generic: dict | None = None
    generic_sharp: dict | None = None
    trust: dict | None = None
    seconds: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The ``report.json`` document: the fields, with ``trust``'s sections (``validation``,
        ``uncertainty``, ``cross_validation``, ``guidance``, ``blurry_frames_gain``) at the top."""
        out = asdict(self)
        trust = out.pop("trust") or {}
        out["seconds"] = {**out["seconds"], **trust.pop("seconds", {})}
        out.update(trust)
        return out


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
                 out_dir: str | os.PathLike, settings: PipelineSettings | None = None,
                 progress: Callable[[str, int, int, dict], None] | None = None,
                 overwrite: bool = False, mixed: Sequence[FrameInput] = ()) -> PipelineReport:
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
        progress: ``progress(stage, done, total, row)`` during extraction.
        overwrite: write into a non-empty folder that is not a ``calibrate`` output
            (:func:`blurcalib.io.atomic.claim_output_dir`).
    Raises:
        PipelineError: unusable input (no readable sharp frame, mixed resolutions, too few
            usable sharp frames, no tag found in any frame, no blurry frame surviving).
        OutputError: the folder holds something else (without ``overwrite``) or cannot be
            written.
    """
    from blurcalib.calib.sharp import CalibrationError
    from blurcalib.deconv.blocks import DeconvSettings

    t_start = time.perf_counter()
    s = settings or PipelineSettings()
    if mixed and (sharp or blurry):
        raise ValueError("give either mixed frames or sharp and blurry frames")
    size = _check_sizes(mixed, [], "frames") if mixed else _check_sizes(sharp, blurry)
    out = claim_output_dir(out_dir, "calibrate", asdict(s), overwrite, extractions=(*KINDS, MIXED))
    staging = out / STAGING_DIR
    shutil.rmtree(staging, ignore_errors=True)  # left by a run killed while writing

    def stage(name: str) -> Callable[[int, int, dict], None] | None:
        if progress is None:
            return None
        return lambda done, total, row: progress(name, done, total, row)

    blurry_settings = ExtractSettings(deconv=DeconvSettings(kernel_size=s.blurry_kernel),
                                      grow=GrowSettings(final_fit_frames=s.final_fit, psf_field=s.psf_field),
                                      local_alignment=s.local_alignment)
    if mixed:
        auto = replace(blurry_settings, kind="auto", sharp_below_px=s.sharp_below_px)
        run = extract_to_folder(mixed, pattern, out / MIXED, auto, workers=s.workers,
                                progress=stage("frames"), expected_size=size, overwrite=overwrite,
                                cluster=s.cluster)
        rows = [{**r, "frame": f"{MIXED}/{r['frame']}"} for r in run.frames]
        extracted = {"sharp": [r for r in rows if r.get("kind") == "sharp"],
                     "blurry": [r for r in rows if r.get("kind") != "sharp"]}
        features = _with_kind(read_feature_table(out / MIXED / FEATURES_FILE), MIXED)
        all_blocks = _with_kind(read_block_table(out / MIXED), MIXED)
        is_sharp = np.isin(all_blocks.frame, [r["frame"] for r in extracted["sharp"]])
        sharp_blocks, blocks = all_blocks.select(is_sharp), all_blocks.select(~is_sharp)
    else:
        runs = {kind: extract_to_folder(paths, pattern, out / kind, settings, workers=s.workers,
                                        progress=stage(kind), expected_size=size, overwrite=overwrite,
                                        cluster=s.cluster)
                for kind, paths, settings in (("sharp", sharp, ExtractSettings.sharp()),
                                              ("blurry", blurry, blurry_settings))}
        extracted = {kind: [{**r, "frame": f"{kind}/{r['frame']}"} for r in run.frames]
                     for kind, run in runs.items()}
        features = FeatureTable.concat([_with_kind(read_feature_table(out / kind / FEATURES_FILE), kind)
                                        for kind in KINDS])
        sharp_blocks = _with_kind(read_block_table(out / "sharp"), "sharp")
        blocks = _with_kind(read_block_table(out / "blurry"), "blurry")
    t_extracted = time.perf_counter()
    seeded = [r for r in extracted["sharp"] + extracted["blurry"] if r["status"] != "not_seeded"]
    if not any(r["status"] == "ok" for r in seeded):
        raise PipelineError("no AprilTag of the pattern was found in any frame: does the pattern "
                            "YAML match the target in the frames?")
    duplicates = mark_duplicates(extracted["sharp"] + extracted["blurry"], features)
    sharp_features = features.select(((features.flags & int(FeatureFlags.SHARP_FRAME)) != 0)
                                     & ~np.isin(features.frame, sorted(duplicates)))
    try:
        calibration = calibrate_sharp(sharp_features, pattern, size)
        if s.lens_correction:
            sharp_features = correct_features(sharp_features, sharp_blocks, calibration.camera)
            calibration = calibrate_sharp(sharp_features, pattern, size)
    except CalibrationError as exc:
        bad = [f"{r['frame']} ({r['status']})" for r in extracted["sharp"] if r["status"] != "ok"]
        hint = f"; sharp frames without features: {', '.join(bad[:10])}" if bad else ""
        raise PipelineError(f"sharp-set calibration: {exc}{hint}") from None

    sharp_rows = [_sharp_row(r, calibration) for r in extracted["sharp"]]
    left_out = np.isin(sharp_features.frame, [r["frame"] for r in sharp_rows
                                              if r["status"] != "used"])
    sharp_features.flags[left_out] |= int(FeatureFlags.FILTERED_OUT)
    if s.lens_correction:
        blocks = correct_blocks(blocks, calibration.camera)
    blurry_frames = [_align_frame(r, blocks, pattern, calibration, size, s) for r in extracted["blurry"]]
    t_aligned = time.perf_counter()
    run = _calibrate_cameras(sharp_features, blurry_frames, sharp_rows, calibration, pattern, size, s)
    run.seconds.update(extraction=t_extracted - t_start,
                       calibration=t_aligned - t_extracted + run.seconds.pop("generic", 0.0))
    report = _publish_run(out, pattern, size, s, sharp_features, blurry_frames, sharp_rows, run)
    usable = [f for f in blurry_frames if f.row["status"] == "used"]
    if extracted["blurry"] and not usable:
        raise PipelineError(f"no blurry frame survived the filters ({report.counts['blurry']}); the "
                            f"sharp-set calibration and all features are kept in {out}")
    return report



def read_feature_input(path: str | os.PathLike, pattern: StarPattern,
                       image_size: tuple[int, int] | None = None) -> tuple[FeatureTable, tuple[int, int]]:
    """Features to calibrate from, and the image size: the reference tool's dataset ``.bin``
    (pixel-corner convention on disk; every frame sharp) or blurcalib's ``features.csv`` (rows
    flagged ``BLURRY_FRAME`` are blurry frames, those flagged ``FILTERED_OUT`` are left out; the
    size must be given, the file does not hold it).

    Raises:
        PipelineError: an unknown suffix, an unreadable or malformed file, or a ``features.csv``
            without ``image_size``.
    """
    from blurcalib.io.refformat import RefFormatError, read_ref_dataset, ref_feature_table
    from blurcalib.io.results import ResultsFileError

    p = Path(path)
    try:
        if p.suffix.lower() == ".bin":
            dataset = read_ref_dataset(p)
            table = ref_feature_table(dataset, pattern)
            return table, image_size or dataset.image_size
        if p.suffix.lower() == ".csv":
            if image_size is None:
                raise PipelineError(f"{p}: a features.csv does not hold the image size: give "
                                    f"--image-size WxH")
            table = read_feature_table(p)
            table = table.select((table.flags & int(FeatureFlags.FILTERED_OUT)) == 0)
            if len(table) and int(table.feature_id.max()) >= pattern.num_features:
                raise PipelineError(f"{p}: feature id {int(table.feature_id.max())} is not one of the "
                                    f"pattern's {pattern.num_features} features")
            return table, image_size
    except (OSError, RefFormatError, ResultsFileError, ValueError) as exc:
        raise PipelineError(f"{p}: {exc}") from None
    raise PipelineError(f"{p}: features must be a reference dataset (.bin) or a blurcalib features.csv")


def run_from_features(path: str | os.PathLike, pattern: StarPattern, out_dir: str | os.PathLike,
                      settings: PipelineSettings | None = None, image_size: tuple[int, int] | None = None,
                      overwrite: bool = False) -> PipelineReport:
    """Calibrate from an existing feature file instead of images (:func:`read_feature_input`):
    the parametric camera on the sharp frames, then the generic cameras, their assessment and
    the same outputs as :func:`run_pipeline`. Blurry frames enter the generic fit on the joint
    route (a free shift each); without blocks there is no lens-bias correction (a blurcalib
    ``features.csv`` is already corrected) and no parametric alignment.

    Raises:
        PipelineError: unusable input (see :func:`read_feature_input`, too few sharp frames, or
            ``route="aligned"``, which needs the blocks).
        OutputError: as :func:`run_pipeline`.
    """
    from blurcalib.calib.sharp import CalibrationError

    s = settings or PipelineSettings()
    if s.route != "joint":
        raise PipelineError("calibrating from features needs the joint route (the aligned route aligns "
                            "blocks to the parametric camera): use --route joint")
    table, size = read_feature_input(path, pattern, image_size)
    out = claim_output_dir(out_dir, "calibrate", {**asdict(s), "features": str(Path(path).resolve())},
                           overwrite)
    shutil.rmtree(out / STAGING_DIR, ignore_errors=True)
    blurry_rows = (table.flags & int(FeatureFlags.BLURRY_FRAME)) != 0
    sharp_features = table.select(~blurry_rows)
    blurry_table = table.select(blurry_rows)
    t0 = time.perf_counter()
    try:
        calibration = calibrate_sharp(sharp_features, pattern, size)
    except CalibrationError as exc:
        raise PipelineError(f"sharp-set calibration from {path}: {exc}") from None
    t_parametric = time.perf_counter() - t0

    def counts(t: FeatureTable) -> dict[str, int]:
        names, n = np.unique(t.frame, return_counts=True)
        return dict(zip(names.tolist(), n.tolist(), strict=True))

    sharp_rows = [_sharp_row({"frame": f, "status": "ok", "features": n}, calibration)
                  for f, n in counts(sharp_features).items()]
    left_out = np.isin(sharp_features.frame, [r["frame"] for r in sharp_rows if r["status"] != "used"])
    sharp_features.flags[left_out] |= int(FeatureFlags.FILTERED_OUT)
    blurry_frames = []
    for f, n in counts(blurry_table).items():
        row = {"frame": f, "kind": "blurry", "extraction": "ok", "features": n}
        if s.model == "parametric":
            row.update(status="no_blocks", reason="a feature file holds no blocks to align to the "
                                                  "parametric camera (the generic model uses it)")
            blurry_frames.append(_BlurryFrame(row))
        else:
            blurry_frames.append(_BlurryFrame(row, raw=blurry_table.select(blurry_table.frame == f)))
    run = _calibrate_cameras(sharp_features, blurry_frames, sharp_rows, calibration, pattern, size, s)
    run.seconds["calibration"] = t_parametric + run.seconds.pop("generic", 0.0)
    return _publish_run(out, pattern, size, s, sharp_features, blurry_frames, sharp_rows, run)

@dataclass(eq=False)
class CalibrationRun:
    """The calibration stage's cameras and their assessment.

    Attributes:
        calibration: the parametric (sharp-set) calibration.
        generic: the generic camera of sharp and blurry frames (None for ``model="parametric"``).
        generic_sharp: the generic camera of the sharp frames alone, when blurry frames entered
            ``generic``.
        trust: held-out error, uncertainty, cross-validation diff and guidance
            (:mod:`blurcalib.calib.trust`), with ``generic``.
        seconds: wall time (s) of the stages: ``extraction``, ``calibration`` (parametric
            camera, alignment, generic cameras) and ``assessment`` (``trust``).
    """

    calibration: Calibration
    generic: GenericCalibration | None = None
    generic_sharp: GenericCalibration | None = None
    trust: Trust | None = None
    seconds: dict[str, float] = field(default_factory=dict)


def _calibrate_cameras(sharp_features: FeatureTable, blurry_frames: Sequence[_BlurryFrame],
                       sharp_rows: list[dict], calibration: Calibration, pattern: StarPattern,
                       size: tuple[int, int], s: PipelineSettings) -> CalibrationRun:
    """The generic cameras (sharp + blurry, and sharp alone when blurry frames entered) and their
    assessment; sets the frames' generic-fit statuses."""
    run = CalibrationRun(calibration)
    if s.model != "generic":
        return run
    t0 = time.perf_counter()
    run.generic = _fit_generic(sharp_features, blurry_frames, calibration, pattern, size, s)
    _generic_statuses(sharp_rows, blurry_frames, run.generic, s.route)
    if run.generic.blurry_frames:
        run.generic_sharp = _fit_generic(sharp_features, [], calibration, pattern, size, s)
    t1 = time.perf_counter()
    run.trust = assess_calibration(run.generic, run.generic_sharp, calibration, sharp_features, pattern,
                                   size, s.trust, JointSettings().bundle)
    run.seconds.update(generic=t1 - t0, assessment=time.perf_counter() - t1)
    return run


def _publish_run(out: Path, pattern: StarPattern, size: tuple[int, int], s: PipelineSettings,
                 sharp_features: FeatureTable, blurry_frames: Sequence[_BlurryFrame],
                 sharp_rows: list[dict], run: CalibrationRun) -> PipelineReport:
    """Write the run's output set into ``OUT/.staging`` and publish it (:func:`_publish`); a
    failed write (a full disk) removes the staging folder and leaves the earlier outputs as they
    were."""
    staging = out / STAGING_DIR
    try:
        report = _stage_run(out, staging, pattern, size, s, sharp_features, blurry_frames, sharp_rows, run)
    except OSError:  # OutputError too
        shutil.rmtree(staging, ignore_errors=True)
        raise
    _publish(staging, out)
    return report


def _stage_run(out: Path, staging: Path, pattern: StarPattern, size: tuple[int, int], s: PipelineSettings,
               sharp_features: FeatureTable, blurry_frames: Sequence[_BlurryFrame],
               sharp_rows: list[dict], run: CalibrationRun) -> PipelineReport:
    """Write the run's output set into ``staging``; ``report.json`` last."""
    calibration, generic = run.calibration, run.generic
    rows = sharp_rows + [f.row for f in blurry_frames]
    ensure_writable_dir(staging)
    save_calibration(staging / CALIBRATION_DIR, calibration)
    trust_files: dict[str, Path] = {}
    if generic is not None:
        save_generic_calibration(staging / CALIBRATION_DIR, generic)
    if run.generic_sharp is not None:
        write_generic_yaml(ensure_writable_dir(staging / CALIBRATION_DIR / SHARP_ONLY_DIR) / INTRINSICS_FILE,
                           run.generic_sharp.model)
    if run.trust is not None:
        trust_files = save_trust(staging / CALIBRATION_DIR, run.trust, size)
    staged = _write_outputs(staging, pattern, size, sharp_features, blurry_frames, rows, calibration,
                            generic)
    staged.update(trust_files)
    outputs = {k: out / p.relative_to(staging) for k, p in staged.items()}
    counts: dict[str, dict[str, int]] = {"sharp": {}, "blurry": {}}
    for r in rows:
        counts[r["kind"]][r["status"]] = counts[r["kind"]].get(r["status"], 0) + 1
    report = PipelineReport(calibration={k: v for k, v in calibration.to_dict().items()
                                         if k in ("camera", "median_error_px", "rms_error_px",
                                                  "num_frames", "num_observations")},
                            frames=rows, outputs={k: str(v) for k, v in outputs.items()},
                            counts=counts,
                            settings={k: v for k, v in asdict(s).items() if k not in ("workers", "cluster")},
                            generic=None if generic is None else generic_report(generic),
                            generic_sharp=None if run.generic_sharp is None
                            else generic_report(run.generic_sharp),
                            trust=None if run.trust is None else run.trust.to_dict(),
                            seconds={k: round(v, 2) for k, v in run.seconds.items()})
    atomic_write_json(staging / REPORT_FILE, report.to_dict(), indent=2, default=str)
    return report


def _with_kind(table: Table, folder: str) -> Table:
    """A table of ``OUT/<folder>/`` with its frames named as in the run's outputs,
    ``<folder>/<frame>``."""
    return replace(table, frame=np.char.add(f"{folder}/", table.frame))


def _extraction_row(extracted: dict, kind: str) -> dict:
    """The start of a frame's row from its extraction summary; not-ok extractions keep their
    status and message as the row's status and reason."""
    row = {"frame": extracted["frame"], "kind": kind, "blur_px": extracted.get("blur_px", ""),
           "noise_dn": extracted.get("noise_dn", ""),
           "extraction": extracted.get("status", ""),
           "seeded_by": extracted.get("seeded_by", ""), "psf": extracted.get("psf", ""),
           "features": extracted.get("features", 0)}
    if row["extraction"] != "ok":
        row["status"] = row["extraction"] or "failed"
        row["reason"] = extracted.get("message") or f"extraction ended with {row['status']!r}"
    return row


def _sharp_row(extracted: dict, calibration: Calibration) -> dict:
    """A sharp frame's row: ``used`` when it entered the sharp-set calibration."""
    row = _extraction_row(extracted, "sharp")
    if "status" in row:
        return row
    errors = calibration.frame_errors().get(row["frame"])
    if errors is None:
        row.update(status="too_few_features",
                   reason=f"{count(row['features'], 'feature')}: too few for the sharp-set calibration "
                           f"(its features are flagged filtered_out)")
    else:
        row.update(status="used", reason="",
                   calibration_median_error=round(errors["median_error_px"] or float("nan"), 4))
    return row


@dataclass(eq=False)
class _BlurryFrame:
    """One blurry frame through the filter and the parametric alignment.

    Attributes:
        row: its ``frames.csv`` row.
        raw: its kept blocks' star centres (None when too few blocks survive).
        aligned: the same features globally aligned to the parametric camera (flagged
            ``filtered_out`` when ill-conditioned; None when the alignment failed).
        residuals: ``(N, 2)`` px of the alignment.
    """

    row: dict
    raw: FeatureTable | None = None
    aligned: FeatureTable | None = None
    residuals: np.ndarray | None = None


def _blur_note(blocks: BlockTable) -> str:
    """Why a frame keeps few blocks when its blur is as long as its squares: ``""`` or a clause
    with the median :attr:`BlockTable.blur_per_square` of its fitted blocks."""
    ratio = blocks.blur_per_square
    ratio = ratio[np.isfinite(ratio)]
    if not ratio.size or np.median(ratio) < BLUR_PER_SQUARE_LIMIT:
        return ""
    return (f"; its blur is {np.median(ratio):.2f} x the star squares' side (median of its fitted "
            f"blocks), and from {BLUR_PER_SQUARE_LIMIT} few stars can be located: a closer view "
            f"(larger squares) or a shorter exposure helps")


def _align_frame(extracted: dict, blocks: BlockTable, pattern: StarPattern, calibration: Calibration,
                 size: tuple[int, int], s: PipelineSettings) -> _BlurryFrame:
    """Filter a blurry frame's blocks and align the kept ones to the parametric camera
    (:func:`blurcalib.calib.alignment.align_blocks`); the row's status is the parametric
    route's (``used``, ``ill_conditioned``, ``alignment_failed``, or why no block is kept)."""
    row = _extraction_row(extracted, "blurry")
    if "status" in row:
        return _BlurryFrame(row)
    b = blocks.select(blocks.frame == row["frame"])
    filt = filter_frame(b, size, s.quality)
    row.update(blocks=len(b), kept=int(filt.kept.sum()),
               centre_sigma_major=round(filt.centre_sigma_major, 3), filter_counts=filt.counts())
    if not filt.frame_ok:
        row["status"] = "low_blur"
        row["reason"] = (f"centre median sigma_major {filt.centre_sigma_major:.2f} px < "
                          f"{s.quality.min_sigma_major} px")
        return _BlurryFrame(row)
    if filt.kept.sum() < MIN_BLOCKS:
        row["status"] = "too_few_blocks"
        row["reason"] = (f"{count(int(filt.kept.sum()), 'block')} survive the BE/loss/connectivity filter, "
                          f"{MIN_BLOCKS} needed{_blur_note(b)}")
        return _BlurryFrame(row)
    kept = b.select(filt.kept)
    flags = FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME
    if s.local_alignment:
        flags |= FeatureFlags.LOCALLY_ALIGNED
    if s.lens_correction:
        flags |= FeatureFlags.LENS_CORRECTED
    raw = kept.features(pattern.square_length_m, flags)
    try:
        ga = align_blocks(calibration.camera, pattern, calibration.points, raw.feature_id,
                          np.stack([raw.x, raw.y], axis=1), kept.loss,
                          AlignmentSettings(loss=s.loss, bias=s.bias, angle_threshold=s.angle_threshold))
    except AlignmentError as exc:
        row.update(status="alignment_failed", reason=str(exc), alignment="failed")
        return _BlurryFrame(row, raw)
    flags |= FeatureFlags.GLOBALLY_ALIGNED
    if ga.ill_conditioned:
        flags |= FeatureFlags.FILTERED_OUT
    aligned = replace(raw, x=ga.corrected[:, 0], y=ga.corrected[:, 1],
                      flags=np.full(len(raw), int(flags), dtype=np.int64))
    row.update(status="ill_conditioned" if ga.ill_conditioned else "used", reason="",
               alignment="ill_conditioned" if ga.ill_conditioned else "ok",
               median_error=round(ga.median_error, 4), mean_error=round(ga.mean_error, 4),
               angle_deg=round(math.degrees(ga.angle_to_normal), 2),
               translation=[round(float(v), 4) for v in ga.translation])
    if ga.ill_conditioned:
        row["reason"] = (f"optical axis {math.degrees(ga.angle_to_normal):.1f} deg from the "
                          f"target normal: translation ill-conditioned, features flagged")
    return _BlurryFrame(row, raw, aligned, ga.residuals)


def _fit_generic(sharp_features: FeatureTable, frames: Sequence[_BlurryFrame], calibration: Calibration,
                 pattern: StarPattern, size: tuple[int, int], s: PipelineSettings) -> GenericCalibration:
    """The generic camera from the sharp features and the blurry frames of the route: the raw
    star centres of every frame with enough kept blocks (``joint``), or the aligned features of
    the well-conditioned frames (``aligned``)."""
    tables = [f.raw if s.route == "joint" else f.aligned for f in frames]
    tables = [t for t in tables if t is not None]
    try:
        return calibrate_generic(sharp_features, FeatureTable.concat(tables) if tables else None,
                                 calibration, pattern, size, JointSettings(cell_px=s.cell_px, route=s.route))
    except ValueError as exc:
        raise PipelineError(f"generic calibration: {exc}") from None


def _generic_statuses(sharp_rows: list[dict], frames: Sequence[_BlurryFrame], generic: GenericCalibration,
                      route: str) -> None:
    """The frame statuses of the generic calibration: ``used`` when a frame's features entered
    the fit. On the joint route the parametric alignment's verdict (``ill_conditioned``,
    ``alignment_failed``) does not leave a frame out (the bundle adjustment estimates its
    shift); it stays in the ``alignment`` column. The blurry features written to the outputs are
    the raw ones corrected by the estimated shift."""
    for row in sharp_rows:
        if row["status"] == "used" and row["frame"] in generic.skipped_frames:
            row.update(status="too_few_features",
                       reason=f"{generic.skipped_frames[row['frame']]} usable features: too few for the "
                               f"generic fit")
    for f in frames:
        name = f.row["frame"]
        entered = f.raw is not None if route == "joint" else f.row["status"] == "used"
        if not entered:
            continue
        if name in generic.skipped_frames:
            f.row.update(status="too_few_features",
                         reason=f"{generic.skipped_frames[name]} usable features: too few for the "
                                 f"generic fit (or no pose)")
            kept = f.aligned if f.aligned is not None else f.raw
            f.aligned = replace(kept, flags=kept.flags | int(FeatureFlags.FILTERED_OUT))
        elif route == "joint":
            shift = generic.shifts[name]
            flags = int(f.raw.flags[0] | FeatureFlags.GLOBALLY_ALIGNED)
            f.aligned = replace(f.raw, x=f.raw.x - shift[0], y=f.raw.y - shift[1],
                                flags=np.full(len(f.raw.x), flags, dtype=np.int64))
            f.row.update(status="used", reason="", shift=[round(float(v), 4) for v in shift])


def _publish(staging: Path, out: Path) -> None:
    """Move the output set staged in ``staging`` into ``out``.

    ``report.json`` (the completion marker) is removed first and moved in last; outputs of an
    earlier run that this run does not produce are removed, and the ``calibration`` folder is
    swapped whole. A run killed in between leaves no ``report.json``; the next run removes the
    staging folder and publishes again.
    """
    (out / REPORT_FILE).unlink(missing_ok=True)
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


def _write_outputs(out: Path, pattern: StarPattern, size: tuple[int, int],
                   sharp_features: FeatureTable, frames: Sequence[_BlurryFrame], rows: list[dict],
                   calibration: Calibration, generic: GenericCalibration | None) -> dict[str, Path]:
    tables = [sharp_features, *(f.aligned for f in frames if f.aligned is not None)]
    features = FeatureTable.concat(tables)
    outputs = {"features": write_features(out / "features.csv", features)}
    names = sorted(set(features.frame.tolist()))
    index = {f: i for i, f in enumerate(names)}
    usable = (features.flags & int(FeatureFlags.FILTERED_OUT)) == 0
    ref = to_ref_dataset(size, names, np.array([index[f] for f in features.frame[usable]]),
                         features.feature_id[usable], features.x[usable], features.y[usable],
                         pattern)
    outputs["reference_features"] = write_ref_dataset(out / "features.bin", ref)
    cols = ["frame", "kind", "blur_px", "noise_dn", "status", "reason", "extraction", "seeded_by", "psf",
            "features", "blocks", "kept", "centre_sigma_major", "alignment", "median_error", "mean_error",
            "angle_deg"]
    outputs["frames"] = atomic_write_csv(out / "frames.csv", cols,
                                         [[r.get(c, "") for c in cols] for r in rows])

    def direction_image(key: str, xy: np.ndarray, residuals: np.ndarray) -> None:
        path = out / f"{key}.png"
        with atomic_path(path) as tmp:
            cv2.imwrite(str(tmp), error_direction_image(xy, residuals, size))
        outputs[key] = path

    # Reprojection-error directions: the parametric alignment of the blurry frames, the sharp-set
    # calibration and, when fitted, the generic camera (its inliers).
    aligned = [f for f in frames if f.residuals is not None]
    if aligned:
        direction_image("error_directions_blurry",
                        np.concatenate([np.stack([f.raw.x, f.raw.y], axis=1) for f in aligned]),
                        np.concatenate([f.residuals for f in aligned]))
    direction_image("error_directions_sharp", calibration.observed, calibration.residuals)
    if generic is not None:
        direction_image("error_directions_generic", generic.observed[generic.inlier],
                        generic.residuals[generic.inlier])
    outputs["frame_errors"] = save_frame_error_plot(out / "frame_errors.png",
                                                    [r for r in rows if r["kind"] == "blurry"],
                                                    calibration.frame_errors())
    return outputs
