"""Derived figures the views draw: error fields of frames and the poses of the frames.

Pure functions of results (no viser, no drawing), so they are tested on their own. Pixels follow
OpenCV's convention: the top-left pixel's centre is ``(0, 0)``, x right, y down.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from blurcalib.calib.joint import GenericCalibration
from blurcalib.calib.sharp import CalibrationError, calibrate_pinhole
from blurcalib.camera.generic import CentralGeneric
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.extract.frame import FrameResult
from blurcalib.geometry.pose import Pose
from blurcalib.growth.quality import FrameFilter
from blurcalib.io.record import FrameStatus
from blurcalib.sim.truth import DatasetTruth, FrameTruth
from blurcalib.target.pattern import StarPattern
from state.alignment import AlignmentCache, FrameAlignment
from state.app_state import AppState
from state.blocks import block_quads

ERROR_SOURCES = ("global alignment", "ground truth", "local alignment")
"""Where an error field comes from, in the order ``auto`` tries them."""

@dataclass(frozen=True)
class ErrorField:
    """One 2D error vector per block of a frame.

    Attributes:
        index: ``(N,)`` indices of the blocks into ``result.blocks``.
        centre: ``(N, 2)`` px, the blocks' star centres.
        quad: ``(N, 4, 2)`` px, the blocks' squares ``H([-1, 1]^2)``.
        error: ``(N, 2)`` px.
        source: one of :data:`ERROR_SOURCES`: ``"global alignment"`` (the residual after the
            frame's pose and translation ``x_G`` are fitted to the reference camera,
            ``p - x_G - pi_d(M, P)``), ``"ground truth"`` (estimate minus the true
            time-averaged position) or ``"local alignment"`` (the block's disagreement with its
            neighbours' shared corners: minus its local-alignment translation).
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
    return np.flatnonzero(result.blocks.accepted)


def error_field(result: FrameResult, flt: FrameFilter | None, truth: FrameTruth | None,
                alignment: FrameAlignment | None = None, source: str | None = None) -> ErrorField | None:
    """The error of each used block of a frame.

    Args:
        result, flt: the frame's result and quality filter.
        truth: its ground truth (None for real data).
        alignment: its global alignment (:func:`state.alignment.align_frame` of the same result
            and filter), or None.
        source: one of :data:`ERROR_SOURCES`; None takes the first available in that order.

    Returns:
        The field, or None when the source (any source, for None) is not available.
    """
    if source is not None and source not in ERROR_SOURCES:
        raise ValueError(f"source must be one of {ERROR_SOURCES} or None, got {source!r}")
    for candidate in ERROR_SOURCES if source is None else (source,):
        field = _field(candidate, result, flt, truth, alignment)
        if field is not None:
            return field
    return None


def _field(source: str, result: FrameResult, flt: FrameFilter | None, truth: FrameTruth | None,
           alignment: FrameAlignment | None) -> ErrorField | None:
    if source == "global alignment":
        if alignment is None or alignment.num_blocks == 0:
            return None
        idx, error = alignment.index, alignment.residuals
    else:
        idx = used_blocks(result, flt)
        if source == "ground truth":
            if truth is None:
                return None
            position = {int(fid): truth.mean[k] for k, fid in enumerate(truth.feature_ids)}
            idx = idx[np.isin(result.blocks.feature_id[idx], truth.feature_ids)]
            if len(idx) == 0:
                return None
            truth_xy = [position[int(f)] for f in result.blocks.feature_id[idx]]
            error = result.blocks.centre[idx] - np.stack(truth_xy)
        else:
            if result.local is None:
                return None
            accepted = np.flatnonzero(result.blocks.accepted)
            row = {int(b): r for r, b in enumerate(accepted)}
            idx = np.array([i for i in idx if int(i) in row], dtype=np.int64)
            if len(idx) == 0:
                return None
            error = -result.local.translation[[row[int(i)] for i in idx]]
    return ErrorField(idx, result.blocks.centre[idx], block_quads(result.blocks.H[idx]), error, source)


@dataclass(frozen=True)
class ErrorFields:
    """The error fields of several frames, from one source.

    Attributes:
        fields: frame name -> its field.
        source: one of :data:`ERROR_SOURCES`.
        image_size: the frames' ``(width, height)`` px (frames of other sizes are left out).
        note: which frames were left out and why.
    """

    fields: dict[str, ErrorField]
    source: str
    image_size: tuple[int, int]
    note: str = ""

    def stacked(self) -> tuple[np.ndarray, np.ndarray]:
        """``(N, 2)`` px star centres and ``(N, 2)`` px errors of every frame's blocks."""
        if not self.fields:
            return np.zeros((0, 2)), np.zeros((0, 2))
        return (np.concatenate([f.centre for f in self.fields.values()]),
                np.concatenate([f.error for f in self.fields.values()]))


def used_frame_fields(state: AppState, alignments: AlignmentCache, source: str | None = None
                      ) -> ErrorFields | None:
    """The error fields of every used frame: finished, and passing the blur pre-filter.

    ``source`` None takes the first *available* source of :data:`ERROR_SOURCES` (global
    alignment when there is a reference camera, ground truth on simulated data, else local
    alignment), so all frames share one. For global alignment, frames failing the orientation
    filter are left out, as in the pipeline. Returns None when the source is not available.
    """
    dataset = state.dataset
    if dataset is None:
        return None
    if source is not None and source not in ERROR_SOURCES:
        raise ValueError(f"source must be one of {ERROR_SOURCES} or None, got {source!r}")
    overview = alignments.overview()
    available = [s for s in ERROR_SOURCES if s != "global alignment" or overview is not None]
    available = [s for s in available if s != "ground truth" or dataset.truth is not None]
    chosen = available[0] if source is None else source
    if chosen not in available:
        return None
    results = state.results()
    ok = {e.name for e in state.entries() if e.record.status is FrameStatus.OK}
    used = {name: r for name, r in results.items() if name in ok and r[1] is not None and r[1].frame_ok}
    sizes = Counter(size for _, _, size in used.values())
    size = sizes.most_common(1)[0][0] if sizes else (0, 0)
    fields: dict[str, ErrorField] = {}
    notes = []
    if chosen == "global alignment":
        for name, alignment in overview.aligned.items():
            if name in used and used[name][2] == size:
                fields[name] = _field(chosen, used[name][0], used[name][1], None, alignment)
        if overview.ill_conditioned:
            notes.append(f"{len(overview.ill_conditioned)} ill-conditioned (orientation filter)")
        if overview.failed:
            notes.append(f"{len(overview.failed)} not aligned")
    else:
        for name, (result, flt, frame_size) in sorted(used.items()):
            truth = None
            if chosen == "ground truth":
                truth = next((f for f in dataset.truth.frames if f.name == name), None)
            field = _field(chosen, result, flt, truth, None) if frame_size == size else None
            if field is not None:
                fields[name] = field
    dropped = sum(1 for name in ok if name in results and name not in used)
    if dropped:
        notes.append(f"{dropped} dropped by the blur pre-filter")
    other = sum(1 for _, _, s in used.values() if s != size)
    if other:
        notes.append(f"{other} of another image size")
    return ErrorFields(dict(sorted(fields.items())), chosen, size, "; ".join(notes))


def cell_means(xy: np.ndarray, error: np.ndarray, image_size: tuple[int, int], cell_px: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Errors averaged over square image cells (as the reference tool draws its error field).

    Args:
        xy: ``(N, 2)`` px positions.
        error: ``(N, 2)`` px error vectors.
        image_size: ``(width, height)`` px.
        cell_px: cell side (px); cell ``(i, j)`` covers x in ``[j c - 0.5, (j + 1) c - 0.5)``.

    Returns:
        The occupied cells' first (top-left) pixel centres ``(K, 2)`` px, ``(j c, i c)``, their
        mean errors ``(K, 2)`` px and their block counts ``(K,)``.
    """
    w, h = image_size
    gw, gh = -(-w // cell_px), -(-h // cell_px)
    ok = np.all(np.isfinite(xy), axis=1) & np.all(np.isfinite(error), axis=1)
    cx = np.clip((xy[ok, 0] + 0.5) // cell_px, 0, gw - 1).astype(np.int64)
    cy = np.clip((xy[ok, 1] + 0.5) // cell_px, 0, gh - 1).astype(np.int64)
    cell = cy * gw + cx
    count = np.bincount(cell, minlength=gw * gh).astype(np.float64)
    sums = np.stack([np.bincount(cell, error[ok, k], minlength=gw * gh) for k in range(2)], axis=1)
    occupied = np.flatnonzero(count)
    corner = np.stack([occupied % gw, occupied // gw], axis=1) * float(cell_px)
    return corner, sums[occupied] / count[occupied, None], count[occupied].astype(np.int64)


FRUSTUM_FOV_MAX = math.radians(150.0)
"""Widest vertical field (rad) a pose's frustum is drawn with: a pinhole frustum of a field near
180 degrees is infinitely wide, so a fisheye's is drawn at this angle."""


def vertical_fov(camera: BrownConrady | ParametricCamera | CentralGeneric) -> float:
    """The camera's vertical field (rad): the angles off the optical axis (the ray of the image
    centre) of the rays through the centres of the first and last rows' middle pixels (of a
    generic camera's calibrated area), added; the pinhole ``2 atan((H - 1) / 2 fy)`` where a
    parametric camera's edge has no ray, 1 rad where a generic one's has none. At most
    :data:`FRUSTUM_FOV_MAX`."""
    x0, y0, x1, y1 = (camera.area_opencv if isinstance(camera, CentralGeneric)
                      else (-0.5, -0.5, camera.width - 0.5, camera.height - 0.5))
    middle, top, bottom = (x0 + x1) / 2, y0 + 0.5, y1 - 0.5
    rays = camera.pixel_to_ray(np.array([[middle, top], [middle, (top + bottom) / 2], [middle, bottom]]))
    if np.all(np.isfinite(rays)):
        fov = float(sum(np.arccos(np.clip(rays[k] @ rays[1], -1.0, 1.0)) for k in (0, 2)))
    elif isinstance(camera, CentralGeneric):
        fov = 1.0
    else:
        fov = 2.0 * math.atan2((camera.height - 1) / 2.0, float(camera.fy))
    return min(fov, FRUSTUM_FOV_MAX)


@dataclass(frozen=True)
class FramePoses:
    """Poses of frames around the target.

    Attributes:
        poses: frame name -> pose (target -> camera).
        fov: vertical field of view (rad, :func:`vertical_fov`).
        aspect: width / height.
        source: ``"ground truth"``, ``"generic bundle adjustment"`` (the poses of the app's
            generic calibration), ``"global alignment"`` (the poses fitted with the reference
            camera) or ``"approximate camera"`` (poses from the frames' features with a camera of
            unknown distortion fitted to them).
    """

    poses: dict[str, Pose]
    fov: float
    aspect: float
    source: str


def truth_poses(truth: DatasetTruth) -> FramePoses:
    """The ground-truth mid-exposure poses of a simulated dataset."""
    model = truth.camera.model
    return FramePoses({f.name: f.pose for f in truth.frames}, vertical_fov(model), model.width / model.height,
                      "ground truth")


def generic_poses(generic: GenericCalibration) -> FramePoses:
    """The poses of a generic calibration's bundle adjustment (field of view and aspect of its
    parametric camera)."""
    camera = generic.parametric
    return FramePoses(dict(generic.poses), vertical_fov(camera), camera.width / camera.height,
                      "generic bundle adjustment")


def alignment_poses(alignments: Mapping[str, FrameAlignment], camera: BrownConrady) -> FramePoses | None:
    """The poses that global alignment fitted to frames, with the reference ``camera`` (None
    when there are none)."""
    if not alignments:
        return None
    return FramePoses({name: a.pose for name, a in alignments.items()}, vertical_fov(camera),
                      camera.width / camera.height,
                      "global alignment")


def feature_poses(pattern: StarPattern,
                  results: dict[str, tuple[FrameResult, FrameFilter | None, tuple[int, int]]],
                  min_features: int = 12) -> FramePoses | None:
    """Poses from each finished frame's used star centres, with an approximate camera.

    The camera is :func:`blurcalib.calib.sharp.calibrate_pinhole` (one focal length, the principal
    point at the image centre, no distortion), fitted to the frames of the most common image size.
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
        obj.append(pattern.points_3d(result.blocks.feature_id[idx]).astype(np.float32))
        img.append(result.blocks.centre[idx].astype(np.float32))
        names.append(name)
    if not names:
        return None
    try:
        camera, poses = calibrate_pinhole(obj, img, size)
    except CalibrationError:
        return None
    w, h = size
    return FramePoses(dict(zip(names, poses, strict=True)), vertical_fov(camera), w / h, "approximate camera")
