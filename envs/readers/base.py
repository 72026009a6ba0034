"""The reader interface every recording format implements.

A reader streams one recording from disk: it knows the sensor size and the time span,
returns the events of any time interval or index range without loading the rest, and, where
the format has them, ground-truth flow for an interval and intensity frames.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from envs.events import MAX_SENSOR_SIDE, Events

__all__ = ["EventReader", "ArrayReader", "FlowGT", "FormatError"]


class FormatError(ValueError):
    """A file that is not in the expected layout; the message names the file and the dataset."""


# (flow, valid): flow (2, H, W) float32 pixels of displacement over the interval; valid (H, W) bool.
FlowGT = tuple[np.ndarray, np.ndarray]


class EventReader(ABC):
    """One recording. Subclasses implement the abstract members; the rest has defaults.

    Attributes every reader sets:
        name: short identifier (file stem or sequence name)
        sensor_size: (height, width) pixels
        num_events: total number of events
    """

    name: str = "recording"
    num_events: int

    @property
    def sensor_size(self) -> tuple[int, int]:
        return getattr(self, "_sensor_size", None)

    @sensor_size.setter
    def sensor_size(self, value) -> None:
        """Every reader's size passes here: a size a file declares is checked when it is opened
        (positive, at most ``MAX_SENSOR_SIDE`` a side), before any image of that size is made."""
        if value is None:  # not known yet (a header without geometry, size picked from the events later)
            self._sensor_size = None
            return
        where = getattr(self, "path", None) or getattr(self, "name", "recording")
        try:
            height, width = (int(v) for v in value)
        except (TypeError, ValueError):
            raise FormatError(f"{where}: sensor size {value!r} is not two whole numbers (height, width)") from None
        if not (0 < height <= MAX_SENSOR_SIDE and 0 < width <= MAX_SENSOR_SIDE):
            raise FormatError(f"{where}: declares a {height} x {width} sensor (height x width); a sensor side must be "
                              f"1 to {MAX_SENSOR_SIDE} pixels (a damaged or hostile file, or the wrong format)")
        self._sensor_size = (height, width)

    # --- events ------------------------------------------------------------------------
    @abstractmethod
    def events_range(self, i_start: int, i_end: int) -> Events:
        """Events with indices in [i_start, i_end)."""

    @abstractmethod
    def index_at(self, t_us: int) -> int:
        """Index of the first event with t >= t_us (num_events if none)."""

    @property
    def t_start(self) -> int:
        """Time (us) at which the recording starts (<= first event time); readers set
        ``_t_start`` or override this."""
        return self._t_start

    @property
    def t_end(self) -> int:
        """Exclusive end time (us): every event has t < t_end; readers set ``_t_end`` or
        override this."""
        return self._t_end

    def events_between(self, t_start: int, t_end: int) -> Events:
        """Events with t in [t_start, t_end) (µs)."""
        return self.events_range(self.index_at(t_start), self.index_at(t_end))

    def time_of(self, index: int) -> int:
        """Timestamp (us) of event ``index``."""
        return int(self.events_range(index, index + 1).t[0])

    # --- ground truth and frames (optional) ---------------------------------------------
    @property
    def has_flow(self) -> bool:
        return False

    def flow_timestamps(self) -> np.ndarray | None:
        """(K,) int64 us: the ground-truth time grid (e.g. frame times), or None.

        Ground-truth-aligned windows span [T_k, T_{k+dt}).
        """
        return None

    def flow_between(self, t_start: int, t_end: int) -> FlowGT | None:
        """Ground-truth flow over [t_start, t_end), or None when the recording has none there."""
        return None

    def frame_timestamps(self) -> np.ndarray | None:
        """(F,) int64 us of the intensity frames, or None."""
        return None

    def frame(self, index: int) -> np.ndarray:
        """Intensity frame ``index`` as (H, W) uint8 or float32."""
        raise KeyError(f"{self.name}: this recording has no frames")

    # --- lifecycle ---------------------------------------------------------------------
    def close(self) -> None:  # noqa: B027 - a reader without open files has nothing to close
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        h, w = self.sensor_size
        return (
            f"{type(self).__name__}({self.name!r}, {h}x{w}, {self.num_events} events, "
            f"t=[{self.t_start}, {self.t_end}) us)"
        )


class ArrayReader(EventReader):
    """A recording held in memory (simulator output, tests, small files).

    events: the whole stream; t_range: optional (t_start, t_end) us, defaults to the events'.
    flow_fn: optional callable (t_start, t_end) -> FlowGT | None for exact ground truth.
    flow_times: optional (K,) int64 us ground-truth grid for aligned windows.
    """

    def __init__(
        self,
        events: Events,
        *,
        name: str = "memory",
        t_range: tuple[int, int] | None = None,
        flow_fn=None,
        flow_times: np.ndarray | None = None,
        frames: np.ndarray | None = None,
        frame_times: np.ndarray | None = None,
    ) -> None:
        self.events = events
        self.name = name
        self.sensor_size = events.sensor_size
        self.num_events = len(events)
        if t_range is None:
            t_range = (int(events.t[0]), int(events.t[-1]) + 1) if len(events) else (0, 1)
        self._t_range = (int(t_range[0]), int(t_range[1]))
        self._flow_fn = flow_fn
        self._flow_times = None if flow_times is None else np.asarray(flow_times, np.int64)
        self._frames = frames
        self._frame_times = None if frame_times is None else np.asarray(frame_times, np.int64)

    def events_range(self, i_start: int, i_end: int) -> Events:
        return self.events[int(i_start) : int(i_end)]

    def index_at(self, t_us: int) -> int:
        return int(self.events.index_at(t_us))

    @property
    def t_start(self) -> int:
        return self._t_range[0]

    @property
    def t_end(self) -> int:
        return self._t_range[1]

    def time_of(self, index: int) -> int:
        return int(self.events.t[index])

    @property
    def has_flow(self) -> bool:
        return self._flow_fn is not None

    def flow_timestamps(self) -> np.ndarray | None:
        return self._flow_times

    def flow_between(self, t_start: int, t_end: int) -> FlowGT | None:
        return None if self._flow_fn is None else self._flow_fn(int(t_start), int(t_end))

    def frame_timestamps(self) -> np.ndarray | None:
        return self._frame_times

    def frame(self, index: int) -> np.ndarray:
        if self._frames is None:
            return super().frame(index)
        return self._frames[index]
