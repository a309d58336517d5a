"""A small, exact rig output folder, as ``blurcalib calibrate-rig`` writes it from frames, for the
app's rig tests: two 320 x 240 generic cameras 50 mm apart, three image sets of a 12 x 9 target
(2 cm) whose features are the cameras' exact projections, and each camera's frames (dots at its
features) in an input folder of its own. Written with the engine's writers, without extraction."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from blurcalib.camera.generic import fit_to_rays
from blurcalib.camera.parametric import BrownConrady
from blurcalib.camera.rig import Rig
from blurcalib.camera.rig_files import write_rig_folder, write_stereo_pair
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureFlags, FeatureObservation, FeatureTable, write_features
from blurcalib.pipeline.rig import CALIBRATION_DIR, RIG_REPORT_FILE
from blurcalib.pipeline.rig_frames import CAMERAS_DIR
from blurcalib.pipeline.run import MIXED

LENS = BrownConrady(fx=300.0, fy=299.0, cx=160.2, cy=119.6, k1=-0.05, k2=0.01, p1=0.0, p2=0.0, k3=0.0,
                    width=320, height=240)
_gx, _gy = np.meshgrid(np.arange(12) * 0.02, np.arange(9) * 0.02)
TARGET = np.column_stack([_gx.ravel(), _gy.ravel(), np.zeros(_gx.size)])
SET_NAMES = ["0001.png", "0002.png", "0003.png"]


@dataclass(frozen=True)
class RigScene:
    """The written folder ``out`` (the rig output), the rig and its sets' poses."""

    out: Path
    rig: Rig
    rig_tr_global: list[Pose]


def _frame_image(xy: np.ndarray) -> np.ndarray:
    image = np.full((240, 320), 60, np.uint8)
    for x, y in xy:
        cv2.circle(image, (round(x * 16), round(y * 16)), 3 * 16, 230, -1, cv2.LINE_AA, 4)
    return image


def write_rig_scene(root: Path, maps: bool = True) -> RigScene:
    """Write the scene (module docstring): inputs in ``root/cam0``, ``root/cam1``; the rig output in
    ``root/rig``."""
    camera = fit_to_rays(LENS.pixel_to_ray, 320, 240, cell_px=40.0)
    R = Pose.from_rvec_tvec([0.003, -0.008, 0.002], np.zeros(3)).R
    rig = Rig((camera, camera.rotated(Pose.from_rvec_tvec([0.0, 0.001, 0.0], np.zeros(3)).R)),
              (Pose.identity(), Pose(R, -R @ np.array([0.05, 0.001, 0.0]))))
    poses = [Pose.from_rvec_tvec([0.1, -0.2, 0.05], [-0.13, -0.09, 0.42]),
             Pose.from_rvec_tvec([-0.15, 0.1, -0.1], [-0.08, -0.07, 0.38]),
             Pose.from_rvec_tvec([0.2, 0.25, 0.0], [-0.12, -0.1, 0.45])]
    out = root / "rig"
    entries = []
    for c in range(2):
        rows = []
        for name, pose in zip(SET_NAMES, poses, strict=True):
            xy, ok = rig.cameras[c].project_valid(rig.camera_tr_rig[c].compose(pose).transform(TARGET))
            ok &= np.all((xy >= 0) & (xy <= [319, 239]), axis=1)
            flags = int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME)
            rows += [FeatureObservation(f"{MIXED}/{name}", int(k), int(k % 12), int(k // 12),
                                        float(TARGET[k, 0]), float(TARGET[k, 1]), float(xy[k, 0]),
                                        float(xy[k, 1]), 1.0, flags)
                     for k in np.nonzero(ok)[0]]
            (root / f"cam{c}").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / f"cam{c}" / name), _frame_image(xy[ok]))
        folder = out / CAMERAS_DIR / f"cam{c}"
        folder.mkdir(parents=True)
        write_features(folder / "features.csv", FeatureTable.from_observations(rows))
        entries.append({"features": str(folder / "features.csv"), "input": str(root / f"cam{c}"),
                        "frames": 3, "blurry_frames": 0, "generic_median_px": 0.0, "rig_median_px": 0.0,
                        "rig_rms_px": 0.0, "rig_observations": len(rows)})
    write_rig_folder(out / CALIBRATION_DIR, rig, poses, TARGET, np.arange(len(TARGET)))
    write_stereo_pair(out, rig, 0, 1, maps=maps)
    rel = rig.relative(0, 1)
    report = {"cameras": entries, "pairs": [{"cameras": [0, 1], "R": rel.R.tolist(), "T_m": rel.t.tolist(),
                                             "baseline_mm": float(np.linalg.norm(rel.t)) * 1000.0}],
              "sets": 3, "set_names": SET_NAMES}
    (out / RIG_REPORT_FILE).write_text(json.dumps(report))
    return RigScene(out, rig, poses)
