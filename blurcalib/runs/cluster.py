"""Frames as tasks on a Dask distributed cluster (``pip install blurcalib[cluster]``).

:func:`run_on_cluster` sends one task per frame to a running Dask scheduler and yields the
results as they finish; the caller writes each one at once (so a run on a cluster is resumable
like a local one). Workers read the frames from the paths given, so they need the same file
system view as the client (a shared or network file system); each task computes with one
thread (:func:`blurcalib.runs.runtime.configure_threads`) and keeps large allocations on the heap
(:func:`blurcalib.runs.runtime.keep_large_allocations`). Setting up a cluster: ``docs/cluster.md``.
"""

from __future__ import annotations

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


def run_on_cluster(address: str, fn: Callable[..., R], tasks: Sequence[tuple],
                   shared: tuple = (), timeout_s: float = 30.0) -> Generator[tuple[int, R], None, None]:
    """Run ``fn(*task, *shared)`` for every task on the Dask scheduler at ``address``.

    Args:
        address: the scheduler, e.g. ``tcp://10.0.0.5:8786``.
        fn: a module-level (picklable) function.
        tasks: per-task leading arguments.
        shared: trailing arguments common to all tasks, sent to the workers once.
        timeout_s: how long to wait for the scheduler.
    Yields:
        ``(i, result)``: the index of the task in ``tasks`` and its result, in the order they
        finish.
    Raises:
        ClusterError: ``distributed`` is not installed, the address is malformed
            (:func:`check_address`) or the scheduler does not answer.
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
    with client:
        common = [client.scatter(arg, broadcast=True) for arg in shared]
        futures = {client.submit(_single_threaded, fn, *task, *common, pure=False): i
                   for i, task in enumerate(tasks)}
        for future in as_completed(list(futures), loop=client.loop):
            yield futures[future], future.result()
