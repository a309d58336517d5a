"""``blurcalib calibrate``: the whole pipeline on one capture, frames in and cameras out."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, get_args

from tqdm import tqdm

from blurcalib.argtypes import (
    fold_count,
    image_size,
    non_negative_number,
    positive_number,
    rolling_shutter_mode,
)
from blurcalib.calib.alignment import BIASES, LOSSES, AlignmentSettings
from blurcalib.calib.joint import ROUTES, JointSettings
from blurcalib.calib.rolling_shutter import RollingShutterSettings
from blurcalib.calib.sequence import MODELS, PARAMETRIC_MODELS, SequenceSettings
from blurcalib.calib.undistortion import UNDISTORT
from blurcalib.calib.validation import ValidationMethod, ValidationSettings
from blurcalib.cli.common import (
    CliError,
    add_fit_options,
    add_run_options,
    add_source_options,
    plain,
    source_frames,
)
from blurcalib.growth.quality import LossMode, QualitySettings
from blurcalib.io.text import count
from blurcalib.runs.runtime import check_device
from blurcalib.target.pattern import StarPattern, load_pattern

if TYPE_CHECKING:
    from blurcalib.io.sources import FrameInput
    from blurcalib.pipeline.run import PipelineReport, PipelineSettings
    from blurcalib.sim.demo import DemoLog


def pipeline_settings(args: argparse.Namespace) -> PipelineSettings:
    """The pipeline's settings from the options of ``calibrate`` and ``demo``."""
    from blurcalib.calib.bundle import BundleSettings
    from blurcalib.calib.capture import CaptureSettings
    from blurcalib.calib.trust import TrustSettings
    from blurcalib.extract.frame import ExtractSettings
    from blurcalib.pipeline.run import PipelineSettings

    try:
        device = check_device(args.device)
        base = ExtractSettings(local_alignment=args.local_alignment,
                               sharp_below_px=getattr(args, "sharp_below", ExtractSettings.sharp_below_px))
        extraction = replace(base, grow=replace(base.grow, final_fit_frames=args.final_fit,
                                                psf_field=not args.no_psf_field),
                             deconv=replace(base.deconv, device=device))
        calibration = SequenceSettings(
            quality=QualitySettings(tau_be=args.tau_be, tau_loss=args.tau_loss,
                                    min_sigma_major=args.min_sigma_major, loss_mode=args.loss_threshold),
            alignment=AlignmentSettings(loss=args.loss, bias=args.bias), model=args.model,
            parametric=args.parametric,
            generic=JointSettings(cell_px=args.cell_px, route=args.route,
                                  bundle=BundleSettings(device=device), undistort=args.undistort),
            lens_correction=not args.no_lens_correction,
            trust=TrustSettings(validation=ValidationSettings(method=args.validation, folds=args.folds)),
            rolling_shutter=RollingShutterSettings(args.rolling_shutter))
        capture = CaptureSettings(refuse=not args.allow_degenerate)
        return PipelineSettings(extraction, calibration, capture, workers=args.workers, cluster=args.cluster)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def calibrate_and_report(sharp: list[Path], blurry: list[Path], pattern: StarPattern, out: Path,
                         args: argparse.Namespace, features: Path | None = None,
                         mixed: Sequence[FrameInput] = (), log: DemoLog | None = None,
                         feature_sets: Sequence[tuple[Path, StarPattern]] = ()) -> PipelineReport:
    """Run the pipeline on frames (``sharp`` and ``blurry``, or ``mixed`` frames classified by
    their own blur), on a feature file (``features``) or on feature files of several patterns
    (``feature_sets``, each with its pattern), and print its figures; with ``log`` (the demo's
    :class:`blurcalib.sim.demo.DemoLog`) tell it the stages instead and print nothing."""
    from blurcalib.pipeline.patterns import run_from_feature_sets
    from blurcalib.pipeline.run import PipelineError, run_from_features, run_pipeline
    from blurcalib.pipeline.text import report_lines
    from blurcalib.runs.events import FrameDone, RunEvent

    bars: dict[str, tqdm] = {}

    def update(stage: str, event: RunEvent) -> None:
        if not isinstance(event, FrameDone):
            return
        if stage not in bars:
            if log is not None:
                log.stage(f"2/4 extracting the {count(event.total, f'{stage} frame')}")
            bars[stage] = tqdm(total=event.total, desc=f"extracting {stage}", unit="frame",
                               file=sys.stderr, dynamic_ncols=True, disable=None)
        bars[stage].n = event.done
        bars[stage].set_postfix_str(f"{event.record.frame}: {event.record.status.value}", refresh=True)
        if log is not None:
            r = event.record
            log.detail(f"{stage} {event.done}/{event.total}: {r.frame} {r.status.value}, "
                       f"{count(r.features, 'feature')}")

    def on_stage(name: str) -> None:
        if log is not None:
            log.stage(f"3/4 {name}")

    try:
        if feature_sets:
            report = run_from_feature_sets(feature_sets, out, pipeline_settings(args), args.image_size,
                                           overwrite=args.overwrite)
        elif features is not None:
            report = run_from_features(features, pattern, out, pipeline_settings(args), args.image_size,
                                       overwrite=args.overwrite)
        else:
            report = run_pipeline(sharp, blurry, pattern, out, pipeline_settings(args), update,
                                  overwrite=args.overwrite, mixed=mixed,
                                  on_stage=None if log is None else on_stage)
    except PipelineError as exc:
        raise CliError(str(exc)) from None
    finally:
        for bar in bars.values():
            bar.close()
    if log is None:
        print("\n".join(report_lines(report)))
    return report


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Calibrate a camera from one capture: extract star features from sharp and blurry frames,
    calibrate Brown-Conrady on the sharp ones, fit the generic camera to sharp and blurry frames
    together and assess it on frames it has not seen (docs/pipeline.md).

    Writes into --out the generic camera (calibration/intrinsics0.yaml, the reference tool's
    format), the Brown-Conrady camera (calibration/camera.yaml, OpenCV's), the observations
    (features.csv, features.bin), each frame's status (frames.csv) and report.json, written last
    (docs/results-format.md). Prints both cameras' reprojection errors, the held-out errors, the
    projection uncertainty and the frames used. Resumable: extracted frames are reused.

    Several feature files, each with its own --pattern (e.g. the star and the checkerboard shown to
    one camera), give one camera from all their frames, each frame through its own pattern's
    geometry, and the cross-pattern check: each pattern's camera alone against the others'
    (difference, focal-length scale, and whether their uncertainties explain it), the held-out
    error on each pattern's frames, and the features of frames named alike compared
    (docs/accuracy.md)."""
    from blurcalib.io.frames import FrameError, frame_size, list_frames
    from blurcalib.io.sources import FrameInput

    patterns = [load_pattern(p) for p in args.pattern]
    features = [Path(f) for f in args.features or []]
    given = [name for name, v in (("INPUT", args.frames), ("--sharp", args.sharp),
                                  ("--features", features)) if v]
    if len(given) != 1:
        raise CliError("give the frames (INPUT... or --sharp DIR [--blurry DIR]) or a feature file "
                       f"(--features FILE), one of them (got {', '.join(given) or 'none'})")
    if args.blurry and not args.sharp:
        raise CliError("--blurry DIR goes with --sharp DIR (or give every folder as INPUT)")
    if len(patterns) > 1 and len(patterns) != len(features):
        raise CliError(f"{len(patterns)} --pattern files: several patterns go with one --features FILE each, "
                       f"in the same order (got {len(features)}; frames of several patterns: extract each "
                       "set with 'blurcalib extract' and calibrate from their features.csv)")
    if features:
        if args.model == "generic":
            _check_grid([_features_image_size(f, args.image_size) for f in features], args.cell_px)
        if len(features) > 1:
            pairs = list(zip(features, patterns * (len(features) // len(patterns)), strict=True))
            calibrate_and_report([], [], patterns[0], Path(args.out), args, feature_sets=pairs)
        else:
            calibrate_and_report([], [], patterns[0], Path(args.out), args, features=features[0])
        return 0
    pattern = patterns[0]
    if args.frames:
        mixed = source_frames(args)
        if args.model == "generic":
            _check_grid(map(FrameInput.size, mixed), args.cell_px)
        calibrate_and_report([], [], pattern, Path(args.out), args, mixed=mixed)
        return 0
    try:
        sharp = list_frames([args.sharp])
        blurry = list_frames([args.blurry]) if args.blurry else []
    except FrameError as exc:
        raise CliError(str(exc)) from None
    if args.model == "generic":
        _check_grid(map(frame_size, sharp), args.cell_px)
    calibrate_and_report(sharp, blurry, pattern, Path(args.out), args)
    return 0


def _features_image_size(path: Path, given: tuple[int, int] | None) -> tuple[int, int] | None:
    """The image size of a ``--features`` file: ``--image-size``, or a reference dataset's own from
    its header; None when neither is known, or the size is one no frame may have (the reader
    says so)."""
    from blurcalib.io.frames import frame_size_problem
    from blurcalib.io.refformat import ref_dataset_image_size

    size = given or (ref_dataset_image_size(path) if path.suffix.lower() == ".bin" else None)
    return size if size is not None and frame_size_problem(*size) is None else None


def _check_grid(sizes: Iterable[tuple[int, int] | None], cell_px: float) -> None:
    """Refuse ``--cell-px`` whose generic grid over the whole frame could not be fitted
    (:func:`blurcalib.camera.generic.check_grid_size`), before any frame is extracted; the frames'
    ``sizes`` are read up to the first known one."""
    from blurcalib.camera.generic import check_grid_size

    size = next((s for s in sizes if s is not None), None)
    if size is not None:
        try:
            check_grid_size(*size, cell_px)
        except ValueError as exc:
            raise CliError(f"--cell-px {cell_px:g}: {exc}") from None


def add_pipeline_options(p: argparse._ActionsContainer) -> None:
    g = p.add_argument_group("blurry frames: extraction, block filter and alignment")
    g.add_argument("--tau-be", type=non_negative_number, default=QualitySettings.tau_be, metavar="BE",
                   help="largest PSF boundary energy kept (default %(default)s)")
    g.add_argument("--tau-loss", type=positive_number, default=QualitySettings.tau_loss, metavar="L",
                   help="largest block loss kept, grey levels^2: at a noise of 2 grey levels, scaled with "
                        "each block's noise variance (relative), or as given (absolute) "
                        "(default %(default)s)")
    g.add_argument("--loss-threshold", choices=list(get_args(LossMode)), default=QualitySettings.loss_mode,
                   help="--tau-loss in the frame's own noise units, estimated from the image (relative), "
                        "or the paper's absolute grey levels^2 (default %(default)s; docs/pipeline.md)")
    g.add_argument("--min-sigma-major", type=non_negative_number, default=QualitySettings.min_sigma_major,
                   metavar="PX",
                   help="drop blurry frames whose centre median sigma_major is below this, px "
                        "(default %(default)s: keep every frame; the paper's choice for its camera is 3.8)")
    g.add_argument("--loss", choices=LOSSES, default=AlignmentSettings.loss,
                   help="robust loss of the global alignment (default %(default)s)")
    g.add_argument("--bias", choices=[b for b in BIASES if b != "none"], default=AlignmentSettings.bias,
                   help="bias model of the global alignment (default %(default)s)")
    g.add_argument("--local-alignment", action="store_true",
                   help="use the local-alignment translations for blurry frames")
    add_fit_options(g, "blurry ")
    g = p.add_argument_group("the camera")
    g.add_argument("--model", choices=MODELS, default=SequenceSettings.model,
                   help="camera model delivered: the generic B-spline ray grid fitted to sharp and blurry "
                        "frames together, or the parametric camera from the sharp set only "
                        "(default %(default)s)")
    g.add_argument("--parametric", choices=PARAMETRIC_MODELS, default=SequenceSettings.parametric,
                   help="model of the parametric (sharp-set) camera, which the generic camera starts from "
                        "and is regularised toward: Brown-Conrady, OpenCV's rational model, Kannala-Brandt "
                        "(OpenCV's fisheye) or the reference tool's thin-prism fisheye; auto: the one "
                        "with the lowest error on held-out frames (default %(default)s)")
    g.add_argument("--route", choices=ROUTES, default=JointSettings.route,
                   help="blurry frames in the generic fit: star centres with a free per-frame shift "
                        "(joint), or aligned to the parametric camera first, the paper's route "
                        "(default %(default)s)")
    g.add_argument("--cell-px", type=positive_number, default=JointSettings.cell_px, metavar="PX",
                   help="cell length of the generic model's grid, px (default %(default)s)")
    g.add_argument("--undistort", choices=UNDISTORT, default=JointSettings.undistort,
                   help="projection of the undistortion map (calibration/undistortion_map.npz, for "
                        "cv2.remap): a pinhole image, a latitude-longitude or a stereographic one; auto: "
                        "pinhole for a camera of at most 120 degrees of field, latlong beyond "
                        "(default %(default)s; docs/results-format.md)")
    g.add_argument("--no-lens-correction", action="store_true",
                   help="keep star centres as extracted instead of removing the bias of block homographies "
                        "under the sharp-set camera's distortion (docs/generic.md)")
    g.add_argument("--rolling-shutter", type=rolling_shutter_mode, default=RollingShutterSettings.mode,
                   metavar="off|auto|R",
                   help="the rolling shutter in the generic fit: off (a global shutter; a warning when the "
                        "blurry frames' features say otherwise), auto (estimate the readout ratio and model "
                        "it when significant) or a number R: model it whatever the test says (the ratio "
                        "is still estimated); with demo, R also simulates that rolling shutter "
                        "(default %(default)s; docs/rolling-shutter.md)")
    g.add_argument("--allow-degenerate", action="store_true",
                   help="calibrate a capture whose sharp frames cannot determine the focal length (all "
                        "nearly face-on, or at nearly one orientation) instead of refusing it; the problem "
                        "is printed as a warning and kept in report.json (docs/calibration.md)")
    g = p.add_argument_group("assessment")
    g.add_argument("--validation", choices=list(get_args(ValidationMethod)),
                   default=ValidationSettings.method,
                   help="held-out validation of the cameras: k-fold over frames, each held-out frame "
                        "scored by cameras fitted without it, or none (default %(default)s; "
                        "docs/validation.md)")
    g.add_argument("--folds", type=fold_count, default=ValidationSettings.folds, metavar="K",
                   help="number of folds of the validation (default %(default)s; needs at least "
                        f"{ValidationSettings.min_frames} frames)")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``calibrate``."""
    p = sub.add_parser("calibrate", help="the whole pipeline on one capture: frames in, cameras out",
                       description=plain(cmd_calibrate.__doc__))
    g = p.add_argument_group("inputs")
    add_source_options(g, nargs="*")
    g.add_argument("--sharp", metavar="DIR",
                   help="folder of sharp frames (instead of INPUT: the kinds given, not measured)")
    g.add_argument("--blurry", metavar="DIR",
                   help="folder of blurry frames, with --sharp (optional: a sharp-only calibration)")
    g.add_argument("--features", metavar="FILE", action="append",
                   help="calibrate from a feature file instead of frames: the reference tool's dataset "
                        "(.bin) or a blurcalib features.csv (rows flagged BLURRY_FRAME get a free shift); "
                        "repeat it with one --pattern each to calibrate one camera from several patterns "
                        "(with the cross-pattern check; docs/accuracy.md)")
    g.add_argument("--image-size", type=image_size, metavar="WxH",
                   help="image size of a features.csv, px (a .bin holds its own)")
    g.add_argument("--pattern", required=True, metavar="FILE", action="append",
                   help="pattern YAML of the target; with several --features, one per file in the same "
                        "order (or one for all)")
    g = p.add_argument_group("output")
    g.add_argument("--out", required=True, metavar="DIR", help="output folder (resumable)")
    g.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder that is not a calibrate output")
    add_run_options(p)
    add_pipeline_options(p)
    p.set_defaults(func=cmd_calibrate)
