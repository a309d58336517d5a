"""Generic calibration from sharp and blurry frames against ground truth.

Design (features are simulated, not rendered, to keep the experiment fast):

1. The true camera is :func:`blurcalib.sim.truth.d435i_like_camera` (1280 x 720, Brown-Conrady plus a
   smooth non-parametric deviation of ``deviation_px``, 0.3 px); the target is the reference A4
   star pattern (:func:`blurcalib.target.pattern.layout_pattern`) with its nominal metric points.
2. **Sharp frames** (``sharp``): poses from :func:`blurcalib.sim.synth.sample_pose`, kept only when
   at most ``sharp_outside`` of their visible features fall outside the central box (a margin of
   ``sharp_margin`` of the image size on each side): the border band and the corners are thinly
   covered, as in a hand-held sharp set. Features: the true projections plus Gaussian noise of
   ``sharp_noise_px`` per axis.
3. **Blurry frames** (``blurry``): poses anywhere (corners included) and a hand-shake motion
   (rotation-dominated twist, half of them curved) scaled to a median blur length uniform in
   ``[blur_min_px, blur_max_px]``. Features: the true *time-averaged* positions
   (:func:`blurcalib.sim.synth.frame_truth`, the PSF centroids a deconvolution recovers) plus the
   extractor's error (Gaussian of ``blurry_noise_px`` per axis
   with ``blurry_tail`` of the features at 4x that), plus one unknown translation per frame,
   uniform in a disc of ``shift_px`` (the deconvolution's translational ambiguity).
4. Four calibrations, all with the target points fixed to the nominal ones:
   (a) **parametric** Brown-Conrady from the sharp frames (``cv2.calibrateCamera``);
   (b) **generic, sharp only**: :func:`blurcalib.calib.bundle.bundle_adjust` from (a);
   (c) **generic, joint**: sharp and blurry frames in one bundle adjustment, every blurry frame
       with its own pose and a free image shift (weak prior), no orientation filter;
   (d) **generic, paper's route**: every blurry frame first aligned to (a) by
       :func:`blurcalib.calib.alignment.align_global` (one translation ``x_G``), frames within
       the paper's pi/10 of fronto-parallel dropped, then fitted with the aligned features fixed.
   (b)-(d) share one calibrated area, the bounding box of all features, and the grid (cell
   ``cell_px``), so that they differ only in their data.
5. Projection error against the truth: on a lattice of pixels, the true ray of each pixel,
   turned by the best-fit rotation (Kabsch over the lattice; a central model's orientation is a
   gauge), is projected by the estimate; the error is the distance to the pixel. Reported
   (median, p95, max) over the calibrated area, the border band (``border_px`` from the image
   edge) and the four corners (``corner_px`` squares). Error images are saved.
6. Unbiasedness ("calibration feasibility"): the mean residual of the blurry features after the
   joint fit (c), per image region (3 x 3), against the same for the sharp features.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from blurcalib.calib.alignment import align_global, orientation_ok
from blurcalib.calib.bundle import BundleResult, BundleSettings, bundle_adjust
from blurcalib.calib.sharp import solve_pose
from blurcalib.camera.generic import DEFAULT_CELL_PX, CentralGeneric, calibrated_area, fit_to_rays
from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import atomic_path, atomic_write_text, ensure_writable_dir
from blurcalib.paper.common import Option, experiment_parser, run_experiment_cli, settings_from
from blurcalib.sim.evaluate import pixel_lattice, projection_errors
from blurcalib.sim.synth import frame_truth, sample_pose
from blurcalib.sim.truth import Motion, TrueCamera, d435i_like_camera
from blurcalib.target.pattern import StarPattern, layout_pattern

__all__ = [
    "GenericExperiment",
    "GenericSettings",
    "SimFrame",
    "main",
    "run_generic_experiment",
    "simulate_frames",
]


@dataclass(frozen=True)
class GenericSettings:
    """Options of the experiment (see the module docstring)."""

    sharp: int = 20
    blurry: int = 60
    seed: int = 0
    deviation_px: float = 0.3
    sharp_noise_px: float = 0.02
    blurry_noise_px: float = 0.012
    blurry_tail: float = 0.1
    shift_px: float = 3.0
    blur_min_px: float = 4.0
    blur_max_px: float = 15.0
    sharp_margin: float = 0.15
    sharp_outside: float = 0.05
    max_tilt_deg: float = 60.0
    square_px: tuple[float, float] = (24.0, 42.0)
    cell_px: float = DEFAULT_CELL_PX
    border_px: float = 64.0
    corner_px: float = 128.0
    lattice_px: float = 4.0

    def __post_init__(self) -> None:
        if self.sharp < 5 or self.blurry < 0:
            raise ValueError(f"need at least 5 sharp frames and no negative count, got sharp={self.sharp}, "
                             f"blurry={self.blurry}")
        if not self.cell_px > 0:
            raise ValueError(f"cell_px must be positive, got {self.cell_px}")


@dataclass(eq=False)
class SimFrame:
    """One simulated frame's features.

    Attributes:
        kind: ``"sharp"`` or ``"blurry"``.
        pose: true (mid-exposure) pose.
        points: ``(n, 3)`` target points (m).
        observed: ``(n, 2)`` px what the extractor delivers (noise and, blurry, the shift).
        truth: ``(n, 2)`` px true projections (sharp) or time-averaged positions (blurry).
        shift: ``(2,)`` px the frame's unknown translation (zero for sharp frames).
    """

    kind: str
    pose: Pose
    points: np.ndarray = field(repr=False)
    observed: np.ndarray = field(repr=False)
    truth: np.ndarray = field(repr=False)
    shift: np.ndarray


def _inside(px: np.ndarray, cam: np.ndarray, width: int, height: int) -> np.ndarray:
    return ((cam[:, 2] > 0) & (px[:, 0] >= 0) & (px[:, 0] <= width - 1)
            & (px[:, 1] >= 0) & (px[:, 1] <= height - 1))


def _blur_motion(camera: TrueCamera, pose: Pose, points: np.ndarray, rng: np.random.Generator,
                 blur_px: float, curved: bool) -> Motion:
    """A hand-shake motion (as :func:`blurcalib.sim.synth.sample_motion`, without a renderer) whose
    median feature path length is ``blur_px``."""
    depth = float(pose.t[2])
    xi = np.concatenate([rng.normal(size=3) * [1.0, 1.0, 0.45],
                         rng.normal(size=3) * [0.25, 0.25, 0.35] * depth])
    xi2 = np.zeros(6)
    if curved:
        xi2 = np.concatenate([rng.normal(size=3), rng.normal(size=3) * 0.3 * depth])
        xi2 *= rng.uniform(0.4, 1.0) * np.linalg.norm(xi) / max(float(np.linalg.norm(xi2)), 1e-12)
    scale = 1.0
    for _ in range(2):
        m = Motion(xi * scale, xi2 * scale, 33)
        tracks = np.stack([camera.project(p.transform(points)) for p in m.poses(pose)])
        length = np.linalg.norm(np.diff(tracks, axis=0), axis=2).sum(axis=0)
        scale *= blur_px / max(float(np.median(length)), 1e-9)
    samples = int(np.clip(math.ceil(blur_px * 4), 9, 121))
    return Motion(xi * scale, xi2 * scale, samples)


def simulate_frames(settings: GenericSettings, pattern: StarPattern, camera: TrueCamera
                    ) -> list[SimFrame]:
    """The sharp frames, then the blurry frames (see the module docstring)."""
    rng = np.random.default_rng(settings.seed)
    model = camera.model
    W, H = model.width, model.height
    P = pattern.points_3d()
    frames: list[SimFrame] = []
    lo = np.array([W, H]) * settings.sharp_margin
    hi = np.array([W, H]) * (1 - settings.sharp_margin)
    while len(frames) < settings.sharp:
        pose = sample_pose(pattern, camera, rng, settings.max_tilt_deg, settings.square_px)
        cam = pose.transform(P)
        px = camera.project(cam)
        vis = _inside(px, cam, W, H)
        outside = np.any((px[vis] < lo) | (px[vis] > hi), axis=1)
        if outside.mean() > settings.sharp_outside:
            continue
        obs = px[vis] + rng.normal(size=(int(vis.sum()), 2)) * settings.sharp_noise_px
        frames.append(SimFrame("sharp", pose, P[vis], obs, px[vis], np.zeros(2)))
    for i in range(settings.blurry):
        pose = sample_pose(pattern, camera, rng, settings.max_tilt_deg, settings.square_px)
        cam = pose.transform(P)
        vis0 = _inside(camera.project(cam), cam, W, H)
        blur = rng.uniform(settings.blur_min_px, settings.blur_max_px)
        motion = _blur_motion(camera, pose, P[vis0], rng, blur, curved=i % 2 == 1)
        truth = frame_truth(f"blurry/{i:04d}.png", "blurry", pattern, camera, pose, motion, 0.0, rng, 2.0)
        vis = truth.visible & _inside(truth.mean, cam, W, H)
        n = int(vis.sum())
        sigma = np.where(rng.random(n) < settings.blurry_tail, 4.0, 1.0) * settings.blurry_noise_px
        angle = rng.uniform(0, 2 * np.pi)
        shift = settings.shift_px * math.sqrt(rng.uniform()) * np.array([math.cos(angle), math.sin(angle)])
        obs = truth.mean[vis] + rng.normal(size=(n, 2)) * sigma[:, None] + shift
        frames.append(SimFrame("blurry", pose, P[vis], obs, truth.mean[vis], shift))
    return frames


# ------------------------------------------------------------------------------- calibrations
def calibrate_parametric(frames: Sequence[SimFrame], width: int, height: int) -> BrownConrady:
    """Brown-Conrady (5 coefficients) by ``cv2.calibrateCamera`` with the target points fixed."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        _, K, dist, _, _ = cv2.calibrateCamera(
            [f.points.astype(np.float32) for f in frames], [f.observed.astype(np.float32) for f in frames],
            (width, height), None, None)
    finally:
        cv2.setNumThreads(threads)
    return BrownConrady.from_matrix(K, dist.reshape(-1), width, height)


def _stack(frames: Sequence[SimFrame], observed: Sequence[np.ndarray] | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    obs = [f.observed for f in frames] if observed is None else list(observed)
    index = np.concatenate([np.full(len(f.points), i) for i, f in enumerate(frames)])
    return index, np.concatenate([f.points for f in frames]), np.concatenate(obs)


def generic_fit(initial: CentralGeneric, camera: BrownConrady, frames: Sequence[SimFrame],
                shift_free: bool, observed: Sequence[np.ndarray] | None = None,
                settings: BundleSettings | None = None) -> BundleResult:
    """Bundle-adjust ``initial`` over ``frames`` (poses started by PnP with ``camera``)."""
    obs = [f.observed for f in frames] if observed is None else list(observed)
    poses = [solve_pose(camera, f.points, o, ransac_px=20.0) for f, o in zip(frames, obs, strict=True)]
    index, P, p = _stack(frames, obs)
    free = np.array([shift_free and f.kind == "blurry" for f in frames])
    return bundle_adjust(initial, poses, index, P, p, shift_free=free, settings=settings)


# ---------------------------------------------------------------------------------- evaluation
def _regions(px: np.ndarray, width: int, height: int, border: float, corner: float
             ) -> dict[str, np.ndarray]:
    x, y = px[:, 0], px[:, 1]
    edge = np.minimum.reduce([x + 0.5, y + 0.5, width - 0.5 - x, height - 0.5 - y])
    near_x = np.minimum(x + 0.5, width - 0.5 - x) < corner
    near_y = np.minimum(y + 0.5, height - 0.5 - y) < corner
    return {"area": np.ones(len(px), bool), "border": edge < border, "corners": near_x & near_y}


def _stats(err: np.ndarray) -> tuple[float, float, float]:
    e = err[np.isfinite(err)]
    if len(e) == 0:
        return math.nan, math.nan, math.nan
    return float(np.median(e)), float(np.percentile(e, 95)), float(e.max())


@dataclass(eq=False)
class GenericExperiment:
    """Result of :func:`run_generic_experiment`.

    Attributes:
        table: ``{model: {region: (median, p95, max)}}`` px, regions ``area``, ``border``,
            ``corners`` (all inside the common calibrated area).
        area_fraction: share of the image inside the calibrated area.
        bias: ``{kind: {region: (mean dx, mean dy, count)}}`` px, residuals of (c) per region.
        fits: ``{model: (seconds, cpu seconds, iterations, median reprojection error px)}``.
        frames: ``{kind: count}`` used; ``dropped_by_filter``: blurry frames (d) dropped.
        errors: ``{model: (H', W') error image}`` px on the lattice.
    """

    table: dict[str, dict[str, tuple[float, float, float]]]
    area_fraction: float
    bias: dict[str, dict[str, tuple[float, float, int]]]
    fits: dict[str, tuple[float, float, int, float]]
    frames: dict[str, int]
    dropped_by_filter: int
    errors: dict[str, np.ndarray] = field(repr=False)
    warnings: dict[str, list[str]] = field(default_factory=dict)


MODELS = ("(a) parametric, sharp", "(b) generic, sharp", "(c) generic, joint", "(d) generic, paper route")


def _region_bias(result: BundleResult, frames: Sequence[SimFrame], width: int, height: int
                 ) -> dict[str, dict[str, tuple[float, float, int]]]:
    kinds = np.concatenate([[f.kind] * len(f.points) for f in frames])
    obs = np.concatenate([f.observed for f in frames])
    names = [f"{a}-{b}" for a in ("top", "middle", "bottom") for b in ("left", "centre", "right")]
    ry = np.clip((obs[:, 1] * 3 // height).astype(int), 0, 2)
    rx = np.clip((obs[:, 0] * 3 // width).astype(int), 0, 2)
    out: dict[str, dict[str, tuple[float, float, int]]] = {}
    for kind in ("sharp", "blurry"):
        out[kind] = {}
        for k, name in enumerate(names):
            sel = (kinds == kind) & (ry * 3 + rx == k) & result.inlier
            if sel.sum() == 0:
                out[kind][name] = (math.nan, math.nan, 0)
                continue
            m = result.residuals[sel].mean(axis=0)
            out[kind][name] = (float(m[0]), float(m[1]), int(sel.sum()))
    return out


def run_generic_experiment(settings: GenericSettings | None = None,
                           pattern: StarPattern | None = None, progress: bool = True
                           ) -> GenericExperiment:
    """Simulate, calibrate (a)-(d) and compare them with the truth (module docstring)."""
    settings = settings or GenericSettings()
    pattern = pattern or layout_pattern()
    truth = d435i_like_camera(settings.seed, settings.deviation_px)
    W, H = truth.model.width, truth.model.height
    say: Callable[[str], None]
    say = (lambda msg: print(msg, file=sys.stderr, flush=True)) if progress else (lambda msg: None)
    say(f"simulating {settings.sharp} sharp and {settings.blurry} blurry frames")
    frames = simulate_frames(settings, pattern, truth)
    sharp = [f for f in frames if f.kind == "sharp"]
    blurry = [f for f in frames if f.kind == "blurry"]
    param = calibrate_parametric(sharp, W, H)
    area = calibrated_area(np.concatenate([f.observed for f in frames]), W, H)
    say(f"fitting the initial grid over x {area[0]}-{area[2]}, y {area[1]}-{area[3]} (pixel-corner)")
    initial = fit_to_rays(param.pixel_to_ray, W, H, area=area, cell_px=settings.cell_px)
    fits: dict[str, tuple[float, float, int, float]] = {}
    warnings: dict[str, list[str]] = {}
    results: dict[str, BundleResult] = {}
    say("bundle adjustment (b): sharp frames")
    results[MODELS[1]] = generic_fit(initial, param, sharp, shift_free=False)
    say("bundle adjustment (c): sharp and blurry frames, free per-frame shifts")
    results[MODELS[2]] = generic_fit(initial, param, sharp + blurry, shift_free=True)
    say("global alignment of the blurry frames to (a), then bundle adjustment (d)")
    aligned, kept = [], []
    for f in blurry:
        ga = align_global(param, f.points, f.observed, bias="translation")
        if orientation_ok(ga.pose):
            aligned.append(ga.corrected)
            kept.append(f)
    results[MODELS[3]] = generic_fit(initial, param, sharp + kept, shift_free=False,
                                     observed=[f.observed for f in sharp] + aligned)
    for name, res in results.items():
        fits[name] = (res.seconds, res.cpu_seconds, res.iterations, res.median_error)
        warnings[name] = res.warnings
    px = pixel_lattice(W, H, settings.lattice_px)
    inside = initial.in_area(px)
    regions = _regions(px, W, H, settings.border_px, settings.corner_px)
    estimates: dict[str, BrownConrady | CentralGeneric] = {MODELS[0]: param}
    estimates.update({name: res.model for name, res in results.items()})
    table: dict[str, dict[str, tuple[float, float, float]]] = {}
    errors: dict[str, np.ndarray] = {}
    shape = (len(np.unique(px[:, 1])), len(np.unique(px[:, 0])))
    for name, est in estimates.items():
        err = projection_errors(truth, est, px)
        err[~inside] = np.nan
        errors[name] = err.reshape(shape)
        table[name] = {region: _stats(err[mask]) for region, mask in regions.items()}
    return GenericExperiment(
        table=table, area_fraction=float(inside.mean()),
        bias=_region_bias(results[MODELS[2]], sharp + blurry, W, H), fits=fits,
        frames={"sharp": len(sharp), "blurry": len(blurry)},
        dropped_by_filter=len(blurry) - len(kept), errors=errors, warnings=warnings)


# ------------------------------------------------------------------------------------ output
def format_table(exp: GenericExperiment) -> str:
    """The comparison table and the unbiasedness check as text."""
    lines = [f"projection error against the truth (px; median / p95 / max), calibrated area = "
             f"{100 * exp.area_fraction:.1f}% of the image",
             f"{'model':28s} {'calibrated area':>24s} {'border band':>24s} {'corners':>24s}"]
    for name, row in exp.table.items():
        cells = ["{:.4f} / {:.4f} / {:.3f}".format(*row[r]) for r in ("area", "border", "corners")]
        lines.append(f"{name:28s} " + " ".join(f"{c:>24s}" for c in cells))
    lines.append("")
    lines.append("fits: " + "; ".join(f"{name}: {s:.1f} s wall, {c:.1f} s CPU, {it} iterations, "
                                      f"median reprojection {e:.4f} px"
                                      for name, (s, c, it, e) in exp.fits.items()))
    lines.append(f"frames: {exp.frames}; blurry frames dropped by the pi/10 filter in (d): "
                 f"{exp.dropped_by_filter}")
    lines.append("")
    lines.append("mean residual per region after the joint fit (c), px (dx, dy, count):")
    for kind, regions in exp.bias.items():
        cells = [f"{name} ({dx:+.4f}, {dy:+.4f}, {n})" for name, (dx, dy, n) in regions.items()]
        lines.append(f"  {kind}: " + "; ".join(cells))
    return "\n".join(lines)


def save_error_images(exp: GenericExperiment, out: Path, vmax: float = 0.1) -> list[Path]:
    """One colour-mapped PNG per model: error 0 (dark) .. ``vmax`` px (bright); grey outside."""
    paths = []
    for k, (_name, err) in enumerate(exp.errors.items()):
        scaled = np.clip(np.nan_to_num(err, nan=0.0) / vmax * 255, 0, 255).astype(np.uint8)
        img = cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO)
        img[~np.isfinite(err)] = 128
        img = cv2.resize(img, (img.shape[1] * 2, img.shape[0] * 2), interpolation=cv2.INTER_NEAREST)
        path = out / f"error_{'abcd'[k]}.png"
        with atomic_path(path) as tmp:
            cv2.imwrite(str(tmp), img)
        paths.append(path)
    return paths


OPTIONS: tuple[Option, ...] = (Option("--sharp", "sharp", "sharp frames"),
                               Option("--blurry", "blurry", "blurry frames"),
                               Option("--cell-px", "cell_px", "grid cell length, px"))
"""The options of ``blurcalib experiment generic``."""


def build_parser() -> argparse.ArgumentParser:
    """Options of ``blurcalib experiment generic``."""
    parser = experiment_parser("generic", __doc__.split("\n")[0],
                               "table.txt, generic.json and the error images", GenericSettings, OPTIONS)
    parser.set_defaults(seed=GenericSettings.seed)
    return parser


def _run(args: argparse.Namespace) -> list[Path]:
    settings = settings_from(GenericSettings, OPTIONS, args, seed=args.seed)
    out = ensure_writable_dir(args.out)
    t0 = time.perf_counter()
    exp = run_generic_experiment(settings)
    text = format_table(exp)
    print(text)
    for name, lines in exp.warnings.items():
        for line in lines:
            print(f"warning: {name}: {line}")
    print(f"total {time.perf_counter() - t0:.1f} s")
    paths = [atomic_write_text(out / "table.txt", text + "\n"),
             atomic_write_text(out / "generic.json", json.dumps(
                 {"settings": asdict(settings), "table": exp.table, "area_fraction": exp.area_fraction,
                  "bias": exp.bias, "fits": exp.fits, "frames": exp.frames,
                  "dropped_by_filter": exp.dropped_by_filter, "warnings": exp.warnings}, indent=1))]
    return paths + save_error_images(exp, out)


def main(argv: Sequence[str] | None = None) -> int:
    """``blurcalib experiment generic [--out DIR] [--seed N] [--sharp N] [--blurry N] [--cell-px C]``:
    prints the table and writes it, ``generic.json`` and the error images. Returns 0, or 2 (with
    ``blurcalib: error: ...`` on stderr) for bad options or an unwritable output folder."""
    return run_experiment_cli(build_parser(), argv, _run)
