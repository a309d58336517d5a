"""The rig view (views/rig.py) on a live viser server without a browser: an exact rig output's
panel draws the cameras and image sets in 3D, a camera's error field and a pair's rectified set
with its epipolar error; ``app.py --rig`` refuses a folder that is no rig output."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app import main, serve_rig
from state.rig import load_rig
from tests.rig_output_scene import SET_NAMES, write_rig_scene
from views.rig import SCOPES, camera_errors_image, draw_rectified


def test_rig_panel_draws_the_rig(tmp_path: Path) -> None:
    scene = write_rig_scene(tmp_path)
    rig = load_rig(scene.out)
    server, app = serve_rig(rig, 0)
    panel = app.panel
    try:
        assert server.get_port() > 0
        assert "2 cameras, 3 image sets" in panel.summary.content and "baseline 50.0" in panel.summary.content
        panel.draw_scene()
        names = sorted(h.name for h in panel._scene_handles)  # type: ignore[attr-defined]
        assert names == ["/rig/cam0", "/rig/cam0_label", "/rig/cam1", "/rig/cam1_label", "/sets/0", "/sets/1",
                         "/sets/2"]
        labels = [h for h in panel._scene_handles if h.name.endswith("_label")]  # type: ignore[attr-defined]
        assert [h.text for h in labels] == ["cam0", "cam1"]  # type: ignore[attr-defined]
        cam1 = next(h for h in panel._scene_handles if h.name == "/rig/cam1")  # type: ignore[attr-defined]
        assert np.allclose(cam1.position, scene.rig.camera_tr_rig[1].inverse().t, atol=1e-6)

        panel.camera.value, panel.scope.value, panel.image_set.value = "cam1", SCOPES[1], SET_NAMES[2]
        panel.draw_errors()
        assert panel.errors_image.image is not None and panel.errors_image.image.ndim == 3
        assert "**cam1** reprojection error in the rig in 0003.png" in panel.errors_text.content
        assert "| 0003.png | 108 | 0.0000 |" in panel.sets_table.content

        panel.draw_pair()
        text = panel.pair_text.content
        assert "Epipolar error of 0003.png** (cam0 - cam1): 108 features both cameras see" in text
        assert "median 0.0000 px" in text and "not shown" not in text
        image = panel.pair_image.image
        assert image is not None and image.shape[1] == 2 * 320 + 6 and image.std() > 10
    finally:
        app.close()
        server.stop()
    view = rig.rectified(0, SET_NAMES[0])
    assert draw_rectified(view).shape == image.shape
    field, words = camera_errors_image(rig, 0, None)
    assert field.shape[2] == 3 and "over 3 image sets" in words


@pytest.mark.parametrize("what", ["missing", "empty"])
def test_app_refuses_a_folder_that_is_no_rig_output(tmp_path: Path, what: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "D"
    if what == "empty":
        folder.mkdir()
    assert main(["--rig", str(folder), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"app.py: error: {folder}")
    assert ("not a folder" if what == "missing" else "no calibration/") in err
