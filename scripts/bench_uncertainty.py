"""Benchmark of the generic camera's projection uncertainty against the true error, printed.

    python scripts/bench_uncertainty.py [--sharp 20] [--blurry 60] [--seed 0] [--device cpu]

Simulation: ``blurcalib experiment generic``'s (``blurcalib.paper.generic``): the 1280 x 720
camera with its 0.3 px non-parametric deviation, 20 sharp frames thin at the borders (0.02 px
noise), 60 blurry frames anywhere (0.012 px noise, 10 % at 4x, an unknown shift each), the target
points nominal. Fits (b) the generic camera of the sharp frames and (c) that of the sharp and
blurry frames (free shifts), on the experiment's common calibrated area and 25 px grid.

For each fit: the true error after the best-fit rotation
(:func:`blurcalib.sim.evaluate.projection_error_vectors`) on the uncertainty's lattice, the
predicted 1-sigma (:func:`blurcalib.calib.uncertainty.projection_uncertainty`), their RMS and the
ratio (target 0.5-2), the same split into the border band (64 px from the edge) and the inner
area, the focal-scale part of the error field (:func:`blurcalib.sim.evaluate.camera_accuracy`'s
``scale_px``) against its predicted 1-sigma, the time of ``projection_uncertainty``, and the
RMS sigma and ratio with other ``prior_scale`` values (the pipeline's is
``TrustSettings().prior_scale``). Then the border-band sigma of (c) over
(b) (target <= 0.6). Timings depend on the machine's load
(torch single-threaded). The frames and observations each fit kept (the yield) are printed beside;
the figures are also recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import time

import benchrecord
import numpy as np
import torch

from blurcalib.calib.bundle import BundleSettings
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.uncertainty import BORDER_PX, projection_uncertainty
from blurcalib.camera.generic import calibrated_area, fit_to_rays
from blurcalib.paper import generic as experiment
from blurcalib.sim.evaluate import camera_accuracy, projection_error_vectors
from blurcalib.sim.truth import d435i_like_camera
from blurcalib.target.pattern import layout_pattern

PRIOR_SCALES = (1.0, 0.3, 0.15)
"""Other ``prior_scale`` values printed for comparison (``calibrate`` uses ``PRIOR_SCALE``)."""


PRIOR_SCALE = TrustSettings().prior_scale


def _rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(v ** 2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sharp", type=int, default=20)
    parser.add_argument("--blurry", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    torch.set_num_threads(1)
    settings = experiment.GenericSettings(sharp=args.sharp, blurry=args.blurry, seed=args.seed)
    truth = d435i_like_camera(settings.seed, settings.deviation_px)
    W, H = truth.model.width, truth.model.height
    frames = experiment.simulate_frames(settings, layout_pattern(), truth)
    sharp = [f for f in frames if f.kind == "sharp"]
    param = experiment.calibrate_parametric(sharp, W, H)
    area = calibrated_area(np.concatenate([f.observed for f in frames]), W, H)
    initial = fit_to_rays(param.pixel_to_ray, W, H, area=area, cell_px=settings.cell_px)
    bundle = BundleSettings(device=args.device)
    print(f"simulated: {len(sharp)} sharp frames ({settings.sharp_noise_px} px noise), "
          f"{len(frames) - len(sharp)} blurry frames ({settings.blurry_noise_px} px, "
          f"{settings.blurry_tail:.0%} at 4x); grid {initial.grid_width} x {initial.grid_height}")
    bands = {}
    for name, subset, free in (("(b) generic, sharp", sharp, False),
                               ("(c) generic, sharp + blurry", frames, True)):
        res = experiment.generic_fit(initial, param, subset, shift_free=free, settings=bundle)
        t0, c0 = time.perf_counter(), time.process_time()
        unc = projection_uncertainty(res, prior_scale=PRIOR_SCALE)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        px = np.column_stack([unc.x, unc.y])
        err = np.linalg.norm(projection_error_vectors(truth, res.model, px), axis=1)
        ok = np.isfinite(err)
        edge = np.minimum.reduce([unc.x + 0.5, unc.y + 0.5, W - 0.5 - unc.x, H - 0.5 - unc.y])
        band = ok & (edge < BORDER_PX)
        inner = ok & ~band
        ratio = _rms(err[ok]) / _rms(unc.sigma_px[ok])
        bands[name] = unc.border_band()
        print(f"{name}: {len(res.poses)} of {len(subset)} frames, {int(res.inlier.sum())} of "
              f"{len(res.inlier)} observations kept, "
              f"{unc.sigma_px.size} lattice pixels ({unc.shape[1]} x {unc.shape[0]})")
        print(f"  noise estimate {unc.noise_px:.4f} px (effective parameters "
              f"{unc.effective_parameters:.0f}); projection_uncertainty {wall:.1f} s wall / {cpu:.1f} s CPU")
        verdict = "met" if 0.5 <= ratio <= 2 else "MISSED"
        print(f"  RMS true error {_rms(err[ok]):.4f} px, RMS predicted sigma "
              f"{_rms(unc.sigma_px[ok]):.4f} px, ratio {ratio:.2f} (target 0.5-2: {verdict}); "
              f"median true {np.median(err[ok]):.4f} / sigma {unc.median():.4f} px; "
              f"correlation of the maps {np.corrcoef(err[ok], unc.sigma_px[ok])[0, 1]:.2f}")
        print(f"  border band: true {_rms(err[band]):.4f} / sigma {_rms(unc.sigma_px[band]):.4f} px; "
              f"inner area: true {_rms(err[inner]):.4f} / sigma {_rms(unc.sigma_px[inner]):.4f} px")
        acc = camera_accuracy(truth, res.model)
        print(f"  focal-scale part at the corner: true {acc.scale_px:+.4f} px, predicted 1-sigma "
              f"{unc.scale_px:.4f} px; true error without the affine part {acc.shape_median:.4f} px median")
        record.add(name, frames=len(subset), frames_used=len(res.poses), observations=len(res.inlier),
                   observations_kept=int(res.inlier.sum()), rms_true_error_px=_rms(err[ok]),
                   rms_sigma_px=_rms(unc.sigma_px[ok]), true_over_predicted=ratio,
                   median_true_error_px=np.median(err[ok]), median_sigma_px=unc.median(),
                   border_band_sigma_px=bands[name], focal_scale_true_px=acc.scale_px,
                   focal_scale_sigma_px=unc.scale_px, shape_median_px=acc.shape_median,
                   uncertainty_cpu_s=cpu)
        for scale in PRIOR_SCALES:
            other = projection_uncertainty(res, prior_scale=scale)
            print(f"  prior_scale {scale}: RMS sigma {_rms(other.sigma_px[ok]):.4f} px, ratio "
                  f"{_rms(err[ok]) / _rms(other.sigma_px[ok]):.2f}, border band "
                  f"{other.border_band():.4f} px, focal-scale 1-sigma {other.scale_px:.4f} px")
    (b, sb), (c, sc) = bands.items()
    q = sc / sb
    print(f"border-band sigma, {c} over {b}: {sc:.4f} / {sb:.4f} = {q:.3f} "
          f"(target <= 0.6: {'met' if q <= 0.6 else 'MISSED'})")
    record.add("border band, sharp + blurry over sharp-only", sigma_ratio=q)
    record.write()


if __name__ == "__main__":
    main()
