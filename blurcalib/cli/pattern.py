"""``blurcalib pattern``: a printable star target."""

from __future__ import annotations

import argparse
from pathlib import Path

from blurcalib.argtypes import page_size, positive_number
from blurcalib.cli.common import CliError, default_of, plain
from blurcalib.io.atomic import OutputError
from blurcalib.target.pattern import PAGE_SIZES_MM, layout_pattern


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


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``pattern``."""
    p = sub.add_parser("pattern", help="write a printable star target (PDF, PNG, YAML)",
                       description=plain(cmd_pattern.__doc__))
    p.add_argument("--out", required=True, metavar="PATH",
                   help="output path without extension, e.g. targets/star_a4")
    p.add_argument("--page", type=page_size, default=PAGE_SIZES_MM["A4"],
                   help="A4, letter or WIDTHxHEIGHT in mm (default A4)")
    p.add_argument("--square-mm", type=float, default=default_of(layout_pattern, "approx_square_length_mm"),
                   metavar="MM", help="approximate square length, mm (default %(default)s); adjusted to "
                                      "fit the page")
    p.add_argument("--tag", type=int, default=default_of(layout_pattern, "tag_index"), metavar="ID",
                   help="tag36h11 id (default %(default)s)")
    p.add_argument("--segments", type=int, default=default_of(layout_pattern, "num_star_segments"),
                   metavar="N", help="star segments, a multiple of 4 (default %(default)s)")
    p.add_argument("--margin-mm", type=float, default=default_of(layout_pattern, "margin_mm"), metavar="MM",
                   help="page margin, mm (default %(default)s)")
    p.add_argument("--dpi", type=positive_number, default=300.0,
                   help="PNG resolution (default %(default)s; the PNG may have at most 150 megapixels)")
    p.add_argument("--formats", default="pdf,png,yaml", metavar="LIST",
                   help="comma list of pdf, png, yaml (default %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace existing files")
    p.set_defaults(func=cmd_pattern)
