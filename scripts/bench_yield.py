"""Benchmark of frame yield under heavy blur: seeding, the adaptive PSF window, accuracy, speed.

    python scripts/bench_yield.py [--heavy 12] [--light 6] [--repeat 0] [--cache DIR] [--part I/N]
                                  [--device cpu]

1. Simulated frames with 12 to 25 px of blur (1280x720, noise sigma 2, seed 11): per frame how it
   was seeded, whether its blocks were fitted with the frame's path-PSF field (``field``,
   :func:`blurcalib.growth.field.field_growth`) or with free PSFs (``free``), the PSF window reached
   (the largest of the frame's kernels), the share of visible blocks returned, the error of the star
   centres against the time-averaged truth after removing the frame's mean offset. Targets:
   >= 90% of frames extracted, >= 85% of visible features returned, median <= 0.03 px, none off
   by more than 1 px. The same figures after the pipeline's block filter
   (:func:`blurcalib.growth.quality.filter_frame`, default thresholds: BE, loss, connectivity), their
   pose-consistent errors (each frame's best-fit homography removed: a pose change, which a
   calibration refits), and the share returned of the visible features whose blur is shorter than
   their star square. Last, per class of blur length over square side (the feature's blur
   against its star square's side at mid-exposure): the visible features, the share returned and
   their median error.
2. Simulated frames with 4 to 15 px of blur (the set of ``scripts/bench_extract.py``, seed 7):
   the same figures with the fixed 17 px window (``WindowPolicy(largest=17)``, which
   also turns the path-PSF field off) and with the defaults.
   Target: accuracy and time per frame no worse.
3. Photometry (``--photometry N``): simulated frames with 4 to 15 px of blur (seed 23) whose paper
   is at 150, 183, 217 or 250 grey levels and whose sensor has 5, 10 or 20 electrons per grey
   level (the 12 combinations in turn; read noise 0.7 grey levels; :func:`photometric_frame`),
   then ``--demo N`` frames of the demo set (``SynthConfig()``): per frame the true and the
   estimated noise at the frame's level (:mod:`blurcalib.growth.noise`), and the blocks the pipeline's
   block filter keeps with the loss threshold in the frame's noise units (the default) and with
   the paper's absolute one (``QualitySettings(loss_mode="absolute")``); a frame is used when at least
   :data:`blurcalib.calib.alignment.MIN_BLOCKS` are kept. Target: >= 95% of the photometry
   frames used; the demo frames keep their blocks.

``--repeat N`` runs parts 1 and 2 (their default settings) N more times, each time with a
different perturbation of 0.01 grey levels (Gaussian, 0.5 % of the frames' noise) added to every
frame, and prints each run's figures and their range over the runs: the spread that a change of
rounding alone makes (a variant whose figures stay inside it is no better and no worse on these
frames).

Times are wall and process CPU seconds per frame, torch single-threaded, then the mean wall time
of each stage (:meth:`blurcalib.extract.frame.FrameResult.stage_seconds`). ``--cache`` keeps the
simulated frames (pickled) so that a re-run skips the simulation; ``--part I/N`` runs every N-th
frame from the I-th (to spread a run over processes; the figures are then per part).
``--device cuda`` runs the block solves of parts 1 and 2 on the GPU (the first frame then also
pays for CUDA's start: compare the medians). The figures are also recorded as JSON
(``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import time
from pathlib import Path

import benchrecord
import numpy as np
import torch

from blurcalib.calib.alignment import MIN_BLOCKS
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.extract.frame import ExtractSettings, extract_frame, mean_stage_seconds
from blurcalib.growth.quality import QualitySettings, filter_frame
from blurcalib.growth.window import WindowPolicy
from blurcalib.runs.runtime import keep_large_allocations
from blurcalib.sim import render, synth
from blurcalib.sim.evaluate import pose_consistent_errors
from blurcalib.sim.synth import SimulatedFrame, Simulator, SynthConfig


def frames(blur: tuple[float, float], count: int, seed: int, cache: Path | None
           ) -> tuple[Simulator, list[SimulatedFrame]]:
    sim = Simulator(SynthConfig(sharp=0, blurry=count, blur_min_px=blur[0], blur_max_px=blur[1],
                                noise_sigma=2.0, seed=seed))
    path = cache / f"frames_{blur[0]:g}_{blur[1]:g}_{count}_{seed}.pkl" if cache else None
    if path is not None and path.is_file():
        return sim, pickle.loads(path.read_bytes())
    out = [sim.frame(i) for i in range(count)]
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(out))
    return sim, out


def _square_px(pattern, truth, ids: np.ndarray) -> np.ndarray:
    """``(B,)`` px: side (sqrt of the area) of the star squares of features ``ids`` at
    mid-exposure, from the true image positions of their 4-neighbours (one-sided at the
    pattern's edge)."""
    f = pattern.features[ids]
    mid = truth.mid[ids]

    def step(dx: int, dy: int) -> np.ndarray:
        fwd, back = (pattern.feature_ids(f[:, 0] + sign * dx, f[:, 1] + sign * dy) for sign in (1, -1))
        p_f = np.where((fwd >= 0)[:, None], truth.mid[np.maximum(fwd, 0)], np.nan)
        p_b = np.where((back >= 0)[:, None], truth.mid[np.maximum(back, 0)], np.nan)
        both = (p_f - p_b) / 2
        return np.where(np.isnan(both), np.where(np.isnan(p_f), mid - p_b, p_f - mid), both)

    a, b = step(1, 0), step(0, 1)
    return np.sqrt(np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))


def _filtered(result, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Feature ids and centres of the blocks kept by the pipeline's block filter."""
    kept = result.blocks.select(filter_frame(result.blocks, image_size).kept)
    return kept.feature_id, kept.centre


def _summary(label: str, errors: list[np.ndarray], returned: list[float], extracted: int,
             total: int) -> None:
    n = np.concatenate(errors) if errors else np.full(1, np.nan)
    print(f"{label}: {extracted}/{total} frames extracted ({100 * extracted / total:.0f}%), "
          f"{100 * np.mean(returned):.1f}% of visible features returned, median "
          f"{np.median(n):.4f} px, p90 {np.percentile(n, 90):.4f} px, max {n.max():.3f} px, "
          f"{int((n > 1).sum())} off by > 1 px")


@dataclasses.dataclass(frozen=True)
class SetFigures:
    """One run's figures over a set: the share of visible features returned and the median and
    90th percentile error (px; growth, each frame's mean offset removed), the pose-consistent
    median after the block filter (px) and the mean CPU s per frame."""

    returned: float
    median: float
    p90: float
    pose_median: float
    cpu: float

    def line(self) -> str:
        return (f"{100 * self.returned:.1f}% returned, median {self.median:.4f} px, p90 {self.p90:.4f} px, "
                f"pose-consistent {self.pose_median:.4f} px, {self.cpu:.1f} s CPU per frame")


def perturbed(simulated: list[SimulatedFrame], seed: int, sigma: float = 0.01) -> list[SimulatedFrame]:
    """The frames with Gaussian noise of ``sigma`` grey levels added (``rng(seed)``), float32."""
    rng = np.random.default_rng(seed)
    return [dataclasses.replace(fr, image=fr.image.astype(np.float32)
                                + rng.normal(0.0, sigma, fr.image.shape).astype(np.float32))
            for fr in simulated]


def spread(title: str, sim: Simulator, simulated: list[SimulatedFrame], settings: ExtractSettings,
           first: SetFigures, repeats: int, record: benchrecord.BenchRecord) -> None:
    """:func:`run` again ``repeats`` times on :func:`perturbed` frames (seeds 1, 2, ...), one
    line each, then the range of each figure over those runs and ``first`` (the frames as they
    are). Nothing when ``repeats`` is 0."""
    if repeats < 1:
        return
    runs = [first]
    for k in range(1, repeats + 1):
        runs.append(run(f"{title}, perturbed by 0.01 grey levels (seed {k})", sim, perturbed(simulated, k),
                        settings, None, per_frame=False))
    print(f"== {title}: spread over {len(runs)} runs (as they are, then {repeats} perturbed) ==")
    for k, fig in enumerate(runs):
        print(f"  run {k}: {fig.line()}")

    def span(name: str, unit: str, scale: float = 1.0, digits: int = 4) -> str:
        v = [scale * getattr(f, name) for f in runs]
        return f"{min(v):.{digits}f}-{max(v):.{digits}f}{unit}"

    print(f"  range: {span('returned', '%', 100.0, 1)} returned, median {span('median', ' px')}, "
          f"p90 {span('p90', ' px')}, pose-consistent {span('pose_median', ' px')}, "
          f"{span('cpu', ' s', digits=1)} CPU per frame")
    figures = {}
    for name, unit, scale in (("returned", "pct", 100.0), ("median", "px", 1.0), ("p90", "px", 1.0),
                              ("pose_median", "px", 1.0), ("cpu", "s_per_frame", 1.0)):
        values = [scale * getattr(f, name) for f in runs]
        figures[f"{name}_{unit}_min"], figures[f"{name}_{unit}_max"] = min(values), max(values)
    record.add(f"{title}: spread over {len(runs)} runs", runs=len(runs), **figures)


def _by_ratio(ratio_visible: list[np.ndarray], ratio_returned: list[np.ndarray],
              ratio_error: list[np.ndarray]) -> None:
    """Per class of blur length over square side: the visible features, the share returned and
    their median and p90 error (one array per frame, per visible feature)."""
    ratio, got, err = (np.concatenate(v) for v in (ratio_visible, ratio_returned, ratio_error))
    print("by blur length / square side of the visible features (growth):")
    for lo, hi in ((0.0, 0.6), (0.6, 0.8), (0.8, 1.0), (1.0, 1.25), (1.25, 1.5), (1.5, np.inf)):
        sel = (ratio >= lo) & (ratio < hi)
        e = err[sel & got]
        share = 100 * got[sel].mean() if sel.any() else 0.0
        print(f"  {lo:.2f}-{hi:.2f}: {int(sel.sum()):5d} visible, {share:5.1f}% returned, median "
              f"{np.median(e) if e.size else np.nan:.4f} px, p90 "
              f"{np.percentile(e, 90) if e.size else np.nan:.4f} px")


def run(title: str, sim: Simulator, simulated: list[SimulatedFrame], settings: ExtractSettings,
        record: benchrecord.BenchRecord | None, per_frame: bool = True) -> SetFigures:
    print(f"== {title} ==")
    errors, returned, walls, cpus, results = [], [], [], [], []
    errors_q, returned_q = [], []
    pose_q: list[np.ndarray] = []
    short_total = short_returned = 0  # blocks whose blur is shorter than their square
    ratio_visible, ratio_returned, ratio_error = [], [], []  # per visible feature
    extracted = 0
    for fr in simulated:
        t = fr.truth
        blur = float(np.median(t.blur_length[t.visible]))
        visible = int(t.block_inside.sum())
        inside = np.flatnonzero(t.block_inside)
        ratio = t.blur_length[inside] / _square_px(sim.pattern, t, inside)
        short = inside[ratio < 1.0]
        ratio_visible.append(ratio)
        short_total += len(short)
        w0, c0 = time.perf_counter(), time.process_time()
        r = extract_frame(fr.image.astype(np.float32), sim.pattern, t.name, settings)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        walls.append(wall)
        cpus.append(cpu)
        results.append(r)
        if r.status.value != "ok" or not len(r.features):
            returned.append(0.0)
            returned_q.append(0.0)
            ratio_returned.append(np.zeros(len(inside), dtype=bool))
            ratio_error.append(np.full(len(inside), np.nan))
            if per_frame:
                print(f"{t.name}: blur {blur:5.1f} px  {r.status.value}: {r.message}  {wall:5.1f} s")
            continue
        extracted += 1
        ids = r.features.feature_id
        d = np.stack([r.features.x, r.features.y], axis=1) - t.mean[ids]
        n = np.linalg.norm(d - d.mean(axis=0), axis=1)
        errors.append(n)
        returned.append(len(ids) / max(visible, 1))
        short_returned += int(np.isin(short, ids).sum())
        err = np.full(len(t.blur_length), np.nan)
        err[ids] = n
        ratio_returned.append(np.isin(inside, ids))
        ratio_error.append(err[inside])
        ids_q, xy_q = _filtered(r, fr.image.shape[::-1])
        d_q = xy_q - t.mean[ids_q]
        n_q = np.linalg.norm(d_q - d_q.mean(axis=0), axis=1) if len(ids_q) else np.zeros(0)
        errors_q.append(n_q)
        pose_q.append(pose_consistent_errors(xy_q, t.mean[ids_q]))
        returned_q.append(len(ids_q) / max(visible, 1))
        if not per_frame:
            continue
        field = "field" if r.growth.psf_field is not None else "free "
        print(f"{t.name}: blur {blur:5.1f} px  seeded by {r.seed.method:13s}  {field} window "
              f"{r.growth.fit.psf.shape[-1]:2d} px  {len(ids):3d}/{visible:3d} blocks  median "
              f"{np.median(n):.4f}  max {n.max():.3f} px  (filtered {len(ids_q):3d}, max "
              f"{n_q.max() if len(n_q) else np.nan:.3f} px)  {wall:5.1f} s wall  {cpu:5.1f} s CPU")
    _summary("ALL (growth)", errors, returned, extracted, len(simulated))
    _summary("ALL (block filter)", errors_q, returned_q, extracted, len(simulated))
    pose = np.concatenate(pose_q) if pose_q else np.full(1, np.nan)
    print(f"after the block filter, pose-consistent (each frame's best-fit homography removed instead "
          f"of its mean offset): median {np.median(pose):.4f} px, p90 {np.percentile(pose, 90):.4f} px")
    print(f"visible features whose blur is shorter than their star square: {short_total}, of which "
          f"{100 * short_returned / max(short_total, 1):.1f}% returned")
    if per_frame:
        _by_ratio(ratio_visible, ratio_returned, ratio_error)
    print(f"time: {np.mean(walls):.1f} s wall, {np.mean(cpus):.1f} s CPU per frame (median "
          f"{np.median(walls):.1f} s wall, {np.median(cpus):.1f} s CPU)")
    print("stages, mean s wall per frame: "
          + ", ".join(f"{k} {v:.2f}" for k, v in mean_stage_seconds(results).items()))
    growth = np.concatenate(errors) if errors else np.full(1, np.nan)
    filtered = np.concatenate(errors_q) if errors_q else np.full(1, np.nan)
    if record is not None:
        record.add(title, frames=len(simulated), frames_extracted=extracted,
                   returned_pct=100 * np.mean(returned), median_px=np.median(growth),
                   p90_px=np.percentile(growth, 90), max_px=np.max(growth),
                   off_by_over_1px=int((growth > 1).sum()),
                   filtered_returned_pct=100 * np.mean(returned_q), filtered_max_px=np.max(filtered),
                   pose_consistent_median_px=np.median(pose), pose_consistent_p90_px=np.percentile(pose, 90),
                   short_blur_returned_pct=100 * short_returned / max(short_total, 1),
                   cpu_s_per_frame=np.mean(cpus), wall_s_per_frame=np.mean(walls))
    return SetFigures(float(np.mean(returned)), float(np.median(growth)), float(np.percentile(growth, 90)),
                      float(np.median(pose)), float(np.mean(cpus)))


def photometric_frame(sim: Simulator, index: int, white: float, electrons_per_level: float,
                      read_sigma: float = 0.7) -> SimulatedFrame:
    """Blurry frame ``index`` of ``sim`` (same pose and motion as :meth:`Simulator.frame`) with the
    paper at ``white`` grey levels (the ink scaled alike) and Poisson-Gaussian noise of
    ``electrons_per_level`` electrons per grey level and ``read_sigma`` grey levels."""
    name, kind = sim.frame_names()[index]
    cfg = sim.config
    rng = np.random.default_rng([cfg.seed, index])
    pose = synth.sample_pose(sim.pattern, sim.camera, rng, cfg.max_tilt_deg, cfg.square_px)
    motion = synth.sample_motion(sim.renderer, pose, sim.pattern, rng,
                                 rng.uniform(cfg.blur_min_px, cfg.blur_max_px),
                                 curved=bool(rng.uniform() < cfg.curved_fraction))
    truth = synth.frame_truth(name, kind, sim.pattern, sim.camera, pose, motion,
                              float(rng.uniform(*cfg.defocus_px)), rng, cfg.noise_sigma)
    black = truth.levels[0] * white / truth.levels[1]
    truth = dataclasses.replace(truth, levels=(black, white), noise=(1.0 / electrons_per_level, read_sigma))
    levels = [sim.texture(render.MIP_TEXELS_PER_SQUARE[k])
              for k in render.mip_levels_for(sim.camera, pose, sim.pattern, cfg.supersample)]
    irradiance = sim.renderer.irradiance(levels, pose, motion)
    return SimulatedFrame(render.sensor_image(irradiance, truth, rng), truth)


def photometry(title: str, frames: list[SimulatedFrame], pattern, record: benchrecord.BenchRecord) -> None:
    """Noise estimate and blocks kept with the relative and the absolute loss threshold."""
    print(f"== {title} ==")
    modes = {"relative": QualitySettings(), "absolute": QualitySettings(loss_mode="absolute")}
    used = dict.fromkeys(modes, 0)
    for fr in frames:
        t = fr.truth
        gain, read = t.noise
        r = extract_frame(fr.image.astype(np.float32), pattern, t.name)
        if r.status.value != "ok" or r.noise is None:
            print(f"{t.name}: {r.status.value} {r.message}")
            continue
        level = r.noise.level
        true_sigma = float(np.sqrt(read**2 + 1 / 12 + gain * level))
        size = fr.image.shape[::-1]
        kept = {m: int(filter_frame(r.blocks, size, q).kept.sum()) for m, q in modes.items()}
        for m in modes:
            used[m] += kept[m] >= MIN_BLOCKS
        acc = r.blocks.accepted
        ratio = np.median(r.blocks.loss[acc] / r.blocks.noise_var[acc])
        print(f"{t.name}: white {t.levels[1]:5.1f}, {1 / gain:4.1f} e/level, noise at {level:5.1f}: true "
              f"{true_sigma:.2f}, estimated {r.noise.sigma:.2f} grey levels; median loss "
              f"{np.median(r.blocks.loss[acc]):5.1f} (x{ratio:.2f} the noise variance)"
              f"; kept {kept['relative']:3d} (relative) / {kept['absolute']:3d} (absolute) "
              f"of {int(acc.sum()):3d}", flush=True)
    n = len(frames)
    print("frames used: " + ", ".join(f"{m} {used[m]}/{n} ({100 * used[m] / max(n, 1):.0f}%)" for m in modes))
    record.add(title, frames=n, **{f"used_{m}_loss_threshold": used[m] for m in modes},
               **{f"used_{m}_loss_threshold_pct": 100 * used[m] / max(n, 1) for m in modes})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--heavy", type=int, default=12, help="frames with 12-25 px blur")
    parser.add_argument("--light", type=int, default=6, help="frames with 4-15 px blur")
    parser.add_argument("--photometry", type=int, default=12,
                        help="frames with 150-250 grey levels of white and 5-20 electrons per level")
    parser.add_argument("--demo", type=int, default=4, help="frames of the demo set for the loss threshold")
    parser.add_argument("--repeat", type=int, default=0,
                        help="runs of parts 1 and 2 again, each on frames perturbed by 0.01 grey levels")
    parser.add_argument("--cache", type=Path, default=None, help="folder for simulated frames")
    parser.add_argument("--part", default="0/1", help="I/N: every N-th frame from the I-th")
    parser.add_argument("--device", default="cpu", help="torch device of the block solves (cpu, cuda)")
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    deconv = DeconvSettings(device=args.device)
    first, step = (int(v) for v in args.part.split("/"))
    torch.set_num_threads(1)
    keep_large_allocations()  # as the command line and its workers do
    if args.heavy:
        sim, heavy = frames((12.0, 25.0), args.heavy, 11, args.cache)
        heavy = heavy[first::step]
        title, settings = "12-25 px blur, adaptive window (default)", ExtractSettings(deconv=deconv)
        spread(title, sim, heavy, settings, run(title, sim, heavy, settings, record), args.repeat, record)
    if args.light:
        sim, light = frames((4.0, 15.0), args.light, 7, args.cache)
        light = light[first::step]
        run("4-15 px blur, fixed 17 px window", sim, light,
            ExtractSettings(window=WindowPolicy(largest=17), deconv=deconv), record)
        title, settings = "4-15 px blur, adaptive window (default)", ExtractSettings(deconv=deconv)
        spread(title, sim, light, settings, run(title, sim, light, settings, record), args.repeat, record)
    if args.photometry:
        sim = Simulator(SynthConfig(sharp=0, blurry=args.photometry, blur_min_px=4.0, blur_max_px=15.0,
                                    seed=23))
        grid = [(w, e) for w in (150.0, 183.0, 217.0, 250.0) for e in (5.0, 10.0, 20.0)]
        looks = [grid[i % len(grid)] for i in range(args.photometry)]
        shot = [photometric_frame(sim, i, w, e) for i, (w, e) in enumerate(looks)][first::step]
        photometry("white 150-250 grey levels, 5-20 electrons per level, 4-15 px blur", shot, sim.pattern,
                   record)
    if args.demo:
        sim = Simulator(SynthConfig())
        demo = [sim.frame(sim.config.sharp + i) for i in range(args.demo)][first::step]
        photometry("demo frames (SynthConfig())", demo, sim.pattern, record)
    record.write()


if __name__ == "__main__":
    main()
