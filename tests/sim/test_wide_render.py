"""The simulator through wide lenses: the fisheye presets, the target-facing canvas, wide-lens
poses, and renders that agree with their ground truth beyond 90 degrees off the axis."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.pose import Pose
from blurcalib.sim.render import MIP_TEXELS_PER_SQUARE, Renderer, dot_texture, mip_levels_for
from blurcalib.sim.synth import Simulator, SynthConfig, frame_truth, sample_pose
from blurcalib.sim.truth import Motion, TrueCamera, d435i_like_camera, fisheye_camera
from blurcalib.target.pattern import layout_pattern
from tests.dot_checks import blurred_dot_error
from tests.symmetry import symmetry_centres

SMALL_FISHEYE = fisheye_camera(190.0, seed=1, width=320, height=180)


def _ray_to(theta: float, phi: float) -> np.ndarray:
    return np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)])


def _facing(ray: np.ndarray, rng: np.random.Generator, tilt: float) -> np.ndarray:
    """A rotation turning the target's normal (z) to ``ray``, tilted by up to ``tilt`` rad."""
    axis = np.cross([0.0, 0.0, 1.0], ray)
    angle = math.atan2(float(np.linalg.norm(axis)), float(ray[2]))
    return cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0] @ cv2.Rodrigues(rng.normal(size=3) * tilt)[0]


def test_fisheye_presets_have_their_field() -> None:
    for fov in (130.0, 190.0):
        camera = fisheye_camera(fov)
        ends = np.array([[-0.5, camera.model.cy], [camera.width - 0.5, camera.model.cy]])
        edges = camera.pixel_to_ray(ends)
        # the principal point is 2.3 px off the centre: the edges straddle half the field
        assert np.degrees(np.arccos(edges[:, 2])).mean() == pytest.approx(fov / 2, abs=0.3)
        assert np.degrees(camera.field_stop) == pytest.approx(100.0)
        dev = camera.deviation(np.random.default_rng(0).uniform([0, 0], [1279, 719], (400, 2)))
        assert 0.1 < np.abs(dev).max() < 0.5
    corner = fisheye_camera(190.0).pixel_to_ray(np.array([[0.0, 0.0]]))
    assert not fisheye_camera(190.0).in_view(corner).any()  # beyond the 200 degree image circle
    with pytest.raises(ValueError, match="200"):
        fisheye_camera(210.0)


def test_true_fisheye_round_trips_and_serialises() -> None:
    px = np.random.default_rng(1).uniform([0, 0], [319, 179], (500, 2))
    rays = SMALL_FISHEYE.pixel_to_ray(px)
    assert np.degrees(np.arccos(rays[:, 2].min())) > 100
    assert np.abs(SMALL_FISHEYE.project(rays * 0.3) - px).max() < 1e-8
    back = TrueCamera.from_dict(SMALL_FISHEYE.to_dict())
    assert np.array_equal(back.model.params, SMALL_FISHEYE.model.params)
    assert np.array_equal(back.waves, SMALL_FISHEYE.waves) and back.field_stop_deg == 100.0
    angles = (10, 89, 95, 99.9, 100.1, 150)
    seen = SMALL_FISHEYE.in_view(np.array([_ray_to(math.radians(a), 0.3) for a in angles]))
    assert seen.tolist() == [True, True, True, True, False, False]
    legacy = d435i_like_camera(0)
    assert TrueCamera.from_dict(legacy.to_dict()).forward_only
    assert np.allclose(legacy.pixel_to_ray(px), BrownConradyCamera.from_brown_conrady(legacy.model).unproject(
        legacy._undeviate(px)), atol=1e-15)


def test_dot_centroid_matches_time_average_far_off_the_axis() -> None:
    """A small dot seen 20 to 97 degrees off the axis, blurred by a general 6-DoF motion: its
    intensity centroid is the area-weighted mean of its image positions."""
    renderer = Renderer(SMALL_FISHEYE)
    rng = np.random.default_rng(0)
    centre = (0.01, 0.02)
    P = np.array([*centre, 0.0])
    tex = dot_texture(centre, radius_m=0.0004, texel_m=0.00015, extent_m=0.0015)
    errors = []
    pixels = np.array([[200.0, 100.0], [280.0, 40.0], [20.0, 90.0], [12.0, 40.0], [305.0, 150.0],
                       [10.0, 25.0]])
    rays = SMALL_FISHEYE.pixel_to_ray(pixels)
    assert np.degrees(np.arccos(rays[:, 2])).max() > 96
    for ray in rays:
        R = _facing(ray, rng, 0.3)
        pose = Pose(R, 0.06 * ray - R @ P)
        xi = np.concatenate([rng.normal(size=3) * 0.02, rng.normal(size=3) * 0.001])
        xi2 = np.concatenate([rng.normal(size=3) * 0.01, np.zeros(3)])
        error, track = blurred_dot_error(renderer, tex, pose, xi, xi2, P)
        assert np.all((track >= 0) & (track <= [319, 179]))
        errors.append(error)
    assert max(errors) < 0.03


def test_still_rolling_shutter_through_a_fisheye_equals_global() -> None:
    """A rolling shutter without motion renders what the global shutter does, through a
    target-facing canvas (row bands, dark sub-samples beyond the field stop) too."""
    renderer = Renderer(SMALL_FISHEYE)
    ray = SMALL_FISHEYE.pixel_to_ray(np.array([[30.0, 60.0]]))[0]
    tex = dot_texture((0.0, 0.0), radius_m=0.004, texel_m=0.0005, extent_m=0.01)
    R = _facing(ray, np.random.default_rng(3), 0.2)
    pose = Pose(R, 0.1 * ray)
    still = Motion(np.zeros(6), np.zeros(6), 6)
    rolling = renderer.irradiance([tex], pose, still, rolling_shutter=2.0)
    assert rolling.max() > 0.5 and rolling[0, 0] == 0.0  # the corner is beyond the image circle
    assert np.abs(rolling - renderer.irradiance([tex], pose, still)).max() < 1e-5


@pytest.mark.slow
def test_wide_canvas_renders_a_perspective_lens_like_its_own_canvas() -> None:
    """The same Brown-Conrady lens, rendered through one perspective canvas and through the
    target-facing canvas of the family's model, gives the same blurry frame."""
    model = BrownConrady(fx=300.0, fy=300.0, cx=160.3, cy=119.6, k1=0.03, k2=-0.04, p1=0.0005,
                         p2=-0.0003, k3=0.01, width=320, height=240)
    waves = d435i_like_camera(1).waves
    cfg = SynthConfig(sharp=0, blurry=1, square_px=(18.0, 26.0), max_tilt_deg=25.0, blur_min_px=4.0,
                      blur_max_px=8.0, seed=3)
    forward = Simulator(cfg, camera=TrueCamera(model, waves))
    wide = Renderer(TrueCamera(BrownConradyCamera.from_brown_conrady(model), waves))
    truth = forward.frame(0).truth
    levels = [forward.texture(MIP_TEXELS_PER_SQUARE[k])
              for k in mip_levels_for(forward.camera, truth.pose, forward.pattern, 3)]
    a = forward.renderer.irradiance(levels, truth.pose, truth.motion)
    b = wide.irradiance(levels, truth.pose, truth.motion)
    assert np.sqrt(np.mean((a - b) ** 2)) < 0.005 and np.abs(a - b).max() < 0.05


def test_wide_poses_fill_the_image_and_reach_far_off_the_axis() -> None:
    pattern = layout_pattern()
    camera = fisheye_camera(190.0)
    rng = np.random.default_rng(2)
    angles, pixels = [], []
    for _ in range(24):
        pose = sample_pose(pattern, camera, rng, 60.0, (24.0, 42.0))
        truth = frame_truth("f", "sharp", pattern, camera, pose, Motion.still(), 0.5, rng, 2.0)
        cam = pose.transform(pattern.points_3d())[truth.visible]
        assert truth.visible.sum() >= 40 and camera.in_view(cam).all()
        angles.append(np.degrees(np.arccos(cam[:, 2] / np.linalg.norm(cam, axis=1))))
        pixels.append(truth.mid[truth.visible])
    angles, pixels = np.concatenate(angles), np.concatenate(pixels)
    assert angles.max() > 92.0 and np.mean(angles > 60.0) > 0.2
    # every sixth of the image's width holds features, the leftmost and rightmost included
    columns = np.histogram(pixels[:, 0], bins=6, range=(0, 1280))[0]
    assert columns.min() > 0.03 * len(pixels)


@pytest.mark.slow
def test_star_centres_of_fisheye_renders_match_the_truth() -> None:
    """Sharp renders of a 190 degree lens: star centres (an independent symmetry detector, which
    needs stars of 8 px or more on their short side) agree with the projected truth."""
    camera = fisheye_camera(190.0, seed=2, width=640, height=360)
    cfg = SynthConfig(sharp=3, blurry=0, square_px=(16.0, 22.0), max_tilt_deg=30.0, seed=5)
    sim = Simulator(cfg, camera=camera)
    angles = []
    for index in range(3):
        truth = sim.frame(index).truth
        levels = [sim.texture(MIP_TEXELS_PER_SQUARE[k])
                  for k in mip_levels_for(camera, truth.pose, sim.pattern, 3)]
        clean = sim.renderer.irradiance(levels, truth.pose, truth.motion)
        cam = truth.pose.transform(sim.pattern.points_3d())
        side = np.linalg.svd(camera.point_jacobian(cam) @ truth.pose.R[:, :2], compute_uv=False)[:, 1]
        sel = truth.block_inside & (side * sim.pattern.square_length_m >= 8.0)
        assert sel.sum() > 50
        start = truth.mid[sel] + np.random.default_rng(index).uniform(-0.5, 0.5, (sel.sum(), 2))
        err = np.linalg.norm(symmetry_centres(clean, start) - truth.mid[sel], axis=1)
        assert np.median(err) < 0.04 and np.percentile(err, 90) < 0.1
        angles.append(np.degrees(np.arccos(cam[sel, 2] / np.linalg.norm(cam[sel], axis=1))))
    assert np.concatenate(angles).max() > 60.0


@pytest.mark.parametrize(("argv", "needle"), [
    (["--fov", "150"], "--fov sets the field of view of --lens fisheye"),
    (["--lens", "fisheye", "--fov", "250"], "must be in (0, 200]"),
])
def test_synth_lens_options_are_checked(tmp_path, capsys, argv: list[str], needle: str) -> None:
    from blurcalib.cli import main

    assert main(["synth", "--out", str(tmp_path / "ds"), "--sharp", "1", "--blurry", "0", *argv]) == 2
    assert needle in capsys.readouterr().err
    assert not (tmp_path / "ds" / "ground_truth.json").exists()
