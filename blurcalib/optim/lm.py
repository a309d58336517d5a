"""The damped least-squares driver (Levenberg-Marquardt) of the engine's fits.

A fit lowers the cost ``c_b(x_b)`` of each of ``B`` independent items ``b`` at once (``B = 1``:
one problem); the cost is the problem's own (a robust sum of squared residuals, px^2 or grey
levels^2). From an item's linearisation at ``x_b`` (the normal equations ``N_b = J^T W J``,
``g_b = -J^T W r``, ``W`` the iteratively reweighted least squares weights) a step solves::

    (N_b + lambda_b D_b) delta_b = g_b,        D_b = diag(N_b)   (Marquardt's damping)

The problem forms ``N_b`` and ``g_b`` and solves the system (its Schur complements and the
floors and ridges of its diagonal are its own); this module runs the loop around it:

* **trial**: the point ``x_b + delta_b`` and its cost, for the items still going;
* **acceptance** (:class:`Acceptance`): a trial whose cost is finite and lower than the current
  one is accepted: the item moves there and is linearised again; a rejected item keeps its
  point and linearisation and tries again, more damped;
* **damping** (:class:`Damping`): ``lambda <- max(lambda / shrink, floor)`` after an accepted
  trial, ``lambda <- lambda grow`` after a rejected one; no trial is made above ``ceiling``;
* **stopping** (:class:`Stopping`, reasons :class:`Stop`): per item, the accepted steps, the
  rejections in a row, the cost's relative change and the problem's own tests of a step; the
  trial steps of the whole batch. An item that stops drops out of the later trials;
* **lock-step rounds** (:attr:`Stopping.lockstep`, optional): the items tried retry together
  from their linearisations until none of them is rejected, and only then move.

Every trial step appends an :class:`LmStep` to the run's log (the damping tried, the costs,
which items were tried, accepted and moved), logged at debug level. A batched problem keeps its
items' state in numpy arrays or torch tensors (any device); the loop's own per-item state lives
beside it, and the loop synchronises with the device once per trial step (the ``nonzero`` that
selects the items going; in lock-step rounds also the test whether all were accepted) and not
otherwise.

:func:`run_batch` runs a batched problem (:class:`BatchProblem`); :func:`run_single` runs one
problem written as functions of its point (:class:`SingleProblem`) on it.
"""

from __future__ import annotations

import itertools
import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, Generic, Protocol, TypeVar

import numpy as np
import torch

__all__ = ["Acceptance", "BatchProblem", "Damping", "LmRule", "LmRun", "LmStep", "SingleProblem", "SingleRun",
           "Stop", "Stopping", "run_batch", "run_single"]

log = logging.getLogger(__name__)

Array = Any
"""A ``numpy.ndarray`` or a ``torch.Tensor`` (one kind per run)."""


class Stop(IntEnum):
    """Why an item stopped."""

    GOING = 0
    """Still going (during a run only)."""
    CONVERGED = 1
    """A convergence test of :class:`Stopping` or of the problem fired."""
    DAMPING = 2
    """Its damping grew above the ceiling: no step lowers its cost any more."""
    REJECTIONS = 3
    """:attr:`Stopping.max_rejections` trials in a row were rejected."""
    ITERATIONS = 4
    """It took :attr:`Stopping.max_iterations` accepted steps."""
    TRIALS = 5
    """The run's :attr:`Stopping.max_trials` trial steps are spent."""


SETTLED = (Stop.CONVERGED, Stop.DAMPING)
"""Reasons that mean the cost is at a minimum to its own resolution."""


@dataclass(frozen=True)
class Damping:
    """The rule of the damping ``lambda`` (dimensionless, relative to ``diag(N)``).

    Attributes:
        start: ``lambda`` of an item's first trial.
        shrink: after an accepted trial ``lambda <- max(lambda / shrink, floor)``.
        grow: after a rejected trial ``lambda <- lambda grow``.
        floor: the smallest ``lambda`` after an accepted trial.
        ceiling: no trial is made with ``lambda > ceiling`` (the item stops, :attr:`Stop.DAMPING`).
    """

    start: float
    shrink: float
    grow: float
    floor: float = 0.0
    ceiling: float = math.inf

    def __post_init__(self) -> None:
        if not (0.0 <= self.floor <= self.start <= self.ceiling and self.start > 0):
            raise ValueError(f"damping needs 0 <= floor <= start <= ceiling, start > 0: {self}")
        if not (self.shrink >= 1.0 and self.grow > 1.0):
            raise ValueError(f"damping needs shrink >= 1 and grow > 1: {self}")

    def update(self, lam: Array, accepted: Array, ops: _Ops) -> Array:
        """The dampings after trials at ``lam (R,)``, ``accepted (R,)`` or not."""
        shrunk = lam / self.shrink
        if self.floor > 0:
            shrunk = ops.maximum(shrunk, self.floor)
        return ops.where(accepted, shrunk, lam * self.grow)


@dataclass(frozen=True)
class Acceptance:
    """Which trials are accepted: those of finite cost ``c'`` with ``c' < c (1 + rtol)`` (``<=``
    with ``ties``), ``c`` the item's current cost.

    Attributes:
        ties: accept a trial of the same cost.
        rtol: accept a trial whose cost exceeds the current one by up to this share of it (the
            resolution of a cost that is itself computed iteratively).
    """

    ties: bool = False
    rtol: float = 0.0

    def test(self, trial: Array, current: Array, ops: _Ops) -> Array:
        """``(R,)`` bool: the trials of costs ``trial (R,)`` accepted against ``current (R,)``."""
        bound = current if self.rtol == 0.0 else current * (1 + self.rtol)
        return ops.isfinite(trial) & ((trial <= bound) if self.ties else (trial < bound))


@dataclass(frozen=True)
class Stopping:
    """When an item stops (:class:`Stop`); None: no such limit.

    Attributes:
        max_iterations: accepted steps of an item (its linearisations after the first).
        max_trials: trial steps of the run (every item going takes one per step).
        max_rejections: rejected trials in a row of an item.
        rtol: an accepted trial that lowers the cost by at most this share of it,
            ``c - c' <= rtol c``, ends the item (converged).
        rtol_rejected: also a rejected trial that raises it by at most that share,
            ``c' - c <= rtol c`` (the cost's resolution reached).
        lockstep: rounds of at most this many trials in which the items tried retry together
            (None: an item moves as soon as its trial is accepted). In a round every item tried
            retries from its linearisation, at its own damping (relaxed after an accepted trial,
            grown after a rejected one), until none of them is rejected or the round's trials
            are spent; then the items whose last trial was accepted move and those whose last
            trial was rejected stop (:attr:`Stop.REJECTIONS`): the batch is linearised once per
            round. A round synchronises with the device at each trial.
    """

    max_iterations: int | None = None
    max_trials: int | None = None
    max_rejections: int | None = None
    rtol: float | None = None
    rtol_rejected: bool = False
    lockstep: int | None = None

    def converged(self, trial: Array, current: Array, accepted: Array) -> Array | None:
        """``(R,)`` bool, the items whose trial ends them by :attr:`rtol`, or None."""
        if self.rtol is None:
            return None
        done = accepted & (current - trial <= self.rtol * current)
        if self.rtol_rejected:
            done = done | (~accepted & (trial - current <= self.rtol * current))
        return done


@dataclass(frozen=True)
class LmRule:
    """A fit's damping, acceptance and stopping rules."""

    damping: Damping
    stopping: Stopping
    acceptance: Acceptance = Acceptance()

    def __post_init__(self) -> None:
        s = self.stopping
        each_bounded = s.max_rejections is not None or s.lockstep is not None
        bounded = (s.max_trials is not None or math.isfinite(self.damping.ceiling)
                   or (each_bounded and s.max_iterations is not None))
        if not bounded:
            raise ValueError("a fit needs max_trials, a finite damping ceiling, or max_iterations with "
                             "max_rejections or lockstep")


@dataclass
class LmStep:
    """One trial step of a run, ``(B,)`` arrays of the problem's kind and device.

    Attributes:
        index: the step (from 0).
        lam: the damping of each item's trial (the items not tried: their current damping).
        cost: the items' costs after the step.
        tried: the items that made a trial.
        accepted: the items whose trial was accepted.
        moved: the items that moved to their trial point (the accepted ones, or in a lock-step
            round none until it ends).
    """

    index: int
    lam: Array
    cost: Array
    tried: Array
    accepted: Array
    moved: Array

    def describe(self) -> str:
        """One line (a host synchronisation on a device)."""
        lam, cost = np.asarray(_host(self.lam)), np.asarray(_host(self.cost))
        tried, accepted = np.asarray(_host(self.tried)), np.asarray(_host(self.accepted))
        if len(cost) == 1:
            verdict = "accepted" if accepted[0] else ("rejected" if tried[0] else "not tried")
            return f"LM step {self.index}: cost {cost[0]:.9g}, lambda {lam[0]:.3g}, {verdict}"
        median = float(np.median(lam[tried])) if tried.any() else math.nan
        return (f"LM step {self.index}: {int(tried.sum())} of {len(cost)} items tried, {int(accepted.sum())} "
                f"accepted; cost sum {cost.sum():.9g}, median lambda tried {median:.3g}")


@dataclass
class LmRun:
    """What :func:`run_batch` did, ``(B,)`` arrays of the problem's kind and device.

    Attributes:
        lam: each item's damping at the end (to continue a fit with).
        stop: why each item stopped (:class:`Stop` values).
        steps: accepted steps per item.
        iterations: linearisations per item whose trials were made: its accepted steps, plus one
            where its last linearisation's trials were all rejected.
        trials: trials per item.
        log: the trial steps.
    """

    lam: Array
    stop: Array
    steps: Array
    iterations: Array
    trials: Array
    log: list[LmStep] = field(repr=False)


class BatchProblem(Protocol):
    """A batch of ``B`` items, its state (points, linearisations, trial points) kept by itself.

    Attributes:
        cost: ``(B,)`` float64, the items' current costs.
    """

    @property
    def cost(self) -> Array: ...

    def solve(self, lam: Array, going: Array) -> Array | None:
        """Solve the damped system of the items ``going (B,)`` with dampings ``lam (B,)``,
        linearising first those that moved (the others' steps may be solved or not); keep the
        steps. Returns ``(B,)`` bool, the items whose step is worth a trial (the others stop,
        converged), or None: all."""

    def trial(self, rows: Array, index: int, last: bool) -> Array:
        """The trial points of the items ``rows (R,)`` (their points plus their steps), kept;
        returns their costs ``(R,)`` (NaN where the step could not be solved). ``index`` is the
        trial step, ``last`` whether the run makes no trial after it."""

    def accept(self, rows: Array, accepted: Array) -> Array | None:
        """Move the items ``rows[accepted]`` to their trial points (updating :attr:`cost`).
        Returns ``(R,)`` bool, the items that the step ends (converged), or None."""


@dataclass(frozen=True)
class _Ops:
    """The array operations of a run, of numpy (:data:`_NUMPY`) or torch (:data:`_TORCH`)."""

    full: Callable[[Array, Any, Any], Array]  # (like, value, dtype): like's shape and device
    where: Callable[[Array, Any, Any], Array]
    isfinite: Callable[[Array], Array]
    nonzero: Callable[[Array], Array]  # (B,) bool -> the indices of its True entries
    maximum: Callable[[Array, float], Array]
    copy: Callable[[Array], Array]
    float64: Any
    int64: Any
    bool_: Any


_NUMPY = _Ops(lambda like, value, dtype: np.full(like.shape, value, dtype=dtype), np.where, np.isfinite,
              np.flatnonzero, np.maximum, np.copy, np.float64, np.int64, np.bool_)
_TORCH = _Ops(lambda like, value, dtype: torch.full(like.shape, value, dtype=dtype, device=like.device),
              torch.where, torch.isfinite, lambda mask: torch.nonzero(mask)[:, 0], torch.clamp_min,
              torch.clone, torch.float64, torch.int64, torch.bool)


def _host(a: Array) -> Array:
    return a.cpu().numpy() if isinstance(a, torch.Tensor) else a


class _Items:
    """The loop's per-item state: going, why stopped, accepted steps, trials, rejections in a row."""

    def __init__(self, ops: _Ops, cost: Array) -> None:
        self.ops = ops
        self.going = ops.full(cost, True, ops.bool_)
        self.stop = ops.full(cost, int(Stop.GOING), ops.int64)
        self.steps = ops.full(cost, 0, ops.int64)
        self.trials = ops.full(cost, 0, ops.int64)
        self.rejected = ops.full(cost, 0, ops.int64)

    def halt(self, mask: Array, reason: Stop) -> None:
        """Stop the items of ``mask (B,)`` still going, for ``reason``."""
        self.stop = self.ops.where(self.going & mask, int(reason), self.stop)
        self.going = self.going & ~mask

    def moved(self, rows: Array, accepted: Array) -> None:
        """Count the accepted steps ``accepted (R,)`` of the items ``rows (R,)`` and their rejections
        in a row."""
        self.steps[rows] += accepted
        self.rejected[rows] = self.ops.where(accepted, 0, self.rejected[rows] + 1)

    def halt_rows(self, rows: Array, mask: Array | None, reason: Stop) -> None:
        """Stop the items ``rows[mask]`` (``mask (R,)``; None: none) still going, for ``reason``."""
        if mask is not None:
            self.stop[rows] = self.ops.where(mask & self.going[rows], int(reason), self.stop[rows])
            self.going[rows] = self.going[rows] & ~mask


def run_batch(problem: BatchProblem, rule: LmRule, lam: Array | None = None) -> LmRun:
    """Levenberg-Marquardt on a batch (module docstring); ``lam (B,)`` continues from dampings
    of an earlier run (default :attr:`Damping.start`)."""
    ops = _TORCH if isinstance(problem.cost, torch.Tensor) else _NUMPY
    d, s = rule.damping, rule.stopping
    items = _Items(ops, problem.cost)
    lam = ops.full(problem.cost, d.start, ops.float64) if lam is None else ops.copy(lam)
    steps: list[LmStep] = []
    retries = 0  # trials so far of a lock-step round
    for index in range(s.max_trials) if s.max_trials is not None else itertools.count():
        if math.isfinite(d.ceiling):
            items.halt(lam > d.ceiling, Stop.DAMPING)
        if s.max_iterations is not None:
            items.halt(items.steps >= s.max_iterations, Stop.ITERATIONS)
        if s.max_rejections is not None:
            items.halt(items.rejected >= s.max_rejections, Stop.REJECTIONS)
        worth = problem.solve(lam, items.going)
        if worth is not None:
            items.halt(~worth, Stop.CONVERGED)
        tried = ops.copy(items.going)
        rows = ops.nonzero(tried)
        if len(rows) == 0:
            break
        current = problem.cost[rows]
        trial = problem.trial(rows, index, s.max_trials is not None and index == s.max_trials - 1)
        accepted = rule.acceptance.test(trial, current, ops)
        lam_tried = ops.copy(lam)
        lam[rows] = d.update(lam[rows], accepted, ops)
        items.trials[rows] += 1
        retries += 1
        moved = accepted
        if s.lockstep is not None and retries < s.lockstep and not bool(accepted.all()):
            moved = ops.full(accepted, False, ops.bool_)  # the round goes on
        else:
            retries = 0
            done = _either(s.converged(trial, current, accepted), problem.accept(rows, accepted))
            items.halt_rows(rows, done, Stop.CONVERGED)
            items.moved(rows, accepted)
            items.halt_rows(rows, None if s.lockstep is None else ~accepted, Stop.REJECTIONS)
        steps.append(LmStep(index, lam_tried, ops.copy(problem.cost), tried,
                            _scattered(ops, tried, rows, accepted), _scattered(ops, tried, rows, moved)))
        if log.isEnabledFor(logging.DEBUG):
            log.debug(steps[-1].describe())
    items.halt(items.going, Stop.TRIALS)
    iterations = items.steps + (items.rejected > 0)
    return LmRun(lam, items.stop, items.steps, iterations, items.trials, steps)


def _scattered(ops: _Ops, like: Array, rows: Array, values: Array) -> Array:
    """``(B,)`` bool: ``values (R,)`` at ``rows``, False elsewhere."""
    out = ops.full(like, False, ops.bool_)
    out[rows] = values
    return out


def _either(a: Array | None, b: Array | None) -> Array | None:
    if a is None:
        return b
    return a if b is None else a | b


X = TypeVar("X")
S = TypeVar("S")
D = TypeVar("D")


class SingleProblem(ABC, Generic[X, S, D]):
    """One problem (``B = 1``) as functions of its point ``X``: its linearisation ``S`` and steps ``D``."""

    @abstractmethod
    def linearise(self, x: X) -> S:
        """The undamped system at ``x`` (normal equations, with their weights)."""

    @abstractmethod
    def solve(self, system: S, lam: float) -> D | None:
        """The step of the system damped by ``lam``; None where it cannot be solved (not positive
        definite: the trial counts as rejected)."""

    @abstractmethod
    def trial(self, x: X, step: D) -> tuple[X, float]:
        """The point ``x`` moved by ``step``, and its cost."""

    def accept(self, x: X, moved: X, step: D, cost: float) -> tuple[X, float, bool]:
        """The point kept when ``moved`` (of cost ``cost``) is accepted from ``x``, its cost, and
        whether the step ends the fit (converged). Default: ``moved``, ``cost``, no."""
        return moved, cost, False


@dataclass
class SingleRun(Generic[X]):
    """What :func:`run_single` did.

    Attributes:
        x, cost: the final point and its cost.
        lam: the final damping; stop: why it stopped.
        iterations, steps, trials: as :class:`LmRun`'s.
        log: the trial steps (``(1,)`` arrays).
    """

    x: X
    cost: float
    lam: float
    stop: Stop
    iterations: int
    steps: int
    trials: int
    log: list[LmStep] = field(repr=False)

    @property
    def settled(self) -> bool:
        """Whether it stopped at a minimum of its cost (:data:`SETTLED`)."""
        return self.stop in SETTLED


class _Single(Generic[X, S, D]):
    """A :class:`SingleProblem` as a batch of one item (:class:`BatchProblem`)."""

    def __init__(self, problem: SingleProblem[X, S, D], x: X, cost: float) -> None:
        self.problem = problem
        self.x = x
        self.cost = np.array([cost], dtype=np.float64)
        self.system: S | None = None
        self.step: D | None = None
        self.moved: X | None = None
        self.moved_cost = math.nan

    def solve(self, lam: np.ndarray, going: np.ndarray) -> None:
        if going[0]:
            if self.system is None:
                self.system = self.problem.linearise(self.x)
            self.step = self.problem.solve(self.system, float(lam[0]))

    def trial(self, rows: np.ndarray, index: int, last: bool) -> np.ndarray:
        if self.step is None:
            return np.array([math.nan])
        self.moved, self.moved_cost = self.problem.trial(self.x, self.step)
        return np.array([self.moved_cost], dtype=np.float64)

    def accept(self, rows: np.ndarray, accepted: np.ndarray) -> np.ndarray | None:
        if not accepted[0] or self.moved is None or self.step is None:
            return None
        self.x, cost, done = self.problem.accept(self.x, self.moved, self.step, self.moved_cost)
        self.cost[0] = cost
        self.system = None
        return np.array([done])


def run_single(problem: SingleProblem[X, S, D], x: X, cost: float, rule: LmRule, lam: float | None = None
               ) -> SingleRun[X]:
    """Levenberg-Marquardt on one problem from ``x`` of cost ``cost`` (module docstring); ``lam``
    continues from the damping of an earlier run (default :attr:`Damping.start`)."""
    one = _Single(problem, x, cost)
    run = run_batch(one, rule, None if lam is None else np.array([lam], dtype=np.float64))
    return SingleRun(one.x, float(one.cost[0]), float(run.lam[0]), Stop(int(run.stop[0])),
                     int(run.iterations[0]), int(run.steps[0]), int(run.trials[0]), run.log)
