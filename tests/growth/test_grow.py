"""The PSF window of region growing fits the blur."""

from __future__ import annotations

import numpy as np
import pytest

from blurcalib.deconv.blocks import fit_blocks, fit_blocks_hinted
from blurcalib.deconv.settings import DeconvSettings
from blurcalib.geometry.homography import apply_homography
from blurcalib.growth.final import final_fit
from blurcalib.growth.fronts import fit_hinted
from blurcalib.growth.judge import inconsistent
from blurcalib.growth.masks import blur_footprint, pixel_mask
from blurcalib.growth.seed import line_kernel
from blurcalib.growth.settings import GrowSettings
from blurcalib.growth.window import WindowPolicy, fit_front
from blurcalib.io.results import BlockStatus
from blurcalib.psf.kernel import blur_per_square, psf_moments
from blurcalib.sim.blocks import simulate_blocks
from blurcalib.sim.evaluate import pose_consistent_errors
from blurcalib.target.pattern import layout_pattern


def test_kernel_size_grows_with_the_blur() -> None:
    window = WindowPolicy(start=17, largest=41)
    sizes = [window.choose(s) for s in (0.5, 2.0, 4.0, 5.0, 6.0, 8.0, 20.0)]
    assert sizes == sorted(sizes) and all(k % 2 == 1 for k in sizes)
    assert sizes[0] == 17 and sizes[-1] == 41  # the configured window and the cap
    # ~1.5 x the extent sqrt(12) sigma of a straight blur: a 24 px blur (sigma 6.9 px) -> 37 px.
    assert window.choose(24.0 / np.sqrt(12.0)) == 37
    assert WindowPolicy(per_extent=1.2).choose(24.0 / np.sqrt(12.0)) == 29
    assert window.choose(np.array([np.nan])) == 17
    assert window.choose(3.0, largest=15) == 17  # a cap below the start window is no cap
    assert window.adapts and not WindowPolicy(largest=17).adapts
    with pytest.raises(ValueError, match="odd"):
        WindowPolicy(largest=40)


def test_truncated_psf_is_refitted_with_a_larger_window() -> None:
    pattern = layout_pattern()
    sim = simulate_blocks(pattern, 6, np.random.default_rng(3), blur_px=(22.0, 24.0),
                          gauss_sigma=(0.3, 0.5), square_px=(34.0, 38.0), tile_px=128,
                          truth_kernel_size=41, init_shift_px=0.5)
    deconv = DeconvSettings()
    fixed = fit_blocks(sim.image.astype(np.float32), sim.H0, pattern.num_star_segments, 17, deconv)
    fitted = np.isfinite(fixed.boundary_energy)
    assert np.median(fixed.boundary_energy[fitted]) > 0.1  # a 17 px window truncates 23 px blur
    grown = fit_front(sim.image.astype(np.float32), sim.H0, pattern.num_star_segments, fixed, WindowPolicy(),
                      deconv, GrowSettings())
    assert grown.psf.shape[-1] > 17 and grown.kernel_size == grown.psf.shape[-1]
    ok = np.array([s is BlockStatus.ACCEPTED for s in grown.status])
    assert ok.sum() >= 5 and np.all(grown.boundary_energy[ok] < 0.12)
    err = np.linalg.norm(grown.centre[ok] - sim.centre_true[ok], axis=1)
    err_fixed = np.linalg.norm(fixed.centre[ok] - sim.centre_true[ok], axis=1)
    assert np.median(err) < 0.1 and np.median(err) < np.median(err_fixed)
    # Padding keeps the kernels: same sums, same centroid convention.
    assert np.allclose(np.nansum(grown.psf[ok], axis=(1, 2)), 1.0, atol=1e-3)


def _grid(n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """``(n^2, 2)`` feature coordinates and their star centres (px) through a perspective
    homography with 30 px squares."""
    fy, fx = np.mgrid[0:n, 0:n]
    f = np.stack([fx.ravel(), fy.ravel()], axis=1)
    H = np.array([[15.0, 2.0, 100.0], [-1.5, 14.0, 80.0], [3e-3, -2e-3, 1.0]])
    return f, apply_homography(H, f.astype(np.float64))


def test_block_off_its_neighbours_homography_is_inconsistent() -> None:
    f, c = _grid()
    moved = c.copy()
    moved[27] += [1.5, -0.5]  # settled 1.6 px off
    moved[36] += [0.3, 0.2]  # within the tolerance
    bad = inconsistent(f, moved, f, moved, 12, 1.0)
    assert np.flatnonzero(bad).tolist() == [27]
    # A chain: a whole front that settled 2 px off together agrees with itself, but not with the
    # blocks accepted before it, which are what a front is judged by during the growth.
    front = f[:, 0] == 7
    shifted = c[front] + [2.0, 0.0]
    assert not inconsistent(f[front], shifted, f[front], shifted, 12, 1.0).any()
    assert inconsistent(f[front], shifted, f[~front], c[~front], 12, 1.0).all()
    # Too few references, or references on a line: no judgement.
    assert not inconsistent(f[:1], c[:1] + 5.0, f[1:5], c[1:5], 12, 1.0).any()
    row = f[:, 1] == 0
    assert not inconsistent(f[8:9], c[8:9] + 5.0, f[row], c[row], 12, 1.0).any()


def test_tag_mask_follows_the_blur() -> None:
    """A straight 20 px blur: the fitted PSFs give a footprint along the blur, and the pixels it
    leaves out around a tag are far fewer than a disk of the kernel radius would."""
    pattern = layout_pattern()
    angle = 0.6
    sim = simulate_blocks(pattern, 4, np.random.default_rng(5), psf=line_kernel(20.0, angle),
                          square_px=(34.0, 38.0), tile_px=128, init_shift_px=0.5)
    fit = fit_blocks(sim.image.astype(np.float32), sim.H0, pattern.num_star_segments, 31)
    footprint = blur_footprint(fit, 20.0)
    assert footprint is not None
    ys, xs = np.nonzero(footprint)
    c = (footprint.shape[0] - 1) / 2
    orient = 0.5 * np.arctan2(2 * np.mean((xs - c) * (ys - c)),
                              np.mean((xs - c) ** 2) - np.mean((ys - c) ** 2))
    assert abs((orient - angle + np.pi / 2) % np.pi - np.pi / 2) < 0.1
    extent = np.hypot(xs - c, ys - c).max()
    assert 11.0 <= extent <= 20.0  # half the blur plus the seed margin and the width
    tag = np.zeros((200, 200), dtype=np.uint8)
    tag[80:120, 80:120] = 1
    along = pixel_mask(tag, 31, footprint)
    disk = pixel_mask(tag, 31)
    assert (~along).sum() < 0.75 * (~disk).sum()
    assert not along[tag == 1].any() and along.sum() > disk.sum()


@pytest.mark.slow
def test_window_adapts_where_the_blur_outgrows_it_away_from_the_tag() -> None:
    """Frame 11 of ``scripts/bench_yield.py``'s heavy set: its tag ring reads 14 px of blur
    extent with little boundary energy (0.06), so the ring keeps the configured window; the blur
    grows towards the image's edge and the growth widens the window from the first front whose
    PSFs reach its border. Measured: 261 blocks, max 0.10 px off, against 252 blocks, max 0.18 px
    with the window held at 17 px (medians 0.013 and 0.012 px)."""
    import torch

    from blurcalib.extract.frame import ExtractSettings, extract_frame
    from blurcalib.sim.synth import Simulator, SynthConfig

    torch.set_num_threads(1)
    sim = Simulator(SynthConfig(sharp=0, blurry=12, blur_min_px=12.0, blur_max_px=25.0,
                                noise_sigma=2.0, seed=11))
    frame = sim.frame(11)
    image = frame.image.astype(np.float32)

    def errors(settings: ExtractSettings) -> tuple[np.ndarray, list[int]]:
        g = extract_frame(image, sim.pattern, frame.truth.name, settings).growth
        rows = np.flatnonzero(g.accepted)
        d = g.fit.centre[rows] - frame.truth.mean[g.feature_id[rows]]
        sizes = [ev.psf.shape[-1] for ev in g.events]
        return np.linalg.norm(d - np.median(d, axis=0), axis=1), sizes

    fixed, fixed_sizes = errors(ExtractSettings(window=WindowPolicy(largest=17)))
    adapted, sizes = errors(ExtractSettings())
    assert set(fixed_sizes) == {17}
    assert sizes[0] == 17 and max(sizes) > 17  # the ring kept the window, later fronts widened it
    assert len(adapted) > 200 and len(fixed) > 200
    assert adapted.max() < fixed.max() and np.median(adapted) < 0.03


def test_a_front_whose_hints_fail_is_fitted_again_without_them() -> None:
    """PSF hints far from the true PSF (a corner of the window) leave every block of a front not
    converged, px off; the front is then fitted with the full schedule and lands on the truth."""
    pattern = layout_pattern()
    sim = simulate_blocks(pattern, 4, np.random.default_rng(21), blur_px=(5.0, 9.0), supersample=4,
                          tile_px=80, init_shift_px=0.4, truth_kernel_size=13)
    image = sim.image.astype(np.float32)
    deconv = DeconvSettings()
    wrong = np.zeros((4, 13, 13))
    wrong[:, :3, :3] = 1.0
    hinted = fit_blocks_hinted(image, sim.H0, pattern.num_star_segments, wrong, deconv)
    assert all(s is BlockStatus.NOT_CONVERGED for s in hinted.status)
    assert np.max(np.linalg.norm(hinted.centre - sim.centre_true, axis=1)) > 0.5
    fit = fit_hinted(image, sim.H0, pattern.num_star_segments, 13, deconv, None, wrong)
    assert all(s is BlockStatus.ACCEPTED for s in fit.status)
    assert np.max(np.linalg.norm(fit.centre - sim.centre_true, axis=1)) < 0.05


@pytest.mark.slow
def test_a_block_whose_hint_fails_is_fitted_again_while_its_front_succeeds() -> None:
    """In a front whose other blocks are accepted with good hints, a block given a wrong hint
    (a corner of the window) is left not converged, px off; its blur is short for its square, so
    it is fitted again with the full schedule and lands on the truth. Re-fitting only fronts
    that accept nothing (``retry_below_blur_per_square=0``) loses it."""
    pattern = layout_pattern()
    sim = simulate_blocks(pattern, 4, np.random.default_rng(21), blur_px=(5.0, 9.0), supersample=4,
                          tile_px=80, init_shift_px=0.4, truth_kernel_size=13)
    image = sim.image.astype(np.float32)
    deconv = DeconvSettings()
    hints = sim.psf_true.copy()
    hints[3] = 0.0
    hints[3, :3, :3] = 1.0
    hinted = fit_blocks_hinted(image, sim.H0, pattern.num_star_segments, hints, deconv)
    assert [s is BlockStatus.ACCEPTED for s in hinted.status] == [True, True, True, False]
    assert np.linalg.norm(hinted.centre[3] - sim.centre_true[3]) > 0.5
    assert np.array_equal(hinted.converged_within(deconv.converge_tol_px), hinted.converged)
    assert not hinted.converged_within(1.0)[3]  # no contrast: not fitted, however little it moved
    assert blur_per_square(psf_moments(hints[3:]).sigma_major, sim.H0[3:])[0] < 0.5
    front_only = fit_hinted(image, sim.H0, pattern.num_star_segments, 13, deconv, None, hints,
                            GrowSettings(retry_below_blur_per_square=0.0))
    assert front_only.status[3] is BlockStatus.NOT_CONVERGED
    fit = fit_hinted(image, sim.H0, pattern.num_star_segments, 13, deconv, None, hints)
    assert all(s is BlockStatus.ACCEPTED for s in fit.status)
    assert np.max(np.linalg.norm(fit.centre - sim.centre_true, axis=1)) < 0.05
    assert np.array_equal(fit.H[:3], hinted.H[:3])  # the accepted blocks keep their hinted fit


@pytest.mark.slow
def test_final_fit_over_a_larger_area_moves_inner_blocks_closer_to_the_truth() -> None:
    """The final fit (loss over 1.5 x the square, from the growth's fit) brings the inner blocks
    closer to the truth (measured over these 112 blocks of 14-18 px blur: median 0.0245 ->
    0.0202 px over the 82 inner ones); blocks on the pattern's rim, and fits that move further
    than ``final_max_shift_px``, are left as they were."""
    pattern = layout_pattern()
    deconv, window = DeconvSettings(), WindowPolicy(start=29)
    before, after, rim_kept, inner_changed, inner = [], [], [], [], []
    for seed in range(5, 12):
        sim = simulate_blocks(pattern, 16, np.random.default_rng(seed), blur_px=(14.0, 18.0),
                              square_px=(26.0, 30.0), tile_px=112, truth_kernel_size=29,
                              init_shift_px=0.3, supersample=4)
        image = sim.image.astype(np.float32)
        fit = fit_blocks(image, sim.H0, pattern.num_star_segments, 29, deconv)
        ok = np.array([s is BlockStatus.ACCEPTED for s in fit.status])
        ids = pattern.feature_ids(sim.features[:, 0], sim.features[:, 1])
        final = final_fit(image, pattern, ids, fit, ok, window, deconv, GrowSettings(), None)
        f = sim.features
        rim = (f[:, 0] == 0) | (f[:, 1] == 0) | (f[:, 0] == pattern.squares_x - 2) \
            | (f[:, 1] == pattern.squares_y - 2)
        changed = np.any(final.H != fit.H, axis=(1, 2))
        assert np.all(final.loss_extent == np.where(changed, 1.5, 1.0))
        rim_kept.append(not changed[rim].any())
        inner_changed.append(int(changed[~rim & ok].sum()))
        inner.append(int((~rim & ok).sum()))
        before.append(np.linalg.norm(fit.centre - sim.centre_true, axis=1)[changed])
        after.append(np.linalg.norm(final.centre - sim.centre_true, axis=1)[changed])
        if seed == 5:
            for rules in (GrowSettings(final_max_shift_px=1e-6), GrowSettings(final_extent=1.0)):
                kept = final_fit(image, pattern, ids, fit, ok, window, deconv, rules, None)
                assert np.array_equal(kept.H, fit.H) and np.array_equal(kept.psf, fit.psf, equal_nan=True)
    assert all(rim_kept) and sum(inner_changed) >= 0.9 * sum(inner) and sum(inner) >= 60
    b, a = np.concatenate(before), np.concatenate(after)
    assert np.median(a) < 0.9 * np.median(b) and np.percentile(a, 90) < np.percentile(b, 90)
    with pytest.raises(ValueError, match="final_fit_frames"):
        GrowSettings(final_fit_frames="sharp")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="final_extent"):
        GrowSettings(final_extent=0.5)
    with pytest.raises(ValueError, match="field_refit_px"):
        GrowSettings(field_refit_px=-0.1)
    with pytest.raises(ValueError, match="ring_refit_noise"):
        GrowSettings(ring_refit_noise=-1.0)


def test_field_blocks_are_spread_over_those_whose_loss_area_lies_inside_the_image() -> None:
    """The pattern overflows a 640 x 480 frame (30 px per feature): farthest-point sampling over
    every block off the rim picks blocks at the image's border whose 1.5 x squares cross it,
    which the field's fit would leave out; :func:`field_rows` spreads its 24 blocks over those
    inside, as far apart as they reach."""
    from blurcalib.deconv.windows import block_windows
    from blurcalib.growth.field import field_rows, spread
    from blurcalib.growth.final import inner
    from blurcalib.growth.seed import block_homography

    pattern = layout_pattern()
    ids = np.arange(len(pattern.features))
    H_feature = np.array([[30.0, 2.0, 60.0], [-1.5, 30.0, -20.0], [0.0, 0.0, 1.0]])
    H = block_homography(H_feature, pattern.features[:, 0], pattern.features[:, 1])
    shape, deconv, settings = (480, 640), DeconvSettings(), GrowSettings()
    wide = DeconvSettings(loss_extent=settings.final_extent)

    def inside(rows: np.ndarray) -> np.ndarray:
        return np.array([st is BlockStatus.ACCEPTED for st in block_windows(H[rows], shape, wide)[3]])

    off_rim = np.flatnonzero(inner(pattern, ids))
    before = off_rim[spread(H[off_rim, :2, 2], settings.field_blocks)]
    assert not inside(before).all()  # what the fit would have lost
    rows = field_rows(pattern, ids, H, shape, deconv, settings)
    assert len(rows) == settings.field_blocks and np.all(np.diff(rows) > 0)
    assert inside(rows).all() and inner(pattern, ids[rows]).all()
    pool = off_rim[inside(off_rim)]
    span = np.ptp(H[pool, :2, 2], axis=0)
    assert np.all(np.ptp(H[rows, :2, 2], axis=0) > 0.9 * span)
    # too few blocks inside: spread over all of them off the rim, as the fit can use some
    few = field_rows(pattern, ids, H, (60, 80), deconv, settings)
    assert len(few) == settings.field_blocks and inner(pattern, ids[few]).all()


@pytest.mark.slow
def test_the_path_field_locates_stars_whose_blur_is_as_long_as_their_squares() -> None:
    """Frame 3 of ``scripts/bench_yield.py``'s heavy set: 22 px of blur on 20-24 px squares (three
    quarters of its visible features have blur longer than their square). Free PSFs settle px
    off around the tag and the growth stops early; the growth seeded from the tag ring tied to one
    homography and grown with the frame's path-PSF field returns most stars, each within a few
    tenths of a px (measured: 71 -> 304-310 of 329 features, pose-consistent median 0.06 px, max
    0.65 px)."""
    import torch

    from blurcalib.extract.frame import ExtractSettings, extract_frame
    from blurcalib.sim.synth import Simulator, SynthConfig

    torch.set_num_threads(1)
    sim = Simulator(SynthConfig(sharp=0, blurry=12, blur_min_px=12.0, blur_max_px=25.0,
                                noise_sigma=2.0, seed=11))
    frame = sim.frame(3)
    truth = frame.truth
    image = frame.image.astype(np.float32)
    visible = int(truth.block_inside.sum())
    free = extract_frame(image, sim.pattern, truth.name, ExtractSettings(grow=GrowSettings(psf_field=False)))
    result = extract_frame(image, sim.pattern, truth.name, ExtractSettings())
    assert free.growth.psf_field is None and result.growth.psf_field is not None
    # the stages each growth ran: free PSFs then the second judgement, or the field in between
    assert list(free.growth.seconds) == ["free", "final", "judge"]
    assert list(result.growth.seconds) == ["free", "field", "judge"]
    assert len(free.features) < 0.35 * visible and len(result.features) > 0.85 * visible, (
        len(free.features), len(result.features), visible)
    ids = result.features.feature_id
    err = pose_consistent_errors(np.stack([result.features.x, result.features.y], axis=1), truth.mean[ids])
    assert np.median(err) < 0.1 and err.max() < 1.0, (np.median(err), err.max())
    field = result.growth.psf_field
    assert field.degree == 2 and 0.4 < np.exp(field.log_sigma) < 1.5
    path = field.theta(truth.mean[ids[:1]])[0, :2]  # the straight part of the path: its length
    assert abs(np.linalg.norm(path) - np.median(truth.blur_length[ids])) < 0.25 * np.median(truth.blur_length)


def test_a_tag_ring_fitted_far_above_the_noise_is_fitted_again_from_its_first_field() -> None:
    """Twelve blocks of one plane under a 26 px blur on 24 px squares (noise variance 4), each
    started 3 px off in its own direction (a tag ring's predictions under heavy blur), their
    free PSFs truncated by a 17 px window. From one start the ring's tied field fit settles px
    off at many times the noise's variance; :func:`ring_seed` given the noise fits it again from
    the first fit's field and lands on the stars. From another start the second fit settles off
    too (measured: 2.6 px), and the first is kept: the same result as without the noise."""
    from blurcalib.geometry.homography import homography_centre, translation
    from blurcalib.growth.field import ring_seed
    from blurcalib.growth.ledger import Growth
    from blurcalib.growth.seed import block_homography
    from blurcalib.psf.path import PathField
    from tests.deconv.test_field import SEGMENTS, _render_plane

    pattern = layout_pattern()
    H = np.array([[24.0, 2.0, 40.0], [-1.5, 24.0, 30.0], [1e-4, 5e-5, 1.0]])
    path = PathField(np.array([[24.0, 9.0, 2.0, -3.0]]), np.log(0.8), (360, 300))
    image = _render_plane(pattern, H, path.image_size, path.kernels(np.zeros((1, 2)), 45)[0],
                          np.random.default_rng(2))
    fx, fy = np.meshgrid(np.arange(4, 8), np.arange(3, 6))
    f = np.stack([fx.ravel(), fy.ravel()], axis=1).astype(float)
    ids = np.array([np.flatnonzero(np.all(pattern.features == p, axis=1))[0] for p in f])
    true = homography_centre(block_homography(H, f[:, 0], f[:, 1]))
    args = (WindowPolicy(), DeconvSettings(), GrowSettings(), None)
    for draw, lands in ((7, True), (3, False)):
        off = np.random.default_rng(draw).normal(size=(len(f), 2))
        off *= 3.0 / np.linalg.norm(off, axis=1, keepdims=True)
        H0 = translation(off) @ block_homography(H, f[:, 0], f[:, 1])
        growth = Growth(fit_blocks(image, H0, SEGMENTS, 17), ids, [BlockStatus.ACCEPTED] * len(ids),
                        np.zeros(len(ids), dtype=np.int64), H0)
        rows, H_once, _ = ring_seed(image, pattern, growth, *args)
        assert np.array_equal(rows, np.arange(len(ids)))
        assert np.median(np.linalg.norm(homography_centre(H_once) - true, axis=1)) > 1.0
        _, H_ring, field = ring_seed(image, pattern, growth, *args, noise_var=4.0)
        err = np.linalg.norm(homography_centre(H_ring) - true, axis=1)
        if lands:
            assert np.median(err) < 0.1 and err.max() < 0.2 and field.degree == 1, err
        else:
            np.testing.assert_array_equal(H_ring, H_once)
