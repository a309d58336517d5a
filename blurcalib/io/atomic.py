"""Atomic file writes: every file blurcalib writes appears whole or not at all.

A write goes to a temporary file in the destination folder, is flushed to disk and is then
renamed over the destination with ``os.replace`` (atomic on POSIX and Windows). An interrupted
run therefore never leaves a truncated table, image or YAML behind; a run killed mid-write
leaves at most a hidden temporary file, which :func:`remove_temporaries` clears on the next run.

An output folder belongs to a run: :func:`claim_output_dir` refuses a non-empty folder that
does not hold a blurcalib output of the same kind (the run manifest ``blurcalib-run.json`` names
the command and the settings of the outputs the folder holds: written when a run takes a new
folder, and again by :func:`write_run_manifest` when a run publishes its outputs) unless asked to
overwrite. :func:`output_lock` keeps a second run from writing into a folder, or into a folder
inside it or around it, while a first one does.

A write that fails for want of space, quota or permission raises :class:`OutputError` naming the
file (``No space left on device``); the destination keeps its earlier content.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

from blurcalib.io.csv_reader import csv_chunks

RUN_MANIFEST = "blurcalib-run.json"
"""The run manifest: ``{"tool": "blurcalib", "command": ..., "settings": {...}}``."""

_TEMPORARY = re.compile(r"\..*\.[a-z0-9_]{8}\.tmp(\.[^.]*)?")
"""Names of :func:`atomic_path`'s temporary files: ``.<stem>.<8 random chars>.tmp<suffix>``."""


_STORAGE_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM,
                             errno.EFBIG, errno.EIO})
"""``errno`` values of a write that fails for want of space, quota or permission: reported as
:class:`OutputError` (one line naming the file), not as a traceback."""

class OutputError(OSError):
    """An output file or folder cannot be written; the message names the path."""


def storage_error(exc: OSError) -> OutputError | None:
    """``exc`` as a one-line :class:`OutputError` naming its file when it is a write that failed
    for want of space, quota or permission (``No space left on device``); None otherwise."""
    if isinstance(exc, OutputError):
        return exc
    if exc.errno not in _STORAGE_ERRORS:
        return None
    where = f"{os.fsdecode(exc.filename)}: " if exc.filename is not None else ""
    return OutputError(f"{where}cannot write ({exc.strerror or exc})")


@contextlib.contextmanager
def output_lock(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Hold the output folder ``path`` for one run: a second run that asks for it, for a folder
    inside it (``calibrate``'s ``OUT/frames``, ``OUT/sharp``, ``OUT/blurry``) or for a folder around
    it while this one holds it is refused with :class:`OutputError`.

    The lock is an advisory ``flock`` on the folder itself, exclusive, and a shared one on each
    folder above it that can be opened (no file is added to any of them), released when the block
    ends or the process dies: an exclusive lock waits for no shared one and the other way round.
    The folder is created if missing and removed again when the run leaves it empty (a run refused
    before it wrote anything). Where ``fcntl`` is missing (Windows) no lock is taken.

    Raises:
        OutputError: another run holds the folder, one inside it or one around it, or the folder
            cannot be created.
    """
    folder = Path(path)
    created = not folder.exists()
    if folder.exists() and not folder.is_dir():
        yield folder  # the claim names the problem
        return
    ensure_writable_dir(folder)
    try:
        import fcntl
    except ImportError:  # no advisory locks: run unlocked
        yield folder
        return
    with contextlib.ExitStack() as held:
        if created:  # removed last, also when the lock is refused
            held.callback(_remove_if_empty, folder)
        busy = "another blurcalib run is writing into this folder or into one inside it"
        _flock(held, fcntl, folder, fcntl.LOCK_EX, f"{folder}: {busy}")
        for above in folder.resolve().parents:
            _flock(held, fcntl, above, fcntl.LOCK_SH, f"{folder}: it is inside {above}, the output folder "
                                                     f"of another blurcalib run under way", missing_ok=True)
        yield folder


def _remove_if_empty(folder: Path) -> None:
    """Remove ``folder`` when it is empty (a folder made for a run that wrote nothing into it)."""
    with contextlib.suppress(OSError):
        folder.rmdir()


def _flock(held: contextlib.ExitStack, fcntl: ModuleType, folder: Path, mode: int, busy: str,
           missing_ok: bool = False) -> None:
    """Take the advisory lock ``mode`` on ``folder`` without waiting, released when ``held``
    closes; a folder that cannot be opened is skipped when ``missing_ok``.

    Raises:
        OutputError: another process holds a conflicting lock (message ``busy``: wait for that
            run to end or choose another output folder).
    """
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        if missing_ok:
            return
        raise
    held.callback(os.close, fd)
    try:
        fcntl.flock(fd, mode | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise
        raise OutputError(f"{busy}; wait for it to end or choose another output folder") from None


def _strict(value: object) -> object:
    """``value`` with every non-finite float replaced by None (JSON ``null``)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict(v) for v in value]
    return value


def strict_json(doc: object, **kwargs: Any) -> str:
    """``doc`` as strict JSON (RFC 8259): NaN and infinities become ``null``; ``kwargs`` go to
    ``json.dumps`` (``indent``, ``default``, ``sort_keys``)."""
    return json.dumps(_strict(doc), allow_nan=False, **kwargs)


def atomic_write_json(path: str | os.PathLike[str], doc: object, **kwargs: object) -> Path:
    """Write ``doc`` as strict JSON (:func:`strict_json`, a trailing newline) atomically."""
    return atomic_write_text(path, strict_json(doc, **kwargs) + "\n")


def ensure_writable_dir(path: str | os.PathLike[str]) -> Path:
    """Create ``path`` (and parents) if needed and check that files can be written in it.

    Raises:
        OutputError: naming the folder, when it cannot be created or written.
    """
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot create output folder ({exc.strerror or exc})") from exc
    if not folder.is_dir():
        raise OutputError(f"{folder}: output path exists and is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{folder}: output folder is not writable")
    return folder


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it is renamed onto ``path``.

    The caller writes the whole file to the yielded path (with any library: cv2, numpy,
    matplotlib). If the block raises, the temporary file is removed and ``path`` is untouched.
    The temporary name keeps the destination's suffix so that libraries choosing a format by
    extension (cv2.imwrite, matplotlib) still work. An overwritten file keeps its permission
    bits; a new one gets ``0o666`` less the process umask, as ``open`` would give it.
    """
    dest = Path(path)
    if dest.exists():
        mode = stat.S_IMODE(dest.stat().st_mode)
    else:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    folder = dest.parent if str(dest.parent) else Path(".")
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.stem}.", suffix=f".tmp{dest.suffix}",
                                        dir=folder)
    except OSError as exc:
        raise OutputError(f"{dest}: cannot write ({exc.strerror or exc})") from exc
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, dest)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError) and not isinstance(exc, OutputError) and exc.errno in _STORAGE_ERRORS:
            raise OutputError(f"{dest}: cannot write ({exc.strerror or exc})") from exc
        raise


def remove_temporaries(folder: str | os.PathLike[str]) -> list[Path]:
    """Delete the temporary files that :func:`atomic_path` left in ``folder`` when a run was
    killed mid-write (not recursive); return their paths."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    stray = sorted(p for p in folder.iterdir() if _TEMPORARY.fullmatch(p.name) and p.is_file())
    for path in stray:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
    return stray


def run_manifest(folder: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The run manifest of ``folder``, or None when it has none (or an unreadable one)."""
    try:
        doc = json.loads((Path(folder) / RUN_MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) and doc.get("tool") == "blurcalib" else None


def _command(folder: Path) -> str | None:
    """The command of the blurcalib output in ``folder`` (None when it holds none)."""
    manifest = run_manifest(folder)
    return None if manifest is None else manifest.get("command")


def output_dir_problem(path: str | os.PathLike[str], command: str,
                       extractions: Sequence[str] = ()) -> str | None:
    """Why :func:`claim_output_dir` would refuse ``path`` as the output folder of a ``command``
    run without ``overwrite`` (a message naming the folder), or None when it would take it;
    nothing is written."""
    folder = Path(path)
    if not folder.is_dir() or not any(folder.iterdir()):
        return None
    manifest = run_manifest(folder)
    if manifest is None and not all(p.name in extractions and _command(p) == "extract"
                                    for p in folder.iterdir()):
        return f"{folder}: output folder is not empty and is not a blurcalib output (no {RUN_MANIFEST})"
    if manifest is not None and manifest.get("command") != command:
        return (f"{folder}: output folder holds a blurcalib {manifest.get('command')!r} output, "
                f"not {command!r}")
    return None


def claim_output_dir(path: str | os.PathLike[str], command: str, settings: dict[str, Any],
                     overwrite: bool = False, extractions: Sequence[str] = ()) -> Path:
    """Make ``path`` the output folder of a ``command`` run.

    An empty or missing folder, one whose manifest names the same command (a re-run or
    resume), or one that holds nothing but ``extract`` outputs in the subfolders named by
    ``extractions`` (``calibrate``'s ``sharp`` and ``blurry``, made by earlier ``blurcalib
    extract`` runs) is taken; any other non-empty folder is refused unless ``overwrite``, so
    that files that are not ours are never replaced. A folder with a sub-folder that cannot be
    written is refused before the manifest is touched. The folder's stray temporary files are
    removed. A folder without a manifest of ``command`` gets one naming ``settings``; a folder
    with one keeps it, naming the settings of the outputs it holds, until the run publishes its
    own (:func:`write_run_manifest`), so that a run that fails (a full disk) leaves the manifest
    describing the outputs it leaves.

    Args:
        path: the output folder.
        command: the kind of output (``"extract"``, ``"calibrate"``).
        settings: JSON-serialisable settings of the run, recorded in the manifest.
        overwrite: write into a non-empty folder that is not an output of ``command``.
        extractions: subfolders that are ``extract`` outputs of their own.
    Raises:
        OutputError: the folder holds something else, or cannot be created or written.
    """
    folder = Path(path)
    problem = None if overwrite else output_dir_problem(folder, command, extractions)
    if problem is not None:
        raise OutputError(f"{problem}; use --overwrite to write into it")
    ensure_writable_dir(folder)
    _check_writable_tree(folder)
    remove_temporaries(folder)
    if _command(folder) != command:
        write_run_manifest(folder, command, settings)
    return folder


def write_run_manifest(folder: str | os.PathLike[str], command: str, settings: dict[str, Any]) -> Path:
    """Write ``folder``'s run manifest (atomically): a ``command`` output made with ``settings``
    (JSON-serialisable). A run calls it when it publishes its outputs, before the first of them
    replaces an earlier run's."""
    return atomic_write_text(Path(folder) / RUN_MANIFEST, json.dumps(
        {"tool": "blurcalib", "command": command, "settings": settings}, indent=2, sort_keys=True) + "\n")


def _check_writable_tree(folder: Path) -> None:
    """Refuse an output folder with a sub-folder the run could not write into, before the run
    manifest is rewritten (so the manifest never names settings its tables were not made with)."""
    for root, dirs, _ in os.walk(folder):
        for name in dirs:
            sub = Path(root) / name
            if not os.access(sub, os.W_OK | os.X_OK):
                raise OutputError(f"{sub}: output folder is not writable")


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_csv(path: str | os.PathLike[str], header: Sequence[str],
                     rows: Iterable[Sequence[object]]) -> Path:
    """Write a CSV table (``header`` then ``rows``, quoted as the ``csv`` module does) atomically."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return atomic_write_text(path, buffer.getvalue())


def read_csv_columns(path: Path, required: Sequence[str], error: type[Exception], what: str,
                     optional: Sequence[str] = ()) -> tuple[dict[str, list[str]], int]:
    """The ``required`` columns of a CSV with a header, and those of ``optional`` it has, as
    lists of strings, and its row count (the whole file: :func:`blurcalib.io.csv_reader.csv_chunks`
    reads it in chunks).

    Args:
        path: the file.
        required: column names that must be in the header (others are ignored).
        optional: column names read when the header has them (columns added to a format later).
        error: the exception raised for a missing, unreadable or malformed file; its message
            starts with the path.
        what: what the file is, for the messages (``"results file"``, ``"calibration file"``).
    """
    columns: dict[str, list[str]] = {}
    for _, chunk in csv_chunks(path, required, error, what, optional):
        for name, values in chunk.items():
            columns.setdefault(name, []).extend(values)
    return columns, len(columns[required[0]]) if required else 0
