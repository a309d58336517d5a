"""The calibration sequence: from star-centre features to the cameras and their assessment, in memory.

:func:`calibrate_features` is what ``blurcalib calibrate`` (:mod:`blurcalib.pipeline.run`) and the
app (``state/calibration.py``) run:

1. the parametric camera and the target points from the sharp frames
   (:func:`blurcalib.calib.sharp.calibrate_sharp`), its model the one given or, with
   ``parametric="auto"``, the model of the family with the lowest held-out error
   (:func:`blurcalib.calib.model_choice.choose_model`; when its fit on every frame fails, the
   next best); with too few sharp frames and
   :attr:`SequenceSettings.blurry_in_parametric`, the blurry frames' kept star centres join
   (their per-frame shift is not modelled there; the generic fit models it);
2. with :attr:`SequenceSettings.lens_correction`: every star centre moved by minus the bias of
   its block homography through that camera (any model of the family, any field of view)
   (:mod:`blurcalib.calib.lens_bias`), the
   parametric camera calibrated again from the corrected features, and the blurry frames'
   blocks corrected under that final camera; sharp frames it leaves out are flagged
   ``FILTERED_OUT``;
3. per blurry frame with blocks: the BE / loss / connectivity filter and the blur pre-filter
   (:func:`blurcalib.growth.quality.filter_frame`, on the corrected blocks, unless the caller
   gives the kept blocks), and the global alignment of the kept blocks to the parametric camera
   (``eq:global_align``, :func:`blurcalib.calib.alignment.align_kept_blocks`);
4. with ``model="generic"``: the central generic camera (:func:`blurcalib.calib.joint.calibrate_generic`)
   of the sharp features and the blurry frames of the route (``joint``: every frame's kept star
   centres with a free image shift; ``aligned``: the aligned features of the well-conditioned
   frames), and the generic camera of the sharp frames alone when blurry frames entered;
   The generic camera starts from the parametric camera's rays and its smoothness prior keeps
   their shape. A generic fit that fails (singular normal equations, a frame without a pose) is
   recorded (:attr:`CalibrationRun.generic_failure`: what the capture lacks), not raised: the
   parametric calibration stands;
5. the assessment (:func:`blurcalib.calib.trust.assess_calibration`: held-out error, projection
   uncertainty, cross-validation diff, guidance). A failed assessment is recorded
   (:attr:`CalibrationRun.trust_failure`, :attr:`CalibrationRun.sharp_failure`), not raised.

Pixels follow OpenCV's convention: the centre of the top-left pixel is ``(0, 0)``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any

import numpy as np

from blurcalib.calib.alignment import AlignmentError, AlignmentSettings, GlobalAlignment, align_kept_blocks
from blurcalib.calib.joint import GenericCalibration, JointSettings, calibrate_generic
from blurcalib.calib.lens_bias import correct_blocks, correct_features
from blurcalib.calib.model_choice import AUTO, ModelChoice, choose_model
from blurcalib.calib.rolling_shutter import (
    RollingShutterResult,
    RollingShutterSettings,
    blur_velocities,
    calibrate_rolling_shutter,
)
from blurcalib.calib.sharp import Calibration, CalibrationError, calibrate_sharp
from blurcalib.calib.trust import Trust, TrustSettings, assess_calibration
from blurcalib.calib.uncertainty import projection_uncertainty
from blurcalib.camera.family import MODELS as CAMERA_MODELS
from blurcalib.growth.quality import FrameFilter, QualitySettings, filter_frame
from blurcalib.io.results import BlockTable, FeatureFlags, FeatureTable
from blurcalib.target.pattern import StarPattern

__all__ = ["PARAMETRIC_MODELS", "BlurryFrame", "BlurryOutcome", "CalibrationRun", "SequenceCancelledError",
           "SequenceSettings", "Stage", "calibrate_features", "generic_failure"]

MODELS: tuple[str, ...] = ("generic", "parametric")
"""Camera models the sequence delivers."""
PARAMETRIC_MODELS: tuple[str, ...] = (AUTO, *CAMERA_MODELS)
"""The settings of the parametric camera's model: ``auto`` or a model of the family."""
BLURRY_FLAGS = FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME
"""The flags of a blurry frame's star centres."""
MIN_PARAMETRIC_FRAMES = 2
"""Fewest frames of a parametric stage that the blurry frames join."""


class Stage(Enum):
    """The sequence's stages, announced to :func:`calibrate_features`'s ``on_stage``."""

    PARAMETRIC = "parametric calibration"
    GENERIC = "generic calibration"
    ASSESSMENT = "assessment (held-out error, uncertainty)"


class SequenceCancelledError(Exception):
    """``on_stage`` asked the sequence to stop."""


@dataclass(frozen=True)
class SequenceSettings:
    """Settings of :func:`calibrate_features`.

    Attributes:
        quality: the block filter and the blur pre-filter of the blurry frames.
        alignment: the global alignment of the blurry frames to the parametric camera (loss,
            bias, orientation filter, fewest kept blocks). ``bias="translation"`` by default:
            the features are PSF-centroid positions without the drift the paper's bilinear field
            compensates, and on simulated data the bilinear field also absorbs part of the true
            lens's non-parametric deviation (docs/pipeline.md).
        model: ``generic`` (the central generic camera fitted to sharp and blurry frames
            together) or ``parametric`` (the parametric camera only).
        parametric: the parametric camera's model (:data:`blurcalib.camera.family.MODELS`:
            ``Brown_Conrady``, ``rational``, ``Kannala_Brandt``, ``thin_prism_fisheye``) or
            ``auto``: the one with the lowest held-out error
            (:func:`blurcalib.calib.model_choice.choose_model`).
        generic: the generic fit (grid cell, route). ``route="joint"`` (default: raw star
            centres, each frame's translational ambiguity a free shift, no orientation filter)
            or ``"aligned"`` (the paper's route: globally aligned to the parametric camera, then
            held fixed; ill-conditioned frames left out). Measured on simulated data
            (``blurcalib experiment generic``, docs/generic.md): 0.005 px median error against
            the true camera for ``joint``, 0.14 px for ``aligned``.
        lens_correction: correct every star centre for the lens bias of its block homography
            under the parametric camera and calibrate that camera again (a Brown-Conrady
            camera; other models are not corrected).
        min_sharp_frames, min_sharp_features: fewest usable sharp frames, and features of a
            usable sharp frame, of the parametric stage.
        blurry_in_parametric: with fewer than ``min_sharp_frames`` sharp frames, the blurry
            frames' kept star centres join the parametric stage (at least
            :data:`MIN_PARAMETRIC_FRAMES` frames of ``alignment.min_blocks`` features); off, too
            few sharp frames are an error.
        trust: the assessment's options.
    """

    quality: QualitySettings = field(default_factory=QualitySettings)
    alignment: AlignmentSettings = field(default_factory=AlignmentSettings)
    model: str = "generic"
    parametric: str = AUTO
    generic: JointSettings = field(default_factory=JointSettings)
    lens_correction: bool = True
    min_sharp_frames: int = 5
    min_sharp_features: int = 20
    blurry_in_parametric: bool = False
    trust: TrustSettings = field(default_factory=TrustSettings)
    rolling_shutter: RollingShutterSettings = field(default_factory=RollingShutterSettings)

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        if self.parametric not in PARAMETRIC_MODELS:
            raise ValueError(f"parametric must be one of {PARAMETRIC_MODELS}, got {self.parametric!r}")


@dataclass(frozen=True, eq=False)
class BlurryFrame:
    """One blurry frame's input.

    Attributes:
        name: the frame.
        blocks: its blocks (star centres ``H(0, 0)``, figures), or None for a frame known by its
            features only (a feature file: no filter, lens-bias correction or alignment).
        kept: ``(B,)`` the blocks kept by the caller's quality filter, or None to filter the
            (corrected) blocks here with :attr:`SequenceSettings.quality`.
        features: the star centres of a frame without blocks.
        flags: the :class:`FeatureFlags` of the star centres made from its blocks.
    """

    name: str
    blocks: BlockTable | None = None
    kept: np.ndarray | None = None
    features: FeatureTable | None = None
    flags: int = int(BLURRY_FLAGS)


@dataclass(eq=False)
class BlurryOutcome:
    """What the sequence made of one blurry frame.

    Attributes:
        frame: its input.
        filter: its quality filter (None without blocks or when the caller gave the kept blocks).
        blocks: its blocks, lens-corrected when the sequence corrects them (None without blocks).
        kept: ``(B,)`` the blocks kept (None without blocks).
        raw: its kept star centres (None when too few blocks survive or the pre-filter drops it).
        alignment: the global alignment of ``raw`` to the parametric camera, or None.
        alignment_error: why the alignment failed ("" when it did not).
        aligned: the features written for it: ``raw`` globally aligned (parametric alignment, or
            on the joint route moved by the generic fit's shift), flagged ``FILTERED_OUT`` when
            ill-conditioned or left out by the generic fit; None when it has none.
        entered: its features entered the generic fit.
        shift: ``(2,)`` px, its image shift estimated by the generic fit (joint route), or None.
        skipped_features: usable features when the generic fit left it out, else None.
    """

    frame: BlurryFrame
    filter: FrameFilter | None = None
    blocks: BlockTable | None = None
    kept: np.ndarray | None = None
    raw: FeatureTable | None = None
    alignment: GlobalAlignment | None = None
    alignment_error: str = ""
    aligned: FeatureTable | None = None
    entered: bool = False
    shift: np.ndarray | None = None
    skipped_features: int | None = None

    @property
    def num_kept(self) -> int:
        """Blocks kept (0 without blocks)."""
        return 0 if self.kept is None else int(self.kept.sum())

    @property
    def ill_conditioned(self) -> bool:
        """The parametric alignment flags it: seen nearly frontally, its translation ill-conditioned."""
        return self.alignment is not None and self.alignment.ill_conditioned


@dataclass(eq=False)
class CalibrationRun:
    """The cameras of :func:`calibrate_features` and their assessment.

    Attributes:
        calibration: the parametric calibration (after the lens-bias correction).
        choice: the held-out scores of the family's models, with ``parametric="auto"``.
        sharp: the sharp features it used (corrected; frames it left out flagged ``FILTERED_OUT``).
        blurry: one outcome per blurry frame, in input order.
        parametric_with_blurry: blurry frames entered the parametric stage.
        generic: the generic camera of sharp and blurry frames (None for ``model="parametric"``).
        generic_sharp: the generic camera of the sharp frames alone, when blurry frames entered
            ``generic``.
        trust: held-out error, uncertainty, cross-validation diff and guidance, or None.
        generic_failure: why there is no generic camera though ``model="generic"`` (what the
            capture lacks), or "".
        trust_failure: why there is no assessment though there is a generic camera, or "".
        sharp_failure: why there is no sharp-only generic camera though blurry frames entered, or
            why it was not assessed with the rest, or "".
        rolling_shutter: the rolling-shutter step of the joint route's generic fit
            (:mod:`blurcalib.calib.rolling_shutter`), or None.
        seconds: wall time (s): ``parametric`` (with the lens-bias correction, the filter and the
            alignment), ``generic`` (both generic cameras) and ``assessment``.
    """

    calibration: Calibration
    sharp: FeatureTable
    blurry: list[BlurryOutcome]
    parametric_with_blurry: bool = False
    choice: ModelChoice | None = None
    generic: GenericCalibration | None = None
    generic_sharp: GenericCalibration | None = None
    trust: Trust | None = None
    generic_failure: str = ""
    trust_failure: str = ""
    sharp_failure: str = ""
    rolling_shutter: RollingShutterResult | None = None
    seconds: dict[str, float] = field(default_factory=dict)


def calibrate_features(sharp: FeatureTable, sharp_blocks: BlockTable | None, blurry: Sequence[BlurryFrame],
                       pattern: StarPattern, image_size: tuple[int, int],
                       settings: SequenceSettings | None = None,
                       on_stage: Callable[[Stage], bool] | None = None,
                       assess: bool = True) -> CalibrationRun:
    """Run the calibration sequence (module docstring).

    Args:
        sharp: the sharp frames' star centres (px).
        sharp_blocks: their blocks, for the lens-bias correction (None: sharp features stay as
            given).
        blurry: the blurry frames.
        pattern: the target.
        image_size: ``(width, height)`` px.
        settings: the sequence's settings.
        on_stage: called before each :class:`Stage`; returning False stops the sequence.
        assess: run stage 5 (False: the cameras only, without ``generic_sharp`` and ``trust``).

    Raises:
        CalibrationError: too few usable frames for the parametric camera.
        ValueError: the generic fit cannot be made (its message says why).
        SequenceCancelledError: ``on_stage`` returned False.
    """
    s = settings or SequenceSettings()

    def announce(stage: Stage) -> None:
        if on_stage is not None and not on_stage(stage):
            raise SequenceCancelledError(stage.value)

    announce(Stage.PARAMETRIC)
    t0 = time.perf_counter()
    outcomes = [BlurryOutcome(f, blocks=f.blocks) for f in blurry]
    calibration, sharp, with_blurry, choice = _parametric(sharp, sharp_blocks, outcomes, pattern, image_size,
                                                          s)
    for o in outcomes:
        _align(o, calibration, pattern, image_size, s)
    run = CalibrationRun(calibration, sharp, outcomes, with_blurry, choice)
    t1 = time.perf_counter()
    run.seconds["parametric"] = t1 - t0
    if s.model != "generic":
        return run
    announce(Stage.GENERIC)
    try:
        run.generic, run.rolling_shutter = _fit_generic(sharp, outcomes, calibration, pattern, image_size, s)
    except (ValueError, np.linalg.LinAlgError, RuntimeError) as exc:  # torch's LinAlgError: RuntimeError
        run.generic_failure = generic_failure(exc, sharp, outcomes, image_size, s.generic.cell_px)
    run.seconds["generic"] = time.perf_counter() - t1
    if run.generic is None or not assess:
        return run
    announce(Stage.ASSESSMENT)
    _assess(run, pattern, image_size, s)
    return run


def _parametric(sharp: FeatureTable, sharp_blocks: BlockTable | None, outcomes: list[BlurryOutcome],
                pattern: StarPattern, size: tuple[int, int], s: SequenceSettings
                ) -> tuple[Calibration, FeatureTable, bool, ModelChoice | None]:
    """Stages 1 and 2: the parametric camera (its model chosen with ``parametric="auto"``), the
    lens-bias correction of the sharp star centres (and of the blurry ones where they join) under
    a Brown-Conrady camera, the camera again, and the blurry frames' blocks corrected under that
    final camera (the outcomes' ``blocks``); the sharp features it used, with the frames it left
    out flagged, and the model choice."""
    frames = len(set(sharp.frame.tolist()))
    with_blurry = s.blurry_in_parametric and frames < s.min_sharp_frames
    kw: dict[str, Any]
    kw = (dict(min_frames=MIN_PARAMETRIC_FRAMES, min_features=s.alignment.min_blocks) if with_blurry
          else dict(min_frames=s.min_sharp_frames, min_features=s.min_sharp_features))

    def table_of(features: FeatureTable) -> FeatureTable:
        extra = [_kept_features(o, pattern, size, s) for o in outcomes] if with_blurry else []
        return FeatureTable.concat([features, *(t for t in extra if t is not None)])

    choice = choose_model(table_of(sharp), pattern, size, **kw) if s.parametric == AUTO else None
    models = [s.parametric] if choice is None else choice.ranked()

    def calibrate(features: FeatureTable) -> Calibration:
        return calibrate_sharp(table_of(features), pattern, size, model=models[0], **kw)

    while True:  # a chosen model whose fit on every frame fails gives way to the next
        try:
            calibration = calibrate(sharp)
            break
        except CalibrationError:
            if len(models) == 1:
                raise
            models.pop(0)
    if s.lens_correction:
        if sharp_blocks is not None:
            sharp = correct_features(sharp, sharp_blocks, calibration.camera)
        if with_blurry:
            _correct(outcomes, calibration)
        calibration = calibrate(sharp)
        _correct(outcomes, calibration)
    used = set(calibration.frame_errors())
    sharp = replace(sharp, flags=np.where(np.isin(sharp.frame, sorted(used)), sharp.flags,
                                          sharp.flags | int(FeatureFlags.FILTERED_OUT)))
    with_blurry = with_blurry and not used.isdisjoint(o.frame.name for o in outcomes)
    return calibration, sharp, with_blurry, choice


def _correct(outcomes: list[BlurryOutcome], calibration: Calibration) -> None:
    """The outcomes' blocks: their frames' blocks corrected for the lens bias under ``calibration``."""
    for o in outcomes:
        if o.frame.blocks is not None:
            o.blocks = correct_blocks(o.frame.blocks, calibration.camera)


def _kept_features(o: BlurryOutcome, pattern: StarPattern, size: tuple[int, int], s: SequenceSettings
                   ) -> FeatureTable | None:
    """The star centres of a frame's kept blocks (its features when it has no blocks), or None
    when the pre-filter drops it or fewer than ``alignment.min_blocks`` blocks are kept."""
    f = o.frame
    if o.blocks is None:
        return f.features
    if f.kept is not None:
        o.kept = np.array(f.kept, dtype=bool)
    else:
        o.filter = filter_frame(o.blocks, size, s.quality)
        o.kept = o.filter.kept.copy() if o.filter.frame_ok else np.zeros(len(o.blocks), dtype=bool)
    o.kept &= np.all(np.isfinite(o.blocks.centre), axis=1)
    if o.num_kept < s.alignment.min_blocks:
        return None
    flags = f.flags | int(FeatureFlags.LENS_CORRECTED) if s.lens_correction else f.flags
    return o.blocks.select(o.kept).features(pattern.square_length_m, flags)


def _align(o: BlurryOutcome, calibration: Calibration, pattern: StarPattern, size: tuple[int, int],
           s: SequenceSettings) -> None:
    """Stage 3 for one frame: its kept star centres and their alignment to the parametric camera."""
    o.raw = _kept_features(o, pattern, size, s)
    if o.raw is None or o.blocks is None:
        return
    assert o.kept is not None  # kept with the blocks
    try:
        _, o.alignment = align_kept_blocks(calibration.camera, pattern, calibration.points, o.blocks, o.kept,
                                           s.alignment)
    except AlignmentError as exc:
        o.alignment_error = str(exc)
        return
    flags = o.raw.flags | int(FeatureFlags.GLOBALLY_ALIGNED)
    if o.alignment.ill_conditioned:
        flags = flags | int(FeatureFlags.FILTERED_OUT)
    corrected = o.alignment.corrected
    o.aligned = replace(o.raw, x=corrected[:, 0], y=corrected[:, 1], flags=flags)


def _fit_generic(sharp: FeatureTable, outcomes: list[BlurryOutcome], calibration: Calibration,
                 pattern: StarPattern, size: tuple[int, int], s: SequenceSettings
                 ) -> tuple[GenericCalibration, RollingShutterResult | None]:
    """Stage 4: the generic camera of the sharp features and the blurry frames of the route; the
    outcomes of the frames that entered get their shift (joint route) or their features flagged
    when the fit left them out. On the joint route the parametric alignment's verdict does not
    leave a frame out (the fit estimates its shift), and its written features are the raw ones
    moved by minus that shift. On the joint route the rolling-shutter step follows
    (:func:`blurcalib.calib.rolling_shutter.calibrate_rolling_shutter`); when it models the
    rolling shutter, the written features are also moved by minus their frame's rolling
    displacement."""
    joint = s.generic.route == "joint"
    for o in outcomes:
        o.entered = o.raw is not None if joint else o.alignment is not None and not o.ill_conditioned
    tables = [t for t in (o.raw if joint else o.aligned for o in outcomes) if t is not None]
    blurry = FeatureTable.concat(tables) if tables else None
    generic = calibrate_generic(sharp, blurry, calibration, pattern, size, s.generic)
    rolling = None
    if joint and blurry is not None and generic.blurry_frames:
        blocks = [o.blocks.select(o.kept) for o in outcomes
                  if o.raw is not None and o.blocks is not None and o.kept is not None]
        generic, rolling = calibrate_rolling_shutter(sharp, blurry, calibration, pattern, size,
                                                     s.rolling_shutter, s.generic, blur_velocities(blocks),
                                                     first=generic)
    corrected = rolling.corrected if rolling is not None else None
    for o in (o for o in outcomes if o.entered):
        name = o.frame.name
        if name in generic.skipped_frames:
            o.skipped_features = generic.skipped_frames[name]
            kept = o.aligned if o.aligned is not None else o.raw
            assert kept is not None  # a frame that entered has its star centres
            o.aligned = replace(kept, flags=kept.flags | int(FeatureFlags.FILTERED_OUT))
        elif joint:
            o.shift = generic.shifts[name]
            assert o.raw is not None  # a frame that entered has its star centres
            flags = int(o.raw.flags[0] | FeatureFlags.GLOBALLY_ALIGNED)
            seen = o.raw if corrected is None else corrected.select(corrected.frame == name)
            o.aligned = replace(seen, x=seen.x - o.shift[0], y=seen.y - o.shift[1],
                                flags=np.full(len(seen), flags, dtype=np.int64))
    return generic, rolling


def _assess(run: CalibrationRun, pattern: StarPattern, size: tuple[int, int], s: SequenceSettings) -> None:
    """Stage 5: the generic camera of the sharp features alone when blurry frames entered the
    generic fit, then the assessment. A failure is recorded, not raised: the calibration stands
    without its assessment, and when only the sharp-only camera's part fails, the generic camera
    is assessed alone and the sharp-only camera keeps its uncertainty map."""
    t0 = time.perf_counter()
    assert run.generic is not None  # stage 4 ran
    if run.generic.blurry_frames:
        try:
            run.generic_sharp = calibrate_generic(run.sharp, None, run.calibration, pattern, size, s.generic)
        except ValueError as exc:  # CalibrationError too
            run.sharp_failure = str(exc)
    t1 = time.perf_counter()
    for generic_sharp in ([run.generic_sharp, None] if run.generic_sharp is not None else [None]):
        try:
            run.trust = assess_calibration(run.generic, generic_sharp, run.calibration, run.sharp, pattern,
                                           size, s.trust, s.generic.bundle)
            break
        except (ValueError, RuntimeError) as exc:  # torch's LinAlgError is a RuntimeError
            failure = f"{type(exc).__name__}: {exc}"
            if generic_sharp is None:
                run.trust_failure = failure
            else:
                run.sharp_failure = f"its assessment failed ({failure})"
    if run.trust is not None and run.generic_sharp is not None and run.trust.uncertainty_sharp is None:
        try:
            run.trust.uncertainty_sharp = projection_uncertainty(run.generic_sharp.bundle,
                                                                 step_px=s.trust.step_px)
        except (ValueError, RuntimeError) as exc:
            run.sharp_failure += f"; no uncertainty map ({type(exc).__name__}: {exc})"
    run.seconds["generic"] += t1 - t0
    run.seconds["assessment"] = time.perf_counter() - t1


def generic_failure(exc: BaseException, sharp: FeatureTable, outcomes: Sequence[BlurryOutcome],
                    size: tuple[int, int], cell_px: float) -> str:
    """One line: why the generic fit failed and what the capture lacks: the share of the grid
    cells (``cell_px`` px) of the used features' bounding box without any observation, and the
    frames there were."""
    used = [sharp.select((sharp.flags & int(FeatureFlags.FILTERED_OUT)) == 0)]
    used += [o.raw for o in outcomes if o.raw is not None]
    xy = np.concatenate([np.column_stack([t.x, t.y]) for t in used])
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    frames = len({f for t in used for f in t.frame.tolist()})
    reason = " ".join(f"{type(exc).__name__}: {exc}".split())
    if len(xy) == 0:
        return f"generic calibration failed ({reason}): the capture has no usable feature"
    lo = np.floor(xy.min(axis=0) / cell_px)
    cells = np.floor(xy / cell_px) - lo
    shape = (cells.max(axis=0) + 1).astype(int)
    filled = np.zeros((shape[1], shape[0]), dtype=bool)
    filled[cells[:, 1].astype(int), cells[:, 0].astype(int)] = True
    empty = 100.0 * (1.0 - filled.mean())
    return (f"generic calibration failed ({reason}): the capture lacks observations in {empty:.0f} % of "
            f"the {cell_px:g} px grid cells of its calibrated area ({frames} frames of {size[0]}x{size[1]} "
            "px); add frames that fill the empty corners and edges, or use a larger --cell-px")
