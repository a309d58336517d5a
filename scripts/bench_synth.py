"""Benchmark of the simulator: time and peak memory to render 1280x720 frames.

    python scripts/bench_synth.py [--frames N]

Prints the time of every sharp and blurry frame of the default dataset (after the one-time
set-up of the lens map and textures) and the median, with the frames rendered and their visible
features (the yield); the target is 5 s or less per blurry frame on a 2-core machine. The figures
are also recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import resource
import time

import benchrecord
import numpy as np

from blurcalib.sim.synth import Simulator, SynthConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=8, help="blurry frames to time")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    config = SynthConfig(sharp=2, blurry=args.frames)
    start = time.perf_counter()
    sim = Simulator(config)
    sim.frame(0)
    setup = time.perf_counter() - start
    print(f"set-up (lens map, textures, first frame): {setup:.2f} s")
    record.add("set-up", wall_s=setup)
    times: dict[str, list[float]] = {"sharp": [], "blurry": []}
    cpus: dict[str, list[float]] = {"sharp": [], "blurry": []}
    visible: dict[str, list[int]] = {"sharp": [], "blurry": []}
    for index, (name, kind) in enumerate(sim.frame_names()):
        start, c0 = time.perf_counter(), time.process_time()
        frame = sim.frame(index)
        elapsed = time.perf_counter() - start
        times[kind].append(elapsed)
        cpus[kind].append(time.process_time() - c0)
        t = frame.truth
        visible[kind].append(int(t.visible.sum()))
        blur = float(np.median(t.blur_length[t.visible])) if t.visible.any() else 0.0
        print(f"{name}: {elapsed:5.2f} s  T={t.motion.samples:3d}  median blur {blur:5.1f} px  "
              f"visible features {int(t.visible.sum())}")
    for kind, values in times.items():
        if values:
            print(f"{kind}: {len(values)} frames rendered, median {np.median(visible[kind]):.0f} visible "
                  f"features; median {np.median(values):.2f} s, max {max(values):.2f} s per frame "
                  f"(CPU median {np.median(cpus[kind]):.2f} s)")
            record.add(f"{kind} frames", frames=len(values),
                       median_visible_features=np.median(visible[kind]),
                       median_wall_s_per_frame=np.median(values), max_wall_s_per_frame=max(values),
                       median_cpu_s_per_frame=np.median(cpus[kind]))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak memory: {peak:.0f} MB")
    record.add("memory", peak_mb=peak)
    record.write()


if __name__ == "__main__":
    main()
