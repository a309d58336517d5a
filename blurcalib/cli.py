"""The ``blurcalib`` command line: one subcommand per job.

Every subcommand reports bad input as ``blurcalib: error: <file>: <problem>`` on stderr and
exits with status 2; files are written atomically, so an interrupted or failed run leaves no
half-written output behind.
"""

from __future__ import annotations

import argparse
import inspect
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path
from typing import get_args

from tqdm import tqdm

from blurcalib import __version__
from blurcalib.argtypes import (
    cluster_address,
    fold_count,
    image_size,
    non_negative_number,
    page_size,
    positive_int,
    positive_number,
    psf_window,
    readout_ratio,
    rolling_shutter_mode,
)
from blurcalib.calib.alignment import BIASES, LOSSES, AlignmentSettings
from blurcalib.calib.joint import ROUTES, JointSettings
from blurcalib.calib.rolling_shutter import RollingShutterSettings
from blurcalib.calib.sequence import MODELS, PARAMETRIC_MODELS, SequenceSettings
from blurcalib.calib.validation import ValidationMethod, ValidationSettings
from blurcalib.growth.quality import LossMode, QualitySettings
from blurcalib.growth.settings import FinalFitFrames, GrowSettings
from blurcalib.growth.window import SHARP_START, WindowPolicy
from blurcalib.io.atomic import OutputError, output_lock, storage_error
from blurcalib.io.text import count
from blurcalib.runs.cluster import ClusterError
from blurcalib.runs.runtime import (
    DeviceError,
    available_cores,
    capped_count,
    check_device,
    configure_threads,
    keep_large_allocations,
)
from blurcalib.target.pattern import (
    PAGE_SIZES_MM,
    PatternFileError,
    StarPattern,
    layout_pattern,
    load_pattern,
)

DEFAULT_DEMO_DIR = Path("out") / "demo"


class CliError(Exception):
    """A user-facing error: printed without a traceback, exit status 2."""


def _progress(desc: str) -> tuple[tqdm, Callable[[int, int, str], None]]:
    bar = tqdm(total=0, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True,
               disable=None)

    def update(done: int, total: int, name: str) -> None:
        bar.total = total
        bar.n = done
        bar.set_postfix_str(name, refresh=False)
        bar.refresh()

    return bar, update


# ----------------------------------------------------------------------------- subcommands
def cmd_pattern(args: argparse.Namespace) -> int:
    """Write a printable star target: a vector PDF, a PNG and the pattern YAML, laid out as the
    reference tool's generator lays it out (the defaults reproduce its A4 17 x 24 pattern byte for
    byte). Prints the layout and the files written."""
    from blurcalib.target.printable import write_printable

    try:
        pattern = layout_pattern(page_size_mm=args.page, approx_square_length_mm=args.square_mm,
                                 tag_index=args.tag, num_star_segments=args.segments,
                                 margin_mm=args.margin_mm)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    formats = tuple(f.strip() for f in args.formats.split(",") if f.strip())
    try:
        paths = write_printable(pattern, Path(args.out), dpi=args.dpi, formats=formats,
                                overwrite=args.overwrite)
    except OutputError:
        raise
    except ValueError as exc:
        raise CliError(str(exc)) from None
    print(f"pattern: {pattern.squares_x} x {pattern.squares_y} squares of "
          f"{pattern.square_length_mm:.3f} mm, {pattern.num_star_segments} segments, "
          f"tag36h11 #{args.tag}, {pattern.num_features} features")
    for kind, path in paths.items():
        print(f"  {kind}: {path}")
    return 0


FISHEYE_FOV = 130.0
"""``synth --lens fisheye``'s default horizontal field of view (deg)."""


def _check_empty_output(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise CliError(f"{out}: output path exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise CliError(f"{out}: output folder is not empty (use --overwrite to replace its "
                       "dataset)")


def _simulate(out: Path, args: argparse.Namespace, pattern: StarPattern | None) -> None:
    from blurcalib.sim.synth import SynthConfig, write_dataset
    from blurcalib.sim.truth import fisheye_camera

    readout = args.rolling_shutter if isinstance(args.rolling_shutter, float) else 0.0  # demo: off, auto
    lens, fov = getattr(args, "lens", "standard"), getattr(args, "fov", None)
    if fov is not None and lens != "fisheye":
        raise CliError("--fov sets the field of view of --lens fisheye")
    try:
        config = SynthConfig(sharp=args.sharp, blurry=args.blurry, blur_min_px=args.blur_min,
                             blur_max_px=args.blur_max, max_tilt_deg=args.max_tilt,
                             noise_sigma=args.noise, seed=args.seed,
                             rolling_shutter=readout)
        camera = fisheye_camera(FISHEYE_FOV if fov is None else fov, args.seed) if lens == "fisheye" else None
    except ValueError as exc:
        raise CliError(str(exc)) from None
    start = time.perf_counter()
    bar, update = _progress("simulating")
    with bar:
        truth = write_dataset(out, config, pattern=pattern, camera=camera, progress=update,
                              workers=args.workers)
    elapsed = time.perf_counter() - start
    blurry = [f for f in truth.frames if f.kind == "blurry"]
    print(f"simulated {count(len(truth.frames), 'frame')} ({config.sharp} sharp, {len(blurry)} blurry) "
          f"in {elapsed:.1f} s into {out}")
    if blurry:
        import numpy as np

        med = [float(np.median(f.blur_length[f.visible])) for f in blurry]
        print(f"  blurry frames: median feature blur {min(med):.1f} to {max(med):.1f} px")
    print(f"  ground truth: {out / 'ground_truth.json'}")


def cmd_synth(args: argparse.Namespace) -> int:
    """Simulate sharp and blurry frames of the star target with exact ground truth
    (ground_truth.json; docs/synthetic-data.md). Prints the frames written and the blurry frames'
    blur."""
    out = Path(args.out)
    _check_empty_output(out, args.overwrite)
    pattern = load_pattern(args.pattern) if args.pattern else None
    _simulate(out, args, pattern)
    return 0


def _pipeline_settings(args: argparse.Namespace):
    """The pipeline's settings from the options of ``calibrate`` and ``demo``."""
    from blurcalib.calib.bundle import BundleSettings
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
                                  bundle=BundleSettings(device=device)),
            lens_correction=not args.no_lens_correction,
            trust=TrustSettings(validation=ValidationSettings(method=args.validation, folds=args.folds)),
            rolling_shutter=RollingShutterSettings(args.rolling_shutter))
        return PipelineSettings(extraction, calibration, workers=args.workers, cluster=args.cluster)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _run_pipeline(sharp: list[Path], blurry: list[Path], pattern: StarPattern, out: Path,
                  args: argparse.Namespace, features: Path | None = None, mixed: Sequence = ()):
    """Run the pipeline on frames (``sharp`` and ``blurry``, or ``mixed`` frames classified by
    their own blur), or on a feature file (``features``), and print its figures."""
    from blurcalib.calib.trust import summary_lines
    from blurcalib.pipeline.run import PipelineError, run_from_features, run_pipeline
    from blurcalib.runs.events import FrameDone, RunEvent

    bars: dict[str, tqdm] = {}

    def update(stage: str, event: RunEvent) -> None:
        if not isinstance(event, FrameDone):
            return
        if stage not in bars:
            bars[stage] = tqdm(total=event.total, desc=f"extracting {stage}", unit="frame",
                               file=sys.stderr, dynamic_ncols=True, disable=None)
        bars[stage].n = event.done
        bars[stage].set_postfix_str(f"{event.record.frame}: {event.record.status.value}", refresh=True)

    try:
        if features is not None:
            report = run_from_features(features, pattern, out, _pipeline_settings(args), args.image_size,
                                       overwrite=args.overwrite)
        else:
            report = run_pipeline(sharp, blurry, pattern, out, _pipeline_settings(args), update,
                                  overwrite=args.overwrite, mixed=mixed)
    except PipelineError as exc:
        raise CliError(str(exc)) from None
    finally:
        for bar in bars.values():
            bar.close()
    cal = report.calibration
    print(f"sharp-set calibration ({cal['model']}): {count(cal['num_frames'], 'frame')}, "
          f"median {cal['median_error_px']:.4f} px, RMS {cal['rms_error_px']:.4f} px")
    if report.parametric_choice is not None and report.parametric_choice["summary"]:
        print(report.parametric_choice["summary"])
    if report.generic_failure:
        print(f"warning: {report.generic_failure}")
    if report.assessment_failure:
        print(f"warning: no assessment: {report.assessment_failure}")
    if report.generic is not None:
        g = report.generic
        print(f"generic calibration ({g['route']} route): {g['grid_width']}x{g['grid_height']} grid, "
              f"{count(g['frames'], 'frame')} ({g['blurry_frames']} blurry), "
              f"median {g['median_error_px']:.4f} px, RMS {g['rms_error_px']:.4f} px")
        fit = "generic, sharp + blurry frames" if g["blurry_frames"] else "generic, sharp frames"
        for warning in g["warnings"]:
            print(f"warning: {fit}: {warning}")
    if report.generic_sharp is not None:
        for warning in report.generic_sharp["warnings"]:
            print(f"warning: generic, sharp frames: {warning}")
    if report.rolling_shutter is not None and report.rolling_shutter["message"]:
        print(report.rolling_shutter["message"])
    for line in summary_lines(report.to_dict()):
        print(line)
    for kind in ("sharp", "blurry"):
        print(f"{kind} frames: " + (", ".join(f"{v} {k}" for k, v in sorted(report.counts[kind].items()))
                                    or "none"))
    for kind, path in report.outputs.items():
        print(f"  {kind}: {path}")
    return report


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Calibrate a camera from one capture: extract star features from sharp and blurry frames,
    calibrate Brown-Conrady on the sharp ones, fit the generic camera to sharp and blurry frames
    together and assess it on frames it has not seen (docs/pipeline.md).

    Writes into --out the generic camera (calibration/intrinsics0.yaml, the reference tool's
    format), the Brown-Conrady camera (calibration/camera.yaml, OpenCV's), the observations
    (features.csv, features.bin), each frame's status (frames.csv) and report.json, written last
    (docs/results-format.md). Prints both cameras' reprojection errors, the held-out errors, the
    projection uncertainty and the frames used. Resumable: extracted frames are reused."""
    from blurcalib.io.frames import FrameError, frame_size, list_frames
    from blurcalib.io.sources import FrameInput

    pattern = load_pattern(args.pattern)
    given = [name for name, v in (("INPUT", args.frames), ("--sharp", args.sharp),
                                  ("--features", args.features)) if v]
    if len(given) != 1:
        raise CliError("give the frames (INPUT... or --sharp DIR [--blurry DIR]) or a feature file "
                       f"(--features FILE), one of them (got {', '.join(given) or 'none'})")
    if args.blurry and not args.sharp:
        raise CliError("--blurry DIR goes with --sharp DIR (or give every folder as INPUT)")
    if args.features is not None:
        if args.model == "generic":
            _check_grid([_features_image_size(Path(args.features), args.image_size)], args.cell_px)
        _run_pipeline([], [], pattern, Path(args.out), args, features=Path(args.features))
        return 0
    if args.frames:
        mixed = _frame_inputs(args)
        if args.model == "generic":
            _check_grid(map(FrameInput.size, mixed), args.cell_px)
        _run_pipeline([], [], pattern, Path(args.out), args, mixed=mixed)
        return 0
    try:
        sharp = list_frames([args.sharp])
        blurry = list_frames([args.blurry]) if args.blurry else []
    except FrameError as exc:
        raise CliError(str(exc)) from None
    if args.model == "generic":
        _check_grid(map(frame_size, sharp), args.cell_px)
    _run_pipeline(sharp, blurry, pattern, Path(args.out), args)
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


def cmd_demo(args: argparse.Namespace) -> int:
    """Simulate the default dataset (20 sharp and 60 blurry 1280x720 frames; --lens fisheye: a
    fisheye lens of --fov degrees) into OUT/data, run calibrate on it into OUT/calibration and
    print each camera against the true one. A complete dataset is reused, and the calibration
    resumes where it stopped."""
    from blurcalib.io.frames import list_frames
    from blurcalib.io.results import read_feature_table
    from blurcalib.sim.evaluate import evaluate_features
    from blurcalib.sim.truth import GROUND_TRUTH_FILE, load_ground_truth

    out = Path(args.out)
    data = out / "data"
    if (data / GROUND_TRUTH_FILE).is_file() and not args.overwrite:
        from blurcalib.camera.parametric import BrownConrady

        lens = "standard" if isinstance(load_ground_truth(data).camera.model, BrownConrady) else "fisheye"
        if lens != args.lens:
            raise CliError(f"{data}: holds a simulated dataset of the {lens} lens, not --lens {args.lens}; "
                           "use another --out or --overwrite")
        print(f"reusing the simulated dataset in {data}")
    else:
        _check_empty_output(data, args.overwrite)
        _simulate(data, args, None)
    pattern = load_pattern(data / "pattern.yaml")
    _run_pipeline(list_frames([data / "sharp"]), list_frames([data / "blurry"]), pattern,
                  out / "calibration", args)
    truth = load_ground_truth(data)
    table = read_feature_table(out / "calibration" / "features.csv")
    acc = evaluate_features(table, truth, pattern)
    if acc:
        import numpy as np

        med = float(np.median([a.median for a in acc]))
        print(f"accuracy of the aligned blurry features against the true camera (pose refitted): "
              f"median over {count(len(acc), 'frame')} {med:.4f} px "
              f"(per frame {min(a.median for a in acc):.4f} to {max(a.median for a in acc):.4f} px)")
    from blurcalib.sim.accuracy import camera_accuracy_lines

    print("\n".join(camera_accuracy_lines(out / "calibration", truth.camera)))
    return 0


def cmd_extract(args: argparse.Namespace) -> int:
    """Extract star features, PSFs and per-block figures from frames. Each frame is classified
    sharp or blurry by its own measured blur and seeded on its AprilTag, or in a video or folder
    from its nearest extracted neighbour; its blocks are grown from there.

    Writes features.csv, blocks.csv, psfs.npz, corners.csv and frames.csv into --out
    (docs/results-format.md); prints a status per frame and the totals. Resumable: a frame is
    redone only when its input, the pattern or the settings changed, or when it failed."""
    from blurcalib.extract.frame import ExtractSettings
    from blurcalib.io.record import FrameStatus
    from blurcalib.runs.events import FrameDone, RunEvent
    from blurcalib.runs.folder import extract_to_folder

    pattern = load_pattern(args.pattern)
    paths = _frame_inputs(args)
    if args.sharp and args.kind not in ("auto", "sharp"):
        raise CliError(f"--sharp contradicts --kind {args.kind}")
    kind = "sharp" if args.sharp else args.kind
    try:
        # --kind sharp: calibrate's sharp settings (ExtractSettings.sharp), so that its runs reuse these
        base = ExtractSettings.sharp() if kind == "sharp" else ExtractSettings(kind=kind,
                                                                               sharp_below_px=args.sharp_below)
        window = replace(base.window, start=args.psf_size) if args.psf_size else base.window
        deconv = replace(base.deconv, device=check_device(args.device))
    except ValueError as exc:
        raise CliError(str(exc)) from None
    grow = replace(base.grow, final_fit_frames=args.final_fit,
                   psf_field=base.grow.psf_field and not args.no_psf_field)
    settings = replace(base, window=window, deconv=deconv, grow=grow, local_alignment=args.local_alignment)
    bar = tqdm(total=len(paths), desc="extracting", unit="frame", file=sys.stderr,
               dynamic_ncols=True, disable=None)

    def update(event: RunEvent) -> None:
        if not isinstance(event, FrameDone):
            return
        row = event.record
        bar.n = event.done
        bar.set_postfix_str(f"{row.frame}: {row.status.value} {row.features} features", refresh=True)
        if row.status is not FrameStatus.OK:
            tqdm.write(f"{row.frame}: {row.status.value}: {row.message}", file=sys.stderr)

    with bar:
        summary = extract_to_folder(paths, pattern, Path(args.out), settings,
                                    workers=args.workers, progress=update,
                                    overwrite=args.overwrite, cluster=args.cluster)
    total_features = sum(r.features for r in summary.records)
    ok = sum(r.status is FrameStatus.OK for r in summary.records)
    print(f"{ok}/{count(len(summary.records), 'frame')} ok, {count(total_features, 'feature')}"
          + (f" ({count(len(summary.skipped), 'frame')} already done, skipped)" if summary.skipped else ""))
    for kind, path in summary.outputs.items():
        print(f"  {kind}: {path}")
    return 0 if ok else 1


def _frame_inputs(args: argparse.Namespace) -> list:
    """The frames of the positional inputs (folders, images, videos) with ``--every`` and
    ``--max-frames`` (:func:`blurcalib.io.sources.frame_inputs`)."""
    from blurcalib.io.frames import FrameError
    from blurcalib.io.sources import frame_inputs

    try:
        return frame_inputs(args.frames, every=args.every, max_frames=args.max_frames)
    except FrameError as exc:
        raise CliError(str(exc)) from None


def cmd_experiment(args: argparse.Namespace) -> int:
    """Reproduce one of the paper's experiments on simulated data (docs/experiments.md); the
    options of each are in blurcalib experiment NAME --help."""
    from blurcalib.paper import alignment, generic, patterns, psf_quality, threshold_sweep

    runners = {"patterns": patterns.main, "alignment": alignment.main,
               "psf-quality": psf_quality.main, "threshold-sweep": threshold_sweep.main,
               "generic": generic.main}
    return runners[args.name](args.rest)


def cmd_view(args: argparse.Namespace) -> int:
    """Start the browser app (app.py of the source checkout); every option goes to the app."""
    import subprocess

    app = Path(__file__).resolve().parents[1] / "app.py"
    if not app.is_file():
        raise CliError("the browser app (app.py, views/, state/) ships with the source checkout; "
                       "run blurcalib from a checkout set up with `bash scripts/setup.sh`")
    argv = [sys.executable, str(app), *args.rest]
    return subprocess.call(argv)


# --------------------------------------------------------------------------------- parser
def _default(func: Callable, name: str) -> object:
    """The default of ``func``'s parameter ``name``: the option's default, said once."""
    return inspect.signature(func).parameters[name].default


def _plain(doc: str | None) -> str:
    """A docstring as help text: without reST's double backticks."""
    return (doc or "").replace("``", "")


def _add_lens_options(p: argparse._ActionsContainer) -> None:
    """The simulated lens of ``synth`` and ``demo``."""
    p.add_argument("--lens", choices=["standard", "fisheye"], default="standard",
                   help="standard: a 90 degree Brown-Conrady lens like a RealSense D435I's; fisheye: a "
                        "Kannala-Brandt lens of --fov horizontal field whose image circle is 200 degrees "
                        "(both 1280x720 px with a smooth lens deviation of 0.3 px; default %(default)s)")
    p.add_argument("--fov", type=float, metavar="DEG",
                   help=f"horizontal field of view of --lens fisheye, deg, up to 200 "
                        f"(default {FISHEYE_FOV:g})")


def _add_synth_options(p: argparse._ActionsContainer, rolling_shutter: bool = True) -> None:
    from blurcalib.sim.synth import SynthConfig

    g = p.add_argument_group("simulation")
    g.add_argument("--sharp", type=int, default=SynthConfig.sharp, metavar="N",
                   help="number of sharp frames (default %(default)s)")
    g.add_argument("--blurry", type=int, default=SynthConfig.blurry, metavar="N",
                   help="number of blurry frames (default %(default)s)")
    g.add_argument("--blur-min", type=float, default=SynthConfig.blur_min_px, metavar="PX",
                   help="smallest median blur length of a blurry frame, px (default %(default)s)")
    g.add_argument("--blur-max", type=float, default=SynthConfig.blur_max_px, metavar="PX",
                   help="largest median blur length of a blurry frame, px (default %(default)s)")
    g.add_argument("--max-tilt", type=float, default=SynthConfig.max_tilt_deg, metavar="DEG",
                   help="largest angle between the target's normal and the optical axis (a fisheye: the "
                        "ray the target is seen along), deg (default %(default)s)")
    g.add_argument("--noise", type=float, default=SynthConfig.noise_sigma, metavar="SIGMA",
                   help="noise standard deviation at mid grey, grey levels (default %(default)s)")
    g.add_argument("--seed", type=int, default=SynthConfig.seed, metavar="N",
                   help="random seed (default %(default)s)")
    if rolling_shutter:
        g.add_argument("--rolling-shutter", type=readout_ratio, default=SynthConfig.rolling_shutter,
                       metavar="R", help="readout time of a rolling shutter in exposure times: row v is "
                                         "exposed over its own window (default %(default)s: a global "
                                         "shutter; docs/rolling-shutter.md)")
    g.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), metavar="N",
                   help="frames rendered in parallel (default 2, or 1 on a one-core machine)")
    g.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty output folder")


def _add_run_options(p: argparse._ActionsContainer, workers: bool = True) -> None:
    g = p.add_argument_group("where it runs")
    if workers:
        g.add_argument("--workers", type=positive_int, default=available_cores(), metavar="N",
                       help="frames processed in parallel, one process each (default: one per core); "
                            "the calibration then computes with as many threads")
    g.add_argument("--threads", type=positive_int, default=1, metavar="N",
                   help="compute threads of this process, for frames it runs itself (--workers 1); "
                        "worker processes use one (default %(default)s; more only helps on an idle machine)")
    g.add_argument("--cluster", metavar="ADDRESS", type=cluster_address,
                   help="run frames as tasks on this Dask scheduler, e.g. tcp://host:8786 (docs/cluster.md)")
    g.add_argument("--device", default="cpu",
                   help="torch device of the block solver and the bundle adjustment: cpu, cuda or cuda:N "
                        "(default %(default)s); workers share one GPU badly, so with many cores cpu "
                        "extracts a folder faster (docs/calibration.md)")


def _add_fit_options(p: argparse._ActionsContainer, which: str) -> None:
    p.add_argument("--final-fit", choices=get_args(FinalFitFrames), default=GrowSettings.final_fit_frames,
                   help=f"which {which}frames without the path-PSF field get a final fit of each block "
                        "over 1.5 x its square: those whose PSF window grew with the blur (adaptive), "
                        "all (more accurate features, about 1 s more per frame with little blur) or "
                        "none (default %(default)s; docs/deconvolution.md)")
    p.add_argument("--no-psf-field", action="store_true",
                   help=f"fit {which}frames with free PSFs only: no field of motion-path PSFs in frames "
                        "whose blur is long (for a rolling shutter, whose paths bend with the image row; "
                        "docs/deconvolution.md; sharp frames never use it)")


def _add_pipeline_options(p: argparse._ActionsContainer) -> None:
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
    _add_fit_options(g, "blurry ")
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
    g = p.add_argument_group("assessment")
    g.add_argument("--validation", choices=list(get_args(ValidationMethod)),
                   default=ValidationSettings.method,
                   help="held-out validation of the cameras: k-fold over frames, each held-out frame "
                        "scored by cameras fitted without it, or none (default %(default)s; "
                        "docs/validation.md)")
    g.add_argument("--folds", type=fold_count, default=ValidationSettings.folds, metavar="K",
                   help="number of folds of the validation (default %(default)s; needs at least "
                        f"{ValidationSettings.min_frames} frames)")


def _add_source_options(p: argparse._ActionsContainer, nargs: str = "+") -> None:
    """The frame inputs (positional ``INPUT...``, ``nargs``), ``--every``, ``--max-frames`` and
    ``--sharp-below``, read by :func:`_frame_inputs`."""
    from blurcalib.extract.frame import SHARP_BELOW_PX

    p.add_argument("frames", nargs=nargs, metavar="INPUT",
                   help="folders of frames, image files (png, jpg, tiff, bmp; 8 or 16 bit, colour is "
                        "converted to grey) or videos (mp4, avi, mkv, mov); a video's frames are named "
                        "VIDEO#000123")
    p.add_argument("--every", type=positive_int, default=1, metavar="N",
                   help="keep every N-th frame of each folder and video (default %(default)s)")
    p.add_argument("--max-frames", type=positive_int, default=None, metavar="N",
                   help="keep at most N frames of each folder and video (default: all)")
    p.add_argument("--sharp-below", type=positive_number, default=SHARP_BELOW_PX, metavar="PX",
                   help="frames whose measured blur (median blur extent of the tag ring's PSFs) is "
                        "below this are sharp, px (default %(default)s; docs/pipeline.md)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="blurcalib",
        description="Sub-pixel star features and spatially varying PSFs from motion-blurred "
                    "calibration frames, and the generic camera calibrated from sharp and blurry "
                    "frames together.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="simulate the default dataset and run the pipeline on it",
                       description=_plain(cmd_demo.__doc__))
    p.add_argument("--out", default=str(DEFAULT_DEMO_DIR), metavar="DIR",
                   help="output folder (default %(default)s); its data/ is reused when complete")
    _add_lens_options(p)
    _add_synth_options(p, rolling_shutter=False)
    _add_pipeline_options(p)
    _add_run_options(p, workers=False)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("calibrate", help="the whole pipeline on one capture: frames in, cameras out",
                       description=_plain(cmd_calibrate.__doc__))
    g = p.add_argument_group("inputs")
    _add_source_options(g, nargs="*")
    g.add_argument("--sharp", metavar="DIR",
                   help="folder of sharp frames (instead of INPUT: the kinds given, not measured)")
    g.add_argument("--blurry", metavar="DIR",
                   help="folder of blurry frames, with --sharp (optional: a sharp-only calibration)")
    g.add_argument("--features", metavar="FILE",
                   help="calibrate from a feature file instead of frames: the reference tool's dataset "
                        "(.bin) or a blurcalib features.csv (rows flagged BLURRY_FRAME get a free shift)")
    g.add_argument("--image-size", type=image_size, metavar="WxH",
                   help="image size of a features.csv, px (a .bin holds its own)")
    g.add_argument("--pattern", required=True, metavar="FILE", help="pattern YAML of the target")
    g = p.add_argument_group("output")
    g.add_argument("--out", required=True, metavar="DIR", help="output folder (resumable)")
    g.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder that is not a calibrate output")
    _add_run_options(p)
    _add_pipeline_options(p)
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("pattern", help="write a printable star target (PDF, PNG, YAML)",
                       description=_plain(cmd_pattern.__doc__))
    p.add_argument("--out", required=True, metavar="PATH",
                   help="output path without extension, e.g. targets/star_a4")
    p.add_argument("--page", type=page_size, default=PAGE_SIZES_MM["A4"],
                   help="A4, letter or WIDTHxHEIGHT in mm (default A4)")
    p.add_argument("--square-mm", type=float, default=_default(layout_pattern, "approx_square_length_mm"),
                   metavar="MM", help="approximate square length, mm (default %(default)s); adjusted to "
                                      "fit the page")
    p.add_argument("--tag", type=int, default=_default(layout_pattern, "tag_index"), metavar="ID",
                   help="tag36h11 id (default %(default)s)")
    p.add_argument("--segments", type=int, default=_default(layout_pattern, "num_star_segments"),
                   metavar="N", help="star segments, a multiple of 4 (default %(default)s)")
    p.add_argument("--margin-mm", type=float, default=_default(layout_pattern, "margin_mm"), metavar="MM",
                   help="page margin, mm (default %(default)s)")
    p.add_argument("--dpi", type=positive_number, default=300.0,
                   help="PNG resolution (default %(default)s; the PNG may have at most 150 megapixels)")
    p.add_argument("--formats", default="pdf,png,yaml", metavar="LIST",
                   help="comma list of pdf, png, yaml (default %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace existing files")
    p.set_defaults(func=cmd_pattern)

    p = sub.add_parser("extract", help="extract star features and PSFs from frames",
                       description=_plain(cmd_extract.__doc__))
    g = p.add_argument_group("inputs")
    _add_source_options(g)
    g.add_argument("--pattern", required=True, metavar="FILE", help="pattern YAML of the target")
    g = p.add_argument_group("output")
    g.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (resumable: done frames are skipped)")
    g.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder that is not an extract output")
    g = p.add_argument_group("extraction")
    g.add_argument("--kind", choices=["auto", "sharp", "blurry"], default="auto",
                   help="auto: each frame is sharp or blurry by its own measured blur (--sharp-below); "
                        f"sharp: small PSF window ({SHARP_START} px) and sharp-frame flags; "
                        "blurry: a window that fits the blur (default %(default)s)")
    g.add_argument("--sharp", action="store_true", help="the same as --kind sharp")
    g.add_argument("--psf-size", type=psf_window, default=0, metavar="PX",
                   help=f"starting PSF window side, odd px; it grows with the blur (default "
                        f"{WindowPolicy.start} for blurry frames, {SHARP_START} for sharp ones)")
    g.add_argument("--local-alignment", action="store_true",
                   help="move star centres by the local-alignment translations")
    _add_fit_options(g, "")
    _add_run_options(p)
    p.set_defaults(func=cmd_extract)

    p = sub.add_parser("experiment", help="reproduce one of the paper's experiments",
                       description=_plain(cmd_experiment.__doc__))
    p.add_argument("name", choices=["patterns", "alignment", "psf-quality", "threshold-sweep", "generic"],
                   metavar="NAME",
                   help="patterns: star vs checkerboard PSF recovery (fig:exp2_test); "
                        "alignment: global alignment verification (tab:exp4, fig:exp41, fig:exp42); "
                        "psf-quality: PSF field and quality scatter plots (fig:exp_real1, "
                        "fig:exp_real2); threshold-sweep: error against tau_L (fig:exp_real3); "
                        "generic: generic camera from sharp and blurry frames vs the truth")
    p.add_argument("rest", nargs=argparse.REMAINDER, metavar="OPTIONS",
                   help="options of the experiment (see blurcalib experiment NAME --help)")
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("view", help="start the browser app (viser)", description=_plain(cmd_view.__doc__),
                       add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER, metavar="OPTIONS",
                   help="[FOLDER] [--pattern P.yaml] [--out DIR] [--port N] (see python app.py --help)")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("synth", help="simulate sharp and blurry frames with ground truth",
                       description=_plain(cmd_synth.__doc__))
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--pattern", metavar="FILE", help="pattern YAML (default: the reference A4 17x24 target)")
    _add_lens_options(p)
    _add_synth_options(p)
    p.set_defaults(func=cmd_synth)
    return parser

def _output_lock(args: argparse.Namespace):
    """The lock on the output folder of a command that writes one (:func:`blurcalib.io.atomic.output_lock`):
    a second run into the same folder is refused while this one runs."""
    if args.func in (cmd_calibrate, cmd_extract, cmd_synth, cmd_demo):
        return output_lock(args.out)
    return nullcontext()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``blurcalib`` console script and ``python -m blurcalib``."""
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["view"]:  # every option goes to the app, --help included
        args = argparse.Namespace(func=cmd_view, rest=argv[1:])
    else:
        args = parser.parse_args(argv)
    for option in ("threads", "workers"):
        if getattr(args, option, None) is not None:
            value, note = capped_count(getattr(args, option), f"--{option}")
            setattr(args, option, value)
            if note is not None:
                print(f"blurcalib: note: {note}", file=sys.stderr)
    try:
        configure_threads(getattr(args, "threads", None))
        keep_large_allocations()
        with _output_lock(args):
            return int(args.func(args))
    except (CliError, PatternFileError, OutputError, ClusterError, DeviceError) as exc:
        print(f"blurcalib: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a quota or a read-only file system: one line, not a traceback
        error = storage_error(exc)
        if error is None:
            raise
        print(f"blurcalib: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("blurcalib: interrupted; finished files are kept", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
