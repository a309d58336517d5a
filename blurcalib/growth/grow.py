"""Region growing: solve blocks breadth-first from the seed, front by front.

The first front is the ring of features around the tag (:mod:`blurcalib.growth.fronts`), fitted
twice under heavy blur (:func:`blurcalib.growth.fronts.refine_ring`). Every accepted block
predicts its 4-neighbours, and each front is solved as one batch
(:mod:`blurcalib.deconv.blocks`), in the PSF window the previous front's PSFs ask for
(:mod:`blurcalib.growth.window`), with the pixels that see a tag through the blur left out
(:mod:`blurcalib.growth.masks`). A block that fails (window outside the image, degenerate
homography, not converged, loss too high, PSF truncated, a jump away from its prediction, or in a
heavily blurred frame a disagreement with its neighbours; :mod:`blurcalib.growth.judge`) is
rejected and seeds nothing. Every decision is recorded in a :class:`GrowthLedger` and reported to
an optional callback, so a GUI can draw the growth live.

Once grown, a frame whose window adapted, or whose blur is long for its squares, gets its
path-PSF field and grows on with it (:mod:`blurcalib.growth.field`); otherwise its accepted
blocks may be fitted once more over a larger area (:mod:`blurcalib.growth.final`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from blurcalib.deconv.blocks import fit_blocks
from blurcalib.deconv.result import BlockFit
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.growth.field import field_growth
from blurcalib.growth.final import final_fit
from blurcalib.growth.fronts import first_front, fit_hinted, next_front, psf_hint, refine_ring
from blurcalib.growth.judge import judge_again, judge_front, off_neighbours
from blurcalib.growth.ledger import Growth, GrowthEvent, GrowthLedger
from blurcalib.growth.masks import blur_footprint, pixel_mask, tag_mask
from blurcalib.growth.noise import NoiseModel
from blurcalib.growth.quality import noise_scale
from blurcalib.growth.seed import Seed
from blurcalib.growth.settings import GrowSettings
from blurcalib.growth.window import (
    FrameWindow,
    WindowPolicy,
    fit_front,
    front_blur,
    median_blur_per_square,
    needs_adaptive_window,
)
from blurcalib.io.results import BlockStatus
from blurcalib.target.pattern import StarPattern


def grow(image: np.ndarray, pattern: StarPattern, seed: Seed, window: WindowPolicy | None = None,
         deconv: DeconvSettings | None = None, settings: GrowSettings | None = None,
         on_event: Callable[[GrowthEvent], None] | None = None,
         should_stop: Callable[[], bool] | None = None, noise: NoiseModel | None = None,
         go_on: Callable[[np.ndarray], bool] | None = None) -> Growth | None:
    """Grow from ``seed`` over the frame ``image`` ``(H, W)`` (grey levels).

    Args:
        image: the frame.
        pattern: the target.
        seed: where the target is (:func:`blurcalib.growth.seed.seed_frame`).
        window: the PSF windows.
        deconv: block solver settings.
        settings: acceptance rules.
        on_event: called once per attempted block, in order, as fronts finish, and once more
            for a block that the final consistency check of an adaptive frame rejects.
        should_stop: polled between fronts; growth ends early when it returns True.
        noise: the frame's noise (:func:`blurcalib.growth.noise.estimate_noise`): the loss limit
            :attr:`GrowSettings.max_loss` grows with its variance at the frame's level above the
            reference (:func:`blurcalib.growth.quality.noise_scale`); None keeps it as given.
        go_on: called with ``sigma_major (A,)`` (px) of the accepted blocks of the first front's
            first fit and, when it returned True, once more with those of the first front as
            judged (after the tag ring's re-fit); when it returns False the growth ends with
            that fit as its first front and is returned as it is (no field, final fit or second
            judgement), e.g. when the first front shows a sharp frame that is to be grown with
            other settings (the ring's re-fit is then saved where its first fit shows it).
    Returns:
        The growth, or None when not a single block could be attempted; its
        :attr:`Growth.seconds` holds the stages' wall times.
    """
    window = window or WindowPolicy()
    deconv = deconv or DeconvSettings()
    settings = settings or GrowSettings()
    if noise is not None:
        scale = float(noise_scale(noise.variance(noise.level)))
        settings = replace(settings, max_loss=settings.max_loss * scale)
    t0 = time.perf_counter()
    start = first_front(pattern, seed, image.shape)
    if start is None:
        return None
    front_ids, front_H = start
    front_src: list[list[int]] = []  # the accepted blocks that predicted each (none for the ring)
    N = pattern.num_star_segments
    tag = tag_mask(pattern, seed.H_feature, image.shape)
    state = FrameWindow(window.start)
    ledger = GrowthLedger(pattern, on_event)
    front_index = 0
    stop = False  # go_on ended the growth after the ring's first fit
    while front_ids and len(ledger) < settings.max_blocks:
        if should_stop is not None and should_stop():
            break
        H0 = np.stack(front_H)
        if state.adaptive is None:
            H0, fit, stop = _first_fit(image, pattern, seed, front_ids, H0, tag, state, window, deconv,
                                       settings, go_on)
        elif state.adaptive:
            hint = psf_hint(ledger.accepted_psf, front_src, state.size, settings)
            first = fit_hinted(image, H0, N, state.size, deconv, pixel_mask(tag, state.size, state.footprint),
                               hint, settings)
            fit = fit_front(image, H0, N, first, window, deconv, settings, tag, state.footprint)
        else:
            fit = fit_hinted(image, H0, N, window.start, deconv, pixel_mask(tag, window.start),
                             psf_hint(ledger.accepted_psf, front_src, window.start, settings), settings)
            if front_blur(fit)[1] > settings.refit_boundary_energy:  # the blur outgrew the window
                state.adaptive = True
                fit = fit_front(image, H0, N, fit, window, deconv, settings, tag)
                state.heavy = bool(front_blur(fit)[0] > settings.heavy_above_extent_px)
        off = (off_neighbours(pattern, front_ids, fit, ledger.accepted_H, settings) if state.heavy
               else np.zeros(len(front_ids), dtype=bool))
        newly_accepted, accepted_rows = [], []
        for k, (fid, status) in enumerate(zip(front_ids, judge_front(fit, H0, settings, off), strict=True)):
            ledger.record(fid, status, front_index, H0[k], fit, k)
            if status is BlockStatus.ACCEPTED:
                ledger.accept(fid, fit.H[k], fit.psf[k])
                newly_accepted.append(fid)
                accepted_rows.append(k)
        ledger.add_fits(fit)
        front_ids, front_H, front_src = next_front(pattern, ledger.accepted_H, ledger.row, newly_accepted)
        front_index += 1
        if front_index == 1 and go_on is not None and (stop or not go_on(fit.sigma_major[accepted_rows])):
            growth = ledger.growth()
            growth.seconds = {"free": time.perf_counter() - t0}
            return growth
        if state.adaptive:
            state.size = window.choose(fit.sigma_major[accepted_rows])
    if ledger.fit is None:
        return None
    growth = ledger.growth()
    seconds = {"free": time.perf_counter() - t0}
    stopped = should_stop is not None and should_stop()
    growth = _finish(image, pattern, growth, state, tag, window, deconv, settings, on_event, should_stop,
                     stopped, noise, seconds)
    growth.seconds = seconds
    return growth


def _finish(image: np.ndarray, pattern: StarPattern, growth: Growth, state: FrameWindow, tag: np.ndarray,
            window: WindowPolicy, deconv: DeconvSettings, settings: GrowSettings,
            on_event: Callable[[GrowthEvent], None] | None, should_stop: Callable[[], bool] | None,
            stopped: bool, noise: NoiseModel | None, seconds: dict[str, float]) -> Growth:
    """The stages after the free growth (:func:`grow`'s arguments; ``stopped``: ``should_stop``
    ended it, which skips the field): the path-PSF field when the window adapted or the blur is
    long for the squares, else the final fit where ``settings`` asks for it, then the second
    judgement of a heavily blurred or field-grown frame. Each stage's wall time (s) is added to
    ``seconds``."""
    if not stopped and settings.psf_field and window.adapts and (
            state.adaptive or median_blur_per_square(growth.fit) >= settings.field_above_blur_per_square):
        t0 = time.perf_counter()
        growth = field_growth(image, pattern, growth, window, deconv, settings, tag, on_event, should_stop,
                              None if noise is None else float(noise.variance(noise.level)))
        seconds["field"] = time.perf_counter() - t0
    if growth.psf_field is None and (settings.final_fit_frames == "all"
                                     or (state.adaptive and settings.final_fit_frames == "adaptive")):
        t0 = time.perf_counter()
        growth.fit = final_fit(image, pattern, growth.feature_id, growth.fit, growth.accepted, window, deconv,
                               settings, tag, state.footprint)
        seconds["final"] = time.perf_counter() - t0
    if state.heavy or growth.psf_field is not None:  # every block now has neighbours on all sides
        t0 = time.perf_counter()
        growth = judge_again(pattern, growth, settings, on_event)
        seconds["judge"] = time.perf_counter() - t0
    return growth


def _first_fit(image: np.ndarray, pattern: StarPattern, seed: Seed, front_ids: list[int], H0: np.ndarray,
               tag: np.ndarray, state: FrameWindow, window: WindowPolicy, deconv: DeconvSettings,
               settings: GrowSettings, go_on: Callable[[np.ndarray], bool] | None
               ) -> tuple[np.ndarray, BlockFit, bool]:
    """The first front's fit from its predictions ``H0 (B, 3, 3)``, which decides ``state``
    (whether the window adapts, the frame is heavily blurred, the blur's footprint); with a tag,
    the ring re-fitted from its first fit (:func:`blurcalib.growth.fronts.refine_ring`) unless
    ``go_on`` (:func:`grow`'s) ends the growth after the first fit.
    Returns the predictions, the fit and whether the growth ends there."""
    N = pattern.num_star_segments
    fit = fit_blocks(image, H0, N, window.start, deconv, pixel_mask(tag, window.start))
    state.adaptive = needs_adaptive_window(fit, settings)
    if state.adaptive:
        fit = fit_front(image, H0, N, fit, window, deconv, settings, tag)
    # judged with the window that holds the blur: a truncated PSF reads shorter
    state.heavy = bool(front_blur(fit)[0] > settings.heavy_above_extent_px)
    if state.adaptive and state.heavy:
        seed_blur = seed.blur[0] if math.isfinite(seed.blur[0]) else 0.0
        extent = max(fit.kernel_size / window.per_extent, seed_blur)
        state.footprint = blur_footprint(fit, extent)
    if go_on is not None:
        statuses = judge_front(fit, H0, settings, np.zeros(len(H0), dtype=bool))
        accepted = np.array([st is BlockStatus.ACCEPTED for st in statuses], dtype=bool)
        if not go_on(fit.sigma_major[accepted]):
            return H0, fit, True
    if seed.source == "tag":
        refined = refine_ring(image, pattern, front_ids, fit, window, deconv, settings, tag, state.adaptive,
                              state.footprint)
        if refined is not None:
            return *refined, False
    return H0, fit, False
