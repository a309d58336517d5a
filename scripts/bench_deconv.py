"""Accuracy and speed of the local deconvolution (``blurcalib.deconv.blocks``) on simulated blocks.

Simulates blocks with known ground truth (:func:`blurcalib.sim.blocks.simulate_blocks`: the exact
pattern box-filtered over 8 x 8 samples per pixel, ~30 px squares under a random perspective, a
random curved motion path of 4 to 15 px plus a small Gaussian, gain and offset gradients, ink ~30
and paper ~200 grey levels, Gaussian noise of 2 grey levels, 8-bit quantisation; the initial
homography off by up to 1.5 px and 3 % scale), fits them all in one batch with each solver variant
and prints the star-centre error (recovered ``H'(0, 0)`` after PSF re-centring against the true
``H(0, 0)`` plus the true kernel's centroid), the residual, the share of blocks whose fit
converged (the yield) and the time per block. The figures are also recorded as JSON
(``scripts/benchrecord.py``).

Usage::

    python scripts/bench_deconv.py [--blocks 64] [--seed 7] [--kernel-size 17] [--repeats 3] [--threads 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import benchrecord
import numpy as np
import torch

from blurcalib.deconv.blocks import fit_blocks
from blurcalib.deconv.result import BlockFit
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.geometry.homography import translation
from blurcalib.sim.blocks import SimulatedBlocks, simulate_blocks
from blurcalib.target.pattern import layout_pattern

VARIANTS: tuple[tuple[str, dict], ...] = (
    ("default", {}),
    ("2 x 2 supersampled latent", {"supersample": 2}),
    ("float64", {"dtype": "float64"}),
)


def errors(fit: BlockFit, sim: SimulatedBlocks) -> np.ndarray:
    """Star-centre errors (px) of the fitted blocks."""
    return np.linalg.norm(fit.centre - sim.centre_true, axis=1)


def timed_fit(sim: SimulatedBlocks, kernel_size: int, settings: DeconvSettings, repeats: int
              ) -> tuple[BlockFit, float, float]:
    """Fit all blocks ``repeats`` times; returns the fit and the median wall and process CPU
    times (s)."""
    times, cpus = [], []
    fit = None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fit = fit_blocks(sim.image, sim.H0, 16, kernel_size, settings)
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    assert fit is not None
    return fit, float(np.median(times)), float(np.median(cpus))


def tiled(sim: SimulatedBlocks, copies: int) -> SimulatedBlocks:
    """The simulated image repeated ``copies`` times side by side, with its blocks."""
    shifts = [np.array([i * sim.image.shape[1], 0.0]) for i in range(copies)]
    return dataclasses.replace(
        sim, image=np.concatenate([sim.image] * copies, axis=1),
        H_true=np.concatenate([translation(t) @ sim.H_true for t in shifts]),
        H0=np.concatenate([translation(t) @ sim.H0 for t in shifts]),
        psf_true=np.concatenate([sim.psf_true] * copies),
        centre_true=np.concatenate([sim.centre_true + t for t in shifts]),
        features=np.concatenate([sim.features] * copies))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--blocks", type=int, default=64, help="simulated blocks (one batch)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--kernel-size", type=int, default=17)
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per variant (median)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (1: per-process figures, as the command line's workers compute)")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    torch.set_num_threads(args.threads)

    t0 = time.perf_counter()
    sim = simulate_blocks(layout_pattern(), args.blocks, np.random.default_rng(args.seed))
    print(f"simulated {args.blocks} blocks in {time.perf_counter() - t0:.1f} s "
          f"(blur 4-15 px, noise 2 grey levels, H0 off by <= 1.5 px and 3 %)")
    base = DeconvSettings()
    fit_blocks(sim.image, sim.H0[:4], 16, args.kernel_size, base)  # warm-up (allocator, lazy initialisation)

    header = ("variant", "median", "p90", "max", "rms", "converged", "ms/block", "CPU ms")
    print("\n{:42s} {:>8s} {:>8s} {:>8s} {:>6s} {:>9s} {:>9s} {:>7s}".format(*header))
    for name, changes in VARIANTS:
        settings = dataclasses.replace(base, **changes)
        fit, seconds, cpu = timed_fit(sim, args.kernel_size, settings, args.repeats)
        err = errors(fit, sim)
        print(f"{name:42s} {np.median(err):8.4f} {np.percentile(err, 90):8.4f} {err.max():8.4f} "
              f"{np.median(fit.residual_rms):6.2f} {100 * fit.converged.mean():8.0f}% "
              f"{1000 * seconds / len(err):9.1f} {1000 * cpu / len(err):7.1f}")
        record.add(name, blocks=len(err), converged_pct=100 * fit.converged.mean(),
                   median_px=np.median(err), p90_px=np.percentile(err, 90), max_px=err.max(),
                   residual_rms_grey=np.median(fit.residual_rms), wall_ms_per_block=1000 * seconds / len(err),
                   cpu_ms_per_block=1000 * cpu / len(err))

    big = tiled(sim, 4)
    fit, seconds, cpu = timed_fit(big, args.kernel_size, base, 1)
    err = errors(fit, big)
    print(f"\n{len(err)} blocks (the {args.blocks} above, four times), defaults: {seconds:.2f} s, "
          f"{1000 * seconds / len(err):.1f} ms/block ({1000 * cpu / len(err):.1f} ms CPU); "
          f"{100 * fit.converged.mean():.0f}% converged, "
          f"median error {np.median(err):.4f} px, max {err.max():.4f} px")
    record.add(f"{len(err)} blocks in one batch, defaults", blocks=len(err),
               converged_pct=100 * fit.converged.mean(), median_px=np.median(err), max_px=err.max(),
               wall_s=seconds, wall_ms_per_block=1000 * seconds / len(err),
               cpu_ms_per_block=1000 * cpu / len(err))
    record.write()


if __name__ == "__main__":
    main()
