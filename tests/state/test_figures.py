"""The frame poses' field of view: what a pose's frustum is drawn with, for any lens."""

from __future__ import annotations

import math

import pytest

from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.parametric import BrownConrady
from state.figures import FRUSTUM_FOV_MAX, vertical_fov


def test_a_pinhole_camera_has_its_pinhole_field() -> None:
    camera = BrownConrady(fx=420.0, fy=410.0, cx=319.5, cy=239.5, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0,
                          width=640, height=480)
    assert vertical_fov(camera) == pytest.approx(2.0 * math.atan2(240.0, 410.0), abs=1e-9)


@pytest.mark.parametrize(("fy", "expected"), [(360.0, 2.0), (240.0, FRUSTUM_FOV_MAX)])
def test_a_fisheye_has_its_angular_field_up_to_the_drawn_limit(fy: float, expected: float) -> None:
    """An ideal equidistant lens sees ``H / fy`` rad across its height (2.0 rad here; 3.0 rad is drawn
    at the limit), where the pinhole formula would say 1.57 and 1.95 rad."""
    camera = KannalaBrandtCamera.from_values(1280, 720, fx=fy, fy=fy, cx=639.5, cy=359.5,
                                             k1=0.0, k2=0.0, k3=0.0, k4=0.0)
    assert vertical_fov(camera) == pytest.approx(expected, abs=1e-6)
