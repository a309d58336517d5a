"""The app's publish/subscribe: what changed (:class:`Topic`) and messages for the user
(:class:`Notice`).

Listeners are called from the thread that made the change (a viser callback or the run worker),
outside the state's lock; a listener that raises is logged and the others still run.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

log = logging.getLogger(__name__)


class Topic(str, Enum):
    """What changed; subscribers re-read the state they show."""

    FOLDER = "folder"
    FRAMES = "frames"
    CURRENT = "current"
    LIVE = "live"
    RESULT = "result"
    FILTER = "filter"
    SELECTION = "selection"
    RUN = "run"
    CALIBRATION = "calibration"


@dataclass(frozen=True)
class Notice:
    """A message for the user: ``level`` is ``info``, ``warning`` or ``error``."""

    level: str
    title: str
    text: str


class Events:
    """Topic and notice subscribers, and the notices sent so far."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._listeners: list[Callable[[Topic], None]] = []
        self._notice_listeners: list[Callable[[Notice], None]] = []
        self.notices: list[Notice] = []

    def subscribe(self, listener: Callable[[Topic], None]) -> None:
        """Call ``listener(topic)`` after every change (from the changing thread; keep it fast)."""
        with self._lock:
            self._listeners.append(listener)

    def subscribe_notices(self, listener: Callable[[Notice], None]) -> None:
        """Call ``listener(notice)`` for every message to the user."""
        with self._lock:
            self._notice_listeners.append(listener)

    def emit(self, *topics: Topic) -> None:
        """Tell every topic subscriber that ``topics`` changed."""
        with self._lock:
            listeners = list(self._listeners)
        for topic in topics:
            for listener in listeners:
                try:
                    listener(topic)
                except Exception:
                    log.exception("listener failed on %s", topic.value)

    def notify(self, level: str, title: str, text: str) -> Notice:
        """Record a message for the user and pass it to the notice subscribers."""
        notice = Notice(level, title, text)
        with self._lock:
            self.notices.append(notice)
            listeners = list(self._notice_listeners)
        for listener in listeners:
            try:
                listener(notice)
            except Exception:
                log.exception("notice listener failed")
        return notice
