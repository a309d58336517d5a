"""Benchmark of wide-angle and fisheye lenses: the whole pipeline on simulated captures, printed.

    python scripts/bench_fisheye.py DATASET [DATASET ...] [--cache DIR] [--workers N] [--validation none]

Each DATASET is a ``blurcalib synth`` folder (``sharp/``, ``blurry/``, ``pattern.yaml``,
``ground_truth.json``), e.g. ``blurcalib synth --lens fisheye --fov 130 --sharp 10 --blurry 30
--blur-min 3 --blur-max 18``. The pipeline (``blurcalib calibrate``, defaults: ``--parametric
auto``) runs into ``CACHE/<dataset name>/`` (extraction resumable, so a second run only
calibrates again). Printed per dataset:

* **yield**: blurry frames given, their frames in the generic fit, features per kind;
* **the parametric model**: the one chosen, and each model's held-out median error (px)
  (Brown-Conrady's beside it);
* **accuracy against the truth** (px, after the best-fit rotation:
  :func:`blurcalib.sim.evaluate.projection_errors`), median over the generic camera's
  calibrated area, and over its border (pixels within 10 % of the image size of an edge), of
  the parametric camera, the generic camera of the sharp frames alone and the generic camera of
  sharp and blurry frames; each generic camera scores only where it is calibrated, so the two are
  also compared over the area both calibrated (the sharp-only camera's is often smaller: the
  blurry frames reach further into the corners);
* **time**: process CPU time (s) of the calibration, this process and its workers (the machine
  may be shared: wall time is not a product figure).
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import benchrecord
import numpy as np

from blurcalib.calib.sequence import SequenceSettings
from blurcalib.calib.sharp import load_calibration
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.validation import ValidationSettings
from blurcalib.camera.family import as_family
from blurcalib.camera.files import read_generic_yaml
from blurcalib.io.frames import list_frames
from blurcalib.pipeline.run import (
    CALIBRATION_DIR,
    SHARP_ONLY_DIR,
    PipelineError,
    PipelineSettings,
    run_pipeline,
)
from blurcalib.sim.evaluate import pixel_lattice, projection_errors
from blurcalib.sim.truth import load_ground_truth
from blurcalib.target.pattern import load_pattern

COMMON = ", area both calibrated"
"""The label suffix of the generic cameras' figures over the area both calibrated."""
BORDER = 0.10
"""The border band: pixels within this share of the image's width (height) of a vertical
(horizontal) edge."""


def _cpu_seconds() -> float:
    """CPU time (s) of this process and its finished children."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def accuracies(out: Path, truth) -> tuple[float, dict[str, tuple[float, float, float]]]:
    """The share of the image the generic camera calibrated, and each camera of
    ``out/calibration`` against ``truth`` over that area: (median, p95, border median) px; with
    a sharp-only generic camera, also both generic cameras over the area both calibrated
    (labels ending in ``COMMON``) and that area's share (key ``COMMON`` alone, as its first
    figure)."""
    folder = out / CALIBRATION_DIR
    model = truth.camera.model
    px = pixel_lattice(model.width, model.height, 8.0)
    generic_file = folder / "intrinsics0.yaml"
    area = read_generic_yaml(generic_file).in_area(px) if generic_file.is_file() else np.ones(len(px), bool)
    size = np.array([model.width, model.height], dtype=np.float64)
    border = np.any((px < BORDER * size) | (px > (1 - BORDER) * size - 1), axis=1)
    parametric = load_calibration(folder)
    cameras = [(f"parametric ({parametric.model})", parametric.camera)]
    if (folder / SHARP_ONLY_DIR / "intrinsics0.yaml").is_file():
        sharp_only = read_generic_yaml(folder / SHARP_ONLY_DIR / "intrinsics0.yaml")
        cameras.append(("generic, sharp frames", sharp_only))
    if generic_file.is_file():
        cameras.append(("generic, sharp + blurry frames", read_generic_yaml(generic_file)))
    found = {}

    def score(label: str, camera, where: np.ndarray) -> None:
        err = projection_errors(truth.camera, camera, px[where])
        edge = err[border[where]]
        found[label] = (float(np.nanmedian(err)), float(np.nanpercentile(err, 95)),
                        float(np.nanmedian(edge)) if np.isfinite(edge).any() else float("nan"))

    for label, camera in cameras:
        score(label, camera, area)
    if len(cameras) == 3:
        common = area & cameras[1][1].in_area(px)
        found[COMMON] = (float(common.mean()), float("nan"), float("nan"))
        for label, camera in cameras[1:]:
            score(f"{label}{COMMON}", camera, common)
    return float(area.mean()), found


def bench(dataset: Path, cache: Path, workers: int, validation: str, record: benchrecord.BenchRecord) -> None:
    """Run and print one dataset's figures (module docstring)."""
    truth = load_ground_truth(dataset)  # before the long run: a folder without its truth fails now
    pattern = load_pattern(dataset / "pattern.yaml")
    sharp, blurry = list_frames([dataset / "sharp"]), list_frames([dataset / "blurry"])
    out = cache / dataset.name
    cpu = _cpu_seconds()
    try:
        trust = TrustSettings(validation=ValidationSettings(method=validation))
        settings = PipelineSettings(calibration=SequenceSettings(trust=trust), workers=workers)
        report = run_pipeline(sharp, blurry, pattern, out, settings, overwrite=True)
    except PipelineError as exc:
        print(f"{dataset.name}: calibration failed: {exc}")
        return
    cpu = _cpu_seconds() - cpu
    print(f"{dataset.name}: true lens {as_family(truth.camera.model).MODEL}, {len(sharp)} sharp and "
          f"{len(blurry)} blurry frames")
    used = [r for r in report.frames if r.kind == "blurry" and r.used]
    generic = report.generic or {}
    print(f"  yield: {len(used)} of {len(blurry)} blurry frames in the generic fit "
          f"({100 * len(used) / max(len(blurry), 1):.0f} %), {generic.get('observations', 0)} observations")
    choice = report.parametric_choice
    model = report.calibration["model"]
    print(f"  {choice['summary'] if choice and choice['summary'] else f'parametric model {model}'}")
    if report.generic_failure:
        print(f"  {report.generic_failure}")
    if generic:
        print(f"  generic fit: median {generic['median_error_px']:.4f} px (sharp "
              f"{generic['sharp_median_error_px']:.4f}, blurry {generic['blurry_median_error_px']:.4f})")
    share, found = accuracies(out, truth)
    print(f"  accuracy against the truth over the calibrated area ({100 * share:.0f} % of the image; px, "
          "median / p95 / border median):")
    common = found.pop(COMMON, None)
    for label, (median, p95, edge) in found.items():
        if label.endswith(COMMON):
            continue
        print(f"    {label:<36} {median:.4f} / {p95:.4f} / {edge:.4f}")
    if common is not None:
        print(f"  the generic cameras over the area both calibrated ({100 * common[0]:.0f} % of the image):")
        for label, (median, p95, edge) in found.items():
            if label.endswith(COMMON):
                print(f"    {label.removesuffix(COMMON):<36} {median:.4f} / {p95:.4f} / {edge:.4f}")
    print(f"  time: {cpu:.0f} s CPU (extraction and calibration; extraction reused when cached)")
    keys = {"generic, sharp frames": "generic_sharp",
            "generic, sharp + blurry frames": "generic_sharp_blurry",
            f"generic, sharp frames{COMMON}": "common_area_generic_sharp",
            f"generic, sharp + blurry frames{COMMON}": "common_area_generic_sharp_blurry"}
    figures = {f"{keys.get(label, 'parametric')}_{what}": value for label, errors in found.items()
               for what, value in zip(("median_px", "p95_px", "border_median_px"), errors, strict=True)}
    record.add(dataset.name, blurry_frames=len(blurry), blurry_frames_used=len(used), parametric_model=model,
               calibrated_area_pct=100 * share, cpu_s=cpu,
               **({} if common is None else {"common_area_pct": 100 * common[0]}), **figures)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("datasets", nargs="+", type=Path, help="blurcalib synth folders")
    parser.add_argument("--cache", type=Path, default=Path("out") / "bench_fisheye",
                        help="where each dataset's calibrate output goes (default %(default)s)")
    parser.add_argument("--workers", type=int, default=2, help="frames extracted in parallel (default 2)")
    parser.add_argument("--validation", choices=["kfold", "none"], default="kfold",
                        help="the assessment's held-out validation (none: faster; the cameras are the same)")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    for dataset in args.datasets:
        bench(dataset, args.cache, args.workers, args.validation, record)
    record.write()


if __name__ == "__main__":
    main()
