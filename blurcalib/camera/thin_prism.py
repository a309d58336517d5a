"""The reference tool's thin-prism fisheye (``CentralThinPrismFisheyeModel``, the ETH3D benchmark's
model) in the parametric family.

With the equidistant base point ``m = theta (X, Y) / rho`` (or, without the equidistant
projection, the perspective ``(X/Z, Y/Z)``) and ``r^2 = |m|^2``::

    d = m (1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8) + tangential(p1, p2) + (sx1 r^2, sy1 r^2)
    u = (fx d_x + cx, fy d_y + cy)

with OpenCV's tangential terms. Without ``p1, p2, sx1, sy1`` it is Kannala-Brandt. Parameters
``fx, fy, cx, cy, k1, k2, k3, k4, p1, p2, sx1, sy1``, the reference tool's order. The reference
tool projects only ``Z > 0``; here, as for Kannala-Brandt, ``theta = atan2(rho, Z)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from blurcalib.camera.lens import ParametricCamera

__all__ = ["ThinPrismFisheyeCamera"]


@dataclass(frozen=True, eq=False)
class ThinPrismFisheyeCamera(ParametricCamera):
    """The thin-prism fisheye; ``equidistant`` False gives its perspective variant.

    Attributes:
        equidistant: the reference tool's ``use_equidistant_projection``.
    """

    equidistant: bool = True

    MODEL: ClassVar[str] = "thin_prism_fisheye"
    PARAM_NAMES: ClassVar[tuple[str, ...]] = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "p1", "p2",
                                              "sx1", "sy1")
    KERNEL_INDEX: ClassVar[tuple[int, ...]] = (0, 1, 2, 3, 7, 8, 9, 10)

    def __post_init__(self) -> None:
        super().__post_init__()
        if not isinstance(self.equidistant, bool | np.bool_):
            raise ValueError(f"equidistant must be true or false, got {self.equidistant!r}")
        object.__setattr__(self, "equidistant", bool(self.equidistant))

    @property
    def angular(self) -> bool:
        return self.equidistant

    def _extra(self) -> dict[str, Any]:
        return {"equidistant": self.equidistant}

    @classmethod
    def _build(cls, params: np.ndarray, width: int, height: int, extra: Mapping[str, Any]
               ) -> ThinPrismFisheyeCamera:
        unknown = sorted(set(extra) - {"equidistant"})
        if unknown:
            raise ValueError(f"camera description has unknown keys {unknown}")
        return cls(params, width, height, equidistant=extra.get("equidistant", True))
