"""The ``blurcalib`` command line: one subcommand per job.

Every subcommand reports bad input as ``blurcalib: error: <file>: <problem>`` on stderr and
exits with status 2; files are written atomically, so an interrupted or failed run leaves no
half-written output behind.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from contextlib import AbstractContextManager, nullcontext

from blurcalib import __version__
from blurcalib.cli import calibrate, calibrate_rig, compare, demo, experiment, extract, pattern, synth, view
from blurcalib.cli.common import CliError
from blurcalib.io.atomic import OutputError, output_lock, storage_error
from blurcalib.runs.cluster import ClusterError
from blurcalib.runs.runtime import DeviceError, capped_count, configure_threads, keep_large_allocations
from blurcalib.target.pattern import PatternFileError


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``blurcalib`` and its subcommands, in the order ``--help`` lists them."""
    parser = argparse.ArgumentParser(
        prog="blurcalib",
        description="Sub-pixel star features and spatially varying PSFs from motion-blurred "
                    "calibration frames, and the generic camera calibrated from sharp and blurry "
                    "frames together.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in (demo, calibrate, calibrate_rig, pattern, extract, experiment, view, compare, synth):
        command.add_parser(sub)
    return parser


def _output_lock(args: argparse.Namespace) -> AbstractContextManager[object]:
    """The lock on the output folder of a command that writes one (:func:`blurcalib.io.atomic.output_lock`):
    a second run into the same folder is refused while this one runs."""
    writers = (calibrate.cmd_calibrate, calibrate_rig.cmd_calibrate_rig, extract.cmd_extract, synth.cmd_synth,
               demo.cmd_demo)
    if args.func in writers:
        return output_lock(args.out)
    return nullcontext()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``blurcalib`` console script and ``python -m blurcalib``."""
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["view"]:  # every option goes to the app, --help included
        args = argparse.Namespace(func=view.cmd_view, rest=argv[1:])
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
