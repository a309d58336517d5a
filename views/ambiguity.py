"""Teaching demo: the translational ambiguity of deconvolution and what resolves it.

A slider shifts the latent star image by delta and the kernel by -delta; the blurred image does
not change (its residual against delta = 0 is shown: zero up to rounding), while the star centre
moves with delta. A second figure shows how blurcalib pins the shift down on a whole target:
blocks whose star centres carry that delta plus a free shift each, after local alignment and
after global alignment (:func:`state.demo.alignment_demo`, which runs the engine's own
alignments).
"""

from __future__ import annotations

import cv2
import numpy as np
import viser

from state.demo import MAX_SHIFT, TILE_PX, AlignmentDemo, AmbiguityDemo, alignment_demo, ambiguity_demo
from views.common import Coalescer, grey_rgb, heat, hstack, titled, upscale

PANEL_PX = 192
ERROR_GAIN = 5.0
"""The alignment figure draws each block at its true place plus this many times its error."""
STEP_SCALE = 0.55
"""Scale of the alignment figure's panels relative to the demo camera's 640 x 480 px."""

EXPLANATION = """\
**Why the star centre is ambiguous.** A blurred star is `k * L`: the latent star `L` convolved with
the PSF `k` (in words: every point of the star smeared along the path the camera shook). Moving
the star by δ and the PSF by −δ gives exactly the same image,
`k(d + δ) * L(x − δ) = k * L` (in words: a star drawn δ to the right, smeared by a path that starts
δ further left, lands on the same pixels; the residual panel stays flat). A block's fit alone
therefore cannot say where the star is: any δ explains the pixels equally well.

**How blurcalib pins it down.**
1. **PSF re-centring**: after each fit the PSF is shifted so that its centroid `c` sits on the
   kernel centre, and the block's homography moves by the same amount, `H ← T(c) H` (in words:
   slide the PSF back to the middle and move the star by the same distance the other way, which
   leaves the image unchanged). The star centre becomes the centre of the star's
   *time-averaged* image, a well-defined point.
2. **Local alignment**: neighbouring blocks share square corners. One translation per block makes
   the shared corners agree, removing the blocks' independent δ up to one shift of the whole
   frame.
3. **Global alignment**: one camera model (calibrated from the sharp frames) and a pose must
   explain every block of the frame, which fixes the remaining shift `x_G` (in words: the one
   shift left over is found by asking where the calibrated camera says the target must be).

The figure below runs both alignments of the engine on a tilted target whose blocks carry the δ
above plus a shift of their own.
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
    return hstack([titled(latent, "star L' (moved +delta)", "red: its centre"),
                   titled(kernel, "PSF k' (moved -delta)", "white: its centroid"),
                   titled(blurred, "blurred image k' * L'", "the same for every delta"),
                   titled(residual, "k'*L' - k*L  (x50)", f"largest {worst:.0e}")])


def alignment_image(demo: AlignmentDemo, gain: float = ERROR_GAIN) -> np.ndarray:
    """The blocks after deconvolution, local alignment and global alignment, errors x ``gain``.

    True squares in grey, estimated squares in orange (drawn at ``truth + gain * error``), star
    centres as red dots.
    """
    w, h = demo.size
    panels = []
    for step in demo.steps:
        canvas = np.full((round(h * STEP_SCALE), round(w * STEP_SCALE), 3), 255, np.uint8)
        shown = demo.true_quads + gain * (step.quads - demo.true_quads)
        centres = demo.true_centres + gain * step.error
        for quad in demo.true_quads:
            cv2.polylines(canvas, [_pts(quad)], True, (190, 190, 190), 1, cv2.LINE_AA)
        for quad in shown:
            cv2.polylines(canvas, [_pts(quad)], True, (255, 140, 0), 1, cv2.LINE_AA)
        for c in centres:
            cv2.circle(canvas, tuple(int(v) for v in _pts(c[None])[0]), 2, (220, 30, 30), -1, cv2.LINE_AA)
        cv2.rectangle(canvas, (0, 0), (canvas.shape[1] - 1, canvas.shape[0] - 1), (200, 200, 200), 1)
        panels.append(titled(canvas, step.name, f"RMS error {step.rms:.3f} px"))
    return hstack(panels, background=255)


def _pts(xy: np.ndarray) -> np.ndarray:
    """px of the demo camera -> int32 canvas points (pixel centres at +0.5 before scaling)."""
    return np.round((np.asarray(xy) + 0.5) * STEP_SCALE - 0.5).astype(np.int32)


def alignment_caption(demo: AlignmentDemo) -> str:
    """The figures behind :func:`alignment_image`, one line per step."""
    deconv, local, aligned = demo.steps
    mean_left = local.error.mean(axis=0)
    return (f"{len(demo.true_centres)} blocks; each star centre carries δ = ({demo.shift[0]:+.0f}, "
            f"{demo.shift[1]:+.0f}) px plus its own shift within ±{demo.scatter_px:g} px. Errors drawn "
            f"×{ERROR_GAIN:g}.\n\n"
            f"- **after deconvolution**: RMS error {deconv.rms:.3f} px; shared corners disagree by "
            f"{deconv.corner_gap_rms:.3f} px RMS.\n"
            f"- **after local alignment**: corners agree to {local.corner_gap_rms:.3f} px, but the whole "
            f"target is still off by ({mean_left[0]:+.3f}, {mean_left[1]:+.3f}) px: RMS error "
            f"{local.rms:.3f} px.\n"
            f"- **after global alignment**: x_G = ({demo.x_g[0]:+.3f}, {demo.x_g[1]:+.3f}) px removed; "
            f"RMS error {aligned.rms:.3f} px (what is left is the fits' own corner noise, integrated "
            f"by the local alignment and amplified by how much a translation looks like a pose).")


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
        self.scatter = gui.add_slider("per-block shift (px)", min=0.0, max=3.0, step=0.1, initial_value=1.5,
                                      hint="each block's deconvolution may also pick its own shift, "
                                           "uniform within ± this")
        self.noise = gui.add_slider("corner noise (px)", min=0.0, max=0.1, step=0.005, initial_value=0.02,
                                    hint="error of each block's fitted square corners (std per axis)")
        self.draw_again = gui.add_button("New draw")
        self.steps = gui.add_image(alignment_image(alignment_demo((0, 0))), format="png",
                                   label="local and global alignment on a tilted target")
        self.steps_caption = gui.add_markdown("")
        self._seed = 0
        self._redraw = Coalescer(self._draw, 0.05, "ambiguity")
        for slider in (self.dx, self.dy, self.scatter, self.noise):
            slider.on_update(self._redraw.request)
        self.draw_again.on_click(self._on_draw_again)
        self._redraw.request()

    def close(self) -> None:
        """Stop the redraw thread."""
        self._redraw.close()

    def _on_draw_again(self, _: viser.GuiEvent) -> None:
        self._seed += 1
        self._redraw.request()

    def _draw(self) -> None:
        delta = (int(self.dx.value), int(self.dy.value))
        steps = alignment_demo(delta, float(self.scatter.value), float(self.noise.value), self._seed)
        self.steps.image = alignment_image(steps)
        self.steps_caption.content = alignment_caption(steps)
        demo = ambiguity_demo(delta, self.num_segments)
        self.image.image = demo_image(demo)
        x, y = demo.star_centre
        worst = float(np.abs(demo.residual).max())
        self.caption.content = (f"star centre at ({x:.0f}, {y:.0f}) px (moves with δ; blue ring: δ = 0) · "
                                f"PSF centroid at ({demo.centroid[0]:+.2f}, {demo.centroid[1]:+.2f}) px · "
                                f"blurred image unchanged: max |residual| = {worst:.1e}")
