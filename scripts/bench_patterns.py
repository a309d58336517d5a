"""Benchmark of pattern-dependent feature bias: one camera, two patterns, the same poses.

    python scripts/bench_patterns.py [--cache DIR] [--sim-frames 3] [--skip-real] [--skip-sim] [--record FILE]

1. The real fixture frames (``real_star16`` and ``real_star8_1``: the 16-segment star and the
   four-segment checkerboard shown in turn on one monitor, 8 frames each at the same poses):
   both extracted as sharp frames, each set calibrated (Brown-Conrady), and printed:
   * the two cameras' difference: focal lengths and principal point, and the checkerboard
     camera's projection of the star camera's rays over the image (median, p95, the focal-length
     scale at the corner, and the shape after the best-fit affine part);
   * the feature-level cross-pattern residual (:func:`blurcalib.calib.cross_pattern.check_patterns`,
     what ``blurcalib compare`` prints): the same target point in the same frame from the two
     patterns, through one homography per frame in the star camera's undistorted pixels, binned by
     radius with a z-score, and the verdict (systematic error or not);
   * the same for blurcalib's star centres against the reference detector's
     (``features_10px.bin``, frames 0-3) on the same star frames.
   Target: the radial component within 0.01 px at every radius.
   Then one camera from both patterns (``blurcalib calibrate --features A --pattern A.yaml
   --features B --pattern B.yaml``, :func:`blurcalib.pipeline.patterns.run_from_feature_sets`, the
   k-fold validation from 8 frames so that each pattern alone is validated too): the frames used,
   the held-out error on each pattern's frames of the joint camera and of each pattern's own,
   and the two patterns' generic cameras compared against their predicted uncertainty.
   Target: within 1.5 x the uncertainty.
2. A simulation with realistic optics (:mod:`blurcalib.sim.optics`): both patterns rendered at the
   same poses facing the camera (:mod:`blurcalib.sim.captures`) through an asymmetric PSF that
   grows with the field (a comatic lobe along the radius, radial astigmatism), extracted as sharp
   frames: each pattern's features (corrected for the block homographies' lens bias with the true
   camera) against the PSF-centroid truth (median, radial error by radius) and the cross-pattern
   residual. Target: both patterns within 0.01 px of the truth.

Extractions and renders are cached in ``--cache`` (default ``out/bench_patterns``), so a second
run prints at once. The figures are recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import itertools
import os
from pathlib import Path

import benchrecord
import cv2
import numpy as np

from blurcalib.calib.cross_pattern import (
    CrossResiduals,
    PatternCheck,
    check_patterns,
    cross_residuals,
    radial_profile,
)
from blurcalib.calib.lens_bias import correct_features
from blurcalib.calib.sequence import SequenceSettings
from blurcalib.calib.sharp import Calibration, calibrate_sharp
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.validation import ValidationSettings
from blurcalib.extract.frame import ExtractSettings, extract_frame
from blurcalib.io.refformat import read_ref_dataset, ref_feature_table
from blurcalib.io.results import FeatureTable, read_feature_table, write_features
from blurcalib.pipeline.patterns import pattern_lines, run_from_feature_sets
from blurcalib.pipeline.run import PipelineSettings
from blurcalib.runs.folder import extract_to_folder
from blurcalib.sim.captures import facing_poses, render_frame
from blurcalib.sim.evaluate import projection_error_vectors
from blurcalib.sim.optics import FieldPsf, Optics
from blurcalib.sim.synth import Simulator, SynthConfig
from blurcalib.sim.truth import TrueCamera
from blurcalib.target.pattern import StarPattern, layout_pattern, load_pattern

FIXTURES = Path(os.environ.get("BLURCALIB_FIXTURES") or Path(__file__).resolve().parents[2] / "shared"
                / "fixtures")
"""The reference fixtures (``BLURCALIB_FIXTURES``, default ``../shared/fixtures`` beside the checkout)."""
EDGES = np.array([0.0, 100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 750.0])
"""Radius bins (px) of the printed profiles."""
SIM_PSF = FieldPsf(sigma=0.8, growth=0.6, astig=0.3, coma=(-0.6, 3.0), lobe_weight=0.25, lobe_sigma=1.5)
"""The simulated lens: a lobe pointing inwards in the middle of the field and outwards beyond
45 % of the half diagonal (as the real fixture frames' fitted PSFs skew), 0.4 px of centroid
shift at the corners."""


def _profile(res: CrossResiduals, title: str) -> dict[str, float]:
    """Print the residual's profile; its figures: median and radial mean per bin (px)."""
    print(f"{title}: {int(res.inlier.sum())} matches in {len(set(res.frame.tolist()))} frames, median "
          f"{res.median_px:.4f} px; radial and tangential components by radius:")
    profile = radial_profile(res, EDGES)
    for line in profile.rows():
        print("   " + line)
    return {"matches": int(res.inlier.sum()), "median_px": res.median_px, **_bins(profile.radial)}


def _bins(radial: np.ndarray) -> dict[str, float]:
    """Radial means by radius bin as record figures (``radial_<lo>_<hi>_px``)."""
    return {f"radial_{lo:.0f}_{hi:.0f}_px": float(v) for (lo, hi), v in
            zip(itertools.pairwise(EDGES), radial, strict=True)}


def _check(check: PatternCheck) -> dict[str, float]:
    print("checkerboard - star features (blurcalib compare):")
    for line in check.lines():
        print("   " + line)
    return {"matches": check.matches, "median_px": check.median_px, "systematic": check.systematic,
            "worst_radial_px": check.worst_radial_px, **_bins(check.profile.radial)}


def _extracted(name: str, cache: Path) -> tuple[StarPattern, FeatureTable]:
    src = FIXTURES / name
    pattern = load_pattern(src / "pattern.yaml")
    frames = sorted((src / "images").glob("*.png"), key=lambda p: int(p.stem))
    extract_to_folder(frames, pattern, cache / name, ExtractSettings.sharp())
    table = read_feature_table(cache / name / "features.csv")
    ok = len(set(table.frame.tolist()))
    print(f"{name}: {ok} of {len(frames)} frames extracted, {len(table)} features")
    return pattern, table


def _cameras(star: Calibration, checker: Calibration, pixels: np.ndarray) -> dict[str, float]:
    """The two cameras and their difference where the features are (``pixels (N, 2)``)."""
    a, b = star.camera, checker.camera
    print(f"star camera:    fx {a.fx:.2f} fy {a.fy:.2f} cx {a.cx:.2f} cy {a.cy:.2f}, median reprojection "
          f"{star.median_error:.4f} px")
    print(f"checker camera: fx {b.fx:.2f} fy {b.fy:.2f} cx {b.cx:.2f} cy {b.cy:.2f}, median reprojection "
          f"{checker.median_error:.4f} px")
    vec = projection_error_vectors(TrueCamera(a), b, pixels)
    centre = np.array([a.cx, a.cy])
    design = np.column_stack([np.ones(len(pixels)), pixels - centre])
    coef, *_ = np.linalg.lstsq(design, vec, rcond=None)  # e ~ t + A (x - c): A's mean diagonal a scale
    shape = np.linalg.norm(vec - design @ coef, axis=1)
    scale = 100 * 0.5 * (coef[1, 0] + coef[2, 1])
    print(f"checker - star: focal lengths {100 * (b.fx / a.fx - 1):+.3f} % / "
          f"{100 * (b.fy / a.fy - 1):+.3f} %; at the {len(pixels)} feature positions the checkerboard "
          "camera projects the star camera's rays "
          f"{np.median(np.linalg.norm(vec, axis=1)):.3f} px away (median; scale {scale:+.3f} %, shape "
          f"{np.median(shape):.3f} px)")
    return {"focal_x_pct": 100 * (b.fx / a.fx - 1), "focal_y_pct": 100 * (b.fy / a.fy - 1),
            "projection_median_px": float(np.median(np.linalg.norm(vec, axis=1))), "scale_pct": scale,
            "shape_median_px": float(np.median(shape))}


def real(cache: Path, record: benchrecord.BenchRecord) -> None:
    print("== real fixture frames: the 16-segment star and the checkerboard at the same poses ==")
    star_pattern, star = _extracted("real_star16", cache)
    checker_pattern, checker = _extracted("real_star8_1", cache)
    size = (1280, 720)
    cal_star = calibrate_sharp(star, star_pattern, size)
    cal_checker = calibrate_sharp(checker, checker_pattern, size)
    record.add("real cameras", **_cameras(cal_star, cal_checker, np.column_stack([star.x, star.y])))
    record.add("real features, checkerboard - star",
               **_check(check_patterns(star, checker, cal_star.camera, cal_checker.camera, edges=EDGES)))
    ref = read_ref_dataset(FIXTURES / "real_star16" / "features_10px.bin")
    reference = ref_feature_table(ref, star_pattern)
    reference = reference.select(np.isin(reference.frame, np.unique(star.frame)))
    record.add("real star frames, blurcalib - reference detector",
               **_profile(cross_residuals(reference, star, cal_star.camera),
                          "blurcalib - reference detector, star frames"))
    joint(cache, record, star_pattern, checker_pattern)


def joint(cache: Path, record: benchrecord.BenchRecord, star: StarPattern, checker: StarPattern) -> None:
    """One camera from both patterns' cached features, and the cross-pattern check of the cameras."""
    print("== one camera from both patterns (calibrate --features star --features checkerboard) ==")
    validation = ValidationSettings(min_frames=8)
    settings = PipelineSettings(calibration=SequenceSettings(trust=TrustSettings(validation=validation)))
    report = run_from_feature_sets([(cache / "real_star16" / "features.csv", star),
                                    (cache / "real_star8_1" / "features.csv", checker)], cache / "joint",
                                   settings, (1280, 720), overwrite=True)
    used = {k: report.counts[k].get("used", 0) for k in ("sharp", "blurry")}
    total = sum(sum(c.values()) for c in report.counts.values())
    generic = report.generic or {}
    print(f"joint camera: {used['sharp'] + used['blurry']} of {total} frames used, "
          f"{generic.get('observations', 'n/a')} observations, median reprojection "
          f"{generic.get('median_error_px', float('nan')):.4f} px")
    for line in pattern_lines(report.patterns):
        print(line)
    doc = report.patterns or {}
    held = doc.get("held_out", {})
    figures: dict[str, float | int | bool | None] = {"frames_used": used["sharp"] + used["blurry"],
                                                     "frames": total}
    for label, name in (("pattern1", "star"), ("pattern2", "checker")):
        for what in ("joint", "alone"):
            score = held.get(label, {}).get(what)
            figures[f"held_out_{name}_{what}_px"] = None if score is None else score["median_px"]
    cam = doc.get("cameras", {}).get("pattern2 - pattern1", {})
    for key in ("median_px", "p90_px", "rms_px", "predicted_rms_px", "ratio", "scale_pct", "shape_median_px",
                "systematic"):
        figures[f"cameras_{key}"] = cam.get(key)
    record.add("real, one camera from both patterns", **figures)


def _sim_features(pattern: StarPattern, optics: Optics, frames: int, cache: Path, seed: int
                  ) -> tuple[FeatureTable, np.ndarray, np.ndarray, TrueCamera]:
    """Rendered (cached) and extracted frames of ``pattern``: features (corrected for the block
    homographies' lens bias, :mod:`blurcalib.calib.lens_bias`), and per feature the projection and
    PSF-centroid truths ``(N, 2)``."""
    sim = Simulator(SynthConfig(sharp=0, blurry=0, seed=seed, noise_sigma=1.0), pattern, optics=optics)
    poses = facing_poses(sim.camera, pattern, frames, np.random.default_rng(seed))
    folder = cache / f"sim_{pattern.num_star_segments}_s{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    tables, proj, cen = [], [], []
    for i, pose in enumerate(poses):
        image_path, truth_path, feat_path = (folder / f"{i}.png", folder / f"{i}.truth.npz",
                                             folder / f"{i}.corrected.features.csv")
        if not truth_path.exists():
            image, truth = render_frame(sim, pose, np.random.default_rng([seed, i]), optics)
            cv2.imwrite(str(image_path), image)
            np.savez(truth_path, projection=truth.projection, centroid=truth.centroid)
        if not feat_path.exists():
            result = extract_frame(cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE), pattern, f"{i}.png",
                                   ExtractSettings.sharp())
            # the block homographies' lens bias, corrected with the true camera's Brown-Conrady part
            write_features(feat_path, correct_features(result.features, result.blocks, sim.camera.model))
        table = read_feature_table(feat_path)
        z = np.load(truth_path)
        tables.append(table)
        proj.append(z["projection"][table.feature_id])
        cen.append(z["centroid"][table.feature_id])
    return FeatureTable.concat(tables), np.concatenate(proj), np.concatenate(cen), sim.camera


def simulated(cache: Path, frames: int, record: benchrecord.BenchRecord, seed: int = 7) -> None:
    print(f"== simulation: {frames} sharp frames per pattern at the same poses, asymmetric field-varying "
          "PSF ==")
    optics = Optics(psf=SIM_PSF)
    found = {}
    for segments in (16, 4):
        pattern = layout_pattern(num_star_segments=segments)
        table, proj, cen, camera = _sim_features(pattern, optics, frames, cache, seed)
        xy = np.column_stack([table.x, table.y])
        centre = np.array([(camera.model.width - 1) / 2, (camera.model.height - 1) / 2])
        d = proj - centre
        r = np.linalg.norm(d, axis=1)
        radial = np.sum((xy - cen) * d / np.maximum(r, 1e-9)[:, None], axis=1)
        bins = " ".join(f"{lo:.0f}-{hi:.0f}: {radial[(r >= lo) & (r < hi)].mean():+.4f}"
                        for lo, hi in itertools.pairwise(EDGES) if ((r >= lo) & (r < hi)).sum() > 5)
        print(f"{segments:2d} segments: {len(table)} features; against the PSF-centroid truth median "
              f"{np.median(np.linalg.norm(xy - cen, axis=1)):.4f} px, against the projection "
              f"{np.median(np.linalg.norm(xy - proj, axis=1)):.4f} px; radial error (px) by radius: {bins}")
        found[segments] = table
        record.add(f"simulated {segments} segments against the PSF-centroid truth", features=len(table),
                   median_px=float(np.median(np.linalg.norm(xy - cen, axis=1))),
                   projection_median_px=float(np.median(np.linalg.norm(xy - proj, axis=1))),
                   **_bins(np.array([radial[(r >= lo) & (r < hi)].mean() if ((r >= lo) & (r < hi)).sum() > 5
                                     else np.nan for lo, hi in itertools.pairwise(EDGES)])))
    record.add("simulated features, checkerboard - star",
               **_profile(cross_residuals(found[16], found[4], camera.model),
                          "checkerboard - star features (simulated)"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", type=Path, default=Path("out") / "bench_patterns")
    parser.add_argument("--sim-frames", type=int, default=3)
    parser.add_argument("--skip-real", action="store_true")
    parser.add_argument("--skip-sim", action="store_true")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    if not args.skip_real:
        real(args.cache, record)
    if not args.skip_sim:
        simulated(args.cache, args.sim_frames, record)
    record.write()


if __name__ == "__main__":
    main()
