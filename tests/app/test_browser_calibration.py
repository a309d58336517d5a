"""End to end in a real headless Chromium (Playwright): press *Run calibration* on frames not
extracted yet (it extracts them first), read the generic error the page shows (it must equal the
state's), the assessment (held-out table, uncertainty maps), see every frame ``used``, the
σ_major pre-filter's statuses, the generic poses in the 3D view, and export.

Same requirements and skips as ``tests/app/test_browser.py``. It saves a screenshot of the
Calibration tab to ``out/app_calibration.png`` (ignored by git); with
``BLURCALIB_UPDATE_SCREENSHOT=1`` it updates ``docs/app_calibration.png``.
"""

from __future__ import annotations

import os
import re
from dataclasses import replace
from pathlib import Path

import pytest

from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.validation import ValidationSettings
from state.calibration import EXPORT_DIR, OPENCV_CAMERA_FILE
from tests.app.test_browser import ROOT, _row, app_page, sync_api
from tests.state.test_app_state import FAST, make_dataset
from tests.state.test_calibration import CONFIG, SETTINGS

pytestmark = [pytest.mark.browser, pytest.mark.slow]

pytest.importorskip("viser", reason="viser not installed: pip install 'viser>=1.1,<1.2'")

HELD_OUT = replace(SETTINGS, sequence=replace(
    SETTINGS.sequence, trust=TrustSettings(validation=ValidationSettings(min_frames=4, folds=2))))
"""The held-out validation lowered to the dataset's 4 frames (2 folds) so that its table shows."""
SCREENSHOT = (ROOT / "docs" / "app_calibration.png" if os.environ.get("BLURCALIB_UPDATE_SCREENSHOT")
              else ROOT / "out" / "app_calibration.png")


def _image(page, label: str):
    """The image of the GUI image widget labelled ``label``."""
    return page.get_by_text(label, exact=True).locator("xpath=..").locator("img")


def test_calibration_view_in_chromium(tmp_path: Path) -> None:
    from app import serve

    folder = make_dataset(tmp_path / "data", CONFIG)
    server, app = serve(folder, None, 0, settings=FAST, calibration=HELD_OUT)
    expect = sync_api.expect
    try:
        with app_page(server) as (_, page, errors):
            page.get_by_role("tab", name="Calibration").click()
            expect(page.get_by_text("No calibration yet")).to_be_visible()
            expect(page.get_by_text("blurry/0000.png: not extracted").first).to_be_visible()

            # One button: the frames are extracted first (no pre-filter by default: all 4 are used).
            page.get_by_role("button", name="Run calibration").click()
            shown = page.get_by_text(re.compile(r"generic median error: [\d.]+ px"))
            expect(shown).to_be_visible(timeout=300_000)
            assert {e.record.status.value for e in app.state.entries()} == {"ok"}
            median = float(re.search(r"generic median error: ([\d.]+) px", shown.inner_text())[1])
            result = app.calibration.result
            assert abs(median - result.generic.median_error) <= 5e-5
            assert result.truth is not None
            expect(page.get_by_text(f"{result.truth.generic_median:.4f}").first).to_be_visible()
            expect(page.get_by_text("At the current thresholds: 4 of 4 frames used.")).to_be_visible()
            expect(page.get_by_role("button", name="Run calibration")).to_be_enabled()
            expect(page.get_by_role("button", name="Export camera")).to_be_enabled()
            # The assessment: the held-out table and the uncertainty maps.
            held_out = page.locator("table").filter(has_text="held-out median (px)")
            expect(held_out).to_be_visible()
            # the report's figures (rounded to 5 decimals there), as the panel says
            score = result.trust.to_dict()["validation"]["generic"]
            assert score["median_px"] == round(result.trust.validation.scores["generic"].median_px, 5)
            row = held_out.locator("tr").filter(has_text="generic, sharp + blurry frames")
            expect(row).to_contain_text(f"{score['median_px']:.4f}")
            expect(row).to_contain_text(f"{score['rms_px']:.4f}")
            uncertainty = _image(page, "Projection uncertainty (px)")
            expect(uncertainty.first).to_have_attribute("src", re.compile("^blob:"))
            size = uncertainty.first.evaluate("img => img.decode().then(() => [img.naturalWidth, "
                                              "img.naturalHeight])")
            assert size[0] > 2 * size[1]  # sharp-only and sharp + blurry side by side
            expect(page.get_by_text("What the blurry frames bought")).to_be_visible()

            # The slider's top (1.15 x the largest frame's σ_major) drops the blurry frames; back at
            # 0 they are used.
            sigma = _row(page, "σ_major pre-filter").get_by_role("slider")
            sigma.focus()
            sigma.press("End")
            top = sigma.get_attribute("aria-valuemax")
            assert top is not None and 1.0 <= float(top) < 10.0
            expect(sigma).to_have_attribute("aria-valuenow", top)
            dropped = page.get_by_text(re.compile(r"blurry/0000\.png: dropped by the pre-filter"))
            expect(dropped).to_be_visible()
            expect(page.get_by_text(re.compile("a sharp frame is not pre-filtered"))).to_be_visible()
            coverage = _image(page, "Coverage (inputs now)")
            expect(coverage.first).to_have_attribute("src", re.compile("^blob:"), timeout=20_000)
            expect(page.get_by_text("At the current thresholds: 2 of 4 frames used.")).to_be_visible()
            sigma.focus()
            sigma.press("Home")
            expect(sigma).to_have_attribute("aria-valuenow", "0")
            expect(page.get_by_text(re.compile(r"4 frames pass the pre-filter"))).to_be_visible()
            expect(page.get_by_text("At the current thresholds: 4 of 4 frames used.")).to_be_visible()
            residuals = _image(page, "Generic fit residuals")
            expect(residuals.first).to_have_attribute("src", re.compile("^blob:"))
            before = residuals.first.get_attribute("src")
            _row(page, "Residuals of").locator("input:not([type='hidden'])").click()
            page.get_by_role("option", name="current frame").click()
            expect(residuals.first).not_to_have_attribute("src", before)

            page.get_by_role("button", name="Export camera").click()
            expect(page.get_by_text(re.compile(r"Exported to .*intrinsics0\.yaml")).first).to_be_visible()
            for name in ("intrinsics0.yaml", OPENCV_CAMERA_FILE, "undistortion_map.npz"):
                assert (folder / EXPORT_DIR / name).is_file(), name

            page.get_by_role("tab", name="Errors").click()
            poses = page.get_by_text(re.compile(r"4 frame poses from the generic bundle adjustment"))
            expect(poses).to_be_visible()
            page.get_by_role("tab", name="Calibration").click()
            page.add_style_tag(content=".mantine-Notification-root { display: none !important; }")
            page.get_by_role("button", name="Run calibration").scroll_into_view_if_needed()
            page.wait_for_timeout(1000)
            SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(SCREENSHOT))
            assert not errors, errors
    finally:
        app.close()
        server.stop()
