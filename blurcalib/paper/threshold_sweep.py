"""Threshold sweep (paper section "Real World Evaluation", paragraph "Alignment evaluation",
figure ``fig:exp_real3``) on a simulated sequence.

The paper plots the median reprojection error after global alignment with the bilinear bias
field (``eq:bilinear_bias``) at ``tau_BE = 0.12`` against the loss threshold ``tau_L`` for three
configurations. Here, per configuration and ``tau_L``:

* **raw** (gray): each block's star centre from its fitted homography *before* the PSF
  re-centring (``BlockFit.H_fit``), no BE filter (``tau_BE = inf``), no local alignment;
* **be_filtered** (blue): the re-centred centres (``BlockFit.H``), BE filter at ``tau_BE``;
* **local_aligned** (red, the full pipeline): the BE filter, and the centres of the local
  alignment that :func:`blurcalib.extract.frame.extract_frame` solves over all growth-accepted blocks
  (``FrameResult.local.H``);
* **local_aligned_kept** (extra, dark red dashed): the local alignment re-solved over the blocks
  that survive the filter only (so the truncated blocks do not pull their neighbours).

Every configuration keeps the loss filter at ``tau_L`` and the BFS connectivity of
:func:`blurcalib.growth.quality.filter_frame` (with ``min_sigma_major = 0``: no frame pre-filter); the
growth's own rejections (loss above 400, BE above 0.3, not converged) apply to all. Each frame is
then aligned to the parametric camera (:func:`blurcalib.calib.alignment.align_global`, Huber loss,
``loss_weights`` of the block losses) with the bilinear bias (the paper's) and with one
translation, and two errors are measured per frame (px):

* **alignment error** (the paper's quantity): the median distance of the aligned features to
  the parametric reprojection with the aligned pose;
* **true error** (which real data cannot give): the median distance of the aligned features to
  the *true* camera's projection of the true target points, the pose refitted to them
  (:func:`blurcalib.sim.evaluate.refit_pose`). Its floor, the same measure on the exact time-averaged
  positions, is reported per frame.

Reported are the median over frames of the per-frame medians and their interquartile range (the
figure's error bars).

Protocol: the camera is :func:`blurcalib.paper.common.experiment_camera` (the
D435I-like camera at half resolution, 0.01 px lens deviation). The parametric camera ``pi_d`` and
the target points come from :func:`blurcalib.calib.sharp.calibrate_sharp` on ``sharp`` frames: by
default the true projections of their (simulator-identical) poses plus Gaussian noise of
``sharp_noise_px`` per axis (no rendering, to save time), or with ``sharp_source="extract"`` the
rendered sharp frames extracted with :meth:`ExtractSettings.sharp`. The ``blurry`` frames
(median blur ``blur_min_px`` to ``blur_max_px``) are rendered and extracted once each and kept in
memory; every configuration and threshold re-filters and re-aligns them.

Pixels follow OpenCV's convention (top-left pixel centre at ``(0, 0)``); losses are grey
levels squared.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter, NullLocator

from blurcalib.calib.alignment import MIN_BLOCKS, AlignmentError, AlignmentSettings, align_blocks
from blurcalib.calib.sharp import Calibration, calibrate_sharp
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.extract.frame import ExtractSettings, extract_frame
from blurcalib.extract.local_alignment import align_locally
from blurcalib.geometry.homography import homography_centre
from blurcalib.growth.quality import QualitySettings, filter_frame
from blurcalib.io.atomic import atomic_path, atomic_write_text, ensure_writable_dir
from blurcalib.io.results import FeatureFlags, FeatureObservation, FeatureTable
from blurcalib.paper.common import (
    BLURRY_FRAME_OPTIONS,
    BlurryFrameSettings,
    ExtractedFrame,
    Option,
    experiment_parser,
    extract_frames,
    finite,
    run_experiment_cli,
    settings_from,
)
from blurcalib.sim.evaluate import refit_pose
from blurcalib.sim.synth import Simulator, sample_pose
from blurcalib.sim.truth import TrueCamera
from blurcalib.target.pattern import StarPattern

CONFIGS: tuple[str, ...] = ("raw", "be_filtered", "local_aligned", "local_aligned_kept")
"""The configurations (see the module docstring); the first three are the paper's."""

CONFIG_STYLE: dict[str, tuple[str, str, str]] = {
    "raw": ("gray", "-", "raw H_fit translation, no BE filter, no local alignment"),
    "be_filtered": ("tab:blue", "-", "BE filtered, re-centred, no local alignment"),
    "local_aligned": ("tab:red", "-", "BE filtered + local alignment (full pipeline)"),
    "local_aligned_kept": ("darkred", ":", "BE filtered + local alignment re-solved on kept blocks"),
}
"""Colour, line style and legend label of each configuration."""

BIASES: tuple[str, ...] = ("bilinear", "translation")
"""Global alignment bias models: the paper's bilinear field, and one translation."""

PAPER_FULL_PIPELINE_PX = 0.08
"""The paper's median alignment error of the full pipeline at ``tau_L = 30`` (px)."""


@dataclass(frozen=True)
class SweepSettings(BlurryFrameSettings):
    """Fixed choices of the experiment (the blurry frames' in :class:`BlurryFrameSettings`).

    Attributes:
        blur_min_px, blur_max_px: range of a blurry frame's median blur path length (px).
        sharp: sharp frames calibrating ``pi_d`` (the paper's 20).
        blurry: blurry frames swept (the paper kept 42 of 204 real ones).
        tau_be: ``tau_BE`` of the filtered configurations (0.12).
        tau_losses: the swept ``tau_L`` (grey levels^2; ``inf``: no loss filter).
        sharp_source: ``"truth"`` (noisy true projections) or ``"extract"`` (rendered and
            extracted sharp frames) for the calibration.
        sharp_noise_px: noise per axis of the ``"truth"`` sharp features (px).
        loss: robust loss of the global alignment.
        min_blocks: a frame is aligned only with at least this many kept blocks (the engine's
            :data:`blurcalib.calib.alignment.MIN_BLOCKS`).
    """

    blur_min_px: float = 4.0
    blur_max_px: float = 15.0
    sharp: int = 20
    blurry: int = 12
    tau_be: float = 0.12
    tau_losses: tuple[float, ...] = (5.0, 10.0, 20.0, 30.0, 50.0, 100.0, math.inf)
    sharp_source: str = "truth"
    sharp_noise_px: float = 0.02
    loss: str = "huber"
    min_blocks: int = MIN_BLOCKS

    def __post_init__(self) -> None:
        if self.sharp < 5 or self.blurry < 1:
            raise ValueError(f"need at least 5 sharp and 1 blurry frame, got {self.sharp} and {self.blurry}")
        if not self.tau_losses or any(not t > 0 for t in self.tau_losses) or list(self.tau_losses) != sorted(
                self.tau_losses):
            raise ValueError(f"tau_losses must be positive and increasing, got {self.tau_losses}")
        if not self.tau_be > 0 or self.sharp_noise_px < 0:
            raise ValueError("tau_be must be positive and sharp_noise_px >= 0")
        if self.sharp_source not in ("truth", "extract"):
            raise ValueError(f"sharp_source must be 'truth' or 'extract', got {self.sharp_source!r}")
        if self.min_blocks < 8:
            raise ValueError(f"min_blocks must be >= 8, got {self.min_blocks}")
        super().__post_init__()


# ------------------------------------------------------------------------------ calibration
def sharp_observations_from_truth(sim: Simulator, indices: Sequence[int], noise_px: float, seed: int
                                  ) -> list[FeatureObservation]:
    """Sharp-frame star centres without rendering: the true projections of every feature inside
    the image in the pose the simulator gives frame ``index`` (the same draw), plus Gaussian noise
    of ``noise_px`` px per axis."""
    cfg = sim.config
    model = sim.camera.model
    P = sim.pattern.points_3d()
    L = sim.pattern.square_length_m
    flags = int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME)
    out = []
    for index in indices:
        name = sim.frame_names()[index][0]
        pose = sample_pose(sim.pattern, sim.camera, np.random.default_rng([cfg.seed, index]),
                           cfg.max_tilt_deg, cfg.square_px)
        cam = pose.transform(P)
        x = sim.camera.project(cam)
        inside = np.flatnonzero((cam[:, 2] > 0) & (x[:, 0] >= 0) & (x[:, 0] <= model.width - 1)
                                & (x[:, 1] >= 0) & (x[:, 1] <= model.height - 1))
        noisy = x[inside] + np.random.default_rng([seed, index, 1]).normal(0.0, noise_px, (len(inside), 2))
        for j, (u, v) in zip(inside, noisy, strict=True):
            fx, fy = (int(c) for c in sim.pattern.features[j])
            out.append(FeatureObservation(name, int(j), fx, fy, fx * L, fy * L, float(u), float(v), 1.0,
                                          flags))
    return out


def sharp_observations_extracted(sim: Simulator, indices: Sequence[int], device: str,
                                 progress: Callable[[str], None] | None = None) -> FeatureTable:
    """Sharp-frame star centres from rendering and extracting the frames with the sharp settings
    (:meth:`ExtractSettings.sharp`)."""
    settings = ExtractSettings.sharp(deconv=DeconvSettings(device=device))
    out = []
    for index in indices:
        frame = sim.frame(index)
        result = extract_frame(frame.image.astype(np.float32), sim.pattern, frame.truth.name, settings)
        out.append(result.features)
        if progress is not None:
            progress(f"  {frame.truth.name}: {result.status.value}, {len(result.features)} features")
    return FeatureTable.concat(out)


# ------------------------------------------------------------------------------------ sweep
@dataclass(frozen=True)
class FrameAlignment:
    """One frame aligned in one configuration, threshold and bias model.

    Attributes:
        kept: blocks kept by the filter.
        status: ``aligned``, ``too_few_blocks`` or ``failed`` (the alignment raised).
        alignment_px: median distance of the aligned features to the parametric reprojection
            (px; NaN unless aligned).
        true_px: median distance of the aligned features to the true camera's projection with
            the pose refitted (px; NaN unless aligned).
        angle: estimated angle between optical axis and target normal (rad; NaN unless aligned).
    """

    kept: int
    status: str
    alignment_px: float = math.nan
    true_px: float = math.nan
    angle: float = math.nan


def config_homographies(frame: ExtractedFrame, config: str) -> np.ndarray:
    """``(B, 3, 3)`` block homographies of a frame in a configuration (before its filter), whose
    ``H(0, 0)`` are the star centres: ``H_fit`` for ``raw``, ``H`` otherwise, with the
    extraction's local alignment for the accepted blocks in ``local_aligned``
    (``local_aligned_kept`` re-solves it after filtering, :func:`sweep_frame`)."""
    growth = frame.growth
    if config == "raw":
        return growth.fit.H_fit
    H = growth.fit.H.copy()
    if config == "local_aligned" and frame.result.local is not None:
        H[growth.accepted] = frame.result.local.H
    return H


def true_floor(frame: ExtractedFrame, camera: TrueCamera, pattern: StarPattern) -> float:
    """Median true error (px) of the exact time-averaged positions of the frame's accepted
    blocks, the pose refitted: what a perfect extraction would score (the blur path is not a
    single perspective view)."""
    growth = frame.growth
    ids = growth.feature_id[growth.accepted]
    if len(ids) < 6:
        return math.nan
    P = pattern.points_3d(ids)
    xy = frame.truth.mean[ids]
    pose = refit_pose(camera, P, xy, frame.truth.pose)
    return float(np.median(np.linalg.norm(camera.project(pose.transform(P)) - xy, axis=1)))


def _align(frame: ExtractedFrame, kept: np.ndarray, centre: np.ndarray, bias: str, calibration: Calibration,
           camera: TrueCamera, pattern: StarPattern, settings: SweepSettings) -> FrameAlignment:
    fit = frame.growth.fit
    ids = frame.growth.feature_id[kept]
    try:
        ga = align_blocks(calibration.camera, pattern, calibration.points, ids, centre[kept], fit.loss[kept],
                          AlignmentSettings(loss=settings.loss, bias=bias, min_blocks=settings.min_blocks))
    except AlignmentError:
        return FrameAlignment(len(kept), "failed")
    P = pattern.points_3d(ids)
    pose = refit_pose(camera, P, ga.corrected, frame.truth.pose)
    true = np.linalg.norm(camera.project(pose.transform(P)) - ga.corrected, axis=1)
    return FrameAlignment(len(kept), "aligned", ga.median_error, float(np.median(true)), ga.angle_to_normal)


def sweep_frame(frame: ExtractedFrame, calibration: Calibration, camera: TrueCamera, pattern: StarPattern,
                settings: SweepSettings) -> dict[tuple[str, float, str], FrameAlignment]:
    """Filter and align one extracted frame for every configuration, ``tau_L`` and bias model.

    Thresholds that keep the same blocks share one alignment.
    """
    blocks = frame.result.blocks
    out: dict[tuple[str, float, str], FrameAlignment] = {}
    cache: dict[tuple[str, bytes, str], FrameAlignment] = {}
    for config in CONFIGS:
        own = "be_filtered" if config == "local_aligned_kept" else config
        table = replace(blocks, H=config_homographies(frame, own))
        base = table.centre
        tau_be = math.inf if config == "raw" else settings.tau_be
        for tau in settings.tau_losses:
            quality = QualitySettings(tau_be=tau_be, tau_loss=tau, min_sigma_major=0.0)
            filt = filter_frame(table, frame.image_size, quality)
            kept = np.flatnonzero(filt.kept)
            centre = base
            if config == "local_aligned_kept" and len(kept):
                centre = base.copy()
                local = align_locally(table.H[kept], table.fx[kept], table.fy[kept])
                centre[kept] = homography_centre(local.H)
            for bias in BIASES:
                key = (config, kept.tobytes(), bias)
                if key not in cache:
                    cache[key] = (_align(frame, kept, centre, bias, calibration, camera, pattern, settings)
                                  if len(kept) >= settings.min_blocks
                                  else FrameAlignment(len(kept), "too_few_blocks"))
                out[(config, tau, bias)] = cache[key]
    return out


@dataclass(eq=False)
class SweepExperiment:
    """Result of :func:`analyse_sweep` / :func:`run_threshold_sweep`.

    Attributes:
        settings: the settings.
        camera: the true camera.
        calibration: the sharp-set calibration (``pi_d`` and refined target points).
        frames: the extracted blurry frames.
        floors: per frame, :func:`true_floor` (px; NaN for frames not extracted).
        cells: ``(config, tau_L, bias) ->`` one :class:`FrameAlignment` per extracted frame (in
            the order of :attr:`aligned_frames`).
        aligned_frames: indices into :attr:`frames` of the extracted frames.
    """

    settings: SweepSettings
    camera: TrueCamera = field(repr=False)
    calibration: Calibration = field(repr=False)
    frames: list[ExtractedFrame] = field(repr=False)
    floors: list[float] = field(repr=False)
    cells: dict[tuple[str, float, str], list[FrameAlignment]] = field(repr=False)
    aligned_frames: list[int] = field(repr=False)

    def kept_blocks(self, config: str, tau: float) -> int:
        """Blocks kept over all frames in a configuration at ``tau_L``."""
        return sum(a.kept for a in self.cells[(config, tau, BIASES[0])])

    def summary(self, config: str, tau: float, bias: str) -> dict[str, Any]:
        """Frames aligned, kept blocks, and the median and quartiles over frames of the per-frame
        alignment and true errors (px)."""
        cells = [a for a in self.cells[(config, tau, bias)] if a.status == "aligned"]
        row: dict[str, Any] = {"config": config, "tau_loss": _tau_json(tau), "bias": bias,
                     "frames_aligned": len(cells), "kept_blocks": self.kept_blocks(config, tau)}
        for name in ("alignment_px", "true_px"):
            values = np.array([getattr(a, name) for a in cells])
            q = np.percentile(values, [25, 50, 75]) if len(values) else [math.nan] * 3
            row.update({f"{name}_median": finite(q[1]), f"{name}_q25": finite(q[0]),
                        f"{name}_q75": finite(q[2])})
        return row


def _tau_json(tau: float) -> float | str:
    return tau if math.isfinite(tau) else "inf"


def analyse_sweep(frames: Sequence[ExtractedFrame], calibration: Calibration, camera: TrueCamera,
                  pattern: StarPattern, settings: SweepSettings) -> SweepExperiment:
    """Sweep already extracted frames (frames not ``ok`` are skipped)."""
    usable = [i for i, f in enumerate(frames) if f.ok]
    cells: dict[tuple[str, float, str], list[FrameAlignment]] = {
        (c, t, b): [] for c in CONFIGS for t in settings.tau_losses for b in BIASES}
    for i in usable:
        for key, value in sweep_frame(frames[i], calibration, camera, pattern, settings).items():
            cells[key].append(value)
    floors = [true_floor(f, camera, pattern) if f.ok else math.nan for f in frames]
    return SweepExperiment(settings, camera, calibration, list(frames), floors, cells, usable)


def simulator(settings: SweepSettings, seed: int) -> Simulator:
    """The sequence: ``sharp`` sharp frames (indices first) then ``blurry`` blurry ones."""
    return settings.simulator(settings.sharp, settings.blurry, seed)


def calibrate(sim: Simulator, settings: SweepSettings, seed: int,
              progress: Callable[[str], None] | None = None) -> Calibration:
    """``pi_d`` and the target points from the sharp frames (``settings.sharp_source``)."""
    indices = range(settings.sharp)
    observations: FeatureTable | list[FeatureObservation]
    if settings.sharp_source == "truth":
        observations = sharp_observations_from_truth(sim, indices, settings.sharp_noise_px, seed)
    else:
        observations = sharp_observations_extracted(sim, indices, settings.device, progress)
    size = (sim.camera.model.width, sim.camera.model.height)
    return calibrate_sharp(observations, sim.pattern, size)


def run_threshold_sweep(settings: SweepSettings | None = None, seed: int = 0,
                        progress: Callable[[str], None] | None = None) -> SweepExperiment:
    """Calibrate, extract the blurry frames once, and sweep (deterministic)."""
    settings = settings or SweepSettings()
    sim = simulator(settings, seed)
    calibration = calibrate(sim, settings, seed, progress)
    if progress is not None:
        progress(f"calibrated pi_d from {calibration.num_frames} sharp frames ({settings.sharp_source}): "
                 f"median {calibration.median_error:.4f} px, RMS {calibration.rms_error:.4f} px")
    blurry = range(settings.sharp, settings.sharp + settings.blurry)
    frames = extract_frames(sim, blurry, settings.extraction(), progress)
    return analyse_sweep(frames, calibration, sim.camera, sim.pattern, settings)


# ----------------------------------------------------------------------------------- output
def format_table(experiment: SweepExperiment) -> str:
    """Per bias model: for each ``tau_L`` and configuration, kept blocks and the median over
    frames of the alignment and true errors (px)."""
    s = experiment.settings

    def cell(v: float | None) -> str:
        return "-" if v is None else f"{v:.3f}"

    lines = [f"Threshold sweep (paper fig:exp_real3): tau_BE = {s.tau_be:g}; per cell kept blocks, "
             "median over frames of the alignment error / true error (px)"]
    for bias in BIASES:
        lines += ["", f"global alignment: {bias}",
                  f"{'tau_L':>7}" + "".join(f"{c:>30}" for c in CONFIGS)]
        for tau in s.tau_losses:
            cells = []
            for config in CONFIGS:
                r = experiment.summary(config, tau, bias)
                cells.append(f"{r['kept_blocks']:>5} {cell(r['alignment_px_median'])} / "
                             f"{cell(r['true_px_median'])} ({r['frames_aligned']})")
            lines.append(f"{tau:>7g}" + "".join(f"{c:>30}" for c in cells))
    floors = [f for f in experiment.floors if math.isfinite(f)]
    if floors:
        lines.append(f"\ntrue-error floor (exact time-averaged positions, pose refitted): median "
                     f"{np.median(floors):.4f} px over {len(floors)} frames")
    lines.append(f"paper: full pipeline ~{PAPER_FULL_PIPELINE_PX} px alignment error at tau_L = 30, "
                 "below BE-only (blue) and raw (gray)")
    return "\n".join(lines)


def results_json(experiment: SweepExperiment, seed: int) -> dict[str, Any]:
    """The experiment as a JSON-able dict: settings, cameras, calibration, per-frame figures,
    the summary table and every per-frame alignment."""
    settings = asdict(experiment.settings)
    settings["tau_losses"] = [_tau_json(t) for t in experiment.settings.tau_losses]
    cal = experiment.calibration
    frames = []
    for i, f in enumerate(experiment.frames):
        row: dict[str, Any] = {
            "frame": f.name, "status": f.result.status.value, "seconds": round(f.seconds, 2),
            "true_median_blur_px": finite(np.median(f.truth.blur_length[f.truth.visible])),
            "true_floor_px": finite(experiment.floors[i])}
        if f.ok:
            row["accepted"] = int(f.growth.accepted.sum())
            if f.result.local is not None:
                row["local_alignment_rms_px"] = [finite(f.result.local.rms_before),
                                                 finite(f.result.local.rms_after)]
        frames.append(row)
    names = [experiment.frames[i].name for i in experiment.aligned_frames]
    return {
        "experiment": "threshold_sweep",
        "paper": "fig:exp_real3",
        "seed": seed,
        "settings": settings,
        "true_camera": experiment.camera.to_dict(),
        "calibration": {"camera": cal.camera.to_dict(), "median_error_px": cal.median_error,
                        "rms_error_px": cal.rms_error, "num_frames": cal.num_frames},
        "paper_full_pipeline_px": PAPER_FULL_PIPELINE_PX,
        "frames": frames,
        "table": [experiment.summary(c, t, b) for b in BIASES for c in CONFIGS
                  for t in experiment.settings.tau_losses],
        "per_frame": [{"config": c, "tau_loss": _tau_json(t), "bias": b,
                       "frames": [{"frame": n, "kept": a.kept, "status": a.status,
                                   "alignment_px": finite(a.alignment_px), "true_px": finite(a.true_px),
                                   "angle_rad": finite(a.angle)}
                                  for n, a in zip(names, cells, strict=True)]}
                      for (c, t, b), cells in experiment.cells.items()],
    }


def save_fig_exp_real3(experiment: SweepExperiment, path: str | Path) -> Path:
    """``fig:exp_real3``: median over frames of the alignment error (left, the paper's measure)
    and of the true error (right) against ``tau_L``, per configuration; bars are the
    interquartile range over frames. Solid: bilinear bias (the paper's); thin dashed: one
    translation. The paper's ~0.08 px of the full pipeline at ``tau_L = 30`` is a star."""
    taus = experiment.settings.tau_losses
    finite = [t for t in taus if math.isfinite(t)]
    top = max(finite) if finite else 1.0
    x = np.array([t if math.isfinite(t) else top * 2.5 for t in taus])
    labels = [f"{t:g}" if math.isfinite(t) else "inf" for t in taus]
    fig = Figure(figsize=(11.0, 4.9), dpi=120)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    for ax, measure, title in ((axes[0], "alignment_px", "alignment error vs parametric reprojection"),
                               (axes[1], "true_px", "true error (true camera, pose refitted)")):
        shown = [PAPER_FULL_PIPELINE_PX]
        for n, config in enumerate(CONFIGS):
            colour, style, label = CONFIG_STYLE[config]
            shift = 1.0 + 0.05 * (n - (len(CONFIGS) - 1) / 2)
            for bias in BIASES:
                rows = [experiment.summary(config, t, bias) for t in taus]
                med, lo, hi = (np.array([np.nan if r[f"{measure}_{q}"] is None else r[f"{measure}_{q}"]
                                         for r in rows]) for q in ("median", "q25", "q75"))
                if bias == "bilinear":
                    ax.errorbar(x * shift, med, yerr=[med - lo, hi - med], color=colour, ls=style, marker="o",
                                ms=3.5, lw=1.2, capsize=2.5, label=label)
                    shown += [*lo, *hi]
                else:
                    ax.plot(x * shift, med, color=colour, ls="--", lw=0.7, alpha=0.7)
                    shown += list(med)
        values = [v for v in shown if math.isfinite(v) and v > 0]
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(min(values) / 1.3, max(values) * 1.3)
        ax.set_xticks(x, labels)
        ax.xaxis.set_minor_locator(NullLocator())
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(FormatStrFormatter("%.3g"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("loss threshold tau_L (grey levels^2)", fontsize=8)
        ax.set_ylabel("median over frames of the per-frame median error (px)", fontsize=8)
        ax.set_title(title, fontsize=8)
        ax.tick_params(which="both", labelsize=7)
        ax.grid(True, which="major", alpha=0.3)
    if 30.0 in taus:
        axes[0].plot([30.0], [PAPER_FULL_PIPELINE_PX], marker="*", ms=11, mfc="none", mec="tab:red",
                     ls="none", label="paper: full pipeline ~0.08 px")
    floors = [f for f in experiment.floors if math.isfinite(f)]
    if floors:
        axes[1].set_title(f"true error (true camera, pose refitted); floor of the exact time-averaged "
                          f"positions {np.median(floors):.4f} px", fontsize=8)
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=3, fontsize=7, frameon=False)
    fig.suptitle("Median reprojection error after global alignment, "
                 f"tau_BE = {experiment.settings.tau_be:g}, {len(experiment.aligned_frames)} frames; "
                 "solid: bilinear bias, dashed: translation; bars: IQR over frames (paper fig:exp_real3)",
                 fontsize=8)
    fig.tight_layout(rect=(0.0, 0.1, 1.0, 1.0))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def write_outputs(experiment: SweepExperiment, out: str | Path, seed: int) -> list[Path]:
    """Write ``threshold_sweep.json`` and ``fig_exp_real3.png`` into the folder ``out`` (created
    if needed) atomically; returns the paths."""
    out = ensure_writable_dir(out)
    return [atomic_write_text(out / "threshold_sweep.json",
                              json.dumps(results_json(experiment, seed), indent=1) + "\n"),
            save_fig_exp_real3(experiment, out / "fig_exp_real3.png")]


# --------------------------------------------------------------------------------- command
OPTIONS: tuple[Option, ...] = (Option("--sharp", "sharp", "sharp calibration frames"),
                               Option("--blurry", "blurry", "blurry frames"),
                               Option("--tau-be", "tau_be", "boundary-energy threshold of the filtered "
                                                            "configurations"),
                               *BLURRY_FRAME_OPTIONS)
"""The options of ``blurcalib experiment threshold-sweep`` (and ``--extract-sharp``)."""


def build_parser() -> argparse.ArgumentParser:
    """Options of ``blurcalib experiment threshold-sweep``."""
    parser = experiment_parser(
        "threshold-sweep",
        "Reproduce the paper's loss-threshold sweep (fig:exp_real3): median reprojection error after "
        "global alignment against tau_L, on a simulated sequence.",
        "threshold_sweep.json and fig_exp_real3.png", SweepSettings, OPTIONS)
    parser.add_argument("--extract-sharp", action="store_true",
                        help="calibrate from rendered and extracted sharp frames instead of noisy true "
                             "projections (slower)")
    return parser


def _run(args: argparse.Namespace) -> list[Path]:
    settings = settings_from(SweepSettings, OPTIONS, args,
                             sharp_source="extract" if args.extract_sharp else "truth")
    out = ensure_writable_dir(args.out)
    experiment = run_threshold_sweep(settings, args.seed, progress=print)
    print(format_table(experiment))
    return write_outputs(experiment, out, args.seed)


def main(argv: Sequence[str] | None = None) -> int:
    """``blurcalib experiment threshold-sweep [--out DIR] [--sharp N] [--blurry N] [--seed N] ...``.

    Prints progress and the table, and writes ``DIR/threshold_sweep.json`` and
    ``DIR/fig_exp_real3.png`` atomically. Returns 0, or 2 (with ``blurcalib: error: ...`` on
    stderr) for bad options, an unwritable output folder or a failed calibration.
    """
    return run_experiment_cli(build_parser(), argv, _run)
