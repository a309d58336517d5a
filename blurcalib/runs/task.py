"""One frame of a run, as a worker does it: load, extract (from its own tag or a neighbour's
seed), and turn whatever goes wrong into the frame's status."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from blurcalib.extract.frame import ExtractSettings, FrameResult, extract_frame
from blurcalib.growth.ledger import GrowthEvent
from blurcalib.io.frames import FrameError, FrameSizeError
from blurcalib.io.record import FrameStatus
from blurcalib.io.sources import FrameInput
from blurcalib.runs.neighbours import NeighbourSeed, seed_from_neighbour
from blurcalib.target.pattern import StarPattern


@dataclass(frozen=True)
class FrameTask:
    """A frame to extract: from its own tag, or with ``hint`` from a neighbour's seed."""

    frame: FrameInput
    hint: NeighbourSeed | None = None


@dataclass(frozen=True)
class FrameJob:
    """What every task of a run shares: the target, the settings and the frames' size
    (``(width, height)``; None: any)."""

    pattern: StarPattern
    settings: ExtractSettings
    size: tuple[int, int] | None


def one_line(exc: BaseException) -> str:
    """An exception as a frame's message: ``TypeName: message`` on one line."""
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


def process_frame(frame: FrameInput, hint: NeighbourSeed | None, pattern: StarPattern,
                  settings: ExtractSettings, expected_size: tuple[int, int] | None,
                  on_event: Callable[[GrowthEvent], None] | None = None,
                  should_stop: Callable[[], bool] | None = None) -> FrameResult:
    """One frame of a run (from its own tag, or with ``hint`` from a neighbour); whatever goes
    wrong ends as this frame's status (``wrong_size``, ``unreadable``, ``failed`` with the
    exception's one-line message). A module-level function: worker processes and cluster tasks
    run it; ``on_event`` and ``should_stop`` are the growth's, in this process."""
    name = frame.name
    t0 = time.perf_counter()
    try:
        image = frame.load(expected_size=expected_size)
        if hint is not None:
            return seed_from_neighbour(image, pattern, name, hint, settings, on_event, should_stop)
        return extract_frame(image, pattern, name, settings, on_event=on_event, should_stop=should_stop)
    except FrameSizeError as exc:
        return FrameResult(name, FrameStatus.WRONG_SIZE, str(exc),
                           seconds={"load": time.perf_counter() - t0})
    except FrameError as exc:
        return FrameResult(name, FrameStatus.UNREADABLE, str(exc),
                           seconds={"load": time.perf_counter() - t0})
    except Exception as exc:  # any failure stays with its frame; the batch goes on
        return FrameResult(name, FrameStatus.FAILED, one_line(exc),
                           seconds={"failed": time.perf_counter() - t0})
