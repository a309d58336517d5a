"""End to end in a real headless Chromium (Playwright): open the app, run a frame, tune, inspect,
click a camera frustum in the 3D view.

After the run the tuning panel shows the frame's error after global alignment (the same median
as the state's), which follows the τ_L slider, and the Errors tab shows the residuals.

A second test opens a page of another local origin and checks that it cannot open the app's
websocket (``views/security.py``), while the app's own page can.

Needs Debian's ``/usr/bin/chromium`` and the ``playwright`` package (no ``playwright install``:
the test launches the system browser); it is skipped, saying which is missing, otherwise. It saves
a screenshot to ``out/app_screenshot.png`` (ignored by git); with ``BLURCALIB_UPDATE_SCREENSHOT=1``
it updates ``docs/app_screenshot.png``, the screenshot the README shows.
"""

from __future__ import annotations

import os
import re
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from blurcalib.extract.frame import ExtractSettings
from blurcalib.growth.settings import GrowSettings
from state import RunSettings
from tests.state.test_app_state import SMALL_CONFIG, make_dataset

pytestmark = pytest.mark.browser

CHROMIUM = Path("/usr/bin/chromium")
if not CHROMIUM.exists():
    pytest.skip(f"{CHROMIUM} not found: apt-get install chromium", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api",
                               reason="playwright not installed: pip install playwright")
pytest.importorskip("viser", reason="viser not installed: pip install 'viser>=1.1,<1.2'")
# The app answers within a second on an idle machine; on a loaded 2-core machine a step (an
# export, a bundle adjustment's figures) can take longer than expect's 5 s default.
sync_api.expect.set_options(timeout=60_000)

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--enable-unsafe-swiftshader"]
ROOT = Path(__file__).resolve().parents[2]
SCREENSHOT = (ROOT / "docs" / "app_screenshot.png" if os.environ.get("BLURCALIB_UPDATE_SCREENSHOT")
              else ROOT / "out" / "app_screenshot.png")
SETTINGS = RunSettings(blurry=ExtractSettings(grow=GrowSettings(max_blocks=25)))
"""Blurry frames grow two fronts (the ring around the tag and the next one): a few seconds."""


def _row(page, label: str):
    """The GUI row (label and input) whose label reads ``label``."""
    return page.locator("label", has_text=re.compile(f"^{re.escape(label)}$")).locator(
        "xpath=ancestor::div[contains(@class,'Flex-root')][1]")


def _kept(page) -> int:
    text = page.get_by_text(re.compile(r"kept: \d+ blocks")).inner_text()
    return int(re.search(r"kept: (\d+) blocks", text).group(1))


@contextmanager
def app_page(server) -> Iterator[tuple[object, object, list[str]]]:
    """Headless Chromium on the app that ``server`` serves: ``(browser, page, errors)``, the page
    connected (1600x1000) and ``errors`` collecting its console errors; the browser closes after."""
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=FLAGS)
        try:
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            errors: list[str] = []
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.goto(f"http://127.0.0.1:{server.get_port()}/")
            page.wait_for_function("() => !document.body.innerText.includes('Connecting...')", timeout=30_000)
            yield browser, page, errors
        finally:
            browser.close()


def test_run_tune_and_inspect_in_chromium(tmp_path: Path) -> None:
    from app import serve

    folder = make_dataset(tmp_path / "data", replace(SMALL_CONFIG, sharp=0, blurry=1))
    server, app = serve(folder, None, 0, settings=SETTINGS)
    expect = sync_api.expect
    try:
        with app_page(server) as (browser, page, errors):
            frame_image = page.get_by_text("Frame", exact=True).locator("xpath=..").locator("img")
            expect(frame_image.first).to_have_attribute("src", re.compile("^blob:"), timeout=20_000)
            before = frame_image.first.get_attribute("src")
            expect(page.get_by_text("not extracted yet")).to_be_visible()

            run = page.get_by_role("button", name="Run frame")
            run.click()
            done = re.compile(r"done: \d+ of \d+ blocks accepted")
            expect(page.get_by_text(done)).to_be_visible(timeout=120_000)
            expect(run).to_be_enabled()
            expect(page.get_by_role("button", name="Cancel")).to_be_disabled()
            assert frame_image.first.get_attribute("src") != before
            accepted = int(re.search(r"done: (\d+)", page.get_by_text(re.compile("done: ")).inner_text())[1])
            assert accepted == int(app.state.view().result.blocks.accepted.sum()) > 10
            expect(page.get_by_text(re.compile(r"time by stage: .*free PSFs [\d.]+ s"))).to_be_visible()

            kept = _kept(page)
            assert kept > 0
            aligned = page.get_by_text(re.compile(r"after global alignment: median [\d.]+ px"))
            expect(aligned).to_be_visible(timeout=30_000)
            median = float(re.search(r"median ([\d.]+) px", aligned.inner_text())[1])
            assert abs(median - app.alignments.frame("blurry/0000.png").median_error) < 1e-3
            assert f"over {kept} blocks (reference: ground-truth camera)" in aligned.inner_text()
            slider = _row(page, "τ_L").get_by_role("slider")
            slider.focus()
            slider.press("Home")
            expect(slider).to_have_attribute("aria-valuenow", "0")
            expect(page.get_by_text("kept: 0 blocks")).to_be_visible()
            expect(page.get_by_text("0 blocks kept by the filter, alignment needs 12")).to_be_visible()
            assert app.state.quality.tau_loss == 0.0
            page.get_by_role("button", name="Defaults", exact=True).click()
            expect(page.get_by_text(f"kept: {kept} blocks")).to_be_visible()

            page.set_input_files("input[type='file'][accept='image/*']", str(folder / "blurry" / "0000.png"))
            expect(_row(page, "Frame").locator("input:not([type='hidden'])")).to_have_value("upload/0000.png")
            expect(page.get_by_text("not extracted yet")).to_be_visible()
            assert [e.name for e in app.state.entries()] == ["blurry/0000.png", "upload/0000.png"]
            # A click on blurry/0000.png's camera frustum in the 3D view opens it again: the
            # viewer is put behind that camera, looking at its centre, and the canvas centre clicked.
            truth = {f.name: f.pose for f in app.state.dataset.truth.frames}
            camera = truth["blurry/0000.png"].inverse()
            d = 25.0 * app.state.dataset.pattern.square_length_m
            for client in server.get_clients().values():
                client.camera.position = camera.t - d * camera.R[:, 2] + 0.15 * d * camera.R[:, 0]
                client.camera.look_at = camera.t
            box = page.locator("canvas").first.bounding_box()
            for _ in range(5):  # the client may still be moving its camera: click again until it opens
                page.wait_for_timeout(1000)
                page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
                if app.state.view().entry.name == "blurry/0000.png":
                    break
            expect(_row(page, "Frame").locator("input:not([type='hidden'])")).to_have_value("blurry/0000.png")
            expect(page.get_by_text(f"kept: {kept} blocks")).to_be_visible()

            page.get_by_role("tab", name="Block").click()
            _row(page, "Jump to").locator("input:not([type='hidden'])").click()
            page.get_by_role("option", name="highest loss").click()
            expect(page.get_by_text(re.compile(r"block #\d+ feature"))).to_be_visible()
            assert app.state.selected is not None
            ratio = app.state.view().result.blocks.blur_per_square[app.state.selected]
            expect(page.get_by_text(f"blur / square side {ratio:.2f}")).to_be_visible()
            page.get_by_role("tab", name="Errors").click()
            expect(page.get_by_text(re.compile(r"global alignment \(reference: ground-truth camera\): star "
                                               r"centre minus x_G"))).to_be_visible()
            page.get_by_role("tab", name="Frame").click()
            page.add_style_tag(content=".mantine-Notification-root { display: none !important; }")
            page.wait_for_timeout(500)
            SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(SCREENSHOT))

            folder_field = _row(page, "Folder").locator("input")
            folder_field.fill(str(tmp_path / "missing"))
            page.get_by_role("button", name="Open folder").click()
            expect(page.get_by_text("no such folder").filter(visible=True).first).to_be_visible()
            assert app.state.dataset.folder == folder and len(app.state.entries()) == 2
            expect(folder_field).to_have_value(str(folder))

            bad_pattern = tmp_path / "bad.yaml"
            bad_pattern.write_text("num_star_segments: 7\n")
            page.set_input_files("input[type='file'][accept='.yaml,.yml']", str(bad_pattern))
            refused = page.get_by_text(re.compile("Pattern refused.*num_star_segments"))
            expect(refused.filter(visible=True).first).to_be_visible()
            assert app.state.dataset.pattern_path == folder / "pattern.yaml" and app.state.results()

            page.get_by_role("tab", name="Ambiguity").click()
            expect(page.get_by_text(re.compile(r"own shift within ±1\.5 px"))).to_be_visible()
            scatter = _row(page, "per-block shift (px)").get_by_role("slider")
            scatter.focus()
            scatter.press("Home")
            expect(page.get_by_text(re.compile(r"own shift within ±0 px"))).to_be_visible()
            expect(page.get_by_text(re.compile(r"after global alignment: x_G = "))).to_be_visible()

            other = browser.new_page(viewport={"width": 1280, "height": 800})
            other.goto(f"http://127.0.0.1:{server.get_port()}/")
            expect(other.get_by_text(f"kept: {kept} blocks")).to_be_visible(timeout=30_000)
            expect(other.get_by_text(re.compile(r"done: \d+ of \d+ blocks accepted"))).to_be_visible()
            other.close()

            assert not errors, errors
    finally:
        app.close()
        server.stop()


_OPEN_WEBSOCKET = """async ([url, protocol]) => await new Promise((resolve) => {
    const ws = new WebSocket(url, protocol);
    ws.onopen = () => { ws.close(); resolve("open"); };
    ws.onerror = () => resolve("refused");
})"""


def test_foreign_page_cannot_connect_in_chromium(tmp_path: Path) -> None:
    """A page of another origin (another local web server: same address, another port) fails to
    open the app's websocket; the same script on the app's own page opens it."""
    import viser

    from app import serve

    (tmp_path / "hostile").mkdir()
    (tmp_path / "hostile" / "index.html").write_text("<html><body>hostile page</body></html>")
    hostile = ThreadingHTTPServer(("127.0.0.1", 0), partial(SimpleHTTPRequestHandler,
                                                            directory=str(tmp_path / "hostile")))
    threading.Thread(target=hostile.serve_forever, daemon=True).start()
    (tmp_path / "empty").mkdir()
    server, app = serve(tmp_path / "empty", None, 0)  # no dataset needed: the handshake is under test
    url = f"ws://127.0.0.1:{server.get_port()}"
    protocol = f"viser-v{viser.__version__}"
    try:
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=FLAGS)
            page = browser.new_page()
            page.goto(f"http://127.0.0.1:{hostile.server_address[1]}/")
            assert page.evaluate(_OPEN_WEBSOCKET, [url, protocol]) == "refused"
            page.goto(f"http://127.0.0.1:{server.get_port()}/")
            assert page.evaluate(_OPEN_WEBSOCKET, [url, protocol]) == "open"
            browser.close()
    finally:
        hostile.shutdown()
        app.close()
        server.stop()
