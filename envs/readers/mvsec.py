"""MVSEC (Zhu et al. 2018): reader for ``<seq>_data.hdf5`` + ``<seq>_gt_flow_dist.npz`` and the
evaluation protocol (docs/method.md, "Metrics"; docs/formats.md).

Layout read (DAVIS 346, 260 x 346):

    davis/left/events         (N, 4) float64  [x, y, t (epoch seconds), p in {-1, +1}]
    davis/left/image_raw      (F, 260, 346) uint8      [optional]
    davis/left/image_raw_ts   (F,) float64 epoch seconds   [optional]
    <seq>_gt_flow_dist.npz:  timestamps (K,) epoch s; x_flow_dist, y_flow_dist (K, 260, 346):
                             map i = displacement in pixels from timestamps[i] to timestamps[i+1]

Time origin: every time this reader returns is integer µs relative to the first event,
``t_us = rint(t_s * 1e6) - origin_us`` with ``origin_us = rint(first_event_t_s * 1e6)``
(``reader.origin_us``; the same origin for events, ground truth and frames). So the first event
is at t = 0 and the outdoor_day1 cut "222.4-240.4 s" means t in [222.4e6, 240.4e6) µs.

Ground truth (``flow_between``): from the 20 Hz displacement maps by linear scaling inside one
interval or by chaining the maps with nearest-neighbour lookups across intervals
(:mod:`envs.readers.flowgt`), ``gt_mode="chain"`` (the default). ``gt_mode="zhu"`` follows the
EV-FlowNet evaluation (Zhu et al. 2018): a window shorter than the 20 Hz interval holding its
start gets that interval's map scaled by ``(t_end - t_start) / gt_dt``, even where the window
reaches into the next interval; longer windows are chained as above. The frames-mode grid (``flow_timestamps``) is the grayscale image
timestamps (the EV-FlowNet protocol: dt = 1 spans two consecutive images, dt = 4 five), or the
ground-truth timestamps with ``grid="gt"`` or when the file has no images.

Crop: ``crop=(top, left, height, width)`` or ``"center256"`` keeps the events inside the box,
shifts them to the box origin and crops ground truth and frames (which are computed on the full
sensor first, so motion from outside the box is propagated correctly); ``sensor_size`` becomes
the crop size. ``num_events`` and ``events_range`` indices stay those of the file (a window may
hold fewer events than its index range once cropped).

Memory: events are read per window through a chunked binary search on the time column; the
ground truth is read one map at a time (memory-mapped from an uncompressed npz, streamed from a
compressed one).
"""

from __future__ import annotations

import os
import re
import struct
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Literal

import numpy as np

from envs.events import Events
from envs.readers._common import (
    SortedColumn,
    check_finite,
    check_pixel_coordinates,
    crop_events,
    open_h5,
    require,
    resolve_crop,
    seconds_to_us,
)
from envs.readers.base import EventReader, FlowGT, FormatError
from envs.readers.flowgt import flow_from_displacements, valid_of

__all__ = [
    "MVSECReader",
    "MVSEC_GT_MODES",
    "MVSEC_HOOD_ROW",
    "MVSEC_SEQUENCES",
    "MVSEC_VALID_FRAMES",
    "OUTDOOR_DAY1_CUT_S",
    "MVSEC_CROP",
    "MVSEC_SENSOR_SIZE",
    "mvsec_eval_windows",
    "mvsec_hood_row",
    "mvsec_scored_span",
    "sequence_name",
]

MVSEC_SENSOR_SIZE = (260, 346)
#: the four sequences of the flow benchmark (Zhu et al. 2018; Hagenaars et al. 2021)
MVSEC_SEQUENCES = ("indoor_flying1", "indoor_flying2", "indoor_flying3", "outdoor_day1")
#: ground truth is evaluated only inside these grid-index ranges [first, last] (docs/method.md, "Metrics")
MVSEC_VALID_FRAMES = {
    "indoor_flying1": (60, 1340),
    "indoor_flying2": (140, 1500),
    "indoor_flying3": (100, 1711),
    "outdoor_day1": (4356, 4706),
}
#: outdoor_day1 is evaluated on this time span, seconds after the first event (= reader time 0)
OUTDOOR_DAY1_CUT_S = (222.4, 240.4)
#: the central 256 x 256 crop used for evaluation (as Hagenaars)
MVSEC_CROP = "center256"
#: the car's hood: rows >= 190 of the central 256 x 256 crop (sensor rows >= 192) are left out of
#: the scores of the outdoor (car) sequences, as the EV-FlowNet evaluation does
MVSEC_HOOD_ROW = 190
#: how ``flow_between`` makes a window's ground truth (module docstring)
MVSEC_GT_MODES = ("chain", "zhu")


def sequence_name(path: str | os.PathLike) -> str:
    """'.../indoor_flying1_data.hdf5' -> 'indoor_flying1' (the file stem without the suffix)."""
    stem = Path(path).name
    return re.sub(r"(_data\.hdf5|_data\.h5|_gt_flow_dist\.npz|\.hdf5|\.h5)$", "", stem)


class _NpyInZip:
    """One (K, H, W) array of an .npz, read one slice at a time.

    Uncompressed members (``np.savez``) are memory-mapped; compressed ones (``np.savez_compressed``)
    are streamed, seeking forward from the last position (sequential access is cheap, going back
    restarts the member).
    """

    def __init__(self, path: Path, key: str) -> None:
        self.path, self.key = path, key
        self._zip = zipfile.ZipFile(path)
        member = key + ".npy"
        try:
            self._info = self._zip.getinfo(member)
        except KeyError:
            members = self._zip.namelist()
            self._zip.close()
            raise FormatError(f"{path}: missing array '{key}' (members: {members})") from None
        with self._zip.open(self._info) as fh:
            version = np.lib.format.read_magic(fh)
            reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            self.shape, fortran, self.dtype = reader(fh)
            self._header_len = fh.tell()
        if fortran or len(self.shape) != 3:
            raise FormatError(f"{path}: array '{key}' must be a C-ordered (K, H, W) stack, got shape {self.shape}")
        self._frame_bytes = int(np.prod(self.shape[1:])) * self.dtype.itemsize
        self._mmap = None
        self._stream = None
        self._pos = 0
        if self._info.compress_type == zipfile.ZIP_STORED:
            with open(path, "rb") as raw:
                raw.seek(self._info.header_offset)
                local = struct.unpack("<IHHHHHIIIHH", raw.read(30))
            data_start = self._info.header_offset + 30 + local[9] + local[10] + self._header_len
            self._mmap = np.memmap(path, dtype=self.dtype, mode="r", offset=data_start, shape=self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, k: int) -> np.ndarray:
        k = int(k)
        if not 0 <= k < self.shape[0]:
            raise IndexError(f"{self.path}:{self.key}: index {k} out of range {self.shape[0]}")
        if self._mmap is not None:
            return np.array(self._mmap[k])
        target = self._header_len + k * self._frame_bytes
        if self._stream is None or target < self._pos:
            if self._stream is not None:
                self._stream.close()
            self._stream = self._zip.open(self._info)
            self._pos = 0
        self._stream.seek(target)
        buf = self._stream.read(self._frame_bytes)
        self._pos = target + len(buf)
        return np.frombuffer(buf, self.dtype).reshape(self.shape[1:]).copy()

    def close(self) -> None:
        if self._stream is not None:
            self._stream.close()
        self._mmap = None
        self._zip.close()


class MVSECReader(EventReader):
    """One MVSEC sequence (see the module docstring for the layout, time origin and crop).

    path: ``<seq>_data.hdf5``. gt: the ``_gt_flow_dist.npz`` path; default: the file of that name
    beside ``path`` when it exists; False for none. camera: "left" or "right".
    crop: None, (top, left, height, width) or "center256". grid: "images" or "gt" (frames-mode
    grid; see module docstring). gt_mode: "chain" or "zhu" (module docstring). validate: check
    every window's events (bounds, time order).
    """

    layout = "mvsec"

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        gt: str | os.PathLike | bool | None = None,
        camera: str = "left",
        crop=None,
        grid: str = "images",
        gt_mode: Literal["chain", "zhu"] = "chain",
        validate: bool = True,
    ) -> None:
        if gt_mode not in MVSEC_GT_MODES:
            raise ValueError(f"gt_mode must be one of {MVSEC_GT_MODES}, got {gt_mode!r}")
        self.gt_mode = gt_mode
        self.path = Path(path)
        self.name = sequence_name(self.path)
        self.sequence = self.name
        self.validate = validate
        self._file = open_h5(self.path, "MVSEC")
        f = self._file
        base = f"davis/{camera}"
        ev = self._events_dataset(base)
        self._events = ev
        self.num_events = int(ev.shape[0])
        self.full_sensor_size = MVSEC_SENSOR_SIZE
        if f"{base}/image_raw" in f:
            self.full_sensor_size = tuple(int(v) for v in f[f"{base}/image_raw"].shape[1:3])
        self.crop = resolve_crop(crop, self.full_sensor_size)
        self.sensor_size = self.full_sensor_size if self.crop is None else (self.crop[2], self.crop[3])
        self._events_name = f"/{base}/events"
        self._events_field = f"{self._events_name} column 2 (t, seconds)"
        try:
            check_finite(ev[0:1, 2], str(self.path), self._events_field)
            self.origin_us = int(np.rint(float(ev[0, 2]) * 1e6))
            self._t_end = int(self._seconds_to_us(ev[self.num_events - 1 : self.num_events, 2], self.num_events - 1)[0]) + 1
        except Exception:
            f.close()
            raise
        self._times = SortedColumn(lambda i0, i1: self._seconds_to_us(self._events[i0:i1, 2], i0), self.num_events)
        self._open_frames(base)
        # ground truth
        if gt is None:
            candidate = self.path.with_name(self.name + "_gt_flow_dist.npz")
            gt = candidate if candidate.exists() else False
        self._gt_t = None
        self._gt_x = self._gt_y = None
        self.gt_path = None
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        if grid not in ("images", "gt"):
            f.close()
            raise ValueError(f"grid must be 'images' or 'gt', got {grid!r}")
        if gt:
            try:
                self._open_gt(Path(gt))
            except Exception:
                self.close()
                raise
        self.grid = grid

    def _events_dataset(self, base: str):
        """The camera's (N, 4) events dataset ``/<base>/events`` (non-empty); else the file is
        closed and a FormatError raised."""
        f = self._file
        try:
            require(f, self.path, "MVSEC", {f"{base}/events": ("f", 2)})
            ev = f[f"{base}/events"]
            if ev.shape[1] != 4:
                raise FormatError(
                    f"{self.path}: dataset '/{base}/events' has shape {ev.shape}, the MVSEC layout "
                    "expects (N, 4) columns [x, y, t_seconds, p]"
                )
            if ev.shape[0] == 0:
                raise FormatError(f"{self.path}: dataset '/{base}/events' is empty")
        except Exception:
            f.close()
            raise
        return ev

    def _open_frames(self, base: str) -> None:
        """The camera's APS frames and their times in µs from the origin, where the file has
        them (else None); frames without timestamps close the file and raise a FormatError."""
        f = self._file
        self._images = None
        self._image_t = None
        if f"{base}/image_raw" in f:
            if f"{base}/image_raw_ts" not in f:
                f.close()
                raise FormatError(f"{self.path}: '/{base}/image_raw' has no timestamps: missing dataset '/{base}/image_raw_ts'")
            self._images = f[f"{base}/image_raw"]
            try:
                self._image_t = seconds_to_us(f[f"{base}/image_raw_ts"][:], self.origin_us, source=str(self.path),
                                              field=f"/{base}/image_raw_ts")
            except Exception:
                f.close()
                raise

    def _open_gt(self, path: Path) -> None:
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such ground-truth file")
        try:
            with np.load(path) as npz:
                if "timestamps" not in npz.files:
                    raise FormatError(f"{path}: missing array 'timestamps' (MVSEC gt_flow_dist layout)")
                ts = np.asarray(npz["timestamps"], np.float64)
        except (zipfile.BadZipFile, ValueError, OSError) as err:
            if isinstance(err, FormatError):
                raise
            raise FormatError(f"{path}: not a readable .npz file: {err}") from err
        self._gt_x = _NpyInZip(path, "x_flow_dist")
        self._gt_y = _NpyInZip(path, "y_flow_dist")  # (if this raises, close() closes the first)
        for arr in (self._gt_x, self._gt_y):
            if arr.shape != (len(ts),) + self.full_sensor_size:
                raise FormatError(
                    f"{path}: array '{arr.key}' has shape {arr.shape}, expected "
                    f"({len(ts)}, {self.full_sensor_size[0]}, {self.full_sensor_size[1]}) (one map per timestamp)"
                )
        if ts.ndim != 1 or (np.diff(ts) <= 0).any():
            raise FormatError(f"{path}: array 'timestamps' must be 1-D and increasing")
        self._gt_t = seconds_to_us(ts, self.origin_us, source=str(path), field="timestamps")
        self.gt_path = path

    # -- events -----------------------------------------------------------------------------
    @property
    def t_start(self) -> int:
        return 0

    @property
    def t_end(self) -> int:
        return self._t_end

    def _seconds_to_us(self, t_seconds: np.ndarray, offset: int) -> np.ndarray:
        """Event times (the events' column 2, from row ``offset``) -> µs after the first event."""
        return seconds_to_us(t_seconds, self.origin_us, source=str(self.path), field=self._events_field, offset=offset)

    def index_at(self, t_us: int) -> int:
        return self._times.searchsorted(int(t_us))

    def time_of(self, index: int) -> int:
        i = int(index)
        return int(self._seconds_to_us(self._events[i : i + 1, 2], i)[0])

    def events_range(self, i_start: int, i_end: int) -> Events:
        i_start, i_end = max(0, int(i_start)), min(self.num_events, int(i_end))
        if i_end <= i_start:
            return Events.empty(self.sensor_size)
        block = self._events[i_start:i_end]
        source = str(self.path)
        if self.validate:  # -0.6 or 10.7 is an error, not a pixel
            x = check_pixel_coordinates(block[:, 0], source, f"{self._events_name} column 0 (x)", i_start)
            y = check_pixel_coordinates(block[:, 1], source, f"{self._events_name} column 1 (y)", i_start)
        else:
            x, y = block[:, 0].astype(np.int64), block[:, 1].astype(np.int64)
        t = self._seconds_to_us(block[:, 2], i_start)
        p = block[:, 3]
        keep, x, y = crop_events(x, y, self.crop)
        if keep is not None:
            t, p = t[keep], p[keep]
        return Events.create(
            x, y, t, p, self.sensor_size,
            source=f"{self.path} (events {i_start}..{i_end})", validate=self.validate,
        )

    # -- ground truth ---------------------------------------------------------------------------
    @property
    def has_flow(self) -> bool:
        return self._gt_t is not None

    def gt_timestamps(self) -> np.ndarray | None:
        """(K,) int64 µs of the ground-truth maps (map i spans [T_i, T_{i+1}))."""
        return self._gt_t

    def flow_timestamps(self) -> np.ndarray | None:
        if self._gt_t is None:
            return None
        if self.grid == "images" and self._image_t is not None:
            return self._image_t
        return self._gt_t

    def _map(self, i: int) -> np.ndarray:
        d = self._cache.get(i)
        if d is None:
            d = np.stack([self._gt_x[i], self._gt_y[i]]).astype(np.float64)
            self._cache[i] = d
            if len(self._cache) > 8:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(i)
        return d

    def flow_between(self, t_start: int, t_end: int) -> FlowGT | None:
        """Flow over [t_start, t_end) µs: (2, H, W) float32 px, valid (H, W) bool; cropped like the events.

        None outside the ground-truth span. Scaled inside one 20 Hz interval, chained across
        intervals; with ``gt_mode="zhu"`` a window shorter than the interval holding its start is
        that interval's map scaled (module docstring)."""
        if self._gt_t is None:
            return None
        out = None
        if self.gt_mode == "zhu":
            out = self._zhu_flow(int(t_start), int(t_end))
        if out is None:
            out = flow_from_displacements(self._map, self._gt_t, t_start, t_end, lambda i: valid_of(self._map(i)))
        if out is None:
            return None
        flow, valid = out
        if self.crop is not None:
            top, left, h, w = self.crop
            flow, valid = flow[:, top : top + h, left : left + w], valid[top : top + h, left : left + w]
        return np.ascontiguousarray(flow), np.ascontiguousarray(valid)

    def _zhu_flow(self, t_start: int, t_end: int) -> FlowGT | None:
        """EV-FlowNet's ground truth for a window shorter than the 20 Hz interval holding its
        start: that interval's map times (t_end - t_start) / gt_dt (full frame); None otherwise."""
        times = self._gt_t
        if t_end <= t_start or t_start < times[0] or t_end > times[-1]:
            return None
        i = int(np.searchsorted(times, t_start, side="right")) - 1
        if i >= len(times) - 1:
            return None
        gt_dt = int(times[i + 1] - times[i])
        if t_end - t_start >= gt_dt:  # as long as the interval or longer: chained instead
            return None
        d = self._map(i)
        valid = valid_of(d)
        flow = np.where(valid, d * ((t_end - t_start) / float(gt_dt)), 0.0).astype(np.float32)
        return flow, valid

    # -- frames -------------------------------------------------------------------------------
    def frame_timestamps(self) -> np.ndarray | None:
        return self._image_t

    def frame(self, index: int) -> np.ndarray:
        if self._images is None:
            return super().frame(index)
        image = self._images[int(index)]
        if self.crop is not None:
            top, left, h, w = self.crop
            image = image[top : top + h, left : left + w]
        return np.ascontiguousarray(image)

    def close(self) -> None:
        for arr in (self._gt_x, self._gt_y):
            if arr is not None:
                arr.close()
        if getattr(self, "_file", None) is not None and self._file.id.valid:
            self._file.close()


def _gt_grid(reader) -> np.ndarray:
    """The 20 Hz ground-truth timestamps (µs) the valid ranges index."""
    gt = reader.gt_timestamps() if hasattr(reader, "gt_timestamps") else reader.flow_timestamps()
    if gt is None:
        raise ValueError(f"{reader.name}: no ground truth (pass gt=<seq>_gt_flow_dist.npz)")
    return np.asarray(gt, np.int64)


def mvsec_scored_span(reader: MVSECReader, sequence: str | None = None, *,
                      outdoor_cut: str = "time") -> tuple[int, int]:
    """The time span ``(t_first, t_last)`` µs that the MVSEC protocol scores.

    Indoor: MVSEC_VALID_FRAMES index the 20 Hz ground-truth timestamps (not the image
    timestamps): the span is ``[gt_t[first], gt_t[last]]`` (last clamped to the file).
    outdoor_day1: by default (``outdoor_cut="time"``) OUTDOOR_DAY1_CUT_S, seconds after the first
    event, from Zhu et al. 2018 ("the outdoor_day1 sequence spans between 222.4 s and 240.4 s");
    ``outdoor_cut="frames"`` uses the ground-truth indices 4356-4706 instead (the same cut as
    other evaluations state it). Unknown sequences: the whole ground-truth grid.
    """
    if outdoor_cut not in ("time", "frames"):
        raise ValueError(f"outdoor_cut must be 'time' or 'frames', got {outdoor_cut!r}")
    gt = _gt_grid(reader)
    sequence = sequence or getattr(reader, "sequence", reader.name)
    if sequence == "outdoor_day1" and outdoor_cut == "time":
        lo, hi = (int(round(s * 1e6)) for s in OUTDOOR_DAY1_CUT_S)
        return lo, hi
    first, last = MVSEC_VALID_FRAMES.get(sequence, (0, len(gt) - 1))
    last = min(last, len(gt) - 1)
    if first > last:
        raise ValueError(f"{reader.name}: the valid range {first}-{last} of {sequence} is past the "
                         f"{len(gt)} ground-truth timestamps of the file")
    return int(gt[first]), int(gt[last])


def mvsec_hood_row(sequence: str, crop: tuple[int, int, int, int] | None) -> int | None:
    """First row (in the frame of ``crop``, (top, left, h, w) or None for the full sensor) of the
    car's hood for the outdoor sequences (rows >= MVSEC_HOOD_ROW of the central 256 crop); None
    for sequences without a hood (indoor)."""
    if not sequence.startswith("outdoor"):
        return None
    central_top = (MVSEC_SENSOR_SIZE[0] - 256) // 2
    top = crop[0] if crop is not None else 0
    return MVSEC_HOOD_ROW + central_top - top


def mvsec_eval_windows(reader: MVSECReader, dt: int, sequence: str | None = None, *, outdoor_cut: str = "time",
                       stride: int | None = None, grid: str | None = None) -> np.ndarray:
    """The evaluation windows of the MVSEC protocol: (K, 2) int64 ``[t_start, t_end)`` µs.

    Windows span ``dt`` steps of the evaluation grid, ``[T_k, T_{k+dt})`` for k = k0, k0 +
    stride, k0 + 2 stride, ... from the first grid time inside :func:`mvsec_scored_span`
    (``T_k0 >= t_first``), kept while ``T_{k+dt} <= t_last``. grid: ``"images"`` (the grayscale
    image timestamps, EV-FlowNet's dt = 1 / dt = 4 frames), ``"gt"`` (the 20 Hz ground-truth
    timestamps: the E-RAFT / idnet "20 Hz" evaluation), or None for ``reader.flow_timestamps()``. stride: grid steps between
    window starts, default ``dt`` (contiguous, as Hagenaars); 1 with dt = 4 gives the overlapping
    windows of Zhu, Spike-FlowNet and tub-rip.
    """
    if dt not in (1, 4):
        raise ValueError(f"MVSEC evaluates dt = 1 or 4 frames, got {dt}")
    stride = dt if stride is None else int(stride)
    if stride < 1:
        raise ValueError(f"stride must be >= 1 grid step, got {stride}")
    if grid not in (None, "images", "gt"):
        raise ValueError(f"grid must be None, 'images' or 'gt', got {grid!r}")
    lo, hi = mvsec_scored_span(reader, sequence, outdoor_cut=outdoor_cut)
    if grid == "gt":
        times = _gt_grid(reader)
    else:
        times = reader.frame_timestamps() if grid == "images" else reader.flow_timestamps()
        if times is None:
            raise ValueError(f"{reader.name}: no {'image' if grid else 'flow'} timestamps to cut windows on")
        times = np.unique(np.asarray(times, np.int64))
    first = int(np.searchsorted(times, lo, side="left"))
    starts = np.arange(first, len(times) - dt, stride)
    rows = np.stack([times[starts], times[starts + dt]], axis=1).astype(np.int64).reshape(-1, 2)
    return rows[(rows[:, 0] >= lo) & (rows[:, 1] <= hi)]
