"""Benchmark of the generic camera: bundle-adjustment speed and memory, real frames,
and the simulated comparison, printed.

    python scripts/bench_generic.py [--frames 80 200] [--skip-real] [--skip-experiment]

1. **Speed.** Simulated features (``blurcalib.paper.generic``: 20 sharp frames, the rest
   blurry with free per-frame shifts) on the 1280 x 720 camera, 25 px cells; the joint bundle
   adjustment of N frames, each size in its own process so that its peak memory (max RSS) is
   its own. Targets: 80 frames <= 60 s, 200 frames <= 3 min, peak memory <= 2 GB. Wall time
   and process CPU time are printed (torch single-threaded; the machine may be shared).
2. **Real frames** (``../shared/fixtures/real_star16``, the reference detector's features of 27
   sharp frames, target points nominal): the generic model's median reprojection error beside
   OpenCV's rational 8-coefficient model (``CALIB_RATIONAL_MODEL``) on the same features.
   Target: generic below rational-8.
3. **Accuracy against the truth**: ``blurcalib experiment generic`` (table (a)-(d)) with its
   targets checked.

Each part prints the observations it kept (the yield) beside accuracy and time; the figures are
also recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import benchrecord
import cv2
import numpy as np
import torch

from blurcalib.calib.bundle import BundleSettings, bundle_adjust
from blurcalib.calib.sharp import solve_pose
from blurcalib.camera.generic import calibrated_area, fit_to_rays
from blurcalib.camera.parametric import BrownConrady
from blurcalib.io.refformat import read_ref_dataset
from blurcalib.paper import generic as experiment
from blurcalib.sim.truth import d435i_like_camera
from blurcalib.target.pattern import layout_pattern

REAL = Path(__file__).resolve().parents[2] / "shared" / "fixtures" / "real_star16"


def speed_run(frames: int) -> dict:
    """One joint bundle adjustment of ``frames`` simulated frames; figures as a dict."""
    torch.set_num_threads(1)
    settings = experiment.GenericSettings(sharp=20, blurry=frames - 20, seed=1)
    truth = d435i_like_camera(settings.seed, settings.deviation_px)
    sim = experiment.simulate_frames(settings, layout_pattern(), truth)
    sharp = [f for f in sim if f.kind == "sharp"]
    param = experiment.calibrate_parametric(sharp, 1280, 720)
    t0, c0 = time.perf_counter(), time.process_time()
    area = calibrated_area(np.concatenate([f.observed for f in sim]), 1280, 720)
    initial = fit_to_rays(param.pixel_to_ray, 1280, 720, area=area, cell_px=settings.cell_px)
    t_init, c_init = time.perf_counter() - t0, time.process_time() - c0
    res = experiment.generic_fit(initial, param, sim, shift_free=True)
    return {"frames": frames, "observations": int(sum(len(f.points) for f in sim)),
            "grid": list(initial.grid.shape[:2]), "init_s": t_init, "init_cpu_s": c_init,
            "ba_s": res.seconds, "ba_cpu_s": res.cpu_seconds, "iterations": res.iterations,
            "inliers": int(res.inlier.sum()),
            "median_px": res.median_error,
            "peak_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def speed(sizes: list[int], record: benchrecord.BenchRecord) -> None:
    print("== bundle adjustment speed (joint: sharp + blurry frames, free shifts) ==")
    targets = {80: 60.0, 200: 180.0}
    for n in sizes:
        out = subprocess.run([sys.executable, __file__, "--speed-run", str(n)], capture_output=True,
                             text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        target = targets.get(n)
        verdict = "" if target is None else f" (target <= {target:.0f} s: " \
            f"{'met' if r['ba_s'] <= target else 'MISSED'})"
        print(f"{n} frames, {r['inliers']} of {r['observations']} observations kept, grid {r['grid'][1]} x "
              f"{r['grid'][0]}: BA {r['ba_s']:.1f} s wall / {r['ba_cpu_s']:.1f} s CPU, "
              f"{r['iterations']} iterations"
              f"{verdict}; "
              f"initial grid fit {r['init_s']:.1f} s wall / {r['init_cpu_s']:.1f} s CPU; "
              f"median reprojection {r['median_px']:.4f} px; peak memory {r['peak_gb']:.2f} GB "
              f"(target <= 2 GB: {'met' if r['peak_gb'] <= 2 else 'MISSED'})")
        record.add(f"bundle adjustment, {n} frames", frames=n, observations=r["observations"],
                   observations_kept=r["inliers"], grid=f"{r['grid'][1]} x {r['grid'][0]}",
                   median_reprojection_px=r["median_px"], ba_wall_s=r["ba_s"], ba_cpu_s=r["ba_cpu_s"],
                   iterations=r["iterations"], initial_fit_cpu_s=r["init_cpu_s"], peak_gb=r["peak_gb"])


def real_frames(cell_px: float, record: benchrecord.BenchRecord) -> None:
    print(f"== real frames (real_star16, reference features, {cell_px:g} px cells) ==")
    data = read_ref_dataset(REAL / "features_10px.bin")
    geo = data.geometry
    coords = {int(i): (x, y) for i, x, y in zip(geo.ids, geo.fx, geo.fy, strict=True)}
    W, H = data.image_size
    pts, obs = [], []
    for img in data.images:
        if len(img.features) < 20:
            continue
        xy = np.array([coords[int(i)] for i in img.features], dtype=np.float64) * geo.square_length_m
        pts.append(np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32))
        obs.append(img.xy.astype(np.float32))
    cv2.setNumThreads(1)
    results = {}
    for name, flags in (("Brown-Conrady (5)", 0), ("OpenCV rational (8)", cv2.CALIB_RATIONAL_MODEL)):
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(pts, obs, (W, H), None, None, flags=flags)
        pred = [cv2.projectPoints(p, r, t, K, dist)[0].reshape(-1, 2)
                for p, r, t in zip(pts, rvecs, tvecs, strict=True)]
        err = np.linalg.norm(np.concatenate(pred) - np.concatenate(obs), axis=1)
        results[name] = (K, dist, float(np.median(err)))
        print(f"{name}: median reprojection error {np.median(err):.4f} px, "
              f"RMS {np.sqrt(np.mean(err**2)):.4f} px "
              f"({len(pts)} of {len(data.images)} frames, {len(err)} features)")
        record.add(f"real frames, {name}", frames_used=len(pts), features=len(err),
                   median_reprojection_px=np.median(err), rms_reprojection_px=np.sqrt(np.mean(err**2)))
    K, dist, _ = results["Brown-Conrady (5)"]
    param = BrownConrady.from_matrix(K, dist.reshape(-1)[:5], W, H)
    area = calibrated_area(np.concatenate(obs), W, H)
    initial = fit_to_rays(param.pixel_to_ray, W, H, area=area, cell_px=cell_px)
    poses = [solve_pose(param, p, o) for p, o in zip(pts, obs, strict=True)]
    index = np.concatenate([np.full(len(p), i) for i, p in enumerate(pts)])
    res = bundle_adjust(initial, poses, index, np.concatenate(pts), np.concatenate(obs),
                        settings=BundleSettings())
    rational = results["OpenCV rational (8)"][2]
    print(f"generic ({initial.grid_width} x {initial.grid_height} nodes): median reprojection error "
          f"{res.median_error:.4f} px, RMS {res.rms_error:.4f} px, {int(res.inlier.sum())} inliers "
          f"of {len(res.inlier)}; {res.seconds:.1f} s wall / {res.cpu_seconds:.1f} s CPU "
          f"(target: below rational-8's {rational:.4f} px: "
          f"{'met' if res.median_error < rational else 'MISSED'})")
    for line in res.warnings:
        print(f"  warning: {line}")
    record.add("real frames, generic", frames_used=len(pts), features=len(res.inlier),
               features_kept=int(res.inlier.sum()), grid=f"{initial.grid_width} x {initial.grid_height}",
               median_reprojection_px=res.median_error, rms_reprojection_px=res.rms_error,
               wall_s=res.seconds, cpu_s=res.cpu_seconds)


def accuracy(record: benchrecord.BenchRecord) -> None:
    print("== accuracy against the truth (blurcalib experiment generic) ==")
    exp = experiment.run_generic_experiment(progress=False)
    print(experiment.format_table(exp))
    for name, row in exp.table.items():
        record.add(f"experiment generic, {name}",
                   **{f"{region}_{stat}_px": value for region, stats in row.items()
                      for stat, value in zip(("median", "p95", "max"), stats, strict=True)})
    record.add("experiment generic, frames", **exp.frames, blurry_dropped_by_filter_d=exp.dropped_by_filter,
               calibrated_area_pct=100 * exp.area_fraction)
    a, b, c = (exp.table[m] for m in experiment.MODELS[:3])
    print(f"targets: (c) median over the calibrated area {c['area'][0]:.4f} px <= 0.02 "
          f"({'met' if c['area'][0] <= 0.02 else 'MISSED'}), area {100 * exp.area_fraction:.1f}% >= 95% "
          f"({'met' if exp.area_fraction >= 0.95 else 'MISSED'}); border median {c['border'][0]:.4f} <= "
          f"half of (b) {b['border'][0]:.4f} "
          f"({'met' if c['border'][0] <= b['border'][0] / 2 else 'MISSED'}); "
          f"median {c['area'][0]:.4f} <= a fifth of (a) {a['area'][0]:.4f} "
          f"({'met' if c['area'][0] <= a['area'][0] / 5 else 'MISSED'})")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, nargs="*", default=[80, 200])
    ap.add_argument("--real-cell-px", type=float, default=40.0)
    ap.add_argument("--skip-real", action="store_true")
    ap.add_argument("--skip-experiment", action="store_true")
    ap.add_argument("--speed-run", type=int, help=argparse.SUPPRESS)
    benchrecord.add_option(ap)
    args = ap.parse_args()
    if args.speed_run:
        print(json.dumps(speed_run(args.speed_run)))
        return 0
    record = benchrecord.start(__file__, args)
    torch.set_num_threads(1)
    print("(torch single-threaded)")
    if args.frames:
        speed(args.frames, record)
    if not args.skip_real:
        real_frames(args.real_cell_px, record)
    if not args.skip_experiment:
        accuracy(record)
    record.write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
