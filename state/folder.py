"""Finding a dataset on disk: its frames, its pattern and, for simulated data, its ground truth.

A folder holds frames directly (``images/*.png``) or in sub-folders (a simulated dataset's
``sharp/`` and ``blurry/``). The pattern is ``--pattern`` when given, else ``pattern.yaml`` in the
folder or its parent. Frame names are paths relative to the folder (``blurry/0003.png``), the
names the ground truth uses. A video file opens as a dataset of its frames, named
``VIDEO#000123`` (:mod:`blurcalib.io.sources`), with the pattern beside it.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from blurcalib.io.frames import FrameError, list_frames
from blurcalib.io.sources import frame_inputs, is_video
from blurcalib.sim.showcase import FAULTS_FILE, FrameFaults, load_faults, showcase_camera, write_showcase
from blurcalib.sim.synth import SynthConfig, write_dataset
from blurcalib.sim.truth import (
    GROUND_TRUTH_FILE,
    DatasetTruth,
    TrueCamera,
    load_ground_truth,
)
from blurcalib.target.pattern import PatternFileError, StarPattern, load_pattern

PATTERN_FILE = "pattern.yaml"

BUILTIN_DIR = Path("blurcalib") / "app_dataset"
"""The built-in dataset's folder inside the user's cache folder (:func:`builtin_dataset_folder`):
the 13 frames of :mod:`blurcalib.sim.showcase`."""

RESULTS_DIR = Path("blurcalib") / "results"
"""The folder, inside the user's cache folder, of the app's results of each dataset
(:func:`default_output_folder`)."""

EXPORT_DIR = "calibration_app"
"""Folder, inside the dataset folder, that the app exports its calibration into (its images are not
frames)."""


SHOWN_PATH_CHARS = 120
"""Longest path written whole in a message; longer ones keep their start and end."""


class DatasetError(ValueError):
    """A folder cannot be opened as a dataset; the message names the path and the problem."""


def shown_path(path: str | os.PathLike) -> str:
    """A path for a message: whole up to :data:`SHOWN_PATH_CHARS` characters, else its start and
    end around ``...`` (a 5,000-character path typed into the app stays one readable line)."""
    text = os.fspath(path)
    if len(text) <= SHOWN_PATH_CHARS:
        return text
    keep = (SHOWN_PATH_CHARS - 3) // 2
    return f"{text[:keep]}...{text[-keep:]}"


@dataclass(frozen=True)
class FrameFile:
    """One frame: its name (relative to the dataset folder), file, kind and, for a video's
    frame, its index in the video (None for an image file)."""

    name: str
    path: Path
    kind: str
    index: int | None = None


@dataclass(frozen=True)
class Dataset:
    """A folder opened for the app.

    Attributes:
        folder: the dataset folder.
        pattern_path: the pattern YAML used.
        pattern: the target.
        frames: the frame files, in order.
        truth: the ground truth of a simulated dataset (None for real data).
        warnings: problems that did not stop the load (an unreadable ground truth).
        source: the video file opened (its folder is ``folder``); None when a folder was opened.
        faults: what each frame of the built-in dataset shows, and its faults
            (:func:`blurcalib.sim.showcase.load_faults`; empty for other datasets).
    """

    folder: Path
    pattern_path: Path
    pattern: StarPattern
    frames: tuple[FrameFile, ...]
    truth: DatasetTruth | None
    warnings: tuple[str, ...] = ()
    source: Path | None = None
    faults: dict[str, FrameFaults] = field(default_factory=dict)


def find_pattern(folder: Path, pattern: str | os.PathLike | None) -> Path:
    """The pattern file: ``pattern`` when given, else ``pattern.yaml`` in ``folder`` or its parent."""
    if pattern is not None:
        return Path(pattern)
    for candidate in (folder / PATTERN_FILE, folder.parent / PATTERN_FILE):
        if candidate.is_file():
            return candidate
    raise DatasetError(f"{shown_path(folder)}: no {PATTERN_FILE} in the folder or its parent; name the "
                       f"pattern file")


def frame_files(folder: Path) -> list[Path]:
    """Image files of ``folder``, or, when it has none, of its sub-folders (in name order; the
    app's export folder :data:`EXPORT_DIR` is not a folder of frames)."""
    try:
        return list_frames([folder])
    except FrameError:
        subdirs = sorted(p for p in folder.iterdir()
                         if p.is_dir() and not p.name.startswith(".") and p.name != EXPORT_DIR)
        found = []
        for sub in subdirs:
            try:
                found.extend(list_frames([sub]))
            except FrameError:
                continue
        if not found:
            raise DatasetError(f"{shown_path(folder)}: no image files (png, jpg, tif, bmp) in the folder or "
                               "its sub-folders") from None
        return found


def _kind(name: str, truth: DatasetTruth | None) -> str:
    if truth is not None:
        for f in truth.frames:
            if f.name == name:
                return f.kind
    return "sharp" if "sharp" in (part.lower() for part in Path(name).parts[:-1]) else "blurry"


def _load_pattern(path: Path) -> StarPattern:
    """The pattern, or a :class:`DatasetError` that quotes nothing of the file (its path may have
    been typed by a client that cannot read the file: :attr:`PatternFileError.summary`)."""
    try:
        return load_pattern(path)
    except PatternFileError as exc:
        raise DatasetError(exc.summary.replace(str(path), shown_path(path))) from None


def discover(folder: str | os.PathLike, pattern: str | os.PathLike | None = None) -> Dataset:
    """Open ``folder`` (a folder of frames, or a video file) as a dataset.

    Raises:
        DatasetError: the folder or video is missing, cannot be read (a path too long, no
            permission), holds no frames, or the pattern is missing or malformed (the message
            names the path, shortened by :func:`shown_path`, and quotes nothing of the pattern
            file).
    """
    root = Path(folder).expanduser()
    try:
        return _discover(root, pattern)
    except OSError as exc:
        raise DatasetError(f"{shown_path(root)}: cannot open ({exc.strerror or type(exc).__name__})"
                           ) from None


def _discover(root: Path, pattern: str | os.PathLike | None) -> Dataset:
    """:func:`discover` of an expanded path; OSError passes through."""
    if root.is_file() and is_video(root):
        pattern_path = find_pattern(root.parent, pattern)
        star = _load_pattern(pattern_path)
        try:
            frames = frame_inputs([root])
        except FrameError as exc:
            raise DatasetError(str(exc)) from None
        return Dataset(root.parent, pattern_path, star,
                       tuple(FrameFile(f.name, f.path, "blurry", f.index) for f in frames), None, source=root)
    if not root.is_dir():
        raise DatasetError(f"{shown_path(root)}: no such folder or video" if not root.exists()
                           else f"{shown_path(root)}: neither a folder nor a video file (mp4, avi, mkv, mov)")
    pattern_path = find_pattern(root, pattern)
    star = _load_pattern(pattern_path)
    paths = frame_files(root)
    warnings: list[str] = []
    truth = None
    if (root / GROUND_TRUTH_FILE).is_file():
        try:
            truth = load_ground_truth(root)
        except ValueError as exc:
            warnings.append(str(exc))
    names = [p.relative_to(root).as_posix() for p in paths]
    if truth is not None:
        order = {f.name: i for i, f in enumerate(truth.frames)}
        ranked = sorted(range(len(names)), key=lambda i: (order.get(names[i], len(order)), i))
        names, paths = [names[i] for i in ranked], [paths[i] for i in ranked]
    frames = tuple(FrameFile(n, p, _kind(n, truth)) for n, p in zip(names, paths, strict=True))
    faults = {}
    if (root / FAULTS_FILE).is_file():
        try:
            faults = load_faults(root)
        except ValueError as exc:
            warnings.append(str(exc))
    return Dataset(root, pattern_path, star, frames, truth, tuple(warnings), faults=faults)


def default_camera() -> TrueCamera:
    """The built-in dataset's camera: the D435I-like camera at half resolution (640 x 360)."""
    return showcase_camera()


def user_cache() -> Path:
    """The user's cache folder: ``$XDG_CACHE_HOME``, or else ``~/.cache``."""
    cache = os.environ.get("XDG_CACHE_HOME", "").strip()
    return Path(cache) if cache and Path(cache).is_absolute() else Path.home() / ".cache"


def builtin_dataset_folder() -> Path:
    """Where the app keeps its built-in dataset: ``blurcalib/app_dataset`` in the user's cache
    folder (:func:`user_cache`; never inside the installed package)."""
    return user_cache() / BUILTIN_DIR


def default_output_folder(dataset: str | os.PathLike) -> Path:
    """Where the app writes a dataset's results when no output folder is given:
    ``blurcalib/results/<name>-<digest>`` in the user's cache folder (:func:`user_cache`), the
    digest the first 12 hex digits of the SHA-256 of the dataset's resolved path (a folder, or a
    video file), so that a read-only dataset can be extracted and each dataset has its own."""
    path = Path(dataset).expanduser().resolve()
    digest = hashlib.sha256(os.fsencode(path)).hexdigest()[:12]
    name = re.sub(r"[^A-Za-z0-9._-]", "_", path.name) or "root"
    return user_cache() / RESULTS_DIR / f"{name}-{digest}"


def default_dataset(root: str | os.PathLike, config: SynthConfig | None = None,
                    camera: TrueCamera | None = None,
                    progress: Callable[[int, int, str], None] | None = None, workers: int = 1) -> Path:
    """The simulated dataset in ``root``, rendered on first use (a complete one is reused).

    Args:
        root: its folder (:func:`builtin_dataset_folder` for the app).
        config: what to simulate; None: the built-in dataset (:mod:`blurcalib.sim.showcase`).
        camera: the camera of a ``config`` (default :func:`default_camera`).
        progress: called after each rendered frame with ``(done, total, name)``.
        workers: render in this many processes.
    """
    out = Path(root)
    if not (out / GROUND_TRUTH_FILE).is_file():
        if config is None:
            write_showcase(out, progress=progress, workers=workers)
        else:
            write_dataset(out, config, camera=camera or default_camera(), progress=progress, workers=workers)
    return out
