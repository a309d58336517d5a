"""Tuning panel: the quality filter's thresholds as sliders, with kept and removed counts and the
alignment error they give.

Moving a slider re-filters every finished frame from its stored figures
(:func:`blurcalib.growth.quality.filter_frame`, milliseconds per frame); the frame view shows the
result (kept blocks are the ones breadth-first connected to the seed block). The kept blocks are
then aligned globally to the reference camera (:mod:`state.alignment`, a few milliseconds per
frame, cached), and the panel reports the residual error after alignment (px) for the current
frame and over every aligned frame (finished, passing the pre-filter and the orientation filter).
"""

from __future__ import annotations

import math

import viser

from blurcalib.growth.quality import QualitySettings
from blurcalib.io.text import count
from state import AppState, Topic
from state.alignment import AlignmentCache, AlignmentError
from state.blocks import filter_counts
from views.common import Coalescer, md


def alignment_lines(alignments: AlignmentCache, frame: str | None) -> list[str]:
    """Markdown lines: the alignment error of ``frame`` (None: no frame) and over the aligned frames."""
    choice = alignments.reference()
    if choice.reference is None:
        return [f"**alignment error**: – {md(choice.reason)}"]
    source = md(choice.reference.source)
    lines = []
    if frame is not None:
        try:
            a = alignments.frame(frame)
        except AlignmentError as exc:
            lines.append(f"**alignment error**: – {md(str(exc))} (reference: {source})")
        else:
            angle = math.degrees(a.angle_to_normal)
            lines.append(f"**alignment error** after global alignment: median {a.median_error:.3f} px, "
                         f"RMS {a.rms_error:.3f} px over {count(a.num_blocks, 'block')} "
                         f"(reference: {source}) · "
                         f"x_G ({a.translation[0]:+.3f}, {a.translation[1]:+.3f}) px, optical axis "
                         f"{angle:.1f}° from the target normal"
                         + ("" if a.orientation_ok else ": **ill-conditioned** (orientation filter)"))
    overview = alignments.overview()
    if overview is None:
        return lines
    left_out = []
    if overview.ill_conditioned:
        left_out.append(f"{len(overview.ill_conditioned)} ill-conditioned")
    if overview.failed:
        left_out.append(f"{len(overview.failed)} not aligned")
    if overview.dropped:
        left_out.append(f"{overview.dropped} dropped by the pre-filter")
    rest = f" ({', '.join(left_out)})" if left_out else ""
    if overview.aligned:
        lines.append(f"{count(len(overview.aligned), 'aligned frame')}: alignment median "
                     f"{overview.median_error:.3f} px, RMS {overview.rms_error:.3f} px over "
                     f"{count(overview.num_blocks, 'block')}{rest}")
    else:
        lines.append(f"all frames: none aligned{rest}")
    return lines


class TuningPanel:
    """Sliders for tau_BE, tau_L and the sigma_major pre-filter, and the counts they give."""

    def __init__(self, state: AppState, server: viser.ViserServer, alignments: AlignmentCache) -> None:
        self.state = state
        self.alignments = alignments
        q = state.quality
        gui = server.gui
        self.tau_be = gui.add_slider("τ_BE", min=0.0, max=0.5, step=0.01, initial_value=q.tau_be,
                                     hint="remove blocks whose PSF has more than this share of its energy "
                                          "in the kernel's outer two-pixel ring")
        self.tau_loss = gui.add_slider("τ_L", min=0.0, max=200.0, step=1.0, initial_value=q.tau_loss,
                                       hint="remove blocks whose mean squared residual exceeds this "
                                            "(grey levels²)")
        self.sigma = gui.add_slider("σ_major pre-filter", min=0.0, max=10.0, step=0.1,
                                    initial_value=q.min_sigma_major,
                                    hint="drop blurry frames whose median PSF σ_major in the centre region "
                                         "is below this (px); 0 (the default) keeps every frame, the "
                                         "paper used 3.8 for its camera")
        self.reset = gui.add_button("Defaults")
        self.counts = gui.add_markdown("")
        self.alignment = gui.add_markdown("")
        self._apply = Coalescer(self._refilter, 0.05, "tuning-refilter")
        self._redraw = Coalescer(self._show, 0.1, "tuning-counts")
        for slider in (self.tau_be, self.tau_loss, self.sigma):
            slider.on_update(self._on_slider)
        self.reset.on_click(self._on_reset)
        state.subscribe(self._on_change)
        self._redraw.request()

    def close(self) -> None:
        """Stop the threads."""
        self._apply.close()
        self._redraw.close()

    def _on_slider(self, event: viser.GuiEvent) -> None:
        if event.client is not None:
            self._apply.request()

    def _on_reset(self, _: viser.GuiEvent) -> None:
        d = QualitySettings()
        self.tau_be.value, self.tau_loss.value, self.sigma.value = d.tau_be, d.tau_loss, d.min_sigma_major
        self._apply.request()

    def _refilter(self) -> None:
        self.state.refilter(self.tau_be.value, self.tau_loss.value, self.sigma.value)

    def _on_change(self, topic: Topic) -> None:
        if topic in (Topic.FILTER, Topic.RESULT, Topic.CURRENT, Topic.FOLDER, Topic.FRAMES):
            self._redraw.request()

    def _show(self) -> None:
        view = self.state.view()
        q = self.state.quality
        lines = []
        if view is None or view.filter is None:
            lines.append("**kept**: – (run the frame to get its blocks)")
        else:
            c = filter_counts(view.filter)
            lines.append(f"**kept: {c.kept}** blocks · **removed: {c.removed}** "
                         f"(BE > τ_BE: {c.removed_be}, loss > τ_L: {c.removed_loss}, "
                         f"not connected: {c.disconnected}) · rejected by growth: {c.rejected}")
            sigma = view.filter.centre_sigma_major
            if view.entry.kind == "sharp":
                lines.append(f"frame pre-filter: median σ_major in the centre {sigma:.2f} px; a sharp "
                             "frame is not pre-filtered (blurry frames only)")
            else:
                verdict = "passes" if view.filter.frame_ok else "**dropped** (too little blur)"
                lines.append(f"frame pre-filter: median σ_major in the centre {sigma:.2f} px "
                             f"vs {q.min_sigma_major:g} px: frame {verdict}")
        totals = [(flt, name) for name, (_, flt, _) in self.state.results().items() if flt is not None]
        if totals:
            kept = sum(int(f.kept.sum()) for f, _ in totals)
            used = [f for f, _ in totals if f.frame_ok]
            passing = count(len(used), "frame") + (" passes" if len(used) == 1 else " pass")
            lines.append(f"{count(len(totals), 'finished frame')}: {count(kept, 'block')} kept; {passing} "
                         f"the pre-filter ({count(sum(int(f.kept.sum()) for f in used), 'block')})")
        self.counts.content = "\n\n".join(lines)
        frame = view.entry.name if view is not None and view.result is not None else None
        self.alignment.content = "\n\n".join(alignment_lines(self.alignments, frame))
