"""Thread policy: how many threads each process computes with, and how many worker processes.

The block solver runs many small tensor operations; torch's intra-op (OpenMP) threads speed
these up little on an idle machine. By OpenMP's default a thread that waits at a barrier spins
on its core before it sleeps, and on shared cores the spinning threads take the core from the
threads they wait for: one real sharp frame on a busy 2-core machine took 4 to 8 times the CPU
and 5 to 7 times the wall time with 2 threads than with 1. So the package makes OpenMP threads
sleep while they wait (:func:`passive_openmp_wait`, set when ``blurcalib`` is imported, before
torch starts its threads): the same frame with 2 threads then takes the CPU time of 1 thread.
NumPy's and SciPy's OpenBLAS wait the same way in their own threads: one solve of the parametric
bundle adjustment (a 171-parameter Cholesky factor) took 0.17 s on a busy 2-core machine with
OpenBLAS's default two threads, 0.07 s with its threads sent to sleep at once and 0.016 s with one
thread, so NumPy computes with one thread too (:func:`quiet_openblas`).
Every process still computes with one thread by default and parallelism comes from worker
processes, one per core. The calibration
runs in one process once the frames are done, on large tensors: its torch computes with one
thread per worker, the cores the workers had (:func:`compute_threads`; the demo's features on 2
cores: calibration 15.8 -> 12.4 s, assessment 9.5 -> 8.3 s).
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

OMP_WAIT_POLICY = "OMP_WAIT_POLICY"
"""The OpenMP environment variable of the wait policy (``PASSIVE``: waiting threads sleep)."""

PARENT_POLL_S = 1.0
"""How often a worker process checks that the process that started it is still alive (s)."""


def passive_openmp_wait() -> bool:
    """Make OpenMP threads sleep, not spin, while they wait (``OMP_WAIT_POLICY=PASSIVE``) unless
    the environment already sets a policy; True when this call set it.

    OpenMP (torch's intra-op threads, libgomp) reads the variable once, when torch is imported,
    so this must run before that: ``blurcalib`` calls it when imported, and its worker processes
    inherit the environment. A process that imported torch before ``blurcalib`` keeps OpenMP's
    default (spinning) policy.
    """
    if os.environ.get(OMP_WAIT_POLICY):
        return False
    os.environ[OMP_WAIT_POLICY] = "PASSIVE"
    return True


OPENBLAS_POLICY = {"OPENBLAS_NUM_THREADS": "1", "OPENBLAS_THREAD_TIMEOUT": "4"}
"""OpenBLAS's environment variables and the values :func:`quiet_openblas` gives them: one thread,
and a thread that waits spins for ``2^4`` clock cycles before it sleeps (its default about
``2^28``), for a user who asks for more threads."""


def quiet_openblas() -> list[str]:
    """Make NumPy's and SciPy's OpenBLAS compute with one thread and let idle threads sleep at once
    (:data:`OPENBLAS_POLICY`), each variable unless the environment already sets it; returns the
    variables this call set.

    OpenBLAS reads them when NumPy (or SciPy, with its own OpenBLAS) is first imported, so this
    must run before that: ``blurcalib`` calls it when imported, before it imports NumPy, and its
    worker processes inherit the environment.
    """
    chosen = [name for name in OPENBLAS_POLICY if not os.environ.get(name)]
    for name in chosen:
        os.environ[name] = OPENBLAS_POLICY[name]
    return chosen


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS reports it)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return max(os.cpu_count() or 1, 1)


def default_workers(frames: int) -> int:
    """Worker processes for ``frames`` frames: one per core, at most one per frame."""
    return max(1, min(available_cores(), frames))


def configure_threads(threads: int | None = None) -> int:
    """Set the compute threads of this process (torch intra-op, OpenMP, OpenCV); returns them.

    Args:
        threads: threads to use; None or 0 means 1 (the policy above).
    Raises:
        ValueError: ``threads`` is negative.
    """
    if threads is not None and threads < 0:
        raise ValueError(f"threads must be >= 0, got {threads}")
    n = threads or 1
    os.environ["OMP_NUM_THREADS"] = str(n)  # for libraries that read it at their first use
    import cv2
    import torch

    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    return n


@contextmanager
def compute_threads(threads: int) -> Iterator[int]:
    """Compute with ``threads`` torch intra-op threads inside the block, and with this process's
    own again after it; yields the threads set. OpenCV keeps its threads: with more than one its
    calibration differs between runs in the last digits, torch's does not."""
    import torch

    before = torch.get_num_threads()
    n = max(int(threads), 1)
    torch.set_num_threads(n)
    try:
        yield n
    finally:
        torch.set_num_threads(before)


MMAP_THRESHOLD_BYTES = 32 << 20
"""Allocations below this stay on glibc's heap (:func:`keep_large_allocations`)."""
TRIM_THRESHOLD_BYTES = 1 << 30
"""Free heap memory glibc keeps before returning it to the system."""


def keep_large_allocations() -> bool:
    """Let glibc keep freed tensors' memory for the next ones in this process; True when set.

    ``mallopt(M_MMAP_THRESHOLD, 32 MiB)``, ``mallopt(M_TRIM_THRESHOLD, 1 GiB)`` and
    ``mallopt(M_MMAP_MAX, 0)``: every allocation comes from the heap, and freed memory stays
    there for the next one instead of being mapped afresh (and its pages faulted in, zeroed) each
    time. The block solver allocates and frees tensors of a few MiB thousands of times per frame;
    Dask's workers start with ``MALLOC_TRIM_THRESHOLD_=65536``, which turns off glibc's adaptive
    mmap threshold, so each such tensor is mapped and unmapped again (measured: twice the CPU per
    blurry frame, mostly system time; ``docs/cluster.md``). The bundle adjustment and its
    assessment allocate ``(G, G)`` matrices of tens of MB, above the largest mmap threshold glibc
    accepts (32 MiB), hence no mapping at all (measured on the demo: the assessment 11.5 s
    instead of 15.4 s, the calibration 21.2 s instead of 24.4 s). False where the C library is
    not glibc (nothing changed).
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold, m_mmap_max = -1, -3, -4  # glibc's malloc.h
    return (bool(mallopt(m_mmap_threshold, MMAP_THRESHOLD_BYTES))
            and bool(mallopt(m_trim_threshold, TRIM_THRESHOLD_BYTES)) and bool(mallopt(m_mmap_max, 0)))


def capped_count(value: int, what: str) -> tuple[int, str | None]:
    """``value`` threads or processes capped at :func:`available_cores`, and the one-line note
    to print when it was capped (None otherwise): more than one per core only competes for the
    cores (``--threads 1000`` started 3,002 threads and made one frame 90 times slower)."""
    cores = available_cores()
    if value <= cores:
        return value, None
    return cores, f"{what} {value} is more than the {cores} cores available: using {cores}"


def exit_with_parent(poll_s: float = PARENT_POLL_S) -> None:
    """Make this worker process exit when the process that started it dies (a ``kill -9`` of
    the parent would otherwise leave it blocked forever, holding its memory).

    A daemon thread checks the parent every ``poll_s`` seconds and ends the process with
    ``os._exit`` once the parent is gone (the worker was re-parented). Call it from a worker
    pool's initialiser; in a process that no ``multiprocessing`` parent started it does nothing.
    """
    parent = multiprocessing.parent_process()
    if parent is None:
        return
    pid = parent.pid

    def watch() -> None:
        while True:
            if os.getppid() != pid:
                os._exit(1)
            time.sleep(poll_s)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


class DeviceError(ValueError):
    """The requested torch device is not available (a one-line message)."""


def check_device(device: str) -> str:
    """``device`` if torch can compute on it, else :class:`DeviceError`: the one device check
    of the command line, the experiments and the engine's callers."""
    import torch

    try:
        dev = torch.device(device)
    except RuntimeError:
        raise DeviceError(f"--device {device!r}: not a torch device (use cpu, cuda or cuda:N)") from None
    if dev.type not in ("cpu", "cuda"):
        raise DeviceError(f"--device {device!r}: unsupported device type {dev.type!r} (use cpu or cuda)")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DeviceError(f"--device {device!r}: CUDA is not available on this machine (torch "
                          f"{torch.__version__}); use --device cpu")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise DeviceError(f"--device {device!r}: only {torch.cuda.device_count()} CUDA device(s)")
    return device
