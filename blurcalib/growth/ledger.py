"""The record of a frame's growth: a row per attempted block, the decisions as events, and
:class:`GrowthLedger`, which keeps both (the free and the field growth record through it)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from blurcalib.deconv.result import BlockFit
from blurcalib.io.results import BlockStatus
from blurcalib.psf.path import PathField
from blurcalib.target.pattern import StarPattern


@dataclass(frozen=True)
class GrowthEvent:
    """One block's decision, as reported to the callback.

    Attributes:
        feature_id: the block's feature id.
        fx, fy: its feature coordinates.
        status: accepted or the reason for rejection.
        H: ``(3, 3)`` fitted (or, when not fitted, predicted) block homography.
        psf: ``(K, K)`` fitted PSF (NaN when not fitted).
        loss: grey levels^2 (NaN when not fitted).
        front: index of the growth front (0 for the ring around the tag).
    """

    feature_id: int
    fx: int
    fy: int
    status: BlockStatus
    H: np.ndarray
    psf: np.ndarray
    loss: float
    front: int


@dataclass
class Growth:
    """Result of growing one frame.

    Attributes:
        fit: every attempted block's fit, concatenated over the fronts (``len(fit) == B``).
        feature_id: ``(B,)`` feature ids in the order of ``fit``.
        status: ``B`` statuses after the growth rules (``fit.status`` refined).
        front: ``(B,)`` growth front of each block.
        predicted: ``(B, 3, 3)`` the predictions the fits started from.
        events: every decision, in order (as reported to the callback).
        psf_field: the frame's path-PSF field when the growth used one
            (:func:`blurcalib.growth.field.field_growth`).
        seconds: wall time (s) of the stages :func:`blurcalib.growth.grow.grow` ran: ``free``
            (the fronts with free PSFs), ``field`` (the path-PSF field's fit and growth),
            ``final`` (the final fit), ``judge`` (the second judgement); stages not run are absent.
    """

    fit: BlockFit
    feature_id: np.ndarray
    status: list[BlockStatus]
    front: np.ndarray
    predicted: np.ndarray
    events: list[GrowthEvent] = field(default_factory=list)
    psf_field: PathField | None = None
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def accepted(self) -> np.ndarray:
        """``(B,)`` bool, blocks accepted by the growth."""
        return np.array([s is BlockStatus.ACCEPTED for s in self.status], dtype=bool)


class GrowthLedger:
    """The rows of one frame's growth as it goes: per attempted block its feature id, status,
    front, prediction and fit, the accepted blocks' homographies and PSFs by feature id, and the
    decision events, each reported to ``on_event`` as it is recorded.

    Args:
        pattern: the target.
        on_event: called with every event, in order.
        growth: a growth to go on from (its rows, fits and events), or None to start empty.
    """

    def __init__(self, pattern: StarPattern, on_event: Callable[[GrowthEvent], None] | None = None,
                 growth: Growth | None = None) -> None:
        self.pattern = pattern
        self.on_event = on_event
        self.ids: list[int] = [] if growth is None else [int(v) for v in growth.feature_id]
        self.status: list[BlockStatus] = [] if growth is None else list(growth.status)
        self.front: list[int] = [] if growth is None else [int(v) for v in growth.front]
        self.predicted: list[np.ndarray] = [] if growth is None else list(growth.predicted)
        self.fit: BlockFit | None = None if growth is None else growth.fit
        self.events: list[GrowthEvent] = [] if growth is None else list(growth.events)
        self.row: dict[int, int] = {fid: k for k, fid in enumerate(self.ids)}
        self.accepted_H: dict[int, np.ndarray] = {}
        self.accepted_psf: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.ids)

    def record(self, feature_id: int, status: BlockStatus, front: int, predicted: np.ndarray,
               fit: BlockFit, k: int) -> int:
        """The decision ``status`` on block ``feature_id`` of ``front``, started from
        ``predicted (3, 3)`` and fitted as row ``k`` of ``fit``: a new row, or the block's row
        updated; reported. Its fit joins the rows with :meth:`add_fits` or :meth:`replace_fits`.
        Returns the row."""
        row = self.row.get(feature_id)
        if row is None:
            row = self.row[feature_id] = len(self.ids)
            self.ids.append(feature_id)
            self.status.append(status)
            self.front.append(front)
            self.predicted.append(predicted)
        else:
            self.status[row], self.front[row], self.predicted[row] = status, front, predicted
        self.emit(row, fit, k)
        return row

    def restate(self, row: int, status: BlockStatus, fit: BlockFit, k: int) -> None:
        """Row ``row`` now has ``status`` (fitted as row ``k`` of ``fit``); reported."""
        self.status[row] = status
        self.emit(row, fit, k)

    def emit(self, row: int, fit: BlockFit, k: int) -> None:
        """Record, and report to ``on_event``, row ``row``'s decision, its block fitted as row
        ``k`` of ``fit`` (a block not fitted keeps its prediction as ``H``)."""
        fid = self.ids[row]
        fx, fy = (int(v) for v in self.pattern.features[fid])
        event = GrowthEvent(fid, fx, fy, self.status[row], fit.H[k], fit.psf[k], float(fit.loss[k]),
                            int(self.front[row]))
        self.events.append(event)
        if self.on_event is not None:
            self.on_event(event)

    def accept(self, feature_id: int, H: np.ndarray, psf: np.ndarray | None = None) -> None:
        """Block ``feature_id`` is accepted with ``H (3, 3)`` (normalised here) and its re-centred
        ``psf``."""
        self.accepted_H[feature_id] = H / H[2, 2]
        if psf is not None:
            self.accepted_psf[feature_id] = psf

    def add_fits(self, fit: BlockFit) -> None:
        """Append ``fit``'s rows to the rows' fits (in the order they were recorded)."""
        self.fit = fit if self.fit is None else BlockFit.concat([self.fit, fit])

    def replace_fits(self, rows: np.ndarray, other: BlockFit, other_rows: np.ndarray) -> None:
        """The fits of rows ``rows`` are now the rows ``other_rows`` of ``other``."""
        assert self.fit is not None  # rows to replace are rows added
        self.fit = self.fit.with_rows(rows, other, other_rows)

    @property
    def accepted_rows(self) -> np.ndarray:
        """``(R,)`` int, the rows accepted so far."""
        return np.array([k for k, st in enumerate(self.status) if st is BlockStatus.ACCEPTED], dtype=np.int64)

    def growth(self, psf_field: PathField | None = None) -> Growth:
        """The :class:`Growth` of the rows recorded (their fits all added)."""
        assert self.fit is not None  # callers record a fit first
        return Growth(self.fit, np.array(self.ids, dtype=np.int64), list(self.status),
                      np.array(self.front, dtype=np.int64), np.stack(self.predicted), list(self.events),
                      psf_field)
