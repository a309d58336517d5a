"""The app's loaded rig: a ``calibrate-rig`` output folder (:mod:`blurcalib.pipeline.rig_output`) and
what its views show, computed by the engine on first use and kept.

* per camera: its reprojection errors in the rig (:func:`blurcalib.calib.rig_residuals.camera_residuals`)
  and its frame of an image set;
* per pair and image set: both frames remapped into the pair's rectified images (the output's maps,
  :func:`blurcalib.pipeline.rig_output.rig_rectification_maps`) and the set's epipolar error
  (:func:`blurcalib.calib.rig_residuals.set_epipolar`);
* the target's points of each set in the rig's frame, for the 3D view.

Thread-safe: the views' redraw threads call it; one lock guards the caches.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from blurcalib.calib.rig_residuals import CameraResiduals, SetEpipolar, camera_residuals, set_epipolar
from blurcalib.io.results import FeatureFlags
from blurcalib.pipeline.rig_output import (
    RigOutput,
    RigOutputError,
    RigPair,
    load_set_frame,
    read_rig_output,
    rig_rectification_maps,
)

__all__ = ["RectifiedSet", "RigOutputError", "RigState", "load_rig"]


@dataclass(frozen=True, eq=False)
class RectifiedSet:
    """A pair's image set, rectified.

    Attributes:
        pair: the pair.
        set_name: the image set.
        images: ``(2,)`` each camera's frame remapped into its rectified image ``(H, W)`` uint8, None
            where the frame is not available.
        missing: why frames are not shown (empty when both are).
        epipolar: the set's features both cameras see, rectified, and their epipolar errors.
        blurry: whether either camera's frame of the set is blurry (its free image shift, which the
            files do not hold, is in the epipolar error).
    """

    pair: RigPair
    set_name: str
    images: tuple[np.ndarray | None, np.ndarray | None] = field(repr=False)
    missing: str
    epipolar: SetEpipolar = field(repr=False)
    blurry: bool


class RigState:
    """A loaded rig output (module docstring)."""

    def __init__(self, output: RigOutput) -> None:
        self.output = output
        self._lock = threading.Lock()
        self._residuals: dict[int, CameraResiduals] = {}
        self._maps: dict[tuple[int, int], tuple[np.ndarray, ...]] = {}

    @property
    def camera_labels(self) -> list[str]:
        """``cam0``, ``cam1``, ... one per camera."""
        return [f"cam{c}" for c in range(self.output.rig.size)]

    @property
    def set_labels(self) -> list[str]:
        """The image sets' names (``set k`` where the folder does not name them)."""
        return [self.output.set_label(s) for s in range(len(self.output.rig_tr_global))]

    @property
    def pair_labels(self) -> list[str]:
        """``cam0 - cam1``, ... one per pair with a stereo file."""
        return [f"cam{p.i} - cam{p.j}" for p in self.output.pairs]

    def residuals(self, c: int) -> CameraResiduals:
        """Camera ``c``'s reprojection errors in the rig (computed once)."""
        with self._lock:
            if c not in self._residuals:
                out = self.output
                self._residuals[c] = camera_residuals(out.rig, c, out.set_poses, out.cameras[c].features)
            return self._residuals[c]

    def frame(self, c: int, set_name: str) -> np.ndarray | None:
        """Camera ``c``'s frame of ``set_name`` (grey levels ``(H, W)``), None when not available."""
        return load_set_frame(self.output.cameras[c], set_name)

    def set_points(self, s: int) -> np.ndarray | None:
        """``(M, 3)`` m: the target's points of image set ``s`` in the rig's frame (None: unused set)."""
        pose = self.output.rig_tr_global[s]
        return None if pose is None else pose.transform(self.output.points)

    def _pair_maps(self, pair: RigPair) -> tuple[np.ndarray, ...]:
        with self._lock:
            key = (pair.i, pair.j)
            if key not in self._maps:
                self._maps[key] = rig_rectification_maps(self.output, pair)
            return self._maps[key]

    def rectified(self, p: int, set_name: str) -> RectifiedSet:
        """Pair ``p``'s image set ``set_name``, rectified (module docstring).

        Raises:
            RigOutputError: the pair's maps file cannot be read.
        """
        out = self.output
        pair = out.pairs[p]
        cams = (pair.i, pair.j)
        epipolar = set_epipolar(pair.rectification, out.rig.cameras[pair.i], out.rig.cameras[pair.j],
                                out.cameras[pair.i].features, out.cameras[pair.j].features, set_name)
        frames = [self.frame(c, set_name) for c in cams]
        missing = []
        for c, image in zip(cams, frames, strict=True):
            if image is None:
                cam = out.cameras[c]
                where = (f"its input {cam.source} is not found" if cam.found is None
                         else f"no readable frame {set_name} in {cam.found}")
                missing.append(f"cam{c}: {where}")
        images: list[np.ndarray | None] = [None, None]
        if any(f is not None for f in frames):
            maps = self._pair_maps(pair)
            for k, image in enumerate(frames):
                if image is not None:
                    remapped = cv2.remap(image, maps[2 * k], maps[2 * k + 1], cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                    images[k] = np.clip(remapped, 0, 255).astype(np.uint8)
        blurry = any(bool(np.any(t.flags[t.frame == set_name] & int(FeatureFlags.BLURRY_FRAME)))
                     for t in (out.cameras[pair.i].features, out.cameras[pair.j].features))
        return RectifiedSet(pair, set_name, (images[0], images[1]), "; ".join(missing), epipolar, blurry)


def load_rig(folder: str | os.PathLike[str]) -> RigState:
    """Load a ``calibrate-rig`` output folder.

    Raises:
        RigOutputError: not a rig output, or a file in it unreadable (the message names it).
    """
    return RigState(read_rig_output(folder))
