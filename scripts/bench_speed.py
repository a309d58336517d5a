"""Speed benchmark of feature extraction on close-up blurry frames.

    python scripts/bench_speed.py [--frames 4] [--threads 1] [--kind default] [--pair] [--device cpu]
    python scripts/bench_speed.py --frames 8 --compare REV [--rounds 3]

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
``--kind``: the extraction settings, ``default`` (the checkout's ``blurcalib extract`` default,
``auto`` where it has it), ``auto`` or ``blurry``.
``--compare REV`` runs the same frames (rendered once, by this checkout) through this checkout
and a copy of git revision ``REV`` (``git archive``) in turns, ``--rounds`` times, each in its own
process with ``--kind``, and prints the CPU seconds per frame of each (median over the rounds)
with the features each returned: two versions side by side on one machine, its load shared alike.
Targets: <= 2 s per frame, ratio <= 2.5, <= 1 GB per worker. The frames seeded and the features
returned of the visible blocks (the yield) are printed beside; the figures are also recorded as
JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import benchrecord
import numpy as np

KINDS = ("default", "auto", "blurry")


def save_frames(count: int, seed: int, folder: Path) -> Path:
    """Render ``count`` close-up frames with this checkout into ``folder/frames.npz`` (images,
    names, true time-averaged positions and visible blocks) beside ``pattern.yaml``."""
    from blurcalib.sim.synth import Simulator, SynthConfig

    sim = Simulator(SynthConfig(sharp=0, blurry=count, blur_min_px=4.0, blur_max_px=15.0,
                                square_px=(30.0, 47.0), noise_sigma=2.0, seed=seed))
    frames = [sim.frame(i) for i in range(count)]
    sim.pattern.save_yaml(folder / "pattern.yaml")
    path = folder / "frames.npz"
    np.savez(path, images=np.stack([f.image for f in frames]), names=np.array([f.truth.name for f in frames]),
             mean=np.stack([f.truth.mean for f in frames]),
             visible=np.stack([f.truth.block_inside for f in frames]))
    return path


def keep_freed_memory() -> None:
    """glibc keeps freed tensors' memory on its heap, as this version's command line and workers
    do (:func:`blurcalib.runs.runtime.keep_large_allocations`); set here for every checkout, older
    ones included, so that a comparison is of the extraction alone."""
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return
    for option, value in ((-3, 32 << 20), (-1, 1 << 30), (-4, 0)):  # mmap threshold, trim threshold, mmap max
        mallopt(option, value)


def _extraction(kind: str, device: str):
    """``(extract_frame, settings)`` of the checkout on the path (its layout as it was: the
    package of modules of later versions, or single modules)."""
    try:
        from blurcalib.deconv.settings import DeconvSettings
        from blurcalib.extract.frame import ExtractSettings, extract_frame
    except ImportError:  # an older checkout
        from blurcalib.deconv import DeconvSettings
        from blurcalib.extract import ExtractSettings, extract_frame
    has_auto = hasattr(ExtractSettings, "auto")
    if kind == "auto" and not has_auto:
        raise SystemExit("this checkout has no --kind auto")
    base = ExtractSettings.auto() if kind == "auto" or (kind == "default" and has_auto) else ExtractSettings()
    return extract_frame, replace_deconv(base, DeconvSettings(device=device))


def replace_deconv(settings, deconv):
    from dataclasses import replace

    return replace(settings, deconv=deconv)


def run(frames_file: Path, threads: int, device: str, quiet: bool, kind: str = "default") -> dict:
    """Extract the frames of ``frames_file`` (:func:`save_frames`); per-frame figures and totals."""
    import torch

    torch.set_num_threads(threads)  # (not blurcalib.runs.runtime: the script also times older checkouts)
    keep_freed_memory()
    try:
        from blurcalib.target.pattern import load_pattern
    except ImportError:  # an older checkout
        from blurcalib.pattern import load_pattern

    extract_frame, settings = _extraction(kind, device)
    data = np.load(frames_file)
    pattern = load_pattern(frames_file.parent / "pattern.yaml")
    rows = []
    for name, raw, mean, visible in zip(data["names"], data["images"], data["mean"], data["visible"],
                                        strict=True):
        name = str(name)
        image = raw.astype(np.float32)
        c0, w0 = time.process_time(), time.perf_counter()
        result = extract_frame(image, pattern, name, settings)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        err, far = np.nan, 0
        if len(result.features):
            xy = np.stack([result.features.x, result.features.y], axis=1)
            ids = result.features.feature_id
            d = xy - mean[ids]
            n = np.linalg.norm(d - np.median(d, axis=0), axis=1)
            err, far = float(np.median(n)), int(np.sum(n > 0.5))
        # an older checkout has no growth stages
        stages = result.stage_seconds() if hasattr(result, "stage_seconds") else result.seconds
        row = {"frame": name, "cpu": cpu, "wall": wall, "blocks": len(result.blocks),
               "features": len(result.features), "visible": int(visible.sum()), "median_px": err,
               "far": far, "stages": stages,
               **{k: result.seconds.get(k, 0.0) for k in ("seed", "fit", "align")}}
        rows.append(row)
        if not quiet:
            print(f"{name}: {row['blocks']:3d} blocks {row['features']:3d} features  "
                  f"median {err:.4f} px ({far} > 0.5 px)  cpu {cpu:5.2f} s  wall {wall:5.2f} s  "
                  f"(seed {row['seed']:.2f}, fit {row['fit']:.2f}, align {row['align']:.2f} s wall)",
                  flush=True)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"rows": rows, "peak_mb": peak}


def _child(frames_file: Path, threads: int, device: str, kind: str, checkout: Path | None = None
           ) -> subprocess.Popen:
    """This script on ``frames_file`` in its own process, with the package of ``checkout`` (this
    one by default) first on the path."""
    env = dict(os.environ)
    if checkout is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(checkout), env.get("PYTHONPATH", "")])
    return subprocess.Popen([sys.executable, __file__, "--frames-file", str(frames_file), "--threads",
                             str(threads), "--device", device, "--kind", kind, "--json"],
                            stdout=subprocess.PIPE, text=True, env=env, cwd=checkout)


def _rows(proc: subprocess.Popen) -> list[dict]:
    out, _ = proc.communicate()
    if proc.returncode:
        raise SystemExit(f"a benchmark process failed (exit status {proc.returncode})")
    return json.loads(out.strip().splitlines()[-1])["rows"]


def _wall(proc: subprocess.Popen) -> float:
    return sum(r["wall"] for r in _rows(proc) if r["blocks"])


def compare(frames_file: Path, rev: str, rounds: int, threads: int, device: str, kind: str,
            record: benchrecord.BenchRecord) -> None:
    """This checkout against a copy of git revision ``rev``, in turns (:data:`__doc__`)."""
    root = Path(__file__).resolve().parents[1]
    commit = subprocess.run(["git", "rev-parse", "--short", rev], cwd=root, capture_output=True, text=True,
                            check=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="bench-speed-rev-") as tmp:
        other = Path(tmp)
        archive = subprocess.run(["git", "archive", commit], cwd=root, capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(other)], input=archive, check=True)
        versions = {"this checkout": root, commit: other}
        cpu: dict[str, list[float]] = {v: [] for v in versions}
        wall: dict[str, list[float]] = {v: [] for v in versions}
        features: dict[str, int] = {}
        for r in range(rounds):
            for name, checkout in versions.items():
                rows = [x for x in _rows(_child(frames_file, threads, device, kind, checkout)) if x["blocks"]]
                cpu[name].append(sum(x["cpu"] for x in rows) / len(rows))
                wall[name].append(sum(x["wall"] for x in rows) / len(rows))
                features[name] = sum(x["features"] for x in rows)
                print(f"round {r + 1}: {name}: cpu {cpu[name][-1]:.2f} s, wall {wall[name][-1]:.2f} s per "
                      f"frame, {features[name]} features", flush=True)
    for name in versions:
        print(f"{name} (--kind {kind}): cpu {np.median(cpu[name]):.2f} s per frame (median of {rounds}; "
              f"{min(cpu[name]):.2f}-{max(cpu[name]):.2f}), wall {np.median(wall[name]):.2f} s, "
              f"{features[name]} features")
        section = f"{name} (--kind {kind})" if name == "this checkout" else f"revision {rev} (--kind {kind})"
        record.add(section,
                   cpu_s_per_frame=float(np.median(cpu[name])), cpu_min_s_per_frame=min(cpu[name]),
                   cpu_max_s_per_frame=max(cpu[name]), wall_s_per_frame=float(np.median(wall[name])),
                   features=features[name], rounds=rounds)
    ratio = float(np.median(cpu["this checkout"]) / np.median(cpu[commit]))
    print(f"this checkout / {rev}: {ratio:.3f} x the CPU per frame")
    record.add("comparison", cpu_ratio=ratio)


def report(res: dict, threads: int, record: benchrecord.BenchRecord) -> int:
    """Print and record one run's figures; returns the frames seeded."""
    rows = [r for r in res["rows"] if r["blocks"]]  # frames that were seeded
    n = len(rows)
    cpu = sum(r["cpu"] for r in rows) / n
    wall = sum(r["wall"] for r in rows) / n
    split = {k: sum(r[k] for r in rows) for k in ("seed", "fit", "align")}
    total = sum(split.values())
    blocks = np.mean([r["blocks"] for r in rows])
    print(f"per frame ({n} seeded frames, {threads} thread(s), {blocks:.0f} blocks): "
          f"cpu {cpu:.2f} s, wall {wall:.2f} s; seeding {100 * split['seed'] / total:.0f}%, "
          f"fitting {100 * split['fit'] / total:.0f}%, alignment {100 * split['align'] / total:.0f}%")
    names = list(dict.fromkeys(k for r in rows for k in r["stages"]))
    print("stages, mean s wall per frame: "
          + ", ".join(f"{k} {np.mean([r['stages'].get(k, 0.0) for r in rows]):.2f}" for k in names))
    returned = sum(r["features"] for r in rows) / max(sum(r["visible"] for r in rows), 1)
    median = np.nanmedian([r["median_px"] for r in rows])
    print(f"{n} of {len(res['rows'])} frames seeded, {100 * returned:.1f}% of their visible features "
          f"returned ({sum(r['features'] for r in rows)}); median star-centre error: {median:.4f} px "
          f"(median of the frames' medians), {sum(r['far'] for r in rows)} features off by > 0.5 px")
    print(f"peak memory: {res['peak_mb']:.0f} MB")
    record.add("close-up frames (blur 4-15 px)", frames=len(res["rows"]), frames_seeded=n,
               returned_pct=100 * returned, median_px=median, off_by_over_half_px=sum(r["far"] for r in rows),
               blocks_per_frame=blocks, threads=threads, cpu_s_per_frame=cpu, wall_s_per_frame=wall,
               peak_mb=res["peak_mb"])
    return n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4, help="simulated frames (seed 11: 3 of 4 seed)")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1: per-process figures)")
    parser.add_argument("--kind", choices=KINDS, default="default",
                        help="extraction settings (default: the checkout's extract default)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pair", action="store_true", help="also time two runs at once")
    parser.add_argument("--compare", metavar="REV", help="run a git revision's copy side by side")
    parser.add_argument("--rounds", type=int, default=3, help="turns of each version with --compare")
    parser.add_argument("--frames-file", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    benchrecord.add_option(parser)
    args = parser.parse_args()
    if args.json:
        print(json.dumps(run(args.frames_file, args.threads, args.device, quiet=True, kind=args.kind)))
        return
    record = benchrecord.start(__file__, args)
    with tempfile.TemporaryDirectory(prefix="bench-speed-") as tmp:
        frames_file = save_frames(args.frames, args.seed, Path(tmp))
        if args.compare:
            compare(frames_file, args.compare, args.rounds, args.threads, args.device, args.kind, record)
            record.write()
            return
        res = run(frames_file, args.threads, args.device, quiet=False, kind=args.kind)
        n = report(res, args.threads, record)
        if args.pair:
            single = _wall(_child(frames_file, args.threads, args.device, args.kind))
            procs = [_child(frames_file, args.threads, args.device, args.kind) for _ in range(2)]
            both = max(_wall(p) for p in procs)
            print(f"two runs at once: {both:.1f} s vs {single:.1f} s alone (ratio {both / single:.2f}); "
                  f"throughput with one process per core: {both / (2 * n):.2f} s wall per frame")
            record.add("two runs at once", ratio_to_one_run=both / single,
                       wall_s_per_frame_two_processes=both / (2 * n))
    record.write()


if __name__ == "__main__":
    main()
