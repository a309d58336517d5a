"""Rigid poses: the transform from target (world) to camera coordinates, ``X_cam = R X_world + t``.

The calibration target is the plane ``Z_world = 0`` (metres); rotations are stored as matrices
and exchanged with OpenCV as Rodrigues vectors (rad).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
import numpy.typing as npt
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

_ROTATION_TOL = 1e-6


def as_points(values: ArrayLike, dim: int, name: str) -> npt.NDArray[np.float64]:
    """Convert to a float64 array of shape ``(..., dim)`` or raise ValueError."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != dim:
        raise ValueError(f"{name} must have shape (..., {dim}), got {arr.shape}")
    return arr


@dataclass(frozen=True, eq=False)
class Pose:
    """Rigid transform from target (world) to camera coordinates: ``X_cam = R X_world + t``.

    Attributes:
        R: rotation matrix, shape (3, 3) (validated orthonormal with det +1).
        t: translation, shape (3,), metres.

    Arrays are stored as read-only float64 copies.
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        R = np.array(self.R, dtype=np.float64)
        t = np.array(self.t, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3):
            raise ValueError(f"R must have shape (3, 3), got {R.shape}")
        if t.shape != (3,):
            raise ValueError(f"t must have 3 elements, got shape {np.shape(self.t)}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise ValueError("pose contains non-finite values")
        if np.max(np.abs(R.T @ R - np.eye(3))) > _ROTATION_TOL or np.linalg.det(R) <= 0.0:
            raise ValueError(f"R is not a rotation matrix: {R.tolist()}")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @classmethod
    def identity(cls) -> Pose:
        """Pose with ``R = I`` and ``t = 0``."""
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_rvec_tvec(cls, rvec: ArrayLike, tvec: ArrayLike) -> Pose:
        """From an OpenCV Rodrigues vector ``rvec (3,)`` rad and ``tvec (3,)`` m."""
        rvec = np.asarray(rvec, dtype=np.float64).reshape(-1)
        if rvec.shape != (3,):
            raise ValueError(f"rvec must have 3 elements, got shape {rvec.shape}")
        R, _ = cv2.Rodrigues(rvec)
        return cls(R, np.asarray(tvec))

    @property
    def rvec(self) -> np.ndarray:
        """Rodrigues rotation vector, shape (3,), rad (axis times angle)."""
        rvec, _ = cv2.Rodrigues(np.ascontiguousarray(self.R))
        return rvec.reshape(3)

    @property
    def camera_center(self) -> np.ndarray:
        """Camera centre in world coordinates ``-R^T t``, shape (3,), m."""
        return cast(np.ndarray, -self.R.T @ self.t)

    def transform(self, points: ArrayLike) -> np.ndarray:
        """Map world points ``(N, 3)`` m to camera coordinates ``R X + t`` ``(N, 3)`` m."""
        pts = as_points(points, 3, "points")
        return cast(np.ndarray, pts @ self.R.T + self.t)

    def inverse(self) -> Pose:
        """Inverse transform (camera -> world): ``R' = R^T``, ``t' = -R^T t``."""
        return Pose(self.R.T, -self.R.T @ self.t)

    def compose(self, other: Pose) -> Pose:
        """``self ∘ other``: apply ``other`` first, then ``self``.

        ``X -> R_s (R_o X + t_o) + t_s``, i.e. ``R = R_s R_o`` and ``t = R_s t_o + t_s``.
        """
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def optical_axis_angle_to_target_normal(self) -> float:
        """Angle (rad, in ``[0, pi/2]``) between the optical axis and the target normal.

        The optical axis in world coordinates is ``R^T (0, 0, 1)``, the target normal is
        ``(0, 0, ±1)``; 0 means the camera looks straight at the target (fronto-parallel).
        """
        axis = self.R[2]
        return float(np.arctan2(np.hypot(axis[0], axis[1]), abs(axis[2])))

    @classmethod
    def from_quaternion(cls, q: ArrayLike, t: ArrayLike) -> Pose:
        """From a quaternion ``q = (qx, qy, qz, qw)`` (Eigen's component names; normalised here)
        and ``t (3,)`` m.

        Raises:
            ValueError: ``q`` not 4 finite numbers of non-zero norm.
        """
        q = np.asarray(q, dtype=np.float64).reshape(-1)
        norm = float(np.linalg.norm(q)) if q.shape == (4,) else 0.0
        if not (np.isfinite(norm) and norm > 0):
            raise ValueError(f"quaternion must be 4 finite numbers of non-zero norm, got {q.tolist()}")
        return cls(Rotation.from_quat(q / norm).as_matrix(), np.asarray(t))

    @property
    def quaternion(self) -> np.ndarray:
        """``(4,)`` unit quaternion ``(qx, qy, qz, qw)`` of ``R``, ``qw >= 0``."""
        q: npt.NDArray[np.float64] = Rotation.from_matrix(self.R).as_quat()
        return -q if q[3] < 0 else q

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable dict ``{"R": 3x3 nested list, "t": [tx, ty, tz]}`` (exact)."""
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Pose:
        """Inverse of :meth:`to_dict`; a missing key raises ValueError naming it."""
        if not isinstance(data, Mapping):
            raise ValueError(f"pose description must be a mapping, got {type(data).__name__}")
        for name in ("R", "t"):
            if name not in data:
                raise ValueError(f"pose description is missing key {name!r}")
        return cls(np.asarray(data["R"], dtype=np.float64), np.asarray(data["t"], np.float64))


