"""blurcalib's browser app: watch features and PSFs being extracted, tune the quality filter,
inspect blocks, see the error field and the frames' poses, and learn the translational ambiguity.

    python app.py [FOLDER] [--pattern P.yaml] [--out DIR] [--port N]
    python app.py --rig D [--port N]


With no folder it opens a small simulated dataset, rendered on first use into the user's cache
folder (``~/.cache/blurcalib/app_dataset``, or under ``$XDG_CACHE_HOME``). Extracted frames are
written into ``--out`` (by default a folder of the dataset's own under
``~/.cache/blurcalib/results/``, so that a read-only dataset works): opening the dataset again
shows them as done, and a run resumes where the last one stopped. The app serves on
127.0.0.1 (port 8080 by default, the next free one if taken) and prints its URL; only pages of
that origin can drive it, and it is never shared (``views/security.py``). A ``--host`` that other
machines can reach (``0.0.0.0``) is refused without ``--allow-remote``, and warned about with it.
All browser tabs share one state (``state/``); each panel is a module of ``views/``.

``--rig D`` opens a ``blurcalib calibrate-rig`` output folder instead (``state/rig.py``,
``views/rig.py``): the rig's cameras and image sets in 3D, each camera's reprojection errors and a
pair's rectified image sets with their epipolar error.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import viser

from blurcalib.argtypes import positive_int
from blurcalib.runs.runtime import available_cores, capped_count, configure_threads, keep_large_allocations
from state import AppState, RunSettings, default_dataset
from state.alignment import AlignmentCache
from state.calibration import CalibrationRunner, CalibrationSettings
from state.folder import builtin_dataset_folder
from state.rig import RigOutputError, RigState, load_rig
from state.seeding import TagSearchCache
from views.ambiguity import AmbiguityPanel
from views.browser import add_page_script
from views.calibration import CalibrationPanel
from views.errors import ErrorsPanel
from views.frame_view import FrameViewPanel
from views.frames import FramesPanel
from views.inspect import InspectPanel
from views.psf_field import PsfFieldPanel
from views.rig import RigPanel
from views.security import ServeError, check_host, check_listen, secure_viser_server
from views.tuning import TuningPanel

VIEWS_WIDTH = 760
"""Width (px) of the docked panel holding the frame, PSF, block, error and demo views."""


class Panel(Protocol):
    def close(self) -> None: ...


@dataclass
class App:
    """A running app: its state, the global alignments of its frames, its calibration and its panels."""

    state: AppState
    alignments: AlignmentCache
    calibration: CalibrationRunner
    panels: list[Panel] = field(default_factory=list)

    def close(self) -> None:
        """Cancel a run and a calibration and stop the panels' threads (the server is stopped by its
        owner)."""
        self.state.cancel()
        self.calibration.cancel()
        self.state.wait(30.0)
        self.calibration.wait(60.0)
        for panel in self.panels:
            panel.close()


@dataclass
class RigApp:
    """A running rig view: the loaded rig and its panel."""

    rig: RigState
    panel: RigPanel

    def close(self) -> None:
        """Stop the panel's threads (the server is stopped by its owner)."""
        self.panel.close()


def serve_rig(rig: RigState, port: int = 8080, *, host: str = "127.0.0.1", allow_remote: bool = False
              ) -> tuple[viser.ViserServer, RigApp]:
    """Start the rig view of a loaded rig output (:func:`state.rig.load_rig`) on ``host:port``
    (as :func:`serve`). Returns the server and the app; stop with ``app.close()`` then
    ``server.stop()``.

    Raises:
        ServeError: as :func:`serve`.
    """
    check_listen(host, port)
    check_host(host, allow_remote)
    server = secure_viser_server(host, port, "blurcalib rig")
    server.gui.configure_theme(control_width="large", show_share_button=False, dark_mode=False,
                               brand_color=(40, 110, 200))
    server.gui.main_panel.dock_right()
    views = server.gui.add_panel()
    panel = RigPanel(rig, server, views)
    views.dock_left()
    views.set_width(VIEWS_WIDTH)
    return server, RigApp(rig, panel)


def _progress(done: int, total: int, name: str) -> None:
    print(f"  simulated {done}/{total}: {name}", flush=True)


def serve(folder: str | os.PathLike | None = None, pattern: str | os.PathLike | None = None,
          port: int = 8080, *, host: str = "127.0.0.1", allow_remote: bool = False,
          settings: RunSettings | None = None, calibration: CalibrationSettings | None = None,
          out: str | os.PathLike | None = None) -> tuple[viser.ViserServer, App]:
    """Start the app on ``host:port`` (``port`` 0: any free port; read the real one with
    ``server.get_port()``) and open ``folder`` (default: the built-in simulated dataset).

    A folder that cannot be opened leaves the app running with an error in its status line.
    The address is tried before anything else is done.

    Args:
        folder: dataset folder (frames, or sub-folders of frames, and ``pattern.yaml``).
        pattern: the pattern YAML (default: ``pattern.yaml`` in the folder or its parent).
        port: TCP port.
        host: interface to listen on.
        allow_remote: listen on a host other machines can reach (:func:`views.security.check_host`).
        settings: extraction settings per frame kind.
        calibration: the calibration's settings.
        out: the folder the frames of ``folder`` are extracted into (default: the dataset's own
            folder in the user's cache, :func:`state.folder.default_output_folder`).
    Returns:
        The viser server and the app; stop with ``app.close()`` then ``server.stop()``.
    Raises:
        ServeError: the app cannot listen on ``host:port``, or ``host`` is reachable from other
            machines without ``allow_remote``.
    """
    check_listen(host, port)
    check_host(host, allow_remote)
    server = secure_viser_server(host, port, "blurcalib")
    if folder is None:
        builtin = builtin_dataset_folder()
        first = not (builtin / "ground_truth.json").is_file()
        print(f"{'rendering' if first else 'opening'} the built-in dataset in {builtin}"
              + (" (first use only)" if first else ""), flush=True)
        try:
            folder = default_dataset(builtin, progress=_progress, workers=min(available_cores(), 4))
        except BaseException:
            server.stop()
            raise
    state = AppState(settings)
    server.gui.configure_theme(control_width="large", show_share_button=False, dark_mode=False,
                               brand_color=(40, 110, 200))
    server.gui.main_panel.dock_right()
    add_page_script(server)
    app = App(state, AlignmentCache(state), CalibrationRunner(state, calibration))
    app.panels.append(FramesPanel(state, server, app.calibration))
    with server.gui.add_folder("Quality filter"):
        app.panels.append(TuningPanel(state, server, app.alignments))
    views = server.gui.add_panel()
    with views.add_tab("Frame", viser.Icon.PHOTO):
        app.panels.append(FrameViewPanel(state, server, TagSearchCache(state)))
    with views.add_tab("PSF field", viser.Icon.GRID_DOTS):
        app.panels.append(PsfFieldPanel(state, server))
    with views.add_tab("Block", viser.Icon.ZOOM_IN):
        app.panels.append(InspectPanel(state, server))
    with views.add_tab("Errors", viser.Icon.ARROWS_MOVE):
        app.panels.append(ErrorsPanel(state, server, app.alignments, app.calibration))
    with views.add_tab("Calibration", viser.Icon.CAMERA):
        app.panels.append(CalibrationPanel(state, server, app.calibration))
    with views.add_tab("Ambiguity", viser.Icon.SCHOOL):
        app.panels.append(AmbiguityPanel(server))
    views.dock_left()
    views.set_width(VIEWS_WIDTH)
    state.load_folder(folder, pattern, out)
    return server, app


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a TCP port number (0 to 65535), got {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port number (0 to 65535), got {value}")
    return value


SIGNAL_POLL_S = 0.5
"""The main thread's longest sleep (s). The kernel may deliver SIGTERM (or SIGINT) to any of the
app's threads; Python then runs the handler in the main thread only once that thread runs again,
so a main thread asleep for an hour (viser's ``sleep_forever``) would ignore the signal."""


def _stop(signum: int, frame: object) -> None:
    """SIGTERM or Ctrl+C ends the app: its clean-up runs (uploads deleted, runs cancelled), and a
    later signal is ignored so that it cannot cut the clean-up short (``timeout`` and a process
    group's kill each send one; a second raise inside the clean-up left a traceback and the
    uploads behind). Ignored by a handler that does nothing, not ``SIG_IGN``: a signal that has
    arrived but whose handler has not run yet would then raise ``OSError`` ("ignored due to race
    condition") inside the clean-up."""
    signal.signal(signal.SIGTERM, _ignore)
    signal.signal(signal.SIGINT, _ignore)
    raise KeyboardInterrupt


def _ignore(signum: int, frame: object) -> None:
    """A signal that comes while the app stops: nothing to do (:func:`_stop`)."""


def build_parser(prog: str = "app.py") -> argparse.ArgumentParser:
    """The command line of ``python app.py`` (``prog``: its name in usage lines, ``blurcalib view``
    when the command line starts it)."""
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    p.add_argument("folder", nargs="?", metavar="FOLDER",
                   help="dataset folder (default: a built-in simulated dataset)")
    p.add_argument("--rig", metavar="D",
                   help="open a calibrate-rig (or demo --rig) output folder: the rig in 3D, each camera's "
                        "errors, a pair's rectified image sets")
    p.add_argument("--pattern", metavar="FILE",
                   help="pattern YAML (default: pattern.yaml in the folder or its parent)")
    p.add_argument("--out", metavar="DIR",
                   help="output folder of the extracted frames, resumed when opened again (default: the "
                        "dataset's own folder under ~/.cache/blurcalib/results)")
    p.add_argument("--port", type=_port, default=8080, metavar="N",
                   help="TCP port (default %(default)s; the next free one if taken)")
    p.add_argument("--host", default="127.0.0.1", metavar="ADDRESS",
                   help="interface to listen on (default %(default)s); one other machines can reach "
                        "(0.0.0.0) needs --allow-remote")
    p.add_argument("--allow-remote", action="store_true",
                   help="listen on a --host other machines can reach: any client there can browse and read "
                        "files, export into any folder and run jobs as this user (a warning is printed)")
    p.add_argument("--threads", type=positive_int, default=1, metavar="N",
                   help="compute threads of the extraction and calibration (default %(default)s)")
    return p


def main(argv: Sequence[str] | None = None, prog: str = "app.py") -> int:
    """Run the app until interrupted (``prog``: its name in messages)."""
    parser = build_parser(prog)
    args = parser.parse_args(argv)
    if args.rig is not None and args.folder is not None:
        parser.error("give a FOLDER or --rig D, not both")
    threads, note = capped_count(args.threads, "--threads")
    if note is not None:
        print(f"{prog}: note: {note}", file=sys.stderr)
    configure_threads(threads)
    keep_large_allocations()
    try:
        check_listen(args.host, args.port)
        warning = check_host(args.host, args.allow_remote)
        if warning is not None:
            print(f"{prog}: warning: {warning}", file=sys.stderr, flush=True)
        app: App | RigApp
        if args.rig is not None:
            server, app = serve_rig(load_rig(args.rig), args.port, host=args.host,
                                    allow_remote=args.allow_remote)
        else:
            server, app = serve(args.folder, args.pattern, args.port, host=args.host,
                                allow_remote=args.allow_remote, out=args.out)
    except (ServeError, RigOutputError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    try:  # from here a signal, even one that comes while the address is printed, runs the clean-up
        for notice in app.state.notices if isinstance(app, App) else []:
            if notice.level == "error":
                print(f"{notice.title}: {notice.text}", file=sys.stderr)
        print(f"blurcalib app: http://{args.host}:{server.get_port()}/  (Ctrl+C to stop)", flush=True)
        while True:  # short sleeps: see SIGNAL_POLL_S
            time.sleep(SIGNAL_POLL_S)
    except KeyboardInterrupt:
        pass  # _stop: the clean-up below runs once, later signals ignored
    finally:
        app.close()
        server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
