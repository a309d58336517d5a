"""The Kannala-Brandt fisheye model as OpenCV's ``cv::fisheye`` has it, in the parametric family.

With ``theta`` the angle of the ray off the optical axis::

    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    u = (fx theta_d X / rho + cx, fy theta_d Y / rho + cy)

(``rho = sqrt(X^2 + Y^2)``; OpenCV's skew ``alpha`` is 0). OpenCV computes
``theta = atan(rho / Z)``, which holds for ``Z > 0``; here ``theta = atan2(rho, Z)``, so rays up to
:attr:`~blurcalib.camera.lens.ParametricCamera.max_angle` (where ``theta_d`` stops increasing,
at most 180 degrees) project, beyond 90 degrees too. Parameters ``fx, fy, cx, cy, k1, k2, k3, k4``.
"""

from __future__ import annotations

from typing import ClassVar

from blurcalib.camera.lens import ParametricCamera

__all__ = ["KannalaBrandtCamera"]


class KannalaBrandtCamera(ParametricCamera):
    """The equidistant fisheye with a ``theta`` polynomial (``cv2.fisheye``)."""

    MODEL: ClassVar[str] = "Kannala_Brandt"
    PARAM_NAMES: ClassVar[tuple[str, ...]] = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    KERNEL_INDEX: ClassVar[tuple[int, ...]] = (0, 1, 2, 3)
    ANGULAR: ClassVar[bool] = True
    OPENCV_DISTORTION: ClassVar[tuple[str, ...] | None] = ("k1", "k2", "k3", "k4")
