"""The rig view in a real headless Chromium (Playwright): ``app.py --rig``'s page shows the rig's
summary and, on the Rectified pair tab, the chosen set's epipolar error, without console errors.
Skipped, naming what is missing, without ``/usr/bin/chromium`` or playwright."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.app.test_browser import app_page, sync_api
from tests.rig_output_scene import write_rig_scene

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_rig_view_in_chromium(tmp_path: Path) -> None:
    from app import serve_rig
    from state.rig import load_rig

    server, app = serve_rig(load_rig(write_rig_scene(tmp_path).out), 0)
    try:
        with app_page(server) as (_, page, errors):
            sync_api.expect(page.get_by_text(re.compile(r"2 cameras, 3 image sets"))).to_be_visible()
            page.get_by_text("Rectified pair").click()
            epipolar = page.locator("p", has_text="Epipolar error of 0001.png")
            sync_api.expect(epipolar).to_be_visible()
            exact = re.compile(r"108 features both cameras see, median 0\.0000 px")
            sync_api.expect(epipolar).to_contain_text(exact)
            assert not errors, errors
    finally:
        app.close()
        server.stop()
