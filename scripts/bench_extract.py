"""Benchmark of feature extraction from blurry frames: accuracy against ground truth and speed.

    python scripts/bench_extract.py [--frames 6] [--skip-semireal] [--device cpu]

1. Simulated blurry frames (1280x720, blur 4 to 15 px, noise sigma 2 grey levels): star centres
   against the ground-truth time-averaged positions after removing each frame's mean offset
   (median, p90, max), the share of visible blocks recovered, and the same with local alignment.
   Targets: median <= 0.03 px, p90 <= 0.08 px, >= 90% recovered, no feature off by > 1 px.
2. Semi-real: the real fixture frames blurred with known, centred, spatially varying motion
   kernels: distance of the blurry-frame star centres to the same frames' sharp ones (after
   removing the mean offset). Target: median <= 0.08 px. The sharp frames' star centres are
   also compared with the reference detector's features of the same frames (those
   ``features_10px.bin`` holds, ``0.png`` to ``3.png``; after each frame's mean offset,
   features within 1 px).
3. Speed: seconds per frame and per block, split into seeding, fitting and alignment, peak
   memory; for the semi-real frames (sharp and blurred) process CPU per frame and the mean wall
   time of each stage, the growth's split out (:meth:`FrameResult.stage_seconds`).
   Target: <= 10 s per 1280x720 frame with ~250 blocks and a 17x17 PSF, <= 3 GB.

Each part prints its yield (frames extracted, blocks or features found) beside accuracy and time;
the figures are also recorded as JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import os
import resource
import time
from pathlib import Path

import benchrecord
import cv2
import numpy as np
import torch

from blurcalib.deconv.settings import DeconvSettings
from blurcalib.extract.frame import ExtractSettings, extract_frame, mean_stage_seconds
from blurcalib.geometry.homography import homography_centre
from blurcalib.io.frames import load_frame
from blurcalib.io.refformat import read_ref_dataset
from blurcalib.runs.runtime import keep_large_allocations
from blurcalib.sim.synth import Simulator, SynthConfig
from blurcalib.sim.truth import splat
from blurcalib.target.pattern import load_pattern

FIXTURES = Path(os.environ.get("BLURCALIB_FIXTURES") or Path(__file__).resolve().parents[2] / "shared"
                / "fixtures")
"""The reference fixtures (``BLURCALIB_FIXTURES``, default ``../shared/fixtures`` beside the checkout)."""
REAL = FIXTURES / "real_star16"


def _errors(result, truth_xy: np.ndarray, use_local: bool = False) -> tuple[np.ndarray, np.ndarray]:
    ids = result.features.feature_id
    if use_local and result.local is not None:
        xy = homography_centre(result.local.H)
        ids = result.growth.feature_id[result.growth.accepted]
    else:
        xy = np.stack([result.features.x, result.features.y], axis=1)
    d = xy - truth_xy[ids]
    return ids, d - d.mean(axis=0)


def simulated(frames: int, device: str, record: benchrecord.BenchRecord) -> None:
    print("== simulated blurry frames (blur 4-15 px, noise 2) ==")
    sim = Simulator(SynthConfig(sharp=0, blurry=frames, blur_min_px=4.0, blur_max_px=15.0,
                                noise_sigma=2.0, seed=7))
    settings = ExtractSettings(deconv=DeconvSettings(device=device))
    all_err, all_err_la, recovered, times, cpus, blocks = [], [], [], [], [], []
    split = {"seed": 0.0, "fit": 0.0, "align": 0.0}
    for i in range(frames):
        frame = sim.frame(i)
        t = frame.truth
        start, c0 = time.perf_counter(), time.process_time()
        result = extract_frame(frame.image.astype(np.float32), sim.pattern, t.name, settings)
        elapsed, cpu = time.perf_counter() - start, time.process_time() - c0
        if result.status.value != "ok":
            print(f"{t.name}: {result.status.value} {result.message}")
            continue
        ids, err = _errors(result, t.mean)
        _, err_la = _errors(result, t.mean, use_local=True)
        n = np.linalg.norm(err, axis=1)
        n_la = np.linalg.norm(err_la, axis=1)
        visible = int(t.block_inside.sum())
        rec = len(ids) / max(visible, 1)
        blur = float(np.median(t.blur_length[t.visible]))
        print(f"{t.name}: blur {blur:5.1f} px  {len(ids):3d}/{visible:3d} blocks  "
              f"median {np.median(n):.4f}  p90 {np.percentile(n, 90):.4f}  max {n.max():.3f} px  "
              f"(local alignment: median {np.median(n_la):.4f})  {elapsed:5.1f} s")
        all_err.append(n)
        all_err_la.append(n_la)
        recovered.append(rec)
        times.append(elapsed)
        cpus.append(cpu)
        blocks.append(len(result.blocks))
        for k in split:
            split[k] += result.seconds.get(k, 0.0)
    if not all_err:
        return
    n = np.concatenate(all_err)
    n_la = np.concatenate(all_err_la)
    print(f"ALL: {len(all_err)}/{frames} frames extracted, recovered {100 * np.mean(recovered):.1f}% of "
          f"visible blocks; median {np.median(n):.4f} px, p90 {np.percentile(n, 90):.4f} px, "
          f"max {n.max():.3f} px")
    print(f"     with local alignment: median {np.median(n_la):.4f} px, "
          f"p90 {np.percentile(n_la, 90):.4f} px")
    total = sum(split.values())
    print(f"speed: {np.mean(times):.2f} s per frame, {1000 * sum(times) / sum(blocks):.1f} ms per "
          f"block ({np.mean(blocks):.0f} blocks per frame); seeding {100 * split['seed'] / total:.0f}%,"
          f" fitting {100 * split['fit'] / total:.0f}%, alignment {100 * split['align'] / total:.0f}%; "
          f"{np.mean(cpus):.2f} s CPU per frame")
    record.add("simulated blurry frames (blur 4-15 px)", frames=frames, frames_extracted=len(all_err),
               recovered_pct=100 * np.mean(recovered), median_px=np.median(n), p90_px=np.percentile(n, 90),
               max_px=n.max(), local_alignment_median_px=np.median(n_la),
               local_alignment_p90_px=np.percentile(n_la, 90), cpu_s_per_frame=np.mean(cpus),
               wall_s_per_frame=np.mean(times), wall_ms_per_block=1000 * sum(times) / sum(blocks),
               blocks_per_frame=np.mean(blocks))


def _motion_kernel(angle: float, length: float, size: int) -> np.ndarray:
    """A centred straight motion kernel (centroid at the kernel centre)."""
    s = np.linspace(-0.5, 0.5, max(8, int(4 * length)))
    offsets = np.stack([s * length * np.cos(angle), s * length * np.sin(angle)], axis=1)
    k = splat(offsets, size)
    return k / k.sum()


def blur_spatially_varying(image: np.ndarray, rng: np.random.Generator, size: int = 15
                           ) -> np.ndarray:
    """Blur with centred motion kernels varying smoothly over a 3 x 3 grid of anchors
    (bilinear blending of the anchor-blurred images: a spatially varying PSF whose kernel at
    any point is the blend of centred kernels, hence centred)."""
    h, w = image.shape
    gy, gx = 3, 3
    base_angle = rng.uniform(0, np.pi)
    out = np.zeros_like(image, dtype=np.float64)
    xs = np.linspace(0, 1, w)
    ys = np.linspace(0, 1, h)
    for j in range(gy):
        for i in range(gx):
            angle = base_angle + 0.35 * (i - 1) + 0.25 * (j - 1)
            length = 5.0 + 2.0 * i + 1.5 * j
            k = _motion_kernel(angle, length, size)
            blurred = cv2.filter2D(image.astype(np.float64), -1, k, borderType=cv2.BORDER_REFLECT)
            wx = np.maximum(0, 1 - np.abs(xs * (gx - 1) - i))
            wy = np.maximum(0, 1 - np.abs(ys * (gy - 1) - j))
            out += blurred * wy[:, None] * wx[None, :]
    return out


def semi_real(device: str, record: benchrecord.BenchRecord) -> None:
    print("== semi-real: fixture frames blurred with known centred, spatially varying kernels ==")
    pattern = load_pattern(REAL / "pattern.yaml")
    rng = np.random.default_rng(0)
    meds = []
    runs: dict[str, tuple[list, list[float]]] = {"sharp": ([], []), "blurred": ([], [])}

    def timed(kind: str, image: np.ndarray, name: str, settings: ExtractSettings):
        c0 = time.process_time()
        result = extract_frame(image, pattern, name, settings)
        runs[kind][0].append(result)
        runs[kind][1].append(time.process_time() - c0)
        return result

    for path in sorted((REAL / "images").glob("*.png")):
        image = load_frame(path)
        sharp = timed("sharp", image, path.name, ExtractSettings.sharp())
        blurred = blur_spatially_varying(image, rng) + rng.normal(0, 1.0, image.shape)
        blurry = timed("blurred", np.clip(blurred, 0, 255).astype(np.float32), path.name,
                       ExtractSettings(deconv=DeconvSettings(device=device)))
        if sharp.status.value != "ok" or blurry.status.value != "ok":
            print(f"{path.name}: sharp {sharp.status.value}, blurry {blurry.status.value} "
                  f"{blurry.message}")
            continue
        s, b = sharp.features, blurry.features
        _, i, j = np.intersect1d(s.feature_id, b.feature_id, return_indices=True)
        d = np.stack([b.x[j] - s.x[i], b.y[j] - s.y[i]], axis=1)
        n = np.linalg.norm(d - d.mean(axis=0), axis=1)
        meds.append(n)
        print(f"{path.name}: {len(d)} common features, median {np.median(n):.4f} px, "
              f"p90 {np.percentile(n, 90):.4f} px, mean offset {np.round(d.mean(axis=0), 3)}")
    if meds:
        n = np.concatenate(meds)
        print(f"ALL: {len(meds)}/{len(runs['sharp'][0])} frames extracted sharp and blurred, "
              f"{len(n)} common features; median {np.median(n):.4f} px, p90 {np.percentile(n, 90):.4f} px")
        record.add("semi-real blurred fixture frames", frames=len(runs["sharp"][0]),
                   frames_compared=len(meds), common_features=len(n), median_px=np.median(n),
                   p90_px=np.percentile(n, 90))
    _against_reference(runs["sharp"][0], record)
    for kind, (results, cpus) in runs.items():
        print(f"{kind} frames: CPU {np.mean(cpus):.2f} s per frame (median {np.median(cpus):.2f} s); stages, "
              "mean s wall: " + ", ".join(f"{k} {v:.2f}" for k, v in mean_stage_seconds(results).items()))
        record.add(f"fixture frames, {kind}: time", frames=len(cpus), cpu_s_per_frame=np.mean(cpus),
                   median_cpu_s_per_frame=np.median(cpus))


def _against_reference(results: list, record: benchrecord.BenchRecord) -> None:
    """Prints the sharp frames' star centres against the reference detector's features."""
    reference = read_ref_dataset(REAL / "features_10px.bin")
    names = {img.name for img in reference.images}
    dist, total, frames = [], 0, 0
    for result in results:
        if result.frame not in names or result.status.value != "ok":
            continue
        ref = reference.image(result.frame)
        f = result.features
        _, i, j = np.intersect1d(f.feature_id, ref.features, return_indices=True)
        d = np.stack([f.x[i], f.y[i]], axis=1) - ref.xy[j]
        d = d[np.linalg.norm(d, axis=1) < 1.0]
        dist.append(np.linalg.norm(d - d.mean(axis=0), axis=1))
        total += len(ref.features)
        frames += 1
    if dist:
        n = np.concatenate(dist)
        print(f"sharp frames against the reference detector ({frames} frames): {len(n)} of its {total} "
              f"features within 1 px, median {np.median(n):.4f} px, p90 {np.percentile(n, 90):.4f} px")
        record.add("sharp fixture frames against the reference detector", frames=frames,
                   reference_features=total, within_1px=len(n), within_1px_pct=100 * len(n) / total,
                   median_px=np.median(n), p90_px=np.percentile(n, 90))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--skip-semireal", action="store_true")
    parser.add_argument("--device", default="cpu")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    torch.set_num_threads(1)  # per-process figures: torch's pool collapses when processes share the cores
    keep_large_allocations()  # as the command line and its workers do
    simulated(args.frames, args.device, record)
    if not args.skip_semireal:
        semi_real(args.device, record)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak memory: {peak:.0f} MB")
    record.add("memory", peak_mb=peak)
    record.write()


if __name__ == "__main__":
    main()
