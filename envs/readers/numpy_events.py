"""Events as numpy files: ``.npy`` holding one structured array with fields x, y, t, p (tonic's
layout, ``t`` in µs) and ``.npz`` holding either that array as ``events`` or the four arrays
``x``, ``y``, ``t``, ``p``, with an optional ``sensor_size`` (height, width). Read with
``allow_pickle=False`` (a file cannot run code); ``.npy`` is memory-mapped, not loaded whole.
``scripts/convert.py REC out.npy`` writes them (:func:`write_numpy_events`).

The sensor size comes from the file's ``sensor_size``, else from ``sensor_size=`` (H, W), tonic's
(W, H, P), or "auto" (``--sensor-size`` on the command line).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from envs.atomic import open_no_follow
from envs.events import Events
from envs.memory import FIELDS, events_from_memory
from envs.outputs import Output

from ._common import SENSOR_SIZE_HINT
from .base import ArrayReader, EventReader, FormatError

__all__ = ["NumpyEventsReader", "write_numpy_events", "NUMPY_DTYPE", "is_numpy_events"]

#: the structured dtype written (tonic's field names; t int64 µs, p 0/1)
NUMPY_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("p", "u1")])


def _load(path: Path):
    try:
        if path.suffix.lower() == ".npy":
            return np.load(path, mmap_mode="r", allow_pickle=False), None
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise FormatError(f"{path}: not a readable numpy file ({err})") from None
    keys = set(archive.files)
    size = archive["sensor_size"] if "sensor_size" in keys else None
    if "events" in keys:
        return archive["events"], size
    if set(FIELDS) <= keys:
        return {k: archive[k] for k in FIELDS}, size
    raise FormatError(f"{path}: an .npz without 'events' or the arrays {list(FIELDS)} (holds {sorted(keys)})")


def is_numpy_events(path: str | os.PathLike) -> bool:
    """True for an .npz that holds events (MVSEC's ground-truth .npz does not)."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            keys = set(archive.files)
    except (OSError, ValueError, EOFError):
        return False
    return "events" in keys or set(FIELDS) <= keys


class NumpyEventsReader(ArrayReader):
    """A recording in an ``.npy`` / ``.npz`` file (module docstring)."""

    def __init__(self, path: str | os.PathLike, sensor_size=None) -> None:
        self.path = Path(path)
        data, stored = _load(self.path)
        if isinstance(data, np.ndarray) and data.dtype.names is None:
            raise FormatError(f"{self.path}: holds a plain {data.dtype} array of shape {data.shape}; expected a "
                              f"structured array with fields {list(FIELDS)}")
        size = sensor_size if stored is None else tuple(int(v) for v in np.asarray(stored).ravel())
        if size is None:
            raise FormatError(f"{self.path}: stores no sensor size; {SENSOR_SIZE_HINT}")
        events = events_from_memory(data, size, source=str(self.path))
        super().__init__(events, name=self.path.stem)


def write_numpy_events(reader: EventReader, out: Output, chunk_events: int = 1 << 20, bar=None) -> Path:
    """``reader``'s events to ``out`` (a claimed :class:`envs.outputs.Output`, suffix .npy or
    .npz), through its temporary and committed whole. .npy: a structured array (NUMPY_DTYPE)
    filled chunk by chunk in a memory-mapped file; .npz: the same array as ``events`` and
    ``sensor_size``, built in memory."""
    n = reader.num_events
    suffix = out.path.suffix.lower()
    if suffix == ".npy":
        array = np.lib.format.open_memmap(out.temporary, mode="w+", dtype=NUMPY_DTYPE, shape=(n,))
    else:
        array = np.zeros(n, NUMPY_DTYPE)
    for i0 in range(0, n, chunk_events):
        i1 = min(n, i0 + chunk_events)
        chunk: Events = reader.events_range(i0, i1)
        part = array[i0:i1]
        part["x"], part["y"], part["t"], part["p"] = chunk.x, chunk.y, chunk.t, chunk.p > 0
        if bar is not None:
            bar.update(i1 - i0)
    if suffix == ".npy":
        array.flush()
        del array
    else:
        with open_no_follow(out.temporary, "wb") as f:
            np.savez(f, events=array, sensor_size=np.asarray(reader.sensor_size, np.int64))
    return out.commit()
