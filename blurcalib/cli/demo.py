"""``blurcalib demo``: the default simulated dataset, calibrated and compared with the truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from blurcalib.cli.calibrate import add_pipeline_options, calibrate_and_report, pipeline_settings
from blurcalib.cli.common import CliError, add_run_options, check_empty_output, plain
from blurcalib.cli.synth import add_lens_options, add_rig_options, add_synth_options, simulate
from blurcalib.io.text import count
from blurcalib.target.pattern import load_pattern

DEFAULT_DEMO_DIR = Path("out") / "demo"
RIG_SETS = (8, 4)
"""``demo --rig``'s sharp and blurry image sets unless ``--sharp`` and ``--blurry`` are given."""
RIG_SCALE = 0.5
"""``demo --rig``'s image scale: two 640x360 cameras."""


def cmd_demo(args: argparse.Namespace) -> int:
    """Simulate the default dataset (20 sharp and 60 blurry 1280x720 frames; --lens fisheye: a
    fisheye lens of --fov degrees) into OUT/data, run calibrate on it into OUT/calibration and
    compare each camera with the true one. Prints a line per stage (also into OUT/demo.log when
    the output is not a terminal), then the result in words, the details, the figures written
    and what the terms mean. A complete dataset is reused, and the calibration resumes where it
    stopped. With --rig: a simulated stereo pair (8 sharp and 4 blurry image sets of two 640x360
    cameras 50 mm apart) through calibrate-rig, each camera and the extrinsics against the truth."""
    from blurcalib.sim.synth import SynthConfig

    if args.rig:
        args.sharp, args.blurry = (RIG_SETS[0] if args.sharp is None else args.sharp,
                                   RIG_SETS[1] if args.blurry is None else args.blurry)
        return _demo_rig(args)
    args.sharp = SynthConfig.sharp if args.sharp is None else args.sharp
    args.blurry = SynthConfig.blurry if args.blurry is None else args.blurry
    from blurcalib.io.frames import frame_size, list_frames
    from blurcalib.io.results import read_feature_table
    from blurcalib.pipeline.text import report_lines
    from blurcalib.sim.accuracy import camera_accuracy_lines, true_accuracies
    from blurcalib.sim.demo import DemoLog, figure_lines, result_lines, term_lines
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
        log = DemoLog(out)
        log.stage(f"1/4 reusing the simulated dataset in {data}")
    else:
        check_empty_output(data, args.overwrite)
        log = DemoLog(out)
        log.stage(f"1/4 simulating {args.sharp} sharp and {args.blurry} blurry frames into {data}")
        simulate(data, args, None)
    pattern = load_pattern(data / "pattern.yaml")
    sharp = list_frames([data / "sharp"])
    report = calibrate_and_report(sharp, list_frames([data / "blurry"]), pattern, out / "calibration", args,
                                  log=log)
    log.stage("4/4 comparing every camera with the true camera")
    truth = load_ground_truth(data)
    found = true_accuracies(out / "calibration", truth.camera)
    acc = evaluate_features(read_feature_table(out / "calibration" / "features.csv"), truth, pattern)
    details = report_lines(report)
    if acc:
        import numpy as np

        med = float(np.median([a.median for a in acc]))
        details.append(f"accuracy of the aligned blurry features against the true camera (pose refitted): "
                       f"median over {count(len(acc), 'frame')} {med:.4f} px (per frame "
                       f"{min(a.median for a in acc):.4f} to {max(a.median for a in acc):.4f} px)")
    details += camera_accuracy_lines(found)
    size = frame_size(sharp[0])
    assert size is not None  # a frame the simulator wrote
    print("\n".join(["", *result_lines(report.to_dict(), found, size), "", "Details",
                     *(f"  {line}" for line in details), "", *figure_lines(report.outputs), "",
                     *term_lines()]))
    if log.path is not None:
        print(f"progress log: {log.path}")
    return 0


def _demo_rig(args: argparse.Namespace) -> int:
    """``demo --rig`` (:func:`cmd_demo`): simulate into OUT/data, calibrate-rig into
    OUT/calibration, compare with the truth."""
    from blurcalib.camera.rig_files import read_rig_folder
    from blurcalib.pipeline.rig import CALIBRATION_DIR
    from blurcalib.pipeline.rig_frames import calibrate_rig_frames, camera_frames
    from blurcalib.pipeline.run import PipelineError
    from blurcalib.runs.events import FrameDone, RunEvent
    from blurcalib.sim.demo import DemoLog
    from blurcalib.sim.rig import RIG_TRUTH_FILE, load_rig_truth
    from blurcalib.sim.rig_eval import rig_accuracy, rig_accuracy_lines

    if args.lens != "standard":
        raise CliError("--rig simulates a pair of the standard lens; leave out --lens")
    out = Path(args.out)
    data = out / "data"
    if (data / RIG_TRUTH_FILE).is_file() and not args.overwrite:
        log = DemoLog(out)
        log.stage(f"1/3 reusing the simulated rig in {data}")
    else:
        check_empty_output(data, args.overwrite)
        log = DemoLog(out)
        log.stage(f"1/3 simulating {args.sharp} sharp and {args.blurry} blurry image sets of a stereo pair "
                  f"into {data}")
        simulate(data, args, None)
    truth, _ = load_rig_truth(data)
    pattern = load_pattern(data / "cam0" / "pattern.yaml")
    log.stage("2/3 calibrating the rig: each camera's frames, then the extrinsics")
    cameras = [camera_frames(data / f"cam{c}") for c in range(len(truth.cameras))]

    def progress(camera: int, stage: str, event: RunEvent) -> None:
        if isinstance(event, FrameDone):
            r = event.record
            log.detail(f"camera {camera} {event.done}/{event.total}: {r.frame} {r.status.value}, "
                       f"{count(r.features, 'feature')}")

    try:
        run = calibrate_rig_frames(cameras, pattern, out / "calibration", pipeline_settings(args), progress,
                                   overwrite=args.overwrite)
    except PipelineError as exc:
        raise CliError(str(exc)) from None
    log.stage("3/3 comparing the rig with the true rig")
    rig = read_rig_folder(out / "calibration" / CALIBRATION_DIR).rig
    lines = rig_accuracy_lines(rig_accuracy(truth, rig))
    report = run.rig.report
    details = [f"camera {c}: {count(cam['frames'], 'frame')} ({cam['blurry_frames']} blurry) of "
               f"{len(run.cameras[c].frames)}; generic median {cam['generic_median_px']:.4f} px, rig bundle "
               f"median {cam['rig_median_px']:.4f} px" for c, cam in enumerate(report["cameras"])]
    print("\n".join(["", "Result", *(f"  {line}" for line in lines), "", "Details",
                     *(f"  {line}" for line in details), f"  image sets used: {report['sets']}",
                     f"  the rig: {out / 'calibration'} (docs/rig.md)"]))
    return 0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``demo``."""
    p = sub.add_parser("demo", help="simulate the default dataset and run the pipeline on it",
                       description=plain(cmd_demo.__doc__))
    p.add_argument("--out", default=str(DEFAULT_DEMO_DIR), metavar="DIR",
                   help="output folder (default %(default)s); its data/ is reused when complete")
    add_lens_options(p)
    add_rig_options(p, RIG_SCALE)
    add_synth_options(p, rolling_shutter=False, rig_counts=RIG_SETS)
    add_pipeline_options(p)
    add_run_options(p, workers=False)
    p.set_defaults(func=cmd_demo)
