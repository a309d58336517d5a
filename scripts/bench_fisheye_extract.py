"""Benchmark of feature extraction through wide-angle and fisheye lenses: yield and accuracy
against ground truth, before and after the lens-bias correction of the block centres.

    python scripts/bench_fisheye_extract.py DATASET [DATASET ...] [--cache DIR]
        [--results DIR [DIR ...]]

Each ``DATASET`` is a simulated folder (``blurcalib synth --out DIR``, with
``ground_truth.json``), e.g. ``blurcalib synth --lens fisheye --fov 130 --sharp 2 --blurry 6
--blur-min 3 --blur-max 18 --seed 5`` beside the same of ``--lens standard`` (the mild lens, the
reference). Every frame is extracted (``ExtractSettings.auto()``); its accepted blocks' star
centres are compared with the truth (the time-averaged star positions):

* yield: accepted features over the visible stars;
* raw: median distance to the truth (px);
* pose fit: median residual after a least-squares pose under the true camera (the features'
  pose consistency; a blurry frame's motion adds its own share);

each as extracted and after :func:`blurcalib.calib.lens_bias.correct_blocks` with the true lens
model (the lens deviation field, a few tenths of a pixel, is left to the calibration), for sharp
and blurry frames, and by angle off the optical axis. CPU time (``time.process_time``) of the
extraction and of the correction, per frame.

``--cache DIR`` keeps each frame's extracted blocks (``DIR/<dataset>/<frame>.csv|.npz``) so that
a second run measures the correction alone; ``--results`` takes each dataset's blocks from a
``blurcalib extract`` results folder instead (``blocks.csv`` and ``psfs.npz``, one folder per
dataset, in the same order). The figures are also recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import benchrecord
import cv2
import numpy as np

from blurcalib.calib.lens_bias import correct_blocks
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.extract.frame import ExtractSettings, extract_frame
from blurcalib.io.results import BlockTable, read_block_files, read_block_table, write_blocks
from blurcalib.sim.evaluate import refit_pose
from blurcalib.sim.truth import DatasetTruth, FrameTruth, load_ground_truth
from blurcalib.target.pattern import StarPattern, load_pattern

BANDS = ((0.0, 40.0), (40.0, 70.0), (70.0, 90.0), (90.0, 101.0))
"""Angle bands (deg off the optical axis) of the per-angle figures."""


@dataclass
class Tally:
    """Found and visible stars and the errors (px) of one kind of frame (or one angle band)."""

    found: int = 0
    visible: int = 0
    raw: list[np.ndarray] = field(default_factory=list)
    fit: list[np.ndarray] = field(default_factory=list)

    def figures(self) -> dict[str, float]:
        """The figures of :meth:`line` for the record."""
        raw = np.concatenate(self.raw) if self.found else np.zeros(0)
        fit = np.concatenate(self.fit) if self.found else np.zeros(0)
        fitted = np.isfinite(fit).any()
        return {"found": self.found, "visible": self.visible,
                "yield_pct": 100.0 * self.found / max(self.visible, 1),
                "raw_median_px": float(np.median(raw)) if raw.size else float("nan"),
                "pose_fit_median_px": float(np.nanmedian(fit)) if fitted else float("nan"),
                "pose_fit_p90_px": float(np.nanpercentile(fit, 90)) if fitted else float("nan")}

    def line(self) -> str:
        share = 100.0 * self.found / max(self.visible, 1)
        text = f"{self.found:5d}/{self.visible:5d} ({share:5.1f} %)"
        if self.found:
            raw, fit = np.concatenate(self.raw), np.concatenate(self.fit)
            text += (f"  raw {np.median(raw):.4f}  pose fit {np.nanmedian(fit):.4f}"
                     f" (p90 {np.nanpercentile(fit, 90):.4f})")
        return text


def extracted_blocks(data: Path, name: str, pattern: StarPattern, cache: Path | None
                     ) -> tuple[BlockTable, float]:
    """The accepted blocks of frame ``name`` and the extraction's CPU time (s; NaN when cached)."""
    stem = cache / data.name / name.replace("/", "_") if cache is not None else None
    if stem is not None and stem.with_suffix(".npz").exists():
        return read_block_files(stem.with_suffix(".csv"), stem.with_suffix(".npz")), float("nan")
    image = cv2.imread(str(data / name), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    start = time.process_time()
    result = extract_frame(image, pattern, name, ExtractSettings.auto())
    seconds = time.process_time() - start
    blocks = result.blocks.select(result.blocks.accepted)
    if stem is not None:
        stem.parent.mkdir(parents=True, exist_ok=True)
        write_blocks(stem.with_suffix(".csv"), stem.with_suffix(".npz"), blocks)
    return blocks, seconds


def errors(truth: DatasetTruth, frame: FrameTruth, pattern: StarPattern, blocks: BlockTable
           ) -> tuple[np.ndarray, np.ndarray]:
    """``(N,)`` px distances of the block centres to the truth and to the refitted pose's
    projections (NaN when the frame has under 6 features or is off by a pixel)."""
    ids, xy = blocks.feature_id, blocks.centre
    raw = np.linalg.norm(xy - frame.mean[ids], axis=1)
    fit = np.full(len(ids), np.nan)
    if len(ids) >= 6 and np.median(raw) < 1.0:
        points = pattern.points_3d(ids)
        pose = refit_pose(truth.camera, points, xy, frame.pose)
        fit = np.linalg.norm(truth.camera.project(pose.transform(points)) - xy, axis=1)
    return raw, fit


def bench(data: Path, record: benchrecord.BenchRecord, cache: Path | None, results: Path | None = None
          ) -> None:
    truth = load_ground_truth(data)
    pattern = load_pattern(data / "pattern.yaml")
    lens = truth.camera.model
    extracted = read_block_table(results) if results is not None else None
    tallies: dict[tuple[str, str, tuple[float, float] | None], Tally] = {}
    cpu: dict[str, list[float]] = {"extract": [], "correct": []}
    for frame in truth.frames:
        if extracted is not None:
            blocks = extracted.select(extracted.accepted & (extracted.frame == frame.name))
            seconds = float("nan")
        else:
            blocks, seconds = extracted_blocks(data, frame.name, pattern, cache)
        cpu["extract"].append(seconds)
        start = time.process_time()
        corrected = correct_blocks(blocks, lens)
        cpu["correct"].append(time.process_time() - start)
        camera_points = frame.pose.transform(pattern.points_3d())
        angle = np.degrees(np.arccos(camera_points[:, 2] / np.linalg.norm(camera_points, axis=1)))
        found = np.zeros(len(frame.visible), dtype=bool)
        found[blocks.feature_id] = True
        for label, table in (("as extracted", blocks), ("lens-bias corrected", corrected)):
            raw, fit = errors(truth, frame, pattern, table)
            for band in (None, *BANDS):
                in_band = frame.visible.copy()
                if band is not None:
                    in_band &= (angle >= band[0]) & (angle < band[1])
                t = tallies.setdefault((label, frame.kind, band), Tally())
                t.found += int(found[in_band].sum())
                t.visible += int(in_band.sum())
                rows = in_band[blocks.feature_id]
                t.raw.append(raw[rows])
                t.fit.append(fit[rows])
    lens_text = f"{type(lens).__name__}, {field_deg(lens):.0f} deg horizontal, {len(truth.frames)} frames"
    title = f"{data.name}: {lens_text}"
    print(f"{data}: {lens_text}")
    for label in ("as extracted", "lens-bias corrected"):
        print(f"  {label}:")
        for kind in ("sharp", "blurry"):
            if (label, kind, None) not in tallies:
                continue
            print(f"    {kind:6s} {tallies[label, kind, None].line()}")
            record.add(f"{title}, {kind}, {label}", **tallies[label, kind, None].figures())
            for band in BANDS:
                t = tallies[label, kind, band]
                if t.visible:
                    print(f"      {band[0]:3.0f}-{band[1]:3.0f} deg {t.line()}")
    extract = np.array(cpu["extract"])
    timing = f"median {np.nanmedian(extract):.1f} s" if np.isfinite(extract).any() else "cached"
    print(f"  CPU per frame: extraction {timing}, correction median {np.median(cpu['correct']):.3f} s")
    extraction = float(np.nanmedian(extract)) if np.isfinite(extract).any() else float("nan")
    record.add(f"{title}, CPU per frame (shared machine)", extraction_cpu_s=extraction,
               correction_cpu_s=float(np.median(cpu["correct"])))


def field_deg(lens: BrownConrady | ParametricCamera) -> float:
    """The horizontal field (deg): twice the angle off the axis of the image's left edge."""
    edge = np.array([[-0.5, lens.cy]])
    if isinstance(lens, BrownConrady):
        return 2.0 * float(np.degrees(np.arctan(abs(lens.unproject(edge)[0, 0]))))
    return 2.0 * float(np.degrees(np.arccos(np.clip(lens.unproject(edge)[0, 2], -1.0, 1.0))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", type=Path, help="simulated dataset folders")
    parser.add_argument("--cache", type=Path, default=None, help="folder for the extracted blocks")
    parser.add_argument("--results", type=Path, nargs="+", default=None,
                        help="each dataset's blurcalib extract results folder, in the datasets' order")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    if args.results is not None and len(args.results) != len(args.datasets):
        parser.error(f"--results names {len(args.results)} folders for {len(args.datasets)} datasets")
    record = benchrecord.start(__file__, args)
    print("CPU times on a shared machine; accuracy and yield against the simulated truth.")
    for k, data in enumerate(args.datasets):
        bench(data, record, args.cache, args.results[k] if args.results is not None else None)
    record.write()


if __name__ == "__main__":
    main()
