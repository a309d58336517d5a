"""Block inspector and the scatter plots of the paper's ``fig:exp_real2``.

The inspector shows one block of the current frame: its observed window with the loss's pixels
outlined, the fitted model (:func:`blurcalib.deconv.blocks.render_model`, no re-fit), the residual and
the PSF, with its figures; a frame read back from its output folder keeps no fit, and shows its
observed window with the block's square outlined, and its PSF. The plots are loss vs blur size
(sigma_major) coloured by eccentricity and loss vs boundary energy coloured by sigma_major, with
the thresholds; kept blocks are dots, removed ones crosses, the selected one ringed; below them,
why blocks with a lower loss than kept ones were dropped (another rule did it). A block is chosen
by a click on it in the frame view, by its number or by a "jump to" choice (the extreme points); a
finished frame with no block selected opens on its first block, block 0.
"""

from __future__ import annotations

import cv2
import numpy as np
import viser
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from blurcalib.deconv.blocks import render_model
from blurcalib.io.results import BLUR_PER_SQUARE_LIMIT, BlockTable
from state import AppState, FrameView, Topic
from state.blocks import block_quads, lower_loss_removed
from views.common import Coalescer, grey_rgb, heat, hstack, label, placeholder, upscale

JUMPS = ("choose…", "highest loss", "lowest loss", "highest boundary energy", "largest blur (σ_major)",
         "longest blur for its square", "most eccentric")
PANEL_PX = 180


def _figures(view: FrameView) -> dict[str, np.ndarray]:
    blocks = view.result.blocks if view.result is not None else BlockTable.empty()
    return {name: getattr(blocks, name)
            for name in ("loss", "boundary_energy", "sigma_major", "eccentricity", "blur_per_square")}


def jump_target(view: FrameView, choice: str) -> int | None:
    """The block a "jump to" choice picks among the fitted blocks (None if there is none)."""
    f = _figures(view)
    loss = f["loss"]
    fitted = np.isfinite(loss)
    if not fitted.any():
        return None
    key = {"highest loss": loss, "lowest loss": -loss, "highest boundary energy": f["boundary_energy"],
           "largest blur (σ_major)": f["sigma_major"], "longest blur for its square": f["blur_per_square"],
           "most eccentric": f["eccentricity"]}.get(choice)
    if key is None:
        return None
    return int(np.argmax(np.where(fitted & np.isfinite(key), key, -np.inf)))


def stored_block_images(view: FrameView, index: int) -> np.ndarray:
    """Observed window (the block's square outlined) and PSF of block ``index`` of a frame read
    back from its files, whose fit (its window, mask and model) is not kept: the model and the
    residual panels say so."""
    blocks = view.result.blocks
    if not np.isfinite(blocks.loss[index]) or view.image is None:
        return placeholder(f"block {index} was not fitted (status {blocks.status[index]})",
                           (4 * PANEL_PX, PANEL_PX))
    square = block_quads(blocks.H[[index]])[0]
    h, w = view.image.shape
    margin = 0.25 * float(np.ptp(square, axis=0).max())
    x0, y0 = np.clip(np.floor(square.min(axis=0) - margin).astype(int), 0, [w - 1, h - 1])
    x1, y1 = np.clip(np.ceil(square.max(axis=0) + margin).astype(int) + 1, 1, [w, h])
    window = view.image[y0:y1, x0:x1]
    lo, hi = float(np.percentile(window, 1)), float(np.percentile(window, 99))
    observed = upscale(grey_rgb((window - lo) * 255.0 / max(hi - lo, 1.0)), PANEL_PX)
    s = PANEL_PX / window.shape[0]
    cv2.polylines(observed, [np.round((square - [x0 - 0.5, y0 - 0.5]) * s).astype(np.int32)], True,
                  (255, 220, 0), 1, cv2.LINE_AA)
    psf = upscale(heat(blocks.psf[index]), PANEL_PX)
    for panel, text in ((observed, "observed"), (psf, "PSF")):
        label(panel, text, (6, 18), 0.5)
    kept = placeholder("model: run the frame", (PANEL_PX, PANEL_PX))
    return hstack([observed, kept, placeholder("again to see it", (PANEL_PX, PANEL_PX)), psf])


def block_images(view: FrameView, index: int) -> np.ndarray:
    """Observed window (loss pixels outlined), model, residual and PSF of block ``index``; for a
    frame read back from its files, :func:`stored_block_images`."""
    result = view.result
    if result is None or view.image is None:
        return placeholder("no result", (4 * PANEL_PX, PANEL_PX))
    if result.growth is None:
        return stored_block_images(view, index)
    try:
        m = render_model(result.growth.fit, view.image, index)
    except ValueError as exc:
        return placeholder(str(exc), (4 * PANEL_PX, PANEL_PX))
    lo, hi = float(np.percentile(m.observed, 1)), float(np.percentile(m.observed, 99))
    gain = 255.0 / max(hi - lo, 1.0)
    observed = upscale(grey_rgb((m.observed - lo) * gain), PANEL_PX)
    mask = cv2.resize(m.mask.astype(np.uint8), observed.shape[1::-1], interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(observed, contours, -1, (255, 220, 0), 1)
    model = upscale(grey_rgb((m.model - lo) * gain), PANEL_PX)
    r = m.residual * m.mask
    span = max(3.0 * float(np.sqrt(np.mean(m.residual[m.mask] ** 2))) if m.mask.any() else 0.0, 5.0)
    residual = upscale((colormaps["RdBu_r"](np.clip(0.5 + 0.5 * r / span, 0, 1))[..., :3] * 255)
                       .astype(np.uint8), PANEL_PX)
    psf = upscale(heat(result.blocks.psf[index]), PANEL_PX)
    for panel, text in ((observed, "observed"), (model, "model"), (residual, f"residual ±{span:.0f}"),
                        (psf, "PSF")):
        label(panel, text, (6, 18), 0.5)
    return hstack([observed, model, residual, psf])


def scatter_plots(view: FrameView) -> np.ndarray:
    """``fig:exp_real2``: loss vs sigma_major (colour: eccentricity), loss vs BE (colour:
    sigma_major); kept blocks dots, removed crosses, the selected block ringed."""
    f = _figures(view)
    loss, be, sig, ecc = f["loss"], f["boundary_energy"], f["sigma_major"], f["eccentricity"]
    fitted = np.isfinite(loss) & (loss > 0)
    kept = view.filter.kept if view.filter is not None else np.zeros(len(loss), dtype=bool)
    fig = Figure(figsize=(8.8, 3.3), dpi=100, layout="constrained")
    canvas = FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    q = view.quality
    panels = ((axes[0], sig, ecc, "blur size σ_major (px)", "eccentricity", "viridis", (0.0, 1.0)),
              (axes[1], be, sig, "boundary energy", "σ_major (px)", "plasma", None))
    for ax, x, c, xlabel, clabel, cmap, clim in panels:
        lim = clim or (float(np.nanmin(c[fitted])) if fitted.any() else 0.0,
                       float(np.nanmax(c[fitted])) if fitted.any() else 1.0)
        sel_k, sel_r = fitted & kept, fitted & ~kept
        mappable = ax.scatter(x[sel_k], loss[sel_k], c=c[sel_k], cmap=cmap, vmin=lim[0], vmax=lim[1], s=14,
                              label="kept")
        ax.scatter(x[sel_r], loss[sel_r], c=c[sel_r], cmap=cmap, vmin=lim[0], vmax=lim[1], s=18, marker="x",
                   linewidths=1.0, label="removed")
        ax.axhline(q.tau_loss, color="0.3", ls="--", lw=0.8)
        if ax is axes[1]:
            ax.axvline(q.tau_be, color="0.3", ls="--", lw=0.8)
        if view.selected is not None and fitted[view.selected]:
            i = view.selected
            ax.scatter([x[i]], [loss[i]], s=160, facecolors="none", edgecolors="red", linewidths=1.8)
            ax.annotate(f"#{i}", (x[i], loss[i]), xytext=(6, 6), textcoords="offset points", color="red")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("loss (grey levels²)")
        fig.colorbar(mappable, ax=ax, label=clabel)
    axes[0].legend(loc="upper left", fontsize=8)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


class InspectPanel:
    """The block inspector and the two scatter plots of the current frame."""

    def __init__(self, state: AppState, server: viser.ViserServer) -> None:
        self.state = state
        gui = server.gui
        self.block = gui.add_number("Block #", 0, min=0, step=1, hint="index of the block in the frame")
        self.jump = gui.add_dropdown("Jump to", options=JUMPS)
        self.images = gui.add_image(placeholder("no block", (4 * PANEL_PX, PANEL_PX)),
                                    label="observed · model · residual · PSF", format="png")
        self.figures = gui.add_markdown("")
        self.plots = gui.add_image(placeholder("no result", (880, 330)),
                                   label="Loss against blur size and boundary energy", format="png")
        self.plots_note = gui.add_markdown("")
        self.block.on_update(self._on_block)
        self.jump.on_update(self._on_jump)
        self._redraw_block = Coalescer(self._draw_block, 0.1, "inspect-block")
        self._redraw_plots = Coalescer(self._draw_plots, 0.3, "inspect-plots")
        state.subscribe(self._on_change)

    def close(self) -> None:
        """Stop the redraw threads."""
        self._redraw_block.close()
        self._redraw_plots.close()

    def _on_change(self, topic: Topic) -> None:
        if topic in (Topic.CURRENT, Topic.RESULT, Topic.SELECTION, Topic.FOLDER):
            self._redraw_block.request()
        if topic in (Topic.CURRENT, Topic.RESULT, Topic.FILTER, Topic.SELECTION, Topic.FOLDER):
            self._redraw_plots.request()

    def _on_block(self, event: viser.GuiEvent) -> None:
        if event.client is not None:
            self.state.select_block(int(self.block.value))

    def _on_jump(self, event: viser.GuiEvent) -> None:
        if event.client is None or self.jump.value == JUMPS[0]:
            return
        view = self.state.view()
        target = jump_target(view, self.jump.value) if view is not None else None
        if target is not None:
            self.state.select_block(target)
        self.jump.value = JUMPS[0]

    def _draw_block(self) -> None:
        view = self.state.view()
        if view is None or view.result is None or not len(view.result.blocks):
            self.images.image = placeholder("run the frame, then choose a block", (4 * PANEL_PX, PANEL_PX))
            self.figures.content = ""
            return
        self.block.max = len(view.result.blocks) - 1
        if view.selected is None:
            self.state.select_block(0)
            view = self.state.view()
            if view is None or view.result is None or view.selected is None:
                return
        i = view.selected
        self.block.value = i
        b = view.result.blocks
        x, y = b.centre[i]
        status = str(view.filter.status[i] if view.filter is not None else b.status[i])
        lines = [f"**block #{i}** feature ({b.fx[i]}, {b.fy[i]}), id {b.feature_id[i]}: "
                 f"**{status.replace('_', ' ')}**",
                 f"star centre ({x:.2f}, {y:.2f}) px · loss {b.loss[i]:.1f} · "
                 f"BE {b.boundary_energy[i]:.3f} · "
                 f"σ_major {b.sigma_major[i]:.2f} px · σ_minor {b.sigma_minor[i]:.2f} px · "
                 f"eccentricity {b.eccentricity[i]:.2f} · orientation {np.degrees(b.orientation[i]):.0f}° · "
                 f"blur / square side {b.blur_per_square[i]:.2f} "
                 f"(from {BLUR_PER_SQUARE_LIMIT} stars are hard to locate)"]
        if view.truth is not None:
            row = np.flatnonzero(view.truth.feature_ids == b.feature_id[i])
            if len(row):
                ex, ey = np.array([x, y]) - view.truth.mean[row[0]]
                lines.append(f"error vs ground truth ({ex:+.3f}, {ey:+.3f}) px, "
                             f"|e| = {np.hypot(ex, ey):.3f} px; true blur length "
                             f"{view.truth.blur_length[row[0]]:.1f} px")
        self.images.image = block_images(view, i)
        self.figures.content = "  \n".join(lines)

    def _draw_plots(self) -> None:
        view = self.state.view()
        if view is None or view.result is None or not len(view.result.blocks):
            self.plots.image = placeholder("no result", (880, 330))
            self.plots_note.content = ""
            return
        self.plots.image = scatter_plots(view)
        low = lower_loss_removed(view.result.blocks, view.filter) if view.filter is not None else {}
        self.plots_note.content = "" if not low else (
            f"**{sum(low.values())} crosses lie below kept dots**: their loss is low, but another rule "
            "dropped them: " + ", ".join(f"{reason} ({n})" for reason, n in low.items()) + ".")
