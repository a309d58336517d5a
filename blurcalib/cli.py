"""The ``blurcalib`` command line: one subcommand per job.

Every subcommand reports bad input as ``blurcalib: error: <file>: <problem>`` on stderr and
exits with status 2; files are written atomically, so an interrupted or failed run leaves no
half-written output behind.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import get_args

from tqdm import tqdm

from blurcalib.cluster import ClusterError
from blurcalib.fileio import OutputError
from blurcalib.grow import FinalFitFrames, GrowSettings
from blurcalib.pattern import PAGE_SIZES_MM, PatternFileError, StarPattern, layout_pattern, load_pattern
from blurcalib.runtime import DeviceError, available_cores, check_device, configure_threads

DEFAULT_DEMO_DIR = Path("out") / "demo"


class CliError(Exception):
    """A user-facing error: printed without a traceback, exit status 2."""


def _page_size(text: str) -> tuple[float, float]:
    if text in PAGE_SIZES_MM:
        return PAGE_SIZES_MM[text]
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"page must be one of {', '.join(PAGE_SIZES_MM)} or WIDTHxHEIGHT in mm, got {text!r}"
        ) from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"page size must be positive, got {text!r}")
    return (w, h)


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
    """``blurcalib pattern``: a printable target (vector PDF, PNG, YAML)."""
    from blurcalib.printable import write_printable

    try:
        pattern = layout_pattern(page_size_mm=args.page, approx_square_length_mm=args.square_mm,
                                 tag_index=args.tag, num_star_segments=args.segments,
                                 margin_mm=args.margin_mm)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    formats = tuple(f.strip() for f in args.formats.split(",") if f.strip())
    try:
        paths = write_printable(pattern, Path(args.out), dpi=args.dpi, formats=formats)
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


def _check_empty_output(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise CliError(f"{out}: output path exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise CliError(f"{out}: output folder is not empty (use --overwrite to replace its "
                       "dataset)")


def _simulate(out: Path, args: argparse.Namespace, pattern: StarPattern | None) -> None:
    from blurcalib.synth import SynthConfig, write_dataset

    try:
        config = SynthConfig(sharp=args.sharp, blurry=args.blurry, blur_min_px=args.blur_min,
                             blur_max_px=args.blur_max, max_tilt_deg=args.max_tilt,
                             noise_sigma=args.noise, seed=args.seed)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    start = time.perf_counter()
    bar, update = _progress("simulating")
    with bar:
        truth = write_dataset(out, config, pattern=pattern, progress=update, workers=args.workers)
    elapsed = time.perf_counter() - start
    blurry = [f for f in truth.frames if f.kind == "blurry"]
    print(f"simulated {len(truth.frames)} frames ({config.sharp} sharp, {len(blurry)} blurry) "
          f"in {elapsed:.1f} s into {out}")
    if blurry:
        import numpy as np

        med = [float(np.median(f.blur_length[f.visible])) for f in blurry]
        print(f"  blurry frames: median feature blur {min(med):.1f} to {max(med):.1f} px")
    print(f"  ground truth: {out / 'ground_truth.json'}")


def cmd_synth(args: argparse.Namespace) -> int:
    """``blurcalib synth``: simulate sharp and blurry frames with ground truth."""
    out = Path(args.out)
    _check_empty_output(out, args.overwrite)
    pattern = load_pattern(args.pattern) if args.pattern else None
    _simulate(out, args, pattern)
    return 0


def _pipeline_settings(args: argparse.Namespace):
    from blurcalib.pipeline import PipelineSettings
    from blurcalib.quality import QualitySettings

    try:
        return PipelineSettings(
            quality=QualitySettings(tau_be=args.tau_be, tau_loss=args.tau_loss,
                                    min_sigma_major=args.min_sigma_major),
            loss=args.loss, bias=args.bias, workers=args.workers, cluster=args.cluster,
            local_alignment=args.local_alignment, model=args.model, route=args.route, cell_px=args.cell_px,
            lens_correction=not args.no_lens_correction, final_fit=args.final_fit,
            psf_field=not args.no_psf_field)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _run_pipeline(sharp: list[Path], blurry: list[Path], pattern: StarPattern, out: Path,
                  args: argparse.Namespace):
    from blurcalib.pipeline import PipelineError, run_pipeline

    bars: dict[str, tqdm] = {}

    def update(stage: str, done: int, total: int, row: dict) -> None:
        if stage not in bars:
            bars[stage] = tqdm(total=total, desc=f"extracting {stage}", unit="frame",
                               file=sys.stderr, dynamic_ncols=True, disable=None)
        bars[stage].n = done
        bars[stage].set_postfix_str(f"{row['frame']}: {row['status']}", refresh=True)

    try:
        report = run_pipeline(sharp, blurry, pattern, out, _pipeline_settings(args), update,
                              overwrite=args.overwrite)
    except PipelineError as exc:
        raise CliError(str(exc)) from None
    finally:
        for bar in bars.values():
            bar.close()
    cal = report.calibration
    print(f"sharp-set calibration: {cal['num_frames']} frames, median {cal['median_error_px']:.4f} px, "
          f"RMS {cal['rms_error_px']:.4f} px")
    if report.generic is not None:
        g = report.generic
        print(f"generic calibration ({g['route']} route): {g['grid_width']}x{g['grid_height']} grid, "
              f"{g['frames']} frames ({g['blurry_frames']} blurry), median {g['median_error_px']:.4f} px, "
              f"RMS {g['rms_error_px']:.4f} px")
        for warning in g["warnings"]:
            print(f"warning: {warning}")
    for kind in ("sharp", "blurry"):
        print(f"{kind} frames: " + ", ".join(f"{v} {k}" for k, v in sorted(report.counts[kind].items())))
    for kind, path in report.outputs.items():
        print(f"  {kind}: {path}")
    return report


def cmd_calibrate(args: argparse.Namespace) -> int:
    """``blurcalib calibrate``: extract, calibrate the sharp set, filter, align the blurry set."""
    from blurcalib.frames import FrameError, list_frames

    pattern = load_pattern(args.pattern)
    try:
        sharp = list_frames([args.sharp])
        blurry = list_frames([args.blurry]) if args.blurry else []
    except FrameError as exc:
        raise CliError(str(exc)) from None
    _run_pipeline(sharp, blurry, pattern, Path(args.out), args)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """``blurcalib demo``: simulate a dataset, run the whole pipeline on it, measure accuracy."""
    from blurcalib.evaluate import evaluate_features
    from blurcalib.frames import list_frames
    from blurcalib.results import read_feature_table
    from blurcalib.synth import GROUND_TRUTH_FILE, load_ground_truth

    out = Path(args.out)
    data = out / "data"
    if (data / GROUND_TRUTH_FILE).is_file() and not args.overwrite:
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
              f"median over {len(acc)} frames {med:.4f} px "
              f"(per frame {min(a.median for a in acc):.4f} to {max(a.median for a in acc):.4f} px)")
    _print_camera_accuracy(out / "calibration", pattern, truth, args)
    return 0


def _print_camera_accuracy(out: Path, pattern: StarPattern, truth, args: argparse.Namespace) -> None:
    """The demo's answer to "is the camera better because of the blurry frames": each camera's
    projection error against the true camera over the image (after the best-fit rotation), for
    the parametric camera, the generic camera of the sharp frames alone, and the generic camera
    of sharp and blurry frames together."""
    from blurcalib.calibrate import load_calibration
    from blurcalib.evaluate import camera_accuracy
    from blurcalib.joint import JointSettings, calibrate_generic
    from blurcalib.refcamera import read_generic_yaml
    from blurcalib.results import FeatureFlags, read_feature_table

    calibration = load_calibration(out / "calibration")
    cameras = [("parametric, sharp frames", calibration.camera)]
    intrinsics = out / "calibration" / "intrinsics0.yaml"
    if intrinsics.is_file():
        table = read_feature_table(out / "features.csv")  # the calibration's own: lens-corrected
        sharp = table.select((table.flags & int(FeatureFlags.SHARP_FRAME)) > 0)
        size = (calibration.camera.width, calibration.camera.height)
        alone = calibrate_generic(sharp, None, calibration, pattern, size,
                                  JointSettings(cell_px=args.cell_px, route=args.route))
        cameras += [("generic, sharp frames", alone.model),
                     ("generic, sharp + blurry frames", read_generic_yaml(intrinsics))]
    print("camera against the true camera over the image (px, after the best-fit rotation; shape: after "
          "the best-fit focal lengths and principal point too, docs/generic.md):")
    for label, camera in cameras:
        a = camera_accuracy(truth.camera, camera)
        print(f"  {label:<32} median {a.median:.4f}, p95 {a.p95:.4f}, max {a.max:.4f} "
              f"({100 * a.defined:.0f}% of the image calibrated); shape median {a.shape_median:.4f}, "
              f"focal scale {a.scale_px:+.4f} at the corners")


def cmd_extract(args: argparse.Namespace) -> int:
    """``blurcalib extract``: star features, PSFs and per-block figures from frames."""
    from blurcalib.deconv import DeconvSettings
    from blurcalib.extract import ExtractSettings, extract_to_folder
    from blurcalib.frames import FrameError, list_frames

    pattern = load_pattern(args.pattern)
    try:
        paths = list_frames(args.frames)
    except FrameError as exc:
        raise CliError(str(exc)) from None
    kernel = args.psf_size or (7 if args.sharp else 17)
    try:
        deconv = DeconvSettings(kernel_size=kernel, device=check_device(args.device))
    except ValueError as exc:
        raise CliError(str(exc)) from None
    # --sharp: calibrate's sharp settings (ExtractSettings.sharp), so that its runs reuse these
    base = ExtractSettings.sharp() if args.sharp else ExtractSettings()
    grow = replace(base.grow, final_fit_frames=args.final_fit,
                   psf_field=base.grow.psf_field and not args.no_psf_field)
    settings = replace(base, deconv=deconv, grow=grow, local_alignment=args.local_alignment)
    bar = tqdm(total=len(paths), desc="extracting", unit="frame", file=sys.stderr,
               dynamic_ncols=True, disable=None)
    counts: dict[str, int] = {}

    def update(done: int, total: int, row: dict) -> None:
        counts[row["status"]] = counts.get(row["status"], 0) + 1
        bar.n = done
        bar.set_postfix_str(f"{row['frame']}: {row['status']} {row['features']} features",
                            refresh=True)
        if row["status"] != "ok":
            tqdm.write(f"{row['frame']}: {row['status']}: {row['message']}", file=sys.stderr)

    with bar:
        summary = extract_to_folder(paths, pattern, Path(args.out), settings,
                                    workers=args.workers, progress=update,
                                    overwrite=args.overwrite, cluster=args.cluster)
    total_features = sum(int(r.get("features", 0)) for r in summary.frames)
    ok = sum(r["status"] == "ok" for r in summary.frames)
    print(f"{ok}/{len(summary.frames)} frames ok, {total_features} features"
          + (f" ({len(summary.skipped)} frames already done, skipped)" if summary.skipped else ""))
    for kind, path in summary.outputs.items():
        print(f"  {kind}: {path}")
    return 0 if ok else 1


def cmd_experiment(args: argparse.Namespace) -> int:
    """``blurcalib experiment NAME``: reproduce one of the paper's experiments."""
    from blurcalib.experiments import alignment, generic, patterns, psf_quality, threshold_sweep

    runners = {"patterns": patterns.main, "alignment": alignment.main,
               "psf-quality": psf_quality.main, "threshold-sweep": threshold_sweep.main,
               "generic": generic.main}
    return runners[args.name](args.rest)


def cmd_view(args: argparse.Namespace) -> int:
    """``blurcalib view``: start the browser app (``app.py`` of the source checkout)."""
    import subprocess

    app = Path(__file__).resolve().parents[1] / "app.py"
    if not app.is_file():
        raise CliError("the browser app (app.py, views/, state/) ships with the source checkout; "
                       "run blurcalib from a checkout set up with `bash scripts/setup.sh`")
    argv = [sys.executable, str(app), *args.rest]
    return subprocess.call(argv)


# --------------------------------------------------------------------------------- parser
def _add_synth_options(p: argparse.ArgumentParser, sharp: int, blurry: int) -> None:
    p.add_argument("--sharp", type=int, default=sharp, help="number of sharp frames (%(default)s)")
    p.add_argument("--blurry", type=int, default=blurry,
                   help="number of blurry frames (%(default)s)")
    p.add_argument("--blur-min", type=float, default=2.0,
                   help="smallest median blur length of a blurry frame, px (%(default)s)")
    p.add_argument("--blur-max", type=float, default=20.0,
                   help="largest median blur length of a blurry frame, px (%(default)s)")
    p.add_argument("--max-tilt", type=float, default=60.0,
                   help="largest angle between optical axis and target normal, deg (%(default)s)")
    p.add_argument("--noise", type=float, default=2.0,
                   help="noise standard deviation at mid grey, grey levels (%(default)s)")
    p.add_argument("--seed", type=int, default=0, help="random seed (%(default)s)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                   help="frames rendered in parallel (%(default)s)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty output folder")


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _add_run_options(p: argparse.ArgumentParser, workers: bool = True) -> None:
    if workers:
        p.add_argument("--workers", type=_positive, default=available_cores(),
                       help="frames processed in parallel, one process each (%(default)s: one per core)")
    p.add_argument("--threads", type=_positive, default=1,
                   help="compute threads of this process, for frames it runs itself (--workers 1); "
                        "worker processes use one (%(default)s; more only helps on an idle machine)")
    p.add_argument("--cluster", metavar="ADDRESS",
                   help="run frames as tasks on this Dask scheduler (tcp://host:8786; docs/cluster.md)")


def _add_fit_options(p: argparse.ArgumentParser, which: str) -> None:
    p.add_argument("--final-fit", choices=get_args(FinalFitFrames), default=GrowSettings.final_fit_frames,
                   help=f"which {which}frames without the path-PSF field get a final fit of each block "
                        "over 1.5 x its square: those whose PSF window grew with the blur, all (more "
                        "accurate features, about 1 s more per frame with little blur) or none "
                        "(%(default)s; docs/deconvolution.md)")
    p.add_argument("--no-psf-field", action="store_true",
                   help=f"fit {which}frames with free PSFs only: no field of motion-path PSFs in frames "
                        "whose blur is long (for a rolling shutter, whose paths bend with the image row; "
                        "docs/deconvolution.md; sharp frames never use it)")


def _add_pipeline_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tau-be", type=float, default=0.12,
                   help="largest PSF boundary energy kept (%(default)s)")
    p.add_argument("--tau-loss", type=float, default=30.0,
                   help="largest block loss kept, grey levels^2 (%(default)s)")
    p.add_argument("--min-sigma-major", type=float, default=0.0,
                   help="drop blurry frames whose centre median sigma_major is below this, px "
                        "(%(default)s: keep every frame; the paper's choice for its camera is 3.8)")
    p.add_argument("--loss", choices=["huber", "mean", "median"], default="huber",
                   help="robust loss of the global alignment (%(default)s)")
    p.add_argument("--bias", choices=["translation", "bilinear", "quadrants"], default="translation",
                   help="bias model of the global alignment (%(default)s)")
    p.add_argument("--local-alignment", action="store_true",
                   help="use the local-alignment translations for blurry frames")
    _add_fit_options(p, "blurry ")
    p.add_argument("--model", choices=["generic", "parametric"], default="generic",
                   help="camera model delivered: the generic B-spline ray grid fitted to sharp and blurry "
                        "frames together, or Brown-Conrady from the sharp set only (%(default)s)")
    p.add_argument("--route", choices=["joint", "aligned"], default="joint",
                   help="blurry frames in the generic fit: star centres with a free per-frame shift "
                        "(joint), or aligned to the parametric camera first, the paper's route (%(default)s)")
    p.add_argument("--cell-px", type=float, default=25.0,
                   help="cell length of the generic model's grid, px (%(default)s)")
    p.add_argument("--no-lens-correction", action="store_true",
                   help="keep star centres as extracted instead of removing the bias of block homographies "
                        "under the sharp-set camera's distortion (docs/generic.md)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="blurcalib",
        description="Sub-pixel star features and spatially varying PSFs from motion-blurred "
                    "calibration frames.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="simulate the default dataset and run the pipeline on it",
                       description=cmd_demo.__doc__)
    p.add_argument("--out", default=str(DEFAULT_DEMO_DIR),
                   help="output folder (%(default)s); its data/ is reused when complete")
    _add_synth_options(p, sharp=20, blurry=60)
    _add_pipeline_options(p)
    _add_run_options(p, workers=False)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("calibrate", help="the whole pipeline on folders of sharp and blurry frames",
                       description=cmd_calibrate.__doc__)
    p.add_argument("--sharp", required=True, help="folder of sharp frames")
    p.add_argument("--blurry", help="folder of blurry frames (optional: a sharp-only calibration)")
    p.add_argument("--pattern", required=True, help="pattern YAML of the target")
    p.add_argument("--out", required=True, help="output folder (resumable)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder that is not a calibrate output")
    _add_run_options(p)
    _add_pipeline_options(p)
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("pattern", help="write a printable star target (PDF, PNG, YAML)",
                       description=cmd_pattern.__doc__)
    p.add_argument("--out", required=True,
                   help="output path without extension, e.g. targets/star_a4")
    p.add_argument("--page", type=_page_size, default=PAGE_SIZES_MM["A4"],
                   help="A4, letter or WIDTHxHEIGHT in mm (A4)")
    p.add_argument("--square-mm", type=float, default=12.0,
                   help="approximate square length, mm (%(default)s); adjusted to fit the page")
    p.add_argument("--tag", type=int, default=0, help="tag36h11 id (%(default)s)")
    p.add_argument("--segments", type=int, default=16,
                   help="star segments, a multiple of 4 (%(default)s)")
    p.add_argument("--margin-mm", type=float, default=4.0, help="page margin, mm (%(default)s)")
    p.add_argument("--dpi", type=float, default=300.0, help="PNG resolution (%(default)s)")
    p.add_argument("--formats", default="pdf,png,yaml", help="comma list (%(default)s)")
    p.set_defaults(func=cmd_pattern)

    p = sub.add_parser("extract", help="extract star features and PSFs from frames",
                       description=cmd_extract.__doc__)
    p.add_argument("frames", nargs="+", help="image files or folders (png, jpg, tiff)")
    p.add_argument("--pattern", required=True, help="pattern YAML of the target")
    p.add_argument("--out", required=True, help="output folder (resumable: done frames are skipped)")
    p.add_argument("--sharp", action="store_true",
                   help="frames are sharp: small PSF window (7 px) and sharp-frame flags")
    p.add_argument("--psf-size", type=int, default=0,
                   help="PSF window side, odd px (17 for blurry, 7 with --sharp)")
    p.add_argument("--local-alignment", action="store_true",
                   help="move star centres by the local-alignment translations")
    _add_fit_options(p, "")
    _add_run_options(p)
    p.add_argument("--device", default="cpu", help="torch device for the block solver (cpu, cuda)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder that is not an extract output")
    p.set_defaults(func=cmd_extract)

    p = sub.add_parser("experiment", help="reproduce one of the paper's experiments",
                       description=cmd_experiment.__doc__)
    p.add_argument("name", choices=["patterns", "alignment", "psf-quality", "threshold-sweep", "generic"],
                   help="patterns: star vs checkerboard PSF recovery (fig:exp2_test); "
                        "alignment: global alignment verification (tab:exp4, fig:exp41, fig:exp42); "
                        "psf-quality: PSF field and quality scatter plots (fig:exp_real1, "
                        "fig:exp_real2); threshold-sweep: error against tau_L (fig:exp_real3); "
                        "generic: generic camera from sharp and blurry frames vs the truth (issue 9)")
    p.add_argument("rest", nargs=argparse.REMAINDER,
                   help="options of the experiment (see blurcalib experiment NAME --help)")
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("view", help="start the browser app (viser)", description=cmd_view.__doc__,
                       add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER,
                   help="[FOLDER] [--pattern P.yaml] [--port N] (see python app.py --help)")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("synth", help="simulate sharp and blurry frames with ground truth",
                       description=cmd_synth.__doc__)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--pattern", help="pattern YAML (default: the reference A4 17x24 target)")
    _add_synth_options(p, sharp=20, blurry=60)
    p.set_defaults(func=cmd_synth)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``blurcalib`` console script and ``python -m blurcalib``."""
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["view"]:  # every option goes to the app, --help included
        args = argparse.Namespace(func=cmd_view, rest=argv[1:])
    else:
        args = parser.parse_args(argv)
    try:
        configure_threads(getattr(args, "threads", None))
        return int(args.func(args))
    except (CliError, PatternFileError, OutputError, ClusterError, DeviceError) as exc:
        print(f"blurcalib: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("blurcalib: interrupted; finished files are kept", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
