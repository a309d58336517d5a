"""The damped least-squares driver: known minima, the damping rule, acceptance and stopping."""

from __future__ import annotations

import itertools
import logging
import math

import numpy as np
import pytest
import torch

from blurcalib.optim.lm import (
    Acceptance,
    Damping,
    LmRule,
    SingleProblem,
    Stop,
    Stopping,
    run_batch,
    run_single,
)


class Linear(SingleProblem[np.ndarray, tuple[np.ndarray, np.ndarray], np.ndarray]):
    """``|A x - y|^2``: its Gauss-Newton step is the least-squares solution."""

    def __init__(self, A: np.ndarray, y: np.ndarray) -> None:
        self.A, self.y = A, y

    def cost(self, x: np.ndarray) -> float:
        r = self.A @ x - self.y
        return float(r @ r)

    def linearise(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.A.T @ self.A, self.A.T @ (self.y - self.A @ x)

    def solve(self, system: tuple[np.ndarray, np.ndarray], lam: float) -> np.ndarray:
        N, g = system
        return np.linalg.solve(N + lam * np.diag(np.diag(N)), g)

    def trial(self, x: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, float]:
        return x + step, self.cost(x + step)


def rosenbrock(x: np.ndarray | torch.Tensor) -> tuple:
    """Rosenbrock's function as least squares, ``r = (10 (x2 - x1^2), 1 - x1)``, minimum 0 at
    ``(1, 1)``; rows of ``x (B, 2)``."""
    return 10.0 * (x[:, 1] - x[:, 0] ** 2), 1.0 - x[:, 0]


def rosenbrock_step(x: np.ndarray | torch.Tensor, lam: np.ndarray | torch.Tensor) -> tuple:
    """The damped Gauss-Newton step ``(N + lam diag(N)) d = -J^T r`` of :func:`rosenbrock`, by
    Cramer's rule on the 2 x 2 systems."""
    r1, r2 = rosenbrock(x)
    x1 = x[:, 0]
    a, b, d = (400.0 * x1 * x1 + 1.0) * (1.0 + lam), -200.0 * x1, 100.0 * (1.0 + lam)
    g1, g2 = 20.0 * x1 * r1 + r2, -10.0 * r1
    det = a * d - b * b
    return (d * g1 - b * g2) / det, (a * g2 - b * g1) / det


def rosenbrock_cost(x: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    r1, r2 = rosenbrock(x)
    return r1 * r1 + r2 * r2


class Rosenbrock(SingleProblem[np.ndarray, np.ndarray, np.ndarray]):
    """:func:`rosenbrock` of one point ``(2,)``."""

    def linearise(self, x: np.ndarray) -> np.ndarray:
        return x

    def solve(self, system: np.ndarray, lam: float) -> np.ndarray:
        return np.array(rosenbrock_step(system[None], np.float64(lam)))[:, 0]

    def trial(self, x: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, float]:
        return x + step, float(rosenbrock_cost((x + step)[None])[0])


class Rosenbrocks:
    """A batch of :func:`rosenbrock` problems, rows of ``x (B, 2)`` (numpy or torch)."""

    def __init__(self, x: np.ndarray | torch.Tensor) -> None:
        self.x = x.clone() if isinstance(x, torch.Tensor) else x.copy()  # the problem moves its rows
        self.cost = rosenbrock_cost(self.x)

    def solve(self, lam, going) -> None:
        self.step = rosenbrock_step(self.x, lam)

    def trial(self, rows, index: int, last: bool):
        moved = self.x[rows]
        moved[:, 0] += self.step[0][rows]
        moved[:, 1] += self.step[1][rows]
        self.moved = moved
        return rosenbrock_cost(moved)

    def accept(self, rows, accepted) -> None:
        self.x[rows[accepted]] = self.moved[accepted]
        self.cost[rows[accepted]] = rosenbrock_cost(self.moved[accepted])


class Scripted(SingleProblem[int, int, int]):
    """Trials accepted or rejected as ``outcomes`` says (the cost falls by 1 or rises by 1); the
    point counts accepted steps. ``converged_at``: the accepted step that ends the fit."""

    def __init__(self, outcomes: list[bool], converged_at: int | None = None) -> None:
        self.outcomes, self.converged_at, self.cost = list(outcomes), converged_at, 100.0

    def linearise(self, x: int) -> int:
        return x

    def solve(self, system: int, lam: float) -> int:
        return 1

    def trial(self, x: int, step: int) -> tuple[int, float]:
        return x + step, self.cost - 1.0 if self.outcomes.pop(0) else self.cost + 1.0

    def accept(self, x: int, moved: int, step: int, cost: float) -> tuple[int, float, bool]:
        self.cost = cost
        return moved, cost, moved == self.converged_at


def test_linear_least_squares_is_solved_in_one_step_at_vanishing_damping() -> None:
    rng = np.random.default_rng(1)
    A, y = rng.normal(size=(20, 3)), rng.normal(size=20)
    problem = Linear(A, y)
    rule = LmRule(Damping(start=1e-13, shrink=10.0, grow=10.0), Stopping(max_iterations=1, max_trials=5))
    run = run_single(problem, np.zeros(3), problem.cost(np.zeros(3)), rule)
    best = np.linalg.lstsq(A, y, rcond=None)[0]
    assert run.steps == 1 and run.stop is Stop.ITERATIONS
    np.testing.assert_allclose(run.x, best, rtol=0, atol=1e-10)
    assert run.cost == pytest.approx(problem.cost(best), rel=1e-12)


def test_rosenbrock_reaches_its_minimum() -> None:
    rule = LmRule(Damping(start=1e-3, shrink=3.0, grow=4.0, ceiling=1e10),
                  Stopping(max_iterations=200, rtol=1e-15, rtol_rejected=True))
    start = np.array([-1.2, 1.0])
    run = run_single(Rosenbrock(), start, float(rosenbrock_cost(start[None])[0]), rule)
    assert run.settled
    np.testing.assert_allclose(run.x, [1.0, 1.0], atol=1e-8)
    assert run.cost < 1e-16
    costs = [float(step.cost[0]) for step in run.log]
    assert all(b <= a for a, b in itertools.pairwise(costs))  # accepted steps only lower it


@pytest.mark.parametrize("kind", ["numpy", "torch"])
def test_batch_items_converge_at_their_own_step_and_drop_out(kind: str) -> None:
    starts = np.array([[-1.2, 1.0], [0.0, 0.0], [1.0, 1.0], [2.0, 3.0], [0.9, 0.8]])
    x = torch.as_tensor(starts) if kind == "torch" else starts
    problem = Rosenbrocks(x)
    rule = LmRule(Damping(start=1e-3, shrink=3.0, grow=4.0, ceiling=1e10),
                  Stopping(max_iterations=200, rtol=1e-15, rtol_rejected=True))
    run = run_batch(problem, rule)
    final = np.asarray(problem.x)
    np.testing.assert_allclose(final, np.ones_like(final), atol=1e-8)
    assert (np.asarray(run.stop) == Stop.CONVERGED).all()
    steps = np.asarray(run.steps)
    assert steps[2] == 0 and len(set(steps.tolist())) >= 3  # the start at the minimum takes none
    tried = np.stack([np.asarray(step.tried) for step in run.log])
    assert (tried[1:] <= tried[:-1]).all()  # an item that stopped is not tried again
    np.testing.assert_array_equal(tried.sum(axis=0), np.asarray(run.trials))


def test_damping_grows_on_rejection_and_shrinks_on_acceptance_down_to_its_floor() -> None:
    damping = Damping(start=1.0, shrink=2.0, grow=4.0, floor=0.3, ceiling=100.0)
    problem = Scripted([True, True, False, False, False, False, False])
    run = run_single(problem, 0, problem.cost, LmRule(damping, Stopping()))
    tried = [float(step.lam[0]) for step in run.log]
    assert tried == pytest.approx([1.0, 0.5, 0.3, 1.2, 4.8, 19.2, 76.8])
    assert [bool(step.accepted[0]) for step in run.log] == [True, True, False, False, False, False, False]
    assert run.lam == pytest.approx(307.2) and run.stop is Stop.DAMPING
    assert (run.steps, run.iterations, run.trials, run.x, run.cost) == (2, 3, 7, 2, 98.0)


def test_a_later_run_continues_from_the_damping_it_is_given() -> None:
    problem = Scripted([False, True])
    rule = LmRule(Damping(1.0, 2.0, 4.0), Stopping(max_iterations=1, max_trials=5))
    run = run_single(problem, 0, problem.cost, rule, lam=8.0)
    assert [float(step.lam[0]) for step in run.log] == [8.0, 32.0] and run.lam == 16.0


@pytest.mark.parametrize(("stopping", "outcomes", "stop", "trials"), [
    (Stopping(max_iterations=2, max_trials=9), [True] * 5, Stop.ITERATIONS, 2),
    (Stopping(max_trials=3), [False, True, False, True], Stop.TRIALS, 3),
    (Stopping(max_trials=9, max_rejections=3), [True, False, False, False, True], Stop.REJECTIONS, 4),
    (Stopping(max_trials=9, rtol=0.005), [True] * 9, Stop.TRIALS, 9),  # 1 of 100 and less: above it
    (Stopping(max_trials=9, rtol=0.011), [True] * 9, Stop.CONVERGED, 1),
    (Stopping(max_trials=9, rtol=0.011), [False] * 9, Stop.TRIALS, 9),
    (Stopping(max_trials=9, rtol=0.011, rtol_rejected=True), [False] * 9, Stop.CONVERGED, 1),
    (Stopping(max_trials=9), [True] * 9, Stop.CONVERGED, 3),  # the problem's own test, at step 3
])
def test_stopping_rules_fire(stopping: Stopping, outcomes: list[bool], stop: Stop, trials: int) -> None:
    problem = Scripted(outcomes, converged_at=3 if stop is Stop.CONVERGED and not stopping.rtol else None)
    run = run_single(problem, 0, problem.cost, LmRule(Damping(1.0, 2.0, 4.0), stopping))
    assert (run.stop, run.trials) == (stop, trials)


def test_an_unsolvable_step_is_a_rejected_trial() -> None:
    class Singular(Linear):
        def solve(self, system: tuple[np.ndarray, np.ndarray], lam: float) -> np.ndarray | None:
            return None if lam < 1.0 else super().solve(system, lam)

    problem = Singular(np.eye(2), np.ones(2))
    rule = LmRule(Damping(start=0.01, shrink=10.0, grow=10.0, ceiling=1e3), Stopping(max_iterations=1))
    run = run_single(problem, np.zeros(2), 2.0, rule)
    assert [bool(step.accepted[0]) for step in run.log] == [False, False, True]
    assert [float(step.lam[0]) for step in run.log] == pytest.approx([0.01, 0.1, 1.0])
    np.testing.assert_allclose(run.x, [0.5, 0.5])  # (N + N) d = g at lambda 1
    assert run.iterations == 1 and run.trials == 3


class Fixed(Scripted):
    """A trial of the given cost."""

    def __init__(self, cost: float) -> None:
        super().__init__([])
        self.trial_cost = cost

    def trial(self, x: int, step: int) -> tuple[int, float]:
        return x + step, self.trial_cost


@pytest.mark.parametrize(("acceptance", "accepted"), [
    (Acceptance(), [False, False, True, False]),
    (Acceptance(ties=True), [False, True, True, False]),
    (Acceptance(rtol=0.02), [True, True, True, False]),
])
def test_acceptance(acceptance: Acceptance, accepted: list[bool]) -> None:
    rule = LmRule(Damping(1.0, 2.0, 4.0), Stopping(max_trials=1), acceptance)
    runs = [run_single(Fixed(c), 0, 100.0, rule) for c in (101.0, 100.0, 99.0, math.nan)]
    assert [bool(run.log[0].accepted[0]) for run in runs] == accepted


def test_items_whose_step_is_not_worth_a_trial_stop_untried() -> None:
    problem = Rosenbrocks(np.array([[-1.2, 1.0], [0.0, 0.0]]))
    solve = problem.solve

    def only_the_first(lam, going):
        solve(lam, going)
        return np.array([True, False])

    problem.solve = only_the_first
    run = run_batch(problem, LmRule(Damping(1e-3, 3.0, 4.0), Stopping(max_trials=4)))
    assert run.stop.tolist() == [Stop.TRIALS, Stop.CONVERGED] and run.trials.tolist() == [4, 0]
    np.testing.assert_array_equal(problem.x[1], [0.0, 0.0])


class ScriptedBatch:
    """Items whose trials are accepted or rejected as their ``outcomes`` say (the cost falls or
    rises by 1)."""

    def __init__(self, outcomes: list[list[bool]]) -> None:
        self.outcomes = [list(o) for o in outcomes]
        self.cost = np.full(len(outcomes), 100.0)

    def solve(self, lam, going) -> None:
        return None

    def trial(self, rows, index: int, last: bool):
        self.moved = np.array([self.cost[b] + (-1.0 if self.outcomes[b].pop(0) else 1.0) for b in rows])
        return self.moved

    def accept(self, rows, accepted) -> None:
        self.cost[rows[accepted]] = self.moved[accepted]


def test_lockstep_rounds_move_items_together_and_stop_those_still_rejected() -> None:
    rejected = [False, False, False]
    problem = ScriptedBatch([[True] * 9, [False, True, *rejected], [True, True, *rejected]])
    rule = LmRule(Damping(1.0, 2.0, 4.0), Stopping(max_iterations=4, lockstep=3))
    run = run_batch(problem, rule)
    moved = np.stack([step.moved for step in run.log]).tolist()
    # round 1: item 1 rejected first, all accepted at the second trial; round 2: items 1 and 2 are
    # rejected at every trial: after 3 trials item 0 moves and they stop; item 0 goes on alone
    assert moved[:5] == [[False] * 3, [True] * 3, [False] * 3, [False] * 3, [True, False, False]]
    assert run.stop.tolist() == [Stop.ITERATIONS, Stop.REJECTIONS, Stop.REJECTIONS]
    assert run.steps.tolist() == [4, 1, 1] and problem.cost.tolist() == [96.0, 99.0, 99.0]
    assert run.trials.tolist() == [7, 5, 5] and len(run.log) == 7
    assert [float(step.lam[0]) for step in run.log[:5]] == [1.0, 0.5, 0.25, 0.125, 0.0625]
    assert [float(step.lam[1]) for step in run.log[:5]] == [1.0, 4.0, 2.0, 8.0, 32.0]


def test_rules_are_checked() -> None:
    with pytest.raises(ValueError, match="max_trials"):
        LmRule(Damping(1.0, 2.0, 4.0), Stopping(max_iterations=5))
    for bad in [dict(start=0.0, shrink=2.0, grow=4.0), dict(start=1.0, shrink=0.5, grow=4.0),
                dict(start=1.0, shrink=2.0, grow=1.0), dict(start=1.0, shrink=2.0, grow=4.0, floor=2.0)]:
        with pytest.raises(ValueError, match="damping"):
            Damping(**bad)


def test_each_step_is_logged_at_debug_level(caplog: pytest.LogCaptureFixture) -> None:
    problem = Scripted([True, False])
    with caplog.at_level(logging.DEBUG, logger="blurcalib.optim.lm"):
        run_single(problem, 0, problem.cost, LmRule(Damping(1.0, 2.0, 4.0), Stopping(max_trials=2)))
    lines = [r.getMessage() for r in caplog.records if r.name == "blurcalib.optim.lm"]
    assert lines == ["LM step 0: cost 99, lambda 1, accepted", "LM step 1: cost 99, lambda 0.5, rejected"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_batch_on_the_gpu_runs_as_on_the_cpu() -> None:
    starts = torch.tensor([[-1.2, 1.0], [0.0, 0.0], [2.0, 3.0]], dtype=torch.float64)
    rule = LmRule(Damping(start=1e-3, shrink=3.0, grow=4.0, ceiling=1e10), Stopping(max_trials=40))
    cpu, gpu = Rosenbrocks(starts), Rosenbrocks(starts.cuda())
    a, b = run_batch(cpu, rule), run_batch(gpu, rule)
    assert b.lam.device.type == "cuda" and b.log[-1].cost.device.type == "cuda"
    torch.testing.assert_close(gpu.x.cpu(), cpu.x, rtol=0, atol=1e-12)
    assert torch.equal(a.steps, b.steps.cpu()) and torch.equal(a.stop, b.stop.cpu())
