"""Extraction of many frames into an output folder, resumable.

A folder run (:func:`extract_to_folder`) writes each frame's results as soon as it is done
(``frames/<stem>.*``, see ``docs/results-format.md``), so an interrupted run loses at most the
frame in progress and a re-run skips frames finished with the same pattern, settings and input
file; at the end the per-frame files of the run's frames are collected into ``features.csv``,
``blocks.csv``, ``psfs.npz``, ``corners.csv`` (the square corners shared by neighbouring
blocks, after local alignment) and ``frames.csv`` (per-frame status). Frames come from folders,
image files and videos (:mod:`blurcalib.io.sources`); in a sequence, a frame whose tag is not found
is seeded from its nearest extracted neighbour, verified against its own pixels
(:func:`seed_from_neighbour`).
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from contextlib import ExitStack
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from blurcalib.extract.frame import (
    FINAL_STATUSES,
    FRAMES_TABLE,
    ExtractSettings,
    FrameResult,
    FrameStatus,
    extract_frame,
    grow_frame,
)
from blurcalib.geometry.homography import homography_centre, homography_scale, translation
from blurcalib.growth.seed import (
    LabelCheck,
    Seed,
    block_homography,
    check_labelling,
    homography_from_features,
    tag_ring_features,
)
from blurcalib.io.atomic import OutputError, atomic_write_csv, claim_output_dir, remove_temporaries
from blurcalib.io.frames import FrameError, FrameSizeError, frame_size_problem
from blurcalib.io.results import (
    FRAMES_DIR,
    BlockTable,
    FeatureTable,
    collect_results,
    frame_result_paths,
    read_feature_table,
    read_frame_status,
    write_frame_results,
)
from blurcalib.io.sources import FrameInput, in_sequences
from blurcalib.io.text import printable_name
from blurcalib.runs.runtime import exit_with_parent, keep_large_allocations
from blurcalib.target.pattern import StarPattern


def _located(path: Path) -> Path:
    """The absolute path a frame is named by: the file it resolves to, or, for a broken symbolic
    link or a link loop, the link itself."""
    return path.resolve() if path.exists() else path.parent.resolve() / path.name



def frame_names(paths: Sequence[Path]) -> list[str]:
    """Names recorded for frames: paths relative to their common folder (``0.png``,
    ``seq1/0.png``), with ``/`` separators, non-UTF-8 bytes escaped (:func:`printable_name`)."""
    if not paths:
        return []
    resolved = [_located(Path(p)) for p in paths]
    common = Path(os.path.commonpath([p.parent for p in resolved]))
    return [printable_name(p.relative_to(common).as_posix()) for p in resolved]


def as_frame_inputs(frames: Sequence[FrameInput | str | os.PathLike]) -> list[FrameInput]:
    """Frames given as :class:`blurcalib.io.sources.FrameInput` or as image paths (named by
    :func:`frame_names`, each in the sequence of its folder, in the order given)."""
    paths = [Path(f) for f in frames if not isinstance(f, FrameInput)]
    named = iter(in_sequences([FrameInput(n, p) for p, n in zip(paths, frame_names(paths), strict=True)]))
    return [f if isinstance(f, FrameInput) else next(named) for f in frames]


def _source(frame: FrameInput) -> str:
    """What a frame was extracted from: its file, and a video frame's index (``walk.mp4#12``)."""
    path = printable_name(str(_located(frame.path)))
    return path if frame.index is None else f"{path}#{frame.index}"


@dataclass(frozen=True)
class FolderSummary:
    """Outcome of :func:`extract_to_folder`: per-frame summaries and the output files."""

    frames: list[dict]
    skipped: list[str]
    outputs: dict[str, Path]


def _init_worker() -> None:
    """A worker process of a :class:`FramePool`: one torch thread, glibc's allocations kept."""
    import torch

    exit_with_parent()
    keep_large_allocations()  # a spawned worker starts with glibc's defaults
    torch.set_num_threads(1)


class FramePool:
    """Worker processes for :func:`extract_to_folder`, started on first use and kept for the
    calls that share it (the sharp and blurry folders of a calibration: starting ``workers``
    processes, each importing torch, takes about 2 s of wall time).

    A context manager: the processes end with it. Tasks carry their pattern and settings, so
    calls with different settings share the processes.
    """

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._executor: ProcessPoolExecutor | None = None

    def __enter__(self) -> FramePool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def submit(self, frame: FrameInput, hint: NeighbourSeed | None, pattern: StarPattern,
               settings: ExtractSettings, expected_size: tuple[int, int] | None) -> Future:
        """Process a frame (:func:`_process`) in a worker; the processes start on the first task."""
        if self._executor is None:
            spawn = multiprocessing.get_context("spawn")
            self._executor = ProcessPoolExecutor(self.workers, mp_context=spawn, initializer=_init_worker)
        return self._executor.submit(_process, frame, hint, pattern, settings, expected_size)

    def close(self) -> None:
        """End the worker processes (a later task starts new ones: after a broken pool, e.g. a
        worker killed for memory)."""
        if self._executor is not None:
            self._executor.shutdown()
            self._executor = None


def _one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


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


_MOVING = "; not seeded from its neighbours: its sequence moves the target by "
"""Starts the part of a ``not_seeded`` frame's message that says why no neighbour's seed was tried."""

_REFUSED = "; the seed from neighbour "
"""Starts the part of a ``not_seeded`` frame's message that says why a neighbour's seed was refused."""


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
                        settings: ExtractSettings | None = None) -> FrameResult:
    """Extract a frame from a neighbour's seed, accepted only when its labelling is verified.

    The frame is grown from ``hint.H_feature`` (from the ring around the tag when it is in view,
    else from the blocks nearest the image centre) and
    its star centres' homography is checked against its pixels (:func:`verify_labelling`): a
    seed a square (or more) off grows as well as a right one, and only the tag and the target's
    border tell them apart. An accepted frame is ``ok`` with ``seeded_by = neighbour``; a refused
    one stays ``not_seeded``, the message saying why.
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
    result = grow_frame(image, pattern, frame, seed, settings)
    refused = f"{hint.message}{_REFUSED}{hint.neighbour} was refused: "
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


def _process(frame: FrameInput, hint: NeighbourSeed | None, pattern: StarPattern,
             settings: ExtractSettings, expected_size: tuple[int, int] | None) -> FrameResult:
    """One frame of a folder run (from its own tag, or with ``hint`` from a neighbour);
    whatever goes wrong ends as this frame's status."""
    name = frame.name
    t0 = time.perf_counter()
    try:
        image = frame.load(expected_size=expected_size)
        if hint is not None:
            return seed_from_neighbour(image, pattern, name, hint, settings)
        return extract_frame(image, pattern, name, settings)
    except FrameSizeError as exc:
        return FrameResult(name, FrameStatus.WRONG_SIZE, str(exc),
                           seconds={"load": time.perf_counter() - t0})
    except FrameError as exc:
        return FrameResult(name, FrameStatus.UNREADABLE, str(exc),
                           seconds={"load": time.perf_counter() - t0})
    except Exception as exc:  # any failure stays with its frame; the batch goes on
        return FrameResult(name, FrameStatus.FAILED, _one_line(exc),
                           seconds={"failed": time.perf_counter() - t0})


def _settings_record(settings: ExtractSettings) -> dict:
    """The settings that determine a frame's result, as a JSON-serialisable dict (the torch
    device aside: it changes where, not what, is computed)."""
    record = asdict(settings)
    record["deconv"].pop("device")
    return record


def _digest(doc: object) -> str:
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode("utf-8")).hexdigest()


def _input_key(run_key: str, frame: FrameInput) -> str:
    """A frame's result key: the run's pattern and settings, the input file's size and
    modification time and a video frame's index (a missing file gets a key of its own and is
    redone)."""
    try:
        st = frame.path.stat()
        stamp: object = [st.st_size, st.st_mtime_ns]
    except OSError:
        stamp = None
    return _digest([run_key, stamp] if frame.index is None else [run_key, stamp, frame.index])


def _common_size(sizes: Sequence[tuple[int, int] | None]) -> tuple[int, int] | None:
    """The most common size of the frames that can be processed (the first seen among
    equally common ones), None if there is none."""
    known = [s for s in sizes if s is not None and frame_size_problem(*s) is None]
    return max(dict.fromkeys(known), key=known.count) if known else None


def write_frames_table(out: Path, summaries: Sequence[dict]) -> Path:
    """``frames.csv``: one row per frame (frame, status, message, seeded_by, psf, kind, blur_px,
    noise_dn, blocks, accepted, features, seconds)."""
    cols = ["frame", "status", "message", "seeded_by", "psf", "kind", "blur_px", "noise_dn", "blocks",
            "accepted", "features", "seconds"]
    rows = [[s.get(c, "") for c in cols] for s in sorted(summaries, key=lambda r: r["frame"])]
    return atomic_write_csv(out / FRAMES_TABLE, cols, rows)


def _check_sources(out: Path, sources: dict[str, str]) -> None:
    """Refuse to replace a frame's stored result that was extracted from another file (another
    dataset whose frames have the same names): each result records its ``source``."""
    for name, source in sources.items():
        status = read_frame_status(out, name)
        recorded = None if status is None else status.get("source")
        if recorded is not None and recorded != source:
            raise OutputError(f"{out}: its frame {name} was extracted from {recorded}, not {source} "
                              f"(another dataset with the same frame names); use --overwrite to "
                              f"replace its results, or choose another output folder")


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


def _neighbour_seeds(out: Path, frames: Sequence[FrameInput], summaries: dict[str, dict], slots: int
                     ) -> tuple[list[tuple[FrameInput, list[NeighbourSeed]]], dict[str, float]]:
    """The frames ended ``not_seeded`` that have an extracted neighbour not tried yet
    (:data:`NEIGHBOUR_REACH`, :data:`NEIGHBOUR_TRIES`) and whose sequence moves slowly around
    them (:data:`NEIGHBOUR_MOTION_SQUARES`, over the extracted frames within twice the reach),
    each with the seeds of its untried neighbours to try in this round, nearest first: every
    frame its nearest one's, and while the round has fewer than ``slots`` attempts, the frames
    their next ones'. Also returns the frames passed over because their sequence moves faster,
    with its motion (squares per frame)."""
    sequences: dict[str, list[FrameInput]] = {}
    for f in frames:
        if f.sequence:
            sequences.setdefault(f.sequence, []).append(f)
    known: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}

    def homography(name: str) -> tuple[np.ndarray, np.ndarray] | None:
        """An extracted frame's homography and mean feature coordinates (None: too few stars)."""
        if name not in known:
            table = read_feature_table(frame_result_paths(out, name).features)
            H = homography_from_features(table.fx, table.fy, table.x, table.y)
            known[name] = None if H is None else (H, np.array([table.fx.mean(), table.fy.mean()]))
        return known[name]

    def extracted(g: FrameInput) -> bool:
        return summaries.get(g.name, {}).get("status") == FrameStatus.OK.value

    candidates: list[tuple[FrameInput, str, list[FrameInput], int]] = []
    moving: dict[str, float] = {}
    for members in sequences.values():
        members = sorted(members, key=lambda f: f.order)
        for rank, f in enumerate(members):
            status = summaries.get(f.name, {})
            tried = status.get("neighbours_tried", [])
            if status.get("status") != FrameStatus.NOT_SEEDED.value or len(tried) >= NEIGHBOUR_TRIES:
                continue
            reach = 2 * NEIGHBOUR_REACH
            around = range(max(0, rank - reach), min(len(members), rank + reach + 1))
            poses = [(r, *pose) for r in around if extracted(members[r])
                     and (pose := homography(members[r].name)) is not None]
            motion = sequence_motion(poses)
            if motion > NEIGHBOUR_MOTION_SQUARES:
                moving[f.name] = motion
                continue
            near = sorted((abs(r - rank), r) for r in range(max(0, rank - NEIGHBOUR_REACH),
                                                           min(len(members), rank + NEIGHBOUR_REACH + 1)))
            untried = [members[r] for _, r in near if extracted(members[r]) and members[r].name not in tried]
            message = status.get("message", "").split(_REFUSED)[0].split(_MOVING)[0]
            candidates.append((f, message, untried, NEIGHBOUR_TRIES - len(tried)))
    rounds: dict[str, tuple[FrameInput, list[NeighbourSeed]]] = {}

    def add(f: FrameInput, message: str, untried: list[FrameInput], room: int) -> bool:
        """The seed of ``f``'s nearest untried neighbour whose features give a homography, while
        ``f`` has ``room`` for more tries."""
        while untried and len(rounds.get(f.name, (f, []))[1]) < room:
            g = untried.pop(0)
            pose = homography(g.name)
            if pose is not None:
                rounds.setdefault(f.name, (f, []))[1].append(NeighbourSeed(g.name, pose[0], message))
                return True
        return False

    for c in candidates:
        add(*c)
    attempts = len(rounds)
    while attempts < slots and any(add(*c) for c in candidates if c[0].name in rounds):
        attempts += 1
    return list(rounds.values()), moving


def extract_to_folder(frames: Sequence[FrameInput | Path], pattern: StarPattern, out_dir: str | os.PathLike,
                      settings: ExtractSettings | None = None, workers: int = 1,
                      progress: Callable[[int, int, dict], None] | None = None,
                      expected_size: tuple[int, int] | None = None, overwrite: bool = False,
                      cluster: str | None = None, pool: FramePool | None = None) -> FolderSummary:
    """Extract every frame of ``frames`` into ``out_dir`` (resumable).

    Every frame ends with a status: an unreadable frame, one of another size, one that cannot
    be seeded or fails is recorded with its status and message, and the others go on. A frame
    finished by an earlier run is skipped when its result key (the pattern, the settings, the
    input file's size and modification time and a video frame's index) is unchanged and its
    status is final (:data:`FINAL_STATUSES`); otherwise it is redone. The top-level tables list
    exactly the frames of this run, by their names. With ``cluster`` (a Dask scheduler address)
    the frames run as tasks there (:mod:`blurcalib.runs.cluster`), else in the worker
    processes of ``pool`` (:class:`FramePool`, shared between calls), or of ``workers`` processes
    started for this call (one: this process).

    Once every frame has been tried from its own tag, the frames of a sequence (a video, a
    folder) whose tag was not found are seeded from their nearest extracted neighbour and
    verified (:func:`seed_from_neighbour`), in rounds, so that a seeded frame can seed the next.
    With several workers, while a round has fewer than :data:`NEIGHBOUR_TRIES` attempts per
    worker, its frames try their next neighbours in it too, and the nearest verified seed is
    kept: the round takes about as long as the rounds one neighbour at a time would, and ends
    with the same result. Where the sequence moves the target by more than
    :data:`NEIGHBOUR_MOTION_SQUARES` squares per frame around a frame (frames of unrelated
    poses), no neighbour's seed can be right and none is tried; the frame's message says so.

    Args:
        frames: :class:`blurcalib.io.sources.FrameInput` (:func:`blurcalib.io.sources.frame_inputs`),
            or image paths (:func:`as_frame_inputs`).
        expected_size: ``(width, height)`` every frame must have; None takes the most common
            size of the readable frames. Frames of another size get the status ``wrong_size``.
        overwrite: write into a non-empty folder that is not an ``extract`` output
            (:func:`blurcalib.io.atomic.claim_output_dir`), or replace results of frames of the
            same name extracted from other files (each frame's status records its ``source``).
    Raises:
        OutputError: the folder holds something else, or results of another dataset's frames
            of the same names (without ``overwrite``), or cannot be written.
    """
    settings = settings or ExtractSettings()
    inputs = as_frame_inputs(frames)
    names = [f.name for f in inputs]
    if len(set(names)) != len(names):
        raise ValueError("frame names must be unique, one per frame")
    record = _settings_record(settings)
    sources = {f.name: _source(f) for f in inputs}
    if not overwrite:
        _check_sources(Path(out_dir), sources)
    out = claim_output_dir(out_dir, "extract", record, overwrite)
    remove_temporaries(out / FRAMES_DIR)
    video_sizes: dict[Path, tuple[int, int] | None] = {}
    for f in inputs:
        if f.index is not None and f.path not in video_sizes:
            video_sizes[f.path] = f.size()
    sizes = {f.name: f.size() if f.index is None else video_sizes[f.path] for f in inputs}
    size = expected_size or _common_size(list(sizes.values()))
    run_key = _digest({"pattern": pattern.to_yaml_text(), "settings": record})
    keys = {f.name: _input_key(run_key, f) for f in inputs}
    summaries: dict[str, dict] = {}
    for n in names:
        status = read_frame_status(out, n)
        if (status is not None and status.get("key") == keys[n]
                and status.get("status") in FINAL_STATUSES
                and (size is None or sizes[n] in (None, size))):
            summaries[n] = status
    skipped = list(summaries)
    tried: dict[str, list[str]] = {}

    def finish(result: FrameResult) -> None:
        summary = {**result.summary(), "key": keys[result.frame], "source": sources[result.frame]}
        if result.frame in tried:
            summary["neighbours_tried"] = tried[result.frame]
        write_frame_results(out, result.frame, result.features, result.blocks, result.corners,
                            summary)
        summaries[result.frame] = summary
        write_frames_table(out, list(summaries.values()))
        if progress is not None:
            progress(len(summaries), len(names), summary)

    def attempts(rounds: list[tuple[FrameInput, list[NeighbourSeed]]]) -> Callable[[int, FrameResult], None]:
        """The callback of a round of neighbour seeds: a frame's attempts, once all are in, are
        finished as the first verified one (nearest neighbour first), else the last refusal."""
        expected = {f.name: len(hints) for f, hints in rounds}
        got: dict[str, dict[int, FrameResult]] = {name: {} for name in expected}

        def done(i: int, result: FrameResult) -> None:
            mine = got[result.frame]
            mine[i] = result
            if len(mine) == expected[result.frame]:
                ordered = [mine[k] for k in sorted(mine)]
                finish(next((r for r in ordered if r.status is FrameStatus.OK), ordered[-1]))

        return done

    with ExitStack() as stack:
        if pool is None and cluster is None and workers > 1:
            pool = stack.enter_context(FramePool(workers))
        parallel = cluster is None and pool is not None and pool.workers > 1

        def run(tasks: list[tuple[FrameInput, NeighbourSeed | None]],
                done: Callable[[int, FrameResult], None]) -> None:
            """Process ``tasks``, calling ``done(i, result)`` for each as it finishes."""
            if cluster is not None and tasks:
                from blurcalib.runs.cluster import run_on_cluster

                for i, result in run_on_cluster(cluster, _process, tasks, (pattern, settings, size)):
                    done(i, result)
            elif parallel and len(tasks) > 1:
                futures = {pool.submit(f, hint, pattern, settings, size): i
                           for i, (f, hint) in enumerate(tasks)}
                for future in as_completed(futures):
                    i = futures[future]
                    try:
                        result = future.result()
                    except Exception as exc:  # a worker died (e.g. out of memory): the frame failed
                        result = FrameResult(tasks[i][0].name, FrameStatus.FAILED, _one_line(exc))
                        if isinstance(exc, BrokenProcessPool):  # the next tasks get new processes
                            pool.close()
                    done(i, result)
            else:
                for i, (f, hint) in enumerate(tasks):
                    done(i, _process(f, hint, pattern, settings, size))

        run([(f, None) for f in inputs if f.name not in summaries], lambda _, result: finish(result))
        # more tries at once only where they run side by side (one process tries one at a time)
        side_by_side = len(inputs) if cluster is not None else pool.workers if parallel else 0
        slots = NEIGHBOUR_TRIES * side_by_side
        while True:
            rounds, moving = _neighbour_seeds(out, inputs, summaries, slots)
            if not rounds:
                break
            for f, hints in rounds:
                before = summaries[f.name].get("neighbours_tried", [])
                tried[f.name] = [*before, *(h.neighbour for h in hints)]
            run([(f, hint) for f, hints in rounds for hint in hints], attempts(rounds))
    for name, motion in moving.items():  # say why these were not seeded from their neighbours
        summary = summaries[name]
        if _MOVING not in summary.get("message", ""):
            limit = f"{NEIGHBOUR_MOTION_SQUARES:g}"
            summary["message"] = (f"{summary.get('message', '')}{_MOVING}{motion:.1f} squares per frame "
                                  f"around it (a neighbour's seed needs at most {limit})")
            write_frame_results(out, name, FeatureTable.empty(), BlockTable.empty(), [], summary)
    outputs = collect_results(out, names)
    outputs["frames"] = write_frames_table(out, list(summaries.values()))
    return FolderSummary([summaries[n] for n in names], skipped, outputs)
