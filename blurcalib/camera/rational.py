"""OpenCV's rational model (``cv2.CALIB_RATIONAL_MODEL``) in the parametric family.

``u = K (d(X/Z, Y/Z), 1)`` with the radial factor
``(1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)`` and OpenCV's tangential
terms ``p1, p2`` (:mod:`blurcalib.camera.distortion`); parameters ``fx, fy, cx, cy, k1, k2, p1,
p2, k3, k4, k5, k6``, OpenCV's order. The reference tool's ``CentralOpenCVModel`` is this model.
"""

from __future__ import annotations

from typing import ClassVar

from blurcalib.camera.lens import ParametricCamera

__all__ = ["RationalCamera"]


class RationalCamera(ParametricCamera):
    """OpenCV's eight-coefficient rational camera model."""

    MODEL: ClassVar[str] = "rational"
    PARAM_NAMES: ClassVar[tuple[str, ...]] = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3",
                                              "k4", "k5", "k6")
    KERNEL_INDEX: ClassVar[tuple[int, ...]] = (0, 1, 7, 8, 2, 4, 5, 6)
    ANGULAR: ClassVar[bool] = False
    OPENCV_DISTORTION: ClassVar[tuple[str, ...] | None] = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
