"""``blurcalib compare``: the cross-pattern check of two feature files of one camera."""

from __future__ import annotations

import argparse

from blurcalib.argtypes import image_size, positive_number
from blurcalib.cli.common import CliError, plain
from blurcalib.target.pattern import load_pattern


def cmd_compare(args: argparse.Namespace) -> int:
    """Compare two feature files of one camera at the same poses, each of a different pattern (e.g.
    the 16-segment star and the four-segment checkerboard shown in turn on a monitor; frames named
    alike): calibrate Brown-Conrady from each file's sharp frames, take the same target point in the
    same frame from both through one homography per frame, and print the second file's residual
    against the first by radius from the principal point, the second camera's focal lengths against
    the first's, and whether the residual shows systematic error, i.e. a radius bin whose radial
    mean is beyond --z-limit standard errors and --limit-px (docs/accuracy.md). A feature
    definition that depended only on the lens would leave no systematic residual. Writes nothing."""
    from blurcalib.calib.cross_pattern import check_patterns
    from blurcalib.calib.sharp import CalibrationError, calibrate_sharp
    from blurcalib.camera.parametric import BrownConrady
    from blurcalib.io.feature_input import FeatureInputError, read_feature_input
    from blurcalib.io.results import FeatureFlags

    if len(args.pattern) > 2:
        raise CliError(f"--pattern: one file for both feature files or one per file "
                       f"(got {len(args.pattern)})")
    tables, cameras = [], []
    for path, pattern_file in zip(args.features, args.pattern * (3 - len(args.pattern)), strict=True):
        pattern = load_pattern(pattern_file)
        try:
            table, size = read_feature_input(path, pattern, args.image_size)
        except FeatureInputError as exc:
            raise CliError(str(exc)) from None
        table = table.select((table.flags & int(FeatureFlags.BLURRY_FRAME)) == 0)
        try:
            camera = calibrate_sharp(table, pattern, size).camera
        except CalibrationError as exc:
            raise CliError(f"{path}: {exc}") from None
        assert isinstance(camera, BrownConrady)  # the default model
        cameras.append(camera)
        tables.append(table)
    try:
        check = check_patterns(tables[0], tables[1], cameras[0], cameras[1], z_limit=args.z_limit,
                               limit_px=args.limit_px)
    except ValueError as exc:
        raise CliError(f"{args.features[0]} and {args.features[1]}: {exc}") from None
    print(f"{args.features[1]} against {args.features[0]}:")
    for line in check.lines():
        print("  " + line)
    return 0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``compare``."""
    p = sub.add_parser("compare", help="the cross-pattern check: two patterns' features of one camera",
                       description=plain(cmd_compare.__doc__))
    p.add_argument("features", nargs=2, metavar="FEATURES",
                   help="two feature files, the reference tool's dataset (.bin) or a blurcalib features.csv")
    p.add_argument("--pattern", nargs="+", required=True, metavar="FILE",
                   help="pattern YAML of the targets: one for both files, or one per file")
    p.add_argument("--image-size", type=image_size, metavar="WxH",
                   help="image size of a features.csv, px (a .bin holds its own)")
    p.add_argument("--z-limit", type=positive_number, default=5.0, metavar="Z",
                   help="a radial mean beyond this many standard errors is not noise (default %(default)s)")
    p.add_argument("--limit-px", type=positive_number, default=0.01, metavar="PX",
                   help="radial means up to this are not reported as systematic, px (default %(default)s)")
    p.set_defaults(func=cmd_compare)
