"""Two behaviours of the app's page that viser has no API for, added as one script.

viser 1.1 moves the 3D view with the arrow keys (and WASD/QE) from a ``keydown`` listener on
the document that skips only text fields; a focused slider thumb (``role="slider"``) is no text
field, so an arrow key on a slider both moved the slider and turned the camera. viser also reports
no clicks inside a GUI image. The script, run once per page:

- stops arrow, Home, End and Page keys whose target is a slider thumb at ``document.body``: the
  slider (React handles keys at its root, inside the body) still moves, the document never sees
  the key, so the camera stays;
- relays a click on an image whose label contains :data:`CLICK_MARK` to the text field labelled
  :data:`CLICK_FIELD` as ``click X, Y`` (fractions of the image's width and height, 0 to 1,
  from its top-left corner), the way typing into it would; the app reads it from there.

viser shows the script as HTML (:meth:`viser.GuiApi.add_html`), which does not run ``<script>``
elements: it runs from the ``onerror`` handler of an image that cannot load.
"""

from __future__ import annotations

import html

import viser

CLICK_MARK = "click a block to inspect it"
"""Text in the label of an image whose clicks are relayed (the frame view)."""
CLICK_FIELD = "Block at (px)"
"""Label of the text field that receives the clicks."""
CLICK_PREFIX = "click "
"""What a relayed click starts with: ``click 0.25000, 0.50000``."""

_SCRIPT = """
if (!window.__blurcalibPage) {
  window.__blurcalibPage = 1;
  var keys = ['ArrowLeft', 'ArrowRight', 'ArrowUp', 'ArrowDown', 'Home', 'End', 'PageUp', 'PageDown'];
  document.body.addEventListener('keydown', function (e) {
    var t = e.target;
    if (t && t.getAttribute && t.getAttribute('role') === 'slider' && keys.indexOf(e.key) >= 0) {
      e.stopPropagation();
    }
  });
  document.addEventListener('click', function (e) {
    var img = e.target;
    if (!img || img.tagName !== 'IMG' || !img.parentElement) return;
    var box = img.parentElement.parentElement;
    var label = box && box.querySelector('p');
    if (!label || label.textContent.indexOf(MARK) < 0) return;
    var r = img.getBoundingClientRect();
    var value = PREFIX + ((e.clientX - r.left) / r.width).toFixed(5) + ', '
      + ((e.clientY - r.top) / r.height).toFixed(5);
    var labels = Array.prototype.slice.call(document.querySelectorAll('label'));
    var field = labels.filter(function (l) { return l.textContent === FIELD; })[0];
    var row = field && field.closest('div[class*=Flex-root]');
    var input = row && row.querySelector('input');
    if (!input) return;
    Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, 'value').set.call(input, value);
    input.dispatchEvent(new Event('input', {bubbles: true}));
  }, true);
}
"""


def page_script() -> str:
    """The HTML that runs the script (an image that cannot load, with the script as its
    ``onerror`` handler)."""
    code = (_SCRIPT.replace("MARK", repr(CLICK_MARK)).replace("PREFIX", repr(CLICK_PREFIX))
            .replace("FIELD", repr(CLICK_FIELD)))
    code = " ".join(line.strip() for line in code.strip().splitlines())
    return f'<img src="data:," alt="" style="display:none" onerror="{html.escape(code, quote=True)}">'


def add_page_script(server: viser.ViserServer) -> viser.GuiHtmlHandle:
    """Add the script to the page of every client (once, before the panels)."""
    return server.gui.add_html(page_script())


def parse_click(text: str) -> tuple[float, float] | None:
    """``(u, v)`` fractions of a relayed click (:data:`CLICK_PREFIX`), or None for other text."""
    if not text.startswith(CLICK_PREFIX):
        return None
    try:
        u, v = (float(part) for part in text[len(CLICK_PREFIX):].split(","))
    except ValueError:
        return None
    return (u, v) if 0.0 <= u <= 1.0 and 0.0 <= v <= 1.0 else None
