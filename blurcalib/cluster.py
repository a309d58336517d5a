"""Frames as tasks on a Dask distributed cluster (``pip install blurcalib[cluster]``).

:func:`run_on_cluster` sends one task per frame to a running Dask scheduler and yields the
results as they finish; the caller writes each one at once (so a run on a cluster is resumable
like a local one). Workers read the frames from the paths given, so they need the same file
system view as the client (a shared or network file system); each task computes with one
thread (:func:`blurcalib.runtime.configure_threads`). Setting up a cluster: ``docs/cluster.md``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

from blurcalib.runtime import configure_threads

R = TypeVar("R")


class ClusterError(Exception):
    """Dask is missing or the scheduler cannot be reached (a one-line message)."""


def _single_threaded(fn: Callable[..., R], *args: Any) -> R:
    configure_threads(1)
    return fn(*args)


def run_on_cluster(address: str, fn: Callable[..., R], tasks: Sequence[tuple],
                   shared: tuple = (), timeout_s: float = 30.0) -> Iterator[R]:
    """Run ``fn(*task, *shared)`` for every task on the Dask scheduler at ``address``.

    Args:
        address: the scheduler, e.g. ``tcp://10.0.0.5:8786``.
        fn: a module-level (picklable) function.
        tasks: per-task leading arguments.
        shared: trailing arguments common to all tasks, sent to the workers once.
        timeout_s: how long to wait for the scheduler.
    Yields:
        The results in the order they finish.
    Raises:
        ClusterError: ``distributed`` is not installed or the scheduler does not answer.
    """
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ClusterError("--cluster needs Dask: pip install 'blurcalib[cluster]'") from None
    try:
        client = Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ClusterError(f"{address}: cannot reach the Dask scheduler ({exc})") from None
    with client:
        common = [client.scatter(arg, broadcast=True) for arg in shared]
        futures = [client.submit(_single_threaded, fn, *task, *common, pure=False) for task in tasks]
        for future in as_completed(futures, loop=client.loop):
            yield future.result()
