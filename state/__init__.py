"""The browser app's state: plain, thread-safe dataclasses with no viser import.

:class:`AppState` holds the folder, the frames and their per-frame results, the quality
thresholds, the selection and the run queue; views subscribe to its :class:`Topic` changes.
"""

from state.app_state import AppState
from state.entries import FrameEntry, FrameView
from state.events import Notice, Topic
from state.folder import Dataset, DatasetError, default_dataset, discover
from state.worker import RunProgress, RunSettings

__all__ = ["AppState", "Dataset", "DatasetError", "FrameEntry", "FrameView", "Notice", "RunProgress",
           "RunSettings", "Topic", "default_dataset", "discover"]
