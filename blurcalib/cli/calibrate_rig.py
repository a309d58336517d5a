"""``blurcalib calibrate-rig``: a rig of cameras from each camera's features."""

from __future__ import annotations

import argparse

from blurcalib.argtypes import image_size, positive_number
from blurcalib.calib.joint import JointSettings
from blurcalib.cli.common import CliError, plain
from blurcalib.io.text import count
from blurcalib.target.pattern import load_pattern


def cmd_calibrate_rig(args: argparse.Namespace) -> int:
    """Calibrate a rig of cameras (a stereo pair, or more) from each camera's features: each camera's
    Brown-Conrady and generic camera as calibrate --features does (blurry frames with a free shift
    each), then the rig's extrinsics by one bundle adjustment over all cameras' frames, one target
    pose per image set (frames of the same name in the cameras' feature files; docs/rig.md).

    Writes into --out the reference tool's rig folder (calibration/intrinsics{N}.yaml,
    camera_tr_rig.yaml, rig_tr_global.yaml, points.yaml), OpenCV's stereo_{i}_{j}.yaml (R, T, E,
    R1, R2, P1, P2, Q) with its rectification maps rectify_{i}_{j}.npz for every pair, and
    report.json, written last. Prints each camera's errors and each pair's extrinsics."""
    import numpy as np

    from blurcalib.geometry.pose import Pose
    from blurcalib.pipeline.rig import calibrate_rig_features
    from blurcalib.pipeline.run import PipelineError

    pattern = load_pattern(args.pattern)
    try:
        run = calibrate_rig_features(args.features, pattern, args.out, args.image_size, args.cell_px,
                                     maps=not args.no_maps, overwrite=args.overwrite)
    except PipelineError as exc:
        raise CliError(str(exc)) from None
    report = run.report
    for c, cam in enumerate(report["cameras"]):
        print(f"camera {c}: {count(cam['frames'], 'frame')} ({cam['blurry_frames']} blurry), generic median "
              f"{cam['generic_median_px']:.4f} px; rig bundle median {cam['rig_median_px']:.4f} px")
    for pair in report["pairs"]:
        i, j = pair["cameras"]
        angle = float(np.degrees(np.linalg.norm(Pose(np.array(pair["R"]), np.zeros(3)).rvec)))
        print(f"camera {j} <- camera {i}: T = ({', '.join(f'{v * 1000:.3f}' for v in pair['T_m'])}) mm, "
              f"baseline {pair['baseline_mm']:.3f} mm, rotation {angle:.4f} deg")
    print(f"image sets used: {report['sets']}; wrote {len(run.outputs)} files into {args.out}")
    return 0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``calibrate-rig``."""
    p = sub.add_parser("calibrate-rig", help="a rig of cameras (stereo pair) from each camera's features",
                       description=plain(cmd_calibrate_rig.__doc__))
    p.add_argument("--features", nargs="+", required=True, metavar="FILE",
                   help="one feature file per camera, camera 0 first: a blurcalib features.csv (rows "
                        "flagged BLURRY_FRAME get a free shift) or the reference tool's dataset (.bin)")
    p.add_argument("--image-size", type=image_size, metavar="WxH",
                   help="image size of the features.csv files, px (a .bin holds its own)")
    p.add_argument("--pattern", required=True, metavar="FILE", help="pattern YAML of the target")
    p.add_argument("--cell-px", type=positive_number, default=JointSettings.cell_px, metavar="PX",
                   help="generic grid cell length, px (default %(default)s)")
    p.add_argument("--no-maps", action="store_true", help="leave out the rectification maps")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty folder that is not a calibrate-rig output")
    p.set_defaults(func=cmd_calibrate_rig)
