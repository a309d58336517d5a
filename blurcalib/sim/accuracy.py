"""The cameras of a ``calibrate`` output folder against the true camera of simulated data.

This is ``blurcalib demo``'s answer to "is the camera better because of the blurry frames": each
camera's projection error against the truth over the image (px, OpenCV convention, after the
best-fit rotation: :func:`blurcalib.sim.evaluate.camera_accuracy`), for the parametric camera,
the generic camera of the sharp frames alone and the generic camera of sharp and blurry frames
together (and that camera with the rolling shutter off, when it was fitted); and whether each
generic camera's predicted uncertainty matches its true error: the RMS of the true error over
the RMS of the predicted sigma on ``uncertainty.npz``'s lattice (honest when near 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from blurcalib.calib.sharp import load_calibration
from blurcalib.calib.trust import UNCERTAINTY_NPZ
from blurcalib.camera.files import read_generic_yaml
from blurcalib.camera.generic import CentralGeneric
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.pipeline.run import CALIBRATION_DIR, GLOBAL_SHUTTER_DIR, SHARP_ONLY_DIR
from blurcalib.sim.evaluate import CameraAccuracy, camera_accuracy, projection_errors
from blurcalib.sim.truth import TrueCamera

PARAMETRIC, GENERIC_SHARP, GENERIC_BOTH, GLOBAL_SHUTTER = (
    "parametric, sharp frames", "generic, sharp frames", "generic, sharp + blurry frames",
    "generic, rolling shutter off")
"""Labels of the cameras a ``calibrate`` folder can hold."""


@dataclass(frozen=True)
class TrueAccuracy:
    """One camera against the truth: its ``label``, its :class:`CameraAccuracy` and the RMS of
    its true error over the RMS of its predicted uncertainty (None without an uncertainty map)."""

    label: str
    accuracy: CameraAccuracy
    honesty: float | None


def _cameras(folder: Path) -> list[tuple[str, BrownConrady | ParametricCamera | CentralGeneric, str | None]]:
    """``(label, camera, uncertainty key or None)`` of each camera the folder holds."""
    cameras: list[tuple[str, BrownConrady | ParametricCamera | CentralGeneric, str | None]] = [
        (PARAMETRIC, load_calibration(folder).camera, None)]
    sharp_only = folder / SHARP_ONLY_DIR / "intrinsics0.yaml"
    if sharp_only.is_file():
        cameras.append((GENERIC_SHARP, read_generic_yaml(sharp_only), "sigma_px_sharp"))
    if (folder / "intrinsics0.yaml").is_file():
        label = GENERIC_BOTH if len(cameras) > 1 else GENERIC_SHARP
        cameras.append((label, read_generic_yaml(folder / "intrinsics0.yaml"), "sigma_px"))
    global_shutter = folder / GLOBAL_SHUTTER_DIR / "intrinsics0.yaml"
    if global_shutter.is_file():
        cameras.append((GLOBAL_SHUTTER, read_generic_yaml(global_shutter), None))
    return cameras


def true_accuracies(out: str | Path, truth: TrueCamera) -> list[TrueAccuracy]:
    """Every camera in ``out/calibration/`` (a ``calibrate`` output folder) against ``truth``."""
    folder = Path(out) / CALIBRATION_DIR
    unc = np.load(folder / UNCERTAINTY_NPZ) if (folder / UNCERTAINTY_NPZ).is_file() else None
    found = []
    for label, camera, key in _cameras(folder):
        honesty = None
        if unc is not None and key in unc and isinstance(camera, CentralGeneric):
            sigma = unc[key].reshape(-1)
            px = np.column_stack([unc["x"].reshape(-1), unc["y"].reshape(-1)])
            ok = np.isfinite(sigma) & camera.in_area(px)
            err = projection_errors(truth, camera, px[ok])
            fine = np.isfinite(err)
            honesty = float(np.sqrt(np.mean(err[fine] ** 2)) / np.sqrt(np.mean(sigma[ok][fine] ** 2)))
        found.append(TrueAccuracy(label, camera_accuracy(truth, camera), honesty))
    return found


def camera_accuracy_lines(found: list[TrueAccuracy]) -> list[str]:
    """One printable line per camera after a heading, in plain words."""
    lines = ["each camera against the true camera (px over the image, after the best-fit rotation):"]
    for t in found:
        a = t.accuracy
        line = (f"  {t.label:<32} median {a.median:.4f}, 95% within {a.p95:.4f}, worst {a.max:.4f} "
                f"({100 * a.defined:.0f}% of the image calibrated); lens shape alone {a.shape_median:.4f}, "
                f"focal length off by {a.scale_px:+.4f} at the corners")
        if t.honesty is not None:
            line += f"; true error {t.honesty:.2f} x the predicted uncertainty"
        lines.append(line)
    return lines
