"""Duplicate views: frames that show the target from the same pose as an earlier frame.

Copies of one frame (or re-encodings of it, or frames of a camera and target that did not move)
add no geometry to a calibration: five copies of one sharp frame gave a "calibrated" camera
(median error 0.0014 px, fx 836 px against 900 px from five distinct views). A frame is a
duplicate of an earlier one when they observe the same features at the same image positions:

* they share at least :data:`MIN_SHARED` of the features of the one with fewer, and at least
  :data:`MIN_SHARED_FEATURES`, and
* the median distance ``median_i |p_i - q_i|`` (px) between the two frames' positions of their
  shared features is at most :data:`DUPLICATE_TOLERANCE_PX`.

Distinct views move the star centres by pixels to hundreds of pixels; a re-encoded or slightly
damaged copy moves them by hundredths to tenths of a pixel. Frames are compared in the given
order and the first of a group is kept, so a sharp frame is kept over its blurry copy when the
sharp frames come first. Candidate pairs are found through features seen in the same 2-px cell
(an index over all frames, linear in the observations), then measured exactly.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from blurcalib.io.record import FrameRecord, FrameStatus
from blurcalib.io.results import FeatureTable

DUPLICATE_TOLERANCE_PX = 0.25
"""Largest median distance (px) between two frames' shared star centres for a duplicate."""

MIN_SHARED = 0.5
"""Smallest fraction of the smaller frame's features that the two frames must share."""

MIN_SHARED_FEATURES = 8
"""Fewest shared features that can make two frames duplicates."""

_CELL_PX = 2.0
"""Cell of the candidate index (px): duplicates put most shared features in the same cell."""

@dataclass(frozen=True)
class Duplicate:
    """A frame found to duplicate an earlier one.

    Attributes:
        frame: the duplicate frame.
        original: the earlier frame it duplicates (kept).
        shared: features the two frames share.
        median_px: median distance between their shared features' positions (px).
    """

    frame: str
    original: str
    shared: int
    median_px: float

    @property
    def reason(self) -> str:
        """The ``frames.csv`` reason of the duplicate."""
        return (f"same view as {self.original}: {self.shared} shared features {self.median_px:.3f} px apart "
                f"(median; a duplicate is within {DUPLICATE_TOLERANCE_PX} px), so it adds nothing")


def find_duplicates(table: FeatureTable, order: Sequence[str]) -> list[Duplicate]:
    """The frames of ``order`` that duplicate an earlier frame of ``order`` (module docstring).

    Args:
        table: the frames' feature observations (frames not in ``order`` are ignored).
        order: frame names in the order of preference (the first of a group is kept).
    Returns:
        One :class:`Duplicate` per duplicate frame, in ``order``.
    """
    rows: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(0, dtype=np.int64))
    index = np.argsort(table.frame, kind="stable")
    names, starts = np.unique(table.frame[index], return_index=True)
    for name, rows_of in zip(names.tolist(), np.split(index, starts[1:]), strict=True):
        rows[name] = rows_of
    cells: dict[tuple[int, int, int], list[int]] = defaultdict(list)
    kept: list[str] = []
    found: list[Duplicate] = []
    for name in order:
        r = rows[name]
        if len(r) < MIN_SHARED_FEATURES:
            continue
        ids = table.feature_id[r]
        xy = np.stack([table.x[r], table.y[r]], axis=1)
        keys = list(zip(ids.tolist(), *np.floor(xy / _CELL_PX).astype(np.int64).T.tolist(), strict=True))
        votes = Counter(k for key in keys for k in cells.get(key, ()))
        duplicate = None
        for candidate, votes_for in votes.most_common():
            if votes_for < MIN_SHARED_FEATURES // 2:
                break
            duplicate = _compare(table, rows[kept[candidate]], ids, xy, name, kept[candidate])
            if duplicate is not None:
                break
        if duplicate is not None:
            found.append(duplicate)
            continue
        for key in keys:
            cells[key].append(len(kept))
        kept.append(name)
    return found


def _compare(table: FeatureTable, rows: np.ndarray, ids: np.ndarray, xy: np.ndarray, name: str,
             original: str) -> Duplicate | None:
    """``name`` (features ``ids``, positions ``xy (N, 2)``) as a duplicate of ``original``
    (its table rows ``rows``), or None when they are distinct views."""
    other_ids = table.feature_id[rows]
    shared, mine, theirs = np.intersect1d(ids, other_ids, return_indices=True)
    if len(shared) < max(MIN_SHARED_FEATURES, MIN_SHARED * min(len(ids), len(other_ids))):
        return None
    other = np.stack([table.x[rows][theirs], table.y[rows][theirs]], axis=1)
    median = float(np.median(np.linalg.norm(xy[mine] - other, axis=1)))
    if median > DUPLICATE_TOLERANCE_PX:
        return None
    return Duplicate(name, original, len(shared), median)


def mark_duplicates(records: Sequence[FrameRecord], table: FeatureTable) -> list[FrameRecord]:
    """The extracted frames ``records`` (in the order of preference) with each duplicate view
    given the status ``duplicate`` and the reason as its message, naming the frame it
    duplicates; only frames with status ``ok`` are compared.

    Args:
        records: the extraction's records.
        table: their feature observations.
    """
    order = [r.frame for r in records if r.status is FrameStatus.OK]
    duplicates = {d.frame: d for d in find_duplicates(table, order)}
    return [replace(r, status=FrameStatus.DUPLICATE, message=duplicates[r.frame].reason)
            if r.frame in duplicates else r for r in records]
