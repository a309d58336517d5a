"""Benchmark of the simulator: time and peak memory to render 1280x720 frames.

    python scripts/bench_synth.py [--frames N]

Prints the time of every sharp and blurry frame of the default dataset (after the one-time
set-up of the lens map and textures) and the median; the target is 5 s or less per blurry frame
on a 2-core machine.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from blurcalib.sim.synth import Simulator, SynthConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=8, help="blurry frames to time")
    args = parser.parse_args()
    config = SynthConfig(sharp=2, blurry=args.frames)
    start = time.perf_counter()
    sim = Simulator(config)
    sim.frame(0)
    print(f"set-up (lens map, textures, first frame): {time.perf_counter() - start:.2f} s")
    times = {"sharp": [], "blurry": []}
    for index, (name, kind) in enumerate(sim.frame_names()):
        start = time.perf_counter()
        frame = sim.frame(index)
        elapsed = time.perf_counter() - start
        times[kind].append(elapsed)
        t = frame.truth
        blur = float(np.median(t.blur_length[t.visible])) if t.visible.any() else 0.0
        print(f"{name}: {elapsed:5.2f} s  T={t.motion.samples:3d}  median blur {blur:5.1f} px  "
              f"visible features {int(t.visible.sum())}")
    for kind, values in times.items():
        if values:
            print(f"{kind}: median {np.median(values):.2f} s, max {max(values):.2f} s per frame")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak memory: {peak:.0f} MB")


if __name__ == "__main__":
    main()
