"""The simulator: renders agree with their ground truth to hundredths of a pixel."""

from __future__ import annotations

import json

import numpy as np
import pytest

from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import OutputError
from blurcalib.sim.render import MIP_TEXELS_PER_SQUARE, Renderer, dot_texture, mip_levels_for
from blurcalib.sim.synth import Simulator, SynthConfig, write_dataset
from blurcalib.sim.truth import GROUND_TRUTH_FILE, Motion, TrueCamera, d435i_like_camera, load_ground_truth
from tests.dot_checks import blurred_dot_error, centroid
from tests.symmetry import symmetry_centres


@pytest.fixture(scope="module")
def small_camera() -> TrueCamera:
    model = BrownConrady(fx=300.0, fy=300.0, cx=160.3, cy=119.6, k1=0.03, k2=-0.04, p1=0.0005,
                         p2=-0.0003, k3=0.01, width=320, height=240)
    return TrueCamera(model, d435i_like_camera(1).waves)


@pytest.fixture(scope="module")
def renderer(small_camera: TrueCamera) -> Renderer:
    return Renderer(small_camera)


def _rotation(rng: np.random.Generator, scale: float) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(rng.normal(size=3) * scale)[0]


def test_dot_centroid_matches_time_average(small_camera: TrueCamera, renderer: Renderer) -> None:
    """A small dot blurred by a general 6-DoF motion: its intensity centroid is the mean of its
    sampled image positions, weighted by the image area the dot covers at each sample (which
    changes when the camera zooms or tilts)."""
    rng = np.random.default_rng(0)
    centre = (0.01, 0.02)
    P = np.array([*centre, 0.0])
    tex = dot_texture(centre, radius_m=0.0004, texel_m=0.00015, extent_m=0.0015)
    errors = []
    for _ in range(6):
        R = _rotation(rng, 0.3)
        t = np.array([rng.uniform(-0.03, 0.03), rng.uniform(-0.02, 0.02), 0.15]) - R @ P
        pose = Pose(R, t)
        xi = np.concatenate([rng.normal(size=3) * 0.02, rng.normal(size=3) * 0.002])
        xi2 = np.concatenate([rng.normal(size=3) * 0.01, np.zeros(3)])
        error, track = blurred_dot_error(renderer, tex, pose, xi, xi2, P)
        assert np.linalg.norm(track[-1] - track[0]) > 2.0
        errors.append(error)
    assert max(errors) < 0.02


def test_dot_centroid_in_plane_motion_is_plain_time_average(small_camera: TrueCamera,
                                                            renderer: Renderer) -> None:
    """Fronto-parallel view and a translation parallel to the target: the dot's image keeps its
    size, so the centroid is the plain time average (the ground truth's ``mean``)."""
    centre = (0.0, 0.0)
    P = np.zeros(3)
    tex = dot_texture(centre, radius_m=0.0004, texel_m=0.00015, extent_m=0.0015)
    pose = Pose(np.eye(3), np.array([0.004, -0.003, 0.15]))
    xi = np.array([0.0, 0.0, 0.0, 0.006, 0.004, 0.0])
    xi2 = np.array([0.0, 0.0, 0.0, -0.003, 0.006, 0.0])
    motion = Motion(xi, xi2, renderer.time_samples_for(pose, xi, xi2, P[None]))
    img = renderer.irradiance([tex], pose, motion).astype(np.float64)
    track = np.stack([small_camera.project(p.transform(P[None]))[0] for p in motion.poses(pose)])
    assert np.linalg.norm(track[-1] - track[0]) > 10.0
    assert np.linalg.norm(centroid(img) - track.mean(axis=0)) < 0.02


@pytest.fixture(scope="module")
def sharp_sim(small_camera: TrueCamera) -> Simulator:
    cfg = SynthConfig(sharp=3, blurry=2, square_px=(18.0, 26.0), max_tilt_deg=25.0,
                      blur_min_px=4.0, blur_max_px=8.0, seed=3)
    return Simulator(cfg, camera=small_camera)


@pytest.mark.slow
def test_star_centres_on_sharp_renders_match_projected_truth(sharp_sim: Simulator) -> None:
    for index in range(2):
        frame = sharp_sim.frame(index)
        truth = frame.truth
        levels = [sharp_sim.texture(MIP_TEXELS_PER_SQUARE[k]) for k in
                  mip_levels_for(sharp_sim.camera, truth.pose, sharp_sim.pattern, 3)]
        clean = sharp_sim.renderer.irradiance(levels, truth.pose, truth.motion)
        sel = truth.block_inside
        assert sel.sum() > 50
        start = truth.mid[sel] + np.random.default_rng(index).uniform(-0.5, 0.5, (sel.sum(), 2))
        found = symmetry_centres(clean, start)
        err = np.linalg.norm(found - truth.mid[sel], axis=1)
        assert np.median(err) < 0.04
        assert np.percentile(err, 90) < 0.1
        assert np.abs((found - truth.mid[sel]).mean(axis=0)).max() < 0.02
        # The noisy 8-bit frame gives the same centres within its noise.
        noisy = symmetry_centres(frame.image.astype(np.float64), found)
        assert np.median(np.linalg.norm(noisy - found, axis=1)) < 0.05


def test_deterministic_and_seeded(sharp_sim: Simulator, small_camera: TrueCamera) -> None:
    a = sharp_sim.frame(3).image
    again = Simulator(sharp_sim.config, camera=small_camera).frame(3).image
    other = sharp_sim.frame(4).image
    assert np.array_equal(a, again)
    assert not np.array_equal(a, other)


def test_blurry_truth_psf(sharp_sim: Simulator) -> None:
    frame = sharp_sim.frame(3)
    truth = frame.truth
    assert truth.kind == "blurry" and truth.motion.samples > 1
    lengths = truth.blur_length[truth.visible]
    assert 3.0 < np.median(lengths) < 9.0
    idx = np.flatnonzero(truth.block_inside)[:5]
    for i in idx:
        psf = truth.psf_at(sharp_sim.camera, truth.mid[i], size=25)
        assert psf.sum() == pytest.approx(1.0, abs=1e-6)
        c = (psf.shape[0] - 1) / 2
        ys, xs = np.mgrid[0:psf.shape[0], 0:psf.shape[1]]
        centroid = np.array([(psf * xs).sum(), (psf * ys).sum()]) - c
        assert np.allclose(centroid, truth.mean[i] - truth.mid[i], atol=2e-3)


def test_sharp_psf_is_centred_defocus(sharp_sim: Simulator) -> None:
    truth = sharp_sim.frame(0).truth
    psf = truth.psf_at(sharp_sim.camera, truth.mid[np.flatnonzero(truth.visible)[0]], size=9)
    assert np.allclose(psf, psf[::-1, ::-1], atol=1e-12)
    var = (psf * (np.arange(9) - 4.0)[None, :] ** 2).sum()
    assert var == pytest.approx(truth.defocus_sigma**2, rel=0.05)


@pytest.mark.slow
def test_write_dataset_round_trip(tmp_path, small_camera: TrueCamera) -> None:
    cfg = SynthConfig(sharp=1, blurry=1, square_px=(18.0, 26.0), blur_min_px=3, blur_max_px=5)
    calls = []
    truth = write_dataset(tmp_path / "ds", cfg, camera=small_camera,
                          progress=lambda i, n, name: calls.append((i, n, name)))
    files = sorted(p.relative_to(tmp_path / "ds").as_posix()
                   for p in (tmp_path / "ds").rglob("*") if p.is_file())
    assert files == ["blurry/0000.png", GROUND_TRUTH_FILE, "pattern.yaml", "sharp/0000.png"]
    assert calls[-1] == (2, 2, "blurry/0000.png")
    loaded = load_ground_truth(tmp_path / "ds")
    assert json.loads((tmp_path / "ds" / GROUND_TRUTH_FILE).read_text())["version"] == 1
    for a, b in zip(truth.frames, loaded.frames, strict=True):
        assert a.name == b.name and a.motion.samples == b.motion.samples
        assert np.allclose(a.mid, b.mid, atol=1e-8) and np.allclose(a.mean, b.mean, atol=1e-8)
        assert np.array_equal(a.visible, b.visible)
        assert np.allclose(a.pose.R, b.pose.R) and np.allclose(a.pose.t, b.pose.t)
    px = np.array([[100.0, 80.0], [250.0, 200.0]])
    assert np.allclose(loaded.camera.project(np.array([[0.01, 0.02, 0.3]])),
                       small_camera.project(np.array([[0.01, 0.02, 0.3]])))
    assert np.allclose(loaded.camera.unproject(px), small_camera.unproject(px))


def test_unwritable_output_is_reported(tmp_path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match="file"):
        write_dataset(blocker / "ds", SynthConfig(sharp=1, blurry=0))


def test_bad_config_rejected() -> None:
    with pytest.raises(ValueError, match="blur_min_px"):
        SynthConfig(blur_min_px=5, blur_max_px=2)


def test_true_camera_deviation_round_trip() -> None:
    cam = d435i_like_camera(0)
    px = np.random.default_rng(0).uniform([0, 0], [1279, 719], size=(500, 2))
    dev = cam.deviation(px)
    assert 0.05 < np.abs(dev).max() < 0.5
    rays = np.concatenate([cam.unproject(px), np.ones((500, 1))], axis=1)
    assert np.abs(cam.project(rays) - px).max() < 1e-8
