"""The Hagenaars / Monash h5 layout (event_flow, HQF, converted UZH-FPV / ECD / MVSEC).

Layout read (docs/formats.md):

    events/xs, events/ys   (N,) int16 (any integer type accepted)   column, row
    events/ts              (N,) float64 seconds (an integer ts is taken as µs)
    events/ps              (N,) bool or 0/1 (-1/+1 accepted)
    attrs: sensor_resolution = (height, width); t0 (same unit as ts; subtracted); duration
    images/<name>          (H, W) uint8, attribute ``timestamp`` (same clock as ts)    [optional]
    flow_dt1/<name>, flow_dt4/<name>, HQF's flow/<name>
                           (2, H, W) float pixels, x then y, attribute ``timestamp`` = the END of
                           the map's interval                                           [optional]

Times: integer µs relative to t0 (``t_us = rint(ts * 1e6) - rint(t0 * 1e6)``; t0 defaults to
the first event's ts). Map names are sorted, so zero-padded names keep time order.

Ground-truth intervals, as the file states them: a map with a start attribute
(``timestamp_from``, or ``timestamp_start``; what converters write beside ``timestamp``) spans
``[timestamp_from, timestamp)``, the first map included. Without a start attribute a
``flow_dt1`` (or ``flow``) map whose timestamp is ``E_k`` spans ``[E_{k-1}, E_k)``: the first
map has no start and is not used, so a GT-aligned episode of such a file begins at ``E_0``
(the events before the first map's end are not delivered, nor those from the last map's end
on). A ``flow_dt4`` map ending at
``E`` spans 4 steps of the dt1 grid back from E (of the image timestamps when there is no dt1
group; of the dt4 group itself otherwise). ``flow_timestamp="start"`` reads the attribute as
the START instead (some converters write it that way): map k of dt1 then spans
``[T_k, T_{k+1})``. A map pixel is valid when it is finite and not both components are 0.
``flow_between`` returns a stored map when the window is exactly its interval, else scales or
chains the dt1 maps (:mod:`envs.readers.flowgt`).
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from envs.events import Events
from envs.readers._common import SortedColumn, check_finite, open_h5, require, seconds_to_us
from envs.readers.base import EventReader, FlowGT, FormatError
from envs.readers.flowgt import flow_from_displacements, valid_of

__all__ = ["HagenaarsReader", "FLOW_GROUPS"]

FLOW_GROUPS = ("flow_dt1", "flow_dt4", "flow")
#: Attributes that state where a flow map's interval starts (the first one found is used).
START_ATTRIBUTES = ("timestamp_from", "timestamp_start")


class HagenaarsReader(EventReader):
    """A Hagenaars / Monash h5 file (module docstring for the layout and conventions).

    flow_timestamp: "end" (docs/method.md convention) or "start": what a flow map's ``timestamp`` means.
    validate: check every window's events (bounds, time order).
    """

    layout = "hagenaars"

    def _check_layout(self) -> tuple[dict[str, int], np.ndarray]:
        """The lengths of the event datasets xs, ys, ts, ps and the ``sensor_resolution``
        attribute (height, width), once the file is checked to hold the layout (events of one
        length, a positive resolution); else the file is closed and a FormatError raised."""
        f = self._file
        try:
            require(
                f, self.path, "Hagenaars/Monash h5",
                {"events/xs": ("iuf", 1), "events/ys": ("iuf", 1), "events/ts": ("fiu", 1), "events/ps": ("biuf", 1)},
            )
            lengths = {k: f["events"][k].shape[0] for k in ("xs", "ys", "ts", "ps")}
            if len(set(lengths.values())) != 1:
                raise FormatError(f"{self.path}: event datasets differ in length: {lengths}")
            if "sensor_resolution" not in f.attrs:
                raise FormatError(f"{self.path}: missing file attribute 'sensor_resolution' (height, width)")
            res = np.asarray(f.attrs["sensor_resolution"]).ravel()
            if len(res) != 2 or (res <= 0).any():
                raise FormatError(f"{self.path}: attribute 'sensor_resolution' must be (height, width), got {res}")
        except Exception:
            f.close()
            raise
        return lengths, res

    def __init__(self, path: str | os.PathLike, *, flow_timestamp: str = "end", validate: bool = True) -> None:
        if flow_timestamp not in ("end", "start"):
            raise ValueError(f"flow_timestamp must be 'end' or 'start', got {flow_timestamp!r}")
        self.path = Path(path)
        self.name = self.path.stem
        self.validate = validate
        self._file = f = open_h5(self.path, "Hagenaars/Monash h5")
        lengths, res = self._check_layout()
        self.sensor_size = (int(res[0]), int(res[1]))
        self.num_events = lengths["ts"]
        self._ds = {k: f["events"][k] for k in ("xs", "ys", "ts", "ps")}
        ts = self._ds["ts"]
        self._seconds = ts.dtype.kind == "f"
        if "t0" in f.attrs:
            t0 = float(np.asarray(f.attrs["t0"]).ravel()[0])
            where = "attribute 't0'"
        elif self.num_events:
            t0 = float(ts[0])
            where = "events/ts"
        else:
            t0, where = 0.0, "t0"
        try:
            check_finite(np.float64(t0), str(self.path), where)
        except Exception:
            f.close()
            raise
        self.origin_us = int(np.rint(t0 * 1e6)) if self._seconds else int(t0)
        self._times = SortedColumn(lambda i0, i1: self._to_us(self._ds["ts"][i0:i1], offset=i0), self.num_events)
        try:
            last = self.num_events - 1
            if self.num_events:  # NaN first / last times: an error naming the file, not a bogus span
                self._to_us(ts[last : last + 1], offset=last)
        except Exception:
            f.close()
            raise
        first = int(self._to_us(ts[0:1])[0]) if self.num_events else 0
        self._t_start = min(0, first)
        self._t_end = (int(self._to_us(ts[self.num_events - 1 : self.num_events])[0]) + 1) if self.num_events else 1
        # frames and ground truth: names and timestamps only (the maps stay on disk)
        try:
            self._starts: dict[str, np.ndarray] = {}  # per flow group, when every map states its start
            self._image_names, self._image_t = self._group_times("images")
            self._maps: dict[str, tuple[list[str], np.ndarray]] = {}
            for g in FLOW_GROUPS:
                names, times = self._group_times(g)
                if names:
                    self._maps[g] = (names, times)
            self._intervals = self._build_intervals(flow_timestamp)
        except Exception:
            f.close()
            raise

    def _to_us(self, ts: np.ndarray, *, field: str = "events/ts", offset: int = 0) -> np.ndarray:
        """Times as stored -> int64 µs after t0; a NaN raises naming the file, field and index."""
        if self._seconds:
            return seconds_to_us(ts, self.origin_us, source=str(self.path), field=field, offset=offset)
        return np.asarray(ts).astype(np.int64) - np.int64(self.origin_us)

    def _group_times(self, group: str) -> tuple[list[str], np.ndarray | None]:
        if group not in self._file:
            return [], None
        g = self._file[group]
        names = sorted(k for k in g if isinstance(g[k], h5py.Dataset))
        stamps, starts = [], []
        for k in names:
            attrs = g[k].attrs
            if "timestamp" not in attrs:
                raise FormatError(f"{self.path}: dataset '/{group}/{k}' has no attribute 'timestamp'")
            stamps.append(float(np.asarray(attrs["timestamp"]).ravel()[0]))
            key = next((a for a in START_ATTRIBUTES if a in attrs), None)
            starts.append(float(np.asarray(attrs[key]).ravel()[0]) if key else np.nan)
        dtype = np.float64 if self._seconds else np.int64
        times = self._to_us(np.asarray(stamps, dtype), field=f"/{group} attribute 'timestamp'")
        if len(times) > 1 and (np.diff(times) < 0).any():
            raise FormatError(f"{self.path}: '/{group}' timestamps are not in name order")
        starts = np.asarray(starts, np.float64)
        if group in FLOW_GROUPS and len(starts) and np.isfinite(starts).all():
            start_us = self._to_us(starts.astype(dtype))
            if (start_us >= times).any():
                k = int(np.argmax(start_us >= times))
                raise FormatError(
                    f"{self.path}: '/{group}/{names[k]}' starts at or after its end "
                    f"({START_ATTRIBUTES[0]} >= timestamp)"
                )
            self._starts[group] = start_us
        return names, times

    def _build_intervals(self, mode: str) -> dict[tuple[int, int], tuple[str, str]]:
        """{(t_from, t_to): (group, name)} for every stored map, and the dt1 chain."""
        intervals: dict[tuple[int, int], tuple[str, str]] = {}
        dt1 = "flow_dt1" if "flow_dt1" in self._maps else ("flow" if "flow" in self._maps else None)
        self._chain = None  # (times (K+1,), names (K,)) for scaling / chaining
        stated = dt1 is not None and dt1 in self._starts
        if stated:  # each map's interval as the file states it, the first one included
            names, t = self._maps[dt1]
            starts = self._starts[dt1]
            for a, b, n in zip(starts, t, names):
                intervals[(int(a), int(b))] = (dt1, n)
            if (starts[1:] == t[:-1]).all():  # contiguous: one grid, and the maps chain
                self._chain = (np.concatenate([starts[:1], t]), names)
                self._grid = self._chain[0]
            else:  # gaps between maps: windows on every start and end, GT only where a map is
                self._grid = np.unique(np.concatenate([starts, t]))
        elif dt1 is not None:
            names, t = self._maps[dt1]
            if mode == "end":
                pairs = [(int(t[k - 1]), int(t[k]), names[k]) for k in range(1, len(names))]
                self._chain = (t, names[1:])
            else:
                pairs = [(int(t[k]), int(t[k + 1]), names[k]) for k in range(len(names) - 1)]
                self._chain = (t, names[:-1])
            for a, b, n in pairs:
                if b > a:
                    intervals[(a, b)] = (dt1, n)
        if not stated:
            self._grid = self._maps[dt1][1] if dt1 is not None else self._image_t
        if "flow_dt4" in self._starts:
            names, t = self._maps["flow_dt4"]
            for a, b, n in zip(self._starts["flow_dt4"], t, names):
                intervals.setdefault((int(a), int(b)), ("flow_dt4", n))
            if self._grid is None:
                self._grid = np.unique(np.concatenate([self._starts["flow_dt4"], t]))
        elif "flow_dt4" in self._maps:
            names, t = self._maps["flow_dt4"]
            grid = self._grid if self._grid is not None and len(self._grid) else t
            for k, n in enumerate(names):
                j = int(np.searchsorted(grid, t[k]))
                found = j < len(grid) and grid[j] == t[k]
                if mode == "end":
                    if found and j >= 4:
                        a, b = int(grid[j - 4]), int(t[k])
                    elif not found and k >= 1:
                        a, b = int(t[k - 1]), int(t[k])
                    else:
                        continue
                else:
                    if found and j + 4 < len(grid):
                        a, b = int(t[k]), int(grid[j + 4])
                    elif not found and k + 1 < len(names):
                        a, b = int(t[k]), int(t[k + 1])
                    else:
                        continue
                if b > a:
                    intervals.setdefault((a, b), ("flow_dt4", n))
            if self._grid is None:
                self._grid = t
        return intervals

    # -- events -----------------------------------------------------------------------------
    def index_at(self, t_us: int) -> int:
        return self._times.searchsorted(int(t_us))

    def time_of(self, index: int) -> int:
        i = int(index)
        return int(self._to_us(self._ds["ts"][i : i + 1])[0])

    def events_range(self, i_start: int, i_end: int) -> Events:
        i_start, i_end = max(0, int(i_start)), min(self.num_events, int(i_end))
        if i_end <= i_start:
            return Events.empty(self.sensor_size)
        d = self._ds
        return Events.create(
            d["xs"][i_start:i_end], d["ys"][i_start:i_end], self._to_us(d["ts"][i_start:i_end], offset=i_start),
            d["ps"][i_start:i_end], self.sensor_size,
            source=f"{self.path} (events {i_start}..{i_end})", validate=self.validate,
        )

    # -- ground truth -----------------------------------------------------------------------
    @property
    def has_flow(self) -> bool:
        return bool(self._intervals)

    def flow_timestamps(self) -> np.ndarray | None:
        """The dt1 ground-truth grid (map times), or None when the file has no flow."""
        return None if not self._intervals else self._grid

    def _read_map(self, group: str, name: str) -> np.ndarray:
        d = np.asarray(self._file[group][name], np.float64)
        if d.shape != (2,) + self.sensor_size:
            raise FormatError(
                f"{self.path}: dataset '/{group}/{name}' has shape {d.shape}, expected "
                f"(2, {self.sensor_size[0]}, {self.sensor_size[1]}) (x then y)"
            )
        return d

    def flow_between(self, t_start: int, t_end: int) -> FlowGT | None:
        """Flow over [t_start, t_end) µs: a stored map on an exact match, else from the dt1 maps."""
        hit = self._intervals.get((int(t_start), int(t_end)))
        if hit is not None:
            d = self._read_map(*hit)
            valid = valid_of(d)
            return np.where(valid, d, 0.0).astype(np.float32), valid
        if self._chain is None:
            return None
        times, names = self._chain
        group = "flow_dt1" if "flow_dt1" in self._maps else "flow"
        cache: dict[int, np.ndarray] = {}

        def get_map(i: int) -> np.ndarray:
            if i not in cache:
                cache[i] = self._read_map(group, names[i])
            return cache[i]

        return flow_from_displacements(get_map, times, t_start, t_end)

    # -- frames -----------------------------------------------------------------------------
    def frame_timestamps(self) -> np.ndarray | None:
        return self._image_t

    def frame(self, index: int) -> np.ndarray:
        if not self._image_names:
            return super().frame(index)
        return np.asarray(self._file["images"][self._image_names[int(index)]])

    def close(self) -> None:
        if getattr(self, "_file", None) is not None and self._file.id.valid:
            self._file.close()
