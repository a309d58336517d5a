"""Feature extraction from frames: seed, grow, re-centre, align locally, write results.

One frame (:func:`extract_frame`): find the tag (:mod:`blurcalib.seed`), grow blocks front by
front with the batched local deconvolution (:mod:`blurcalib.grow`, :mod:`blurcalib.deconv`;
PSFs come back re-centred on their centroids, so a block's star centre ``H(0, 0)`` is the centre
of the star's time-averaged image), optionally solve the local alignment
(:mod:`blurcalib.local_alignment`) and turn accepted blocks into feature observations.

A folder run (:func:`extract_to_folder`) writes each frame's results as soon as it is done
(``frames/<stem>.*``, see ``docs/results-format.md``), so an interrupted run loses at most the
frame in progress and a re-run skips finished frames; at the end the per-frame files are
collected into ``features.csv``, ``blocks.csv``, ``psfs.npz``, ``corners.csv`` (the square
corners shared by neighbouring blocks, after local alignment) and ``frames.csv`` (per-frame
status).
"""

from __future__ import annotations

import csv
import json
import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

import numpy as np

from blurcalib.deconv import DeconvSettings
from blurcalib.fileio import atomic_write_csv, atomic_write_text, ensure_writable_dir
from blurcalib.frames import FrameError, load_frame
from blurcalib.grow import GrowSettings, Growth, GrowthEvent, grow
from blurcalib.local_alignment import LocalAlignment, align_locally, shared_corners
from blurcalib.pattern import StarPattern
from blurcalib.results import (
    BlockResult,
    BlockStatus,
    FeatureFlags,
    FeatureObservation,
    collect_results,
    completed_frames,
    frame_result_paths,
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
    FAILED = "failed"


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
        """Settings for sharp frames: the same engine with a small (7 x 7) PSF window."""
        return replace(ExtractSettings(deconv=DeconvSettings(kernel_size=7), kind="sharp"),
                       **changes)


@dataclass
class FrameResult:
    """Everything extracted from one frame.

    Attributes:
        frame: frame name.
        status: outcome; ``message`` says why when not ok.
        blocks: every attempted block with its figures and status.
        features: one star-centre observation per accepted block.
        corners: the square corners shared by accepted neighbouring blocks, after local
            alignment (:func:`corner_rows`), one row each.
        seed, growth, local: the intermediate results (None where not reached).
        seconds: time spent in ``seed``, ``fit`` (growth) and ``align``.
    """

    frame: str
    status: FrameStatus
    message: str = ""
    blocks: list[BlockResult] = field(default_factory=list)
    features: list[FeatureObservation] = field(default_factory=list)
    corners: list[list] = field(default_factory=list)
    seed: Seed | None = None
    growth: Growth | None = None
    local: LocalAlignment | None = None
    seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict:
        """A JSON-serialisable one-line summary (the row of ``frames.csv``)."""
        accepted = sum(b.status is BlockStatus.ACCEPTED for b in self.blocks)
        return {"frame": self.frame, "status": self.status.value, "message": self.message,
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
            result.blocks = _block_results(frame, pattern, growth, None)
        return result
    acc = np.flatnonzero(growth.accepted)
    local = None
    if len(acc):
        f = pattern.features[growth.feature_id[acc]]
        local = align_locally(growth.fit.H[acc], f[:, 0], f[:, 1])
    seconds["align"] = time.perf_counter() - t2
    blocks = _block_results(frame, pattern, growth, local if settings.local_alignment else None)
    features = _features(frame, pattern, blocks, settings)
    f = pattern.features[growth.feature_id[acc]]
    corners = corner_rows(frame, pattern, local.H, f[:, 0], f[:, 1])
    return FrameResult(frame, FrameStatus.OK, "", blocks, features, corners, seed, growth, local,
                       seconds)


CORNER_COLUMNS = ("frame", "cx2", "cy2", "X", "Y", "x", "y", "blocks")
"""Columns of ``corners.csv``: the corner's feature coordinates doubled (``cx2 = 2 fx + 1`` for
the corner half a square right of feature ``fx``), its metric point ``(cx2 L / 2, cy2 L / 2)``
(m), its image position (px, OpenCV convention) and the number of blocks that share it."""


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


def _block_results(frame: str, pattern: StarPattern, growth: Growth,
                   local: LocalAlignment | None) -> list[BlockResult]:
    fit = growth.fit
    H = fit.H.copy()
    if local is not None:
        H[np.flatnonzero(growth.accepted)] = local.H
    out = []
    for k, fid in enumerate(growth.feature_id):
        fx, fy = (int(v) for v in pattern.features[fid])
        out.append(BlockResult(
            frame=frame, feature_id=int(fid), fx=fx, fy=fy, H=H[k], psf=np.nan_to_num(fit.psf[k]),
            coeffs=fit.coeffs[k], loss=float(fit.loss[k]),
            boundary_energy=float(fit.boundary_energy[k]), sigma_major=float(fit.sigma_major[k]),
            sigma_minor=float(fit.sigma_minor[k]), eccentricity=float(fit.eccentricity[k]),
            orientation=float(fit.orientation[k]), centroid=fit.centroid[k],
            status=growth.status[k]))
    return out


def _features(frame: str, pattern: StarPattern, blocks: list[BlockResult],
              settings: ExtractSettings) -> list[FeatureObservation]:
    flags = FeatureFlags.STAR_CENTRE | (FeatureFlags.SHARP_FRAME if settings.kind == "sharp"
                                        else FeatureFlags.BLURRY_FRAME)
    if settings.local_alignment:
        flags |= FeatureFlags.LOCALLY_ALIGNED
    L = pattern.square_length_m
    out = []
    for b in blocks:
        if b.status is not BlockStatus.ACCEPTED:
            continue
        x, y = b.H[:2, 2] / b.H[2, 2]
        out.append(FeatureObservation(frame, b.feature_id, b.fx, b.fy, b.fx * L, b.fy * L,
                                      float(x), float(y), 1.0 / (1.0 + b.loss), int(flags)))
    return out


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


def _process(path: Path, name: str, pattern: StarPattern, settings: ExtractSettings,
             expected_size: tuple[int, int] | None) -> FrameResult:
    t0 = time.perf_counter()
    try:
        image = load_frame(path, expected_size=expected_size)
    except FrameError as exc:
        return FrameResult(name, FrameStatus.UNREADABLE, str(exc),
                           seconds={"load": time.perf_counter() - t0})
    try:
        return extract_frame(image, pattern, name, settings)
    except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
        return FrameResult(name, FrameStatus.FAILED, f"{type(exc).__name__}: {exc}")


def _process_in_worker(path: Path, name: str, expected_size: tuple[int, int] | None
                       ) -> FrameResult:
    assert _WORKER_STATE is not None
    return _process(path, name, *_WORKER_STATE, expected_size)


def _write_frame(out: Path, result: FrameResult) -> dict:
    summary = result.summary()
    paths = frame_result_paths(out, result.frame)
    status_path = paths["done"].with_name(paths["done"].name.replace(".done", ".status.json"))
    ensure_writable_dir(status_path.parent)
    atomic_write_text(status_path, json.dumps(summary))
    atomic_write_csv(_corners_path(status_path), CORNER_COLUMNS, result.corners)
    write_frame_results(out, result.frame, result.features, result.blocks)
    return summary


def _corners_path(status_path: Path) -> Path:
    return status_path.with_name(status_path.name.replace(".status.json", ".corners.csv"))


def _collect_corners(out: Path, names: Sequence[str]) -> Path:
    """Concatenate the per-frame corner tables of ``names`` into ``corners.csv``."""
    rows: list[list[str]] = []
    for name in names:
        done = frame_result_paths(out, name)["done"]
        path = _corners_path(done.with_name(done.name.replace(".done", ".status.json")))
        if path.is_file():
            with open(path, newline="", encoding="utf-8") as handle:
                rows += list(csv.reader(handle))[1:]
    return atomic_write_csv(out / "corners.csv", CORNER_COLUMNS, rows)


def _read_summary(out: Path, name: str) -> dict:
    paths = frame_result_paths(out, name)
    status_path = paths["done"].with_name(paths["done"].name.replace(".done", ".status.json"))
    try:
        return json.loads(status_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {"frame": name, "status": "ok", "message": "(summary missing)"}


def write_frames_table(out: Path, summaries: Sequence[dict]) -> Path:
    """``frames.csv``: one row per frame (frame, status, message, blocks, accepted, features,
    seconds)."""
    cols = ["frame", "status", "message", "blocks", "accepted", "features", "seconds"]
    rows = [[s.get(c, "") for c in cols] for s in sorted(summaries, key=lambda r: r["frame"])]
    return atomic_write_csv(out / FRAMES_TABLE, cols, rows)


def extract_to_folder(paths: Sequence[Path], pattern: StarPattern, out_dir: str | os.PathLike,
                      settings: ExtractSettings | None = None, workers: int = 1,
                      progress: Callable[[int, int, dict], None] | None = None,
                      expected_size: tuple[int, int] | None = None,
                      names: Sequence[str] | None = None, cluster: str | None = None) -> FolderSummary:
    """Extract every frame of ``paths`` into ``out_dir`` (resumable).

    Frames already done in ``out_dir`` are skipped. An unreadable frame, a frame that cannot
    be seeded or fails is recorded with its status and message; the others go on. Frames are
    named by :func:`frame_names` unless ``names`` gives one per path. With ``cluster`` (a Dask
    scheduler address) the frames run as tasks there (:mod:`blurcalib.cluster`), else in
    ``workers`` local processes.
    """
    settings = settings or ExtractSettings()
    out = ensure_writable_dir(out_dir)
    names = list(names) if names is not None else frame_names(list(paths))
    if len(names) != len(paths) or len(set(names)) != len(names):
        raise ValueError("frame names must be unique, one per path")
    done = completed_frames(out)
    summaries = {n: _read_summary(out, n) for n in names if n in done}
    todo = [(p, n) for p, n in zip(paths, names, strict=True) if n not in done]
    skipped = [n for n in names if n in done]

    def finish(result: FrameResult) -> None:
        summaries[result.frame] = _write_frame(out, result)
        write_frames_table(out, list(summaries.values()))
        if progress is not None:
            progress(len(summaries), len(names), summaries[result.frame])

    if cluster is not None and todo:
        from blurcalib.cluster import run_on_cluster

        for result in run_on_cluster(cluster, _process, [(p, n) for p, n in todo],
                                     (pattern, settings, expected_size)):
            finish(result)
    elif workers > 1 and len(todo) > 1:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                 initargs=(pattern, settings)) as pool:
            futures = [pool.submit(_process_in_worker, p, n, expected_size) for p, n in todo]
            for future in as_completed(futures):
                finish(future.result())
    else:
        for p, n in todo:
            finish(_process(p, n, pattern, settings, expected_size))
    write_frames_table(out, list(summaries.values()))
    outputs = collect_results(out)
    outputs["corners"] = _collect_corners(out, [n for n in names if n in summaries])
    outputs["frames"] = out / FRAMES_TABLE
    return FolderSummary([summaries[n] for n in names if n in summaries], skipped, outputs)
