"""A fast stand-in for the per-frame engine of the runner (:mod:`blurcalib.runs.task`): a frame's
image value says where its target is, and a frame of value :data:`NO_TAG` has no tag, so that
tests exercise the runner, not the engine."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import blurcalib.runs.task as task_module
from blurcalib.extract.frame import FrameResult
from blurcalib.growth.seed import Seed
from blurcalib.io.record import FrameStatus
from blurcalib.io.results import FeatureTable

NO_TAG = 7
"""The image value of a frame whose tag is not found."""
SQUARE_PX = 30.0
"""The stand-in target's square side in every frame (px)."""


def grid_features(frame: str, shift: float) -> FeatureTable:
    """A 5 x 4 grid of star centres, :data:`SQUARE_PX` apart, moved by ``shift`` px."""
    fy, fx = (a.ravel().astype(float) for a in np.mgrid[0:4, 0:5])
    x, y = 100.0 + SQUARE_PX * fx + shift, 80.0 + SQUARE_PX * fy
    n = len(fx)
    return FeatureTable(np.full(n, frame), np.arange(n), fx, fy, fx * 0.01, fy * 0.01, x, y, np.ones(n),
                        np.ones(n, dtype=np.int64))


def install(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Put the stand-in in place of the engine; returns its calls, ``frame`` for an extraction
    from the frame's own tag and ``frame<-neighbour`` for one from a neighbour's seed (always
    accepted)."""
    calls: list[str] = []
    lock = threading.Lock()

    def extract(image, pattern, frame, settings=None, *args, **kwargs) -> FrameResult:
        with lock:
            calls.append(frame)
        if round(float(image.mean())) == NO_TAG:
            return FrameResult(frame, FrameStatus.NOT_SEEDED, "no AprilTag found (test)")
        features = grid_features(frame, float(image.mean()))
        return FrameResult(frame, FrameStatus.OK, features=features, kind="sharp")

    def from_neighbour(image, pattern, frame, hint, settings=None, *args) -> FrameResult:
        with lock:
            calls.append(f"{frame}<-{hint.neighbour}")
        seed = Seed(hint.H_feature, -1, np.zeros((0, 2)), 1.0, "given", "neighbour")
        return FrameResult(frame, FrameStatus.OK, f"seeded from neighbour {hint.neighbour}",
                           features=grid_features(frame, 1.0), seed=seed, kind="sharp")

    monkeypatch.setattr(task_module, "extract_frame", extract)
    monkeypatch.setattr(task_module, "seed_from_neighbour", from_neighbour)
    return calls
