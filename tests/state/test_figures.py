"""The frame poses' field of view: what a pose's frustum is drawn with, for any lens."""

from __future__ import annotations

import math

import pytest

from blurcalib.camera.generic import fit_to_rays
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.parametric import BrownConrady
from state.figures import FRUSTUM_FOV_MAX, vertical_fov


def test_a_pinhole_camera_has_its_pinhole_field() -> None:
    camera = BrownConrady(fx=420.0, fy=410.0, cx=319.5, cy=239.5, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0,
                          width=640, height=480)
    assert vertical_fov(camera) == pytest.approx(2.0 * math.atan2(239.5, 410.0), abs=1e-9)


@pytest.mark.parametrize(("fy", "expected"), [(360.0, 719.0 / 360.0), (240.0, FRUSTUM_FOV_MAX)])
def test_a_fisheye_has_its_angular_field_up_to_the_drawn_limit(fy: float, expected: float) -> None:
    """An ideal equidistant lens sees ``(H - 1) / fy`` rad between its first and last rows (2.0 rad
    here; 3.0 rad is drawn at the limit), where the pinhole formula would say 1.57 and 1.95 rad."""
    camera = KannalaBrandtCamera.from_values(1280, 720, fx=fy, fy=fy, cx=639.5, cy=359.5,
                                             k1=0.0, k2=0.0, k3=0.0, k4=0.0)
    assert vertical_fov(camera) == pytest.approx(expected, abs=1e-6)


def test_a_generic_camera_has_the_field_of_its_calibrated_area() -> None:
    """A generic camera fitted to a pinhole's rays over rows 40 to 439: the field between the rays of
    its calibrated area's first and last rows (measured from the centre ray, so ~0.927 rad)."""
    pinhole = BrownConrady(fx=400.0, fy=400.0, cx=319.5, cy=239.5, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0,
                           width=640, height=480)
    generic = fit_to_rays(pinhole.pixel_to_ray, 640, 480, area=(0, 40, 639, 439), cell_px=40.0)
    _, y0, _, y1 = generic.area_opencv
    expected = math.atan2(239.5 - (y0 + 0.5), 400.0) + math.atan2(y1 - 0.5 - 239.5, 400.0)
    assert vertical_fov(generic) == pytest.approx(expected, abs=1e-4)
