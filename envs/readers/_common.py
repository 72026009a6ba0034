"""Pieces shared by the streaming readers: opening HDF5 files with layout errors that name the
dataset, binary search over an on-disk time column, crops, and the optional-extra imports.

Nothing here loads a whole event column: :class:`SortedColumn` finds a time with O(log N)
single-element reads and one block read.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from envs.readers.base import FormatError

__all__ = [
    "KNOWN_SENSORS",
    "SENSOR_SIZE_HINT",
    "SortedColumn",
    "auto_sensor_size",
    "check_finite",
    "check_flow_gt",
    "check_pixel_coordinates",
    "open_h5",
    "require",
    "resolve_crop",
    "seconds_to_us",
    "missing_extra",
]

# Built-in HDF5 filters (deflate, shuffle, fletcher32, szip, nbit, scaleoffset); anything else
# (Blosc 32001, zstd 32015, LZ4 32004, bitshuffle 32008...) needs hdf5plugin.
_BUILTIN_FILTERS = {1, 2, 3, 4, 5, 6}


def missing_extra(package: str, extra: str, what: str) -> ImportError:
    """The error raised when an optional extra is not installed."""
    return ImportError(
        f"{what} needs the '{package}' package, which is not installed: "
        f"install the '{extra}' extra: pip install evflow-gym[{extra}]"
    )


#: how a user gives the geometry a file lacks, in every message that asks for it
SENSOR_SIZE_HINT = ("pass --sensor-size H W (or --sensor-size auto) on the command line, sensor_size=(height, width) "
                    "to the reader, or data_options={'sensor_size': (height, width)} to the env")

#: the sensors ``sensor_size="auto"`` picks from, fewest pixels first: (name, (height, width))
KNOWN_SENSORS = (
    ("DAVIS240", (180, 240)),
    ("DAVIS346", (260, 346)),
    ("Prophesee GenX320", (320, 320)),
    ("Prophesee VGA", (480, 640)),
    ("Prophesee HD", (720, 1280)),
)


def auto_sensor_size(max_x: int, max_y: int, source: str | os.PathLike) -> tuple[int, int]:
    """``sensor_size="auto"``: the known sensor (:data:`KNOWN_SENSORS`) with the fewest pixels
    that holds every event, else the events' bounds; never silently: a warning names the choice.

    max_x, max_y: the largest event column and row (-1: no events). Returns (height, width)."""
    import warnings

    fits = [(name, size) for name, size in KNOWN_SENSORS if max_x < size[1] and max_y < size[0]]
    if fits:
        name, size = fits[0]
        why = f"{name}, the smallest known sensor holding every event"
    else:
        size = (max(max_y, 0) + 1, max(max_x, 0) + 1)
        why = "the events' bounds: no known sensor holds every event"
    warnings.warn(f"{source}: sensor_size auto: {size[0]}x{size[1]} (height x width; {why}: x <= {max_x}, "
                  f"y <= {max_y}); pass --sensor-size H W to set it", stacklevel=2)  # one place per reader: shown once
    return size


def open_h5(path: str | os.PathLike, layout: str) -> h5py.File:
    """Open an HDF5 file read-only; a missing or non-HDF5 file raises with the layout named.

    The chunk cache is 4 MiB per dataset (h5py's default is 1 MiB): enough for the window's
    chunks and the search's last probes; the upper levels of the search are memoised anyway.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        return h5py.File(path, "r", rdcc_nbytes=4 << 20, rdcc_nslots=10007)
    except OSError as err:
        raise FormatError(f"{path}: not a readable HDF5 file (expected the {layout} layout): {err}") from err


def require(f: h5py.File, path: Path, layout: str, datasets: dict[str, tuple]) -> None:
    """Check that each dataset exists with an allowed dtype kind and number of dimensions.

    datasets: {name: (dtype kinds e.g. "iuf", ndim or None)}. Raises FormatError naming the first
    missing or malformed dataset.
    """
    for name, (kinds, ndim) in datasets.items():
        if name not in f or not isinstance(f[name], h5py.Dataset):
            raise FormatError(f"{path}: missing dataset '/{name}' (required by the {layout} layout)")
        ds = f[name]
        if ds.dtype.kind not in kinds:
            raise FormatError(
                f"{path}: dataset '/{name}' has dtype {ds.dtype}, the {layout} layout expects "
                f"kind {' or '.join(kinds)} (b=bool, i=int, u=uint, f=float)"
            )
        if ndim is not None and ds.ndim != ndim:
            raise FormatError(
                f"{path}: dataset '/{name}' has shape {ds.shape}, the {layout} layout expects "
                f"{ndim} dimension(s)"
            )


def nonbuiltin_filters(ds: h5py.Dataset) -> list[int]:
    """Ids of the HDF5 filters on ``ds`` that plain h5py cannot decode."""
    plist = ds.id.get_create_plist()
    return [plist.get_filter(i)[0] for i in range(plist.get_nfilters()) if plist.get_filter(i)[0] not in _BUILTIN_FILTERS]


def check_finite(values: np.ndarray, source: str, field: str, offset: int = 0) -> None:
    """Raise FormatError naming ``source``, ``field`` and the first index (plus ``offset``)
    that holds NaN or infinity. values: any shape, float (other dtypes pass)."""
    values = np.asarray(values)
    if values.dtype.kind != "f" or values.size == 0:
        return
    finite = np.isfinite(values)
    if not finite.all():
        i = int(np.flatnonzero(~finite.ravel())[0])
        raise FormatError(f"{source}: field '{field}' is not a finite number at index {offset + i} ({values.ravel()[i].item()!r})")


#: ground truth may displace a pixel by at most this many times the sensor's longer side: a point
#: that moved further within one window left the field of view long before; 1e30 is corruption
FLOW_GT_SENSOR_MULTIPLE = 4


def check_flow_gt(flow: np.ndarray, valid: np.ndarray, sensor_size: tuple[int, int], source: str) -> None:
    """Raise FormatError naming ``source`` and the first bad pixel when a valid pixel of ground
    truth is not finite or moves further than ``FLOW_GT_SENSOR_MULTIPLE * max(H, W)`` pixels.

    flow: (2, H, W) pixels of displacement over the window; valid: (H, W) bool (invalid pixels
    are never scored, so they may hold anything); sensor_size: (H, W) of the recording."""
    flow, valid = np.asarray(flow), np.asarray(valid, bool)
    limit = FLOW_GT_SENSOR_MULTIPLE * max(sensor_size)
    with np.errstate(invalid="ignore"):
        bad = valid & ~(np.isfinite(flow).all(axis=0) & (np.abs(flow) <= limit).all(axis=0))
    if bad.any():
        y, x = (int(v) for v in np.argwhere(bad)[0])
        raise FormatError(
            f"{source}: ground-truth flow at pixel (x={x}, y={y}) is ({float(flow[0, y, x]):.6g}, {float(flow[1, y, x]):.6g}) px; "
            f"a valid pixel must hold a finite displacement of at most {limit} px ({FLOW_GT_SENSOR_MULTIPLE} x the "
            f"{sensor_size[0]}x{sensor_size[1]} sensor's longer side)"
        )


def check_pixel_coordinates(values: np.ndarray, source: str, field: str, offset: int = 0) -> np.ndarray:
    """Whole, non-negative pixel coordinates stored as floats -> int64; anything else (-0.6,
    10.7, NaN) raises FormatError naming ``source``, ``field`` and the first bad index (plus
    ``offset``) rather than being truncated. values: (N,) any numeric dtype."""
    values = np.asarray(values)
    if values.dtype.kind == "f":
        bad = ~np.isfinite(values) | (values < 0) | (values != np.floor(values))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise FormatError(
                f"{source}: field '{field}' must hold whole, non-negative pixel coordinates; index "
                f"{offset + i} holds {values[i].item()!r}"
            )
    return values.astype(np.int64)


def seconds_to_us(t_seconds: np.ndarray, origin_us: int, *, source: str = "timestamps", field: str = "t",
                  offset: int = 0) -> np.ndarray:
    """float seconds -> int64 µs relative to ``origin_us`` (absolute µs on the same clock).

    rint(t * 1e6) first (exact to the µs for epoch times: float64 resolution there is 0.24 µs),
    then the integer origin is subtracted, so the same stored value always maps to the same µs.
    A NaN or infinite time raises FormatError naming ``source``, ``field`` and the index (plus
    ``offset``, the position of ``t_seconds`` in its column).
    """
    t_seconds = np.asarray(t_seconds, np.float64)
    check_finite(t_seconds, source, field, offset)
    return np.rint(t_seconds * 1e6).astype(np.int64) - np.int64(origin_us)


class SortedColumn:
    """Binary search over a non-decreasing time column that stays on disk.

    read(i0, i1) -> (i1 - i0,) int64 µs must convert exactly as the reader's events do, so the
    search and the events agree. Probes are memoised (the upper levels of the search are the same
    for every query), and the last block read is kept for consecutive windows.
    """

    def __init__(self, read: Callable[[int, int], np.ndarray], length: int, block: int = 1 << 15) -> None:
        self._read = read
        self.length = int(length)
        self.block = int(block)
        self._probes: dict[int, int] = {}
        self._last: tuple[int, int, np.ndarray] | None = None

    def _probe(self, i: int) -> int:
        v = self._probes.get(i)
        if v is None:
            if len(self._probes) > 1 << 16:
                self._probes.clear()
            v = self._probes[i] = int(self._read(i, i + 1)[0])
        return v

    def _block(self, lo: int, hi: int) -> np.ndarray:
        if self._last is not None and self._last[0] <= lo and hi <= self._last[1]:
            a, _, values = self._last
            return values[lo - a : hi - a]
        values = self._read(lo, hi)
        self._last = (lo, hi, values)
        return values

    def searchsorted(self, t_us: int, lo: int = 0, hi: int | None = None) -> int:
        """First index in [lo, hi) with t >= t_us (hi if none)."""
        lo = max(0, int(lo))
        hi = self.length if hi is None else min(self.length, int(hi))
        if self._last is not None and hi > lo:  # consecutive windows: answer from the cached block
            a, b, values = self._last
            if a <= lo < b and hi <= b:
                return lo + int(np.searchsorted(values[lo - a : hi - a], t_us, side="left"))
            # the answer lies inside the cached block when t[a] < t_us <= t[b-1] (sorted column)
            if lo <= a and b <= hi and (a == lo or values[0] < t_us) and values[-1] >= t_us:
                return a + int(np.searchsorted(values, t_us, side="left"))
        while hi - lo > self.block:
            mid = (lo + hi) // 2
            if self._probe(mid) < t_us:
                lo = mid + 1
            else:
                hi = mid
        if hi <= lo:
            return lo
        # read a whole block around the answer so the next window's search is a cache hit
        b_lo, b_hi = lo, min(self.length, max(hi, lo + self.block))
        values = self._block(b_lo, b_hi)
        return lo + int(np.searchsorted(values[: hi - lo], t_us, side="left"))


def resolve_crop(crop, sensor_size: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """crop: None, (top, left, height, width), (height, width) (centred) or "centerN" (e.g.
    "center256": central N x N). The one crop rule of the readers and the env.

    Returns (top, left, height, width) inside the sensor, or None for no crop.
    """
    if crop is None:
        return None
    h, w = sensor_size
    if isinstance(crop, str):
        if not crop.startswith("center"):
            raise ValueError(f"crop must be (top, left, height, width) or 'centerN', got {crop!r}")
        n = int(crop[len("center") :] or 256)
        box = ((h - n) // 2, (w - n) // 2, n, n)
    else:
        box = tuple(int(v) for v in crop)
        if len(box) == 2:
            box = ((h - box[0]) // 2, (w - box[1]) // 2, *box)
        if len(box) != 4:
            raise ValueError(f"crop must be (top, left, height, width), (height, width) or 'centerN', got {crop!r}")
    top, left, ch, cw = box
    if ch <= 0 or cw <= 0 or top < 0 or left < 0 or top + ch > h or left + cw > w:
        raise ValueError(f"crop {box} (top, left, height, width) does not fit the {h}x{w} sensor")
    return box


def crop_events(x: np.ndarray, y: np.ndarray, box: tuple[int, int, int, int] | None):
    """Boolean keep-mask and shifted coordinates for a crop box (None: keep all)."""
    if box is None:
        return None, x, y
    top, left, ch, cw = box
    keep = (x >= left) & (x < left + cw) & (y >= top) & (y < top + ch)
    return keep, x[keep] - left, y[keep] - top
