"""Why a frame was not seeded: where the tag search looked in it and what it found, for the frame
view to draw (:func:`blurcalib.growth.seed.search_tags`), computed once per frame."""

from __future__ import annotations

import threading

from blurcalib.growth.seed import TagSearch, search_tags
from blurcalib.io.frames import FrameError
from blurcalib.io.record import FrameStatus
from state.app_state import AppState
from state.events import Topic


class TagSearchCache:
    """The tag search of each frame whose status is ``not_seeded``, cached until the folder or
    the pattern changes."""

    def __init__(self, state: AppState) -> None:
        self.state = state
        self._lock = threading.Lock()
        self._cache: dict[str, TagSearch] = {}
        state.subscribe(self._on_change)

    def _on_change(self, topic: Topic) -> None:
        if topic is Topic.FOLDER:
            with self._lock:
                self._cache.clear()

    def search(self, name: str) -> TagSearch | None:
        """The search of frame ``name``; None when it was seeded, is not extracted yet or
        cannot be read."""
        entry = next((e for e in self.state.entries() if e.name == name), None)
        if entry is None or entry.record.status is not FrameStatus.NOT_SEEDED:
            return None
        with self._lock:
            if name in self._cache:
                return self._cache[name]
        try:
            image = self.state.image(name)
        except (FrameError, KeyError):
            return None
        found = search_tags(image)
        with self._lock:
            self._cache[name] = found
        return found
