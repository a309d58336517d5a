"""Brown-Conrady in the parametric family: OpenCV's five-coefficient model ``(k1, k2, p1, p2, k3)``.

``u = K (d(X/Z, Y/Z), 1)`` with ``d`` the radial ``1 + k1 r^2 + k2 r^4 + k3 r^6`` and OpenCV's
tangential terms (:mod:`blurcalib.camera.distortion`); parameters ``fx, fy, cx, cy, k1, k2, p1,
p2, k3``, the order of :func:`blurcalib.camera.parametric.project_poses`. It is
:class:`blurcalib.camera.parametric.BrownConrady` behind the family's interface (directions,
not normalised coordinates).
"""

from __future__ import annotations

from typing import ClassVar

from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady

__all__ = ["BrownConradyCamera"]


class BrownConradyCamera(ParametricCamera):
    """OpenCV's default camera model (``cv2.calibrateCamera`` without flags)."""

    MODEL: ClassVar[str] = "Brown_Conrady"
    PARAM_NAMES: ClassVar[tuple[str, ...]] = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    KERNEL_INDEX: ClassVar[tuple[int, ...]] = (0, 1, 7, 8, 2)
    ANGULAR: ClassVar[bool] = False
    OPENCV_DISTORTION: ClassVar[tuple[str, ...] | None] = ("k1", "k2", "p1", "p2", "k3")

    @classmethod
    def from_brown_conrady(cls, camera: BrownConrady) -> BrownConradyCamera:
        """The same camera as a :class:`BrownConrady` (identical parameters)."""
        return cls(camera.params, camera.width, camera.height)

    def to_brown_conrady(self) -> BrownConrady:
        """The same camera as the calibration's :class:`BrownConrady`."""
        return BrownConrady(**self.named(), width=self.width, height=self.height)
