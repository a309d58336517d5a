"""PSF quality analysis (paper section "Real World Evaluation", figures ``fig:exp_real1`` and
``fig:exp_real2``) on simulated motion-blurred frames.

Protocol, adapted from the paper's 204 hand-held D435I frames to the simulator:

1. The camera is :func:`blurcalib.paper.common.experiment_camera`: the D435I-like
   Brown-Conrady camera of :func:`blurcalib.sim.truth.d435i_like_camera` resized by ``scale``
   (0.5: 640 x 360 px, to keep a run within minutes on two cores) with a non-parametric lens
   deviation of ``deviation_px``.
   The target is the reference A4 pattern; frames are :class:`blurcalib.sim.synth.Simulator`'s
   blurry frames (``SynthConfig(sharp=0, blurry=frames)``, median blur length uniform in
   ``[blur_min_px, blur_max_px]``, hand-shake motion with roll and zoom, defocus, noise).
2. Every frame is extracted once with the blurry-frame engine
   (:func:`blurcalib.extract.frame.extract_frame`, ``K x K`` PSF window, 17 by default as in the
   paper). Each fitted block carries its deconvolution loss (``eq:deconvolution``, grey
   levels^2), boundary energy ratio (BE, the share of PSF energy in the window's outer two-pixel
   ring), PSF second-moment ellipse (``sigma_major`` px, eccentricity
   ``sqrt(1 - (sigma_minor / sigma_major)^2)``: 0 round, towards 1 elongated), and its PSF
   before (``BlockFit.psf_fit``, with ``BlockFit.H_fit``) and after (``BlockFit.psf``,
   ``BlockFit.H``) the sub-pixel centroid re-centring.

Outputs:

* ``fig_exp_real1.png``: the PSF field of one frame, every accepted block's PSF normalised to its
  peak and drawn in its square's place, without (``psf_fit``) and with (``psf``) the centroid
  correction, and a bottom row magnifying the PSFs of the red-boxed region (a cross marks the
  kernel centre, a dot the centroid). The frame is the one whose true blur varies most over the
  field (:func:`field_variation`: roll and zoom blur) among frames whose PSFs fit the window.
* ``fig_exp_real2.png``: all fitted blocks of all frames: loss against ``sigma_major`` coloured by
  eccentricity, and loss against BE coloured by ``sigma_major``, with the filter thresholds
  ``tau_BE`` and ``tau_L``.
* ``psf_quality.json``: settings, per-frame and per-block figures, and the statistics of
  :func:`quality_statistics` (loss above / below BE 0.15, the paper's observation; loss against
  blur size; the effect of the re-centring against the ground-truth time-averaged positions).

Units: pixels in the OpenCV convention (top-left pixel centre at ``(0, 0)``); losses in grey
levels squared (8-bit frames); PSFs follow ``docs/conventions.md``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.stats import spearmanr

from blurcalib.geometry.homography import homography_centre
from blurcalib.io.atomic import atomic_path, atomic_write_text, ensure_writable_dir
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
from blurcalib.paper.psf_field import FieldChoice, choose_field_frame, save_fig_exp_real1
from blurcalib.sim.synth import Simulator
from blurcalib.sim.truth import TrueCamera
from blurcalib.target.pattern import StarPattern

PAPER_CLAIMS: dict[str, str] = {
    "fig:exp_real1": "without centroid correction PSFs near the image boundary shift off centre and "
                     "become irregular; with re-centring the field is spatially coherent",
    "fig:exp_real2 right": "elements with BE > 0.15 exhibit systematically elevated loss",
    "fig:exp_real2 left": "low sigma_major (defocus dominated, high eccentricity) frames have higher "
                          "and more variable loss than motion-blur dominated ones",
}
"""The paper's qualitative observations, quoted in the JSON beside the measurements."""


# ------------------------------------------------------------------------------ block figures
@dataclass(frozen=True)
class BlockFigures:
    """Figures of every fitted block (finite loss, BE and ``sigma_major``) of the extracted
    frames, pooled (``n`` blocks).

    Attributes:
        frame: ``(n,)`` index of the block's frame in the frame list.
        block: ``(n,)`` index of the block in its frame's ``growth.fit``.
        feature_id, fx, fy: ``(n,)`` the block's feature.
        accepted: ``(n,)`` bool, accepted by the growth (others were rejected for loss > 400,
            BE > 0.3 or no convergence, but have figures).
        loss: ``(n,)`` grey levels^2.
        boundary_energy: ``(n,)`` BE ratio.
        sigma_major: ``(n,)`` px.
        eccentricity: ``(n,)`` in ``[0, 1)``.
        centroid: ``(n, 2)`` px, centroid of ``psf_fit`` from the kernel centre: the re-centring
            moved the star centre by it.
        centre_fit: ``(n, 2)`` px, star centre ``H_fit(0, 0)`` before re-centring.
        centre: ``(n, 2)`` px, star centre ``H(0, 0)`` after re-centring.
        true_mean: ``(n, 2)`` px, the feature's true time-averaged image position.
        true_blur: ``(n,)`` px, the feature's true blur path length.
        radius: ``(n,)`` distance of the star centre from the image centre over the half
            diagonal (0 centre, 1 corner).
    """

    frame: np.ndarray
    block: np.ndarray
    feature_id: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    accepted: np.ndarray
    loss: np.ndarray
    boundary_energy: np.ndarray
    sigma_major: np.ndarray
    eccentricity: np.ndarray
    centroid: np.ndarray
    centre_fit: np.ndarray
    centre: np.ndarray
    true_mean: np.ndarray
    true_blur: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def error_fit(self) -> np.ndarray:
        """``(n,)`` px, distance of the un-re-centred star centre to the true time-averaged one."""
        return cast(np.ndarray, np.linalg.norm(self.centre_fit - self.true_mean, axis=1))

    @property
    def error_recentred(self) -> np.ndarray:
        """``(n,)`` px, distance of the re-centred star centre to the true time-averaged one."""
        return cast(np.ndarray, np.linalg.norm(self.centre - self.true_mean, axis=1))


def block_figures(frames: Sequence[ExtractedFrame], pattern: StarPattern) -> BlockFigures:
    """Collect :class:`BlockFigures` from the frames' fits (frames not ``ok`` contribute none)."""
    cols: dict[str, list[np.ndarray]] = {name: [] for name in BlockFigures.__dataclass_fields__}
    for i, f in enumerate(frames):
        if not f.ok:
            continue
        growth = f.growth
        fit = growth.fit
        k = np.flatnonzero(np.isfinite(fit.loss) & np.isfinite(fit.boundary_energy)
                           & np.isfinite(fit.sigma_major))
        ids = growth.feature_id[k]
        centre = fit.centre[k]
        w, h = f.image_size
        half_diagonal = 0.5 * math.hypot(w, h)
        values = {
            "frame": np.full(len(k), i), "block": k, "feature_id": ids,
            "fx": pattern.features[ids, 0], "fy": pattern.features[ids, 1],
            "accepted": growth.accepted[k], "loss": fit.loss[k],
            "boundary_energy": fit.boundary_energy[k], "sigma_major": fit.sigma_major[k],
            "eccentricity": fit.eccentricity[k], "centroid": fit.centroid[k],
            "centre_fit": homography_centre(fit.H_fit[k]),
            "centre": centre, "true_mean": f.truth.mean[ids], "true_blur": f.truth.blur_length[ids],
            "radius": np.hypot(centre[:, 0] - (w - 1) / 2, centre[:, 1] - (h - 1) / 2) / half_diagonal,
        }
        for name, v in values.items():
            cols[name].append(np.asarray(v))
    pairs = {"centroid", "centre_fit", "centre", "true_mean"}
    integers = {"frame", "block", "feature_id", "fx", "fy"}

    def empty(name: str) -> np.ndarray:
        dtype = bool if name == "accepted" else np.int64 if name in integers else np.float64
        return np.zeros((0, 2) if name in pairs else (0,), dtype=dtype)

    return BlockFigures(**{name: np.concatenate(v) if v else empty(name) for name, v in cols.items()})


# ------------------------------------------------------------------------------- statistics
def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.ptp(a[ok]) == 0 or np.ptp(b[ok]) == 0:
        return math.nan
    return float(spearmanr(a[ok], b[ok]).statistic)


def _group(loss: np.ndarray) -> dict[str, float | int | None]:
    """Count, median and quartiles of a group's losses (grey levels^2)."""
    if len(loss) == 0:
        return {"count": 0, "median_loss": None, "q25_loss": None, "q75_loss": None}
    q25, q50, q75 = np.percentile(loss, [25, 50, 75])
    return {"count": len(loss), "median_loss": finite(q50), "q25_loss": finite(q25),
            "q75_loss": finite(q75)}


def _split(loss: np.ndarray, key: np.ndarray, threshold: float) -> dict[str, Any]:
    below, above = _group(loss[key <= threshold]), _group(loss[key > threshold])
    ratio = (above["median_loss"] / below["median_loss"]
             if above["median_loss"] is not None and below["median_loss"] else None)
    return {"threshold": threshold, "below": below, "above": above,
            "median_ratio_above_below": finite(ratio) if ratio is not None else None}


@dataclass(frozen=True)
class PsfQualitySettings(BlurryFrameSettings):
    """Fixed choices of the experiment (the blurry frames' in :class:`BlurryFrameSettings`).

    Attributes:
        frames: blurry frames simulated and extracted (the paper: 204 real frames).
        tau_be: ``tau_BE``, the boundary-energy threshold drawn and counted (0.12).
        tau_loss: ``tau_L``, the loss threshold drawn and counted (grey levels^2, 30).
        be_split: BE above which the paper observes elevated loss (0.15).
        sigma_split: ``sigma_major`` (px) splitting defocus-dominated from motion-dominated
            blocks (the paper's frame pre-filter, 3.8).
        magnified: PSFs shown in ``fig:exp_real1``'s bottom row.
        field_min_blur_px: ``fig:exp_real1`` prefers frames whose true median blur is at least
            this (px), so that the PSFs show their shape.
        be_bins: bin edges of BE for the binned statistics.
    """

    frames: int = 8
    tau_be: float = 0.12
    tau_loss: float = 30.0
    be_split: float = 0.15
    sigma_split: float = 3.8
    magnified: int = 4
    field_min_blur_px: float = 6.0
    be_bins: tuple[float, ...] = (0.0, 0.05, 0.12, 0.15, 0.2, 0.3, math.inf)

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"need at least 1 frame, got {self.frames}")
        if self.magnified < 1:
            raise ValueError(f"magnified must be >= 1, got {self.magnified}")
        if len(self.be_bins) < 2 or list(self.be_bins) != sorted(set(self.be_bins)):
            raise ValueError(f"be_bins must be at least 2 increasing edges, got {self.be_bins}")
        super().__post_init__()


def quality_statistics(blocks: BlockFigures, settings: PsfQualitySettings) -> dict[str, Any]:
    """The numbers behind ``fig:exp_real2`` and the centroid correction of ``fig:exp_real1``.

    * ``be_split`` / ``be_tau``: loss of the blocks with BE at most / above 0.15 and ``tau_BE``
      (pooled over frames, so frame-to-frame differences of noise and blur enter);
    * ``be_split_motion``: the same split at 0.15 among the motion-dominated blocks
      (``sigma_major`` at least 3.8 px), which removes the confound of small-blur frames (BE
      near 0) having a different loss level;
    * ``be_bins``: per BE bin, the blocks' loss and the distance of their re-centred star centre
      to the true time-averaged position (px);
    * ``within_frame_spearman_loss_be``: the median over frames (with at least 20 blocks and a BE
      range above 0.05) of the rank correlation of loss with BE inside the frame;
    * ``sigma_split``: loss of the blocks with ``sigma_major`` below / above 3.8 px;
    * ``spearman``: rank correlations of loss with BE and with ``sigma_major``, of eccentricity
      with ``sigma_major``, of ``sigma_major`` with the true blur length;
    * ``filter``: among growth-accepted blocks, the shares removed by ``BE > tau_BE`` and then by
      ``loss > tau_L`` (before the connectivity step);
    * ``recentring``: over accepted blocks, ``|centroid|`` of ``psf_fit`` (how far the fitted
      PSF sits off the window centre), its rank correlation with the distance from the image
      centre, and the star centres' distances to the true time-averaged positions before and
      after re-centring (px).
    """
    acc = blocks.accepted
    loss, be, sig = blocks.loss, blocks.boundary_energy, blocks.sigma_major
    high_be = acc & (be > settings.tau_be)
    high_loss = acc & ~high_be & (loss > settings.tau_loss)
    n_acc = max(int(acc.sum()), 1)
    cmag = np.linalg.norm(blocks.centroid, axis=1)
    err_fit, err_rc = blocks.error_fit[acc], blocks.error_recentred[acc]

    def pct(v: np.ndarray, q: float) -> float | None:
        return finite(np.percentile(v, q)) if len(v) else None

    err_all = blocks.error_recentred
    bins = []
    be_clipped = np.maximum(be, 0.0)  # round-off leaves some untruncated kernels at -1e-17
    for lo, hi in itertools.pairwise(settings.be_bins):
        sel = (be_clipped >= lo) & (be_clipped < hi)
        bins.append({"be_min": lo, "be_max": hi if math.isfinite(hi) else "inf", **_group(loss[sel]),
                     "median_error_after_px": pct(err_all[sel], 50)})
    within = []
    for i in np.unique(blocks.frame):
        sel = blocks.frame == i
        if sel.sum() >= 20 and np.ptp(be[sel]) > 0.05:
            within.append(_spearman(loss[sel], be[sel]))
    within = [v for v in within if math.isfinite(v)]
    return {
        "blocks": len(blocks), "accepted": int(acc.sum()),
        "frames": len(np.unique(blocks.frame)),
        "median_loss": pct(loss, 50), "median_loss_accepted": pct(loss[acc], 50),
        "be_split": _split(loss, be, settings.be_split),
        "be_tau": _split(loss, be, settings.tau_be),
        "be_split_accepted": _split(loss[acc], be[acc], settings.be_split),
        "sigma_split": _split(loss, sig, settings.sigma_split),
        "be_split_motion": _split(loss[sig >= settings.sigma_split], be[sig >= settings.sigma_split],
                                  settings.be_split),
        "be_bins": bins,
        "within_frame_spearman_loss_be": {"frames": len(within),
                                          "median": finite(np.median(within)) if within else None},
        "spearman": {"loss_boundary_energy": finite(_spearman(loss, be)),
                     "loss_sigma_major": finite(_spearman(loss, sig)),
                     "eccentricity_sigma_major": finite(_spearman(blocks.eccentricity, sig)),
                     "sigma_major_true_blur": finite(_spearman(sig, blocks.true_blur))},
        "filter": {"share_high_be": finite(high_be.sum() / n_acc),
                   "share_high_loss": finite(high_loss.sum() / n_acc),
                   "share_kept": finite((acc & ~high_be & ~high_loss).sum() / n_acc)},
        "recentring": {"median_centroid_px": pct(cmag[acc], 50), "p90_centroid_px": pct(cmag[acc], 90),
                       "max_centroid_px": pct(cmag[acc], 100),
                       "spearman_centroid_radius": finite(_spearman(cmag[acc], blocks.radius[acc])),
                       "median_error_before_px": pct(err_fit, 50), "p90_error_before_px": pct(err_fit, 90),
                       "median_error_after_px": pct(err_rc, 50), "p90_error_after_px": pct(err_rc, 90)},
    }


def frame_rows(frames: Sequence[ExtractedFrame], blocks: BlockFigures, settings: PsfQualitySettings
               ) -> list[dict[str, Any]]:
    """Per-frame figures: status, block counts, true and estimated blur, loss, BE, the share
    kept by the BE / loss thresholds, and the re-centring's effect (px)."""
    rows = []
    for i, f in enumerate(frames):
        sel = (blocks.frame == i) & blocks.accepted
        row: dict[str, Any] = {"frame": f.name, "status": f.result.status.value, "message": f.result.message,
                     "seconds": round(f.seconds, 2),
                     "true_median_blur_px": finite(np.median(f.truth.blur_length[f.truth.visible])),
                     "defocus_sigma_px": finite(f.truth.defocus_sigma),
                     "blocks": int((blocks.frame == i).sum()), "accepted": int(sel.sum())}
        if sel.any():
            kept = (blocks.boundary_energy[sel] <= settings.tau_be) & (blocks.loss[sel] <= settings.tau_loss)
            row.update(
                median_sigma_major_px=finite(np.median(blocks.sigma_major[sel])),
                median_loss=finite(np.median(blocks.loss[sel])),
                median_boundary_energy=finite(np.median(blocks.boundary_energy[sel])),
                share_kept=finite(kept.mean()),
                median_centroid_px=finite(np.median(np.linalg.norm(blocks.centroid[sel], axis=1))),
                median_error_before_px=finite(np.median(blocks.error_fit[sel])),
                median_error_after_px=finite(np.median(blocks.error_recentred[sel])))
        rows.append(row)
    return rows


# ------------------------------------------------------------------------- cross-frame scatter
def save_fig_exp_real2(blocks: BlockFigures, settings: PsfQualitySettings, path: str | Path) -> Path:
    """``fig:exp_real2``: every fitted block of every frame. Left: loss against ``sigma_major``
    coloured by eccentricity; right: loss against BE coloured by ``sigma_major``. Lines mark
    ``tau_L`` (both), ``tau_BE`` and the paper's BE 0.15 (right) and ``sigma_major`` 3.8 px
    (left), and a step line the median loss per BE bin; growth-rejected blocks are drawn as
    crosses."""
    fig = Figure(figsize=(11.0, 4.4), dpi=120)
    FigureCanvasAgg(fig)
    left, right = fig.subplots(1, 2)
    acc = blocks.accepted
    loss = np.maximum(blocks.loss, 1e-2)
    panels = ((left, blocks.sigma_major, blocks.eccentricity, "eccentricity", (0.0, 1.0),
               "sigma_major (px)"),
              (right, blocks.boundary_energy, blocks.sigma_major, "sigma_major (px)",
               (0.0, float(np.nanpercentile(blocks.sigma_major, 98)) if len(blocks) else 1.0),
               "boundary energy ratio BE"))
    for ax, x, colour, label, (vmin, vmax), xlabel in panels:
        image = ax.scatter(x[acc], loss[acc], c=colour[acc], s=5, cmap="viridis", vmin=vmin, vmax=vmax,
                           linewidths=0, label="accepted by the growth")
        ax.scatter(x[~acc], loss[~acc], c=colour[~acc], s=9, cmap="viridis", vmin=vmin, vmax=vmax,
                   marker="x", linewidths=0.6, label="rejected by the growth")
        ax.axhline(settings.tau_loss, color="tab:red", lw=0.9, label=f"tau_L = {settings.tau_loss:g}")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel("deconvolution loss (grey levels^2)", fontsize=8)
        ax.tick_params(which="both", labelsize=7)
        bar = fig.colorbar(image, ax=ax)
        bar.set_label(label, fontsize=8)
        bar.ax.tick_params(labelsize=7)
    left.axvline(settings.sigma_split, color="grey", lw=0.8, ls="--",
                 label=f"sigma_major = {settings.sigma_split:g} px")
    right.axvline(settings.tau_be, color="tab:red", lw=0.9, ls="-", label=f"tau_BE = {settings.tau_be:g}")
    right.axvline(settings.be_split, color="grey", lw=0.8, ls="--", label=f"BE = {settings.be_split:g}")
    stats = quality_statistics(blocks, settings)
    if len(blocks):
        bins = stats["be_bins"]
        last = max(float(np.max(blocks.boundary_energy)), bins[-1]["be_min"] + 0.01)
        edges = [b["be_min"] for b in bins] + [last if bins[-1]["be_max"] == "inf" else bins[-1]["be_max"]]
        values = [np.nan if b["median_loss"] is None else b["median_loss"] for b in bins]
        right.stairs(values, edges, baseline=None, color="black", lw=1.0, label="median loss per BE bin")

    def medians(key: str) -> str:
        values = (stats[key][g]["median_loss"] for g in ("below", "above"))
        return " / ".join("-" if v is None else f"{v:.1f}" for v in values)

    right.set_title(f"median loss BE <= / > {settings.be_split:g}: {medians('be_split')}; only "
                    f"sigma_major >= {settings.sigma_split:g} px: {medians('be_split_motion')}", fontsize=8)
    left.set_title(f"median loss sigma_major <= / > {settings.sigma_split:g} px: {medians('sigma_split')}",
                   fontsize=8)
    for ax in (left, right):
        ax.legend(fontsize=6, loc="upper left")
    fig.suptitle(f"Cross-frame PSF quality: {len(blocks)} fitted blocks of {stats['frames']} frames "
                 "(paper fig:exp_real2)", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


# ---------------------------------------------------------------------------------- experiment
@dataclass(eq=False)
class PsfQualityExperiment:
    """Result of :func:`analyse_psf_quality`.

    Attributes:
        settings: the settings.
        camera: the true camera.
        frames: the extracted frames.
        blocks: every fitted block's figures.
        rows: per-frame figures (:func:`frame_rows`).
        statistics: :func:`quality_statistics`.
        field: the frame and region of ``fig:exp_real1`` (None when no frame was extracted).
    """

    settings: PsfQualitySettings
    camera: TrueCamera = field(repr=False)
    frames: list[ExtractedFrame] = field(repr=False)
    blocks: BlockFigures = field(repr=False)
    rows: list[dict[str, Any]] = field(repr=False)
    statistics: dict[str, Any] = field(repr=False)
    field: FieldChoice | None = None


def analyse_psf_quality(frames: Sequence[ExtractedFrame], camera: TrueCamera, pattern: StarPattern,
                        settings: PsfQualitySettings) -> PsfQualityExperiment:
    """Figures, statistics and the ``fig:exp_real1`` frame from already extracted frames."""
    blocks = block_figures(frames, pattern)
    return PsfQualityExperiment(settings, camera, list(frames), blocks, frame_rows(frames, blocks, settings),
                                quality_statistics(blocks, settings),
                                choose_field_frame(frames, camera, pattern, settings.tau_be,
                                                   settings.field_min_blur_px, settings.magnified))


def simulator(settings: PsfQualitySettings, seed: int) -> Simulator:
    """The experiment's simulator: ``settings.frames`` blurry frames, no sharp ones."""
    return settings.simulator(0, settings.frames, seed)


def run_psf_quality(settings: PsfQualitySettings | None = None, seed: int = 0,
                    progress: Callable[[str], None] | None = None) -> PsfQualityExperiment:
    """Simulate and extract ``settings.frames`` blurry frames, then analyse them (deterministic)."""
    settings = settings or PsfQualitySettings()
    sim = simulator(settings, seed)
    frames = extract_frames(sim, range(settings.frames), settings.extraction(), progress)
    return analyse_psf_quality(frames, sim.camera, sim.pattern, settings)


# ------------------------------------------------------------------------------------- output
def format_table(experiment: PsfQualityExperiment) -> str:
    """Per-frame table and the summary statistics beside the paper's observations."""
    def cell(v: float | None, spec: str = ".2f") -> str:
        return "-" if v is None else format(v, spec)

    lines = ["PSF quality (paper fig:exp_real1, fig:exp_real2); accepted blocks per frame",
             f"{'frame':<18}{'status':>10}{'acc/blk':>9}{'blur px':>9}{'sig_maj':>8}{'loss':>7}"
             f"{'BE':>6}{'kept':>6}{'|c| px':>8}{'err fit':>8}{'err rc':>8}{'s':>6}"]
    for r in experiment.rows:
        lines.append(f"{r['frame']:<18}{r['status']:>10}{r['accepted']:>4}/{r['blocks']:<4}"
                     f"{cell(r['true_median_blur_px'], '.1f'):>9}{cell(r.get('median_sigma_major_px')):>8}"
                     f"{cell(r.get('median_loss'), '.1f'):>7}{cell(r.get('median_boundary_energy')):>6}"
                     f"{cell(r.get('share_kept')):>6}{cell(r.get('median_centroid_px')):>8}"
                     f"{cell(r.get('median_error_before_px'), '.3f'):>8}"
                     f"{cell(r.get('median_error_after_px'), '.3f'):>8}{r['seconds']:>6.0f}")
    s = experiment.statistics
    lines.append(f"{s['blocks']} fitted blocks ({s['accepted']} accepted by the growth) in "
                 f"{s['frames']} frames")
    for key, name in (("be_split", "BE"), ("be_tau", "BE"), ("sigma_split", "sigma_major"),
                      ("be_split_motion", "(sigma_major >= 3.8 px) BE")):
        sp = s[key]
        lines.append(f"  median loss {name} <= {sp['threshold']:g}: {cell(sp['below']['median_loss'])} "
                     f"({sp['below']['count']} blocks), > {sp['threshold']:g}: "
                     f"{cell(sp['above']['median_loss'])} ({sp['above']['count']} blocks)")
    lines.append("  by BE: " + "; ".join(
        f"[{b['be_min']:g}, {b['be_max']}) n={b['count']} loss {cell(b['median_loss'], '.1f')} "
        f"err {cell(b['median_error_after_px'], '.3f')} px" for b in s["be_bins"]))
    wf = s["within_frame_spearman_loss_be"]
    lines.append(f"  within-frame Spearman(loss, BE): median {cell(wf['median'])} over {wf['frames']} frames")
    sp = s["spearman"]
    lines.append(f"  Spearman: loss~BE {cell(sp['loss_boundary_energy'])}, loss~sigma_major "
                 f"{cell(sp['loss_sigma_major'])}, eccentricity~sigma_major "
                 f"{cell(sp['eccentricity_sigma_major'])}, sigma_major~true blur "
                 f"{cell(sp['sigma_major_true_blur'])}")
    rc = s["recentring"]
    lines.append(f"  re-centring: |centroid of psf_fit| median {cell(rc['median_centroid_px'])} px, "
                 f"p90 {cell(rc['p90_centroid_px'])} px (Spearman with radius "
                 f"{cell(rc['spearman_centroid_radius'])}); star centre vs true time-averaged position: "
                 f"before {cell(rc['median_error_before_px'], '.3f')} px, after "
                 f"{cell(rc['median_error_after_px'], '.3f')} px (medians)")
    if experiment.field is not None:
        lines.append(f"  fig:exp_real1 frame: {experiment.frames[experiment.field.frame].name} "
                     f"(field variation {experiment.field.variation:.2f})")
    return "\n".join(lines)


def results_json(experiment: PsfQualityExperiment, seed: int) -> dict[str, Any]:
    """The experiment as a JSON-able dict: settings, camera, per-frame rows, statistics, the
    ``fig:exp_real1`` choice and every block's figures (columns)."""
    b = experiment.blocks
    frames = experiment.frames

    def column(values: np.ndarray) -> list[Any]:
        return [finite(v) for v in np.asarray(values, dtype=np.float64).tolist()]

    choice = experiment.field
    return {
        "experiment": "psf_quality",
        "paper": "fig:exp_real1, fig:exp_real2",
        "seed": seed,
        "settings": {**asdict(experiment.settings),
                     "be_bins": [v if math.isfinite(v) else "inf" for v in experiment.settings.be_bins]},
        "camera": experiment.camera.to_dict(),
        "paper_claims": PAPER_CLAIMS,
        "statistics": experiment.statistics,
        "frames": experiment.rows,
        "field_frame": None if choice is None else {
            "frame": frames[choice.frame].name, "variation": finite(choice.variation),
            "region_features": [int(frames[choice.frame].growth.feature_id[k]) for k in choice.region],
            "region_box_px": [finite(v) for v in choice.box]},
        "blocks": {
            "frame": [frames[i].name for i in b.frame.tolist()],
            "feature_id": b.feature_id.tolist(), "fx": b.fx.tolist(), "fy": b.fy.tolist(),
            "accepted": b.accepted.tolist(), "loss": column(b.loss),
            "boundary_energy": column(b.boundary_energy), "sigma_major_px": column(b.sigma_major),
            "eccentricity": column(b.eccentricity), "centroid_x_px": column(b.centroid[:, 0]),
            "centroid_y_px": column(b.centroid[:, 1]), "true_blur_px": column(b.true_blur),
            "error_before_px": column(b.error_fit), "error_after_px": column(b.error_recentred)},
    }


def write_outputs(experiment: PsfQualityExperiment, out: str | Path, seed: int) -> list[Path]:
    """Write ``psf_quality.json``, ``fig_exp_real2.png`` and (when a frame was extracted)
    ``fig_exp_real1.png`` into the folder ``out`` (created if needed) atomically; returns the
    paths written."""
    out = ensure_writable_dir(out)
    paths = [atomic_write_text(out / "psf_quality.json", json.dumps(results_json(experiment, seed), indent=1)
                               + "\n"),
             save_fig_exp_real2(experiment.blocks, experiment.settings, out / "fig_exp_real2.png")]
    if experiment.field is not None:
        paths.append(save_fig_exp_real1(experiment.frames, experiment.field, out / "fig_exp_real1.png"))
    return paths


# ------------------------------------------------------------------------------------ command
OPTIONS: tuple[Option, ...] = (Option("--frames", "frames", "blurry frames"), *BLURRY_FRAME_OPTIONS)
"""The options of ``blurcalib experiment psf-quality``."""


def build_parser() -> argparse.ArgumentParser:
    """Options of ``blurcalib experiment psf-quality``."""
    return experiment_parser(
        "psf-quality", "Reproduce the paper's PSF field and PSF quality figures (fig:exp_real1, "
                       "fig:exp_real2) on simulated motion-blurred frames.",
        "psf_quality.json and the figures", PsfQualitySettings, OPTIONS)


def _run(args: argparse.Namespace) -> list[Path]:
    settings = settings_from(PsfQualitySettings, OPTIONS, args)
    out = ensure_writable_dir(args.out)
    print(f"extracting {settings.frames} blurry frames ({settings.kernel_size}x{settings.kernel_size} "
          f"PSF window)")
    experiment = run_psf_quality(settings, args.seed, progress=print)
    print(format_table(experiment))
    return write_outputs(experiment, out, args.seed)


def main(argv: Sequence[str] | None = None) -> int:
    """``blurcalib experiment psf-quality [--out DIR] [--frames N] [--seed N] ...``.

    Prints per-frame progress and the table, and writes ``DIR/psf_quality.json``,
    ``DIR/fig_exp_real1.png`` and ``DIR/fig_exp_real2.png`` atomically. Returns 0, or 2 (with
    ``blurcalib: error: ...`` on stderr) for bad options or an unwritable output folder.
    """
    return run_experiment_cli(build_parser(), argv, _run)
