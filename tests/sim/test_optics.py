"""The simulator's realistic optics: the field-varying asymmetric PSF, the tone curve and the
display's pixel grid behave as specified, and with every effect off a frame renders as before."""

from __future__ import annotations

import numpy as np
import pytest

from blurcalib.camera.parametric import BrownConrady
from blurcalib.psf.kernel import psf_moments
from blurcalib.sim.captures import facing_poses, render_frame
from blurcalib.sim.optics import DisplayGrid, FieldPsf, Optics, ToneCurve, display_texture
from blurcalib.sim.synth import Simulator, SynthConfig
from blurcalib.sim.truth import TrueCamera
from blurcalib.target.pattern import layout_pattern

SIZE = (320, 240)


@pytest.fixture(scope="module")
def small_camera() -> TrueCamera:
    return TrueCamera(BrownConrady(fx=300.0, fy=300.0, cx=160.3, cy=119.6, k1=0.03, k2=-0.04, p1=0.0005,
                                   p2=-0.0003, k3=0.01, width=SIZE[0], height=SIZE[1]))


def test_field_psf_is_radial_and_grows_with_the_field() -> None:
    psf = FieldPsf(sigma=0.8, growth=0.6, astig=0.4, coma=(0.0, 2.0), lobe_weight=0.25, size=17)
    centre = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
    corner = np.hypot(*centre)
    for angle in np.linspace(0, 2 * np.pi, 7)[:-1]:
        e = np.array([np.cos(angle), np.sin(angle)])
        h = 0.8
        k = psf.kernels((centre + h * corner * e)[None], SIZE)[0]
        m = psf_moments(k)
        assert k.sum() == pytest.approx(1.0)
        # the lobe's centroid: w s(h) along the outward radius, nothing across it
        assert m.centroid @ e == pytest.approx(0.25 * 2.0 * h**3, abs=0.01)
        assert abs(m.centroid @ np.array([-e[1], e[0]])) < 1e-3  # the pixel grid is not round
        # astigmatism: the major axis is radial
        assert abs(np.sin(m.orientation - angle)) < 0.01
    at_centre = psf_moments(psf.kernels(centre[None], SIZE)[0])
    assert np.allclose(at_centre.centroid, 0.0, atol=1e-12)
    assert at_centre.eccentricity < 1e-6
    assert psf_moments(k).sigma_minor > at_centre.sigma_minor


def test_field_psf_inward_coma_points_inwards() -> None:
    psf = FieldPsf(coma=(-1.0, 0.0), size=17)
    point = np.array([[300.0, 119.5]])
    assert psf.centroid_at(point, SIZE)[0, 0] < -0.05


def test_point_source_image_is_the_psf_at_its_position() -> None:
    psf = FieldPsf(sigma=0.7, coma=(-0.5, 2.5), node_px=16, size=15)
    image = np.zeros(SIZE[::-1])
    sources = [(37, 211), (120, 160), (5, 300), (230, 6)]
    for y, x in sources:
        image[y, x] = 1.0
    out = psf.apply(image)
    r = (psf.size - 1) // 2
    offs = np.arange(-r, r + 1)
    for y, x in sources:
        expect = psf.centroid_at(np.array([[x, y]], dtype=float), SIZE)[0]
        if x < r or y < r:  # at the border part of the spread leaves the image
            continue
        w = out[y - r:y + r + 1, x - r:x + r + 1]
        assert w.sum() == pytest.approx(1.0, abs=1e-9)
        got = np.array([w.sum(axis=0) @ offs, w.sum(axis=1) @ offs]) / w.sum()
        assert np.allclose(got, expect, atol=1e-9)
    assert np.hypot(*psf.centroid_at(np.array([[300.0, 230.0]]), SIZE)[0]) > 0.1


def test_tone_curve_is_monotonic_and_the_identity_when_off() -> None:
    x = np.linspace(-20, 280, 3001)
    assert np.array_equal(ToneCurve()(x), np.clip(x, 0, 255))
    for tone in (ToneCurve(gamma=2.2), ToneCurve(gamma=0.6, s_curve=1.0), ToneCurve(gamma=2.2, s_curve=0.4)):
        y = tone(x)
        assert np.all(np.diff(y) >= 0) and np.all(np.diff(y[(x > 0) & (x < 255)]) > 0)
        assert tone(np.array([0.0, 255.0])) == pytest.approx([0.0, 255.0])
    assert ToneCurve(gamma=2.2)(np.array([127.5]))[0] > 127.5 + 40


def test_display_texture_shows_pixels_and_moves_the_pattern() -> None:
    pattern = layout_pattern(page_size_mm=(80.0, 80.0), approx_square_length_mm=10.0, tag_length_in_squares=2)
    display = DisplayGrid(pixels_per_square=20.0, subpixel_weights=(0.2, 0.3, 0.5), stripe_fill=0.6,
                          row_fill=0.8, origin=(0.0, 0.0))
    r = 320  # 16 texels per screen pixel
    tex = display_texture(pattern, r, display)
    L = pattern.square_length_m
    x0 = round((3.0 * L - tex.to_plane[0, 2]) / tex.to_plane[0, 0] + 0.5)  # texel edge at fx = 3
    top = float(pattern.page_mm_to_feature(np.zeros(2))[1])
    fy = np.ceil((top + 0.05) * 20) / 20  # a screen pixel row in the page's white margin
    assert fy + 4 / 20 < -1
    y0 = round((fy * L - tex.to_plane[1, 2]) / tex.to_plane[1, 1] + 0.5)
    white = tex.image[y0:y0 + 4 * 16, x0:x0 + 4 * 16]  # 4 x 4 whole screen pixels of white
    assert white.mean() == pytest.approx(1.0, abs=1e-4)
    assert white.min() == 0.0 and white.max() > 2.0  # black matrix and bright stripes
    # each screen pixel's stripes: R, G, B weighted 0.2, 0.3, 0.5 over equal areas
    row = white[8, :16]
    stripes = [row[c * 16 // 3 + 2:(c + 1) * 16 // 3 - 1].mean() for c in range(3)]
    assert stripes[0] < stripes[1] < stripes[2]
    # the B stripe is the brightest: the emission centroid lies right of the pixel centre
    assert display.shift_squares()[0] == pytest.approx((0.2 / 6 + 0.3 / 2 + 0.5 * 5 / 6 - 0.5) / 20.0)
    assert display.shift_squares()[1] == 0


def test_every_effect_off_renders_as_without_optics(small_camera: TrueCamera) -> None:
    cfg = SynthConfig(sharp=1, blurry=0, square_px=(20.0, 26.0), seed=3)
    ref = Simulator(cfg, camera=small_camera).frame(0).image
    assert np.array_equal(ref, Simulator(cfg, camera=small_camera, optics=Optics()).frame(0).image)
    identity = Optics(tone=ToneCurve())
    assert np.array_equal(ref, Simulator(cfg, camera=small_camera, optics=identity).frame(0).image)


def test_capture_truths(small_camera: TrueCamera) -> None:
    pattern = layout_pattern(num_star_segments=4)
    optics = Optics(psf=FieldPsf(coma=(0.0, 3.0), size=13))
    sim = Simulator(SynthConfig(sharp=0, blurry=0, noise_sigma=0.5), pattern, small_camera, optics)
    pose = facing_poses(small_camera, pattern, 1, np.random.default_rng(0), square_px=14.0)[0]
    image, truth = render_frame(sim, pose, np.random.default_rng(1), optics)
    assert image.shape == SIZE[::-1] and truth.visible.sum() > 100
    assert np.allclose(truth.projection, small_camera.project(pose.transform(pattern.points_3d())))
    shift = truth.centroid - truth.projection
    radial = np.sum(shift * (truth.projection - [160.3, 119.6]), axis=1)
    assert np.all(radial[truth.visible] >= -1e-9) and np.abs(shift[truth.visible]).max() > 0.2
