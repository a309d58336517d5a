"""Benchmark of the rolling-shutter model (``docs/rolling-shutter.md``), printed.

    OMP_NUM_THREADS=1 python scripts/bench_rolling_shutter.py [--cache DIR] [--workers 2]

The same 10 sharp (static) and 30 blurry frames (blur 3 to 18 px) of a lens that is not the
simulator's default (:func:`bench_camera`: longer focal length, barrel distortion, its own
deviation field) are rendered twice: read by a rolling shutter whose readout takes 2 exposure
times, and by a global shutter. Each is extracted and calibrated (``blurcalib calibrate --sharp
--blurry``) with ``--rolling-shutter off`` and ``auto``. Printed per run: the generic camera's
distance to the truth over the image after the best-fit rotation (median, p95, max), the blurry
frames used, the readout ratio estimated, and the extraction's accuracy against the row-time
truth. Targets: with the rolling shutter and ``auto``, the camera within 0.03 px (median) of the
truth, >= 90% of the blurry frames used and the ratio within 10% of 2; with the global shutter,
``auto`` finds no rolling shutter and gives the camera of ``off``.

Rendering, extraction and calibration take tens of minutes on 2 cores; every stage is cached in
``--cache`` and reused. The figures are also recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import csv
import math
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import benchrecord
import numpy as np
import torch

from blurcalib.calib.rolling_shutter import RollingShutterSettings
from blurcalib.calib.sequence import BlurryFrame, CalibrationRun, SequenceSettings, calibrate_features
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.validation import ValidationSettings
from blurcalib.camera.parametric import BrownConrady
from blurcalib.io.results import FeatureFlags, read_block_table, read_feature_table
from blurcalib.sim.evaluate import camera_accuracy, evaluate_features
from blurcalib.sim.synth import SynthConfig, write_dataset
from blurcalib.sim.truth import (
    GROUND_TRUTH_FILE,
    DatasetTruth,
    TrueCamera,
    d435i_like_camera,
    load_ground_truth,
)
from blurcalib.target.pattern import StarPattern, load_pattern

READOUT = 2.0


def bench_camera() -> TrueCamera:
    """A 1280 x 720 lens unlike the default: fx ~ 820 px, barrel distortion, another deviation."""
    model = BrownConrady(fx=821.4, fy=819.7, cx=652.3, cy=348.9, k1=-0.118, k2=0.094, p1=-0.0006,
                         p2=0.0009, k3=-0.021, width=1280, height=720)
    return TrueCamera(model, d435i_like_camera(7, deviation_px=0.25).waves)


def config(rolling_shutter: float) -> SynthConfig:
    return SynthConfig(sharp=10, blurry=30, blur_min_px=3.0, blur_max_px=18.0, seed=24,
                       rolling_shutter=rolling_shutter)


def render(folder: Path, rolling_shutter: float, workers: int) -> None:
    if (folder / GROUND_TRUTH_FILE).exists():
        return
    t0 = time.perf_counter()
    write_dataset(folder, config(rolling_shutter), camera=bench_camera(), workers=workers)
    print(f"rendered {folder} in {time.perf_counter() - t0:.0f} s")


def extract(folder: Path, workers: int) -> Path:
    """``blurcalib extract`` of the sharp and the blurry frames into ``folder/extraction`` (cached)."""
    data, out = folder / "data", folder / "extraction"
    for kind in ("sharp", "blurry"):
        if (out / kind / "frames.csv").exists():
            continue
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "blurcalib", "extract", str(data / kind), "--pattern",
                        str(data / "pattern.yaml"), "--out", str(out / kind), "--kind", kind, "--workers",
                        str(workers)], check=True, stdout=subprocess.DEVNULL)
        print(f"extracted {data / kind} in {time.perf_counter() - t0:.0f} s")
    return out


def _named(table, kind: str):
    return replace(table, frame=np.char.add(f"{kind}/", table.frame))


def calibrate(out: Path, pattern: StarPattern, mode: str | float) -> tuple[CalibrationRun, float]:
    """The calibration sequence of ``blurcalib calibrate`` on the extraction, with the rolling
    shutter ``mode`` and without the k-fold validation and cross-validation."""
    sharp = _named(read_feature_table(out / "sharp" / "features.csv"), "sharp")
    sharp_blocks = _named(read_block_table(out / "sharp"), "sharp")
    blocks = _named(read_block_table(out / "blurry"), "blurry")
    with open(out / "blurry" / "frames.csv", newline="", encoding="utf-8") as fh:
        ok = [f"blurry/{r['frame']}" for r in csv.DictReader(fh) if r["status"] == "ok"]
    flags = int(FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME)
    frames = [BlurryFrame(name, blocks=blocks.select(blocks.frame == name), flags=flags) for name in ok]
    settings = SequenceSettings(trust=TrustSettings(validation=ValidationSettings(method="none"),
                                                    cross_validation=False),
                                rolling_shutter=RollingShutterSettings(mode))
    t0 = time.perf_counter()
    run = calibrate_features(sharp, sharp_blocks, frames, pattern, (1280, 720), settings)
    return run, time.perf_counter() - t0


def extraction_accuracy(out: Path, truth: DatasetTruth, pattern: StarPattern,
                        record: benchrecord.BenchRecord, section: str) -> str:
    """Yield and error of the blurry frames' accepted star centres against the row-time truth
    (after each frame's mean offset, the translational ambiguity)."""
    blocks = _named(read_block_table(out / "blurry"), "blurry")
    accepted = blocks.select(blocks.status == "accepted")
    features = accepted.features(pattern.square_length_m, int(FeatureFlags.STAR_CENTRE))
    per_frame = evaluate_features(features, truth, pattern, required_flags=0)
    visible = sum(int(f.block_inside.sum()) for f in truth.frames if f.kind == "blurry")
    err = np.array([f.median_vs_mean for f in per_frame])
    record.add(section, stars_in_image=visible, stars_accepted=len(features),
               accepted_pct=100 * len(features) / max(visible, 1), median_row_time_truth_px=np.median(err))
    return (f"{len(features)} of {visible} blurry-frame stars in the image accepted "
            f"({100 * len(features) / max(visible, 1):.0f}%), median error to the row-time truth "
            f"{np.median(err):.3f} px (median of the frames' medians)")


def report(label: str, run: CalibrationRun, seconds: float, truth: TrueCamera,
           record: benchrecord.BenchRecord) -> dict:
    acc = camera_accuracy(truth, run.generic.model)
    rs = run.rolling_shutter
    used = len(run.generic.blurry_frames)
    ratio = "" if rs is None else f"; r = {rs.ratio:.3f} +- {rs.sigma:.3f} ({rs.message})"
    print(f"{label}: generic camera to the truth median {acc.median:.4f} px, p95 {acc.p95:.4f}, max "
          f"{acc.max:.4f}; blurry frames used {used}/30{ratio}; {seconds:.0f} s")
    record.add(label, blurry_frames=30, blurry_frames_used=used, camera_median_px=acc.median,
               camera_p95_px=acc.p95, camera_max_px=acc.max, readout_ratio=None if rs is None else rs.ratio,
               readout_ratio_sigma=None if rs is None else rs.sigma,
               model_applied=rs is not None and rs.applied, calibration_wall_s=seconds)
    return {"median": acc.median, "used": used, "ratio": math.nan if rs is None else rs.ratio,
            "applied": rs is not None and rs.applied}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/blurcalib_bench_rolling_shutter"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--render-only", action="store_true", help=argparse.SUPPRESS)
    benchrecord.add_option(ap)
    args = ap.parse_args()
    record = benchrecord.start(__file__, args)
    for name, ratio in (("rolling", READOUT), ("global", 0.0)):
        render(args.cache / name / "data", ratio, args.workers)
    if args.render_only:
        return 0
    torch.set_num_threads(1)
    print("(torch single-threaded)")
    results = {}
    for name in ("rolling", "global"):
        folder = args.cache / name
        truth = load_ground_truth(folder / "data")
        pattern = load_pattern(folder / "data" / "pattern.yaml")
        out = extract(folder, args.workers)
        accuracy = extraction_accuracy(out, truth, pattern, record, f"{name} shutter, extraction")
        print(f"== {name} shutter: {accuracy}")
        for mode in ("off", "auto"):
            run, seconds = calibrate(out, pattern, mode)
            label = f"{name} shutter, --rolling-shutter {mode}"
            results[name, mode] = report(label, run, seconds, truth.camera, record)
    auto, g_off, g_auto = results["rolling", "auto"], results["global", "off"], results["global", "auto"]

    def verdict(ok: bool) -> str:
        return "met" if ok else "MISSED"

    print(f"targets: rolling shutter with auto: camera median {auto['median']:.4f} <= 0.03 px "
          f"({verdict(auto['median'] <= 0.03)}); blurry frames used {auto['used']}/30 >= 27 "
          f"({verdict(auto['used'] >= 27)}); r {auto['ratio']:.3f} within 10% of {READOUT:g} "
          f"({verdict(abs(auto['ratio'] - READOUT) <= 0.1 * READOUT)}); global shutter with auto: model "
          f"not applied ({verdict(not g_auto['applied'])}), camera {g_auto['median']:.4f} px against "
          f"off's {g_off['median']:.4f} px")
    record.write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
