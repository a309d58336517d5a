"""What the commands share: the user-facing error, progress bars, the frame inputs and the
options several commands take."""

from __future__ import annotations

import argparse
import inspect
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, get_args

from tqdm import tqdm

from blurcalib.argtypes import cluster_address, positive_int, positive_number
from blurcalib.growth.settings import FinalFitFrames, GrowSettings
from blurcalib.runs.runtime import available_cores

if TYPE_CHECKING:
    from blurcalib.io.sources import FrameInput


class CliError(Exception):
    """A user-facing error: printed without a traceback, exit status 2."""


def progress(desc: str) -> tuple[tqdm, Callable[[int, int, str], None]]:
    """A frame progress bar on stderr and its ``update(done, total, name)`` callback."""
    bar = tqdm(total=0, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True,
               disable=None)

    def update(done: int, total: int, name: str) -> None:
        bar.total = total
        bar.n = done
        bar.set_postfix_str(name, refresh=False)
        bar.refresh()

    return bar, update


def check_empty_output(out: Path, overwrite: bool) -> None:
    """Refuse an output path that is a file, or a non-empty folder unless ``overwrite``."""
    if out.exists() and not out.is_dir():
        raise CliError(f"{out}: output path exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise CliError(f"{out}: output folder is not empty (use --overwrite to replace its "
                       "dataset)")


def source_frames(args: argparse.Namespace) -> list[FrameInput]:
    """The frames of the positional inputs (folders, images, videos) with ``--every`` and
    ``--max-frames`` (:func:`blurcalib.io.sources.frame_inputs`)."""
    from blurcalib.io.frames import FrameError
    from blurcalib.io.sources import frame_inputs

    try:
        return frame_inputs(args.frames, every=args.every, max_frames=args.max_frames)
    except FrameError as exc:
        raise CliError(str(exc)) from None


def default_of(func: Callable[..., object], name: str) -> object:
    """The default of ``func``'s parameter ``name``: the option's default, said once."""
    return inspect.signature(func).parameters[name].default


def plain(doc: str | None) -> str:
    """A docstring as help text: without reST's double backticks."""
    return (doc or "").replace("``", "")


def add_run_options(p: argparse._ActionsContainer, workers: bool = True) -> None:
    g = p.add_argument_group("where it runs")
    if workers:
        g.add_argument("--workers", type=positive_int, default=available_cores(), metavar="N",
                       help="frames processed in parallel, one process each (default: one per core); "
                            "the calibration then computes with as many threads")
    g.add_argument("--threads", type=positive_int, default=1, metavar="N",
                   help="compute threads of this process, for frames it runs itself (--workers 1); "
                        "worker processes use one (default %(default)s)")
    g.add_argument("--cluster", metavar="ADDRESS", type=cluster_address,
                   help="run frames as tasks on this Dask scheduler, e.g. tcp://host:8786 (docs/cluster.md)")
    g.add_argument("--device", default="cpu",
                   help="torch device of the block solver and the bundle adjustment: cpu, cuda or cuda:N "
                        "(default %(default)s); workers share one GPU badly, so with many cores cpu "
                        "extracts a folder faster (docs/calibration.md)")


def add_fit_options(p: argparse._ActionsContainer, which: str) -> None:
    p.add_argument("--final-fit", choices=get_args(FinalFitFrames), default=GrowSettings.final_fit_frames,
                   help=f"which {which}frames without the path-PSF field get a final fit of each block "
                        "over 1.5 x its square: those whose PSF window grew with the blur (adaptive), "
                        "all (more accurate features, about 1 s more per frame with little blur) or "
                        "none (default %(default)s; docs/deconvolution.md)")
    p.add_argument("--no-psf-field", action="store_true",
                   help=f"fit {which}frames with free PSFs only: no field of motion-path PSFs in frames "
                        "whose blur is long (for a rolling shutter, whose paths bend with the image row; "
                        "docs/deconvolution.md; sharp frames never use it)")


def add_source_options(p: argparse._ActionsContainer, nargs: str = "+", inputs: str = "") -> None:
    """The frame inputs (positional ``INPUT...``, ``nargs``; ``inputs`` replaces the start of its
    help), ``--every``, ``--max-frames`` and ``--sharp-below``, read by :func:`source_frames`."""
    from blurcalib.extract.frame import SHARP_BELOW_PX

    p.add_argument("frames", nargs=nargs, metavar="INPUT",
                   help=(inputs or "folders of frames, image files") + " (png, jpg, tiff, bmp; 8 or 16 bit, "
                        "colour is converted to grey) or videos (mp4, avi, mkv, mov); a video's frames are "
                        "named VIDEO#000123")
    p.add_argument("--every", type=positive_int, default=1, metavar="N",
                   help="keep every N-th frame of each folder and video (default %(default)s)")
    p.add_argument("--max-frames", type=positive_int, default=None, metavar="N",
                   help="keep at most N frames of each folder and video (default: all)")
    p.add_argument("--sharp-below", type=positive_number, default=SHARP_BELOW_PX, metavar="PX",
                   help="frames whose measured blur (median blur extent of the tag ring's PSFs) is "
                        "below this are sharp, px (default %(default)s; docs/pipeline.md)")


