"""The project's own recording format ("evflow h5"): writer and streaming reader.

Layout (format_version 1), all times int64 microseconds:

    /events/x    (N,) int16     column
    /events/y    (N,) int16     row
    /events/t    (N,) int64     µs, non-decreasing
    /events/p    (N,) int8      polarity in {-1, +1}
    /ms_to_idx   (M+1,) int64   ms_to_idx[m] = index of the first event with
                                t >= t_start_us + 1000 * m   (like DSEC's)
    /flow/flow   (K, 2, H, W) float32  ground-truth flow, pixels over [t_from, t_to)   [optional]
    /flow/valid  (K, H, W) bool
    /flow/t_from (K,) int64, /flow/t_to (K,) int64
    /frames/images (F, H, W) uint8, /frames/t (F,) int64                               [optional]

File attributes: format="evflow-h5", format_version=1, sensor_height, sensor_width,
t_start_us, t_end_us (exclusive), num_events, name, provenance (a JSON string).

Event datasets are chunked (64 Ki events) and gzip-compressed with the shuffle filter; flow
maps and frames are chunked one map per chunk. A window is read through ``ms_to_idx`` plus a
binary search inside one millisecond, so neither the file nor the time column is loaded.

The writer writes ``<name>.tmp-<host>-<pid>`` next to the target and renames it over the target only
after a successful close, so a crash or an exception never leaves a half-written file under
the final name; temporaries of killed writers are removed when the next writer of that name
starts (:mod:`envs.atomic`).

The reader checks the index on open (``ms_to_idx`` of the right length, non-decreasing, from 0 to
``num_events``, and consistent with the time column at sampled milliseconds; the first and last
events inside ``[t_start_us, t_end_us)``), and every window read through ``events_between``
holds only events of its time span; a file of another layout raises
:class:`envs.readers.base.FormatError`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

import h5py
import numpy as np

from envs.events import MAX_SENSOR_SIDE, MAX_SPAN_US, EventError, Events
from envs.outputs import Output
from envs.readers._common import check_flow_gt
from envs.readers.base import EventReader, FlowGT, FormatError
from envs.readers.flowgt import flow_from_displacements

__all__ = ["H5Writer", "H5Reader", "write_h5", "FORMAT_NAME", "FORMAT_VERSION"]

FORMAT_NAME = "evflow-h5"
FORMAT_VERSION = 1
EVENT_CHUNK = 1 << 16
_EVENT_DTYPES = {"x": np.int16, "y": np.int16, "t": np.int64, "p": np.int8}
_COMPRESSION = {"compression": "gzip", "compression_opts": 1, "shuffle": True}


class H5Writer:
    """Streams a recording into a project h5 file.

    sensor_size: (height, width). name: stored as the recording's name. provenance: any
    JSON-serialisable dict (simulator seed, source file, converter version...).
    t_start_us / t_end_us: the recording's time span; default first event / last event + 1.
    path: the file, or an :class:`envs.outputs.Output` the caller claimed before its work.
    overwrite, inputs, exclusive: as for :class:`envs.outputs.Output`, which claims the path
    (never an input, an existing file only with overwrite; exclusive: one writer at a time).
    """

    def __init__(
        self,
        path: str | os.PathLike | Output,
        sensor_size: tuple[int, int],
        *,
        name: str | None = None,
        provenance: dict | None = None,
        t_start_us: int | None = None,
        t_end_us: int | None = None,
        overwrite: bool = True,
        inputs: Iterable[tuple[str, str | os.PathLike | None]] = (),
        exclusive: bool = False,
    ) -> None:
        self.path = path.path if isinstance(path, Output) else Path(path)
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        if not all(0 < side <= MAX_SENSOR_SIDE for side in self.sensor_size):
            raise ValueError(f"{self.path}: sensor_size {self.sensor_size} (height, width) must be positive and at most "
                             f"{MAX_SENSOR_SIDE} pixels a side")
        self.name = name if name is not None else self.path.stem
        self.provenance = provenance or {}
        json.dumps(self.provenance)  # fail now, not at close
        self._t_start = t_start_us
        self._t_end = t_end_us
        # the checks, the temporary and the rename of every written file (envs.outputs)
        if isinstance(path, Output):  # claimed by the caller already (before its work)
            path.check_inputs(inputs)
            self._output = path
        else:
            self._output = Output(self.path, inputs=inputs, overwrite=overwrite, exclusive=exclusive)
        self._tmp = self._output.temporary
        try:
            self._file = h5py.File(self._tmp, "w")
        except BaseException:
            self._output.discard()
            raise
        group = self._file.create_group("events")
        self._events = {
            field: group.create_dataset(
                field, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(EVENT_CHUNK,), **_COMPRESSION
            )
            for field, dtype in _EVENT_DTYPES.items()
        }
        self._n = 0
        self._last_t: int | None = None
        self._first_t: int | None = None
        self._flows: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        self._flow_group = None
        self._frame_group = None
        self._closed = False

    # -- events ---------------------------------------------------------------------------
    def append_events(self, events: Events) -> None:
        """Append the next events of the stream (validated, continuing in time order)."""
        if events.sensor_size != self.sensor_size:
            raise EventError(
                f"{self.path}: events for sensor {events.sensor_size} appended to a "
                f"{self.sensor_size} recording"
            )
        n = len(events)
        if n == 0:
            return
        if np.issubdtype(events.x.dtype, np.floating):
            raise EventError(f"{self.path}: the project h5 stores integer pixel coordinates; got float x/y")
        h, w = self.sensor_size
        for field, values, size in (("x", events.x, w), ("y", events.y, h)):
            if values.min() < 0 or values.max() >= size:  # a reader that skipped validation
                i = int(np.flatnonzero((values < 0) | (values >= size))[0])
                raise EventError(f"{self.path}: field '{field}' must lie in [0, {size}) for sensor {h}x{w} (height x "
                                 f"width); event {self._n + i} of the stream holds {values[i]}")
        if self._last_t is not None and events.t[0] < self._last_t:
            raise EventError(
                f"{self.path}: field 't' must be non-decreasing across appends: "
                f"{events.t[0]} follows {self._last_t}"
            )
        for field, ds in self._events.items():
            ds.resize((self._n + n,))
            ds[self._n :] = getattr(events, field).astype(_EVENT_DTYPES[field], copy=False)
        if self._first_t is None:
            self._first_t = int(events.t[0])
        self._last_t = int(events.t[-1])
        self._n += n

    # -- ground truth and frames -----------------------------------------------------------
    def add_flow(self, t_from_us: int, t_to_us: int, flow: np.ndarray, valid: np.ndarray | None = None) -> None:
        """Ground-truth flow over [t_from, t_to): flow (2,H,W) pixels, valid (H,W) bool."""
        h, w = self.sensor_size
        flow = np.asarray(flow, np.float32)
        if flow.shape != (2, h, w):
            raise ValueError(f"{self.path}: flow must be (2, {h}, {w}), got {flow.shape}")
        valid = np.ones((h, w), bool) if valid is None else np.asarray(valid, bool)
        if valid.shape != (h, w):
            raise ValueError(f"{self.path}: flow valid mask must be ({h}, {w}), got {valid.shape}")
        if not t_to_us > t_from_us:
            raise ValueError(f"{self.path}: flow interval must have t_to > t_from, got [{t_from_us}, {t_to_us})")
        check_flow_gt(flow, valid, self.sensor_size, f"{self.path} (flow over [{t_from_us}, {t_to_us}) us)")
        if self._flow_group is None:
            g = self._file.create_group("flow")
            g.create_dataset("flow", (0, 2, h, w), np.float32, maxshape=(None, 2, h, w), chunks=(1, 2, h, w), **_COMPRESSION)
            g.create_dataset("valid", (0, h, w), bool, maxshape=(None, h, w), chunks=(1, h, w), **_COMPRESSION)
            g.create_dataset("t_from", (0,), np.int64, maxshape=(None,), chunks=(1024,))
            g.create_dataset("t_to", (0,), np.int64, maxshape=(None,), chunks=(1024,))
            self._flow_group = g
        g = self._flow_group
        k = g["t_from"].shape[0]
        for key, value in (("flow", flow), ("valid", valid), ("t_from", t_from_us), ("t_to", t_to_us)):
            g[key].resize((k + 1,) + g[key].shape[1:])
            g[key][k] = value

    def add_frame(self, t_us: int, image: np.ndarray) -> None:
        """An intensity frame taken at t_us: (H, W) uint8."""
        h, w = self.sensor_size
        image = np.asarray(image)
        if image.shape != (h, w):
            raise ValueError(f"{self.path}: frame must be ({h}, {w}), got {image.shape}")
        if self._frame_group is None:
            g = self._file.create_group("frames")
            g.create_dataset("images", (0, h, w), np.uint8, maxshape=(None, h, w), chunks=(1, h, w), **_COMPRESSION)
            g.create_dataset("t", (0,), np.int64, maxshape=(None,), chunks=(1024,))
            self._frame_group = g
        g = self._frame_group
        k = g["t"].shape[0]
        if k and t_us < g["t"][k - 1]:
            raise ValueError(f"{self.path}: frame times must be non-decreasing ({t_us} after {g['t'][k - 1]})")
        g["images"].resize((k + 1, h, w))
        g["images"][k] = image.astype(np.uint8)
        g["t"].resize((k + 1,))
        g["t"][k] = t_us

    # -- finishing -------------------------------------------------------------------------
    def _build_index(self, t_start: int, t_end: int) -> np.ndarray:
        n_ms = max(1, -(-(t_end - t_start) // 1000))
        bounds = t_start + 1000 * np.arange(n_ms + 1, dtype=np.int64)
        index = np.empty(n_ms + 1, np.int64)
        # one pass over the time column, a chunk at a time
        t_ds = self._events["t"]
        pos = 0
        for i0 in range(0, self._n, EVENT_CHUNK * 16):
            chunk = t_ds[i0 : i0 + EVENT_CHUNK * 16]
            upto = np.searchsorted(bounds, chunk[-1], side="right")  # bounds <= last t in chunk
            index[pos:upto] = i0 + np.searchsorted(chunk, bounds[pos:upto], side="left")
            pos = upto
        index[pos:] = self._n
        return index

    def close(self) -> None:
        """Write the index and attributes, then move the file to its final name."""
        if self._closed:
            return
        try:
            self._finish()
        except BaseException:
            self.abort()
            raise
        self._closed = True

    def _finish(self) -> None:
        t_start = self._t_start if self._t_start is not None else (self._first_t or 0)
        t_end = self._t_end if self._t_end is not None else ((self._last_t + 1) if self._last_t is not None else t_start + 1)
        if self._first_t is not None and (self._first_t < t_start or self._last_t >= t_end):
            raise EventError(
                f"{self.path}: events span [{self._first_t}, {self._last_t}] us, outside the "
                f"declared recording span [{t_start}, {t_end})"
            )
        if t_end - t_start > MAX_SPAN_US:
            raise EventError(f"{self.path}: the recording spans [{t_start}, {t_end}) us, more than {MAX_SPAN_US // 3_600_000_000} h: "
                             "corrupt times? (its millisecond index would not fit in memory)")
        index = self._build_index(t_start, t_end)
        self._file.create_dataset("ms_to_idx", data=index, chunks=(min(len(index), 1 << 14),), **_COMPRESSION)
        attrs = self._file.attrs
        attrs["format"] = FORMAT_NAME
        attrs["format_version"] = FORMAT_VERSION
        attrs["sensor_height"], attrs["sensor_width"] = self.sensor_size
        attrs["t_start_us"] = t_start
        attrs["t_end_us"] = t_end
        attrs["num_events"] = self._n
        attrs["name"] = self.name
        attrs["provenance"] = json.dumps(self.provenance)
        self._file.close()
        self._output.commit()

    def abort(self) -> None:
        """Discard everything written (the final path is left untouched)."""
        if self._closed:
            return
        try:
            if self._file.id.valid:
                self._file.close()
        finally:
            self._output.discard()
            self._closed = True

    def __enter__(self) -> "H5Writer":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_h5(path, events: Events, *, flows=(), frames=(), **kwargs) -> Path:
    """Write a whole recording at once. flows: iterable of (t_from, t_to, flow, valid);
    frames: iterable of (t_us, image). Returns the path."""
    with H5Writer(path, events.sensor_size, **kwargs) as writer:
        writer.append_events(events)
        for item in flows:
            writer.add_flow(*item)
        for t_us, image in frames:
            writer.add_frame(t_us, image)
    return Path(path)


class H5Reader(EventReader):
    """Streams a project h5 file (see the module docstring for the layout).

    Every read is validated against the file's attributes (sensor bounds, time order), so a
    corrupt or hand-made file fails with a message naming the file and the field.
    """

    def __init__(self, path: str | os.PathLike, *, validate: bool = True) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: no such file")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as err:
            raise FormatError(f"{self.path}: not a readable HDF5 file (truncated or corrupt?): {err}") from err
        f = self._file
        try:
            if f.attrs.get("format") != FORMAT_NAME:
                raise FormatError(
                    f"{self.path}: attribute 'format' is {f.attrs.get('format')!r}, expected "
                    f"{FORMAT_NAME!r} (is this a file of another layout? see envs.readers)"
                )
            for key in ("events/x", "events/y", "events/t", "events/p", "ms_to_idx"):
                if key not in f:
                    raise FormatError(f"{self.path}: missing dataset '/{key}'")
            for key in ("sensor_height", "sensor_width", "t_start_us", "t_end_us"):
                if key not in f.attrs:
                    raise FormatError(f"{self.path}: missing file attribute '{key}'")
            lengths = {k: f["events"][k].shape[0] for k in ("x", "y", "t", "p")}
            if len(set(lengths.values())) != 1:
                raise FormatError(f"{self.path}: event datasets differ in length: {lengths}")
        except Exception:
            f.close()
            raise
        self.validate = validate
        self.sensor_size = (int(f.attrs["sensor_height"]), int(f.attrs["sensor_width"]))
        self.num_events = lengths["t"]
        self.name = str(f.attrs.get("name", self.path.stem))
        self.provenance = json.loads(f.attrs.get("provenance", "{}"))
        self._t_start = int(f.attrs["t_start_us"])
        self._t_end = int(f.attrs["t_end_us"])
        self._ds = {k: f["events"][k] for k in ("x", "y", "t", "p")}
        self._ms_to_idx = f["ms_to_idx"][:]  # (duration_ms + 1) int64: small
        if "flow" in f:
            self._flow_from = f["flow/t_from"][:]
            self._flow_to = f["flow/t_to"][:]
        else:
            self._flow_from = self._flow_to = None
        self._frame_t = f["frames/t"][:] if "frames" in f else None
        try:
            self._check_index()
        except Exception:
            f.close()
            raise

    def _check_index(self, samples: int = 16) -> None:
        """Cheap checks that the index and the time span describe the events: ``ms_to_idx`` has
        one entry per millisecond of [t_start_us, t_end_us) plus one, runs from 0 to num_events
        without decreasing, and points at the right events at ``samples`` milliseconds; the first
        and last events lie inside the span. Raises FormatError naming the file and the field."""
        t_start, t_end, n = self._t_start, self._t_end, self.num_events
        if t_end <= t_start:
            raise FormatError(f"{self.path}: attribute 't_end_us' ({t_end}) must be greater than 't_start_us' ({t_start})")
        if n:
            t_first, t_last = self.time_of(0), self.time_of(n - 1)
            if t_first < t_start or t_last >= t_end:
                raise FormatError(
                    f"{self.path}: events span [{t_first}, {t_last}] us, outside the attributes "
                    f"[t_start_us, t_end_us) = [{t_start}, {t_end})"
                )
        index = self._ms_to_idx
        n_ms = max(1, -(-(t_end - t_start) // 1000))
        where = f"{self.path}: dataset '/ms_to_idx'"
        if index.ndim != 1 or len(index) != n_ms + 1:
            raise FormatError(
                f"{where} has shape {index.shape}, expected ({n_ms + 1},): one entry per millisecond of "
                f"[t_start_us, t_end_us) = [{t_start}, {t_end}) plus one (cut short or of another recording?)"
            )
        if index[0] != 0 or index[-1] != n:
            raise FormatError(f"{where} runs from {index[0]} to {index[-1]}, expected 0 to num_events = {n} (zeroed or corrupt?)")
        drops = np.flatnonzero(np.diff(index) < 0)
        if len(drops):
            m = int(drops[0]) + 1
            raise FormatError(f"{where} decreases at entry {m} ({index[m]} after {index[m - 1]}); it must be non-decreasing")
        if n == 0:
            return
        for m in np.unique(np.linspace(0, n_ms, samples).round().astype(np.int64)):
            self._check_entry(int(m))

    def _check_entry(self, m: int, block: np.ndarray | None = None, block_start: int = 0) -> None:
        """ms_to_idx[m] must be the first event with t >= t_start_us + 1000 m: the event before
        it earlier, the event at it not earlier. ``block``: the time column from ``block_start``
        when the caller has read it already."""
        i, bound, n = int(self._ms_to_idx[m]), self._t_start + 1000 * m, self.num_events
        a, b = max(i - 1, 0), min(i + 1, n)
        if block is not None and block_start <= a and b <= block_start + len(block):
            around = block[a - block_start : b - block_start]
        else:
            around = self._ds["t"][a:b]
        before = around[0] if i > 0 else None
        at = around[-1] if i < n else None
        if (before is not None and before >= bound) or (at is not None and at < bound):
            raise FormatError(
                f"{self.path}: dataset '/ms_to_idx' entry {m} = {i} does not point at the first event at or "
                f"after {bound} us (events {a}..{b - 1} have t = {around.tolist()}); the index is corrupt"
            )

    # -- events -----------------------------------------------------------------------------
    def index_at(self, t_us: int) -> int:
        if t_us <= self._t_start:
            return 0
        if t_us >= self._t_end:
            return self.num_events
        m = (int(t_us) - self._t_start) // 1000
        lo, hi = int(self._ms_to_idx[m]), int(self._ms_to_idx[m + 1])
        # one event either side, so the two index entries used are checked against the events
        a, b = max(lo - 1, 0), min(hi + 1, self.num_events)
        block = self._ds["t"][a:b]
        self._check_entry(m, block, a)
        self._check_entry(m + 1, block, a)
        return lo + int(np.searchsorted(block[lo - a : hi - a], t_us, side="left"))

    def events_range(self, i_start: int, i_end: int) -> Events:
        i_start, i_end = max(0, int(i_start)), min(self.num_events, int(i_end))
        if i_end <= i_start:
            return Events.empty(self.sensor_size)
        arrays = {k: ds[i_start:i_end] for k, ds in self._ds.items()}
        try:
            return Events.create(**arrays, sensor_size=self.sensor_size, source=f"{self.path} (events {i_start}..{i_end})", validate=self.validate)
        except OSError as err:  # pragma: no cover - h5py read errors surface above
            raise FormatError(f"{self.path}: could not read events {i_start}..{i_end}: {err}") from err

    def time_of(self, index: int) -> int:
        return int(self._ds["t"][int(index)])

    # -- ground truth and frames -----------------------------------------------------------
    @property
    def has_flow(self) -> bool:
        return self._flow_from is not None

    def flow_timestamps(self) -> np.ndarray | None:
        """The ground-truth grid: each map's t_from plus the last map's t_to."""
        if self._flow_from is None or len(self._flow_from) == 0:
            return None
        return np.append(self._flow_from, self._flow_to[-1])

    def flow_between(self, t_start: int, t_end: int) -> FlowGT | None:
        """Ground truth over [t_start, t_end).

        The stored map of exactly that interval when there is one; otherwise, when the stored
        maps tile time without gaps (t_to[k] == t_from[k+1]), the flow chained through them
        (nearest-neighbour propagation, linear scaling inside one interval: see
        ``envs.readers.flowgt``), e.g. dt = 4 windows from dt = 1 maps; else None.
        """
        stored = self.stored_flow(t_start, t_end)
        if stored is not None or self._flow_from is None:
            return stored
        g = self._file["flow"]
        if len(self._flow_from) and np.array_equal(self._flow_to[:-1], self._flow_from[1:]):
            return flow_from_displacements(
                lambda k: g["flow"][k], self.flow_timestamps(), t_start, t_end,
                get_valid=lambda k: g["valid"][k].astype(bool),
            )
        return None

    def stored_flow(self, t_start: int, t_end: int) -> FlowGT | None:
        """The stored map whose interval is exactly [t_start, t_end), else None."""
        if self._flow_from is None:
            return None
        hits = np.flatnonzero((self._flow_from == t_start) & (self._flow_to == t_end))
        if len(hits) == 0:
            return None
        g = self._file["flow"]
        k = int(hits[0])
        return g["flow"][k].astype(np.float32), g["valid"][k].astype(bool)

    def frame_timestamps(self) -> np.ndarray | None:
        return self._frame_t

    def frame(self, index: int) -> np.ndarray:
        if self._frame_t is None:
            return super().frame(index)
        return self._file["frames/images"][int(index)]

    def close(self) -> None:
        if getattr(self, "_file", None) is not None and self._file.id.valid:
            self._file.close()
