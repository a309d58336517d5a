"""Several patterns calibrated together: one joint target on which each pattern has a place.

A camera shown several targets (e.g. the 16-segment star and the checkerboard in turn on one
monitor) sees one pattern per frame, and each frame has a pose of its own. Put the patterns one
below the other on one sheet, pattern ``k`` moved down by the squares of the patterns above it::

    (fx, fy)_joint = (fx, fy + o_k),   P_joint = (fx L, (fy + o_k) L, 0) m,   o_k = sum_{j<k} squares_y(j)

and every frame's features become features of one target, with ids of their own (no two patterns
share a point, and the interior corners between them are never observed). A frame's pose absorbs
where its pattern lies on the sheet, so the calibration of the joint target (the parametric
camera with its refined target points, the generic camera, the assessment) is the calibration
from all frames, each through its own pattern's geometry. The joint target is a calibration
geometry only: it is never rendered or detected.

Frames are named ``<label>/<frame>`` in the joint tables (labels ``pattern1``, ``pattern2``, ...
in the order given), so that frames named alike in two patterns' files stay apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from blurcalib.io.results import FeatureTable
from blurcalib.target.pattern import PageLayout, StarPattern

__all__ = ["PatternSet", "pattern_set"]

SQUARE_TOLERANCE_M = 1e-9
"""Largest difference of two patterns' square lengths calibrated together (m)."""


@dataclass(frozen=True)
class PatternSet:
    """Patterns calibrated together and their joint target (module docstring).

    Attributes:
        patterns: the patterns, in the order given.
        labels: ``pattern1``, ``pattern2``, ...: the prefix of each pattern's frames.
        joint: the joint target (the patterns one below the other).
        offsets: ``o_k``, each pattern's rows moved down (squares).
    """

    patterns: tuple[StarPattern, ...]
    labels: tuple[str, ...]
    joint: StarPattern
    offsets: tuple[int, ...]

    def to_joint(self, k: int, table: FeatureTable) -> FeatureTable:
        """Pattern ``k``'s features as features of the joint target: ids, feature coordinates and
        target points moved by ``o_k``, frames named ``<label>/<frame>``."""
        fy = table.fy + self.offsets[k]
        ids = self.joint.feature_ids(table.fx, fy)
        if np.any(ids < 0):
            raise ValueError(f"feature coordinates outside {self.labels[k]}'s pattern")
        return replace(table, frame=np.char.add(f"{self.labels[k]}/", table.frame.astype(np.str_)),
                       feature_id=ids, fy=fy, Y=fy * self.joint.square_length_m)

    def pattern_of(self, frames: np.ndarray) -> np.ndarray:
        """``(N,)`` the pattern index of joint frame names ``(N,)`` (-1: no pattern's label)."""
        frames = np.asarray(frames, dtype=np.str_)
        out = np.full(len(frames), -1, dtype=np.int64)
        for k, label in enumerate(self.labels):
            out[np.char.startswith(frames, f"{label}/")] = k
        return out

    def frames_of(self, k: int, frames: Sequence[str]) -> list[str]:
        """The joint frame names of pattern ``k`` among ``frames``."""
        return [f for f in frames if f.startswith(f"{self.labels[k]}/")]


def pattern_set(patterns: Sequence[StarPattern]) -> PatternSet:
    """The joint target of ``patterns`` (module docstring).

    Raises:
        ValueError: fewer than two patterns, or square lengths that differ (the target points of
            one pattern would be scaled against the other's).
    """
    if len(patterns) < 2:
        raise ValueError(f"a pattern set needs at least two patterns, got {len(patterns)}")
    length = patterns[0].square_length_m
    for k, p in enumerate(patterns[1:], start=2):
        if abs(p.square_length_m - length) > SQUARE_TOLERANCE_M:
            raise ValueError(f"pattern {k}'s squares are {p.square_length_m * 1000:.6g} mm, pattern 1's "
                             f"{length * 1000:.6g} mm: patterns calibrated together need one square length")
    offsets = tuple(int(v) for v in np.cumsum([0] + [p.squares_y for p in patterns[:-1]]))
    squares_x = max(p.squares_x for p in patterns)
    squares_y = sum(p.squares_y for p in patterns)
    mm = patterns[0].square_length_mm
    page = PageLayout(width_mm=squares_x * mm, height_mm=squares_y * mm, pattern_start_x_mm=0.0,
                      pattern_start_y_mm=0.0, pattern_end_x_mm=squares_x * mm,
                      pattern_end_y_mm=squares_y * mm)
    tags = tuple(replace(t, tag_y=t.tag_y + o) for p, o in zip(patterns, offsets, strict=True)
                 for t in p.apriltags)
    joint = StarPattern(num_star_segments=patterns[0].num_star_segments, squares_x=squares_x,
                        squares_y=squares_y, square_length_m=length, page=page, apriltags=tags)
    return PatternSet(tuple(patterns), tuple(f"pattern{k + 1}" for k in range(len(patterns))), joint,
                      offsets)
