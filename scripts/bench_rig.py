"""Benchmark of the stereo rig calibration: extrinsics against the truth, printed.

    python scripts/bench_rig.py [--sharp 20] [--blurry 60] [--noise-px 0.05] [--seed 0]

A simulated RealSense D435I-like infrared pair (``blurcalib.sim.rig.d435i_stereo_rig``: two
1280 x 720 cameras 50 mm apart, each with its own 0.3 px lens deviation) sees the target in
``--sharp`` sharp and ``--blurry`` blurry image sets. Each camera's features are the truth's
time-averaged positions with ``--noise-px`` px of Gaussian noise and, on blurry frames, a random
image shift of up to 3 px (``blurcalib.sim.rig_eval.truth_features``): the frames are not rendered
and extracted, so the figures are those of the calibration alone. Each camera is calibrated as
``blurcalib calibrate`` does (Brown-Conrady on the sharp frames, then the generic camera on all),
then the rig's extrinsics by the joint bundle (``blurcalib.calib.rig_calibration``), with the
sharp sets only and with sharp and blurry sets. Printed: each camera's generic error against its
true camera, the extrinsics' error (rotation deg, translation mm, after each camera's gauge
rotation), the rectified epipolar error of the true feature positions seen by both cameras (the
calibrated pair's rectification, px), the yield (sets and observations used) and the CPU time
(the machine may be shared).
"""

from __future__ import annotations

import argparse
import time

import benchrecord
import numpy as np
import torch

from blurcalib.calib.joint import calibrate_generic
from blurcalib.calib.rig_calibration import calibrate_rig
from blurcalib.calib.sharp import calibrate_sharp
from blurcalib.camera.stereo import epipolar_errors, stereo_rectify
from blurcalib.sim.evaluate import camera_accuracy
from blurcalib.sim.rig import RigSimulator, d435i_stereo_rig
from blurcalib.sim.rig_eval import extrinsic_error, truth_features
from blurcalib.sim.synth import SynthConfig
from blurcalib.target.pattern import layout_pattern


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sharp", type=int, default=20, help="sharp image sets (default 20)")
    ap.add_argument("--blurry", type=int, default=60, help="blurry image sets (default 60)")
    ap.add_argument("--noise-px", type=float, default=0.05, help="feature noise, px per axis (default 0.05)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    benchrecord.add_option(ap)
    args = ap.parse_args()
    record = benchrecord.start(__file__, args)
    torch.set_num_threads(1)
    pattern = layout_pattern()
    rig = d435i_stereo_rig(args.seed)
    sim = RigSimulator(SynthConfig(sharp=args.sharp, blurry=args.blurry, seed=args.seed), rig, pattern)
    sets = [sim.image_set(k) for k in range(len(sim.set_names()))]
    rng = np.random.default_rng(args.seed)
    print(f"== simulated D435I-like pair: baseline {np.linalg.norm(rig.relative(0, 1).t) * 1000:.1f} mm, "
          f"{args.sharp} sharp + {args.blurry} blurry sets, noise {args.noise_px} px ==")
    for routes in (("sharp",), ("sharp", "blurry")):
        t0 = time.process_time()
        calibrations = []
        for c in range(len(rig.cameras)):
            frames = [s.frames[c] for s in sets if s.frames[c] is not None and s.kind in routes]
            sharp = truth_features([f for f in frames if f.kind == "sharp"], pattern, args.noise_px, 0.0, rng)
            blurry = [f for f in frames if f.kind == "blurry"]
            blurry_table = truth_features(blurry, pattern, args.noise_px, 3.0, rng) if blurry else None
            param = calibrate_sharp(sharp, pattern, (1280, 720))
            calibrations.append(calibrate_generic(sharp, blurry_table, param, pattern, (1280, 720)))
        cpu_cameras = time.process_time() - t0
        result = calibrate_rig(calibrations)
        cpu_rig = time.process_time() - t0 - cpu_cameras
        err = extrinsic_error(rig, result.bundle.rig)
        calibrated = result.bundle.rig
        rect = stereo_rectify(calibrated.cameras[0], calibrated.cameras[1], calibrated.relative(0, 1))
        both = [s.frames for s in sets if all(f is not None for f in s.frames)]
        pairs = [np.nonzero(f0.visible & f1.visible)[0] for f0, f1 in both]
        cams = calibrated.cameras
        epipolar = epipolar_errors(rect, cams[0].pixel_to_ray, cams[1].pixel_to_ray,
                                   np.concatenate([f[0].mid[k] for f, k in zip(both, pairs, strict=True)]),
                                   np.concatenate([f[1].mid[k] for f, k in zip(both, pairs, strict=True)]))
        epipolar = epipolar[np.isfinite(epipolar)]
        name = " + ".join(routes)
        print(f"-- {name} sets --")
        figures: dict[str, float | int] = {}
        for c, cal in enumerate(calibrations):
            acc = camera_accuracy(rig.cameras[c], cal.model)
            used = int(result.bundle.inlier[c].sum())
            print(f"camera {c}: generic {acc.median:.4f} px from the truth (median), "
                  f"{len(cal.frames)} frames, rig bundle median {result.bundle.median_error[c]:.4f} px "
                  f"over {used} observations")
            figures[f"camera{c}_error_px"] = acc.median
            figures[f"camera{c}_frames"] = len(cal.frames)
            figures[f"camera{c}_observations"] = used
        print(f"extrinsics: rotation {err.rotation_deg:.5f} deg, translation {err.translation_mm:.4f} mm "
              f"(targets 0.01 deg, 0.1 mm); {len(result.sets)} of {len(sets)} sets used, "
              f"{result.bundle.iterations} iterations")
        print(f"rectified epipolar error (true feature positions of both cameras, {len(epipolar)} points): "
              f"median {np.median(epipolar):.4f} px, 95th percentile {np.percentile(epipolar, 95):.4f} px")
        print(f"CPU time: cameras {cpu_cameras:.1f} s, rig bundle {result.bundle.cpu_seconds:.1f} s "
              f"(shared machine: CPU time, not wall)")
        record.add(f"{name} sets", rotation_error_deg=err.rotation_deg,
                   translation_error_mm=err.translation_mm,
                   epipolar_median_px=float(np.median(epipolar)), sets_used=len(result.sets),
                   sets=len(sets), cpu_cameras_s=cpu_cameras,
                   cpu_rig_s=cpu_rig, **figures)
    record.write()


if __name__ == "__main__":
    main()
