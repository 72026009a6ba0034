"""The event container: one struct of arrays per stream or window (docs/method.md, "Conventions").

An event is ``(x, y, t, p)``: ``x`` the column, ``y`` the row, ``t`` the time in integer
microseconds and ``p`` the polarity in {-1, +1}. :class:`Events` holds N of them as four
numpy arrays plus the sensor size, validates them once at construction, and slices by time
with binary search.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

__all__ = ["Events", "EventError", "normalize_polarity", "MAX_SENSOR_SIDE", "MAX_SPAN_US"]

#: the largest sensor side (pixels) a recording may have: DAT's 14-bit coordinates (today's
#: largest event sensors are 1280 wide); a larger coordinate in a file is corruption, not a sensor
MAX_SENSOR_SIDE = 1 << 14
#: the longest time span (µs) a recording may cover, 24 h: a file whose times span more is
#: corrupt, and the project h5's millisecond index (8 bytes per ms) stays under 0.7 GB
MAX_SPAN_US = 24 * 3600 * 1_000_000


class EventError(ValueError):
    """Raised for malformed event data; the message names the field and the first bad index."""


def _check_order_and_bounds(source: str, x: np.ndarray, y: np.ndarray, t: np.ndarray, height: int, width: int,
                            rectified: bool) -> None:
    """Raise :class:`EventError` (naming ``source``, the field and the first bad index) unless
    ``t`` never decreases and the coordinates lie inside the ``height`` x ``width`` sensor
    (``rectified``: float coordinates, finite and in [0, size - 1])."""
    dt = np.diff(t)
    if (dt < 0).any():
        i = _first_index(dt < 0) + 1
        raise EventError(
            f"{source}: field 't' must be non-decreasing; index {i} has t={t[i]} "
            f"after t={t[i - 1]} at index {i - 1}"
        )
    for name, arr, size in (("x", x, width), ("y", y, height)):
        bad = ~np.isfinite(arr) | (arr < 0) | (arr > size - 1) if rectified else (arr < 0) | (arr >= size)
        if bad.any():
            i = _first_index(bad)
            raise EventError(
                f"{source}: field '{name}' must lie in [0, {size}) for sensor "
                f"{height}x{width} (height x width); index {i} holds {arr[i]}"
            )


def _first_index(bad: np.ndarray) -> int:
    return int(np.flatnonzero(bad)[0])


def normalize_polarity(p: np.ndarray, *, source: str = "events") -> np.ndarray:
    """Map polarities given as {0, 1}, {-1, +1} or bool to int8 {-1, +1} (``p > 0`` is ON).

    p: (N,) any numeric or bool dtype.
    Raises EventError naming the first value that is none of 0, 1, -1, True, False.
    """
    p = np.asarray(p)
    if p.dtype == np.bool_:
        return np.where(p, 1, -1).astype(np.int8)
    if p.size:
        bad = ~np.isin(p, (-1, 0, 1))
        if bad.any():
            i = _first_index(bad)
            raise EventError(
                f"{source}: field 'p' must hold polarities in {{0,1}}, {{-1,+1}} or bool; "
                f"index {i} holds {p[i]!r}"
            )
    return np.where(p > 0, 1, -1).astype(np.int8)


@dataclass(frozen=True)
class Events:
    """N events as a struct of arrays.

    x: (N,) int16 column (float32 when rectified), in [0, width)
    y: (N,) int16 row (float32 when rectified), in [0, height)
    t: (N,) int64 microseconds, non-decreasing
    p: (N,) int8 polarity in {-1, +1}
    sensor_size: (height, width) in pixels

    Build with :meth:`Events.create`, which converts and validates; the bare constructor
    trusts its arguments (used internally on already-validated slices).
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    sensor_size: tuple[int, int]

    @classmethod
    def create(
        cls,
        x: Iterable,
        y: Iterable,
        t: Iterable,
        p: Iterable,
        sensor_size: tuple[int, int],
        *,
        source: str = "events",
        validate: bool = True,
    ) -> "Events":
        """Convert to the canonical dtypes and validate.

        Checks, each raising :class:`EventError` with the field and the first bad index:
        equal lengths, integer-valued finite timestamps that never decrease, coordinates
        inside ``sensor_size``, polarities in {0,1}/{-1,+1}/bool. ``source`` names the file
        or dataset in the messages.
        """
        height, width = (int(v) for v in sensor_size)
        if height <= 0 or width <= 0:
            raise EventError(f"{source}: sensor_size must be positive (height, width), got {sensor_size}")
        x, y, t, p = (np.asarray(a) for a in (x, y, t, p))
        for name, arr in (("x", x), ("y", y), ("t", t), ("p", p)):
            if arr.ndim != 1:
                raise EventError(f"{source}: field '{name}' must be 1-D, got shape {arr.shape}")
        n = len(t)
        for name, arr in (("x", x), ("y", y), ("p", p)):
            if len(arr) != n:
                raise EventError(
                    f"{source}: field '{name}' has {len(arr)} entries but 't' has {n}"
                )
        if np.issubdtype(t.dtype, np.floating):
            if validate and n and not np.isfinite(t).all():
                i = _first_index(~np.isfinite(t))
                raise EventError(f"{source}: field 't' is not finite at index {i} ({t[i]!r})")
            t = np.rint(t).astype(np.int64)
        else:
            t = t.astype(np.int64, copy=False)
        p = normalize_polarity(p, source=source)
        rectified = np.issubdtype(x.dtype, np.floating) or np.issubdtype(y.dtype, np.floating)
        if rectified:
            x = x.astype(np.float32, copy=False)
            y = y.astype(np.float32, copy=False)
        if validate and n:
            _check_order_and_bounds(source, x, y, t, height, width, rectified)
        if not rectified:
            x = x.astype(np.int16, copy=False)
            y = y.astype(np.int16, copy=False)
        return cls(x, y, t, p, (height, width))

    @classmethod
    def empty(cls, sensor_size: tuple[int, int]) -> "Events":
        return cls(
            np.zeros(0, np.int16),
            np.zeros(0, np.int16),
            np.zeros(0, np.int64),
            np.zeros(0, np.int8),
            (int(sensor_size[0]), int(sensor_size[1])),
        )

    @classmethod
    def concatenate(cls, parts: list["Events"]) -> "Events":
        """Join consecutive pieces of one stream (no re-validation)."""
        if not parts:
            raise EventError("Events.concatenate needs at least one part")
        return cls(
            *(np.concatenate([getattr(e, f) for e in parts]) for f in ("x", "y", "t", "p")),
            parts[0].sensor_size,
        )

    def __len__(self) -> int:
        return len(self.t)

    # sensor_size's parts by name (readers name their time range alike: t_start, t_end)
    @property
    def height(self) -> int:
        return self.sensor_size[0]

    @property
    def width(self) -> int:
        return self.sensor_size[1]

    def __getitem__(self, index) -> "Events":
        """Slice or index-array selection (keeps the sensor size)."""
        if isinstance(index, (int, np.integer)):
            index = slice(int(index), int(index) + 1 if index != -1 else None)
        return Events(self.x[index], self.y[index], self.t[index], self.p[index], self.sensor_size)

    def index_at(self, t_us: int | np.ndarray) -> int | np.ndarray:
        """Index of the first event with t >= t_us (binary search)."""
        return np.searchsorted(self.t, t_us, side="left")

    def slice_time(self, t_start: int, t_end: int) -> "Events":
        """Events with t in the half-open interval [t_start, t_end) (binary search)."""
        i0, i1 = np.searchsorted(self.t, (t_start, t_end), side="left")
        return self[int(i0) : int(i1)]

    def tau(self, t_start: int, t_end: int) -> np.ndarray:
        """Normalised time (t - t_start) / (t_end - t_start) as float64, in [0, 1) inside the window."""
        return (self.t - t_start) / float(t_end - t_start)

    def as_dict(self) -> dict[str, np.ndarray]:
        """The four arrays, e.g. for a window dict (with ``t_start`` and ``t_end``)."""
        return {"x": self.x, "y": self.y, "t": self.t, "p": self.p}

    def __repr__(self) -> str:
        span = f"t=[{self.t[0]}, {self.t[-1]}] us" if len(self) else "empty"
        return f"Events(n={len(self)}, sensor={self.height}x{self.width}, {span})"
