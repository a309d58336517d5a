"""The cameras of a ``calibrate`` output folder against the true camera of simulated data.

This is ``blurcalib demo``'s answer to "is the camera better because of the blurry frames": each
camera's projection error against the truth over the image (px, OpenCV convention, after the
best-fit rotation: :func:`blurcalib.sim.evaluate.camera_accuracy`), for the parametric camera,
the generic camera of the sharp frames alone and the generic camera of sharp and blurry frames
together (and that camera with the rolling shutter off, when it was fitted); and whether each
generic camera's predicted uncertainty matches its true error: the RMS of the true error over
the RMS of the predicted sigma on ``uncertainty.npz``'s lattice (calibrated when near 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from blurcalib.calib.sharp import load_calibration
from blurcalib.calib.trust import UNCERTAINTY_NPZ
from blurcalib.camera.files import read_generic_yaml
from blurcalib.camera.generic import CentralGeneric
from blurcalib.camera.parametric import BrownConrady
from blurcalib.pipeline.run import CALIBRATION_DIR, GLOBAL_SHUTTER_DIR, SHARP_ONLY_DIR
from blurcalib.sim.evaluate import camera_accuracy, projection_errors
from blurcalib.sim.truth import TrueCamera


def _cameras(folder: Path) -> list[tuple[str, BrownConrady | CentralGeneric, str | None]]:
    """``(label, camera, uncertainty key or None)`` of each camera the folder holds."""
    cameras: list[tuple[str, BrownConrady | CentralGeneric, str | None]] = [
        ("parametric, sharp frames", load_calibration(folder).camera, None)]
    sharp_only = folder / SHARP_ONLY_DIR / "intrinsics0.yaml"
    if sharp_only.is_file():
        cameras.append(("generic, sharp frames", read_generic_yaml(sharp_only), "sigma_px_sharp"))
    if (folder / "intrinsics0.yaml").is_file():
        label = "generic, sharp + blurry frames" if len(cameras) > 1 else "generic, sharp frames"
        cameras.append((label, read_generic_yaml(folder / "intrinsics0.yaml"), "sigma_px"))
    global_shutter = folder / GLOBAL_SHUTTER_DIR / "intrinsics0.yaml"
    if global_shutter.is_file():
        cameras.append(("  the same, rolling shutter off", read_generic_yaml(global_shutter), None))
    return cameras


def camera_accuracy_lines(out: str | Path, truth: TrueCamera) -> list[str]:
    """The accuracy of each camera in ``out/calibration/`` (a ``calibrate`` output folder)
    against ``truth``, one printable line each after a heading."""
    folder = Path(out) / CALIBRATION_DIR
    unc = np.load(folder / UNCERTAINTY_NPZ) if (folder / UNCERTAINTY_NPZ).is_file() else None
    lines = ["camera against the true camera over the image (px, after the best-fit rotation; shape: after "
             "the best-fit focal lengths and principal point too, docs/generic.md):"]
    for label, camera, key in _cameras(folder):
        a = camera_accuracy(truth, camera)
        line = (f"  {label:<32} median {a.median:.4f}, p95 {a.p95:.4f}, max {a.max:.4f} "
                f"({100 * a.defined:.0f}% of the image calibrated); shape median {a.shape_median:.4f}, "
                f"focal scale {a.scale_px:+.4f} at the corners")
        if unc is not None and key in unc:
            sigma = unc[key].reshape(-1)
            px = np.column_stack([unc["x"].reshape(-1), unc["y"].reshape(-1)])
            ok = np.isfinite(sigma) & camera.in_area(px)
            err = projection_errors(truth, camera, px[ok])
            fine = np.isfinite(err)
            ratio = np.sqrt(np.mean(err[fine] ** 2)) / np.sqrt(np.mean(sigma[ok][fine] ** 2))
            line += f"; true error / predicted uncertainty (RMS) {ratio:.2f}"
        lines.append(line)
    return lines
