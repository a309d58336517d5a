"""Feature extraction from one frame: seed, grow, re-centre, align locally, tabulate.

:func:`extract_frame`: find the tag (:mod:`blurcalib.growth.seed`), grow blocks front by
front with the batched local deconvolution (:mod:`blurcalib.growth.grow`, :mod:`blurcalib.deconv.blocks`;
PSFs come back re-centred on their centroids, so a block's star centre ``H(0, 0)`` is the centre
of the star's time-averaged image), optionally solve the local alignment
(:mod:`blurcalib.extract.local_alignment`) and turn accepted blocks into feature observations. With
``ExtractSettings(kind="auto")`` each frame is classified sharp or blurry from its own measured
blur (:func:`ring_blur`, the median blur extent of the tag ring's fitted PSFs, against
:attr:`ExtractSettings.sharp_below_px`); the kind and the blur are recorded in ``frames.csv``.
Many frames are run by :mod:`blurcalib.runs`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from blurcalib.deconv.convolution import denormals_flushed
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.extract.local_alignment import LocalAlignment, align_locally, shared_corners
from blurcalib.growth.grow import grow
from blurcalib.growth.ledger import Growth, GrowthEvent
from blurcalib.growth.noise import NoiseModel, frame_noise
from blurcalib.growth.seed import (
    DEFAULT_SCALES,
    Seed,
    SeedError,
    seed_frame,
)
from blurcalib.growth.settings import GrowSettings
from blurcalib.growth.window import SHARP_START, WindowPolicy
from blurcalib.io.record import FrameRecord, FrameStatus, split_fit_seconds
from blurcalib.io.results import (
    BlockTable,
    FeatureFlags,
    FeatureTable,
)
from blurcalib.io.text import printable_name
from blurcalib.psf.kernel import blur_extent
from blurcalib.target.pattern import StarPattern

FRAME_KINDS: tuple[str, ...] = ("auto", "sharp", "blurry")
"""Values of :attr:`ExtractSettings.kind`."""

SHARP_BELOW_PX = 5.0
"""Default :attr:`ExtractSettings.sharp_below_px`: a frame whose measured blur (:func:`ring_blur`)
is below this is sharp. Measured (``docs/pipeline.md``): sharp simulated frames read 1.3-2.8 px,
the real fixture frames 3.3-3.7 px, blurry simulated frames 3.0-21 px (from 4.7 px of motion,
5.1 px or more), the fixture frames blurred by a 5 px line 6.3-6.5 px."""


@dataclass(frozen=True)
class ExtractSettings:
    """How frames are processed.

    Attributes:
        window: the PSF windows (start, largest, field).
        deconv: block solver settings.
        grow: growth acceptance rules.
        local_alignment: move each block's star centre by its local-alignment translation.
        kind: ``"blurry"``, ``"sharp"`` (recorded in the feature flags) or ``"auto"``: each frame
            is classified from its own measured blur (:func:`ring_blur`), ``sharp`` below
            ``sharp_below_px``; it is grown with these (blurry) settings, and a frame found sharp
            is grown again from the same seed with :meth:`for_kind` ``("sharp")``. A frame whose
            first front already measures sharp is not grown further with the blurry settings
            (the measure is the first front's, so it is known there; the later fronts of a sharp
            frame are grown once, with the sharp settings).
        scales: tag detection scales.
        sharp_below_px: the classification threshold of ``kind="auto"`` (px of blur extent).
    """

    window: WindowPolicy = field(default_factory=WindowPolicy)
    deconv: DeconvSettings = field(default_factory=DeconvSettings)
    grow: GrowSettings = field(default_factory=GrowSettings)
    local_alignment: bool = False
    kind: str = "blurry"
    scales: tuple[float, ...] = DEFAULT_SCALES
    sharp_below_px: float = SHARP_BELOW_PX

    def __post_init__(self) -> None:
        if self.kind not in FRAME_KINDS:
            raise ValueError(f"kind must be one of {FRAME_KINDS}, got {self.kind!r}")
        if not self.sharp_below_px > 0:
            raise ValueError(f"sharp_below_px must be positive, got {self.sharp_below_px}")

    @staticmethod
    def sharp(**changes: Any) -> ExtractSettings:
        """Settings for sharp frames: the same engine with a small PSF window
        (:data:`blurcalib.growth.window.SHARP_START`, 9 x 9) and free PSFs only (no motion-path
        field: a sharp frame's PSF is its defocus; 2 of the demo's 20 sharp frames adapt their
        window, and their features stay as measured before the field)."""
        return replace(ExtractSettings(window=WindowPolicy(start=SHARP_START),
                                       grow=GrowSettings(psf_field=False), kind="sharp"), **changes)

    @staticmethod
    def auto(**changes: Any) -> ExtractSettings:
        """Settings that classify each frame from its measured blur (``kind="auto"``, the blurry
        frames' settings otherwise)."""
        return replace(ExtractSettings(kind="auto"), **changes)

    def for_kind(self, kind: str) -> ExtractSettings:
        """These settings for frames of ``kind`` (``"sharp"`` or ``"blurry"``): for sharp frames
        the :meth:`sharp` window and free PSFs, everything else kept."""
        if kind == "sharp":
            return replace(self, window=replace(self.window, start=SHARP_START),
                           grow=replace(self.grow, psf_field=False), kind="sharp")
        return replace(self, kind=kind)


@dataclass
class FrameResult:
    """Everything extracted from one frame.

    Attributes:
        frame: frame name.
        status: outcome; ``message`` says why when not ok.
        blocks: every attempted block with its figures and status.
        features: one star-centre observation per accepted block (:meth:`BlockTable.features`).
        corners: the square corners shared by accepted neighbouring blocks, after local
            alignment (:func:`corner_rows`), one row each.
        seed, growth, local: the intermediate results (None where not reached).
        seconds: wall time (s) spent in ``seed``, ``fit`` (growth) and ``align``; the growth's
            stages within ``fit`` are :attr:`Growth.seconds`.
        kind: ``sharp`` or ``blurry``, as extracted (empty when not known: not seeded).
        blur_px: the frame's measured blur (:func:`ring_blur`; NaN when not measured).
        noise: the frame's noise (:func:`blurcalib.growth.noise.estimate_noise`; None when not
            estimated), the unit of the blocks' :attr:`BlockTable.noise_var`.
    """

    frame: str
    status: FrameStatus
    message: str = ""
    blocks: BlockTable = field(default_factory=BlockTable.empty)
    features: FeatureTable = field(default_factory=FeatureTable.empty)
    corners: list[list[Any]] = field(default_factory=list)
    seed: Seed | None = None
    growth: Growth | None = None
    local: LocalAlignment | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    kind: str = ""
    blur_px: float = math.nan
    noise: NoiseModel | None = None

    def stage_seconds(self) -> dict[str, float]:
        """Wall time (s) by stage, the growth's split out: ``seed``, then :attr:`Growth.seconds`
        (``free``, ``field``, ``final``, ``judge``) and ``fit_other`` (the rest of ``fit``: the
        frame's noise, a growth started again with a sharp frame's settings), then ``align``;
        stages not run are absent (:func:`blurcalib.io.record.split_fit_seconds`)."""
        return split_fit_seconds(self.seconds, self.growth.seconds if self.growth is not None else {})

    def record(self) -> FrameRecord:
        """The frame's record (:class:`blurcalib.io.record.FrameRecord`, the row of ``frames.csv``):
        ``psf`` says whether the blocks were fitted with the frame's path-PSF field, ``field``, or
        with free PSFs, ``free``, and ``psf_field`` holds the field; the blur, the noise
        (:attr:`blurcalib.growth.noise.NoiseModel.sigma`, grey levels) and the seconds are rounded
        to 3 decimals, the message made printable (:func:`blurcalib.io.text.printable_name`)."""
        path_field = self.growth.psf_field if self.growth is not None else None
        fit = self.growth.seconds if self.growth is not None else {}
        return FrameRecord(
            self.frame, self.status, printable_name(self.message),
            seeded_by=self.seed.method if self.seed is not None else "",
            psf="" if self.growth is None else "free" if path_field is None else "field",
            psf_field=None if path_field is None else path_field.to_dict(), kind=self.kind,
            blur_px=round(self.blur_px, 3) if math.isfinite(self.blur_px) else None,
            noise_dn=round(self.noise.sigma, 3) if self.noise is not None else None,
            blocks=len(self.blocks), accepted=int(self.blocks.accepted.sum()), features=len(self.features),
            seconds=round(sum(self.seconds.values()), 3),
            stages={k: round(v, 3) for k, v in self.seconds.items()},
            fit_stages={k: round(v, 3) for k, v in fit.items()})


def mean_stage_seconds(results: Sequence[FrameResult]) -> dict[str, float]:
    """Mean wall time (s) per frame of each stage (:meth:`FrameResult.stage_seconds`) over
    ``results``, a stage a frame did not run counting 0; in the order the stages run."""
    order = ("seed", "neighbour", "free", "field", "final", "judge", "fit_other", "align")
    stages = [r.stage_seconds() for r in results]
    names = sorted({k for s in stages for k in s},
                   key=lambda k: (order.index(k) if k in order else len(order), k))
    return {k: float(np.mean([s.get(k, 0.0) for s in stages])) for k in names}


@denormals_flushed
def extract_frame(image: np.ndarray, pattern: StarPattern, frame: str,
                  settings: ExtractSettings | None = None, H_feature: np.ndarray | None = None,
                  on_event: Callable[[GrowthEvent], None] | None = None,
                  should_stop: Callable[[], bool] | None = None) -> FrameResult:
    """Extract features and PSFs from one frame ``image (H, W)`` (grey levels 0..255).

    Args:
        image: the frame.
        pattern: the target.
        frame: the frame's name (recorded in every row).
        settings: processing settings (blurry-frame defaults).
        H_feature: a seed homography (feature coordinates -> px) to use instead of the tag.
        on_event: per-block growth callback (for live display).
        should_stop: polled between growth fronts.

    The frame, its seeding too, is computed with denormal floats flushed to zero
    (:func:`blurcalib.deconv.convolution.denormals_flushed`).
    """
    settings = settings or ExtractSettings()
    t0 = time.perf_counter()
    try:
        seed = seed_frame(image, pattern, H_feature, settings.scales)
    except SeedError as exc:
        return FrameResult(frame, FrameStatus.NOT_SEEDED, str(exc),
                           seconds={"seed": time.perf_counter() - t0},
                           kind="" if settings.kind == "auto" else settings.kind)
    return grow_frame(image, pattern, frame, seed, settings, on_event, should_stop,
                      {"seed": time.perf_counter() - t0})


def ring_blur(growth: Growth | None) -> float:
    """A frame's measured blur (px): :func:`median_extent` of the accepted blocks of the growth's
    first front (the ring around the tag, or the first blocks of a given seed)."""
    if growth is None:
        return math.nan
    return median_extent(growth.fit.sigma_major[(growth.front == 0) & growth.accepted])


def median_extent(sigma_major: np.ndarray) -> float:
    """The median blur extent ``sqrt(12) sigma_major`` (:func:`blurcalib.psf.kernel.blur_extent`,
    px) of PSFs of second moments ``sigma_major (A,)`` (px); NaN when none is finite."""
    sigma = sigma_major[np.isfinite(sigma_major)]
    return float(np.median(blur_extent(sigma))) if sigma.size else math.nan


def grow_frame(image: np.ndarray, pattern: StarPattern, frame: str, seed: Seed,
               settings: ExtractSettings, on_event: Callable[[GrowthEvent], None] | None = None,
               should_stop: Callable[[], bool] | None = None,
               seconds: dict[str, float] | None = None) -> FrameResult:
    """The rest of :func:`extract_frame` from a ``seed``: grow (classifying the frame with
    ``settings.kind == "auto"``), align locally, tabulate; ``seconds`` are times spent before."""
    seconds = dict(seconds or {})
    t1 = time.perf_counter()
    kind = "blurry" if settings.kind == "auto" else settings.kind
    used = settings.for_kind(kind) if settings.kind == "auto" else settings
    noise = frame_noise(image)
    auto = settings.kind == "auto"

    def blurry(sigma_major: np.ndarray) -> bool:  # a sharp first front ends the blurry growth there
        return not median_extent(sigma_major) < settings.sharp_below_px

    growth = grow(image, pattern, seed, used.window, used.deconv, used.grow, on_event, should_stop, noise,
                  blurry if auto else None)
    blur = ring_blur(growth)
    if auto and blur < settings.sharp_below_px:
        kind, used = "sharp", settings.for_kind("sharp")
        growth = grow(image, pattern, seed, used.window, used.deconv, used.grow, on_event, should_stop, noise)
    t2 = time.perf_counter()
    seconds["fit"] = t2 - t1
    if growth is None or not growth.accepted.any():
        result = FrameResult(frame, FrameStatus.NO_BLOCKS,
                             "the tag was found but no block around it could be fitted",
                             seed=seed, growth=growth, seconds=seconds, kind=kind, blur_px=blur, noise=noise)
        if growth is not None:
            result.blocks = _block_table(frame, pattern, growth, None, noise)
        return result
    acc = np.flatnonzero(growth.accepted)
    f = pattern.features[growth.feature_id[acc]]
    local = align_locally(growth.fit.H[acc], f[:, 0], f[:, 1])
    seconds["align"] = time.perf_counter() - t2
    blocks = _block_table(frame, pattern, growth, local if used.local_alignment else None, noise)
    features = _features(pattern, blocks, used)
    corners = corner_rows(frame, pattern, local.H, f[:, 0], f[:, 1])
    return FrameResult(frame, FrameStatus.OK, "", blocks, features, corners, seed, growth, local,
                       seconds, kind, blur, noise)


def corner_rows(frame: str, pattern: StarPattern, H: np.ndarray, fx: np.ndarray,
                fy: np.ndarray) -> list[list[Any]]:
    """Rows of ``corners.csv`` for the square corners shared by at least two blocks.

    Args:
        frame: frame name.
        pattern: the target.
        H: ``(B, 3, 3)`` block homographies after local alignment.
        fx, fy: ``(B,)`` feature coordinates of the blocks.
    """
    corner2, xy, count = shared_corners(H, fx, fy)
    half = pattern.square_length_m / 2.0
    return [[frame, int(c[0]), int(c[1]), c[0] * half, c[1] * half, float(p[0]), float(p[1]), int(n)]
            for c, p, n in zip(corner2, xy, count, strict=True)]


def _block_table(frame: str, pattern: StarPattern, growth: Growth,
                 local: LocalAlignment | None, noise: NoiseModel | None = None) -> BlockTable:
    """Every attempted block of a growth, with the local alignment's homographies for the
    accepted ones when ``local`` is given and their noise variances when ``noise`` is."""
    fit = growth.fit
    H = fit.H.copy()
    if local is not None:
        H[np.flatnonzero(growth.accepted)] = local.H
    f = pattern.features[growth.feature_id]
    return BlockTable(np.full(len(f), frame), growth.feature_id, f[:, 0], f[:, 1],
                      np.array(growth.status, dtype=object), fit.loss,
                      fit.boundary_energy, fit.sigma_major, fit.sigma_minor, fit.eccentricity,
                      fit.orientation, fit.centroid, H, fit.coeffs, np.nan_to_num(fit.psf), fit.loss_extent,
                      None if noise is None else noise.block_variance(fit.coeffs))


def _features(pattern: StarPattern, blocks: BlockTable, settings: ExtractSettings) -> FeatureTable:
    flags = FeatureFlags.STAR_CENTRE | (FeatureFlags.SHARP_FRAME if settings.kind == "sharp"
                                        else FeatureFlags.BLURRY_FRAME)
    if settings.local_alignment:
        flags |= FeatureFlags.LOCALLY_ALIGNED
    return blocks.select(blocks.accepted).features(pattern.square_length_m, flags)
