"""``blurcalib extract``: star features and PSFs from frames into a resumable folder."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from blurcalib.argtypes import psf_window
from blurcalib.cli.common import (
    CliError,
    add_fit_options,
    add_run_options,
    add_source_options,
    plain,
    source_frames,
)
from blurcalib.growth.window import SHARP_START, WindowPolicy
from blurcalib.io.text import count
from blurcalib.runs.runtime import check_device
from blurcalib.target.pattern import load_pattern


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
    paths = source_frames(args)
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


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``extract``."""
    p = sub.add_parser("extract", help="extract star features and PSFs from frames",
                       description=plain(cmd_extract.__doc__))
    g = p.add_argument_group("inputs")
    add_source_options(g)
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
    add_fit_options(g, "")
    add_run_options(p)
    p.set_defaults(func=cmd_extract)
