"""DSEC (Gehrig et al. 2021): ``events.h5``, optional ``rectify_map.h5`` and the optical-flow
ground truth (16-bit PNGs + timestamps file). docs/formats.md.

Layout read:

    events/x, events/y   (N,) uint16    pixel (unrectified); DSEC's sensor is 640 x 480
    events/t             (N,) uint32    µs relative to t_offset
    events/p             (N,) uint8     0 = OFF, 1 = ON
    ms_to_idx            (M,) uint64    ms_to_idx[m] = first event with t >= 1000 * m
    t_offset             () int64       µs; absolute time = t_offset + t
    (the event datasets are Blosc/zstd compressed: reading needs ``import hdf5plugin``)

    rectify_map.h5:  rectify_map (H, W, 2) float32, [y, x] -> (x_rect, y_rect)
    flow PNGs:       (H, W, 3) uint16 RGB: x = (R - 2^15) / 128, y = (G - 2^15) / 128,
                     valid = B > 0; pixels of displacement over [from_us, to_us)
    timestamps file: "# from_timestamp_us, to_timestamp_us" then one "from, to" line per PNG,
                     in the sorted order of the PNG file names (absolute µs, t_offset's clock)

Times returned are absolute µs (``t_offset + t``), the clock of the flow timestamps.
Rectification: ``rectify=None`` (default) applies ``rectify_map.h5`` when it lies beside
``events.h5`` (the flow ground truth lives in rectified coordinates); events then carry float32
x/y and those mapped outside the sensor are dropped (``num_events`` and indices stay the file's).
Ground truth: the stored map on an exact interval match, a linearly scaled map when the window
lies inside one interval, else None.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from envs.events import Events
from envs.readers._common import SortedColumn, missing_extra, nonbuiltin_filters, open_h5, require
from envs.readers.base import EventReader, FlowGT, FormatError
from envs.readers.png16 import png_size, read_png, write_png

__all__ = ["DSECReader", "DSEC_SENSOR_SIZE", "decode_flow_png", "encode_flow_png", "read_test_timestamps",
           "require_hdf5plugin"]

DSEC_SENSOR_SIZE = (480, 640)


def require_hdf5plugin(path: Path | None = None, datasets=()) -> bool:
    """Import hdf5plugin (registers Blosc/zstd with HDF5). When it is missing, raise an
    ImportError telling to install the 'dsec' extra if any of ``datasets`` needs a plugin
    filter; return False when none does (plain gzip files still read)."""
    try:
        import hdf5plugin  # noqa: F401
    except ImportError:
        needed = [ds.name for ds in datasets if nonbuiltin_filters(ds)]
        if needed or not datasets:
            err = missing_extra("hdf5plugin", "dsec", f"Reading DSEC {path or 'events.h5'} (Blosc/zstd-compressed {', '.join(needed) or 'events'})")
            raise err from None
        return False
    return True


def decode_flow_png(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """DSEC flow PNG -> (flow (2, H, W) float32 pixels, valid (H, W) bool)."""
    image = read_png(path)
    if image.ndim != 3 or image.shape[2] < 3 or image.dtype != np.uint16:
        raise FormatError(f"{path}: a DSEC flow PNG is 16-bit RGB, got shape {image.shape} dtype {image.dtype}")
    flow = (image[:, :, :2].astype(np.float32) - 2.0**15) / 128.0
    valid = image[:, :, 2] > 0
    flow = np.where(valid[:, :, None], flow, 0.0).astype(np.float32)
    return np.ascontiguousarray(flow.transpose(2, 0, 1)), valid


def encode_flow_png(path: str | os.PathLike, flow: np.ndarray, valid: np.ndarray, *, filters=0) -> None:
    """Inverse of :func:`decode_flow_png` (tests, converters): flow (2, H, W) px, valid (H, W)."""
    rgb = np.zeros(flow.shape[1:] + (3,), np.uint16)
    rgb[:, :, 0] = np.clip(np.rint(flow[0] * 128.0 + 2**15), 0, 65535)
    rgb[:, :, 1] = np.clip(np.rint(flow[1] * 128.0 + 2**15), 0, 65535)
    rgb[:, :, 2] = np.asarray(valid, bool)
    write_png(path, rgb, filters=filters)


def _read_flow_timestamps(path: Path) -> np.ndarray:
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 2:
            raise FormatError(f"{path}: line {n} must be 'from_us, to_us', got {line!r}")
        rows.append((int(parts[0]), int(parts[1])))
    arr = np.asarray(rows, np.int64).reshape(-1, 2)
    bad = np.flatnonzero(arr[:, 1] <= arr[:, 0])
    if len(bad):
        raise FormatError(f"{path}: interval {bad[0]} has to_us <= from_us: {arr[bad[0]].tolist()}")
    return arr


def read_test_timestamps(path: str | os.PathLike) -> np.ndarray:
    """The benchmark's test timestamps, ``test_forward_optical_flow_timestamps/<sequence>.csv``:
    "# from_timestamp_us, to_timestamp_us, file_index" then one row per flow to predict.

    Returns (K, 3) int64 rows ``(from_us, to_us, file_index)``: the window (absolute µs, the
    events' clock) and the index that names its submission file (``<file_index:06d>.png``).
    """
    path = Path(path)
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [part for part in line.replace(",", " ").split()]
        if len(parts) != 3:
            raise FormatError(f"{path}: line {n} must be 'from_us, to_us, file_index', got {line!r}")
        try:
            rows.append(tuple(int(part) for part in parts))
        except ValueError:
            raise FormatError(f"{path}: line {n} holds a non-integer field: {line!r}") from None
    arr = np.asarray(rows, np.int64).reshape(-1, 3)
    bad = np.flatnonzero(arr[:, 1] <= arr[:, 0])
    if len(bad):
        raise FormatError(f"{path}: row {bad[0]} has to_us <= from_us: {arr[bad[0], :2].tolist()}")
    if len(np.unique(arr[:, 2])) != len(arr):
        raise FormatError(f"{path}: file indices repeat (each names one submission PNG)")
    return arr


class DSECReader(EventReader):
    """One DSEC event stream (module docstring for the layout, times and rectification).

    path: ``events.h5``. rectify: None (auto), True (needs ``rectify_map``/the file beside),
    False. rectify_map: path of ``rectify_map.h5``. flow_dir: folder of the flow PNGs;
    flow_timestamps: the ``forward_timestamps.txt`` file (default: ``<flow_dir>/../forward_timestamps.txt``
    or ``<flow_dir>/timestamps.txt`` when present). sensor_size: (height, width) for a
    recording in this layout from another camera that has neither rectify map nor flow PNGs;
    otherwise the size comes from those files (they must agree with each other and with the
    events), and is DSEC's 480 x 640 when there are none.
    """

    layout = "dsec"

    # Like every reader: the path, then keyword-only options (open_recording passes them on).
    def _check_layout(self) -> dict[str, int]:
        """The lengths of the event datasets x, y, t, p, once the file is checked to hold the
        DSEC layout (events of one length, ``ms_to_idx``, ``t_offset``, their compression
        readable); else the file is closed and a FormatError raised."""
        f = self._file
        try:
            require(
                f, self.path, "DSEC",
                {"events/x": ("iu", 1), "events/y": ("iu", 1), "events/t": ("iu", 1), "events/p": ("iub", 1), "ms_to_idx": ("iu", 1)},
            )
            if "t_offset" not in f:
                raise FormatError(f"{self.path}: missing dataset '/t_offset' (required by the DSEC layout)")
            lengths = {k: f["events"][k].shape[0] for k in "xytp"}
            if len(set(lengths.values())) != 1:
                raise FormatError(f"{self.path}: event datasets differ in length: {lengths}")
            require_hdf5plugin(self.path, [f["events"][k] for k in "xytp"])
        except Exception:
            f.close()
            raise
        return lengths

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        rectify: bool | None = None,
        rectify_map: str | os.PathLike | None = None,
        flow_dir: str | os.PathLike | None = None,
        flow_timestamps: str | os.PathLike | None = None,
        sensor_size: tuple[int, int] | None = None,
        validate: bool = True,
    ) -> None:
        self.path = Path(path)
        # DSEC's tree: <sequence>/events/left/events.h5 -> the sequence name
        parts = self.path.parts
        self.name = parts[-4] if len(parts) >= 4 and parts[-3:-1] in (("events", "left"), ("events", "right")) else self.path.parent.name
        self.validate = validate
        self._file = f = open_h5(self.path, "DSEC")
        lengths = self._check_layout()
        self._ds = {k: f["events"][k] for k in "xytp"}
        self._ms_to_idx = f["ms_to_idx"]
        self.t_offset = int(np.asarray(f["t_offset"][()]).ravel()[0])
        self.num_events = lengths["t"]
        self.sensor_size = DSEC_SENSOR_SIZE  # until the rectify map or the flow PNGs say otherwise
        self._times = SortedColumn(lambda i0, i1: self._ds["t"][i0:i1].astype(np.int64) + self.t_offset, self.num_events)
        try:
            self._check_index()
        except Exception:
            f.close()
            raise
        n = self.num_events
        self._t_end = (int(self._ds["t"][n - 1]) + self.t_offset + 1) if n else self.t_offset + 1
        # rectification
        map_path = Path(rectify_map) if rectify_map is not None else self.path.with_name("rectify_map.h5")
        if rectify is None:
            rectify = map_path.exists()
        self.rectified = bool(rectify)
        self._rect = None
        sizes: dict[str, tuple[int, int]] = {}  # what each file (or the caller) says the sensor is
        if sensor_size is not None:
            sizes["sensor_size="] = (int(sensor_size[0]), int(sensor_size[1]))
        if self.rectified:
            self._rect = self._load_rectify_map(map_path)
            sizes[str(map_path)] = tuple(self._rect.shape[:2])
        # ground truth
        self._flow_files: list[Path] = []
        self._flow_t = None
        if flow_dir is not None:
            self._open_flow(Path(flow_dir), None if flow_timestamps is None else Path(flow_timestamps))
            if self._flow_files:
                sizes[str(self._flow_files[0])] = png_size(self._flow_files[0])
        if len(set(sizes.values())) > 1:
            f.close()
            raise FormatError("DSEC files disagree on the sensor size (height x width): " +
                              ", ".join(f"{k}: {h}x{w}" for k, (h, w) in sizes.items()))
        if sizes:
            self.sensor_size = next(iter(sizes.values()))
        self._check_event_extent()

    def _check_event_extent(self, samples: int = 65_536) -> None:
        """The events must fit the sensor size the files state: checked on an even sample of
        events on open (every window is checked again when read)."""
        n = self.num_events
        if not n:
            return
        pick = np.unique(np.linspace(0, n - 1, min(n, samples)).astype(np.int64))
        xs, ys = self._ds["x"][pick], self._ds["y"][pick]
        h, w = self.sensor_size
        if int(xs.max()) >= w or int(ys.max()) >= h:
            self._file.close()
            raise FormatError(
                f"{self.path}: events reach x = {int(xs.max())}, y = {int(ys.max())}, outside the {w}x{h} sensor "
                "(width x height) that the rectify map / flow PNGs state"
            )

    def _load_rectify_map(self, path: Path) -> np.ndarray:
        if not path.exists():
            raise FileNotFoundError(f"{path}: rectification map not found (pass rectify_map= or rectify=False)")
        mf = open_h5(path, "DSEC rectify_map")
        try:
            require(mf, path, "DSEC rectify_map", {"rectify_map": ("f", 3)})
            rect = mf["rectify_map"][:]
        finally:
            mf.close()
        if rect.ndim != 3 or rect.shape[2] != 2 or min(rect.shape[:2]) < 1:
            raise FormatError(f"{path}: dataset '/rectify_map' has shape {rect.shape}, expected (height, width, 2)")
        return rect.astype(np.float32)

    def _open_flow(self, flow_dir: Path, ts_path: Path | None) -> None:
        if not flow_dir.is_dir():
            raise FileNotFoundError(f"{flow_dir}: flow folder not found")
        if ts_path is None:
            for cand in (flow_dir.parent / f"{flow_dir.name}_timestamps.txt", flow_dir / "timestamps.txt"):
                if cand.exists():
                    ts_path = cand
                    break
            else:
                raise FileNotFoundError(f"{flow_dir}: no timestamps file found; pass flow_timestamps=")
        self._flow_files = sorted(flow_dir.glob("*.png"))
        self._flow_t = _read_flow_timestamps(ts_path)
        if len(self._flow_t) != len(self._flow_files):
            raise FormatError(
                f"{ts_path}: {len(self._flow_t)} intervals for {len(self._flow_files)} PNGs in {flow_dir}"
            )
        self._flow_lookup = {(int(a), int(b)): k for k, (a, b) in enumerate(self._flow_t)}

    # -- events ---------------------------------------------------------------------------
    @property
    def t_start(self) -> int:
        return self.t_offset

    @property
    def t_end(self) -> int:
        return self._t_end

    def _check_index(self, samples: int = 16) -> None:
        """Cheap checks of ``ms_to_idx`` on open: entries in [0, num_events], non-decreasing, and
        pointing at the first event of their millisecond at ``samples`` sampled entries (a zeroed or
        shuffled index raises FormatError naming the file instead of giving wrong windows)."""
        index = np.asarray(self._ms_to_idx[:], np.int64)
        n = self.num_events
        where = f"{self.path}: dataset '/ms_to_idx'"
        if n and len(index) == 0:
            raise FormatError(f"{where} is empty for {n} events")
        out = np.flatnonzero((index < 0) | (index > n))
        if len(out):
            raise FormatError(f"{where} entry {out[0]} = {index[out[0]]} is outside [0, num_events = {n}]")
        drops = np.flatnonzero(np.diff(index) < 0)
        if len(drops):
            m = int(drops[0]) + 1
            raise FormatError(f"{where} decreases at entry {m} ({index[m]} after {index[m - 1]}); it must be non-decreasing")
        last_ms = (self._times._probe(n - 1) - self.t_offset) // 1000 if n else 0
        if len(index) < last_ms:  # one entry per millisecond up to the last event's (one short tolerated)
            raise FormatError(f"{where} has {len(index)} entries but the events run to {last_ms} ms; it is cut short")
        for m in np.unique(np.linspace(0, len(index) - 1, samples).round().astype(np.int64)) if n else ():
            self._check_entry(int(m), int(index[m]))

    def _check_entry(self, m: int, i: int) -> None:
        """ms_to_idx[m] = i must be the first event with t >= 1000 m (relative µs)."""
        bound, n = self.t_offset + 1000 * m, self.num_events
        if (i > 0 and self._times._probe(i - 1) >= bound) or (i < n and self._times._probe(i) < bound):
            raise FormatError(
                f"{self.path}: dataset '/ms_to_idx' entry {m} = {i} is not the first event at or after {1000 * m} us "
                "(relative to t_offset); the index is corrupt"
            )

    def index_at(self, t_us: int) -> int:
        rel = int(t_us) - self.t_offset
        if rel <= 0:  # relative times are unsigned: every event is at or after t_offset
            return 0
        m = rel // 1000
        nm = self._ms_to_idx.shape[0]
        lo = int(self._ms_to_idx[min(m, nm - 1)])
        hi = int(self._ms_to_idx[m + 1]) if m + 1 < nm else self.num_events
        # ms_to_idx[m] is the first event at or after m ms, so the answer lies in [lo, hi]
        if m < nm:  # memoised single reads: the two entries this window relies on are checked
            self._check_entry(m, lo)
        if m + 1 < nm:
            self._check_entry(m + 1, hi)
        return self._times.searchsorted(int(t_us), lo, hi)

    def time_of(self, index: int) -> int:
        return int(self._ds["t"][int(index)]) + self.t_offset

    def events_range(self, i_start: int, i_end: int) -> Events:
        i_start, i_end = max(0, int(i_start)), min(self.num_events, int(i_end))
        if i_end <= i_start:
            return Events.empty(self.sensor_size)
        d = self._ds
        x, y = d["x"][i_start:i_end], d["y"][i_start:i_end]
        t = d["t"][i_start:i_end].astype(np.int64) + self.t_offset
        p = d["p"][i_start:i_end]
        source = f"{self.path} (events {i_start}..{i_end})"
        if self._rect is not None:
            h, w = self.sensor_size
            inside = (x < w) & (y < h)
            if self.validate and not inside.all():
                bad = int(np.flatnonzero(~inside)[0])
                raise FormatError(f"{source}: event {i_start + bad} at (x={x[bad]}, y={y[bad]}) is outside the {w}x{h} "
                                  "sensor (width x height, from the rectify map)")
            xy = self._rect[y, x]
            xr, yr = xy[:, 0], xy[:, 1]
            keep = np.isfinite(xr) & np.isfinite(yr) & (xr >= 0) & (xr <= w - 1) & (yr >= 0) & (yr <= h - 1)
            x, y, t, p = xr[keep], yr[keep], t[keep], p[keep]
        return Events.create(x, y, t, p, self.sensor_size, source=source, validate=self.validate)

    # -- ground truth -----------------------------------------------------------------------
    @property
    def has_flow(self) -> bool:
        return self._flow_t is not None and len(self._flow_t) > 0

    def flow_intervals(self) -> np.ndarray | None:
        """(K, 2) int64 µs [from, to) of the stored flow maps."""
        return self._flow_t

    def flow_timestamps(self) -> np.ndarray | None:
        """Sorted union of the maps' from/to times (consecutive pairs without a map give None)."""
        if not self.has_flow:
            return None
        return np.unique(self._flow_t.ravel())

    def flow_between(self, t_start: int, t_end: int) -> FlowGT | None:
        """The stored map for exactly [t_start, t_end); inside one map's interval, that map scaled
        by the fraction of the interval; otherwise None."""
        if not self.has_flow:
            return None
        t_start, t_end = int(t_start), int(t_end)
        k = self._flow_lookup.get((t_start, t_end))
        if k is not None:
            return decode_flow_png(self._flow_files[k])
        inside = np.flatnonzero((self._flow_t[:, 0] <= t_start) & (t_end <= self._flow_t[:, 1]))
        if t_end <= t_start or len(inside) == 0:
            return None
        k = int(inside[0])
        flow, valid = decode_flow_png(self._flow_files[k])
        scale = (t_end - t_start) / float(self._flow_t[k, 1] - self._flow_t[k, 0])
        return (flow * scale).astype(np.float32), valid

    def close(self) -> None:
        if getattr(self, "_file", None) is not None and self._file.id.valid:
            self._file.close()
