"""Calibration at scale from features, printed: time (wall and CPU) per stage, peak memory,
the generic camera's error to the truth and the yield, at several frame counts.

    python scripts/bench_scale.py [--frames 200 1000 2000] [--blurry-share 0.7] [--seed 3] [--device cpu]

Simulation (features, not images): a 1280 x 720 lens the project's other benchmarks do not use
(:func:`blurcalib.sim.truth.d435i_like_camera` of ``--seed`` with its 0.3 px non-parametric
deviation), the reference A4 star pattern, poses anywhere in the image
(:func:`blurcalib.sim.synth.sample_pose`), the true projections plus Gaussian noise of
``--noise`` px per axis. A share ``--blurry-share`` of the frames are blurry: their features
also carry one unknown translation each (uniform in a disc of 3 px), which the generic fit
estimates as a free shift.

Each size runs in its own process (one torch thread) through the engine's API as ``blurcalib
calibrate --features`` does: the parametric camera of the sharp frames
(:func:`blurcalib.calib.sharp.calibrate_sharp`), the generic camera of sharp and blurry frames
and that of the sharp frames alone (:func:`blurcalib.calib.joint.calibrate_generic`), and their
assessment with the default validation and uncertainty
(:func:`blurcalib.calib.trust.assess_calibration`). Printed per size: observations, seconds
per stage (wall / CPU), the peak resident memory of the process (``ru_maxrss``), the generic
cameras' median error to the truth over the image (after the best-fit rotation), the held-out
medians and the frames used (the yield). Timings depend on the machine's load. The figures are
also recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time

import benchrecord
import numpy as np

BLURRY_SHIFT_PX = 3.0


def simulate(frames: int, blurry_share: float, noise_px: float, seed: int):
    """The truth, the pattern and the sharp and blurry feature tables."""
    from blurcalib.io.results import FeatureFlags, FeatureTable
    from blurcalib.sim.synth import sample_pose
    from blurcalib.sim.truth import d435i_like_camera
    from blurcalib.target.pattern import layout_pattern

    truth = d435i_like_camera(seed)
    pattern = layout_pattern()
    W, H = truth.model.width, truth.model.height
    P = pattern.points_3d()
    rng = np.random.default_rng(seed)
    n_blurry = round(frames * blurry_share)
    cols: dict[str, list[np.ndarray]] = {k: [] for k in ("frame", "id", "x", "y", "flags")}
    for i in range(frames):
        blurry = i >= frames - n_blurry
        pose = sample_pose(pattern, truth, rng, 60.0, (24.0, 42.0))
        cam = pose.transform(P)
        px = truth.project(cam)
        vis = (cam[:, 2] > 0) & np.all((px >= 0) & (px <= [W - 1, H - 1]), axis=1)
        ids = np.nonzero(vis)[0]
        obs = px[vis] + rng.normal(size=(len(ids), 2)) * noise_px
        if blurry:
            angle = rng.uniform(0, 2 * np.pi)
            obs += BLURRY_SHIFT_PX * math.sqrt(rng.uniform()) * np.array([math.cos(angle), math.sin(angle)])
        name = f"{'blurry' if blurry else 'sharp'}/{i:05d}"
        cols["frame"].append(np.full(len(ids), name))
        cols["id"].append(ids)
        cols["x"].append(obs[:, 0])
        cols["y"].append(obs[:, 1])
        cols["flags"].append(np.full(len(ids), int(FeatureFlags.BLURRY_FRAME if blurry
                                                    else FeatureFlags.SHARP_FRAME)))
    c = {k: np.concatenate(v) for k, v in cols.items()}
    fxy = pattern.features[c["id"]]
    table = FeatureTable(c["frame"], c["id"], fxy[:, 0], fxy[:, 1], P[c["id"], 0], P[c["id"], 1],
                         c["x"], c["y"], np.ones(len(c["id"])), c["flags"])
    is_blurry = (table.flags & int(FeatureFlags.BLURRY_FRAME)) != 0
    return truth, pattern, (W, H), table.select(~is_blurry), table.select(is_blurry)


def run_size(frames: int, blurry_share: float, noise_px: float, seed: int, device: str) -> dict:
    """One size, in this process: the stages' figures as a dict (the bundle adjustments, the
    validation and the uncertainty on torch ``device``; the parametric camera on the CPU)."""
    import torch

    from blurcalib.calib.bundle import BundleSettings
    from blurcalib.calib.joint import JointSettings, calibrate_generic
    from blurcalib.calib.sharp import calibrate_sharp
    from blurcalib.calib.trust import assess_calibration
    from blurcalib.runs.runtime import keep_large_allocations
    from blurcalib.sim.evaluate import camera_accuracy

    torch.set_num_threads(1)
    keep_large_allocations()  # as the command line does
    truth, pattern, size, sharp, blurry = simulate(frames, blurry_share, noise_px, seed)
    out: dict = {"frames": frames, "observations": len(sharp) + len(blurry), "seconds": {}, "cpu": {}}
    bundle = BundleSettings(device=device)
    joint_settings = JointSettings(bundle=bundle)

    def stage(name: str, fn):
        t0, c0 = time.perf_counter(), time.process_time()
        value = fn()
        out["seconds"][name] = time.perf_counter() - t0
        out["cpu"][name] = time.process_time() - c0
        return value

    cal = stage("parametric", lambda: calibrate_sharp(sharp, pattern, size))
    joint = stage("generic", lambda: calibrate_generic(sharp, blurry, cal, pattern, size, joint_settings))
    alone = stage("generic_sharp", lambda: calibrate_generic(sharp, None, cal, pattern, size, joint_settings))
    trust = stage("assessment", lambda: assess_calibration(joint, alone, cal, sharp, pattern, size,
                                                           bundle=bundle))
    out["assessment_parts"] = {k: round(v, 1) for k, v in trust.seconds.items()}
    out["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    out["error_px"] = camera_accuracy(truth, joint.model).median
    out["error_sharp_px"] = camera_accuracy(truth, alone.model).median
    out["used"] = len(joint.frames)
    out["iterations"] = joint.bundle.iterations
    v = trust.validation
    out["held_out"] = {k: s.median_px for k, s in v.scores.items()} if v is not None else {}
    out["sigma_median_px"] = trust.uncertainty.median()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[200, 1000, 2000])
    parser.add_argument("--blurry-share", type=float, default=0.7)
    parser.add_argument("--noise", type=float, default=0.02, help="feature noise per axis (px)")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--device", default="cpu", help="torch device of the bundle adjustments (cpu, cuda)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    benchrecord.add_option(parser)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(run_size(args.frames[0], args.blurry_share, args.noise, args.seed, args.device)))
        return
    record = benchrecord.start(__file__, args)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    print(f"simulated features: {args.blurry_share:.0%} blurry frames (free shift each), noise "
          f"{args.noise} px, lens seed {args.seed}; one torch thread; device {args.device}; timings depend "
          "on the machine's load")
    for n in args.frames:
        proc = subprocess.run([sys.executable, __file__, "--child", "--frames", str(n), "--blurry-share",
                               str(args.blurry_share), "--noise", str(args.noise), "--seed", str(args.seed),
                               "--device", args.device],
                              env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"{n} frames: failed (exit {proc.returncode}):\n{proc.stderr.strip()[-3000:]}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        s, c = r["seconds"], r["cpu"]
        total, total_cpu = sum(s.values()), sum(c.values())
        stages = ", ".join(f"{k} {s[k]:.1f}/{c[k]:.1f}" for k in s)
        held = ", ".join(f"{k} {v:.4f}" for k, v in r["held_out"].items())
        print(f"{n} frames, {r['observations']:,} observations: {total:.1f} s wall / {total_cpu:.1f} s CPU "
              f"({stages} s wall/CPU; assessment parts {r['assessment_parts']}), peak {r['peak_gb']:.2f} GB")
        print(f"  generic camera to the truth: median {r['error_px']:.4f} px (sharp only "
              f"{r['error_sharp_px']:.4f} px); held-out medians {held} px; median sigma "
              f"{r['sigma_median_px']:.4f} px; frames used {r['used']} of {n}; "
              f"{r['iterations']} LM iterations")
        record.add(f"{n} frames", frames=n, frames_used=r["used"], observations=r["observations"],
                   error_px=r["error_px"], error_sharp_only_px=r["error_sharp_px"],
                   **{f"held_out_{k}_px": v for k, v in r["held_out"].items()},
                   sigma_median_px=r["sigma_median_px"], wall_s=total, cpu_s=total_cpu,
                   **{f"{k}_cpu_s": v for k, v in c.items()}, peak_gb=r["peak_gb"],
                   lm_iterations=r["iterations"])
    record.write()


if __name__ == "__main__":
    main()
