"""The field growth: a frame's path-PSF field fitted from a growth, and the growth gone on with it.

Under blur as long as the star squares a block's free PSF trades its shape against the star's
position; the frame's motion-path field (:mod:`blurcalib.psf.path`) does not
(:func:`field_growth`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import cast

import cv2
import numpy as np

from blurcalib.deconv.blocks import fit_blocks_fixed
from blurcalib.deconv.field import FieldFit, FieldSettings, fit_path_field
from blurcalib.deconv.result import BlockFit
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.deconv.windows import block_windows
from blurcalib.geometry.homography import homography_centre
from blurcalib.growth.final import inner
from blurcalib.growth.fronts import next_front, normalise
from blurcalib.growth.judge import judge_front, neighbour_homographies
from blurcalib.growth.ledger import Growth, GrowthEvent, GrowthLedger
from blurcalib.growth.masks import pixel_mask, tag_centre
from blurcalib.growth.seed import block_homography
from blurcalib.growth.settings import GrowSettings
from blurcalib.growth.window import WindowPolicy
from blurcalib.io.results import BlockStatus
from blurcalib.psf.path import PathField, constant_field
from blurcalib.target.pattern import StarPattern


def field_degree(xy: np.ndarray, image_size: tuple[int, int], count: int | None = None) -> int:
    """Polynomial degree of a path field fitted from blocks at ``xy (B, 2)`` px (``count`` of
    them, default ``B``): 2 from 30 blocks spanning 0.3 of the image's longer side, 1 from 10
    spanning 0.1, else 0 (a field of higher degree than its blocks span would be extrapolated;
    a tag ring seeds with degree 0, then 1)."""
    ok = np.all(np.isfinite(xy), axis=1)
    if not ok.any():
        return 0
    n = int(ok.sum()) if count is None else count
    span = float((xy[ok].max(axis=0) - xy[ok].min(axis=0)).max()) / max(image_size)
    if n >= 30 and span >= 0.3:
        return 2
    return 1 if n >= 10 and span >= 0.1 else 0


def spread(xy: np.ndarray, most: int) -> np.ndarray:
    """Sorted indices of at most ``most`` of the points ``xy (B, 2)``, spread over them
    (farthest-point sampling from the point nearest their mean)."""
    if len(xy) <= most:
        return np.arange(len(xy))
    chosen = [int(np.argmin(np.linalg.norm(xy - xy.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(xy - xy[chosen[0]], axis=1)
    for _ in range(most - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(xy - xy[chosen[-1]], axis=1))
    return np.sort(np.array(chosen))


def field_rows(pattern: StarPattern, ids: np.ndarray, H: np.ndarray, image_shape: tuple[int, int],
               deconv: DeconvSettings, settings: GrowSettings) -> np.ndarray:
    """Sorted rows of the blocks ``ids (B,)`` at ``H (B, 3, 3)`` that fit a path field: at most
    :attr:`GrowSettings.field_blocks` of them spread over the frame (:func:`spread`).

    None lies on the pattern's rim (:func:`blurcalib.growth.final.inner`: their loss area would
    reach the paper beyond the stars, and farthest-point sampling would pick them first). Where
    at least
    :attr:`GrowSettings.field_min_blocks` can, only blocks whose loss area
    (:attr:`GrowSettings.final_extent` x the square, with ``deconv``'s margin) lies inside the
    image are chosen: farthest-point sampling picks blocks at the image's border first, and the
    field's fit leaves out one whose area crosses it, so the field would lose the blocks that
    hold its extent (docs/decisions/field-seeds-inside-image.md).
    """
    off_rim = np.flatnonzero(inner(pattern, ids))
    status = block_windows(H[off_rim], image_shape, replace(deconv, loss_extent=settings.final_extent))[3]
    inside = np.array([st is BlockStatus.ACCEPTED for st in status], dtype=bool)
    pool = off_rim[inside] if inside.sum() >= settings.field_min_blocks else off_rim
    return cast(np.ndarray, pool[spread(homography_centre(H[pool]), settings.field_blocks)])


def fit_with_field(image: np.ndarray, pattern: StarPattern, ids: np.ndarray, H0: np.ndarray,
                   psf_field: PathField, window: WindowPolicy, deconv: DeconvSettings, settings: GrowSettings,
                   tag: np.ndarray | None) -> BlockFit:
    """Fit blocks ``ids (B,)`` from ``H0 (B, 3, 3)`` with their PSFs held at the field's
    (:func:`blurcalib.deconv.blocks.fit_blocks_fixed`), over ``|q|_inf <=``
    :attr:`GrowSettings.final_extent` (blocks on the pattern's rim over their square,
    :func:`blurcalib.growth.final.inner`), in one window that holds every block's path (at most
    :attr:`WindowPolicy.field_largest`); pixels that see the tag through the field's blur at the
    tag are left out (:func:`blurcalib.growth.masks.pixel_mask`)."""
    xy = homography_centre(H0)
    xy = np.where(np.isfinite(xy), xy, 0.0)  # degenerate blocks are not fitted
    size = psf_field.kernel_size(xy, window.field_largest)
    centre = tag_centre(tag)
    footprint = None if centre is None else psf_field.footprint(centre, window.field_largest)
    mask = pixel_mask(tag, size, footprint)
    rim = ~inner(pattern, ids)
    fits, rows = [], []
    for sel, extent in ((np.flatnonzero(~rim), settings.final_extent), (np.flatnonzero(rim), 1.0)):
        if sel.size:
            fits.append(fit_blocks_fixed(image, H0[sel], pattern.num_star_segments,
                                         psf_field.kernels(xy[sel], size),
                                         replace(deconv, loss_extent=extent), mask))
            rows.append(sel)
    return BlockFit.concat(fits).take(np.argsort(np.concatenate(rows), kind="stable"))


def fit_field(image: np.ndarray, pattern: StarPattern, ids: np.ndarray, H: np.ndarray, start: PathField,
              window: WindowPolicy, deconv: DeconvSettings, settings: GrowSettings, tag: np.ndarray | None,
              tied: bool = False) -> tuple[FieldFit, np.ndarray]:
    """:func:`blurcalib.deconv.field.fit_path_field` on blocks ``ids (B,)`` from ``H (B, 3, 3)``:
    those of :func:`field_rows`, or when ``tied`` all but those on the pattern's rim; pixels
    seeing the tag through ``start``'s blur are left out. Returns the fit (of those rows) and
    the blocks' homographies ``(B, 3, 3)`` (rows not in the fit keep ``H``)."""
    largest = window.field_largest
    rows = (np.flatnonzero(inner(pattern, ids)) if tied
            else field_rows(pattern, ids, H, image.shape, deconv, settings))
    centre = tag_centre(tag)
    size = start.kernel_size(homography_centre(H[rows]), largest)
    mask = pixel_mask(tag, size, None if centre is None else start.footprint(centre, largest))
    fit = fit_path_field(image, H[rows], pattern.num_star_segments, start, deconv,
                         FieldSettings(loss_extent=settings.final_extent, largest_kernel=largest), mask,
                         pattern.features[ids[rows]] if tied else None)
    out = H.copy()
    out[rows] = fit.H
    return fit, out


def ring_seed(image: np.ndarray, pattern: StarPattern, growth: Growth, window: WindowPolicy,
              deconv: DeconvSettings, settings: GrowSettings, tag: np.ndarray | None,
              noise_var: float | None = None) -> tuple[np.ndarray, np.ndarray, PathField]:
    """The tag ring's blocks fitted tied to one feature homography with a path field
    (:func:`blurcalib.deconv.field.fit_path_field` with ``features``), from their predictions:
    a field of degree 0 from a straight path along their free PSFs, then of degree 1 when the
    ring spans enough of the image (:func:`field_degree`). Returns the ring's rows, their
    homographies and the field.

    Where the last fit's median block loss exceeds :attr:`GrowSettings.ring_refit_noise` x
    the frame's noise variance ``noise_var`` (grey levels^2; None: never), both fits are made
    again, from the first fit's field and the predictions, and kept where their loss is within
    that limit. While the first fit's field is still wrong it can drag the homography along the
    blur and settle there; started afresh with a field near the blur's, it does not. The
    second fit is not kept on a lower loss alone: where every tied fit of a ring stays far above
    the noise's variance, the lower of two can be the one that is off
    (docs/decisions/field-ring-refit.md).
    """
    h, w = image.shape
    ring = np.flatnonzero(growth.front == 0)
    ids = growth.feature_id[ring]

    def tied_fits(start: PathField) -> tuple[PathField, FieldFit, np.ndarray]:
        """The first fit's field, the last fit and its homographies."""
        first, H = fit_field(image, pattern, ids, growth.predicted[ring], start, window, deconv, settings,
                             tag, tied=True)
        fit = first
        if field_degree(homography_centre(H), (w, h), len(ring)) >= 1:
            fit, H = fit_field(image, pattern, ids, H, first.field.with_degree(1), window, deconv, settings,
                               tag, tied=True)
        return first.field, fit, H

    first_field, fit, H = tied_fits(constant_field(growth.fit.psf[ring], (w, h), 0))
    limit = np.inf if noise_var is None or settings.ring_refit_noise == 0 \
        else settings.ring_refit_noise * noise_var
    if np.nanmedian(fit.loss) > limit:
        _, again, H_again = tied_fits(first_field)
        if np.nanmedian(again.loss) <= limit:
            fit, H = again, H_again
    return ring, H, fit.field


def local_predictions(pattern: StarPattern, ids: np.ndarray, accepted_H: dict[int, np.ndarray],
                      fallback: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """``(B, 3, 3)`` predictions of blocks ``ids`` from the homography of the ``neighbours``
    accepted blocks nearest each in the pattern
    (:func:`blurcalib.growth.judge.neighbour_homographies`, least median of squares), where one
    exists, else ``fallback (B, 3, 3)`` (the mean of the adjacent blocks' predictions); and
    ``(B,)`` bool, where it exists. Under blur as long as the squares a
    block's fit stays where it starts along the blur, so a prediction from one or two neighbours
    would pass their errors on in chains; many neighbours, most with shorter blur, hold it."""
    ref = np.fromiter(accepted_H, dtype=np.int64, count=len(accepted_H))
    f = pattern.features[ids]
    homographies = neighbour_homographies(f, pattern.features[ref],
                                          homography_centre(np.stack([accepted_H[i] for i in ref])),
                                          neighbours, cv2.LMEDS, 0.0)
    out = fallback.copy()
    local = np.array([H is not None for H in homographies], dtype=bool)
    for b in np.flatnonzero(local):
        out[b] = normalise(block_homography(cast(np.ndarray, homographies[b]), f[b, 0:1], f[b, 1:2])[0])
    return out, local


def field_growth(image: np.ndarray, pattern: StarPattern, growth: Growth, window: WindowPolicy,
                 deconv: DeconvSettings, settings: GrowSettings, tag: np.ndarray | None,
                 on_event: Callable[[GrowthEvent], None] | None = None,
                 should_stop: Callable[[], bool] | None = None, noise_var: float | None = None) -> Growth:
    """Fit the frame's path-PSF field from a growth and grow on with it.

    Under blur as long as the star squares a block's free PSF trades its shape against the
    star's position; the frame's motion-path field (:mod:`blurcalib.psf.path`) does not. So:

    1. **Seeds.** The field is fitted (:func:`blurcalib.deconv.field.fit_path_field`) with at most
       :attr:`GrowSettings.field_blocks` of the growth's accepted blocks spread over the frame,
       from a straight path along their PSFs (:func:`blurcalib.psf.path.constant_field`), its
       degree by their spread (:func:`field_degree`). When the growth failed (it accepted fewer
       than half of the blocks it fitted, or fewer than :attr:`GrowSettings.field_min_blocks`:
       blur as long as the squares, whose free fits settle px off) the seeds are the tag ring
       instead, fitted tied to one feature homography (:func:`ring_seed`; ``noise_var`` is
       the frame's noise variance, grey levels^2, or None), and the growth's other accepted
       blocks are tried again.
    2. The seeds are fitted again with the field's PSF over :attr:`GrowSettings.final_extent`
       x their square (:func:`fit_with_field`), kept where accepted and moved less than
       :attr:`GrowSettings.final_max_shift_px`.
    3. The growth goes on, front by front, from the accepted blocks into every block not
       accepted yet, each fitted with the field's PSF and judged by the growth's rules
       (:func:`blurcalib.growth.judge.judge_front`, the loss limited to
       :attr:`GrowSettings.field_loss_factor` x the median of step 2's) and by its neighbours
       (:func:`blurcalib.growth.judge.inconsistent`). Whenever the accepted
       blocks have doubled since the field was fitted, it is fitted again from them (warm
       start); at the end the blocks fitted with an earlier field are fitted with the last where
       its paths moved by more than :attr:`GrowSettings.field_refit_px` at the block.

    ``on_event`` and ``should_stop`` are :func:`blurcalib.growth.grow.grow`'s (polled between
    fronts). Returns the growth unchanged when no field could be fitted; else a new growth (rows of
    blocks accepted now replace their earlier ones, new blocks are appended) with
    :attr:`Growth.psf_field` set.
    """
    ledger = GrowthLedger(pattern, on_event, growth)
    seeded = _field_seeds(image, pattern, growth, window, deconv, settings, tag, noise_var)
    if seeded is None:
        return growth
    seeds, H_seed, psf_field, from_ring = seeded
    refit = fit_with_field(image, pattern, growth.feature_id[seeds], H_seed, psf_field, window, deconv,
                           settings, tag)
    ok = np.array([st is BlockStatus.ACCEPTED for st in refit.status], dtype=bool) & np.isfinite(refit.loss)
    ok &= np.linalg.norm(refit.centre - homography_centre(H_seed), axis=1) < settings.final_max_shift_px
    if not ok.any():
        return growth
    max_loss = min(settings.max_loss, settings.field_loss_factor * float(np.median(refit.loss[ok])))
    ok &= (refit.loss <= max_loss) & (refit.boundary_energy <= settings.max_boundary_energy)
    ledger.replace_fits(seeds[ok], refit, np.flatnonzero(ok))
    for k in np.flatnonzero(ok):
        ledger.restate(int(seeds[k]), BlockStatus.ACCEPTED, refit, int(k))
    # tried again below: blocks whose two fits disagree (a free fit next to the tag can be
    # px off where the field's is right), and with seeds from the ring the other blocks the
    # growth accepted
    acc = np.flatnonzero(growth.accepted)
    demoted = np.union1d(seeds[~ok], np.setdiff1d(acc, seeds) if from_ring else [])
    for k in demoted.astype(np.int64):
        if ledger.status[k] is BlockStatus.ACCEPTED:
            ledger.restate(int(k), BlockStatus.NOT_CONVERGED, growth.fit, int(k))
    assert ledger.fit is not None  # the growth's fits
    for k in ledger.accepted_rows:
        ledger.accept(ledger.ids[k], ledger.fit.H[k])
    psf_field, field_of = _grow_with_field(image, pattern, ledger, psf_field, max_loss, window, deconv,
                                              settings, tag, should_stop)
    # the blocks fitted with an earlier field, with the last one where it moved
    rows = np.array([k for k in ledger.accepted_rows if field_of[ledger.ids[k]] is not psf_field],
                    dtype=np.int64)
    if rows.size:
        fit = ledger.fit
        earlier = [field_of[ledger.ids[k]] for k in rows]
        moved = np.zeros(rows.size)
        for field in {id(f): f for f in earlier}.values():
            sel = np.array([f is field for f in earlier])
            moved[sel] = psf_field.path_change(field, fit.centre[rows[sel]])
        rows = rows[~(moved <= settings.field_refit_px)]
    if rows.size:
        last = fit_with_field(image, pattern, np.array(ledger.ids)[rows], fit.H[rows], psf_field, window,
                              deconv, settings, tag)
        keep = np.array([st is BlockStatus.ACCEPTED for st in last.status], dtype=bool)
        keep &= (last.loss <= max_loss) & (np.linalg.norm(last.centre - fit.centre[rows], axis=1)
                                           < settings.final_max_shift_px)
        ledger.replace_fits(rows[keep], last, np.flatnonzero(keep))
        for k in np.flatnonzero(keep):
            ledger.emit(int(rows[k]), last, int(k))
    return ledger.growth(psf_field)


def _field_seeds(image: np.ndarray, pattern: StarPattern, growth: Growth, window: WindowPolicy,
                 deconv: DeconvSettings, settings: GrowSettings, tag: np.ndarray | None,
                 noise_var: float | None) -> tuple[np.ndarray, np.ndarray, PathField, bool] | None:
    """Step 1 of :func:`field_growth`: the seed rows, their homographies ``(S, 3, 3)``, the
    field and whether the seeds are the tag ring's; None when no field could be fitted."""
    h, w = image.shape
    acc = np.flatnonzero(growth.accepted)
    ring = np.flatnonzero(growth.front == 0)
    fitted = int(np.isfinite(growth.fit.loss).sum())
    from_ring = ring.size >= 6 and (acc.size < settings.field_min_blocks or 2 * acc.size < fitted)
    try:
        if from_ring:
            seeds, H_seed, psf_field = ring_seed(image, pattern, growth, window, deconv, settings, tag,
                                                 noise_var)
        elif acc.size >= settings.field_min_blocks:
            seeds, H_seed = acc, growth.fit.H[acc]
            start = constant_field(growth.fit.psf[acc], (w, h), field_degree(growth.fit.centre[acc], (w, h)))
            psf_field = fit_field(image, pattern, growth.feature_id[acc], H_seed, start, window, deconv,
                                  settings, tag)[0].field
        else:
            return None
    except ValueError:  # no usable PSF or block to fit a field from
        return None
    return seeds, H_seed, psf_field, from_ring


def _grow_with_field(image: np.ndarray, pattern: StarPattern, ledger: GrowthLedger, psf_field: PathField,
                     max_loss: float, window: WindowPolicy, deconv: DeconvSettings, settings: GrowSettings,
                     tag: np.ndarray | None, should_stop: Callable[[], bool] | None
                     ) -> tuple[PathField, dict[int, PathField]]:
    """Step 3 of :func:`field_growth`, recorded in ``ledger`` (whose accepted blocks it starts
    from). Returns the last field and, by feature id, the field each accepted block was fitted
    with."""
    h, w = image.shape
    accepted_H = ledger.accepted_H
    tried = dict.fromkeys(accepted_H, 0)
    new_ids = list(accepted_H)
    field_of = dict.fromkeys(accepted_H, psf_field)  # the field each accepted block was fitted with
    fitted_with = len(accepted_H)  # accepted blocks when the field was last fitted
    front_index = max(ledger.front) + 1
    while new_ids and len(ledger) < settings.max_blocks:
        if should_stop is not None and should_stop():
            break
        if len(accepted_H) >= 2 * fitted_with:
            ids = np.fromiter(accepted_H, dtype=np.int64, count=len(accepted_H))
            H_acc = np.stack(list(accepted_H.values()))
            degree = max(psf_field.degree, field_degree(homography_centre(H_acc), (w, h)))
            try:
                psf_field = fit_field(image, pattern, ids, H_acc, psf_field.with_degree(degree), window,
                                      deconv, settings, tag)[0].field
            except ValueError:
                pass
            fitted_with = len(accepted_H)
        fids, preds, _ = next_front(pattern, accepted_H, tried, new_ids)
        if not fids:
            break
        H0, local = local_predictions(pattern, np.asarray(fids), accepted_H, np.stack(preds),
                                      settings.consistency_neighbours)
        ffit = fit_with_field(image, pattern, np.asarray(fids), H0, psf_field, window, deconv, settings, tag)
        # judged by the neighbours that predicted it (inconsistent's rule, one fit per block)
        off = local & (np.linalg.norm(ffit.centre - homography_centre(H0), axis=1)
                       > settings.max_inconsistency_px)
        statuses = judge_front(ffit, H0, settings, off, max_loss)
        tried.update(dict.fromkeys(fids, 0))
        # a block tried before that fails again keeps its first record
        decided = [k for k, fid in enumerate(fids)
                   if fid not in ledger.row or statuses[k] is BlockStatus.ACCEPTED]
        again = [k for k in decided if fids[k] in ledger.row]
        fresh = [k for k in decided if fids[k] not in ledger.row]
        new_ids = [fids[k] for k in decided if statuses[k] is BlockStatus.ACCEPTED]
        for k in decided:
            if statuses[k] is BlockStatus.ACCEPTED:
                ledger.accept(fids[k], ffit.H[k])
                field_of[fids[k]] = psf_field
        again_rows = np.array([ledger.row[fids[k]] for k in again], dtype=np.int64)
        for k in again + fresh:
            ledger.record(fids[k], statuses[k], front_index, H0[k], ffit, k)
        if again:
            ledger.replace_fits(again_rows, ffit, np.array(again))
        if fresh:
            ledger.add_fits(ffit.take(np.array(fresh)))
        front_index += 1
    return psf_field, field_of
