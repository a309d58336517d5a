"""Tuning panel: the quality filter's thresholds as sliders, with kept and removed counts and the
alignment error they give.

Moving a slider re-filters every finished frame from its stored figures
(:func:`blurcalib.growth.quality.filter_frame`, milliseconds per frame); the frame view shows the
result (kept blocks are the ones breadth-first connected to the seed block). The kept blocks are
then aligned globally to the reference camera (:mod:`state.alignment`, a few milliseconds per
frame, cached), and the panel reports the residual error after alignment (px) for the current
frame and over every aligned frame (finished, passing the pre-filter and the orientation filter).

The sliders span the finished frames' own figures (:func:`state.blocks.filter_ranges`): τ_L on a
logarithmic scale (the slider moves ``log10 τ_L``, its marks read τ_L), τ_BE and the σ_major
pre-filter linearly; the selected block's loss and boundary energy and the current frame's
σ_major are marked on them.
"""

from __future__ import annotations

import math

import numpy as np
import viser
from viser._messages import GuiSliderMark

from blurcalib.growth.quality import QualitySettings
from blurcalib.io.record import FrameStatus
from blurcalib.io.text import count
from state import AppState, FrameView, Topic
from state.alignment import AlignmentCache, AlignmentError
from state.blocks import (
    GROWTH_REASONS,
    FilterRanges,
    Range,
    effective_loss,
    filter_counts,
    filter_ranges,
    lower_loss_removed,
)
from views.common import Coalescer, md

LOSS_MARKS = (1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)
"""τ_L values labelled on its slider where they fall in its range."""


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


def count_lines(view: FrameView) -> list[str]:
    """Markdown: the current frame's blocks by outcome, each count saying what it counts."""
    if view.filter is None or view.result is None:
        if view.entry.record.status is FrameStatus.NOT_SEEDED:
            return ["**no blocks**: the frame was not seeded (its tag was not found; the frame view shows "
                    "where the search looked)"]
        return ["**kept**: – (run the frame to get its blocks)"]
    c = filter_counts(view.filter, view.result.blocks.status)
    lines = [f"**kept: {c.kept}** blocks · **removed by the filter: {c.removed}** (boundary energy > τ_BE: "
             f"{c.removed_be}, loss > τ_L: {c.removed_loss}, cut off from the largest group: "
             f"{c.disconnected})"]
    rejected = sum(c.rejected.values())
    if rejected:
        why = ", ".join(f"{GROWTH_REASONS.get(k, k.replace('_', ' '))}: {n}"
                        for k, n in sorted(c.rejected.items()))
        lines.append(f"**rejected by the growth: {rejected}** ({why}; drawn red)")
    if c.not_fitted:
        lines.append(f"**not fitted: {c.not_fitted}** (their square leaves the image; drawn grey where in "
                     "view)")
    low = lower_loss_removed(view.result.blocks, view.filter)
    if low:
        why = ", ".join(f"{reason}: {n}" for reason, n in low.items())
        lines.append(f"{count(sum(low.values()), 'block')} with a lower loss than some kept block "
                     f"{'was' if sum(low.values()) == 1 else 'were'} dropped for another reason ({why}): "
                     "a low loss alone does not keep a block.")
    return lines


def _loss_marks(rng: Range, marked: list[tuple[float, str]]) -> tuple[GuiSliderMark, ...]:
    """The τ_L slider's marks: round values in its range, then the ``marked`` (τ_L, label)."""
    lo, hi = math.log10(rng.lo), math.log10(rng.hi)
    marks = [GuiSliderMark(math.log10(v), f"{v:g}") for v in LOSS_MARKS if lo <= math.log10(v) <= hi]
    marks += [GuiSliderMark(min(max(math.log10(v), lo), hi), text) for v, text in marked if v > 0]
    return tuple(marks)


class TuningPanel:
    """Sliders for tau_BE, tau_L and the sigma_major pre-filter, and the counts they give."""

    def __init__(self, state: AppState, server: viser.ViserServer, alignments: AlignmentCache) -> None:
        self.state = state
        self.alignments = alignments
        q = state.quality
        gui = server.gui
        self.tau_be = gui.add_slider("τ_BE", min=0.0, max=0.3, step=0.005, initial_value=q.tau_be,
                                     hint="remove blocks whose PSF has more than this share of its energy "
                                          "in the kernel's outer two-pixel ring")
        self.tau_loss = gui.add_slider("log₁₀ τ_L", min=0.0, max=math.log10(400.0), step=0.01,
                                       initial_value=round(math.log10(q.tau_loss), 2),
                                       hint="remove blocks whose mean squared residual exceeds τ_L (grey "
                                            "levels², in the frame's noise units); logarithmic: the marks "
                                            "read τ_L")
        self.sigma = gui.add_slider("σ_major pre-filter", min=0.0, max=10.0, step=0.05,
                                    initial_value=q.min_sigma_major,
                                    hint="drop blurry frames whose median PSF σ_major in the centre region "
                                         "is below this (px); 0 (the default) keeps every frame, the "
                                         "paper used 3.8 for its camera")
        self.reset = gui.add_button("Defaults")
        self.values = gui.add_markdown("")
        self.counts = gui.add_markdown("")
        self.alignment = gui.add_markdown("")
        self._ranges: FilterRanges | None = None
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
        self.tau_be.value, self.sigma.value = d.tau_be, d.min_sigma_major
        self.tau_loss.value = round(math.log10(d.tau_loss), 2)
        self._apply.request()

    def tau_loss_value(self) -> float:
        """τ_L (grey levels²) the log slider stands at."""
        return float(10.0 ** self.tau_loss.value)

    def _refilter(self) -> None:
        self.state.refilter(self.tau_be.value, self.tau_loss_value(), self.sigma.value)

    def _on_change(self, topic: Topic) -> None:
        if topic in (Topic.FILTER, Topic.RESULT, Topic.CURRENT, Topic.FOLDER, Topic.FRAMES,
                     Topic.SELECTION):
            self._redraw.request()

    def _rescale(self, view: FrameView | None) -> None:
        """The sliders' ranges from the finished frames, their marks from the current frame and
        block."""
        q = self.state.quality
        finished = [(r.blocks, f) for r, f, _ in self.state.results().values()]
        ranges = filter_ranges(finished, q)
        loss_marked: list[tuple[float, str]] = []
        be_marked: list[GuiSliderMark] = []
        sigma_marked: list[GuiSliderMark] = []
        if view is not None and view.result is not None and len(view.result.blocks):
            if view.selected is not None and np.isfinite(view.result.blocks.loss[view.selected]):
                i = view.selected
                loss_marked.append((float(effective_loss(view.result.blocks, q)[i]), f"#{i}"))
                be = min(float(view.result.blocks.boundary_energy[i]), ranges.tau_be.hi)
                be_marked.append(GuiSliderMark(be, f"#{i}"))
            if view.filter is not None and view.entry.kind == "blurry" and math.isfinite(
                    view.filter.centre_sigma_major):
                sigma_marked.append(GuiSliderMark(min(view.filter.centre_sigma_major, ranges.sigma.hi),
                                                  "this frame"))
        if ranges != self._ranges:
            self.tau_be.max = ranges.tau_be.hi
            self.tau_loss.min = math.floor(math.log10(ranges.tau_loss.lo) * 100) / 100
            self.tau_loss.max = math.ceil(math.log10(ranges.tau_loss.hi) * 100) / 100
            self.sigma.max = ranges.sigma.hi
            self._ranges = ranges
        self.tau_loss._marks = _loss_marks(ranges.tau_loss, loss_marked)
        self.tau_be._marks = tuple(be_marked) or None
        self.sigma._marks = tuple(sigma_marked) or None

    def _show(self) -> None:
        view = self.state.view()
        q = self.state.quality
        self._rescale(view)
        units = "in each frame's noise units" if q.loss_mode == "relative" else "absolute"
        self.values.content = (f"τ_BE **{q.tau_be:.3f}** · τ_L **{q.tau_loss:.3g}** grey levels² ({units}) "
                               f"· σ_major pre-filter **{q.min_sigma_major:.2f}** px")
        lines = [] if view is None else count_lines(view)
        if view is not None and view.filter is not None:
            sigma = view.filter.centre_sigma_major
            if view.entry.kind == "sharp":
                lines.append(f"frame pre-filter: median σ_major in the centre {sigma:.2f} px; a sharp "
                             "frame is not pre-filtered (blurry frames only)")
            else:
                verdict = "passes" if view.filter.frame_ok else "**dropped** (too little blur)"
                lines.append(f"frame pre-filter: median σ_major in the centre {sigma:.2f} px "
                             f"vs {q.min_sigma_major:g} px: frame {verdict}")
        totals = [flt for _, flt, _ in self.state.results().values() if flt is not None]
        if totals:
            kept = sum(int(f.kept.sum()) for f in totals)
            used = [f for f in totals if f.frame_ok]
            passing = count(len(used), "frame") + (" passes" if len(used) == 1 else " pass")
            lines.append(f"{count(len(totals), 'finished frame')}: {count(kept, 'block')} kept; {passing} "
                         f"the pre-filter ({count(sum(int(f.kept.sum()) for f in used), 'block')})")
        self.counts.content = "\n\n".join(lines)
        frame = view.entry.name if view is not None and view.result is not None else None
        self.alignment.content = "\n\n".join(alignment_lines(self.alignments, frame))
