"""``blurcalib synth``: simulated sharp and blurry frames with ground truth."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

from blurcalib.argtypes import readout_ratio
from blurcalib.cli.common import CliError, check_empty_output, plain, progress
from blurcalib.io.text import count
from blurcalib.target.pattern import StarPattern, load_pattern

if TYPE_CHECKING:
    from blurcalib.sim.synth import SynthConfig

FISHEYE_FOV = 130.0
"""``synth --lens fisheye``'s default horizontal field of view (deg)."""


def simulate(out: Path, args: argparse.Namespace, pattern: StarPattern | None) -> None:
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
    if getattr(args, "rig", False):
        _simulate_rig(out, config, pattern, lens, args.rig_scale)
        return
    start = time.perf_counter()
    bar, update = progress("simulating")
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


def _simulate_rig(out: Path, config: SynthConfig, pattern: StarPattern | None, lens: str,
                  scale: float) -> None:
    """``synth --rig``: the D435I-like infrared pair's synchronised image sets, its images resized
    by ``scale`` (docs/rig.md)."""
    from blurcalib.sim.rig import RIG_TRUTH_FILE, d435i_stereo_rig, write_rig_dataset

    if lens != "standard":
        raise CliError("--rig simulates a pair of the standard lens; leave out --lens")
    bar, update = progress("simulating sets")
    with bar:
        rig, sets = write_rig_dataset(out, config, d435i_stereo_rig(config.seed, scale=scale), pattern,
                                      progress=update)
    frames = [sum(s.frames[c] is not None for s in sets) for c in range(len(rig.cameras))]
    print(f"simulated {count(len(sets), 'image set')} ({config.sharp} sharp, {config.blurry} blurry) of a "
          f"{len(rig.cameras)}-camera rig into {out}: " + ", ".join(
              f"cam{c}/ {count(n, 'frame')}" for c, n in enumerate(frames)))
    print(f"  ground truth: {out / RIG_TRUTH_FILE} and cam*/ground_truth.json")


def cmd_synth(args: argparse.Namespace) -> int:
    """Simulate sharp and blurry frames of the star target with exact ground truth
    (ground_truth.json; docs/synthetic-data.md). Prints the frames written and the blurry frames'
    blur."""
    out = Path(args.out)
    check_empty_output(out, args.overwrite)
    pattern = load_pattern(args.pattern) if args.pattern else None
    simulate(out, args, pattern)
    return 0


def add_lens_options(p: argparse._ActionsContainer) -> None:
    """The simulated lens of ``synth`` and ``demo``."""
    p.add_argument("--lens", choices=["standard", "fisheye"], default="standard",
                   help="standard: a 90 degree Brown-Conrady lens like a RealSense D435I's; fisheye: a "
                        "Kannala-Brandt lens of --fov horizontal field whose image circle is 200 degrees "
                        "(both 1280x720 px with a smooth lens deviation of 0.3 px; default %(default)s)")
    p.add_argument("--fov", type=float, metavar="DEG",
                   help=f"horizontal field of view of --lens fisheye, deg, up to 200 "
                        f"(default {FISHEYE_FOV:g})")


def add_rig_options(p: argparse._ActionsContainer, scale: float = 1.0) -> None:
    """``--rig`` and ``--rig-scale`` of ``synth`` and ``demo`` (``scale`` the default image scale)."""
    from blurcalib.argtypes import positive_number

    p.add_argument("--rig", action="store_true",
                   help="a D435I-like infrared pair instead of one camera: two cameras 50 mm apart seeing "
                        "each set at once, one folder per camera (cam0/, cam1/) and rig_truth.json "
                        "(docs/rig.md; rendered in one process)")
    p.add_argument("--rig-scale", type=positive_number, default=scale, metavar="F",
                   help="--rig: the cameras' images resized by F, same field of view (0.5: 640x360; "
                        "default %(default)s)")


def add_synth_options(p: argparse._ActionsContainer, rolling_shutter: bool = True,
                      rig_counts: tuple[int, int] | None = None) -> None:
    """The simulation's options; ``rig_counts``: the sharp and blurry sets of ``--rig`` when
    ``--sharp`` and ``--blurry`` are not given (their defaults are then None)."""
    from blurcalib.sim.synth import SynthConfig

    g = p.add_argument_group("simulation")
    for kind, default in (("sharp", SynthConfig.sharp), ("blurry", SynthConfig.blurry)):
        extra = "" if rig_counts is None else f"; {rig_counts[kind == 'blurry']} image sets with --rig"
        g.add_argument(f"--{kind}", type=int, default=default if rig_counts is None else None, metavar="N",
                       help=f"number of {kind} frames (default {default}{extra})")
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


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``synth``."""
    p = sub.add_parser("synth", help="simulate sharp and blurry frames with ground truth",
                       description=plain(cmd_synth.__doc__))
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--pattern", metavar="FILE", help="pattern YAML (default: the reference A4 17x24 target)")
    add_lens_options(p)
    add_rig_options(p)
    add_synth_options(p)
    p.set_defaults(func=cmd_synth)
