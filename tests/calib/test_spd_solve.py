"""The reduced camera system's solver: float32 factor with float64 refinement, float64 fallback."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from blurcalib.calib.spd_solve import solve_lower


def _spd(n: int, cond: float, seed: int) -> torch.Tensor:
    """A random ``(n, n)`` symmetric positive definite matrix of condition number ``cond``."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return torch.as_tensor((Q * np.geomspace(1.0, cond, n)) @ Q.T)


@pytest.mark.parametrize("cond", [1e3, 1e6, 3e7, 1e11])
def test_solution_matches_float64_reading_the_lower_triangle_only(cond: float) -> None:
    """Whichever path solves it (1e3, 1e6: the refined float32 factor; 3e7: the refinement
    does not converge; 1e11: no float32 factor; the last two fall back to float64): the float64
    solution, to the float64 solve's own accuracy, with garbage above the diagonal."""
    S = _spd(300, cond, 1)
    x_true = torch.as_tensor(np.random.default_rng(2).normal(size=300))
    b = S @ x_true
    exact = torch.cholesky_solve(b[:, None], torch.linalg.cholesky(S))[:, 0]
    garbage = torch.tril(S) + torch.triu(torch.full_like(S, 1e30), 1)
    x = solve_lower(garbage, b)
    scale = float(exact.abs().max())
    assert float((x - exact).abs().max()) <= max(1e-8 * scale, 10 * float((exact - x_true).abs().max()))


def test_not_positive_definite_raises() -> None:
    S = _spd(50, 10.0, 3)
    S[7, 7] = -1.0
    with pytest.raises(torch.linalg.LinAlgError):
        solve_lower(S, torch.ones(50, dtype=torch.float64))
