"""The pattern comparison of the paper (``fig:exp2_test``): glyph kernels, solver, metrics, claims."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from blurcalib.paper.patterns import (
    GLYPHS,
    PATTERNS,
    KernelSolver,
    PatternResult,
    PatternSettings,
    blur_valid,
    centred_homography,
    experiment_latent,
    format_table,
    glyph_kernel,
    latent_image,
    main,
    mean_scores,
    noise_gains,
    pattern_solvers,
    psnr,
    results_json,
    run_pattern_experiment,
    ssim,
    window_gram,
)


@pytest.fixture(scope="module")
def solvers() -> dict[tuple[str, int], KernelSolver]:
    return pattern_solvers()


@pytest.fixture(scope="module")
def results(solvers: dict[tuple[str, int], KernelSolver]) -> list[PatternResult]:
    return run_pattern_experiment(seed=0, solvers=solvers)


# ----------------------------------------------------------------------------------- kernels
@pytest.mark.parametrize("char", GLYPHS)
def test_glyph_kernel_is_a_15x15_psf(char: str) -> None:
    k = glyph_kernel(char)
    assert k.shape == (15, 15)
    assert (k >= 0).all()
    assert k.sum() == pytest.approx(1.0, abs=1e-12)
    # The glyph strokes carry the mass; the smoothed outer ring holds little of it.
    assert k[1:-1, 1:-1].sum() > 0.9


def test_glyphs_differ_and_keep_their_counters() -> None:
    kernels = [glyph_kernel(c) for c in GLYPHS]
    for i in range(len(kernels)):
        for j in range(i + 1, len(kernels)):
            assert np.abs(kernels[i] - kernels[j]).sum() > 0.3
    a = glyph_kernel("a")
    # The bowl of the 'a' is empty: its centre is much darker than the strokes around it.
    assert a[7, 7] < 0.5 * a.max()


def test_glyph_without_outline_is_rejected() -> None:
    with pytest.raises(ValueError, match="no outline"):
        glyph_kernel(" ")


# ---------------------------------------------------------------------- latent and solver
def test_latents_are_antialiased_binary_patterns() -> None:
    for pattern in PATTERNS:
        latent = latent_image(pattern, 64, homography=centred_homography(64, 16.0, rotation=0.2))
        assert latent.shape == (64, 64)
        assert latent.min() >= 0.0 and latent.max() <= 1.0
        assert 0.4 < latent.mean() < 0.6
        assert ((latent > 0.01) & (latent < 0.99)).any()  # anti-aliased edges
    with pytest.raises(ValueError, match="unknown pattern"):
        latent_image("dots", 16)


def test_blur_follows_the_psf_convention() -> None:
    rng = np.random.default_rng(1)
    latent = rng.random((20, 20))
    k = np.zeros((5, 5))
    k[2 + 1, 2 + 2] = 1.0  # offset d = (2, 1): I(x) = L(x - d)
    observed = blur_valid(latent, k)
    assert observed.shape == (16, 16)
    np.testing.assert_allclose(observed, latent[2 - 1:18 - 1, 2 - 2:18 - 2])


def test_solver_normal_equations_match_the_explicit_design_matrix() -> None:
    latent = experiment_latent("star", 30, PatternSettings())
    k = glyph_kernel("R")
    observed = blur_valid(latent, k)
    windows = np.lib.stride_tricks.sliding_window_view(latent, (15, 15))
    design = windows[:, :, ::-1, ::-1].reshape(-1, 15 * 15)  # D vec(k) = vec(k * L)
    np.testing.assert_allclose(design @ k.ravel(), observed.ravel(), atol=1e-12)
    gram = window_gram(latent, 15)[::-1, ::-1]
    np.testing.assert_allclose(gram, design.T @ design, rtol=1e-10, atol=1e-9)
    solver = KernelSolver(latent, 15, lam=0.0)
    np.testing.assert_allclose(solver.solve(observed, nonneg=False, unit_sum=False), k, atol=1e-8)
    ridge = KernelSolver(latent, 15, lam=0.01).solve(observed, nonneg=False, unit_sum=False)
    n = design.shape[0]
    expected = np.linalg.solve(design.T @ design / n + 0.01 * np.eye(225), design.T @ observed.ravel() / n)
    np.testing.assert_allclose(ridge.ravel(), expected, atol=1e-10)


def test_star_amplifies_noise_less_than_the_checkerboard(solvers) -> None:
    gains = noise_gains(solvers)
    for crop in (80, 160):
        assert gains[("star", crop)] < 0.5 * gains[("checkerboard", crop)]


# ----------------------------------------------------------------------------------- metrics
def test_ssim_of_identical_kernels_is_one_and_falls_with_noise() -> None:
    k = glyph_kernel("g")
    truth = k / k.max()
    assert ssim(truth, truth) == pytest.approx(1.0, abs=1e-12)
    assert psnr(truth, truth) == math.inf
    rng = np.random.default_rng(0)
    noise = rng.standard_normal(truth.shape)
    scores = [ssim(truth + s * noise, truth) for s in (0.01, 0.05, 0.2, 0.5)]
    assert all(a > b for a, b in itertools.pairwise(scores))
    assert scores[0] < 1.0
    assert ssim(truth + 0.05 * noise, truth) == pytest.approx(ssim(truth, truth + 0.05 * noise))
    db = [psnr(truth + s * noise, truth) for s in (0.01, 0.1)]
    assert db[0] == pytest.approx(db[1] + 20.0, abs=1e-9)


def test_ssim_of_constant_images_matches_the_formula() -> None:
    a, b = np.full((15, 15), 0.3), np.full((15, 15), 0.6)
    c1 = 0.01**2
    assert ssim(a, b) == pytest.approx((2 * 0.3 * 0.6 + c1) / (0.3**2 + 0.6**2 + c1))
    with pytest.raises(ValueError):
        ssim(np.zeros((9, 9)), np.zeros((9, 9)))


# ----------------------------------------------------------------------- the paper's claims
def test_experiment_covers_every_configuration(results: list[PatternResult]) -> None:
    assert len(results) == len(PATTERNS) * len(GLYPHS) * 2 * 2
    keys = {(r.pattern, r.glyph, r.crop, r.noise) for r in results}
    assert len(keys) == len(results)
    for r in results:
        assert r.kernel.shape == (15, 15)
        assert (r.kernel >= 0).all() and r.kernel.sum() == pytest.approx(1.0)


def test_without_noise_both_patterns_recover_the_kernel(results: list[PatternResult]) -> None:
    for r in results:
        if r.noise == 0.0:
            assert r.ssim > 0.9, r
            assert r.psnr > 25.0, r


def test_with_noise_the_star_beats_the_checkerboard(results: list[PatternResult]) -> None:
    means = mean_scores(results)
    star_ssim, star_psnr = means[("star", 0.05)]
    checker_ssim, checker_psnr = means[("checkerboard", 0.05)]
    assert star_ssim > checker_ssim + 0.1
    assert star_psnr > checker_psnr + 2.0


def test_experiment_is_deterministic(results: list[PatternResult], solvers) -> None:
    again = run_pattern_experiment(seed=0, crops=(80,), noise_levels=(0.05,), glyphs=("a",),
                                   solvers=solvers)
    first = next(r for r in results if (r.pattern, r.glyph, r.crop, r.noise) == ("star", "a", 80, 0.05))
    assert again[0] == first
    np.testing.assert_array_equal(again[0].kernel, first.kernel)


# ------------------------------------------------------------------------------------ output
def test_table_and_json(results: list[PatternResult]) -> None:
    table = format_table(results)
    assert table.count("\n") >= len(results) + 4
    assert "~0.96" in table and "~0.58" in table and "comparable" in table
    doc = results_json(results, PatternSettings(), 0, {("star", 80): 0.1, ("checkerboard", 80): math.inf})
    text = json.dumps(doc, allow_nan=False)
    assert json.loads(text)["settings"]["lam"] == PatternSettings().lam


@pytest.mark.slow
def test_main_writes_figure_and_json(tmp_path, capsys) -> None:
    out = tmp_path / "exp"
    assert main(["--out", str(out), "--seed", "3"]) == 0
    printed = capsys.readouterr().out
    assert "Means over glyphs and crops" in printed
    assert (out / "patterns.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads((out / "patterns.json").read_text())
    assert doc["seed"] == 3 and len(doc["rows"]) == 32
    assert sorted(p.name for p in out.iterdir()) == ["patterns.json", "patterns.png"]


def test_main_reports_bad_output_and_options(tmp_path, capsys) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["--out", str(blocker)]) == 2
    assert "blurcalib: error:" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "ok"), "--lam", "-1"]) == 2
    assert "lam" in capsys.readouterr().err
