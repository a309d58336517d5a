"""Frames panel: the folder and pattern fields, upload buttons (frames, pattern YAML), the frame list, the run
controls (Run frame, Run all, Cancel, progress) and the status line with the latest message and where the
frame's time went."""

from __future__ import annotations

import tempfile
from pathlib import Path

import viser

from blurcalib.io.frames import IMAGE_EXTENSIONS
from blurcalib.io.record import RUN_STATES, FrameRecord, FrameStatus
from blurcalib.io.text import count
from state import AppState, FrameView, Notice, RunProgress, Topic
from state.app_state import FRAME_KINDS
from state.calibration import CalibrationRunner
from state.folder import DatasetError
from views.common import Coalescer, md
from views.security import safe_upload_name

NOTICE_COLOURS = {"info": "blue", "warning": "yellow", "error": "red"}
NO_FRAMES = "(no frames)"
STAGE_NAMES = {"seed": "seeding", "neighbour": "seeding from a neighbour", "free": "free PSFs",
               "field": "path-PSF field", "final": "final fit", "judge": "second judgement",
               "fit_other": "other", "align": "alignment"}
"""Names of :meth:`blurcalib.io.record.FrameRecord.stage_seconds`'s stages."""


def stage_line(record: FrameRecord, least_s: float = 0.05) -> str:
    """Markdown: where a frame's time went, the stages of at least ``least_s`` seconds in the
    order they ran (:meth:`FrameRecord.stage_seconds`); empty when none took that long."""
    parts = [f"{STAGE_NAMES.get(k, k)} {v:.1f} s" for k, v in record.stage_seconds().items() if v >= least_s]
    return "time by stage: " + ", ".join(parts) if parts else ""


class FramesPanel:
    """The data and run controls; also shows every notice as a notification to all clients."""

    def __init__(self, state: AppState, server: viser.ViserServer,
                 calibration: CalibrationRunner | None = None) -> None:
        self.state = state
        self.server = server
        self.calibration = calibration
        self._uploads = tempfile.TemporaryDirectory(prefix="blurcalib-uploads-")
        self._last_notice: Notice | None = None
        self._shown_pattern = ""  # the pattern in use, as the Pattern field shows it
        gui = server.gui
        folder = (state.dataset.source or state.dataset.folder) if state.dataset is not None else ""
        with gui.add_folder("Data"):
            self.path = gui.add_text("Folder", initial_value=str(folder),
                                     hint="a folder of frames, or a video file (mp4, avi, mkv, mov)")
            self.pattern = gui.add_text("Pattern", initial_value="",
                                        hint="pattern YAML; shows the one in use; empty: pattern.yaml in the "
                                             "folder or its parent")
            self.open = gui.add_button("Open folder", icon=viser.Icon.FOLDER_OPEN)
            self.upload = gui.add_upload_button("Upload frame", icon=viser.Icon.UPLOAD, mime_type="image/*",
                                                hint="add an image file to the open dataset")
            self.upload_pattern = gui.add_upload_button(
                "Upload pattern", icon=viser.Icon.UPLOAD, mime_type=".yaml,.yml",
                hint="extract with this pattern YAML (the reference tool's format); with no folder "
                     "open, start a dataset of uploaded frames")
            self.frame = gui.add_dropdown("Frame", options=(NO_FRAMES,))
            self.kind = gui.add_dropdown("Kind", options=FRAME_KINDS,
                                         hint="sharp frames use a 7 px PSF window, blurry ones 17 px")
            self.run = gui.add_button("Run frame", icon=viser.Icon.PLAYER_PLAY)
            self.run_all = gui.add_button("Run all", icon=viser.Icon.PLAYER_TRACK_NEXT)
            self.cancel = gui.add_button("Cancel", icon=viser.Icon.PLAYER_STOP, color="red", disabled=True)
            self.progress = gui.add_progress_bar(0.0, animated=False)
            self.status = gui.add_markdown("")
        with gui.add_folder("All frames", expand_by_default=False):
            self.table = gui.add_markdown("")
        self.open.on_click(self._on_open)
        self.upload.on_upload(self._on_upload)
        self.upload_pattern.on_upload(self._on_upload_pattern)
        self.frame.on_update(self._on_frame)
        self.kind.on_update(self._on_kind)
        self.run.on_click(lambda _: self.state.run_frame())
        self.run_all.on_click(lambda _: self.state.run_all())
        self.cancel.on_click(lambda _: self.state.cancel())
        self._redraw = Coalescer(self._refresh, 0.1, "frames-panel")
        state.subscribe(self._on_change)
        state.subscribe_notices(self._on_notice)
        self._redraw.request()

    def close(self) -> None:
        """Stop the redraw thread and delete uploaded files."""
        self._redraw.close()
        self._uploads.cleanup()

    def _on_change(self, topic: Topic) -> None:
        if topic in (Topic.FOLDER, Topic.FRAMES, Topic.CURRENT, Topic.RUN, Topic.RESULT, Topic.FILTER,
                     Topic.CALIBRATION):
            self._redraw.request()

    def _on_open(self, _: viser.GuiEvent) -> None:
        """Open the folder; the Pattern field counts only when the user changed it from the pattern
        in use (which it shows), so that another folder finds its own pattern.yaml."""
        typed = self.pattern.value.strip()
        given = typed if typed and typed != self._shown_pattern else None
        self.state.load_folder(self.path.value.strip(), given)

    def _on_frame(self, event: viser.GuiEvent) -> None:
        if event.client is None:
            return
        names = [f.name for f in self.state.entries()]
        if self.frame.value in names:
            self.state.select_frame(names.index(self.frame.value))

    def _on_kind(self, event: viser.GuiEvent) -> None:
        if event.client is not None and self.state.current >= 0:
            self.state.set_kind(self.state.current, self.kind.value)

    def _store(self, uploaded: viser.UploadedFile, suffixes: tuple[str, ...], title: str, kind: str
               ) -> Path | None:
        """Save an upload in its own temporary folder under a name that can be stored
        (:func:`views.security.safe_upload_name`); None (and an error notice) for a file of another
        type or one that cannot be written."""
        name = safe_upload_name(uploaded.name)
        if Path(name).suffix.lower() not in suffixes:
            self.state.notify("error", title, f"{name}: not {kind} (expected {', '.join(suffixes)})")
            return None
        path = Path(tempfile.mkdtemp(dir=self._uploads.name)) / name
        try:
            path.write_bytes(uploaded.content)
        except OSError as exc:
            self.state.notify("error", title, f"{name}: cannot store the upload ({exc.strerror or exc})")
            return None
        return path

    def _on_upload(self, event: viser.GuiEvent) -> None:
        path = self._store(self.upload.value, IMAGE_EXTENSIONS, "Upload refused", "an image file")
        if path is None:
            return
        try:
            self.state.add_frame(path, f"upload/{path.name}")
        except DatasetError as exc:
            self.state.notify("error", "Upload refused", str(exc))

    def _on_upload_pattern(self, event: viser.GuiEvent) -> None:
        path = self._store(self.upload_pattern.value, (".yaml", ".yml"), "Pattern refused", "a YAML file")
        if path is not None:
            self.state.set_pattern(path)

    def _on_notice(self, notice: Notice) -> None:
        self._last_notice = notice
        for client in self.server.get_clients().values():
            client.add_notification(notice.title, notice.text, auto_close_seconds=8.0,
                                    color=NOTICE_COLOURS.get(notice.level, "blue"))
        self._redraw.request()

    def _refresh(self) -> None:
        state = self.state
        progress = state.progress()
        view = state.view()
        frames = [(f.name, f.kind, f.record.status, f.record.accepted, f.record.blocks)
                  for f in state.entries()]
        use = self.calibration.statuses() if self.calibration is not None else {}
        dataset = state.dataset
        folder = (dataset.source or dataset.folder) if dataset is not None else None
        names = tuple(f[0] for f in frames) or (NO_FRAMES,)
        with self.server.atomic():
            if folder is not None and self.path.value != str(folder):
                self.path.value = str(folder)
            in_use = str(dataset.pattern_path) if dataset is not None else ""
            if in_use != self._shown_pattern:
                self.pattern.value = self._shown_pattern = in_use
            if self.frame.options != names:
                self.frame.options = names
            if view is not None:
                self.frame.value = view.entry.name
                self.kind.value = view.entry.kind
            busy = progress.running
            self.run.disabled = busy or view is None
            self.run_all.disabled = busy or view is None
            self.cancel.disabled = not busy or progress.cancelling
            self.open.disabled = busy
            self.progress.value = 100.0 * progress.fraction
            self.progress.animated = busy
            self.status.content = self._status_text(view, progress)
            self.table.content = self._table(frames, use)

    def _status_text(self, view: FrameView | None, progress: RunProgress) -> str:
        lines = []
        if progress.running:
            expected = f" of ~{progress.frame_expected}" if progress.frame_expected else ""
            what = "cancelling" if progress.cancelling else "running"
            lines.append(f"**{what}** {md(progress.frame)}: {progress.frame_blocks}{expected} blocks "
                         f"decided (frame {min(progress.frames_done + 1, progress.frames_total)} of "
                         f"{progress.frames_total})")
        if view is not None:
            e, r = view.entry, view.entry.record
            if r.status is FrameStatus.OK:
                lines.append(f"**done**: {r.accepted} of {count(r.blocks, 'block')} accepted "
                             f"({md(e.name)}, {r.seconds:.1f} s)")
                if r.psf == "field":
                    lines.append("PSFs from the frame's **motion-path field** (its blur is long for "
                                 "its squares; docs/deconvolution.md)")
                if r.seeded_by == "neighbour":
                    lines.append(md(r.message))
                stages = stage_line(r)
                if stages:
                    lines.append(stages)
            elif r.status is FrameStatus.CANCELLED:
                lines.append(f"**cancelled**: {r.accepted} of {count(r.blocks, 'block')} accepted "
                             f"({md(e.name)})")
            elif r.status in RUN_STATES:
                if not progress.running:
                    lines.append(f"{md(e.name)} ({e.kind}): not extracted yet, press **Run frame**")
            else:
                lines.append(f"**{r.status.value.replace('_', ' ')}**: {md(r.message)}")
        notice = self._last_notice
        if notice is not None:
            lines.append(f"*{md(notice.title)}*: {md(notice.text)}")
        return "\n\n".join(lines)

    @staticmethod
    def _table(frames: list[tuple[str, str, FrameStatus, int, int]], use: dict[str, str]) -> str:
        """One row per frame; the last column is ``used`` by the calibration or why not."""
        rows = ["| frame | kind | status | accepted | calibration |", "|---|---|---|---|---|"]
        rows += [f"| {md(n)} | {k} | {s.value.replace('_', ' ')} | {a}/{b} | {md(use.get(n, ''))} |"
                 for n, k, s, a, b in frames]
        return "\n".join(rows)
