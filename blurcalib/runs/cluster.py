"""Frames as tasks on a Dask distributed cluster (``pip install blurcalib[cluster]``).

:func:`run_on_cluster` sends one task per frame to a running Dask scheduler and yields the
results as they finish; the caller writes each one at once (so a run on a cluster is resumable
like a local one). Workers read the frames from the paths given, so they need the same file
system view as the client (a shared or network file system); each task computes with one
thread (:func:`blurcalib.runs.runtime.configure_threads`) and keeps large allocations on the heap
(:func:`blurcalib.runs.runtime.keep_large_allocations`). Setting up a cluster: ``docs/cluster.md``.

A worker lost mid-run (killed, or restarted by its nanny) costs nothing but time: the scheduler
runs its tasks again on the workers left or on the restarted one, and the arguments common to all
tasks are tasks too (not scattered data, which a lost worker takes with it). A task whose workers
keep dying (Dask's ``allowed-failures``), or a scheduler lost, ends the run with
:class:`ClusterError` in one line, once every other task has finished or been lost: what finished
was yielded, and so written, before.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Generator, Sequence
from typing import Any, TypeVar
from urllib.parse import urlsplit

from blurcalib.runs.runtime import configure_threads, keep_large_allocations

R = TypeVar("R")


SCHEMES = ("tcp", "tls")
"""Dask scheduler address schemes accepted by :func:`check_address`."""


class ClusterError(Exception):
    """Dask is missing, the scheduler address is malformed or the scheduler cannot be reached
    (a one-line message)."""


def check_address(address: str) -> str:
    """``address`` if it is a scheduler address ``tcp://HOST:PORT`` (or ``tls://``, or
    ``HOST:PORT``, which Dask reads as ``tcp://``), checked before anything is connected or
    written.

    Raises:
        ClusterError: a malformed address, naming it.
    """
    full = address if "://" in address else f"tcp://{address}"
    problem = None
    try:
        parts = urlsplit(full)
        port = parts.port
    except ValueError:
        parts, port = None, None
        problem = "the port must be a number from 1 to 65535"
    if parts is not None:
        if parts.scheme not in SCHEMES:
            problem = f"unsupported scheme {parts.scheme!r} (use {' or '.join(SCHEMES)})"
        elif not parts.hostname:
            problem = "no host"
        elif port is None or not 1 <= port <= 65535:
            problem = "no port (the scheduler's port, 8786 by default)"
        elif parts.path not in ("", "/") or parts.query or parts.fragment or parts.username:
            problem = "extra parts after HOST:PORT"
    if problem is not None:
        raise ClusterError(f"--cluster {address!r}: not a scheduler address, {problem}; expected "
                           f"tcp://HOST:PORT, e.g. tcp://10.0.0.5:8786")
    return address


def _single_threaded(fn: Callable[..., R], *args: Any) -> R:
    """``fn(*args)`` with one compute thread and glibc keeping large allocations
    (:func:`blurcalib.runs.runtime.keep_large_allocations`), whatever the worker's environment."""
    configure_threads(1)
    keep_large_allocations()
    return fn(*args)


class _OneLineLogs(logging.Filter):
    """Dask's client logs, while it tries to reach a lost scheduler, each failed attempt with its
    traceback: keep each record's one line, drop its traceback, and drop records with no line."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.exc_info, record.exc_text = None, None
        return bool(record.getMessage().strip())


def _value(value: R) -> R:
    """``value`` itself: a task whose result a worker holds, computed again if that worker is lost."""
    return value


def run_on_cluster(address: str, fn: Callable[..., R], tasks: Sequence[tuple[Any, ...]],
                   shared: tuple[Any, ...] = (), timeout_s: float = 30.0,
                   names: Sequence[str] | None = None) -> Generator[tuple[int, R], None, None]:
    """Run ``fn(*task, *shared)`` for every task on the Dask scheduler at ``address``.

    Args:
        address: the scheduler, e.g. ``tcp://10.0.0.5:8786``.
        fn: a module-level (picklable) function.
        tasks: per-task leading arguments.
        shared: trailing arguments common to all tasks, sent to the workers once (as tasks, so
            that a worker lost with them costs nothing but their recomputation).
        timeout_s: how long to wait for the scheduler.
        names: what each task is, for the messages (a frame's name); ``task I`` without.
    Yields:
        ``(i, result)``: the index of the task in ``tasks`` and its result, in the order they
        finish.
    Raises:
        ClusterError: ``distributed`` is not installed, the address is malformed
            (:func:`check_address`), the scheduler does not answer, or tasks were lost (their
            workers kept dying, or the scheduler was lost), raised after the other tasks'
            results, naming the lost ones and how many finished.
    """
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ClusterError("--cluster needs Dask: pip install 'blurcalib[cluster]'") from None
    check_address(address)
    try:
        client = Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise ClusterError(f"{address}: cannot reach the Dask scheduler ({exc})") from None
    lost: dict[int, str] = {}
    quiet = _OneLineLogs()
    client_log = logging.getLogger("distributed.client")
    with contextlib.ExitStack() as stack:
        client_log.addFilter(quiet)
        stack.callback(client_log.removeFilter, quiet)
        stack.enter_context(client)
        common = [client.submit(_value, arg, pure=False) for arg in shared]
        futures = {client.submit(_single_threaded, fn, *task, *common, pure=False): i
                   for i, task in enumerate(tasks)}
        for future in as_completed(list(futures), loop=client.loop):
            i = futures[future]
            try:
                result = future.result()
            except Exception as exc:
                why = _lost(exc)
                if why is None:
                    raise
                lost[i] = why
                continue
            yield i, result
    if lost:
        raise ClusterError(_lost_message(address, lost, len(tasks), names))


def _lost(exc: BaseException) -> str | None:
    """Why a task was lost to the cluster (``exc`` its future's error), or None for an error of
    the task itself."""
    from concurrent.futures import CancelledError

    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    if isinstance(exc, KilledWorker):
        return "its workers kept dying while running it (out of memory?)"
    if isinstance(exc, CancelledError):
        return "the scheduler dropped it (lost, or restarted)"
    if isinstance(exc, CommClosedError):
        return "the connection to the scheduler was lost"
    return None


def _lost_message(address: str, lost: dict[int, str], total: int, names: Sequence[str] | None) -> str:
    """One line: the tasks lost, why (the first one's reason), and that the others were kept."""
    label = [names[i] if names is not None else f"task {i}" for i in sorted(lost)]
    more = f" and {len(label) - 5} more" if len(label) > 5 else ""
    first = lost[min(lost)]
    return (f"{address}: {len(lost)} of {total} tasks did not finish on the Dask cluster "
            f"({', '.join(label[:5])}{more}: {first}); the {total - len(lost)} finished are kept; "
            f"run again to resume")
