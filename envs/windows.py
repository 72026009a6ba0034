"""Cutting a recording into consecutive, non-overlapping event windows (docs/method.md, "Windows and network inputs").

Three modes:

- ``time``: fixed duration ``size`` in microseconds, from the recording's start;
- ``count``: fixed number of events ``size`` (the last window may hold fewer); ``t_start`` is
  the first event's time and ``t_end`` the last event's time + 1 (end made exclusive);
- ``frames``: window k spans ``[T_{k*dt}, T_{(k+1)*dt})`` on a grid ``T`` with ``dt = size``
  grid steps (1 or 4 for MVSEC); events before ``T_0`` and from the last grid time on belong to
  no window. The grid (:func:`window_grid`) is the recording's ground-truth grid where it has
  one ("ground truth": GT-aligned windows), else its APS frame times where it has at least two
  frames ("frames"), else a fixed grid of ``FALLBACK_INTERVAL_US`` from its first event
  ("time"), so this mode works on every recording and ``dt = 4`` always means four intervals.

In every mode each delivered event belongs to exactly one window, and windows come in time
order. The iterator reads window by window through the reader, never the whole recording.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch

from envs.events import Events
from envs.readers.base import EventReader
from losses import EventBatch

__all__ = ["Window", "check_window_fits", "check_window_events", "MAX_WINDOW_EVENTS", "iter_windows", "window_bounds", "window_grid", "WINDOW_MODES", "FALLBACK_INTERVAL_US", "DEFAULT_WINDOW_SIZES"]

WINDOW_MODES = ("time", "count", "frames")
#: The ``frames`` grid's interval on a recording with neither ground truth nor frames (30 Hz).
FALLBACK_INTERVAL_US = 33_333
#: A window's size per mode where none is given: one grid step, 10 ms, 15,000 events.
DEFAULT_WINDOW_SIZES = {"frames": 1, "time": 10_000, "count": 15_000}


@dataclass(frozen=True, eq=False)
class Window:
    """One event window, from the reader to the loss: what :func:`iter_windows` yields and the
    env carries in ``info["window"]``.

    index: the window's place (from 0) in its recording or episode; ``t_start``, ``t_end``: int
    µs, the window ``[t_start, t_end)`` (an event stamped ``t_end`` is accepted as tau = 1);
    ``i_start``, ``i_end``: the recording's event indices it was read from (before any crop);
    ``events``: its events (:class:`~envs.events.Events`, with the sensor size of the frame they
    are in); ``flow_gt`` (2, H, W) float32 pixels over the window and ``flow_gt_valid`` (H, W)
    bool: the ground truth, where the recording has it (else None).

    :meth:`batch` gives what the losses consume (``losses.window_loss(flow, window)``);
    :meth:`cut`, :meth:`split`, :meth:`subsample` and :meth:`bin` give new windows. A window is
    read by its attributes (``window.events.x``, ``window.t_start``); it is not a dict (the
    earlier window dict's ``window["x"]`` raises a TypeError that says what to read instead).
    """

    index: int
    t_start: int
    t_end: int
    i_start: int
    i_end: int
    events: Events
    flow_gt: np.ndarray | None = None
    flow_gt_valid: np.ndarray | None = None

    @property
    def duration_us(self) -> int:
        return self.t_end - self.t_start

    @property
    def sensor_size(self) -> tuple[int, int]:
        """(height, width) of the frame the events and the ground truth are in."""
        return self.events.sensor_size

    def batch(self, device=None, dtype: torch.dtype = torch.float32) -> EventBatch:
        """The window as a batch of one, what the losses take (x, y pixels, tau in [0, 1])."""
        return EventBatch.from_windows([self], device=device, dtype=dtype)

    @classmethod
    def of(cls, events: Events, t_start: int, t_end: int, index: int = 0) -> "Window":
        """The window ``[t_start, t_end)`` holding ``events`` (no recording behind it: ``i_start``,
        ``i_end`` count its own events, from 0)."""
        return cls(int(index), int(t_start), int(t_end), 0, len(events), events)

    def cut(self, t_start: int, t_end: int) -> "Window":
        """The part ``[t_start, t_end)`` of the window, its own events (binary search on t): a
        part that ends where the window ends keeps the events stamped ``t_end`` too, as the
        window does. ``i_start``, ``i_end`` follow; the ground truth is kept only by a cut of the
        whole window (it is the flow over the whole window)."""
        t_start, t_end = int(t_start), int(t_end)
        i0, i1 = np.searchsorted(self.events.t, (t_start, t_end), side="left")
        if t_end == self.t_end:
            i1 = len(self.events)
        whole = (t_start, t_end) == (self.t_start, self.t_end)
        return Window(self.index, t_start, t_end, self.i_start + int(i0), self.i_start + int(i1),
                      self.events[int(i0):int(i1)], self.flow_gt if whole else None,
                      self.flow_gt_valid if whole else None)

    def split(self, parts: int) -> list["Window"]:
        """The window cut (:meth:`cut`) into ``parts`` consecutive parts of equal length (integer
        µs bounds ``t_start + duration * k // parts``): every event in exactly one part."""
        if int(parts) < 1:
            raise ValueError(f"splits must be >= 1, got {parts}")
        parts = int(parts)
        bounds = [self.t_start + self.duration_us * k // parts for k in range(parts)] + [self.t_end]
        return [self.cut(bounds[k], bounds[k + 1]) for k in range(parts)]

    def subsample(self, max_events: int, *, rounding: str = "nearest") -> "Window":
        """The window with at most ``max_events`` events, taken evenly along the (time-ordered)
        stream: indices ``np.linspace(0, n - 1, max_events)`` rounded to the nearest (``rounding=
        "nearest"``, the teacher's rule) or down (``"floor"``, the solver's and the finish's). The
        window itself where it holds no more; bounds and ground truth are kept."""
        n = len(self.events)
        if n <= max_events:
            return self
        pick = np.linspace(0, n - 1, int(max_events))
        if rounding == "nearest":
            pick = pick.round()
        elif rounding != "floor":
            raise ValueError(f"rounding must be 'nearest' or 'floor', got {rounding!r}")
        return dataclasses.replace(self, events=self.events[pick.astype(np.int64)])

    def bin(self, factor: int) -> "Window":
        """The window's events on a grid ``factor`` times coarser: pixel (x, y) to
        (x // factor, y // factor), the sensor ``ceil(H / factor)`` x ``ceil(W / factor)``;
        times, polarities and bounds kept, the ground truth (on the sensor grid) dropped."""
        f = int(factor)
        if f < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        height, width = self.sensor_size
        ev = self.events
        events = Events(np.asarray(ev.x) // f, np.asarray(ev.y) // f, ev.t, ev.p, (-(-height // f), -(-width // f)))
        return dataclasses.replace(self, events=events, flow_gt=None, flow_gt_valid=None)

    def __getitem__(self, key):
        """No longer a dict: a clear error for code written against the earlier window dict."""
        where = f"window.events.{key}" if key in ("x", "y", "t", "p") else f"window.{key}"
        raise TypeError(f"a Window is not a dict: read {where} (window[{key!r}] was the earlier window dict)")

    def __eq__(self, other) -> bool:
        if not isinstance(other, Window):
            return NotImplemented
        arrays = [(getattr(self.events, k), getattr(other.events, k)) for k in ("x", "y", "t", "p")]
        arrays += [(self.flow_gt, other.flow_gt), (self.flow_gt_valid, other.flow_gt_valid)]
        return ((self.index, self.t_start, self.t_end, self.i_start, self.i_end, self.sensor_size)
                == (other.index, other.t_start, other.t_end, other.i_start, other.i_end, other.sensor_size)
                and all(a is b or (a is not None and b is not None and np.array_equal(a, b)) for a, b in arrays))

    __hash__ = None  # mutable arrays inside

    def __repr__(self) -> str:
        gt = ", with ground truth" if self.flow_gt is not None else ""
        return f"Window({self.index}: [{self.t_start}, {self.t_end}) us, {len(self.events)} events{gt})"


def _check_mode(mode: str, size) -> None:
    if mode not in WINDOW_MODES:
        raise ValueError(f"window mode must be one of {WINDOW_MODES}, got {mode!r}")
    if not (isinstance(size, (int, np.integer)) and size > 0):
        raise ValueError(f"window size must be a positive integer for mode {mode!r}, got {size!r}")


def window_grid(reader: EventReader, fallback_interval_us: int = FALLBACK_INTERVAL_US) -> tuple[np.ndarray, str]:
    """The grid that ``frames`` windows follow and where it comes from.

    Returns ((K,) int64 µs, kind): the ground-truth grid ("ground truth"), else the APS frame
    times ("frames", at least two frames), else ``fallback_interval_us`` steps from the first
    event to past the last one ("time").
    """
    grid = reader.flow_timestamps()
    if grid is not None and len(grid) >= 2:
        return np.asarray(grid, np.int64), "ground truth"
    frames = reader.frame_timestamps()
    if frames is not None and len(frames) >= 2:
        return np.unique(np.asarray(frames, np.int64)), "frames"
    t0, t1 = reader.t_start, reader.t_end
    n = max(1, -(-(t1 - t0) // int(fallback_interval_us)))
    return t0 + int(fallback_interval_us) * np.arange(n + 1, dtype=np.int64), "time"


MAX_WINDOW_EVENTS = 5_000_000
"""The most events one window may hold by default (``EventFlowEnv(max_window_events=...)``).
Reading a window, its observation and its reward (L_HMC) take up to about 200 bytes per event
at their peak, the reward most (``python scripts/benchmark.py --only window-memory``), so the
default keeps one window under about 1 GB whatever a file holds; a window beyond it is refused
before its events are read."""


def check_window_events(n: int, limit: int | None, where: str) -> None:
    """ValueError when a window of ``n`` events exceeds ``limit`` (None: no bound)."""
    if limit is not None and n > limit:
        raise ValueError(
            f"{where} holds {n} events, more than the {limit} one window may hold (about {limit * 200 / 2**30:.1f} GB "
            f"to read and score it): cut shorter windows (--window-size, or --window count), or build the env "
            f"with max_window_events=N (None: no bound) where the memory is there")


def check_window_fits(reader: EventReader, mode: str, size: int) -> None:
    """ValueError when a ``time`` or ``count`` window of ``size`` is longer than the whole
    recording: its one window would be the recording cut short (:func:`window_bounds` gives that
    clipped window; the env refuses it, since a user asking for it has mistyped a size)."""
    span = {"time": (reader.t_end - reader.t_start, "us"), "count": (reader.num_events, "events")}.get(mode)
    if span is not None and span[0] > 0 and size > span[0]:
        raise ValueError(f"a {mode} window of {size} {span[1]} is longer than the whole recording ({span[0]} {span[1]}): "
                         f"its one window would be the recording cut short; choose a window size <= {span[0]}")


def window_bounds(
    reader: EventReader, mode: str, size: int, *, t_from: int | None = None
) -> np.ndarray:
    """All window bounds of a recording as (K, 4) int64 rows ``(t_start, t_end, i_start, i_end)``.

    mode/size as in the module docstring (``time``: µs, ``count``: events, ``frames``: grid
    steps). ``t_from`` starts the windowing later (µs; ``time`` and ``count`` modes start
    there, ``frames`` at the first grid time >= t_from).
    """
    _check_mode(mode, size)
    if mode == "time":
        t0 = reader.t_start if t_from is None else max(int(t_from), reader.t_start)
        n = max(0, -(-(reader.t_end - t0) // size))
        starts = t0 + size * np.arange(n, dtype=np.int64)
        ends = np.minimum(starts + size, reader.t_end)
        ts = np.concatenate([starts, ends[-1:]]) if n else np.zeros(0, np.int64)
    elif mode == "frames":
        grid, _ = window_grid(reader)
        if t_from is not None:
            grid = grid[grid >= t_from]
        ts = grid[::size]
        if len(ts) < 2:
            return np.zeros((0, 4), np.int64)
        starts, ends = ts[:-1], ts[1:]
    if mode in ("time", "frames"):
        if len(starts) == 0:
            return np.zeros((0, 4), np.int64)
        idx = np.array([reader.index_at(int(t)) for t in ts], np.int64)
        return np.stack([starts, ends, idx[:-1], idx[1:]], axis=1)
    # count
    i0 = 0 if t_from is None else reader.index_at(int(t_from))
    n = reader.num_events
    i_starts = np.arange(i0, n, size, dtype=np.int64)
    i_ends = np.minimum(i_starts + size, n)
    t_starts = np.array([reader.time_of(int(i)) for i in i_starts], np.int64)
    t_ends = np.array([reader.time_of(int(i) - 1) + 1 for i in i_ends], np.int64)
    return np.stack([t_starts, t_ends, i_starts, i_ends], axis=1) if len(i_starts) else np.zeros((0, 4), np.int64)


def iter_windows(
    reader: EventReader, mode: str = "time", size: int = DEFAULT_WINDOW_SIZES["time"], *, t_from: int | None = None
) -> Iterator[Window]:
    """Yield the recording's windows in order (see :func:`window_bounds` for the arguments).

    >>> for w in iter_windows(reader, "time", 10_000):   # 10 ms windows
    ...     image = count_image(w.events)
    """
    for k, (t_start, t_end, i_start, i_end) in enumerate(window_bounds(reader, mode, size, t_from=t_from)):
        yield Window(k, int(t_start), int(t_end), int(i_start), int(i_end), reader.events_range(i_start, i_end))
