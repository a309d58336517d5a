"""Calibrate a rig of cameras from each camera's features (``blurcalib calibrate-rig``).

Each camera's features (a blurcalib ``features.csv`` or the reference tool's dataset ``.bin``,
:func:`blurcalib.io.feature_input.read_feature_input`; rows flagged ``BLURRY_FRAME`` are blurry
frames) are calibrated as ``blurcalib calibrate --features`` does: Brown-Conrady on the sharp
frames (:func:`blurcalib.calib.sharp.calibrate_sharp`), then the generic camera on the sharp and
blurry frames, a free image shift per blurry frame (:func:`blurcalib.calib.joint.calibrate_generic`).
Frames of the cameras with the same name form one image set; the rig's extrinsics come from the
joint bundle over all cameras (:func:`blurcalib.calib.rig_calibration.calibrate_rig`).

Outputs (``docs/rig.md``), written only once everything is computed, ``report.json`` last:
``calibration/`` the reference tool's rig folder (:func:`blurcalib.camera.rig_files.write_rig_folder`:
``intrinsics{N}.yaml``, ``camera_tr_rig.yaml``, ``rig_tr_global.yaml``, ``points.yaml``), and per
pair of cameras ``i < j`` OpenCV's ``stereo_{i}_{j}.yaml`` with, unless ``maps`` is off, the
rectification maps ``rectify_{i}_{j}.npz`` (:func:`blurcalib.camera.rig_files.write_stereo_pair`).
Each pair's entry in ``report.json`` carries its trust (:mod:`blurcalib.calib.rig_trust`): the
extrinsics' uncertainty (translation mm, rotation deg: the features' noise through the joint
bundle and each camera's own calibration error) and their 5-fold held-out error (px; null where
the pair shares no set).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from blurcalib.calib.joint import GenericCalibration, JointSettings, calibrate_generic
from blurcalib.calib.rig_calibration import RigCalibration, RigError, calibrate_rig
from blurcalib.calib.rig_trust import PairTrust, rig_trust
from blurcalib.calib.sharp import CalibrationError, calibrate_sharp
from blurcalib.camera.generic import DEFAULT_CELL_PX
from blurcalib.camera.rig_files import write_rig_folder, write_stereo_pair
from blurcalib.io.atomic import atomic_write_text, claim_output_dir
from blurcalib.io.feature_input import FeatureInputError, read_feature_input
from blurcalib.io.results import FeatureFlags
from blurcalib.pipeline.run import PipelineError
from blurcalib.target.pattern import StarPattern

__all__ = ["RIG_REPORT_FILE", "RigRun", "calibrate_rig_features", "rig_report", "write_rig_outputs"]

RIG_REPORT_FILE = "report.json"
CALIBRATION_DIR = "calibration"


@dataclass(eq=False)
class RigRun:
    """What :func:`calibrate_rig_features` did: the calibration, its report (``report.json``) and
    the files written."""

    calibration: RigCalibration
    report: dict[str, Any]
    outputs: list[Path]


def _camera(path: Path, pattern: StarPattern, image_size: tuple[int, int] | None, cell_px: float
            ) -> GenericCalibration:
    """One camera's generic calibration from its features (module docstring)."""
    try:
        table, size = read_feature_input(path, pattern, image_size)
    except FeatureInputError as exc:
        raise PipelineError(str(exc)) from None
    blurry = (table.flags & int(FeatureFlags.BLURRY_FRAME)) != 0
    sharp = table.select(~blurry)
    try:
        parametric = calibrate_sharp(sharp, pattern, size)
        return calibrate_generic(sharp, table.select(blurry) if blurry.any() else None, parametric, pattern,
                                 size, JointSettings(cell_px=cell_px))
    except CalibrationError as exc:
        raise PipelineError(f"{path}: sharp-set calibration: {exc}") from None
    except ValueError as exc:
        raise PipelineError(f"{path}: generic calibration: {exc}") from None


def rig_report(result: RigCalibration, features: Sequence[Path],
               inputs: Sequence[tuple[str, int]] | None = None, trust: Sequence[PairTrust] = ()
               ) -> dict[str, Any]:
    """The ``report.json`` document: per camera its features (and, from frames, its ``input`` and
    ``time_offset`` in frames, from ``inputs``),
    frames and errors (px), per pair ``camera j <- camera i`` (OpenCV's ``R``, ``T`` m), its
    baseline (mm) and its ``trust`` (:meth:`blurcalib.calib.rig_trust.PairTrust.to_dict`, NaN
    written as null), the number of image sets used and their names (``set_names``, in the order of
    ``calibration/rig_tr_global.yaml``'s poses)."""
    bundle = result.bundle
    cameras = [{"features": str(path), "frames": len(cal.frames), "blurry_frames": len(cal.blurry_frames),
                "generic_median_px": cal.median_error, "rig_median_px": float(bundle.median_error[c]),
                "rig_rms_px": float(bundle.rms_error[c]), "rig_observations": int(bundle.inlier[c].sum())}
               for c, (cal, path) in enumerate(zip(result.cameras, features, strict=True))]
    if inputs is not None:
        for cam, (source, offset) in zip(cameras, inputs, strict=True):
            cam["input"], cam["time_offset"] = source, offset
    pairs = []
    trusted = {(t.i, t.j): t.to_dict() for t in trust}
    for i in range(bundle.rig.size):
        for j in range(i + 1, bundle.rig.size):
            rel = bundle.rig.relative(i, j)
            extra = {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                     for k, v in trusted.get((i, j), {}).items() if k != "cameras"}
            pairs.append({"cameras": [i, j], "R": rel.R.tolist(), "T_m": rel.t.tolist(),
                          "baseline_mm": float(np.linalg.norm(rel.t)) * 1000.0, **extra})
    return {"cameras": cameras, "pairs": pairs, "sets": len(result.sets), "set_names": list(result.sets),
            "iterations": bundle.iterations,
            "pixel_convention": "opencv (top-left pixel centre at (0, 0))"}


def calibrate_rig_features(features: Sequence[str | os.PathLike[str]], pattern: StarPattern,
                           out_dir: str | os.PathLike[str], image_size: tuple[int, int] | None = None,
                           cell_px: float = DEFAULT_CELL_PX, maps: bool = True, overwrite: bool = False
                           ) -> RigRun:
    """Calibrate the rig whose cameras' features are ``features`` (one file per camera, camera 0
    first) and write its outputs into ``out_dir`` (module docstring).

    Raises:
        PipelineError: fewer than two cameras, a camera's unusable features or failed calibration,
            or cameras that share no image set (the message names the file or camera).
        OutputError: ``out_dir`` holds something else (unless ``overwrite``) or cannot be written.
    """
    paths = [Path(p) for p in features]
    if len(paths) < 2:
        raise PipelineError(f"a rig needs the features of two or more cameras, got {len(paths)}")
    t_cpu = time.process_time()
    cameras = [_camera(p, pattern, image_size, cell_px) for p in paths]
    try:
        result = calibrate_rig(cameras)
    except RigError as exc:
        raise PipelineError(f"rig: {exc}") from None
    out = claim_output_dir(out_dir, "calibrate-rig", {"features": [str(p.resolve()) for p in paths],
                                                       "cell_px": cell_px, "maps": maps}, overwrite)
    return write_rig_outputs(out, result, pattern, paths, maps, t_cpu)


def write_rig_outputs(out: Path, result: RigCalibration, pattern: StarPattern, features: Sequence[Path],
                      maps: bool, t_cpu: float, inputs: Sequence[tuple[str, int]] | None = None) -> RigRun:
    """Write the rig's outputs into the claimed folder ``out`` (module docstring), ``report.json``
    last (:func:`rig_report` of ``features`` and ``inputs``, with the CPU seconds since ``t_cpu``)."""
    points = pattern.points_3d()
    written = write_rig_folder(out / CALIBRATION_DIR, result.bundle.rig, result.bundle.rig_tr_global, points,
                               np.arange(len(points)))
    for i in range(len(result.cameras)):
        for j in range(i + 1, len(result.cameras)):
            written += write_stereo_pair(out, result.bundle.rig, i, j, maps=maps)[1]
    trust = rig_trust(result)
    report = {**rig_report(result, features, inputs, trust), "cpu_seconds": time.process_time() - t_cpu}
    written.append(atomic_write_text(out / RIG_REPORT_FILE, json.dumps(report, indent=1)))
    return RigRun(result, report, written)
