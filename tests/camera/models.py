"""Cameras of the parametric family shared by the camera tests, and directions over a field."""

from __future__ import annotations

import numpy as np

from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.rational import RationalCamera
from blurcalib.camera.thin_prism import ThinPrismFisheyeCamera

BROWN_CONRADY = BrownConradyCamera.from_values(640, 480, fx=420.0, fy=421.5, cx=318.2, cy=242.7, k1=-0.28,
                                               k2=0.09, p1=0.0012, p2=-0.0008, k3=-0.012)
RATIONAL = RationalCamera.from_values(640, 480, fx=300.0, fy=300.6, cx=321.4, cy=238.9, k1=0.35, k2=0.04,
                                      p1=0.0009, p2=-0.0006, k3=0.001, k4=0.72, k5=0.11, k6=0.006)
KANNALA_BRANDT = KannalaBrandtCamera.from_values(1280, 720, fx=407.3, fy=407.4, cx=641.8, cy=357.9,
                                                 k1=-0.021, k2=0.0013, k3=-0.00021, k4=0.00001)
THIN_PRISM = ThinPrismFisheyeCamera.from_values(1280, 720, fx=407.3, fy=407.1, cx=641.8, cy=357.9, k1=-0.02,
                                                k2=0.0011, k3=-0.0002, k4=0.0, p1=0.0008, p2=-0.0005,
                                                sx1=0.0006, sy1=-0.0004)
MODELS: tuple[ParametricCamera, ...] = (BROWN_CONRADY, RATIONAL, KANNALA_BRANDT, THIN_PRISM)


def directions(max_deg: float, n: int, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` unit directions spread over the cap up to ``max_deg`` off the optical axis
    (uniform in angle and azimuth, the axis itself included)."""
    rng = np.random.default_rng(seed)
    theta = np.radians(rng.uniform(0.0, max_deg, n))
    theta[:3] = (0.0, 1e-9, np.radians(max_deg))
    phi = rng.uniform(0.0, 2 * np.pi, n)
    return np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


def field_deg(camera: ParametricCamera) -> float:
    """The half angle (deg) the tests exercise: 100 degrees for an equidistant model, else the
    model's valid field less a margin."""
    return 100.0 if camera.angular else min(75.0, np.degrees(camera.max_angle) - 2.0)
