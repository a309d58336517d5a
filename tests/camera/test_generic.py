"""The central generic model: fit, projection, Jacobians, reference files, undistortion map."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from blurcalib.camera.files import (
    RefCameraError,
    read_generic_yaml,
    read_opencv_yaml,
    write_generic_yaml,
    write_opencv_yaml,
)
from blurcalib.camera.generic import (
    CentralGeneric,
    apply_update,
    calibrated_area,
    fit_to_rays,
    projection_jacobians,
    undistortion_map,
)
from blurcalib.camera.parametric import BrownConrady

CAM = BrownConrady(fx=260.0, fy=258.0, cx=161.3, cy=119.2, k1=-0.21, k2=0.05, p1=0.001,
                   p2=-0.0007, k3=0.01, width=320, height=240)


@pytest.fixture(scope="module")
def model() -> CentralGeneric:
    return fit_to_rays(CAM.pixel_to_ray, CAM.width, CAM.height, cell_px=20.0)


def _pixels(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.4, -0.4], [CAM.width - 0.6, CAM.height - 0.6], (n, 2))


def test_grid_layout_and_area() -> None:
    assert calibrated_area([[0.2, 3.7], [318.9, 200.1]], 320, 240) == (0, 4, 319, 200)
    m = fit_to_rays(CAM.pixel_to_ray, 320, 240, cell_px=40.0, iterations=1)
    assert (m.grid_width, m.grid_height) == (10, 8)
    g = m.to_grid([[-0.5, -0.5], [319.5, 239.5]])
    np.testing.assert_allclose(g, [[1.0, 1.0], [m.grid_width - 2.0, m.grid_height - 2.0]])


def test_fit_reproduces_camera(model: CentralGeneric) -> None:
    px = _pixels(3000)
    rays = CAM.pixel_to_ray(px)
    u, inside = model.project(rays * 2.0)
    assert inside.all()
    assert np.abs(u - px).max() < 1e-3
    reproj = CAM.project(model.pixel_to_ray(px))
    assert np.abs(reproj - px).max() < 1e-3


def test_projection_inverts_unprojection(model: CentralGeneric) -> None:
    px = _pixels(2000, seed=1)
    rays = model.pixel_to_ray(px)
    u, inside = model.project(rays * np.linspace(0.5, 3.0, len(px))[:, None])
    assert inside.all()
    assert np.abs(u - px).max() < 1e-7
    warm, _ = model.project(rays, init=px + 0.3)
    assert np.abs(warm - px).max() < 1e-7


def test_outside_points_are_flagged(model: CentralGeneric) -> None:
    _, inside = model.project(np.array([[3.0, 0.0, 1.0], [0.0, 0.0, 1.0]]))
    assert inside.tolist() == [False, True]


def test_jacobians_match_finite_differences(model: CentralGeneric) -> None:
    sp = model.spline()
    px = torch.as_tensor(_pixels(12, seed=3))
    pts = sp.evaluate(px).d * torch.linspace(1.0, 2.0, 12, dtype=torch.float64)[:, None]
    u, _ = sp.project(pts)
    J_p, J_g, nodes = projection_jacobians(sp, u, pts)
    h = 1e-6
    for c in range(3):
        dp = torch.zeros(3, dtype=torch.float64)
        dp[c] = h
        up, _ = sp.project(pts + dp, u)
        um, _ = sp.project(pts - dp, u)
        np.testing.assert_allclose((up - um) / (2 * h), J_p[:, :, c], atol=2e-4, rtol=1e-5)
    gh, gw = sp.shape
    for j in (0, 5, 10, 15):
        for k in range(2):
            num = torch.zeros(len(u), 2, dtype=torch.float64)
            for sign in (1.0, -1.0):
                for n in range(len(u)):
                    node = int(nodes[n, j])
                    delta = torch.zeros(gh * gw, 2, dtype=torch.float64)
                    delta[node, k] = sign * h
                    grid = apply_update(sp.grid, delta.reshape(gh, gw, 2))
                    un, _ = sp.with_grid(grid).project(pts[n:n + 1], u[n:n + 1])
                    num[n] += sign * un[0] / (2 * h)
            np.testing.assert_allclose(num, J_g[:, :, 2 * j + k], atol=2e-4, rtol=1e-5)


def test_generic_yaml_round_trip(model: CentralGeneric, tmp_path) -> None:
    path = write_generic_yaml(tmp_path / "intrinsics0.yaml", model)
    text = path.read_text().splitlines()
    assert [line.split(" : ")[0] for line in text if not line.startswith("#")] == [
        "type", "width", "height", "calibration_min_x", "calibration_min_y", "calibration_max_x",
        "calibration_max_y", "grid_width", "grid_height", "grid"]
    assert text[0] == "type : CentralGenericModel" and text[9].startswith("# ")
    back = read_generic_yaml(path)
    assert (back.min_x, back.max_x, back.max_y, back.grid.shape) == (0, 319, 239, model.grid.shape)
    np.testing.assert_allclose(back.grid, model.grid, atol=1e-13)
    bspline = tmp_path / "b.yaml"
    doubled = "grid : [" + ", ".join(repr(2.0 * float(v)) for v in model.grid.reshape(-1)) + "]"
    bspline.write_text("\n".join([*text[:-1], doubled]).replace("CentralGenericModel",
                                                              "CentralGenericBSplineModel"))
    scaled = read_generic_yaml(bspline)
    np.testing.assert_allclose(scaled.grid, model.grid, atol=1e-15)


def test_opencv_yaml_round_trip(tmp_path) -> None:
    path = write_opencv_yaml(tmp_path / "cam.yaml", CAM)
    line = path.read_text().splitlines()[3]
    assert line.startswith("parameters : [260, 258, 161.8, 119.7, -0.21, 0.05, 0.01, 0, 0, 0, ")
    back = read_opencv_yaml(path)
    assert back == CAM


@pytest.mark.parametrize(("edit", "field"), [
    (lambda s: s.replace("grid_width : ", "grid_wdth : "), "'grid_width'"),
    (lambda s: s.replace("calibration_min_y : 0", "calibration_min_y : zero"), "'calibration_min_y'"),
    (lambda s: s.replace("grid : [", "grid : [1, "), "'grid'"),
    (lambda s: s.replace("CentralGenericModel", "CentralThinPrismFisheyeModel"), "'type'"),
])
def test_generic_yaml_errors_name_the_field(model: CentralGeneric, tmp_path, edit, field) -> None:
    path = write_generic_yaml(tmp_path / "i.yaml", model)
    path.write_text(edit(path.read_text()))
    with pytest.raises(RefCameraError, match=field) as info:
        read_generic_yaml(path)
    assert "i.yaml" in str(info.value)


def test_opencv_yaml_errors_name_the_field(tmp_path) -> None:
    path = write_opencv_yaml(tmp_path / "c.yaml", CAM)
    path.write_text(path.read_text().replace("parameters : [260, ", "parameters : ["))
    with pytest.raises(RefCameraError, match=r"c\.yaml.*'parameters'"):
        read_opencv_yaml(path)
    path.write_text("type : CentralOpenCVModel\nwidth : 320\n")
    with pytest.raises(RefCameraError, match="missing field 'height'"):
        read_opencv_yaml(path)


def test_undistortion_map(model: CentralGeneric) -> None:
    fx, fy, cx, cy = 300.0, 300.0, 31.5, 23.5
    map_x, map_y = undistortion_map(model, fx, fy, cx, cy, width=64, height=48)
    assert map_x.shape == (48, 64) and map_x.dtype == np.float32
    xx, yy = np.meshgrid(np.arange(64.0), np.arange(48.0))
    rays = np.stack([(xx - cx) / fx, (yy - cy) / fy, np.ones_like(xx)], -1).reshape(-1, 3)
    expected = CAM.project(rays)
    ok = map_x.reshape(-1) >= 0
    assert ok.mean() > 0.9
    assert np.abs(map_x.reshape(-1)[ok] - expected[ok, 0]).max() < 2e-3
    assert np.abs(map_y.reshape(-1)[ok] - expected[ok, 1]).max() < 2e-3
