"""A rig: several central cameras fixed to each other, and where each sits in the rig.

Camera ``c`` sees a rig-frame point ``X`` at ``X_c = R_c X + t_c``: its pose ``camera_tr_rig[c]``
(the reference tool's ``camera_tr_rig``, :mod:`blurcalib.geometry.pose`'s convention with the rig
in the target's place). A calibrated rig's frame is its first camera's (``camera_tr_rig[0]`` the
identity); an image set's target pose is ``rig_tr_global`` (target -> rig), so that camera ``c``
sees the target at ``camera_tr_rig[c] o rig_tr_global``.

Between two cameras ``i`` and ``j`` the pose ``camera j <- camera i`` is
``camera_tr_rig[j] o camera_tr_rig[i]^-1``: OpenCV's stereo ``R, T`` (``X_j = R X_i + T``) with
``i`` its first camera. A central camera's orientation is a gauge; :meth:`Rig.with_frames` turns
cameras' frames (the rays and the poses together) without changing what the rig sees.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from blurcalib.camera.fit import fit_rays
from blurcalib.camera.generic import CentralGeneric
from blurcalib.camera.lens import ParametricCamera
from blurcalib.geometry.pose import Pose

__all__ = ["Rig", "parametric_frames"]


@dataclass(frozen=True, eq=False)
class Rig:
    """Central generic cameras of one rig and their poses in it (module docstring).

    Attributes:
        cameras: ``(C,)`` the cameras, each in its own frame.
        camera_tr_rig: ``(C,)`` rig -> camera poses (m).
    """

    cameras: tuple[CentralGeneric, ...]
    camera_tr_rig: tuple[Pose, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "camera_tr_rig", tuple(self.camera_tr_rig))
        if not self.cameras or len(self.cameras) != len(self.camera_tr_rig):
            raise ValueError(f"a rig needs one pose per camera and at least one camera, got "
                             f"{len(self.cameras)} cameras and {len(self.camera_tr_rig)} poses")

    @property
    def size(self) -> int:
        """The number of cameras ``C``."""
        return len(self.cameras)

    def relative(self, i: int, j: int) -> Pose:
        """``camera j <- camera i`` (OpenCV's stereo ``R, T`` with ``i`` the first camera)."""
        return self.camera_tr_rig[j].compose(self.camera_tr_rig[i].inverse())

    def rebased(self, c: int = 0) -> tuple[Rig, Pose]:
        """The rig whose frame is camera ``c``'s, and ``new rig <- old rig`` (apply it to the
        image sets' ``rig_tr_global``: ``new = returned o old``)."""
        to_c = self.camera_tr_rig[c]
        inverse = to_c.inverse()
        poses = [Pose.identity() if k == c else p.compose(inverse) for k, p in enumerate(self.camera_tr_rig)]
        return Rig(self.cameras, tuple(poses)), to_c

    def with_frames(self, rotations: Sequence[ArrayLike]) -> Rig:
        """Camera ``k``'s frame turned by ``rotations[k] (3, 3)`` (new ``X = Q X_old``): its rays
        turn (:meth:`blurcalib.camera.generic.CentralGeneric.rotated`) and so does its pose in the
        rig; the rig's frame stays (:meth:`rebased` makes it a camera's again)."""
        if len(rotations) != self.size:
            raise ValueError(f"need {self.size} rotations, got {len(rotations)}")
        Qs = [np.asarray(Q, dtype=np.float64) for Q in rotations]
        turned = [Pose(Q, np.zeros(3)).compose(p) for Q, p in zip(Qs, self.camera_tr_rig, strict=True)]
        return Rig(tuple(cam.rotated(Q) for cam, Q in zip(self.cameras, Qs, strict=True)), tuple(turned))


def parametric_frames(rig: Rig, models: Sequence[type[ParametricCamera]], step_px: float = 8.0
                      ) -> tuple[Rig, list[ParametricCamera], Pose]:
    """Each camera in the frame of a parametric camera fitted to its rays, for OpenCV's tools.

    Camera ``k``'s generic rays on a lattice every ``step_px`` px over its calibrated area are fitted
    by ``models[k]`` with a free rotation (:func:`blurcalib.camera.fit.fit_rays`), and the camera's
    frame is turned by that rotation (:meth:`Rig.with_frames`): the generic camera, its pose and
    the parametric camera then share one frame, whose ``z`` axis is the parametric camera's
    optical axis, so that OpenCV's stereo rectification of the parametric cameras and the rig's
    ``R, T`` agree. The rig's frame becomes the first camera's new frame (:meth:`Rig.rebased`).

    Returns:
        The turned rig, the parametric cameras and ``new rig <- old rig`` (for ``rig_tr_global``).
    """
    if len(models) != rig.size:
        raise ValueError(f"need {rig.size} parametric models, got {len(models)}")
    rotations, cameras = [], []
    for camera, model in zip(rig.cameras, models, strict=True):
        x0, y0, x1, y1 = camera.area_opencv
        xx, yy = np.meshgrid(np.arange(x0 + 0.5, x1, step_px), np.arange(y0 + 0.5, y1, step_px))
        px = np.column_stack([xx.ravel(), yy.ravel()])
        fit = fit_rays(model, px, camera.pixel_to_ray(px), camera.width, camera.height)
        rotations.append(fit.rotation)
        cameras.append(fit.camera)
    turned, to_new = rig.with_frames(rotations).rebased(0)
    return turned, cameras, to_new
