"""Which frames whose tag was not found a neighbour round would try to seed now
(:func:`blurcalib.runs.neighbours.neighbours_to_try`): the app's *Run all* redoes exactly these."""

from __future__ import annotations

from pathlib import Path

from blurcalib.io.record import FrameRecord, FrameStatus
from blurcalib.io.sources import FrameInput
from blurcalib.runs.neighbours import NEIGHBOUR_REACH, NEIGHBOUR_TRIES, neighbours_to_try


def _frames(n: int) -> list[FrameInput]:
    return [FrameInput(f"f{i}", Path(f"f{i}.png"), None, "seq", i) for i in range(n)]


def _records(statuses: dict[int, FrameStatus], tried: dict[int, tuple[str, ...]] | None = None
             ) -> dict[str, FrameRecord]:
    tried = tried or {}
    return {f"f{i}": FrameRecord(f"f{i}", status=s, neighbours_tried=tried.get(i))
            for i, s in statuses.items()}


def test_a_frame_not_seeded_alone_is_tried_once_a_neighbour_is_extracted() -> None:
    frames = _frames(6)
    ok, missed = FrameStatus.OK, FrameStatus.NOT_SEEDED
    assert neighbours_to_try(frames, _records({3: missed})) == set()  # no neighbour extracted yet
    assert neighbours_to_try(frames, _records({3: missed, 5: ok})) == {"f3"}
    assert neighbours_to_try(frames, _records({3: missed}), coming={"f4"}) == {"f3"}  # extracted first
    far = 3 + NEIGHBOUR_REACH + 1
    assert neighbours_to_try(_frames(far + 1), _records({3: missed, far: ok})) == set()  # out of reach
    # a neighbour already tried is not tried again; no tries left, none is
    assert neighbours_to_try(frames, _records({3: missed, 2: ok}, {3: ("f2",)})) == set()
    assert neighbours_to_try(frames, _records({3: missed, 2: ok, 4: ok}, {3: ("f2",)})) == {"f3"}
    spent = tuple(f"x{i}" for i in range(NEIGHBOUR_TRIES))
    assert neighbours_to_try(frames, _records({3: missed, 2: ok}, {3: spent})) == set()
    # frames in no sequence have no neighbours
    alone = [FrameInput(f.name, f.path) for f in frames]
    assert neighbours_to_try(alone, _records({3: missed, 2: ok})) == set()
