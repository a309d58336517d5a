"""Benchmark of the paper's local alignment on simulated blurry frames: does it help, and why not.

    python scripts/bench_local_alignment.py [--frames 4] [--device cpu]

For each frame (1280x720, blur 4 to 12 px, noise sigma 2 grey levels) the accepted blocks' star
centres ``H(0, 0)`` (PSF-recentred) are compared with the ground-truth time-averaged positions,
before and after :func:`blurcalib.extract.local_alignment.align_locally`, after removing each frame's
mean offset (median and p90, px). It also splits the shared-corner gaps of neighbouring blocks:

* ``gap``: RMS of all shared-corner gaps ``H_a(c_a) - H_b(c_b)`` (px);
* ``common``: RMS of the mean of a pair's two gaps, the only part a translation per block can
  change (both corners of a pair move by ``x_a - x_b``);
* ``true dx``: RMS of the pairs' true relative translation errors ``d_a - d_b`` (the part local
  alignment exists to remove);
* ``unexplained``: RMS of ``common + (d_a - d_b)``, the part of the common gap that is not a
  relative translation error (shape errors of the blocks' homographies).

Local alignment helps only where ``true dx`` dominates ``common``. Also printed: the accepted
blocks of the visible ones (the yield) and the CPU time per frame; the figures are also recorded
as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import time

import benchrecord
import numpy as np

from blurcalib.deconv.settings import DeconvSettings
from blurcalib.extract.frame import ExtractSettings, extract_frame
from blurcalib.extract.local_alignment import align_locally, corner_gaps, neighbour_pairs
from blurcalib.geometry.homography import homography_centre
from blurcalib.sim.synth import Simulator, SynthConfig


def _rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(v**2, axis=-1))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--device", default="cpu")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    sim = Simulator(SynthConfig(sharp=0, blurry=args.frames, blur_min_px=4.0, blur_max_px=12.0,
                                noise_sigma=2.0, seed=7))
    settings = ExtractSettings(deconv=DeconvSettings(device=args.device))
    print(f"{'frame':<18}{'blocks':>7}{'no LA med/p90':>16}{'LA med/p90':>16}"
          f"{'gap':>8}{'common':>8}{'true dx':>9}{'unexpl.':>9}")
    before_all, after_all, cpus = [], [], []
    accepted = visible = 0
    for i in range(args.frames):
        frame = sim.frame(i)
        c0 = time.process_time()
        result = extract_frame(frame.image.astype(np.float32), sim.pattern, frame.truth.name, settings)
        cpus.append(time.process_time() - c0)
        blocks = result.blocks.select(result.blocks.accepted)
        accepted += len(blocks)
        visible += int(frame.truth.block_inside.sum())
        H, fx, fy = blocks.H, blocks.fx, blocks.fy
        truth = {int(f): xy for f, xy in zip(frame.truth.feature_ids, frame.truth.mean, strict=True)}
        true_xy = np.stack([truth[int(f)] for f in blocks.feature_id])
        centre = blocks.centre
        local = align_locally(H, fx, fy)
        aligned = homography_centre(local.H)
        d = centre - true_xy
        errors = []
        for xy in (centre, aligned):
            e = xy - true_xy
            errors.append(np.hypot(*(e - e.mean(axis=0)).T))
        a, b, kind = neighbour_pairs(fx, fy)
        gaps = corner_gaps(H, a, b, kind)
        common = gaps.mean(axis=1)
        before_all.append(errors[0])
        after_all.append(errors[1])
        print(f"{frame.truth.name:<18}{len(H):>7}"
              + "".join(f"{np.median(e):>9.4f}/{np.percentile(e, 90):.3f}" for e in errors)
              + f"{_rms(gaps):>8.3f}{_rms(common):>8.3f}{_rms(d[a] - d[b]):>9.3f}"
                f"{_rms(common + d[a] - d[b]):>9.3f}")
    before, after = np.concatenate(before_all), np.concatenate(after_all)
    share = 100 * accepted / max(visible, 1)
    print(f"all frames: {accepted} of {visible} visible blocks accepted ({share:.1f}%); without local "
          f"alignment median {np.median(before):.4f} px, p90 "
          f"{np.percentile(before, 90):.4f}; with it median {np.median(after):.4f} px, p90 "
          f"{np.percentile(after, 90):.4f}; {np.mean(cpus):.1f} s CPU per frame")
    record.add("simulated blurry frames (blur 4-12 px)", frames=args.frames, blocks_accepted=accepted,
               blocks_visible=visible, accepted_pct=share,
               median_px=np.median(before), p90_px=np.percentile(before, 90),
               local_alignment_median_px=np.median(after), local_alignment_p90_px=np.percentile(after, 90),
               cpu_s_per_frame=np.mean(cpus))
    record.write()


if __name__ == "__main__":
    main()
