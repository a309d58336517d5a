"""Benchmark of the calibration pipeline: the figures of the "features to a calibrated camera"
stage, printed.

    python scripts/bench_calibrate.py [--sharp 20] [--blurry 24] [--skip-simulated]

1. The real fixture frames (8 sharp frames of the reference target on a monitor): Brown-Conrady
   calibration from blurcalib's own sharp-frame features; target: median reprojection error
   <= 0.1 px.
2. A simulated sequence run through the whole pipeline (``blurcalib calibrate``): the aligned
   blurry-frame features against the true camera with each frame's pose refitted (the figure
   measures feature error, not pose); target: median <= 0.06 px.
3. The paper's Table 1 is printed by ``blurcalib experiment alignment``.

Each part prints the frames it used (the yield) beside accuracy and time; the figures are also
recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import benchrecord
import numpy as np
import torch

from blurcalib.calib.sequence import SequenceSettings
from blurcalib.calib.sharp import calibrate_sharp
from blurcalib.extract.frame import ExtractSettings, extract_frame
from blurcalib.growth.quality import QualitySettings
from blurcalib.io.frames import load_frame
from blurcalib.io.results import FeatureTable, read_feature_table
from blurcalib.pipeline.run import PipelineSettings, run_pipeline
from blurcalib.sim.evaluate import evaluate_features
from blurcalib.sim.synth import SynthConfig, write_dataset
from blurcalib.sim.truth import load_ground_truth
from blurcalib.target.pattern import load_pattern

FIXTURES = Path(os.environ.get("BLURCALIB_FIXTURES") or Path(__file__).resolve().parents[2] / "shared"
                / "fixtures")
"""The reference fixtures (``BLURCALIB_FIXTURES``, default ``../shared/fixtures`` beside the checkout)."""
REAL = FIXTURES / "real_star16"


def real_fixture(record: benchrecord.BenchRecord) -> None:
    print("== real fixture frames: sharp-set calibration ==")
    pattern = load_pattern(REAL / "pattern.yaml")
    features = []
    paths = sorted((REAL / "images").glob("*.png"))
    start, c0 = time.perf_counter(), time.process_time()
    for path in paths:
        result = extract_frame(load_frame(path), pattern, path.name, ExtractSettings.sharp())
        features.append(result.features)
        print(f"{path.name}: {result.status.value}, {len(result.features)} features")
    extracted, c1 = time.perf_counter(), time.process_time()
    calibration = calibrate_sharp(FeatureTable.concat(features), pattern, (1280, 720))
    done = time.perf_counter()
    print(f"calibration of {calibration.num_frames} of {len(paths)} frames: median "
          f"{calibration.median_error:.4f} px, RMS {calibration.rms_error:.4f} px (extraction "
          f"{extracted - start:.1f} s wall, {(c1 - c0) / len(paths):.2f} s CPU per frame; calibration "
          f"{done - extracted:.1f} s)")
    record.add("real fixture frames, sharp-set calibration", frames=len(paths),
               frames_used=calibration.num_frames, features=sum(len(f) for f in features),
               median_px=calibration.median_error, rms_px=calibration.rms_error,
               extraction_cpu_s_per_frame=(c1 - c0) / len(paths), calibration_wall_s=done - extracted)


def simulated(sharp: int, blurry: int, record: benchrecord.BenchRecord) -> None:
    print(f"== simulated sequence: {sharp} sharp + {blurry} blurry frames, whole pipeline ==")
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        start = time.perf_counter()
        write_dataset(data, SynthConfig(sharp=sharp, blurry=blurry, seed=3), workers=2)
        simulated_at = time.perf_counter()
        pattern = load_pattern(data / "pattern.yaml")
        report = run_pipeline(sorted((data / "sharp").glob("*.png")),
                              sorted((data / "blurry").glob("*.png")), pattern, Path(tmp) / "out",
                              PipelineSettings(calibration=SequenceSettings(
                                                  quality=QualitySettings(min_sigma_major=1.0)), workers=2))
        ran_at = time.perf_counter()
        print(f"simulation {simulated_at - start:.0f} s, pipeline {ran_at - simulated_at:.0f} s; "
              f"sharp calibration median {report.calibration['median_error_px']:.4f} px; "
              f"blurry frames {report.counts}")
        table = read_feature_table(Path(tmp) / "out" / "features.csv")
        acc = evaluate_features(table, load_ground_truth(data), pattern)
        med = np.array([a.median for a in acc])
        print(f"aligned blurry features vs the true camera: median over {len(acc)} of {blurry} blurry frames "
              f"{np.median(med):.4f} px (per frame {med.min():.4f} to {med.max():.4f} px)")
        record.add("simulated sequence, whole pipeline", sharp_frames=sharp, blurry_frames=blurry,
                   blurry_frames_evaluated=len(acc), sharp_median_px=report.calibration["median_error_px"],
                   blurry_feature_median_px=np.median(med), simulation_wall_s=simulated_at - start,
                   pipeline_wall_s=ran_at - simulated_at)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sharp", type=int, default=20)
    parser.add_argument("--blurry", type=int, default=24)
    parser.add_argument("--skip-simulated", action="store_true")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    torch.set_num_threads(1)  # per-process figures, as the command line's workers compute
    real_fixture(record)
    if not args.skip_simulated:
        simulated(args.sharp, args.blurry, record)
    record.write()


if __name__ == "__main__":
    main()
