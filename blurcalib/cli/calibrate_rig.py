"""``blurcalib calibrate-rig``: a rig of cameras from each camera's frames, or from its features."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from blurcalib.argtypes import image_size
from blurcalib.cli.calibrate import add_pipeline_options, pipeline_settings
from blurcalib.cli.common import CliError, add_run_options, add_source_options, plain
from blurcalib.io.text import count
from blurcalib.target.pattern import StarPattern, load_pattern

if TYPE_CHECKING:
    from blurcalib.pipeline.rig import RigRun


def cmd_calibrate_rig(args: argparse.Namespace) -> int:
    """Calibrate a rig of cameras (a stereo pair, or more): one input per camera, camera 0 first (a
    folder of frames, or a folder of such folders; an image file; a video), frames of one instant
    with the same file name in every camera's input (a video's: the same index, or shifted by
    --time-offset). Each camera runs the calibrate pipeline into OUT/cameras/camN/ (resumable, the
    same options), then the rig's extrinsics come from one bundle adjustment over all cameras'
    sharp and blurry frames, one target pose per image set (docs/rig.md). With --features instead
    of inputs, each camera's features (as calibrate --features takes them).

    Writes into --out the reference tool's rig folder (calibration/intrinsics{N}.yaml,
    camera_tr_rig.yaml, rig_tr_global.yaml, points.yaml), OpenCV's stereo_{i}_{j}.yaml (R, T, E,
    R1, R2, P1, P2, Q) with its rectification maps rectify_{i}_{j}.npz for every pair, and
    report.json, written last. Prints each camera's errors and each pair's extrinsics, their
    uncertainty and held-out error."""
    from blurcalib.pipeline.rig import calibrate_rig_features
    from blurcalib.pipeline.run import PipelineError

    pattern = load_pattern(args.pattern)
    if bool(args.frames) == bool(args.features):
        raise CliError("give each camera's frames (INPUT INPUT ...) or each camera's features (--features "
                       "FILE FILE ...), one of them")
    try:
        if args.features:
            if args.time_offset:
                raise CliError("--time-offset goes with video inputs, not --features")
            run = calibrate_rig_features(args.features, pattern, args.out, args.image_size, args.cell_px,
                                         maps=not args.no_maps, overwrite=args.overwrite)
        else:
            run = _from_frames(args, pattern)
    except PipelineError as exc:
        raise CliError(str(exc)) from None
    _print_rig(run, args.out)
    return 0


def _from_frames(args: argparse.Namespace, pattern: StarPattern) -> RigRun:
    """Each camera's frames through the pipeline, then the rig (:mod:`blurcalib.pipeline.rig_frames`)."""
    from blurcalib.pipeline.rig_frames import calibrate_rig_frames, camera_frames
    from blurcalib.runs.events import FrameDone, RunEvent

    offsets = args.time_offset or [0] * len(args.frames)
    if len(offsets) != len(args.frames):
        raise CliError(f"--time-offset needs one value per camera ({len(args.frames)}), got {len(offsets)}")
    cameras = [camera_frames(source, args.every, args.max_frames, offset)
               for source, offset in zip(args.frames, offsets, strict=True)]
    bars: dict[tuple[int, str], tqdm] = {}

    def update(camera: int, stage: str, event: RunEvent) -> None:
        if not isinstance(event, FrameDone):
            return
        key = (camera, stage)
        if key not in bars:
            bars[key] = tqdm(total=event.total, desc=f"camera {camera}: extracting", unit="frame",
                             file=sys.stderr, dynamic_ncols=True, disable=None)
        bars[key].n = event.done
        bars[key].set_postfix_str(f"{event.record.frame}: {event.record.status.value}", refresh=True)

    try:
        result = calibrate_rig_frames(cameras, pattern, args.out, pipeline_settings(args), update,
                                      maps=not args.no_maps, overwrite=args.overwrite)
    finally:
        for bar in bars.values():
            bar.close()
    for c, report in enumerate(result.cameras):
        used = {kind: report.counts[kind].get("used", 0) for kind in ("sharp", "blurry")}
        print(f"camera {c} ({cameras[c].source}): {count(len(report.frames), 'frame')}, {used['sharp']} "
              f"sharp and {used['blurry']} blurry used; its own calibration in "
              f"{Path(args.out) / 'cameras' / f'cam{c}'}")
    return result.rig


def _print_rig(run: RigRun, out: str) -> None:
    """Each camera's errors, each pair's extrinsics and the sets used."""
    import numpy as np

    from blurcalib.geometry.pose import Pose

    report = run.report
    for c, cam in enumerate(report["cameras"]):
        print(f"camera {c}: {count(cam['frames'], 'frame')} ({cam['blurry_frames']} blurry), generic median "
              f"{cam['generic_median_px']:.4f} px; rig bundle median {cam['rig_median_px']:.4f} px")
    for pair in report["pairs"]:
        i, j = pair["cameras"]
        angle = float(np.degrees(np.linalg.norm(Pose(np.array(pair["R"]), np.zeros(3)).rvec)))
        print(f"camera {j} <- camera {i}: T = ({', '.join(f'{v * 1000:.3f}' for v in pair['T_m'])}) mm, "
              f"baseline {pair['baseline_mm']:.3f} mm, rotation {angle:.4f} deg")
        if pair.get("translation_uncertainty_mm") is not None:
            print(f"  uncertainty {pair['translation_uncertainty_mm']:.4f} mm, "
                  f"{pair['rotation_uncertainty_deg']:.5f} deg (expected size of the extrinsics' error)")
        if pair.get("holdout_error_px") is not None:
            print(f"  held-out error {pair['holdout_error_px']:.4f} px (median over "
                  f"{pair['holdout_predictions']} features of sets left out, predicted from the other "
                  f"camera)")
    print(f"image sets used: {report['sets']}; wrote {len(run.outputs)} files into {out}")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``calibrate-rig``."""
    p = sub.add_parser("calibrate-rig", help="a rig of cameras (stereo pair) from each camera's frames",
                       description=plain(cmd_calibrate_rig.__doc__))
    g = p.add_argument_group("inputs")
    add_source_options(g, nargs="*", inputs="one input per camera, camera 0 first: a folder of frames (or "
                                            "of sub-folders of frames, as synth --rig writes), an image file")
    g.add_argument("--time-offset", type=int, nargs="+", metavar="N",
                   help="per camera, frames of its video to subtract from a frame's index so that frames "
                        "of one instant match across the videos (default 0 each)")
    g.add_argument("--features", nargs="+", metavar="FILE",
                   help="instead of frames, one feature file per camera, camera 0 first: a blurcalib "
                        "features.csv (rows flagged BLURRY_FRAME get a free shift) or the reference "
                        "tool's dataset (.bin); of the camera options only --cell-px applies")
    g.add_argument("--image-size", type=image_size, metavar="WxH",
                   help="image size of the features.csv files, px (a .bin holds its own)")
    g.add_argument("--pattern", required=True, metavar="FILE", help="pattern YAML of the target")
    g = p.add_argument_group("output")
    g.add_argument("--no-maps", action="store_true", help="leave out the rectification maps")
    g.add_argument("--out", required=True, metavar="DIR", help="output folder (resumable)")
    g.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder that is not a calibrate-rig output")
    add_run_options(p)
    add_pipeline_options(p)
    p.set_defaults(func=cmd_calibrate_rig)
