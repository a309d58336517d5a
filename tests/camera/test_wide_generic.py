"""The generic model and the output images at any field of view; parametric models fitted to rays."""

from __future__ import annotations

import numpy as np
import pytest

from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.fit import fit_rays
from blurcalib.camera.generic import CentralGeneric, fit_to_rays, undistortion_map
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.remap import OutputProjection, output_for, output_maps
from tests.camera.models import BROWN_CONRADY, KANNALA_BRANDT, directions

SMALL_FISHEYE = KANNALA_BRANDT.scaled(0.25)
"""A 190 degree (horizontal) fisheye of 320 x 180 px: its corners are 111 degrees off the axis."""


def _pixels(camera: KannalaBrandtCamera, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.45, -0.45], [camera.width - 0.55, camera.height - 0.55], (n, 2))


@pytest.fixture(scope="module")
def generic_fisheye() -> CentralGeneric:
    return fit_to_rays(SMALL_FISHEYE.unproject, SMALL_FISHEYE.width, SMALL_FISHEYE.height, cell_px=10.0)


@pytest.mark.slow
def test_generic_fit_reproduces_a_190_degree_fisheye(generic_fisheye: CentralGeneric) -> None:
    px = _pixels(SMALL_FISHEYE, 3000)
    truth = SMALL_FISHEYE.unproject(px)
    assert np.degrees(np.arccos(truth[:, 2].min())) > 105  # beyond the front half-space
    angle = np.arccos(np.clip((generic_fisheye.pixel_to_ray(px) * truth).sum(axis=1), -1, 1))
    assert np.median(angle) * SMALL_FISHEYE.fx < 2e-4 and angle.max() * SMALL_FISHEYE.fx < 2e-3  # px
    u, inside = generic_fisheye.project(truth)
    assert inside.all() and np.abs(u - px).max() < 2e-3


@pytest.mark.slow
def test_output_maps_of_a_fisheye_agree_for_both_models(generic_fisheye: CentralGeneric) -> None:
    output = output_for(SMALL_FISHEYE)
    assert output.kind == "latlong"
    a = output_maps(SMALL_FISHEYE, output)
    b = output_maps(generic_fisheye, output)
    ok = (a[0] >= 0) & (b[0] >= 0)
    assert ok.mean() > 0.8 and np.array_equal(a[0] >= 0, b[0] >= 0)
    assert max(np.abs(a[0] - b[0])[ok].max(), np.abs(a[1] - b[1])[ok].max()) < 5e-3
    # Each output pixel's camera pixel sees the output pixel's ray.
    ys, xs = np.nonzero(ok)
    rays = output.rays(xs, ys)
    assert np.abs(SMALL_FISHEYE.project(rays) - np.column_stack([a[0][ok], a[1][ok]])).max() < 1e-3


def test_output_projections_look_along_their_rays() -> None:
    for kind in ("pinhole", "latlong", "stereographic"):
        out = OutputProjection(kind, 100.0, 100.0, 50.0, 40.0, 101, 81)
        centre = out.rays(np.array([50.0]), np.array([40.0]))[0]
        assert np.allclose(centre, [0, 0, 1])
        near = out.rays(np.array([51.0]), np.array([40.0]))[0]
        assert np.arccos(near[2]) == pytest.approx(0.01, rel=1e-4)  # 100 px per radian at the centre
    latlong = OutputProjection("latlong", 100.0, 100.0, 0.0, 0.0, 10, 10)
    assert np.allclose(latlong.rays(np.array([100 * np.pi / 2]), np.array([0.0]))[0], [1, 0, 0])
    assert np.isnan(latlong.rays(np.array([0.0]), np.array([200.0]))).all()
    stereo = OutputProjection("stereographic", 1.0, 1.0, 0.0, 0.0, 10, 10)
    assert np.allclose(stereo.rays(np.array([2.0]), np.array([0.0]))[0], [1, 0, 0])  # r = 2 tan(45 deg)
    assert output_for(BROWN_CONRADY).kind == "pinhole"


def test_undistortion_map_is_the_pinhole_output() -> None:
    small = BROWN_CONRADY.scaled(0.25)
    model = fit_to_rays(small.unproject, small.width, small.height, cell_px=10.0)
    map_x, map_y = undistortion_map(model, 90.0, 90.0, 80.0, 60.0)
    assert map_x.shape == (120, 160)
    ok = map_x >= 0
    assert 0.5 < ok.mean() < 1.0
    ys, xs = np.nonzero(ok)
    rays = np.column_stack([(xs - 80.0) / 90.0, (ys - 60.0) / 90.0, np.ones(len(xs))])
    assert np.abs(small.project(rays) - np.column_stack([map_x[ok], map_y[ok]])).max() < 2e-3


def test_fisheye_is_described_by_the_fisheye_models_only() -> None:
    px = _pixels(SMALL_FISHEYE, 4000, seed=1)
    rays = SMALL_FISHEYE.unproject(px)
    lit = rays[:, 2] >= np.cos(np.radians(100.0))
    kb = fit_rays(KannalaBrandtCamera, px[lit], rays[lit], SMALL_FISHEYE.width, SMALL_FISHEYE.height)
    assert kb.covered == 1.0 and kb.max < 1e-6
    assert np.allclose(kb.camera.params, SMALL_FISHEYE.params, rtol=1e-6, atol=1e-8)
    bc = fit_rays(BrownConradyCamera, px[lit], rays[lit], SMALL_FISHEYE.width, SMALL_FISHEYE.height)
    assert bc.covered < 0.9 and bc.median > 5.0


def test_fit_absorbs_a_rotation() -> None:
    rays = directions(60.0, 800, seed=2)
    px = BROWN_CONRADY.project(rays)
    turn = np.array([[np.cos(0.02), 0, np.sin(0.02)], [0, 1, 0], [-np.sin(0.02), 0, np.cos(0.02)]])
    fit = fit_rays(BrownConradyCamera, px, rays @ turn.T, 640, 480)
    assert fit.max < 1e-6 and np.allclose(fit.rotation, turn.T, atol=1e-8)
