"""Benchmark of extraction on a local Dask cluster against a local one-process run.

    python scripts/bench_cluster.py --sharp SHARP_DIR --blurry BLURRY_DIR --pattern target.yaml
        [--frames 8] [--workers 1 2] [--out /tmp/bench_cluster] [--no-local] [--dask-malloc]

The same frames (the first ``--frames`` of each folder, sharp ones with calibrate's sharp
settings, blurry ones with the default settings) are extracted by ``extract_to_folder`` in this
process (``--workers 1``) and then as tasks on a ``distributed.LocalCluster`` of N worker
processes with one thread each. Printed per run and kind: frames ok and features (the yield),
wall seconds per frame, the CPU seconds per frame of the computing processes (this process for
the local run; the workers, read with ``time.process_time`` before and after, for the cluster)
and of the client (scheduler, result transfer and writing). Then Dask's overhead per task: the
round trip of no-op tasks, and the idle worker time per frame task (wall x N - task durations,
from the scheduler's task stream). Wall times depend on the machine's load; CPU times much less.

The workers start with ``WORKER_MALLOC`` in their environment; ``--dask-malloc`` keeps Dask's
default ``MALLOC_TRIM_THRESHOLD_=65536`` instead. Either way every task sets glibc's thresholds
itself (:func:`blurcalib.runs.runtime.keep_large_allocations`, docs/cluster.md). The figures are
also recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import benchrecord

from blurcalib.extract.frame import ExtractSettings
from blurcalib.io.record import FrameRecord, FrameStatus
from blurcalib.runs.folder import extract_to_folder
from blurcalib.runs.runtime import configure_threads
from blurcalib.target.pattern import load_pattern

ROOT = Path(__file__).resolve().parents[1]
WORKER_MALLOC = {"MALLOC_MMAP_THRESHOLD_": 33554432, "MALLOC_TRIM_THRESHOLD_": 1073741824}
"""glibc settings of the worker processes (32 MiB, 1 GiB): large tensors stay on the heap."""


def _report(label: str, kind: str, rows: list[FrameRecord], wall: float, cpu: float, client_cpu: float,
            record: benchrecord.BenchRecord) -> None:
    n = len(rows)
    ok = sum(r.status is FrameStatus.OK for r in rows)
    features = sum(r.features for r in rows)
    print(f"{label:10s} {kind:6s} {ok:2d}/{n} ok {features:5d} features   wall {wall / n:6.2f} s/frame   "
          f"compute CPU {cpu / n:6.2f} s/frame   client CPU {client_cpu / n:5.2f} s/frame", flush=True)
    record.add(f"{label}, {kind} frames", frames=n, frames_ok=ok, features=features,
               wall_s_per_frame=wall / n, compute_cpu_s_per_frame=cpu / n,
               client_cpu_s_per_frame=client_cpu / n)


def _noop(i: int) -> int:
    return i


def _warm() -> str:
    """Import the extraction on a worker (torch included), so that no frame task pays for it;
    returns the worker's glibc settings."""
    import blurcalib.extract.frame  # noqa: F401

    return " ".join(f"{k}={os.environ.get(k)}" for k in WORKER_MALLOC)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sharp", type=Path, required=True)
    ap.add_argument("--blurry", type=Path, required=True)
    ap.add_argument("--pattern", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_cluster"))
    ap.add_argument("--no-local", dest="local", action="store_false", help="skip the local run")
    ap.add_argument("--dask-malloc", action="store_true", help="keep Dask's MALLOC_TRIM_THRESHOLD_")
    benchrecord.add_option(ap)
    args = ap.parse_args()
    record = benchrecord.start(__file__, args)
    import dask
    from distributed import Client, LocalCluster

    if not args.dask_malloc:
        dask.config.set({f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in WORKER_MALLOC.items()})

    configure_threads(1)
    pattern = load_pattern(args.pattern)
    runs = {"sharp": (sorted(args.sharp.glob("*.png"))[:args.frames], ExtractSettings.sharp()),
            "blurry": (sorted(args.blurry.glob("*.png"))[:args.frames], ExtractSettings())}
    print(f"{os.cpu_count()} cores, {args.frames} frames per kind, one thread per process")
    for kind, (paths, settings) in runs.items() if args.local else ():
        t0, c0 = time.perf_counter(), time.process_time()
        done = extract_to_folder(paths, pattern, args.out / "local" / kind, settings, overwrite=True)
        cpu = time.process_time() - c0
        _report("local 1", kind, done.records, time.perf_counter() - t0, cpu, 0.0, record)
    os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    for n in args.workers:
        t0 = time.perf_counter()
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None) as cl, \
                Client(cl.scheduler_address) as client:
            env = client.run(_warm)
            print(f"dask {n}: cluster start and worker imports {time.perf_counter() - t0:.1f} s, "
                  f"{next(iter(env.values()))}", flush=True)
            t0 = time.perf_counter()
            client.gather(client.map(_noop, range(500), pure=False))
            round_trip = (time.perf_counter() - t0) / 500 * 1e3
            print(f"dask {n}: no-op task round trip {round_trip:.1f} ms/task")
            record.add(f"dask {n}, overhead", noop_round_trip_ms_per_task=round_trip)
            for kind, (paths, settings) in runs.items():
                client.get_task_stream(start=time.time())
                before = client.run(time.process_time)
                t0, start, c0 = time.perf_counter(), time.time(), time.process_time()
                done = extract_to_folder(paths, pattern, args.out / f"dask{n}" / kind, settings,
                                         cluster=cl.scheduler_address, overwrite=True)
                wall, client_cpu = time.perf_counter() - t0, time.process_time() - c0
                after = client.run(time.process_time)
                cpu = sum(after[w] - before[w] for w in after)
                _report(f"dask {n}", kind, done.records, wall, cpu, client_cpu, record)
                tasks = [t for t in client.get_task_stream(start=start)
                         if "_single_threaded" in t["key"]]
                busy = sum(s["stop"] - s["start"] for t in tasks for s in t["startstops"]
                           if s["action"] == "compute")
                idle = (wall * n - busy) / max(len(tasks), 1)
                print(f"dask {n}: {kind:6s} {len(tasks)} tasks, idle worker time {idle:.2f} s/task",
                      flush=True)
                record.add(f"dask {n}, overhead", **{f"{kind}_idle_s_per_task": idle})
    record.write()


if __name__ == "__main__":
    main()
