"""A calibrated rig against the simulated one: features from the truth, extrinsic errors.

A calibrated central camera's frame is its own gauge (:mod:`blurcalib.calib.bundle`: the image
centre along +z), turned from the true camera's by a small rotation ``Q_c``: the best-fit rotation
(:func:`blurcalib.camera.generic.best_fit_rotation`) taking the true camera's rays to the
calibrated camera's over a pixel lattice. The truth's pair ``camera j <- camera i`` seen in the
calibrated frames is ``(Q_j R Q_i^T, Q_j t)``; :func:`extrinsic_error` compares it with the
calibrated rig's: the angle of the rotation difference (deg) and the translation difference (mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from blurcalib.camera.generic import CentralGeneric, best_fit_rotation
from blurcalib.camera.rig import Rig
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureFlags, FeatureObservation, FeatureTable
from blurcalib.sim.evaluate import CameraAccuracy, camera_accuracy, pixel_lattice
from blurcalib.sim.rig import TrueRig
from blurcalib.sim.truth import FrameTruth, TrueCamera
from blurcalib.target.pattern import StarPattern

__all__ = ["ExtrinsicError", "RigAccuracy", "extrinsic_error", "frame_rotation", "rig_accuracy",
           "rig_accuracy_lines", "truth_features"]


def truth_features(frames: Sequence[FrameTruth], pattern: StarPattern, noise_px: float, shift_px: float,
                   rng: np.random.Generator, size: tuple[int, int] = (1280, 720)) -> FeatureTable:
    """The features of frames as exact as the truth: each visible feature's time-averaged position
    (its position in a sharp frame) plus Gaussian noise of ``noise_px`` px per axis, and, for a
    blurry frame, one random image shift of up to ``shift_px`` px per axis (the deconvolution's
    translational ambiguity), flagged ``SHARP_FRAME`` or ``BLURRY_FRAME``; features moved out of the
    ``size = (width, height)`` image are left out. Frame names are the truths' names."""
    rows = []
    points = pattern.points_3d()
    for truth in frames:
        shift = rng.uniform(-shift_px, shift_px, 2) if truth.kind == "blurry" else np.zeros(2)
        ids = np.nonzero(truth.visible)[0]
        kind = FeatureFlags.BLURRY_FRAME if truth.kind == "blurry" else FeatureFlags.SHARP_FRAME
        xy = truth.mean[ids] + shift + rng.normal(0.0, noise_px, (len(ids), 2))
        inside = np.all((xy >= 0) & (xy <= np.array(size) - 1.0), axis=1)
        ids, xy = ids[inside], xy[inside]
        for k, fid in enumerate(ids):
            fx, fy = pattern.features[fid]
            rows.append(FeatureObservation(truth.name, int(fid), int(fx), int(fy), float(points[fid, 0]),
                                           float(points[fid, 1]), float(xy[k, 0]), float(xy[k, 1]), 1.0,
                                           int(FeatureFlags.STAR_CENTRE | kind)))
    return FeatureTable.from_observations(rows)


def frame_rotation(truth: TrueCamera, model: CentralGeneric, step: float = 16.0) -> np.ndarray:
    """``Q (3, 3)``: the calibrated camera's frame from the true camera's (module docstring)."""
    px = pixel_lattice(truth.width, truth.height, step)
    est = model.pixel_to_ray(px)
    ok = np.all(np.isfinite(est), axis=1)
    return best_fit_rotation(truth.pixel_to_ray(px[ok]), est[ok])


@dataclass(frozen=True)
class ExtrinsicError:
    """A calibrated pair against the truth: ``rotation_deg`` (angle of the difference) and
    ``translation_mm`` (norm of the difference), and the true baseline (mm)."""

    rotation_deg: float
    translation_mm: float
    baseline_mm: float


def extrinsic_error(truth: TrueRig, rig: Rig, i: int = 0, j: int = 1) -> ExtrinsicError:
    """The calibrated pair ``camera j <- camera i`` of ``rig`` against ``truth``'s (module docstring)."""
    Qi = frame_rotation(truth.cameras[i], rig.cameras[i])
    Qj = frame_rotation(truth.cameras[j], rig.cameras[j])
    true = truth.relative(i, j)
    want = Pose(Qj @ true.R @ Qi.T, Qj @ true.t)
    got = rig.relative(i, j)
    c = (np.trace(got.R @ want.R.T) - 1.0) / 2.0
    return ExtrinsicError(float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))),
                          float(np.linalg.norm(got.t - want.t)) * 1000.0,
                          float(np.linalg.norm(true.t)) * 1000.0)


@dataclass(frozen=True)
class RigAccuracy:
    """A calibrated rig against the truth: ``cameras (C,)`` each generic camera against its true
    camera (:func:`blurcalib.sim.evaluate.camera_accuracy`), ``pairs`` each pair ``(i, j)`` with
    ``i < j`` and its :class:`ExtrinsicError`."""

    cameras: list[CameraAccuracy]
    pairs: list[tuple[int, int, ExtrinsicError]]


def rig_accuracy(truth: TrueRig, rig: Rig) -> RigAccuracy:
    """Every camera and every pair of ``rig`` against ``truth``."""
    cameras = [camera_accuracy(t, c) for t, c in zip(truth.cameras, rig.cameras, strict=True)]
    pairs = [(i, j, extrinsic_error(truth, rig, i, j))
             for i in range(rig.size) for j in range(i + 1, rig.size)]
    return RigAccuracy(cameras, pairs)


def rig_accuracy_lines(acc: RigAccuracy) -> list[str]:
    """One printable line per camera and per pair, in plain words."""
    lines = [f"camera {c}: the generic camera projects within {a.median:.4f} px of the true camera "
             f"(median over the image; 95% within {a.p95:.4f} px, worst {a.max:.4f} px)"
             for c, a in enumerate(acc.cameras)]
    lines += [f"camera {j} <- camera {i}: extrinsics off by {e.translation_mm:.4f} mm and "
              f"{e.rotation_deg:.5f} deg (true baseline {e.baseline_mm:.3f} mm)" for i, j, e in acc.pairs]
    return lines
