"""``blurcalib view``: the browser app of the source checkout, every option handed on."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from blurcalib.cli.common import CliError, plain


def cmd_view(args: argparse.Namespace) -> int:
    """Start the browser app (app.py of the source checkout); every option goes to the app."""
    import subprocess

    app = Path(__file__).resolve().parents[2] / "app.py"
    if not app.is_file():
        raise CliError("the browser app (app.py, views/, state/) ships with the source checkout; "
                       "run blurcalib from a checkout set up with `bash scripts/setup.sh`")
    start = (f"import sys; sys.path.insert(0, {str(app.parent)!r}); import app; "
             "sys.exit(app.main(sys.argv[1:], prog='blurcalib view'))")
    return subprocess.call([sys.executable, "-c", start, *args.rest])


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register ``view``."""
    p = sub.add_parser("view", help="start the browser app (viser)", description=plain(cmd_view.__doc__),
                       add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER, metavar="OPTIONS",
                   help="[FOLDER] [--pattern P.yaml] [--out DIR] [--port N] (see python app.py --help)")
    p.set_defaults(func=cmd_view)
