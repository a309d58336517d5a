"""Derived figures the views draw: the error field of a frame and the poses of the frames.

Pure functions of results (no viser, no drawing), so they are tested on their own.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import cv2
import numpy as np

from blurcalib.camera import Pose, apply_homography
from blurcalib.extract import FrameResult
from blurcalib.pattern import StarPattern
from blurcalib.quality import FrameFilter
from blurcalib.results import BlockStatus
from blurcalib.synth import DatasetTruth, FrameTruth
from state.app_state import block_centres

SQUARE_CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
"""A block's square corners in block coordinates, in drawing order."""


def block_quads(H: np.ndarray) -> np.ndarray:
    """``(B, 4, 2)`` px: the squares ``H([-1, 1]^2)`` of block homographies ``(B, 3, 3)``."""
    return apply_homography(H, np.broadcast_to(SQUARE_CORNERS, (len(H), 4, 2)))


@dataclass(frozen=True)
class ErrorField:
    """One 2D error vector per block of a frame.

    Attributes:
        index: ``(N,)`` indices of the blocks into ``result.blocks``.
        centre: ``(N, 2)`` px, the blocks' star centres.
        quad: ``(N, 4, 2)`` px, the blocks' squares ``H([-1, 1]^2)``.
        error: ``(N, 2)`` px.
        source: ``"ground truth"`` (estimate minus the true time-averaged position) or
            ``"local alignment"`` (the block's disagreement with its neighbours' shared corners:
            minus its local-alignment translation).
    """

    index: np.ndarray
    centre: np.ndarray
    quad: np.ndarray
    error: np.ndarray
    source: str

    @property
    def rms(self) -> float:
        """RMS length of the errors (px)."""
        return float(np.sqrt(np.mean(np.sum(self.error**2, axis=1)))) if len(self.error) else 0.0


def used_blocks(result: FrameResult, flt: FrameFilter | None) -> np.ndarray:
    """Indices of the blocks that count: kept by the filter, else accepted by the growth."""
    if flt is not None:
        return np.flatnonzero(flt.kept)
    return np.array([i for i, b in enumerate(result.blocks) if b.status is BlockStatus.ACCEPTED],
                    dtype=np.int64)


def error_field(result: FrameResult, flt: FrameFilter | None, truth: FrameTruth | None
                ) -> ErrorField | None:
    """The error of each used block: against the ground truth when there is one, else the
    local-alignment disagreement (None when neither is available)."""
    idx = used_blocks(result, flt)
    if len(idx) == 0:
        return None
    centres = block_centres(result)
    if truth is not None:
        position = {int(fid): truth.mean[k] for k, fid in enumerate(truth.feature_ids)}
        idx = np.array([i for i in idx if result.blocks[i].feature_id in position], dtype=np.int64)
        if len(idx) == 0:
            return None
        error = centres[idx] - np.stack([position[result.blocks[i].feature_id] for i in idx])
        source = "ground truth"
    elif result.local is not None and result.growth is not None:
        accepted = np.flatnonzero(result.growth.accepted)
        row = {int(b): r for r, b in enumerate(accepted)}
        idx = np.array([i for i in idx if int(i) in row], dtype=np.int64)
        if len(idx) == 0:
            return None
        error = -result.local.translation[[row[int(i)] for i in idx]]
        source = "local alignment"
    else:
        return None
    H = np.stack([result.blocks[i].H for i in idx])
    return ErrorField(idx, centres[idx], block_quads(H), error, source)


@dataclass(frozen=True)
class FramePoses:
    """Poses of frames around the target.

    Attributes:
        poses: frame name -> pose (target -> camera).
        fov: vertical field of view (rad).
        aspect: width / height.
        source: ``"ground truth"`` or ``"approximate camera"`` (poses from the frames' features
            with a camera of unknown distortion fitted to them).
    """

    poses: dict[str, Pose]
    fov: float
    aspect: float
    source: str


def truth_poses(truth: DatasetTruth) -> FramePoses:
    """The ground-truth mid-exposure poses of a simulated dataset."""
    model = truth.camera.model
    fov = 2.0 * float(np.arctan2(model.height / 2.0, model.fy))
    return FramePoses({f.name: f.pose for f in truth.frames}, fov, model.width / model.height,
                      "ground truth")


def feature_poses(pattern: StarPattern,
                  results: dict[str, tuple[FrameResult, FrameFilter | None, tuple[int, int]]],
                  min_features: int = 12) -> FramePoses | None:
    """Poses from each finished frame's used star centres, with an approximate camera.

    The camera is ``cv2.calibrateCamera`` with one focal length, the principal point at the
    image centre and no distortion, fitted to the frames of the most common image size.
    Returns None when no frame has ``min_features`` used blocks or the fit fails.
    """
    obj, img, names = [], [], []
    sizes = Counter(size for _, _, size in results.values())
    if not sizes:
        return None
    size = sizes.most_common(1)[0][0]
    for name, (result, flt, frame_size) in sorted(results.items()):
        idx = used_blocks(result, flt)
        if frame_size != size or len(idx) < min_features:
            continue
        ids = np.array([result.blocks[i].feature_id for i in idx])
        obj.append(pattern.points_3d(ids).astype(np.float32))
        img.append(block_centres(result)[idx].astype(np.float32))
        names.append(name)
    if not names:
        return None
    w, h = size
    K = np.array([[float(max(w, h)), 0.0, (w - 1) / 2.0], [0.0, float(max(w, h)), (h - 1) / 2.0],
                  [0.0, 0.0, 1.0]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    try:
        _, K, _, rvecs, tvecs = cv2.calibrateCamera(obj, img, (w, h), K, np.zeros(5), flags=flags)
    except cv2.error:
        return None
    poses = {n: Pose.from_rvec_tvec(r.ravel(), t.ravel())
             for n, r, t in zip(names, rvecs, tvecs, strict=True)}
    fov = 2.0 * float(np.arctan2(h / 2.0, K[1, 1]))
    return FramePoses(poses, fov, w / h, "approximate camera")
