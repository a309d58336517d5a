"""Feature extraction from frames: seed, grow, re-centre, align locally, write results.

One frame (:func:`extract_frame`): find the tag (:mod:`blurcalib.seed`), grow blocks front by
front with the batched local deconvolution (:mod:`blurcalib.grow`, :mod:`blurcalib.deconv`;
PSFs come back re-centred on their centroids, so a block's star centre ``H(0, 0)`` is the centre
of the star's time-averaged image), optionally solve the local alignment
(:mod:`blurcalib.local_alignment`) and turn accepted blocks into feature observations.

A folder run (:func:`extract_to_folder`) writes each frame's results as soon as it is done
(``frames/<stem>.*``, see ``docs/results-format.md``), so an interrupted run loses at most the
frame in progress and a re-run skips frames finished with the same pattern, settings and input
file; at the end the per-frame files of the run's frames are collected into ``features.csv``,
``blocks.csv``, ``psfs.npz``, ``corners.csv`` (the square corners shared by neighbouring
blocks, after local alignment) and ``frames.csv`` (per-frame status).
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, replace
from enum import Enum
from pathlib import Path

import numpy as np

from blurcalib.deconv import DeconvSettings
from blurcalib.fileio import atomic_write_csv, claim_output_dir, remove_temporaries
from blurcalib.frames import FrameError, FrameSizeError, frame_size, frame_size_problem, load_frame
from blurcalib.grow import GrowSettings, Growth, GrowthEvent, grow
from blurcalib.local_alignment import LocalAlignment, align_locally, shared_corners
from blurcalib.pattern import StarPattern
from blurcalib.results import (
    FRAMES_DIR,
    BlockTable,
    FeatureFlags,
    FeatureTable,
    collect_results,
    read_frame_status,
    write_frame_results,
)
from blurcalib.seed import DEFAULT_SCALES, Seed, SeedError, seed_frame

FRAMES_TABLE = "frames.csv"


class FrameStatus(str, Enum):
    """Outcome of one frame."""

    OK = "ok"
    NOT_SEEDED = "not_seeded"
    NO_BLOCKS = "no_blocks"
    UNREADABLE = "unreadable"
    WRONG_SIZE = "wrong_size"
    FAILED = "failed"


FINAL_STATUSES = frozenset({FrameStatus.OK.value, FrameStatus.NOT_SEEDED.value,
                            FrameStatus.NO_BLOCKS.value})
"""Outcomes a resumed run keeps; unreadable, wrong-size and failed frames are retried."""


@dataclass(frozen=True)
class ExtractSettings:
    """How frames are processed.

    Attributes:
        deconv: block solver settings (kernel size etc.).
        grow: growth acceptance rules.
        local_alignment: move each block's star centre by its local-alignment translation.
        kind: ``"blurry"`` or ``"sharp"`` (recorded in the feature flags).
        scales: tag detection scales.
    """

    deconv: DeconvSettings = field(default_factory=DeconvSettings)
    grow: GrowSettings = field(default_factory=GrowSettings)
    local_alignment: bool = False
    kind: str = "blurry"
    scales: tuple[float, ...] = DEFAULT_SCALES

    @staticmethod
    def sharp(**changes) -> ExtractSettings:
        """Settings for sharp frames: the same engine with a small (7 x 7) PSF window and free
        PSFs only (no motion-path field: a sharp frame's PSF is its defocus; 4 of the demo's 20
        sharp frames adapt their window, and their features stay as measured before the field)."""
        return replace(ExtractSettings(deconv=DeconvSettings(kernel_size=7),
                                       grow=GrowSettings(psf_field=False), kind="sharp"), **changes)


@dataclass
class FrameResult:
    """Everything extracted from one frame.

    Attributes:
        frame: frame name.
        status: outcome; ``message`` says why when not ok.
        blocks: every attempted block with its figures and status.
        features: one star-centre observation per accepted block (:meth:`BlockTable.features`).
        corners: the square corners shared by accepted neighbouring blocks, after local
            alignment (:func:`corner_rows`), one row each.
        seed, growth, local: the intermediate results (None where not reached).
        seconds: time spent in ``seed``, ``fit`` (growth) and ``align``.
    """

    frame: str
    status: FrameStatus
    message: str = ""
    blocks: BlockTable = field(default_factory=BlockTable.empty)
    features: FeatureTable = field(default_factory=FeatureTable.empty)
    corners: list[list] = field(default_factory=list)
    seed: Seed | None = None
    growth: Growth | None = None
    local: LocalAlignment | None = None
    seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict:
        """A JSON-serialisable one-line summary (the row of ``frames.csv``; ``psf`` says whether
        the blocks were fitted with the frame's path-PSF field, ``field``, or with free PSFs,
        ``free``, and ``psf_field`` holds the field, :meth:`blurcalib.psf_field.PathField.to_dict`)."""
        accepted = int(self.blocks.accepted.sum())
        path_field = self.growth.psf_field if self.growth is not None else None
        psf = {"psf": "" if self.growth is None else "free" if path_field is None else "field"}
        if path_field is not None:
            psf["psf_field"] = path_field.to_dict()
        return {"frame": self.frame, "status": self.status.value, "message": self.message,
                "seeded_by": self.seed.method if self.seed is not None else "", **psf,
                "blocks": len(self.blocks), "accepted": accepted, "features": len(self.features),
                "seconds": round(sum(self.seconds.values()), 3),
                **{f"seconds_{k}": round(v, 3) for k, v in self.seconds.items()}}


def extract_frame(image: np.ndarray, pattern: StarPattern, frame: str,
                  settings: ExtractSettings | None = None, H_feature: np.ndarray | None = None,
                  on_event: Callable[[GrowthEvent], None] | None = None,
                  should_stop: Callable[[], bool] | None = None) -> FrameResult:
    """Extract features and PSFs from one frame ``image (H, W)`` (grey levels 0..255).

    Args:
        image: the frame.
        pattern: the target.
        frame: the frame's name (recorded in every row).
        settings: processing settings (blurry-frame defaults).
        H_feature: a seed homography (feature coordinates -> px) to use instead of the tag.
        on_event: per-block growth callback (for live display).
        should_stop: polled between growth fronts.
    """
    settings = settings or ExtractSettings()
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    try:
        seed = seed_frame(image, pattern, H_feature, settings.scales)
    except SeedError as exc:
        return FrameResult(frame, FrameStatus.NOT_SEEDED, str(exc),
                           seconds={"seed": time.perf_counter() - t0})
    t1 = time.perf_counter()
    seconds["seed"] = t1 - t0
    growth = grow(image, pattern, seed, settings.deconv, settings.grow, on_event, should_stop)
    t2 = time.perf_counter()
    seconds["fit"] = t2 - t1
    if growth is None or not growth.accepted.any():
        result = FrameResult(frame, FrameStatus.NO_BLOCKS,
                             "the tag was found but no block around it could be fitted",
                             seed=seed, growth=growth, seconds=seconds)
        if growth is not None:
            result.blocks = _block_table(frame, pattern, growth, None)
        return result
    acc = np.flatnonzero(growth.accepted)
    local = None
    if len(acc):
        f = pattern.features[growth.feature_id[acc]]
        local = align_locally(growth.fit.H[acc], f[:, 0], f[:, 1])
    seconds["align"] = time.perf_counter() - t2
    blocks = _block_table(frame, pattern, growth, local if settings.local_alignment else None)
    features = _features(pattern, blocks, settings)
    f = pattern.features[growth.feature_id[acc]]
    corners = corner_rows(frame, pattern, local.H, f[:, 0], f[:, 1])
    return FrameResult(frame, FrameStatus.OK, "", blocks, features, corners, seed, growth, local,
                       seconds)


def corner_rows(frame: str, pattern: StarPattern, H: np.ndarray, fx: np.ndarray,
                fy: np.ndarray) -> list[list]:
    """Rows of ``corners.csv`` for the square corners shared by at least two blocks.

    Args:
        frame: frame name.
        pattern: the target.
        H: ``(B, 3, 3)`` block homographies after local alignment.
        fx, fy: ``(B,)`` feature coordinates of the blocks.
    """
    corner2, xy, count = shared_corners(H, fx, fy)
    half = pattern.square_length_m / 2.0
    return [[frame, int(c[0]), int(c[1]), c[0] * half, c[1] * half, float(p[0]), float(p[1]), int(n)]
            for c, p, n in zip(corner2, xy, count, strict=True)]


def _block_table(frame: str, pattern: StarPattern, growth: Growth,
                 local: LocalAlignment | None) -> BlockTable:
    """Every attempted block of a growth, with the local alignment's homographies for the
    accepted ones when ``local`` is given."""
    fit = growth.fit
    H = fit.H.copy()
    if local is not None:
        H[np.flatnonzero(growth.accepted)] = local.H
    f = pattern.features[growth.feature_id]
    return BlockTable(np.full(len(f), frame), growth.feature_id, f[:, 0], f[:, 1], growth.status, fit.loss,
                      fit.boundary_energy, fit.sigma_major, fit.sigma_minor, fit.eccentricity,
                      fit.orientation, fit.centroid, H, fit.coeffs, np.nan_to_num(fit.psf), fit.loss_extent)


def _features(pattern: StarPattern, blocks: BlockTable, settings: ExtractSettings) -> FeatureTable:
    flags = FeatureFlags.STAR_CENTRE | (FeatureFlags.SHARP_FRAME if settings.kind == "sharp"
                                        else FeatureFlags.BLURRY_FRAME)
    if settings.local_alignment:
        flags |= FeatureFlags.LOCALLY_ALIGNED
    return blocks.select(blocks.accepted).features(pattern.square_length_m, flags)


# ------------------------------------------------------------------------------- folders
def frame_names(paths: Sequence[Path]) -> list[str]:
    """Names recorded for frames: paths relative to their common folder (``0.png``,
    ``seq1/0.png``), with ``/`` separators."""
    if not paths:
        return []
    resolved = [Path(p).resolve() for p in paths]
    common = Path(os.path.commonpath([p.parent for p in resolved]))
    return [p.relative_to(common).as_posix() for p in resolved]


@dataclass(frozen=True)
class FolderSummary:
    """Outcome of :func:`extract_to_folder`: per-frame summaries and the output files."""

    frames: list[dict]
    skipped: list[str]
    outputs: dict[str, Path]


_WORKER_STATE: tuple[StarPattern, ExtractSettings] | None = None
"""Pattern and settings of a worker process of :func:`extract_to_folder` (unset in the main one)."""


def _init_worker(pattern: StarPattern, settings: ExtractSettings) -> None:
    global _WORKER_STATE  # each worker process keeps its pattern and settings
    import torch

    torch.set_num_threads(1)
    _WORKER_STATE = (pattern, settings)


def _one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


def _process(path: Path, name: str, pattern: StarPattern, settings: ExtractSettings,
             expected_size: tuple[int, int] | None) -> FrameResult:
    """One frame of a folder run; whatever goes wrong ends as this frame's status."""
    t0 = time.perf_counter()
    try:
        image = load_frame(path, expected_size=expected_size)
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


def _process_in_worker(path: Path, name: str, expected_size: tuple[int, int] | None
                       ) -> FrameResult:
    if _WORKER_STATE is None:
        raise RuntimeError("worker process was not initialised")
    return _process(path, name, *_WORKER_STATE, expected_size)


def _settings_record(settings: ExtractSettings) -> dict:
    """The settings that determine a frame's result, as a JSON-serialisable dict (the torch
    device aside: it changes where, not what, is computed)."""
    record = asdict(settings)
    record["deconv"].pop("device")
    return record


def _digest(doc: object) -> str:
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode("utf-8")).hexdigest()


def _input_key(run_key: str, path: Path) -> str:
    """A frame's result key: the run's pattern and settings and the input file's size and
    modification time (a missing file gets a key of its own and is redone)."""
    try:
        st = path.stat()
        stamp: object = [st.st_size, st.st_mtime_ns]
    except OSError:
        stamp = None
    return _digest([run_key, stamp])


def _common_size(sizes: Sequence[tuple[int, int] | None]) -> tuple[int, int] | None:
    """The most common size of the frames that can be processed (the first seen among
    equally common ones), None if there is none."""
    known = [s for s in sizes if s is not None and frame_size_problem(*s) is None]
    return max(dict.fromkeys(known), key=known.count) if known else None


def write_frames_table(out: Path, summaries: Sequence[dict]) -> Path:
    """``frames.csv``: one row per frame (frame, status, message, seeded_by, psf, blocks, accepted,
    features, seconds)."""
    cols = ["frame", "status", "message", "seeded_by", "psf", "blocks", "accepted", "features", "seconds"]
    rows = [[s.get(c, "") for c in cols] for s in sorted(summaries, key=lambda r: r["frame"])]
    return atomic_write_csv(out / FRAMES_TABLE, cols, rows)


def extract_to_folder(paths: Sequence[Path], pattern: StarPattern, out_dir: str | os.PathLike,
                      settings: ExtractSettings | None = None, workers: int = 1,
                      progress: Callable[[int, int, dict], None] | None = None,
                      expected_size: tuple[int, int] | None = None, overwrite: bool = False,
                      cluster: str | None = None) -> FolderSummary:
    """Extract every frame of ``paths`` into ``out_dir`` (resumable).

    Every frame ends with a status: an unreadable frame, one of another size, one that cannot
    be seeded or fails is recorded with its status and message, and the others go on. A frame
    finished by an earlier run is skipped when its result key (the pattern, the settings and
    the input file's size and modification time) is unchanged and its status is final
    (:data:`FINAL_STATUSES`); otherwise it is redone. The top-level tables list exactly the
    frames of this run, named by :func:`frame_names`. With ``cluster`` (a Dask scheduler
    address) the frames run as tasks there (:mod:`blurcalib.cluster`), else in ``workers``
    local processes.

    Args:
        expected_size: ``(width, height)`` every frame must have; None takes the most common
            size of the readable frames. Frames of another size get the status ``wrong_size``.
        overwrite: write into a non-empty folder that is not an ``extract`` output
            (:func:`blurcalib.fileio.claim_output_dir`).
    Raises:
        OutputError: the folder holds something else (without ``overwrite``) or cannot be
            written.
    """
    settings = settings or ExtractSettings()
    names = frame_names(list(paths))
    if len(set(names)) != len(names):
        raise ValueError("frame names must be unique, one per path")
    record = _settings_record(settings)
    out = claim_output_dir(out_dir, "extract", record, overwrite)
    remove_temporaries(out / FRAMES_DIR)
    sizes = dict(zip(names, map(frame_size, paths), strict=True))
    size = expected_size or _common_size(list(sizes.values()))
    run_key = _digest({"pattern": pattern.to_yaml_text(), "settings": record})
    keys = {n: _input_key(run_key, Path(p)) for p, n in zip(paths, names, strict=True)}
    summaries: dict[str, dict] = {}
    for n in names:
        status = read_frame_status(out, n)
        if (status is not None and status.get("key") == keys[n]
                and status.get("status") in FINAL_STATUSES
                and (size is None or sizes[n] in (None, size))):
            summaries[n] = status
    skipped = list(summaries)
    todo = [(p, n) for p, n in zip(paths, names, strict=True) if n not in summaries]

    def finish(result: FrameResult) -> None:
        summary = {**result.summary(), "key": keys[result.frame]}
        write_frame_results(out, result.frame, result.features, result.blocks, result.corners,
                            summary)
        summaries[result.frame] = summary
        write_frames_table(out, list(summaries.values()))
        if progress is not None:
            progress(len(summaries), len(names), summary)

    if cluster is not None and todo:
        from blurcalib.cluster import run_on_cluster

        for result in run_on_cluster(cluster, _process, [(p, n) for p, n in todo],
                                     (pattern, settings, size)):
            finish(result)
    elif workers > 1 and len(todo) > 1:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                 initargs=(pattern, settings)) as pool:
            futures = {pool.submit(_process_in_worker, p, n, size): n for p, n in todo}
            for future in as_completed(futures):
                try:
                    result = future.result()
                except Exception as exc:  # a worker died (e.g. out of memory): the frame failed
                    result = FrameResult(futures[future], FrameStatus.FAILED, _one_line(exc))
                finish(result)
    else:
        for p, n in todo:
            finish(_process(p, n, pattern, settings, size))
    outputs = collect_results(out, names)
    outputs["frames"] = write_frames_table(out, list(summaries.values()))
    return FolderSummary([summaries[n] for n in names], skipped, outputs)
