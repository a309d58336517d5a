"""Benchmark of the stereo rig calibration: extrinsics against the truth, printed.

    python scripts/bench_rig.py [--cameras 2 3] [--sharp 20] [--blurry 60] [--sets3 10 14]
                                [--noise-px 0.05] [--seed 0] [--trust-seeds 4] [--trust-sets 10 10]

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

The same run then measures a row of three cameras (``--cameras 3`` alone;
``blurcalib.sim.rig.chain_rig``: each camera 50 mm right of the previous one and turned 20 degrees
further; ``--sets3`` sharp and blurry sets), whose image sets alternate between cameras 0 and 1
and cameras 1 and 2 (the simulator's visibility rule): camera 2 never shares a set with camera 0
and is linked to it only through camera 1. Printed per camera: its generic error, its extrinsics'
error against the truth (``camera c <- camera 0``, mm and deg) and the frames it was calibrated
from; per pair its uncertainty (with the cameras' own errors, and from the features' noise alone)
and held-out error (``blurcalib.calib.rig_trust``) beside its true error, and the epipolar error of
each pair sharing sets.

Last, ``--trust-seeds`` simulations of the pair (``--trust-sets`` sharp and blurry sets each, seeds
0, 1, ...) measure how far the uncertainty can be trusted: per route the RMS over the seeds of the
true error over the predicted uncertainty (1 when the uncertainty is the error's expected size),
translation and rotation, with the cameras' own errors folded in and from the features' noise alone.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import benchrecord
import numpy as np
import torch

from blurcalib.calib.joint import GenericCalibration, calibrate_generic
from blurcalib.calib.rig_calibration import RigCalibration, calibrate_rig
from blurcalib.calib.rig_trust import cameras_covariance, pair_uncertainty, rig_trust
from blurcalib.calib.sharp import calibrate_sharp
from blurcalib.camera.stereo import epipolar_errors, stereo_rectify
from blurcalib.sim.evaluate import camera_accuracy
from blurcalib.sim.rig import RigSet, RigSimulator, TrueRig, chain_rig, d435i_stereo_rig
from blurcalib.sim.rig_eval import extrinsic_error, truth_features
from blurcalib.sim.synth import SynthConfig
from blurcalib.target.pattern import StarPattern, layout_pattern


def calibrate_cameras(rig: TrueRig, sets: Sequence[RigSet], routes: tuple[str, ...], pattern: StarPattern,
                      noise_px: float, rng: np.random.Generator) -> list[GenericCalibration]:
    """Each camera calibrated alone from the truth's features of its frames in the ``routes`` sets."""
    calibrations = []
    for c in range(len(rig.cameras)):
        frames = [s.frames[c] for s in sets if s.frames[c] is not None and s.kind in routes]
        sharp = truth_features([f for f in frames if f.kind == "sharp"], pattern, noise_px, 0.0, rng)
        blurry = [f for f in frames if f.kind == "blurry"]
        blurry_table = truth_features(blurry, pattern, noise_px, 3.0, rng) if blurry else None
        param = calibrate_sharp(sharp, pattern, (1280, 720))
        calibrations.append(calibrate_generic(sharp, blurry_table, param, pattern, (1280, 720)))
    return calibrations


def pair_epipolar(result: RigCalibration, sets: Sequence[RigSet], i: int, j: int) -> np.ndarray:
    """The rectified epipolar errors (px) of the true feature positions seen by cameras ``i`` and ``j``."""
    calibrated = result.bundle.rig
    rect = stereo_rectify(calibrated.cameras[i], calibrated.cameras[j], calibrated.relative(i, j))
    both = [(s.frames[i], s.frames[j]) for s in sets if s.frames[i] is not None and s.frames[j] is not None]
    pairs = [np.nonzero(fi.visible & fj.visible)[0] for fi, fj in both]
    cams = calibrated.cameras
    epipolar = epipolar_errors(rect, cams[i].pixel_to_ray, cams[j].pixel_to_ray,
                               np.concatenate([f[0].mid[k] for f, k in zip(both, pairs, strict=True)]),
                               np.concatenate([f[1].mid[k] for f, k in zip(both, pairs, strict=True)]))
    return epipolar[np.isfinite(epipolar)]


def report_case(rig: TrueRig, sets: Sequence[RigSet], result: RigCalibration,
                calibrations: Sequence[GenericCalibration]) -> dict[str, float | int]:
    """Print each camera's and each sharing pair's figures; return them for the record."""
    figures: dict[str, float | int] = {}
    for c, cal in enumerate(calibrations):
        acc = camera_accuracy(rig.cameras[c], cal.model)
        used = int(result.bundle.inlier[c].sum())
        line = (f"camera {c}: generic {acc.median:.4f} px from the truth (median), {len(cal.frames)} frames, "
                f"rig bundle median {result.bundle.median_error[c]:.4f} px over {used} observations")
        if c > 0:
            err = extrinsic_error(rig, result.bundle.rig, 0, c)
            line += f"; extrinsics {err.translation_mm:.4f} mm, {err.rotation_deg:.5f} deg from the truth"
            figures[f"camera{c}_translation_error_mm"] = err.translation_mm
            figures[f"camera{c}_rotation_error_deg"] = err.rotation_deg
        print(line)
        figures[f"camera{c}_error_px"] = acc.median
        figures[f"camera{c}_frames"] = len(cal.frames)
        figures[f"camera{c}_observations"] = used
    for pair in rig_trust(result, folds=5):
        err = extrinsic_error(rig, result.bundle.rig, pair.i, pair.j)
        alone_mm, alone_deg = pair_uncertainty(result.bundle.rig, result.bundle.covariance, pair.i, pair.j)
        print(f"camera {pair.j} <- camera {pair.i}: uncertainty {pair.translation_mm:.4f} mm, "
              f"{pair.rotation_deg:.5f} deg (the features' noise alone {alone_mm:.4f} mm, "
              f"{alone_deg:.5f} deg; "
              f"true error {err.translation_mm:.4f} mm, {err.rotation_deg:.5f} deg); " + (
                  f"held-out error {pair.holdout_px:.4f} px over {pair.holdout_count} predicted features"
                  if pair.holdout_count else "no held-out error (no shared set)"))
        key = f"pair{pair.i}{pair.j}"
        figures[f"{key}_translation_uncertainty_mm"] = pair.translation_mm
        figures[f"{key}_rotation_uncertainty_deg"] = pair.rotation_deg
        figures[f"{key}_translation_uncertainty_features_mm"] = alone_mm
        figures[f"{key}_rotation_uncertainty_features_deg"] = alone_deg
        figures[f"{key}_holdout_px"] = pair.holdout_px
    C = len(rig.cameras)
    for i in range(C):
        for j in range(i + 1, C):
            if not any(s.frames[i] is not None and s.frames[j] is not None for s in sets):
                print(f"cameras {i} and {j} share no set")
                continue
            try:
                epipolar = pair_epipolar(result, sets, i, j)
            except ValueError as exc:
                print(f"cameras {i}, {j}: rectification failed ({exc})")
                continue
            print(f"cameras {i}, {j}: rectified epipolar error (true feature positions, {len(epipolar)} "
                  f"points): median {np.median(epipolar):.4f} px, "
                  f"95th percentile {np.percentile(epipolar, 95):.4f} px")
            figures[f"pair{i}{j}_epipolar_median_px"] = float(np.median(epipolar))
    return figures


def run_case(cameras: int, sharp: int, blurry: int, noise_px: float, seed: int,
             record: benchrecord.BenchRecord) -> None:
    """Simulate, calibrate and print one rig (the pair, or the row of three), sharp sets only and
    sharp and blurry sets; add its figures to ``record``."""
    pattern = layout_pattern()
    config = SynthConfig(sharp=sharp, blurry=blurry, seed=seed)
    if cameras == 2:
        rig = d435i_stereo_rig(seed)
        sim = RigSimulator(config, rig, pattern)
        title = f"simulated D435I-like pair: baseline {np.linalg.norm(rig.relative(0, 1).t) * 1000:.1f} mm"
    else:
        rig = chain_rig(3, seed)
        sim = RigSimulator(config, rig, pattern, groups=[(0, 1), (1, 2)])
        title = "simulated row of three cameras 50 mm apart, turned 20 deg each; sets of cameras 0+1 or 1+2"
    sets = [sim.image_set(k) for k in range(len(sim.set_names()))]
    rng = np.random.default_rng(seed)
    print(f"== {title}, {sharp} sharp + {blurry} blurry sets, noise {noise_px} px ==")
    prefix = "" if cameras == 2 else "three cameras: "
    for routes in (("sharp",), ("sharp", "blurry")):
        t0 = time.process_time()
        calibrations = calibrate_cameras(rig, sets, routes, pattern, noise_px, rng)
        cpu_cameras = time.process_time() - t0
        result = calibrate_rig(calibrations)
        cpu_rig = time.process_time() - t0 - cpu_cameras
        name = " + ".join(routes)
        print(f"-- {name} sets --")
        figures = report_case(rig, sets, result, calibrations)
        err = extrinsic_error(rig, result.bundle.rig, 0, 1)
        print(f"extrinsics (camera 1 <- camera 0): rotation {err.rotation_deg:.5f} deg, translation "
              f"{err.translation_mm:.4f} mm (targets 0.01 deg, 0.1 mm); {len(result.sets)} of {len(sets)} "
              f"sets used, {result.bundle.iterations} iterations")
        print(f"CPU time: cameras {cpu_cameras:.1f} s, rig bundle {result.bundle.cpu_seconds:.1f} s "
              f"(shared machine: CPU time, not wall)")
        pair = {}
        if cameras == 2 and "pair01_epipolar_median_px" in figures:
            pair = {"epipolar_median_px": figures.pop("pair01_epipolar_median_px")}
        record.add(f"{prefix}{name} sets", rotation_error_deg=err.rotation_deg,
                   translation_error_mm=err.translation_mm, **pair, sets_used=len(result.sets),
                   sets=len(sets), cpu_cameras_s=cpu_cameras, cpu_rig_s=cpu_rig, **figures)


def trust_over_seeds(seeds: int, sharp: int, blurry: int, noise_px: float, record: benchrecord.BenchRecord
                     ) -> None:
    """The pair's extrinsics error against their predicted uncertainty over ``seeds`` simulations:
    per route the RMS over seeds of true error / uncertainty, with the cameras' own errors
    (:func:`blurcalib.calib.rig_trust.cameras_covariance`) and with the features' noise alone."""
    pattern = layout_pattern()
    ratios: dict[str, list[list[float]]] = {}
    print(f"== uncertainty against the true error: the pair, {sharp} sharp + {blurry} blurry sets, seeds "
          f"0-{seeds - 1} ==")
    for seed in range(seeds):
        rig = d435i_stereo_rig(seed)
        sim = RigSimulator(SynthConfig(sharp=sharp, blurry=blurry, seed=seed), rig, pattern)
        sets = [sim.image_set(k) for k in range(len(sim.set_names()))]
        rng = np.random.default_rng(seed)
        for routes in (("sharp",), ("sharp", "blurry")):
            result = calibrate_rig(calibrate_cameras(rig, sets, routes, pattern, noise_px, rng))
            bundle = result.bundle
            err = extrinsic_error(rig, bundle.rig, 0, 1)
            alone = pair_uncertainty(bundle.rig, bundle.covariance, 0, 1)
            both = pair_uncertainty(bundle.rig, bundle.covariance + cameras_covariance(result), 0, 1)
            name = " + ".join(routes)
            print(f"seed {seed}, {name} sets: true error {err.translation_mm:.4f} mm, "
                  f"{err.rotation_deg:.5f} deg; "
                  f"uncertainty {both[0]:.4f} mm, {both[1]:.5f} deg (the features' noise alone "
                  f"{alone[0]:.4f} mm, {alone[1]:.5f} deg)")
            ratios.setdefault(name, []).append([err.translation_mm / both[0], err.rotation_deg / both[1],
                                                err.translation_mm / alone[0], err.rotation_deg / alone[1]])
    for name, rows in ratios.items():
        r = np.array(rows)
        rms = np.sqrt(np.mean(r ** 2, axis=0))
        print(f"{name} sets: true error / uncertainty, RMS over {len(r)} seeds: translation {rms[0]:.2f}, "
              f"rotation {rms[1]:.2f} (the features' noise alone: {rms[2]:.2f}, {rms[3]:.2f})")
        record.add(f"uncertainty over seeds: {name} sets", seeds=len(r), translation_ratio=rms[0],
                   rotation_ratio=rms[1], translation_ratio_features=rms[2], rotation_ratio_features=rms[3],
                   translation_ratio_min=float(r[:, 0].min()), translation_ratio_max=float(r[:, 0].max()),
                   rotation_ratio_min=float(r[:, 1].min()), rotation_ratio_max=float(r[:, 1].max()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, nargs="+", choices=(2, 3), default=[2, 3],
                    help="the rigs measured: 2, the D435I-like pair; 3, a row of three whose camera 2 is "
                         "linked only through camera 1 (default both)")
    ap.add_argument("--sharp", type=int, default=20, help="sharp image sets of the pair (default 20)")
    ap.add_argument("--blurry", type=int, default=60, help="blurry image sets of the pair (default 60)")
    ap.add_argument("--sets3", type=int, nargs=2, default=[10, 14], metavar=("SHARP", "BLURRY"),
                    help="sharp and blurry image sets of the row of three (default 10 14)")
    ap.add_argument("--noise-px", type=float, default=0.05, help="feature noise, px per axis (default 0.05)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ap.add_argument("--trust-seeds", type=int, default=4,
                    help="simulations of the pair whose extrinsics error is compared with the predicted "
                         "uncertainty (default 4; 0: none)")
    ap.add_argument("--trust-sets", type=int, nargs=2, default=[10, 10], metavar=("SHARP", "BLURRY"),
                    help="sharp and blurry image sets of each of those simulations (default 10 10)")
    benchrecord.add_option(ap)
    args = ap.parse_args()
    record = benchrecord.start(__file__, args)
    torch.set_num_threads(1)
    for cameras in args.cameras:
        sharp, blurry = (args.sharp, args.blurry) if cameras == 2 else args.sets3
        run_case(cameras, sharp, blurry, args.noise_px, args.seed, record)
    if args.trust_seeds:
        trust_over_seeds(args.trust_seeds, *args.trust_sets, args.noise_px, record)
    record.write()


if __name__ == "__main__":
    main()
