"""Held-out error on the real fixture camera, printed: blurcalib's k-fold validation of its
cameras beside OpenCV's rational-8 model scored on the same folds.

    python scripts/bench_validation.py [--folds 5] [--fixtures ../shared/fixtures]

Data: the reference tool's features of the real 1280 x 720 camera
(``real_star16/features_10px.bin``, 27 frames, all sharp). blurcalib calibrates from them as
``blurcalib calibrate --features`` does (:func:`blurcalib.pipeline.run.run_from_features`) and
scores its generic and parametric cameras on frames they have not seen
(:func:`blurcalib.calib.validation.kfold_validation`). OpenCV's rational model (``CALIB_RATIONAL_MODEL``,
8 distortion coefficients) is fitted on the same training frames of each fold, and each held-out
frame's pose is fitted alone (``solvePnP`` then ``solvePnPRefineLM``) with the camera held; the
medians are over all held-out features. Prints the frames used (the yield) and the time beside
the figures, and records them as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import benchrecord
import cv2
import numpy as np
import torch

from blurcalib.calib.sequence import SequenceSettings
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.validation import ValidationSettings, assign_folds
from blurcalib.io.feature_input import read_feature_input
from blurcalib.pipeline.run import PipelineSettings, run_from_features
from blurcalib.target.pattern import load_pattern

ROOT = Path(__file__).resolve().parents[1]


def rational_held_out(table, pattern, size: tuple[int, int], fold_of: dict[str, int],
                      folds: int) -> np.ndarray:
    """Residual norms (px) of every held-out feature under OpenCV's rational-8 camera."""
    P = pattern.points_3d().astype(np.float32)
    frames = sorted(fold_of)
    obj = {f: P[table.feature_id[table.frame == f]] for f in frames}
    img = {f: np.column_stack([table.x, table.y])[table.frame == f].astype(np.float32) for f in frames}
    errors = []
    for k in range(folds):
        train = [f for f in frames if fold_of[f] != k]
        _, K, dist, _, _ = cv2.calibrateCamera([obj[f] for f in train], [img[f] for f in train], size, None,
                                               None, flags=cv2.CALIB_RATIONAL_MODEL)
        for f in (f for f in frames if fold_of[f] == k):
            _, rvec, tvec = cv2.solvePnP(obj[f], img[f], K, dist, flags=cv2.SOLVEPNP_SQPNP)
            rvec, tvec = cv2.solvePnPRefineLM(obj[f], img[f], K, dist, rvec, tvec)
            pred = cv2.projectPoints(obj[f], rvec, tvec, K, dist)[0].reshape(-1, 2)
            errors.append(np.linalg.norm(pred - img[f], axis=1))
    return np.concatenate(errors)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--fixtures", type=Path, default=ROOT.parent / "shared" / "fixtures")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    real = args.fixtures / "real_star16"
    pattern = load_pattern(real / "pattern.yaml")
    trust = TrustSettings(validation=ValidationSettings(folds=args.folds))
    settings = PipelineSettings(calibration=SequenceSettings(trust=trust))
    t0, c0 = time.perf_counter(), time.process_time()
    with tempfile.TemporaryDirectory() as out:
        report = run_from_features(real / "features_10px.bin", pattern, Path(out) / "run", settings).to_dict()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    table, size = read_feature_input(real / "features_10px.bin", pattern)
    v = report["validation"]
    frames = sorted(set(table.frame.tolist()))
    fold = assign_folds(frames, np.zeros(len(frames), bool), v["folds"])
    fold_of = dict(zip(frames, fold.tolist(), strict=True))
    rational = rational_held_out(table, pattern, size, fold_of, v["folds"])
    g = report["generic"]
    used = report["counts"]["sharp"].get("used", 0)
    print(f"real fixture camera, reference features: {used} of {len(frames)} frames used; generic training "
          f"median {g['median_error_px']:.4f} px ({g['grid_width']} x {g['grid_height']} grid)")
    record.add("real fixture camera", frames=len(frames), frames_used=used,
               generic_training_median_px=g["median_error_px"],
               grid=f"{g['grid_width']} x {g['grid_height']}")
    print(f"held-out ({v['folds']}-fold over frames, each held-out frame's pose fitted alone):")
    print(f"  generic (blurcalib)             median {v['generic']['median_px']:.4f} px, "
          f"RMS {v['generic']['rms_px']:.4f} px ({v['generic']['frames']} frames)")
    print(f"  OpenCV rational-8               median {np.median(rational):.4f} px, "
          f"RMS {np.sqrt(np.mean(rational ** 2)):.4f} px ({len(frames)} frames)")
    if v.get("parametric"):
        print(f"  Brown-Conrady (blurcalib)       median {v['parametric']['median_px']:.4f} px, "
              f"RMS {v['parametric']['rms_px']:.4f} px")
    record.add("held out", folds=v["folds"], generic_median_px=v["generic"]["median_px"],
               generic_rms_px=v["generic"]["rms_px"], rational8_median_px=np.median(rational),
               rational8_rms_px=np.sqrt(np.mean(rational ** 2)),
               brown_conrady_median_px=(v.get("parametric") or {}).get("median_px"),
               brown_conrady_rms_px=(v.get("parametric") or {}).get("rms_px"))
    unc = report["uncertainty"]["generic"]
    print(f"projection uncertainty: median {unc['median_px']:.4f} px, border band {unc['border_px']:.4f} px; "
          f"cross-validation diff median "
          f"{report['cross_validation']['median_px'] if report['cross_validation'] else float('nan'):.4f} px")
    print(f"calibrate --features: {wall:.1f} s wall, {cpu:.1f} s CPU; of which assessment "
          f"{report['seconds'].get('assessment', float('nan')):.1f} s (calibration "
          f"{report['seconds'].get('calibration', float('nan')):.1f} s)")
    cross = report["cross_validation"]
    record.add("uncertainty", median_px=unc["median_px"], border_band_px=unc["border_px"],
               cross_validation_median_px=cross["median_px"] if cross else None)
    record.add("time", wall_s=wall, cpu_s=cpu, assessment_wall_s=report["seconds"].get("assessment"),
               calibration_wall_s=report["seconds"].get("calibration"))
    record.write()


if __name__ == "__main__":
    main()
