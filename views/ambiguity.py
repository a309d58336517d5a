"""Teaching demo: the translational ambiguity of deconvolution and what resolves it.

A slider shifts the latent star image by delta and the kernel by -delta; the blurred image does
not change (its residual against delta = 0 is shown: zero up to rounding), while the star centre
moves with delta. The text explains how blurcalib pins the shift down.
"""

from __future__ import annotations

import cv2
import numpy as np
import viser

from state.demo import MAX_SHIFT, TILE_PX, AmbiguityDemo, ambiguity_demo
from views.common import Coalescer, grey_rgb, heat, hstack, label, upscale

PANEL_PX = 192

EXPLANATION = """\
**Why the star centre is ambiguous.** A blurred star is `k * L`: the latent star `L` convolved with
the PSF `k`. Moving the star by δ and the PSF by −δ gives exactly the same image,
`k(d + δ) * L(x − δ) = k * L` (the residual panel stays flat). A block's fit alone therefore
cannot say where the star is: any δ explains the pixels equally well.

**How blurcalib pins it down.**
1. **PSF re-centring**: after each fit the PSF is shifted so that its centroid sits on the kernel
   centre, and the block's homography moves by the same amount (`H ← T(c) H`). The star centre
   becomes the centre of the star's *time-averaged* image, a well-defined point.
2. **Local alignment**: neighbouring blocks share square corners. One translation per block makes
   the shared corners agree, removing the blocks' independent δ up to one shift of the whole
   frame.
3. **Global alignment** (next step): one camera model and pose must explain every block of every
   frame, which fixes the remaining per-frame shift against the sharp frames' calibration.
"""


def demo_image(demo: AmbiguityDemo) -> np.ndarray:
    """Latent star (centre marked), kernel (centroid marked), blurred image and residual."""
    s = PANEL_PX / TILE_PX
    latent = upscale(grey_rgb(demo.latent * 255.0), PANEL_PX)
    c0 = (round(s * (TILE_PX / 2 + 0.5)), round(s * (TILE_PX / 2 + 0.5)))
    c = (round(s * (demo.star_centre[0] + 0.5)), round(s * (demo.star_centre[1] + 0.5)))
    cv2.circle(latent, c0, 7, (0, 200, 255), 2, cv2.LINE_AA)
    cv2.drawMarker(latent, c, (255, 40, 40), cv2.MARKER_CROSS, 18, 3, cv2.LINE_AA)
    K = demo.kernel.shape[0]
    kernel = upscale(heat(demo.kernel), PANEL_PX)
    ks = PANEL_PX / K
    centre = (K - 1) / 2.0
    kc = (round(ks * (centre + 0.5)), round(ks * (centre + 0.5)))
    cc = (round(ks * (centre + demo.centroid[0] + 0.5)), round(ks * (centre + demo.centroid[1] + 0.5)))
    cv2.drawMarker(kernel, kc, (0, 200, 255), cv2.MARKER_CROSS, 16, 1, cv2.LINE_AA)
    cv2.circle(kernel, cc, 5, (255, 255, 255), 2, cv2.LINE_AA)
    blurred = upscale(grey_rgb(demo.blurred * 255.0), PANEL_PX)
    worst = float(np.abs(demo.residual).max())
    residual = upscale(grey_rgb(128.0 + demo.residual * 255.0 * 50.0), PANEL_PX)
    label(latent, "star L'", (6, 18), 0.5)
    label(kernel, "PSF k'", (6, 18), 0.5)
    label(blurred, "k' * L'", (6, 18), 0.5)
    label(residual, "k'*L' - k*L (x50)", (6, 18), 0.5)
    label(residual, f"max {worst:.0e}", (6, PANEL_PX - 10), 0.5)
    return hstack([latent, kernel, blurred, residual])


class AmbiguityPanel:
    """The delta sliders, the demo image and the explanation."""

    def __init__(self, server: viser.ViserServer, num_segments: int = 16) -> None:
        self.num_segments = num_segments
        gui = server.gui
        self.dx = gui.add_slider("δx (px)", min=-MAX_SHIFT, max=MAX_SHIFT, step=1, initial_value=0)
        self.dy = gui.add_slider("δy (px)", min=-MAX_SHIFT, max=MAX_SHIFT, step=1, initial_value=0)
        self.image = gui.add_image(demo_image(ambiguity_demo((0, 0), num_segments)),
                                   label="star shifted by δ, PSF by −δ", format="png")
        self.caption = gui.add_markdown("")
        gui.add_markdown(EXPLANATION)
        self._redraw = Coalescer(self._draw, 0.05, "ambiguity")
        self.dx.on_update(self._redraw.request)
        self.dy.on_update(self._redraw.request)
        self._redraw.request()

    def close(self) -> None:
        """Stop the redraw thread."""
        self._redraw.close()

    def _draw(self) -> None:
        demo = ambiguity_demo((int(self.dx.value), int(self.dy.value)), self.num_segments)
        self.image.image = demo_image(demo)
        x, y = demo.star_centre
        worst = float(np.abs(demo.residual).max())
        self.caption.content = (f"star centre at ({x:.0f}, {y:.0f}) px (moves with δ; blue ring: δ = 0) · "
                                f"PSF centroid at ({demo.centroid[0]:+.2f}, {demo.centroid[1]:+.2f}) px · "
                                f"blurred image unchanged: max |residual| = {worst:.1e}")
