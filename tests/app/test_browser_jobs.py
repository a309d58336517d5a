"""The app's three jobs, driven in a real headless Chromium on its built-in dataset.

1. Threshold tuning: the glare frame's edge blocks are removed by τ_L at the defaults; the
   slider's top keeps them, *Defaults* removes them again; arrow keys on a focused slider do not
   turn the 3D view.
2. Debugging a bad frame: a click on a block in the frame opens it in the block inspector; the
   frame whose tag is hidden, run alone, shows where the tag search looked.
3. Teaching the translational ambiguity: the δ slider moves the star while the blurred image
   stays the same (residual at rounding), and the alignment figure ends on the truth.

Same requirements and skips as ``tests/app/test_browser.py``; slow (the dataset is rendered and
two frames extracted).
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest

from blurcalib.io.results import BlockStatus
from state.folder import default_dataset
from tests.app.test_browser import _row, app_page, sync_api
from views.frame_view import FRAME_LABEL, FrameViewPanel

pytestmark = [pytest.mark.browser, pytest.mark.slow]

GLARE, HIDDEN = "blurry/01-glare.png", "blurry/04-tag-hidden.png"


def _choose_frame(page, name: str) -> None:
    _row(page, "Frame").locator("input:not([type='hidden'])").click()
    page.get_by_role("option", name=name).click()


def _run(page, app, name: str) -> None:
    _choose_frame(page, name)
    sync_api.expect(page.get_by_text("not extracted yet")).to_be_visible()
    page.get_by_role("button", name="Run frame").click()
    # The frame's result, not the buttons: on a busy machine the click may reach the server after
    # the buttons were first checked, when they still show the idle state.
    deadline = time.monotonic() + 900.0
    while app.state.view().result is None and time.monotonic() < deadline:
        page.wait_for_timeout(200)
    sync_api.expect(page.get_by_role("button", name="Cancel")).to_be_disabled(timeout=60_000)
    sync_api.expect(page.get_by_role("button", name="Run frame")).to_be_enabled()
    assert app.state.view().entry.name == name and app.state.view().result is not None


def test_the_three_jobs_on_the_built_in_dataset(tmp_path: Path) -> None:
    from app import serve

    folder = default_dataset(tmp_path / "data", workers=2)
    server, app = serve(folder, None, 0, out=tmp_path / "out")
    expect = sync_api.expect
    frame_view = next(p for p in app.panels if isinstance(p, FrameViewPanel))
    try:
        with app_page(server) as (_, page, errors):
            # 1. Threshold tuning on the glare frame.
            _run(page, app, GLARE)
            blocks = app.state.view().result.blocks
            glare = np.isin(blocks.feature_id, app.state.dataset.faults[GLARE].features[0])
            removed = glare & (app.state.view().filter.status.astype(str) == BlockStatus.FILTERED_LOSS.value)
            assert removed.sum() >= 3
            expect(page.get_by_text(f"loss > τ_L: {int(removed.sum())},")).to_be_visible()
            client = next(iter(server.get_clients().values()))
            camera = np.array(client.camera.position)
            slider = _row(page, "log₁₀ τ_L").get_by_role("slider")
            slider.focus()
            page.keyboard.down("ArrowLeft")  # held: viser turns the view while a key is down
            page.wait_for_timeout(800)
            page.keyboard.up("ArrowLeft")
            slider.press("End")
            expect(page.get_by_text("loss > τ_L: 0,")).to_be_visible()
            assert app.state.view().filter.kept[removed].all()
            page.wait_for_timeout(500)
            assert np.allclose(client.camera.position, camera)
            page.get_by_role("button", name="Defaults", exact=True).click()
            expect(page.get_by_text(f"loss > τ_L: {int(removed.sum())},")).to_be_visible()

            # 2. Debugging: click the worst removed block in the frame; it opens in the inspector.
            i = int(np.flatnonzero(removed)[np.argmax(blocks.loss[removed])])
            height, width, _, s = frame_view._layout
            x, y = blocks.centre[i]
            image = page.get_by_text(FRAME_LABEL, exact=True).locator("xpath=..").locator("img").first
            box = image.bounding_box()
            image.click(position={"x": (s * (x + 0.5) - 0.5) / width * box["width"],
                                  "y": (s * (y + 0.5) - 0.5) / height * box["height"]})
            expect(page.get_by_text(re.compile(rf"block #{i} at \(\d+, \d+\) px"))).to_be_visible()
            assert app.state.selected == i
            page.get_by_role("tab", name="Block").click()
            expect(page.get_by_text(re.compile(rf"block #{i} feature .*filtered loss"))).to_be_visible()
            page.get_by_role("tab", name="Frame").click()
            _run(page, app, HIDDEN)  # alone: no neighbour is extracted yet
            expect(page.get_by_text(re.compile(r"Not seeded\. The tag search looked over the whole frame"))
                   ).to_be_visible()
            expect(page.get_by_text(re.compile(r"^no blocks: the frame was not seeded \(its tag was not"))
                   ).to_be_visible()  # the counts
            expect(page.get_by_text(re.compile(r"^alignment error: .*the frame was not seeded"))
                   ).to_be_visible()  # not '0 blocks kept by the filter, alignment needs 12'

            # 3. The ambiguity: the blurred image does not change with δ, the star does.
            page.get_by_role("tab", name="Ambiguity").click()
            caption = page.get_by_text(re.compile(r"star centre at \(\d+, \d+\) px"))
            before = caption.inner_text()
            dx = _row(page, "δx (px)").get_by_role("slider")
            dx.focus()
            dx.press("End")
            expect(caption).not_to_have_text(before)
            worst = float(re.search(r"max \|residual\| = ([\d.e+-]+)", caption.inner_text())[1])
            assert worst < 1e-9
            steps = page.locator("ul").filter(has_text="after global alignment")
            rms = [float(v) for v in re.findall(r"RMS error ([\d.]+) px", steps.inner_text())]
            assert rms[-1] < 0.5 < rms[0]
            assert not errors, errors
    finally:
        app.close()
        server.stop()
