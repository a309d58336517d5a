"""Speed benchmark of feature extraction on close-up blurry frames.

    python scripts/bench_speed.py [--frames 4] [--threads 1] [--pair] [--device cpu]

Simulated 1280x720 frames (blurcalib/sim/synth.py) with star squares of 30 to 47 px and blur of 4 to
15 px, about 250 blocks each. Per frame: process CPU time (the primary figure on a shared
machine) and wall time, split into seeding, fitting (region growing with the block solver) and
alignment, and the mean wall time of each stage with the growth's split out
(:meth:`blurcalib.extract.frame.FrameResult.stage_seconds`: free PSFs, path-PSF field, final
fit, second judgement); the block count and the median star-centre error against the ground-truth
time-averaged positions (each frame's median offset removed) and the features off by > 0.5 px;
at the end the peak resident memory (``getrusage`` maxrss). ``--pair`` then runs the same
frames in two processes at once and prints the ratio of their wall time to a single run's, and
the throughput of the two (wall seconds per frame with one process per core, as ``blurcalib
extract`` runs a folder on a 2-core machine).
Targets: <= 2 s per frame, ratio <= 2.5, <= 1 GB per worker. The frames seeded and the features
returned of the visible blocks (the yield) are printed beside; the figures are also recorded as
JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import benchrecord
import numpy as np


def _frames(count: int, seed: int) -> list:
    from blurcalib.sim.synth import Simulator, SynthConfig

    sim = Simulator(SynthConfig(sharp=0, blurry=count, blur_min_px=4.0, blur_max_px=15.0,
                                square_px=(30.0, 47.0), noise_sigma=2.0, seed=seed))
    return [sim.frame(i) for i in range(count)], sim.pattern


def run(frames: int, seed: int, threads: int, device: str, quiet: bool) -> dict:
    """Extract ``frames`` simulated frames; per-frame figures and totals."""
    import torch

    torch.set_num_threads(threads)  # (not blurcalib.runs.runtime: the script also times older checkouts)
    try:  # glibc keeps freed tensors' memory, as the command line and its workers do
        from blurcalib.runs.runtime import keep_large_allocations
        keep_large_allocations()
    except ImportError:  # an older checkout
        pass
    from blurcalib.deconv.settings import DeconvSettings
    from blurcalib.extract.frame import ExtractSettings, extract_frame

    sims, pattern = _frames(frames, seed)
    settings = ExtractSettings(deconv=DeconvSettings(device=device))
    rows = []
    for frame in sims:
        t = frame.truth
        image = frame.image.astype(np.float32)
        c0, w0 = time.process_time(), time.perf_counter()
        result = extract_frame(image, pattern, t.name, settings)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        err, far = np.nan, 0
        if len(result.features):
            xy = np.stack([result.features.x, result.features.y], axis=1)
            ids = result.features.feature_id
            d = xy - t.mean[ids]
            n = np.linalg.norm(d - np.median(d, axis=0), axis=1)
            err, far = float(np.median(n)), int(np.sum(n > 0.5))
        # an older checkout has no growth stages
        stages = result.stage_seconds() if hasattr(result, "stage_seconds") else result.seconds
        row = {"frame": t.name, "cpu": cpu, "wall": wall, "blocks": len(result.blocks),
               "features": len(result.features), "visible": int(t.block_inside.sum()), "median_px": err,
               "far": far, "stages": stages,
               **{k: result.seconds.get(k, 0.0) for k in ("seed", "fit", "align")}}
        rows.append(row)
        if not quiet:
            print(f"{t.name}: {row['blocks']:3d} blocks {row['features']:3d} features  "
                  f"median {err:.4f} px ({far} > 0.5 px)  cpu {cpu:5.2f} s  wall {wall:5.2f} s  "
                  f"(seed {row['seed']:.2f}, fit {row['fit']:.2f}, align {row['align']:.2f} s wall)",
                  flush=True)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"rows": rows, "peak_mb": peak}


def _child(frames: int, seed: int, threads: int, device: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, __file__, "--frames", str(frames), "--seed", str(seed),
                             "--threads", str(threads), "--device", device, "--json"],
                            stdout=subprocess.PIPE, text=True)


def _wall(proc: subprocess.Popen) -> float:
    out, _ = proc.communicate()
    rows = json.loads(out.strip().splitlines()[-1])["rows"]
    return sum(r["wall"] for r in rows if r["blocks"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4, help="simulated frames (seed 11: 3 of 4 seed)")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1: per-process figures)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pair", action="store_true", help="also time two runs at once")
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = None if args.json else benchrecord.start(__file__, args)
    res = run(args.frames, args.seed, args.threads, args.device, quiet=args.json)
    if record is None:
        print(json.dumps(res))
        return
    rows = [r for r in res["rows"] if r["blocks"]]  # frames that were seeded
    n = len(rows)
    cpu = sum(r["cpu"] for r in rows) / n
    wall = sum(r["wall"] for r in rows) / n
    split = {k: sum(r[k] for r in rows) for k in ("seed", "fit", "align")}
    total = sum(split.values())
    blocks = np.mean([r["blocks"] for r in rows])
    print(f"per frame ({n} seeded frames, {args.threads} thread(s), {blocks:.0f} blocks): "
          f"cpu {cpu:.2f} s, wall {wall:.2f} s; seeding {100 * split['seed'] / total:.0f}%, "
          f"fitting {100 * split['fit'] / total:.0f}%, alignment {100 * split['align'] / total:.0f}%")
    names = list(dict.fromkeys(k for r in rows for k in r["stages"]))
    print("stages, mean s wall per frame: "
          + ", ".join(f"{k} {np.mean([r['stages'].get(k, 0.0) for r in rows]):.2f}" for k in names))
    returned = sum(r["features"] for r in rows) / max(sum(r["visible"] for r in rows), 1)
    median = np.nanmedian([r["median_px"] for r in rows])
    print(f"{n} of {len(res['rows'])} frames seeded, {100 * returned:.1f}% of their visible features "
          f"returned; median star-centre error: {median:.4f} px (median of the frames' medians), "
          f"{sum(r['far'] for r in rows)} features off by > 0.5 px")
    print(f"peak memory: {res['peak_mb']:.0f} MB")
    record.add("close-up frames (blur 4-15 px)", frames=len(res["rows"]), frames_seeded=n,
               returned_pct=100 * returned, median_px=median, off_by_over_half_px=sum(r["far"] for r in rows),
               blocks_per_frame=blocks, threads=args.threads, cpu_s_per_frame=cpu, wall_s_per_frame=wall,
               peak_mb=res["peak_mb"])
    if args.pair:
        single = _wall(_child(args.frames, args.seed, args.threads, args.device))
        procs = [_child(args.frames, args.seed, args.threads, args.device) for _ in range(2)]
        both = max(_wall(p) for p in procs)
        print(f"two runs at once: {both:.1f} s vs {single:.1f} s alone (ratio {both / single:.2f}); "
              f"throughput with one process per core: {both / (2 * n):.2f} s wall per frame")
        record.add("two runs at once", ratio_to_one_run=both / single,
                   wall_s_per_frame_two_processes=both / (2 * n))
    record.write()


if __name__ == "__main__":
    main()
