"""Benchmark of feature yield on real texture: real fixture frames under a smooth field of motion blur.

    python scripts/bench_real_texture.py [--frames 3] [--variants hints,no-hints,hints-front-retry]

The real frames of ``../shared/fixtures/real_star16`` (a real camera's optics, noise and display
pixels) are blurred by a spatially varying field of centred straight motion kernels of 5 to 12 px
(:func:`blur_field`: a 3 x 4 grid of anchor kernels, each image blurred by every anchor's kernel and
the results blended bilinearly, so the kernel at any point is a blend of centred kernels and the
star centres stay where the sharp frame shows them), plus Gaussian noise of 1.5 grey levels. Each
frame is extracted with the blurry-frame defaults and the star centres are compared with the
reference detector's features of the sharp frame (``features_10px.bin``, read with
:mod:`blurcalib.io.refformat`, pixel-corner convention converted to OpenCV's).

Per variant: the yield (share of the reference features found within 1 px), the median distance of
those to the reference, the block statuses and the process CPU time per frame (torch single-threaded;
on a shared machine the CPU time is the figure to compare, taken back to back), and the mean wall
time of each stage (:meth:`blurcalib.extract.frame.FrameResult.stage_seconds`). Variants:

* ``hints``: the defaults (neighbours' PSFs as hints; a hinted block left not converged whose
  blur is short for its square is accepted after a last step under 0.15 px, else re-fitted with
  the full schedule, :func:`blurcalib.growth.fronts.fit_hinted`);
* ``no-hints``: ``GrowSettings(psf_hints=False)``, every block with the full schedule;
* ``hints-front-retry``: hints, failed hinted blocks re-fitted only when their front accepts
  none (``GrowSettings(retry_below_blur_per_square=0)``).

Targets: >= 90% of the reference features, median <= 0.07 px, CPU per frame no more than 20%
above ``hints-front-retry``. The figures are also recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import os
import time
from collections import Counter
from pathlib import Path

import benchrecord
import cv2
import numpy as np
import torch

from blurcalib.extract.frame import ExtractSettings, extract_frame, mean_stage_seconds
from blurcalib.growth.settings import GrowSettings
from blurcalib.io.frames import load_frame
from blurcalib.io.refformat import read_ref_dataset
from blurcalib.runs.runtime import keep_large_allocations
from blurcalib.sim.truth import splat
from blurcalib.target.pattern import load_pattern

FIXTURES = Path(os.environ.get("BLURCALIB_FIXTURES") or Path(__file__).resolve().parents[2] / "shared"
                / "fixtures")
"""The reference fixtures (``BLURCALIB_FIXTURES``, default ``../shared/fixtures`` beside the checkout)."""
REAL = FIXTURES / "real_star16"

VARIANTS = {
    "hints": GrowSettings(),
    "no-hints": GrowSettings(psf_hints=False),
    "hints-front-retry": GrowSettings(retry_below_blur_per_square=0.0),
}


def motion_kernel(angle: float, length: float, size: int) -> np.ndarray:
    """A centred straight motion kernel of ``length`` px at ``angle`` rad, ``(size, size)``, sum 1."""
    s = np.linspace(-0.5, 0.5, max(8, int(4 * length)))
    k = splat(np.stack([s * length * np.cos(angle), s * length * np.sin(angle)], axis=1), size)
    return k / k.sum()


def blur_field(image: np.ndarray, rng: np.random.Generator, lengths: tuple[float, float] = (5.0, 12.0),
               grid: tuple[int, int] = (3, 4), noise_sigma: float = 1.5) -> np.ndarray:
    """``image (H, W)`` blurred by a smooth field of centred motion kernels, plus noise.

    Anchors on a ``grid = (rows, cols)`` spanning the image get a length uniform in ``lengths``
    (px) and an angle that turns smoothly over the image (a random base, +-0.4 rad across it);
    the anchor-blurred images are blended with bilinear weights. Returns float32 grey levels,
    clipped to [0, 255]."""
    h, w = image.shape
    gy, gx = grid
    base = rng.uniform(0, np.pi)
    turn = rng.uniform(-0.4, 0.4, 2)
    xs, ys = np.linspace(0, 1, w), np.linspace(0, 1, h)
    out = np.zeros((h, w))
    for j in range(gy):
        for i in range(gx):
            length = rng.uniform(*lengths)
            angle = base + turn[0] * (i / (gx - 1) - 0.5) + turn[1] * (j / (gy - 1) - 0.5)
            size = 2 * int(np.ceil(length / 2)) + 3
            blurred = cv2.filter2D(image.astype(np.float64), -1, motion_kernel(angle, length, size),
                                   borderType=cv2.BORDER_REFLECT)
            wx = np.maximum(0, 1 - np.abs(xs * (gx - 1) - i))
            wy = np.maximum(0, 1 - np.abs(ys * (gy - 1) - j))
            out += blurred * wy[:, None] * wx[None, :]
    out += rng.normal(0, noise_sigma, out.shape)
    return np.clip(out, 0, 255).astype(np.float32)


def reference_features(pattern) -> dict[str, dict[int, np.ndarray]]:
    """Per image name: pattern feature id -> reference position (px, OpenCV convention)."""
    ref = read_ref_dataset(REAL / "features_10px.bin")
    g = ref.geometry
    to_pattern = dict(zip(g.ids.tolist(), pattern.feature_ids(g.fx, g.fy).tolist(), strict=True))
    return {img.name: {to_pattern[int(i)]: xy for i, xy in zip(img.features, img.xy, strict=True)}
            for img in ref.images}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3, help="fixture frames (0.png, 1.png, ...)")
    parser.add_argument("--variants", default=",".join(VARIANTS),
                        help="comma-separated, of " + ", ".join(VARIANTS))
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    torch.set_num_threads(1)
    keep_large_allocations()  # as the command line and its workers do
    variants = args.variants.split(",")
    pattern = load_pattern(REAL / "pattern.yaml")
    refs = reference_features(pattern)
    names = [f"{i}.png" for i in range(args.frames)]
    print(f"{len(names)} fixture frames, 5-12 px motion-blur field, noise 1.5; process CPU, torch 1 thread, "
          "the variants run back to back on each frame")
    found = dict.fromkeys(variants, 0)
    errors: dict[str, list[np.ndarray]] = {v: [] for v in variants}
    cpus: dict[str, list[float]] = {v: [] for v in variants}
    statuses = {v: Counter() for v in variants}
    results: dict[str, list] = {v: [] for v in variants}
    total = 0
    for i, n in enumerate(names):
        image = blur_field(load_frame(REAL / "images" / n), np.random.default_rng([5, i]))
        ref = refs[n]
        total += len(ref)
        for v in variants:
            c0 = time.process_time()
            r = extract_frame(image, pattern, n, ExtractSettings(grow=VARIANTS[v]))
            cpus[v].append(time.process_time() - c0)
            results[v].append(r)
            statuses[v].update(r.blocks.status.tolist())
            got = dict(zip(r.features.feature_id.tolist(), np.stack([r.features.x, r.features.y], axis=1),
                           strict=True))
            d = np.array([np.linalg.norm(got[f] - xy) for f, xy in ref.items() if f in got])
            found[v] += int(np.sum(d <= 1.0))
            errors[v].append(d[d <= 1.0])
            print(f"{n} {v:15s} {int(np.sum(d <= 1.0)):3d}/{len(ref)} reference features  "
                  f"CPU {cpus[v][-1]:5.2f} s", flush=True)
    for v in variants:
        e = np.concatenate(errors[v])
        median = np.median(e) if e.size else np.nan
        p90 = np.percentile(e, 90) if e.size else np.nan
        print(f"{v:15s} yield {100 * found[v] / max(total, 1):5.1f}% ({found[v]}/{total})  median "
              f"{median:.4f} px  p90 {p90:.4f} px  CPU {np.mean(cpus[v]):5.2f} s/frame  "
              f"blocks {dict(statuses[v])}")
        print(f"{v:15s} stages, mean s wall per frame: "
              + ", ".join(f"{k} {t:.2f}" for k, t in mean_stage_seconds(results[v]).items()))
        record.add(v, frames=len(names), reference_features=total, found_within_1px=found[v],
                   yield_pct=100 * found[v] / max(total, 1), median_px=median, p90_px=p90,
                   cpu_s_per_frame=np.mean(cpus[v]))
    record.write()


if __name__ == "__main__":
    main()
