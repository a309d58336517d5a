"""Sequence seeding: a frame whose tag is not found is seeded from an extracted neighbour.

In a sequence (a video, a folder of frames, :attr:`blurcalib.io.sources.FrameInput.sequence`)
neighbouring frames see the target from nearby poses. A frame whose own tag is not found is grown
from the homography of its nearest extracted neighbour and kept only when its labelling is
verified against its own pixels (:func:`seed_from_neighbour`). :func:`plan_round` chooses the
neighbours a round tries; the runner (:mod:`blurcalib.runs.folder`) runs rounds until none is
left, so that a seeded frame can seed the next.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence, Set
from dataclasses import dataclass

import numpy as np

from blurcalib.extract.frame import ExtractSettings, FrameResult, grow_frame
from blurcalib.geometry.homography import homography_centre, homography_scale, translation
from blurcalib.growth.ledger import GrowthEvent
from blurcalib.growth.seed import (
    LabelCheck,
    Seed,
    block_homography,
    check_labelling,
    homography_from_features,
    tag_ring_features,
)
from blurcalib.io.record import FrameRecord, FrameStatus
from blurcalib.io.results import FeatureTable
from blurcalib.io.sources import FrameInput
from blurcalib.target.pattern import StarPattern

NEIGHBOUR_REACH = 2
"""A frame whose tag is not found is seeded from an extracted frame at most this many places
away in its sequence (:func:`seed_from_neighbour`)."""

NEIGHBOUR_TRIES = 2
"""Neighbours tried per frame whose tag is not found."""

NEIGHBOUR_MOTION_SQUARES = 1.0
"""A frame is seeded from its neighbours only where its sequence moves the target by at most
this many squares per frame (:func:`sequence_motion`): a neighbour's seed grows onto the right
stars only when the frame moved less than about half a square from it, and a folder of frames
taken from unrelated poses (stills, a simulated set) moves it by many squares."""

MOVING = "; not seeded from its neighbours: its sequence moves the target by "
"""Starts the part of a ``not_seeded`` frame's message that says why no neighbour's seed was tried."""

REFUSED = "; the seed from neighbour "
"""Starts the part of a ``not_seeded`` frame's message that says why a neighbour's seed was refused."""


@dataclass(frozen=True)
class NeighbourSeed:
    """A seed for a frame whose tag was not found, from a neighbour in its sequence.

    Attributes:
        neighbour: the neighbour's name.
        H_feature: ``(3, 3)`` the neighbour's homography, feature coordinates -> px
            (:func:`blurcalib.growth.seed.homography_from_features` of its star centres).
        message: why the frame itself could not be seeded.
    """

    neighbour: str
    H_feature: np.ndarray
    message: str


def verify_labelling(image: np.ndarray, pattern: StarPattern, result: FrameResult) -> LabelCheck:
    """Check an extracted frame's labelling against its pixels (:func:`blurcalib.growth.seed.check_labelling`)
    under the homography of its star centres, blurred by the median of its accepted blocks' PSFs."""
    f = result.features
    H = homography_from_features(f.fx, f.fy, f.x, f.y)
    if H is None or result.growth is None:
        return LabelCheck(False, math.nan, 0, "too few star centres to fit the frame's homography")
    psf = np.median(result.growth.fit.psf[result.growth.accepted], axis=0)
    psf = np.clip(np.nan_to_num(psf), 0.0, None)
    return check_labelling(image, pattern, H, psf / psf.sum() if psf.sum() > 0 else None)


def seed_from_neighbour(image: np.ndarray, pattern: StarPattern, frame: str, hint: NeighbourSeed,
                        settings: ExtractSettings | None = None,
                        on_event: Callable[[GrowthEvent], None] | None = None,
                        should_stop: Callable[[], bool] | None = None) -> FrameResult:
    """Extract a frame from a neighbour's seed, accepted only when its labelling is verified.

    The frame is grown from ``hint.H_feature`` (from the ring around the tag when it is in view,
    else from the blocks nearest the image centre) and its star centres' homography is checked
    against its pixels (:func:`verify_labelling`): a seed a square (or more) off grows as well as
    a right one, and only the tag and the target's border tell them apart. An accepted frame is
    ``ok`` with ``seeded_by = neighbour``; a refused one stays ``not_seeded``, the message saying
    why. ``on_event`` and ``should_stop`` are the growth's (:func:`blurcalib.extract.frame.extract_frame`).
    """
    settings = settings or ExtractSettings()
    t0 = time.perf_counter()
    H = np.asarray(hint.H_feature, dtype=np.float64)
    H = H / H[2, 2]
    ring = tag_ring_features(pattern)
    centres = homography_centre(block_homography(H, ring[:, 0], ring[:, 1]))
    h, w = image.shape
    inside = (centres[:, 0] > 0) & (centres[:, 0] < w - 1) & (centres[:, 1] > 0) & (centres[:, 1] < h - 1)
    # the tag ring in view: grown as from a tag (the ring fitted, the seed re-estimated from it)
    source = "tag" if len(ring) and inside.mean() > 0.75 else "given"
    seed = Seed(H, -1, np.zeros((0, 2)), 1.0, source, "neighbour")
    result = grow_frame(image, pattern, frame, seed, settings, on_event, should_stop)
    refused = f"{hint.message}{REFUSED}{hint.neighbour} was refused: "
    unknown = "" if settings.kind == "auto" else settings.kind
    if result.status is not FrameStatus.OK:
        no_blocks = result.status is FrameStatus.NO_BLOCKS
        reason = "no block could be fitted from it" if no_blocks else result.message
        return FrameResult(frame, FrameStatus.NOT_SEEDED, refused + reason,
                           seconds={"neighbour": time.perf_counter() - t0}, kind=unknown)
    t1 = time.perf_counter()
    check = verify_labelling(image, pattern, result)
    if not check.accepted:
        return FrameResult(frame, FrameStatus.NOT_SEEDED, refused + check.reason,
                           seconds={"neighbour": time.perf_counter() - t0}, kind=unknown)
    result.message = (f"seeded from neighbour {hint.neighbour} (labelling verified: residual ratio "
                      f"{check.ratio:.2f} against a square off)")
    result.seconds["verify"] = time.perf_counter() - t1
    return result


def sequence_motion(frames: Sequence[tuple[int, np.ndarray, np.ndarray]]) -> float:
    """The median motion of the target between frames of a sequence, in squares per frame.

    Args:
        frames: ``(rank, H, f)`` of extracted frames in sequence order: ``H (3, 3)`` feature
            coordinates -> px (:func:`blurcalib.growth.seed.homography_from_features`) and
            ``f (2,)`` the mean feature coordinates of the frame's star centres.
    Returns:
        Over consecutive pairs, how far (px) the first frame's mean feature point moved to the
        second, per square side there (the first homography's local scale there,
        :func:`blurcalib.geometry.homography.homography_scale`, px per feature unit) and per
        rank between them; NaN without a pair.
    """
    if len(frames) < 2:
        return math.nan
    rank = np.array([r for r, _, _ in frames])
    H = np.stack([h for _, h, _ in frames])
    at = translation(np.stack([f for _, _, f in frames[:-1]]))  # the origin moved to each first's point
    first, second = H[:-1] @ at, H[1:] @ at
    moved = np.linalg.norm(homography_centre(second) - homography_centre(first), axis=1)
    steps = moved / homography_scale(first) / np.maximum(np.diff(rank), 1)
    steps = steps[np.isfinite(steps)]
    return float(np.median(steps)) if steps.size else math.nan


def moving_message(message: str, motion: float) -> str:
    """A ``not_seeded`` frame's ``message`` saying that no neighbour's seed was tried, its sequence
    moving the target by ``motion`` squares per frame around it (unchanged when it says so)."""
    if MOVING in message:
        return message
    return (f"{message}{MOVING}{motion:.1f} squares per frame around it (a neighbour's seed needs at "
            f"most {NEIGHBOUR_MOTION_SQUARES:g})")


class Poses:
    """The homographies of extracted frames (from their features), each computed once.

    Args:
        features: reads a finished frame's features
            (:meth:`blurcalib.runs.output.RunFolder.features`).
    """

    def __init__(self, features: Callable[[str], FeatureTable]) -> None:
        self._features = features
        self._known: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}

    def of(self, name: str) -> tuple[np.ndarray, np.ndarray] | None:
        """An extracted frame's homography ``(3, 3)`` (feature coordinates -> px) and mean feature
        coordinates ``(2,)``; None with too few star centres."""
        if name not in self._known:
            table = self._features(name)
            H = homography_from_features(table.fx, table.fy, table.x, table.y)
            self._known[name] = None if H is None else (H, np.array([table.fx.mean(), table.fy.mean()]))
        return self._known[name]


@dataclass(frozen=True)
class Candidate:
    """A ``not_seeded`` frame that can try neighbours: ``message`` why its own seed failed,
    ``untried`` its extracted neighbours not tried yet (nearest first), ``room`` tries left."""

    frame: FrameInput
    message: str
    untried: tuple[FrameInput, ...]
    room: int


@dataclass(frozen=True)
class NeighbourRound:
    """The neighbours a round tries: ``attempts`` each frame with the seeds to try, nearest
    first; ``moving`` the frames passed over because their sequence moves the target faster than
    :data:`NEIGHBOUR_MOTION_SQUARES` around them, with that motion (squares per frame)."""

    attempts: list[tuple[FrameInput, list[NeighbourSeed]]]
    moving: dict[str, float]


def plan_round(frames: Sequence[FrameInput], records: Mapping[str, FrameRecord], poses: Poses,
               side_by_side: int, todo: Set[str]) -> NeighbourRound:
    """The next round of neighbour seeds for the frames of ``todo`` that ended ``not_seeded``
    and have an extracted neighbour not tried yet (:data:`NEIGHBOUR_REACH`,
    :data:`NEIGHBOUR_TRIES`) in a sequence that moves slowly around them
    (:data:`NEIGHBOUR_MOTION_SQUARES`, over the extracted frames within twice the reach): every
    such frame tries its nearest neighbour's seed and, while the round has fewer than
    :data:`NEIGHBOUR_TRIES` attempts per task that runs ``side_by_side``, the frames try their next
    ones too (one process tries one seed at a time: 0).

    Args:
        frames: every frame of the run (neighbours among them).
        records: the records of the frames finished so far.
        poses: the extracted frames' homographies.
        side_by_side: tasks the executor runs at once (0: one after the other).
        todo: the frames the run may extract.
    """
    candidates, moving = _candidates(frames, records, poses, todo)
    return NeighbourRound(_assign(candidates, poses, NEIGHBOUR_TRIES * side_by_side), moving)


def _sequences(frames: Sequence[FrameInput]) -> list[list[FrameInput]]:
    """The frames of each sequence, in sequence order (frames in no sequence left out)."""
    sequences: dict[str, list[FrameInput]] = {}
    for f in frames:
        if f.sequence:
            sequences.setdefault(f.sequence, []).append(f)
    return [sorted(members, key=lambda f: f.order) for members in sequences.values()]


def _candidates(frames: Sequence[FrameInput], records: Mapping[str, FrameRecord], poses: Poses,
                todo: Set[str]) -> tuple[list[Candidate], dict[str, float]]:
    """The frames that can try neighbours (:func:`plan_round`), and those passed over for their
    sequence's motion."""
    def extracted(g: FrameInput) -> bool:
        record = records.get(g.name)
        return record is not None and record.status is FrameStatus.OK

    candidates: list[Candidate] = []
    moving: dict[str, float] = {}
    for members in _sequences(frames):
        for rank, f in enumerate(members):
            record = records.get(f.name)
            tried = record.neighbours_tried or () if record is not None else ()
            if (f.name not in todo or record is None or record.status is not FrameStatus.NOT_SEEDED
                    or len(tried) >= NEIGHBOUR_TRIES):
                continue
            reach = 2 * NEIGHBOUR_REACH
            around = range(max(0, rank - reach), min(len(members), rank + reach + 1))
            motion = sequence_motion([(r, *pose) for r in around if extracted(members[r])
                                      and (pose := poses.of(members[r].name)) is not None])
            if motion > NEIGHBOUR_MOTION_SQUARES:
                moving[f.name] = motion
                continue
            near = sorted((abs(r - rank), r) for r in range(max(0, rank - NEIGHBOUR_REACH),
                                                           min(len(members), rank + NEIGHBOUR_REACH + 1)))
            untried = tuple(members[r] for _, r in near
                            if extracted(members[r]) and members[r].name not in tried)
            message = record.message.split(REFUSED)[0].split(MOVING)[0]
            candidates.append(Candidate(f, message, untried, NEIGHBOUR_TRIES - len(tried)))
    return candidates, moving


def neighbours_to_try(frames: Sequence[FrameInput], records: Mapping[str, FrameRecord],
                      coming: Set[str] = frozenset()) -> set[str]:
    """The frames whose tag was not found that have an extracted neighbour (status ``ok``, or in
    ``coming``; at most :data:`NEIGHBOUR_REACH` places away in their sequence) they have not
    tried, with tries left (:data:`NEIGHBOUR_TRIES`): a neighbour round after the frames of
    ``coming`` would try to seed them.

    Args:
        frames: the frames, placed in their sequences (:func:`blurcalib.io.sources.in_sequences`).
        records: each extracted frame's record, by name.
        coming: frames the same run extracts first.
    """
    out = set()
    for members in _sequences(frames):
        for rank, f in enumerate(members):
            record = records.get(f.name)
            if record is None or record.status is not FrameStatus.NOT_SEEDED:
                continue
            tried = record.neighbours_tried or ()
            near = members[max(0, rank - NEIGHBOUR_REACH):rank + NEIGHBOUR_REACH + 1]
            extracted = [g.name for g in near if g.name in coming
                         or ((r := records.get(g.name)) is not None and r.status is FrameStatus.OK)]
            if len(tried) < NEIGHBOUR_TRIES and set(extracted) - set(tried):
                out.add(f.name)
    return out


def _next_seed(candidate: Candidate, queue: list[FrameInput], poses: Poses) -> NeighbourSeed | None:
    """The seed of the nearest neighbour left in ``queue`` (taken from it) whose features give a
    homography; None when none is left."""
    while queue:
        neighbour = queue.pop(0)
        pose = poses.of(neighbour.name)
        if pose is not None:
            return NeighbourSeed(neighbour.name, pose[0], candidate.message)
    return None


def _assign(candidates: Sequence[Candidate], poses: Poses,
            slots: int) -> list[tuple[FrameInput, list[NeighbourSeed]]]:
    """Each candidate's nearest seed, then, while there are fewer than ``slots`` attempts, more
    seeds for the first candidates that have room (in candidate order)."""
    queues = [list(c.untried) for c in candidates]
    seeds: list[list[NeighbourSeed]] = [[] for _ in candidates]
    for c, queue, mine in zip(candidates, queues, seeds, strict=True):
        seed = _next_seed(c, queue, poses)
        if seed is not None:
            mine.append(seed)
    attempts = sum(1 for mine in seeds if mine)
    while attempts < slots:
        for c, queue, mine in zip(candidates, queues, seeds, strict=True):
            if mine and len(mine) < c.room and (seed := _next_seed(c, queue, poses)) is not None:
                mine.append(seed)
                break
        else:
            break
        attempts += 1
    return [(c.frame, mine) for c, mine in zip(candidates, seeds, strict=True) if mine]
